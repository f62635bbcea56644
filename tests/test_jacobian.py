"""Closed-form skinning and projection Jacobians (fit.jacobian) against finite differences."""

from __future__ import annotations

import numpy as np
import torch

from flowmocap.body import load_body_model
from flowmocap.fit.jacobian import projection_jacobian, right_jacobian_so3, skinned_point_jacobian
from flowmocap.geometry import PinholeCamera, axis_angle_to_matrix, look_at
from flowmocap.io import walk_poses


def test_right_jacobian_matches_finite_differences_including_small_angles():
    rng = np.random.default_rng(0)
    for theta in [rng.normal(size=3), 1e-6 * rng.normal(size=3), np.array([0.0, 0.0, 3.0])]:
        Jr = right_jacobian_so3(theta)
        R0 = axis_angle_to_matrix(torch.tensor(theta)).numpy()
        h = 1e-6
        for c in range(3):
            d = np.zeros(3); d[c] = h
            R1 = axis_angle_to_matrix(torch.tensor(theta + d)).numpy()
            # R0^T R1 = exp([Jr d]_x): its skew part is Jr d
            S = R0.T @ R1
            w = np.array([S[2, 1] - S[1, 2], S[0, 2] - S[2, 0], S[1, 0] - S[0, 1]]) / 2 / h
            np.testing.assert_allclose(w, Jr[:, c], atol=1e-5)


def test_skinned_vertex_jacobian_matches_finite_differences():
    body = load_body_model("default", dtype=torch.float64)
    rng = np.random.default_rng(1)
    pose = torch.tensor(walk_poses(np.array([0.2]))[0]) + torch.tensor(rng.normal(scale=0.2, size=72))
    trans = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    betas = torch.tensor(rng.normal(size=(1, 10)))
    out = body(betas=betas, pose=pose[None], trans=trans[None])
    J = skinned_point_jacobian(pose.numpy(), out.transforms[0].numpy(), out.joints[0].numpy(),
                               out.rest_vertices[0].numpy(), body.weights.numpy())
    assert J.shape == (body.num_vertices, 3, 75)
    x = torch.cat([pose, trans])
    h = 1e-6
    verts = rng.choice(body.num_vertices, 200, replace=False)
    for col in list(range(0, 75, 4)) + [3 * 18 + 1, 3 * 21 + 2, 72, 74]:
        xp, xm = x.clone(), x.clone()
        xp[col] += h
        xm[col] -= h
        vp = body(betas=betas, pose=xp[None, :72], trans=xp[None, 72:]).vertices[0].numpy()
        vm = body(betas=betas, pose=xm[None, :72], trans=xm[None, 72:]).vertices[0].numpy()
        fd = (vp - vm) / (2 * h)
        np.testing.assert_allclose(J[verts, :, col], fd[verts], atol=1e-7, err_msg=f"column {col}")


def test_projection_jacobian_matches_finite_differences():
    R, t = look_at((0.3, 0.2, 3.0), (0.0, -0.1, 0.0))
    cam = PinholeCamera.from_focal(320, 240, 300.0, R, t)
    X = np.random.default_rng(2).normal(scale=0.3, size=(20, 3))
    P = projection_jacobian(X, np.asarray(cam.R), np.asarray(cam.t), cam.fx, cam.fy)
    h = 1e-6
    for c in range(3):
        d = np.zeros(3); d[c] = h
        fd = (cam.project(torch.tensor(X + d)).numpy() - cam.project(torch.tensor(X - d)).numpy()) / (2 * h)
        np.testing.assert_allclose(P[:, :, c], fd, rtol=1e-6, atol=1e-6)

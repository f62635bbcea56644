"""The re-initialisation's depth term (flowmocap.fit.energies.root_distance_energy,
TrackerConfig.reinit_depth_weight): closed form, gradient, and its effect on the joint fit."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flowmocap.body import load_body_model
from flowmocap.errors import InputError
from flowmocap.fit import energies as en
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.init import fit_to_joints
from flowmocap.geometry import PinholeCamera, look_at
from flowmocap.io import walk_poses


def test_root_distance_energy_closed_form():
    root = torch.tensor([[0.3, -0.4, 1.2], [0.0, 0.0, 2.6]], dtype=torch.float64)  # distances 1.3 and 2.6
    e = en.root_distance_energy(root, 2.0)
    np.testing.assert_allclose(e.numpy(), [(1.3 / 2 - 1) ** 2, (2.6 / 2 - 1) ** 2], rtol=1e-12)
    assert en.root_distance_residuals(root, 2.0).shape == (2, 1)
    assert float(en.root_distance_energy(root[:1] * (2.0 / 1.3), 2.0)[0]) == pytest.approx(0.0, abs=1e-24)
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(InputError):
            en.root_distance_energy(root, bad)


def test_root_distance_energy_gradient_matches_finite_differences():
    root = torch.tensor([[0.3, -0.4, 1.2]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda r: en.root_distance_energy(r, 1.7), (root,), eps=1e-6, atol=1e-9)
    e = en.root_distance_energy(root, 1.7)[0]
    (g,) = torch.autograd.grad(e, root)
    d = float(root.detach().norm())
    np.testing.assert_allclose(g.numpy()[0], 2 * (d / 1.7 - 1) / 1.7 * root.detach().numpy()[0] / d, rtol=1e-10)


def test_the_joint_fit_stays_near_the_given_root_distance():
    """A refit's joint fit (fit_to_joints, shape fixed) with ``root_distance`` keeps the
    root's distance from the camera near it, where without it the 2D joints alone put the
    body at its true distance; the term is reported, and absent without the argument or
    with the weight 0."""
    model = load_body_model("default")
    R, t = look_at((0.3, 0.2, 3.0), (0.0, -0.1, 0.0))
    cam = PinholeCamera.from_focal(640, 480, 800.0, R, t)
    pose = torch.tensor(walk_poses(np.array([0.3]))[0], dtype=torch.float32)
    with torch.no_grad():
        out = model(pose=pose[None])
        j2d = cam.project(out.joints[0]).numpy()
        true_d = float(cam.to_camera(out.joints[0, 0]).norm())
    conf = np.ones(24)
    start = pose.clone()
    start[3:] *= 0.7

    def root_distance(p, tr):
        with torch.no_grad():
            return float(cam.to_camera(model(pose=p[None], trans=tr[None]).joints[0, 0]).norm())

    kw = dict(fit_shape=False, iterations=20, joints_from_detector=False)
    cfg = TrackerConfig(init_pose_prior_weight=0.0, init_learned_prior_weight=0.0, keypoint_offsets=False,
                        reinit_depth_weight=1e5)
    p0, t0, _, terms0 = fit_to_joints(model, cam, j2d, conf, None, cfg, start, torch.zeros(3), torch.zeros(1, 10), **kw)
    ref = 1.3 * true_d
    p1, t1, _, terms1 = fit_to_joints(model, cam, j2d, conf, None, cfg, start, torch.zeros(3), torch.zeros(1, 10),
                                      root_distance=ref, **kw)
    off = TrackerConfig(init_pose_prior_weight=0.0, init_learned_prior_weight=0.0, keypoint_offsets=False,
                        reinit_depth_weight=0.0)
    _, _, _, terms2 = fit_to_joints(model, cam, j2d, conf, None, off, start, torch.zeros(3), torch.zeros(1, 10),
                                    root_distance=ref, **kw)
    strong = TrackerConfig(init_pose_prior_weight=0.0, init_learned_prior_weight=0.0, keypoint_offsets=False,
                           reinit_depth_weight=1e7)
    p3, t3, _, _ = fit_to_joints(model, cam, j2d, conf, None, strong, start, torch.zeros(3), torch.zeros(1, 10),
                                 root_distance=ref, **kw)
    assert abs(root_distance(p0, t0) / true_d - 1) < 0.03
    # 1e5 trades a 30 % jump against the 2D joints (it ends about 10 % from the reference,
    # where a 2.4x jump would cost 200 times more); a strong one holds the reference
    assert abs(root_distance(p1, t1) / ref - 1) < 0.75 * abs(root_distance(p0, t0) / ref - 1)
    assert abs(root_distance(p3, t3) / ref - 1) < 0.02
    assert "root_distance" not in terms0 and "root_distance" not in terms2
    assert terms1["root_distance"] == pytest.approx(cfg.reinit_depth_weight * (root_distance(p1, t1) / ref - 1) ** 2,
                                                    rel=1e-3, abs=1e-6)

"""Closed-form and reference checks of the renderer's helpers that were reached only through
``shade`` (the fifty-sixth session's coverage audit): the covered pixels' interpolation, the
value noise of the synthetic clothing, the face and vertex normals, and the camera's
projection with depth.
"""

from __future__ import annotations

import numpy as np
import torch

from flowmocap.geometry.camera import PinholeCamera
from flowmocap.render import interpolate, rasterize
from flowmocap.render.interpolate import interpolate_covered
from flowmocap.render.primitives import box, grid_mesh, icosphere
from flowmocap.render.shade import _lattice_tables, face_normals, value_noise, vertex_normals


def _raster():
    verts, faces = box((1.0, 0.8, 0.6))
    ang = 0.6
    R = np.array([[np.cos(ang), 0, np.sin(ang)], [0, 1, 0], [-np.sin(ang), 0, np.cos(ang)]])
    X = verts @ R.T + np.array([0.1, -0.05, 2.5])
    f, cx, cy = 30.0, 20.0, 15.0
    xy = np.column_stack([f * X[:, 0] / X[:, 2] + cx, f * X[:, 1] / X[:, 2] + cy])
    return rasterize(xy, X[:, 2], faces, 30, 40), faces


def test_interpolate_covered_is_interpolate_at_the_covered_pixels():
    r, faces = _raster()
    attr = np.random.default_rng(0).normal(size=(8, 5))
    full = interpolate(r, attr, faces)
    got = interpolate_covered(r, attr, faces)
    assert got.shape == (int(r.mask.sum()), 5) and len(got) > 100
    np.testing.assert_allclose(got, full[r.mask], rtol=1e-12, atol=1e-12)  # row-major order of the mask
    # an attribute linear in the vertex positions comes out linear in the surface point
    lin = attr[:, :3] @ np.diag([1.0, -2.0, 0.5])
    np.testing.assert_allclose(interpolate_covered(r, lin, faces), full[r.mask][:, :3] @ np.diag([1.0, -2.0, 0.5]),
                               atol=1e-12)


def _noise_reference(p, seed):
    """The value noise written out with numpy: the lattice value at each corner of the unit
    cell, blended by the smoothstep of the fractional part along each axis."""
    perm, vals = _lattice_tables(seed)
    i = np.floor(p).astype(np.int64)
    t = p - np.floor(p)
    s = t * t * (3 - 2 * t)
    out = np.zeros(len(p))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                h = perm[(perm[(perm[(i[:, 0] + dx) & 255] + i[:, 1] + dy) & 255] + i[:, 2] + dz) & 255]
                w = (np.where(dx, s[:, 0], 1 - s[:, 0]) * np.where(dy, s[:, 1], 1 - s[:, 1])
                     * np.where(dz, s[:, 2], 1 - s[:, 2]))
                out += w * vals[h]
    return out


def test_value_noise_against_its_definition():
    rng = np.random.default_rng(1)
    p = rng.uniform(-300, 300, (2000, 3))
    v = value_noise(p, seed=3)
    np.testing.assert_allclose(v, _noise_reference(p, 3), atol=1e-12)
    assert v.min() >= 0.0 and v.max() <= 1.0
    # lattice points take the lattice's values; the noise repeats every 256 along each axis
    perm, vals = _lattice_tables(3)
    q = rng.integers(-500, 500, (50, 3)).astype(float)
    lattice = vals[perm[(perm[(perm[q[:, 0].astype(int) & 255] + q[:, 1].astype(int)) & 255]
                         + q[:, 2].astype(int)) & 255]]
    np.testing.assert_allclose(value_noise(q, seed=3), lattice, atol=1e-15)
    for axis in range(3):
        np.testing.assert_allclose(value_noise(p + 256 * np.eye(3)[axis], seed=3), v, atol=1e-9)
    # C1: a step of 1e-6 moves it by at most the smoothstep's bounded slope times the step
    assert np.abs(value_noise(p + 1e-6, seed=3) - v).max() < 1e-5
    assert not np.allclose(value_noise(p, seed=4), v)


def test_face_normals_in_closed_form():
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 0]], float)
    n = face_normals(verts, np.array([[0, 1, 2], [0, 2, 1], [0, 3, 3]]))
    np.testing.assert_allclose(n, [[0, 0, 1], [0, 0, -1], [0, 0, 0]])  # right-hand rule; degenerate: zero
    v, f = box((1.0, 2.0, 3.0))  # every face points out of the box
    centres = v[f].mean(axis=1)
    out = centres / np.linalg.norm(centres, axis=1, keepdims=True)
    assert np.all(np.einsum("ij,ij->i", face_normals(v, f), out) > 0.2)
    assert np.allclose(np.abs(face_normals(v, f)).max(axis=1), 1.0)  # axis-aligned unit normals


def test_vertex_normals_in_closed_form():
    v, f = grid_mesh(4, 3)
    n = vertex_normals(v, f)
    np.testing.assert_allclose(n, np.tile([0.0, 0.0, -1.0], (len(v), 1)), atol=1e-12)  # a flat sheet facing -z
    s, sf = icosphere(2)
    radial = s / np.linalg.norm(s, axis=1, keepdims=True)
    cos = np.einsum("ij,ij->i", vertex_normals(s, sf), radial)
    assert cos.min() > 0.995  # a sphere's smooth normals point out along its radius
    extra = np.vstack([s, [[5.0, 5.0, 5.0]]])  # a vertex in no face: zero
    assert np.all(vertex_normals(extra, sf)[-1] == 0)


def test_project_with_depth_is_project_and_depth():
    R = torch.tensor(np.linalg.qr(np.random.default_rng(2).normal(size=(3, 3)))[0], dtype=torch.float64)
    if torch.det(R) < 0:
        R = -R
    cam = PinholeCamera(fx=500, fy=480, cx=320, cy=240, width=640, height=480, R=R.numpy(), t=[0.1, -0.2, 4.0])
    X = torch.tensor(np.random.default_rng(3).normal(0, 0.5, (2, 7, 3)), dtype=torch.float64, requires_grad=True)
    uv, z = cam.project_with_depth(X)
    assert uv.shape == (2, 7, 2) and z.shape == (2, 7)
    torch.testing.assert_close(uv, cam.project(X))
    torch.testing.assert_close(z, cam.depth(X))
    (uv.sum() + z.sum()).backward()  # differentiable
    assert torch.isfinite(X.grad).all()

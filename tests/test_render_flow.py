"""Rendered flow, the flow objective E_f with its gradient and Jacobian, the pyramid."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from scipy.ndimage import binary_erosion

from flowmocap.errors import InputError
from flowmocap.render import (
    flow_loss,
    flow_residuals,
    flow_target,
    prepare_faces,
    pyr_down,
    rasterize,
    render_flow,
)
from flowmocap.render.primitives import box, grid_mesh, icosphere, mannequin
from flowmocap.render.pyramid import pyr_down_adjoint_region, pyr_down_region

F_PX = 60.0


def project(X, H, W, f=F_PX):
    return np.stack([f * X[:, 0] / X[:, 2] + W / 2, f * X[:, 1] / X[:, 2] + H / 2], axis=1)


def rot_y(a):
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def rot_x(a):
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


# ----------------------------------------------------------------------------- rendered flow


def test_translated_mesh_renders_exactly_the_translation():
    H, W = 48, 64
    verts, faces = mannequin(2)
    X = verts * np.array([1, -1, -1.0]) + np.array([0, 0.88, 3.0])
    xy = project(X, H, W)
    r = rasterize(xy, X[:, 2], faces, H, W)
    t = np.array([1.75, -0.6])
    for kw in ({}, {"depth_cur": X[:, 2], "depth_prev": X[:, 2]}):
        flow, mask = render_flow(r, xy, xy + t, faces, **kw)
        assert flow.dtype == np.float32 and flow.shape == (H, W, 2)
        np.testing.assert_array_equal(mask, r.face_id >= 0)
        assert mask.sum() > 200
        np.testing.assert_allclose(flow[mask], np.broadcast_to(t, (mask.sum(), 2)), atol=1e-5)
        assert np.all(flow[~mask] == 0)


def _analytic_backward_flow(raster, Xc, faces, motion_inv, H, W, f=F_PX):
    """Exact backward flow of the visible surface point at every covered pixel: intersect
    the pixel ray with the visible face's plane (frame i), map the point back to frame
    i - 1 with the rigid motion's inverse, project, subtract the pixel centre."""
    vs, us = np.nonzero(raster.face_id >= 0)
    tri = Xc[faces[raster.face_id[vs, us]]]  # (N, 3, 3)
    ray = np.stack([(us + 0.5 - W / 2) / f, (vs + 0.5 - H / 2) / f, np.ones(len(us))], 1)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    s = (n * tri[:, 0]).sum(1) / (n * ray).sum(1)
    P = ray * s[:, None]
    Pp = motion_inv(P)
    pp = project(Pp, H, W, f)
    return vs, us, pp - np.stack([us + 0.5, vs + 0.5], 1)


def test_rotating_box_flow_matches_the_analytic_surface_flow():
    H, W = 60, 80
    verts, faces = box((1.0, 0.8, 0.7))
    T = np.array([0.1, 0.05, 3.0])
    R_prev = rot_y(0.5) @ rot_x(0.3)
    R_cur = rot_y(0.56) @ rot_x(0.33)  # a 3.4 degree step
    Xc = verts @ R_cur.T + T
    Xp = verts @ R_prev.T + T
    xc, xp = project(Xc, H, W, 150.0), project(Xp, H, W, 150.0)
    r = rasterize(xc, Xc[:, 2], faces, H, W)
    vs, us, exact = _analytic_backward_flow(r, Xc, faces, lambda P: (P - T) @ R_cur @ R_prev.T + T, H, W, 150.0)
    assert len(vs) > 1000 and np.abs(exact).max() > 1.0
    # exact mode: the displacement of the visible surface point
    flow, _ = render_flow(r, xc, xp, faces, depth_cur=Xc[:, 2], depth_prev=Xp[:, 2])
    np.testing.assert_allclose(flow[vs, us], exact, atol=2e-4)
    # paper mode: screen-space interpolation of projected vertex displacements. Its
    # error grows with triangle size (in pixels) times the depth-ratio spread of the
    # triangle's vertices: ~0.4 px for these 50-100 px box faces ...
    flow_p, _ = render_flow(r, xc, xp, faces)
    assert 0.05 < np.abs(flow_p[vs, us] - exact).max() < 0.5
    # ... but exact at the vertices (the displacement of each visible projected vertex)
    for k in range(8):
        u, v = np.floor(xc[k]).astype(int)
        if 0 <= u < W and 0 <= v < H and r.face_id[v, u] >= 0 and k in faces[r.face_id[v, u]]:
            assert np.abs(flow_p[v, u] - (xp[k] - xc[k])).max() < 0.1  # < 1 px from the vertex
    # ... and negligible for a finely tessellated body (triangles ~2 px, like SMPL at 640x480)
    verts, faces = icosphere(4, 0.5)
    verts = verts * np.array([1.0, 1.3, 0.8])
    Xc = verts @ R_cur.T + T
    Xp = verts @ R_prev.T + T
    xc, xp = project(Xc, H, W, 150.0), project(Xp, H, W, 150.0)
    r = rasterize(xc, Xc[:, 2], faces, H, W)
    vs, us, exact = _analytic_backward_flow(r, Xc, faces, lambda P: (P - T) @ R_cur @ R_prev.T + T, H, W, 150.0)
    assert len(vs) > 2000 and np.abs(exact).max() > 1.0
    flow_p, _ = render_flow(r, xc, xp, faces)
    assert np.abs(flow_p[vs, us] - exact).max() < 2e-3
    flow, _ = render_flow(r, xc, xp, faces, depth_cur=Xc[:, 2], depth_prev=Xp[:, 2])
    np.testing.assert_allclose(flow[vs, us], exact, atol=1e-5)


def test_motion_parallel_to_the_image_plane_is_exact_in_paper_mode():
    H, W = 48, 64
    verts, faces = icosphere(2, 0.6)
    Xc = verts + np.array([0.0, 0.0, 2.5])
    shift = np.array([0.07, -0.04, 0.0])  # parallax: near vertices move more pixels
    Xp = Xc + shift
    xc, xp = project(Xc, H, W), project(Xp, H, W)
    r = rasterize(xc, Xc[:, 2], faces, H, W)
    vs, us, exact = _analytic_backward_flow(r, Xc, faces, lambda P: P + shift, H, W)
    flow, _ = render_flow(r, xc, xp, faces)
    np.testing.assert_allclose(flow[vs, us], exact, atol=1e-6)


# ----------------------------------------------------------------------------- pyramid


@pytest.mark.parametrize("shape", [(1, 1), (2, 3), (3, 2), (5, 7), (16, 16), (33, 50), (480, 640)])
def test_pyr_down_matches_opencv(shape):
    rng = np.random.default_rng(0)
    img = rng.standard_normal(shape + (2,)).astype(np.float32)
    np.testing.assert_allclose(pyr_down(img), cv2.pyrDown(img).reshape(pyr_down(img).shape), atol=3e-7)
    gray = rng.standard_normal(shape)
    np.testing.assert_allclose(pyr_down(gray), cv2.pyrDown(gray), atol=1e-12)


def test_pyramid_adjoint_is_the_transpose_on_regions():
    rng = np.random.default_rng(2)
    H, W = 23, 30
    Ho, Wo = 12, 15
    x = np.zeros((H, W, 2))
    x[5:14, 7:20] = rng.standard_normal((9, 13, 2))
    y = np.zeros((Ho, Wo, 2))
    y[2:9, 3:11] = rng.standard_normal((7, 8, 2))
    tmp = np.zeros((H, Wo, 2))
    dx = np.zeros((Ho, Wo, 2))
    pyr_down_region(x, dx, tmp, 0, Ho, 0, Wo)
    np.testing.assert_allclose(dx, pyr_down(x), atol=1e-14)
    dty = np.zeros((H, W, 2))
    pyr_down_adjoint_region(y, dty, tmp, 2, 9, 3, 11)
    assert np.isclose((dx * y).sum(), (x * dty).sum(), rtol=1e-12)


# ----------------------------------------------------------------------------- E_f


def _bumpy_sheet(H=40, W=48, seed=0):
    rng = np.random.default_rng(seed)
    v, f = grid_mesh(6, 5, size=(1.2, 1.0))
    v[:, 2] = 0.1 * np.sin(3 * v[:, 0]) * np.cos(2 * v[:, 1])
    Xc = v + np.array([0.0, 0.0, 3.0])
    Xp = Xc + 0.03 * rng.standard_normal(Xc.shape)
    obs = rng.standard_normal((H, W, 2)) * 0.5 + np.array([0.3, -0.2])
    return f, Xc, Xp, project(Xc, H, W, 40.0), project(Xp, H, W, 40.0), obs


def test_energy_value_is_the_weighted_pyramid_sum():
    H, W = 40, 48
    f, Xc, Xp, xc, xp, obs = _bumpy_sheet(H, W)
    w = np.random.default_rng(3).random((H, W))
    r = rasterize(xc, Xc[:, 2], f, H, W)
    _, mask = render_flow(r, xc, xp, f)
    flow64 = np.zeros((H, W, 2))
    from flowmocap.render.flow import _render_flow_kernel
    _render_flow_kernel(r.face_id, f, xc, xp, np.ones(len(xc)), flow64)
    r0 = np.sqrt(w)[..., None] * (obs - flow64)
    E1 = float(flow_loss(xc, xp, f, obs, w, levels=1, raster=r))
    assert np.isclose(E1, (r0**2).sum(), rtol=1e-12)
    E3 = float(flow_loss(xc, xp, f, obs, w, levels=3, raster=r))
    ref, lev = 0.0, r0
    for l in range(3):
        ref += 4.0**l * (lev**2).sum()
        lev = cv2.pyrDown(lev)
    assert np.isclose(E3, ref, rtol=1e-10)
    Ec = float(flow_loss(xc, xp, f, obs, w, levels=1, raster=r, covered_only=True))
    assert np.isclose(Ec, (r0[mask] ** 2).sum(), rtol=1e-12)
    E2 = float(flow_loss(xc, xp, f, obs, w, levels=2, level_weights=[1.0, 0.5], raster=r))
    assert np.isclose(E2, (r0**2).sum() + 0.5 * (cv2.pyrDown(r0) ** 2).sum(), rtol=1e-10)


@pytest.mark.parametrize("levels", [1, 3])
@pytest.mark.parametrize("exact", [False, True])
def test_flow_loss_gradient_matches_finite_differences(levels, exact):
    H, W = 40, 48
    f, Xc, Xp, xc, xp, obs = _bumpy_sheet(H, W)
    # zero weight near the outline: away from boundaries E_f is smooth in the vertices
    mask = rasterize(xc, Xc[:, 2], f, H, W).face_id >= 0
    w = binary_erosion(mask, iterations=2).astype(float) * (1.0 + np.random.default_rng(4).random((H, W)))
    target = flow_target(obs, w, levels)
    base = {"xc": xc, "xp": xp, "zc": Xc[:, 2].copy(), "zp": Xp[:, 2].copy()}

    def energy(vals):
        kw = {"depth_cur": vals["zc"]}
        if exact:
            kw["depth_prev"] = vals["zp"]
        return float(flow_loss(vals["xc"], vals["xp"], f, target, **kw))

    tens = {k: torch.tensor(v, requires_grad=True) for k, v in base.items()}
    kw = {"depth_cur": tens["zc"]}
    if exact:
        kw["depth_prev"] = tens["zp"]
    E = flow_loss(tens["xc"], tens["xp"], f, target, **kw)
    assert E.dtype == torch.float64
    E.backward()
    rng = np.random.default_rng(5)
    names = ["xc", "xp"] + (["zc", "zp"] if exact else [])
    eps = 1e-6
    for name in names:
        grad = tens[name].grad.numpy().ravel()
        idx = rng.choice(grad.size, size=min(24, grad.size), replace=False)
        fd = np.empty(len(idx))
        for n, i in enumerate(idx):
            vals_p = {k: v.copy() for k, v in base.items()}
            vals_m = {k: v.copy() for k, v in base.items()}
            vals_p[name].reshape(-1)[i] += eps
            vals_m[name].reshape(-1)[i] -= eps
            fd[n] = (energy(vals_p) - energy(vals_m)) / (2 * eps)
        rel = np.linalg.norm(grad[idx] - fd) / np.linalg.norm(fd)
        assert np.linalg.norm(fd) > 1.0
        assert rel < 1e-6, (name, rel)
    if not exact:
        assert tens["zc"].grad is None  # depth only rasterises in paper mode


def test_jacobian_is_consistent_with_flow_loss():
    H, W = 40, 48
    f, Xc, Xp, xc, xp, obs = _bumpy_sheet(H, W)
    for levels, covered_only, exact in [(1, False, False), (3, False, True), (2, True, False)]:
        tens = [torch.tensor(a, requires_grad=True) for a in (xc, xp, Xc[:, 2], Xp[:, 2])]
        kw = dict(levels=levels, covered_only=covered_only, depth_cur=tens[2])
        if exact:
            kw["depth_prev"] = tens[3]
        E = flow_loss(tens[0], tens[1], f, obs, **kw)
        E.backward()
        kw2 = dict(kw, depth_cur=Xc[:, 2])
        if exact:
            kw2["depth_prev"] = Xp[:, 2]
        res = flow_residuals(xc, xp, f, obs, **kw2)
        r = res.residuals
        assert np.isclose(r @ r, E.item(), rtol=1e-12)
        assert res.jac_cur.shape == (len(r), 2 * len(xc))
        np.testing.assert_allclose(2 * res.jac_cur.T @ r, tens[0].grad.numpy().ravel(), atol=1e-9)
        np.testing.assert_allclose(2 * res.jac_prev.T @ r, tens[1].grad.numpy().ravel(), atol=1e-9)
        if exact:
            np.testing.assert_allclose(2 * res.jac_depth_cur.T @ r, tens[2].grad.numpy(), atol=1e-9)
            np.testing.assert_allclose(2 * res.jac_depth_prev.T @ r, tens[3].grad.numpy(), atol=1e-9)
        else:
            assert res.jac_depth_cur is None
        assert res.row_offsets[-1] == len(r)
    # level-0 rows of interior pixels touch exactly the 3 vertices of their face
    res = flow_residuals(xc, xp, f, obs, levels=1, depth_cur=Xc[:, 2], boundary=False)
    nnz_rows = np.diff(res.jac_cur.indptr)
    assert set(np.unique(nnz_rows)) <= {0, 6}


def _square_scene(t, c):
    sq = np.array([[0, 0], [12, 0], [12, 10], [0, 10.0]]) + t
    return sq, sq + c


def test_occlusion_boundary_gradient_matches_pixel_steps_and_descends():
    """A square model offset from the observed moving square: only the outline can
    explain the energy; its gradient equals the +-1 px central difference at level 0."""
    H, W = 40, 50
    faces = np.array([[0, 3, 2], [0, 2, 1]])
    c = np.array([1.5, -0.7])
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    inside = (u > 20.3) & (u < 32.3) & (v > 15.2) & (v < 25.2)
    obs = inside[..., None] * c
    ones = np.ones(4)
    for levels in (1, 3):
        for t0 in (np.array([17.3, 13.2]), np.array([22.7, 16.9])):
            xc = torch.tensor(_square_scene(t0, c)[0], requires_grad=True)
            E = flow_loss(xc, xc + torch.tensor(c), faces, obs, levels=levels, depth_cur=ones)
            E.backward()
            g = xc.grad.numpy().sum(axis=0)  # d E / d (rigid translation)
            fd = []
            for a in range(2):
                d = np.eye(2)[a]
                Ep = float(flow_loss(*_square_scene(t0 + d, c), faces, obs, levels=levels, depth_cur=ones))
                Em = float(flow_loss(*_square_scene(t0 - d, c), faces, obs, levels=levels, depth_cur=ones))
                fd.append((Ep - Em) / 2)
            if levels == 1:
                np.testing.assert_allclose(g, fd, rtol=1e-9)
            else:
                np.testing.assert_allclose(g, fd, rtol=0.05)
            step = -0.5 * g / np.abs(g).max()
            E2 = float(flow_loss(*_square_scene(t0 + step, c), faces, obs, levels=levels, depth_cur=ones))
            assert E2 < 0.8 * E.item()
            no_b = flow_loss(xc.detach().requires_grad_(), xc.detach() + torch.tensor(c), faces, obs,
                             levels=levels, depth_cur=ones, boundary=False)
            assert np.isclose(no_b.item(), E.item())


def test_gradient_step_lowers_the_energy_of_a_body():
    H, W = 60, 80
    verts, faces = mannequin(2)

    def view(a, tx):
        X = (verts - [0, 0.88, 0]) @ rot_y(a).T * np.array([1, -1, -1.0]) + np.array([tx, 0, 3.0])
        return project(X, H, W, 70.0), X[:, 2]

    x_prev, _ = view(0.0, 0.0)
    x_true, z_true = view(0.08, 0.03)
    r = rasterize(x_true, z_true, faces, H, W)
    obs, _ = render_flow(r, x_true, x_prev, faces)
    x_cur, z_cur = view(0.03, 0.0)  # current estimate: rotated and shifted too little
    pf = prepare_faces(faces)
    target = flow_target(obs, None, 3)
    for boundary in (True, False):
        xc = torch.tensor(x_cur, requires_grad=True)
        E = flow_loss(xc, x_prev, pf, target, depth_cur=z_cur, boundary=boundary)
        E.backward()
        g = xc.grad.numpy()
        step = -0.3 * g / np.abs(g).max()
        E2 = float(flow_loss(x_cur + step, x_prev, pf, target, depth_cur=z_cur))
        assert E2 < E.item()


def test_flow_target_and_raw_arrays_agree_and_nonfinite_flow_is_ignored():
    H, W = 40, 48
    f, Xc, Xp, xc, xp, obs = _bumpy_sheet(H, W)
    r = rasterize(xc, Xc[:, 2], f, H, W)
    w = np.ones((H, W))
    E_raw = float(flow_loss(xc, xp, f, obs, w, levels=2, raster=r))
    E_tgt = float(flow_loss(xc, xp, f, flow_target(obs, w, 2), raster=r))
    assert E_raw == E_tgt
    bad = obs.copy()
    bad[3, 4] = np.nan
    w0 = w.copy()
    w0[3, 4] = 0.0
    obs0 = obs.copy()
    obs0[3, 4] = 0.0
    assert float(flow_loss(xc, xp, f, bad, levels=2, raster=r)) == pytest.approx(
        float(flow_loss(xc, xp, f, obs0, w0, levels=2, raster=r)), rel=1e-12)
    # float32 inputs work and give float32 results
    t32 = torch.tensor(xc, dtype=torch.float32, requires_grad=True)
    E = flow_loss(t32, torch.tensor(xp, dtype=torch.float32), f, obs.astype(np.float32), raster=r)
    assert E.dtype == torch.float32
    E.backward()
    assert t32.grad.dtype == torch.float32


def test_flow_ops_reject_bad_inputs():
    H, W = 40, 48
    f, Xc, Xp, xc, xp, obs = _bumpy_sheet(H, W)
    r = rasterize(xc, Xc[:, 2], f, H, W)
    with pytest.raises(InputError):
        flow_loss(xc, xp, f, obs)  # neither raster nor depth
    with pytest.raises(InputError):
        flow_loss(xc, xp, f, obs[..., :1], raster=r)
    with pytest.raises(InputError):
        flow_loss(xc, xp, f, obs[:10], raster=r)  # raster of another size
    with pytest.raises(InputError):
        flow_loss(xc, xp, f, obs, -np.ones((H, W)), raster=r)
    with pytest.raises(InputError):
        flow_loss(xc, xp[:-1], f, obs, raster=r)
    with pytest.raises(InputError):
        flow_loss(np.where(np.arange(len(xc))[:, None] == 3, np.nan, xc), xp, f, obs, raster=r)
    with pytest.raises(InputError):
        flow_loss(xc, xp, f, obs, raster=r, levels=0)
    with pytest.raises(InputError):
        flow_loss(xc, xp, f, flow_target(obs), raster=r, levels=4)
    with pytest.raises(InputError):
        flow_loss(xc, xp, f, obs, raster=r, depth_prev=Xp[:, 2])  # exact mode needs depth_cur
    with pytest.raises(InputError):
        render_flow(r, xc, xp, f[:3])  # raster of another mesh
    with pytest.raises(InputError):
        render_flow(np.zeros((H, W)), xc, xp, f)
    with pytest.raises(InputError):
        flow_target(np.zeros((0, 4, 2)))
    with pytest.raises(InputError):
        pyr_down(np.zeros((0, 3)))


def test_internal_rasterisation_matches_an_explicit_raster():
    """flow_loss rasterises into reused buffers; results must not depend on earlier calls."""
    H, W = 40, 48
    f, Xc, Xp, xc, xp, obs = _bumpy_sheet(H, W)
    sphere, sf = icosphere(2, 0.4)
    Xs = sphere + np.array([0.3, 0.1, 2.5])
    xs = project(Xs, H, W, 40.0)
    for shift in (0.0, 7.0, -5.0):
        E_big = flow_loss(xs + shift, xs + shift + 0.5, sf, obs, depth_cur=Xs[:, 2])
        r = rasterize(xs + shift, Xs[:, 2], sf, H, W)
        assert E_big.item() == flow_loss(xs + shift, xs + shift + 0.5, sf, obs, raster=r).item()
        E = flow_loss(xc + shift, xp + shift, f, obs, depth_cur=Xc[:, 2])
        r = rasterize(xc + shift, Xc[:, 2], f, H, W)
        assert E.item() == flow_loss(xc + shift, xp + shift, f, obs, raster=r).item()
        assert r.bbox == (0, 0, 0, 0) or (r.face_id[: r.bbox[0]] < 0).all()


def test_the_flow_term_on_a_worker_thread_gives_the_same_value_and_gradients():
    """flow_loss_async (the tracker's: E_f on its own thread while the other terms are
    built) is flow_loss bit for bit, and raises its errors when finished."""
    from concurrent.futures import ThreadPoolExecutor

    from flowmocap.render import flow_loss_async

    H, W = 40, 48
    f, Xc, Xp, xc, xp, obs = _bumpy_sheet(H, W)
    target = flow_target(obs, None, 3)
    with ThreadPoolExecutor(max_workers=1) as pool:
        for cull in (False, True):
            grads = []
            values = []
            for run in ("serial", "async"):
                cur = torch.tensor(xc, dtype=torch.float32, requires_grad=True)
                depth = torch.tensor(Xc[:, 2], dtype=torch.float32, requires_grad=True)
                prev = torch.tensor(xp, dtype=torch.float32)
                if run == "serial":
                    E = flow_loss(cur, prev, f, target, depth_cur=depth, cull_backfaces=cull)
                else:
                    finish = flow_loss_async(pool, cur, prev, f, target, depth_cur=depth, cull_backfaces=cull)
                    E = finish()
                (2.0 * E).backward()
                values.append(E.item())
                grads.append(cur.grad.clone())
                assert depth.grad is None  # depth only rasterises
            assert values[0] == values[1] and values[0] > 0
            assert torch.equal(grads[0], grads[1])
            # the worker's rasterisation is the mesh's coverage, as rasterize gives it
            pending = flow_loss_async(pool, cur, prev, f, target, depth_cur=depth, cull_backfaces=cull)
            np.testing.assert_array_equal(pending.raster().face_id,
                                          rasterize(xc, Xc[:, 2], f, H, W, cull_backfaces=cull).face_id)
            assert pending().item() == values[0]
        bad = torch.tensor(xc, dtype=torch.float32)
        bad[0, 0] = float("nan")
        finish = flow_loss_async(pool, bad, torch.tensor(xp), f, target, depth_cur=torch.tensor(Xc[:, 2]))
        with pytest.raises(InputError):
            finish()
        with pytest.raises(InputError, match="FlowTarget"):
            flow_loss_async(pool, bad, torch.tensor(xp), f, obs, depth_cur=torch.tensor(Xc[:, 2]))


def _fd_columns(fun, x0, cols, h=1e-6):
    """Central differences of the vector function ``fun`` w.r.t. the flat entries ``cols`` of ``x0``."""
    out = []
    for i in cols:
        xp, xm = x0.copy(), x0.copy()
        xp.reshape(-1)[i] += h
        xm.reshape(-1)[i] -= h
        out.append((fun(xp) - fun(xm)) / (2 * h))
    return np.stack(out, axis=1)


def _flow_case(H=30, W=36, seed=0):
    """:func:`_bumpy_sheet` with per-pixel weights and its raster, held fixed: with
    visibility fixed the residuals are smooth in the vertices."""
    from flowmocap.render import rasterize

    f, Xc, Xp, xc, xp, obs = _bumpy_sheet(H, W, seed)
    w = np.random.default_rng(seed + 100).random((H, W)) + 0.2
    raster = rasterize(xc, Xc[:, 2], f, H, W)
    assert (raster.face_id >= 0).sum() > 100
    return f, xc, xp, Xc[:, 2].copy(), Xp[:, 2].copy(), obs, w, raster


@pytest.mark.parametrize("levels,covered_only,exact", [(1, False, False), (2, False, True), (3, True, True),
                                                       (2, True, False)])
def test_flow_residual_jacobians_match_finite_differences(levels, covered_only, exact):
    """Every Jacobian of flow_residuals (cur, prev and, exact mode, both depths), column by
    column against central differences of the residuals (visibility fixed, no boundary term)."""
    from flowmocap.render import flow_residuals

    f, xc, xp, zc, zp, obs, w, raster = _flow_case()
    base = {"xc": xc, "xp": xp, "zc": zc, "zp": zp}

    def res(vals):
        kw = dict(levels=levels, raster=raster, covered_only=covered_only, boundary=False)
        if exact:
            kw.update(depth_cur=vals["zc"], depth_prev=vals["zp"])
        return flow_residuals(vals["xc"], vals["xp"], f, obs, w, **kw)

    R = res(base)
    jac = {"xc": R.jac_cur, "xp": R.jac_prev, "zc": R.jac_depth_cur, "zp": R.jac_depth_prev}
    rng = np.random.default_rng(7)
    for name in (["xc", "xp"] + (["zc", "zp"] if exact else [])):
        x0 = base[name]
        cols = rng.choice(x0.size, size=min(12, x0.size), replace=False)

        def fun(x, name=name):
            vals = dict(base)
            vals[name] = x
            return res(vals).residuals

        fd = _fd_columns(fun, x0, cols)
        got = jac[name][:, cols].toarray()
        assert np.abs(fd).max() > 1e-3, name
        np.testing.assert_allclose(got, fd, atol=1e-7 * np.abs(fd).max(), rtol=1e-6, err_msg=name)


@pytest.mark.parametrize("levels", [1, 3])
@pytest.mark.parametrize("exact", [False, True])
def test_flow_loss_covered_only_gradient_matches_finite_differences(levels, exact):
    """flow_loss(covered_only=True): its compiled gradient against central differences (the
    existing tests check it only against the hand-written Jacobian)."""
    from flowmocap.render import flow_loss

    f, xc, xp, zc, zp, obs, w, raster = _flow_case(seed=1)
    base = {"xc": xc, "xp": xp, "zc": zc, "zp": zp}

    def energy(vals, grad=False):
        kw = dict(levels=levels, raster=raster, covered_only=True, boundary=False)
        if exact:
            kw.update(depth_cur=vals["zc"], depth_prev=vals["zp"])
        return flow_loss(vals["xc"], vals["xp"], f, obs, w, **kw)

    tens = {k: torch.tensor(v, requires_grad=True) for k, v in base.items()}
    E = energy(tens)
    E.backward()
    rng = np.random.default_rng(8)
    for name in (["xc", "xp"] + (["zc", "zp"] if exact else [])):
        g = tens[name].grad.numpy().ravel()
        cols = rng.choice(g.size, size=min(16, g.size), replace=False)

        def fun(x, name=name):
            vals = dict(base)
            vals[name] = x
            return np.array([float(energy(vals))])

        fd = _fd_columns(fun, base[name], cols)[0]
        assert np.linalg.norm(fd) > 1e-2
        assert np.linalg.norm(g[cols] - fd) <= 1e-6 * np.linalg.norm(fd), (name, g[cols], fd)

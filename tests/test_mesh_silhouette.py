"""E_c with the model silhouette from the mesh (fit.energies.mesh_silhouette_*)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flowmocap.body import load_body_model
from flowmocap.errors import InputError
from flowmocap.fit.energies import _bilinear, mesh_silhouette_energy, mesh_silhouette_residuals, silhouette_target
from flowmocap.geometry import PinholeCamera, look_at
from flowmocap.io import walk_poses
from flowmocap.render import prepare_faces, rasterize, silhouette


@pytest.fixture(scope="module")
def setup():
    body = load_body_model("default", dtype=torch.float64)
    H, W = 240, 320
    R, t = look_at((0.3, 0.2, 3.0), (0.0, -0.1, 0.0))
    cam = PinholeCamera.from_focal(W, H, 300.0, R, t)  # about 1 px per cm at the body
    pose = torch.tensor(walk_poses(np.array([0.3])))
    faces = prepare_faces(body.faces_np)

    def project(trans):
        v = body(pose=pose, trans=torch.as_tensor(trans, dtype=torch.float64).reshape(1, 3)).vertices[0]
        return cam.project(v), cam.depth(v)

    px, d = project([0.0, 0.0, 0.0])
    mask = silhouette(rasterize(px.numpy(), d.numpy(), faces, H, W))
    return {"project": project, "faces": faces, "target": silhouette_target(mask, dtype=torch.float64),
            "mask": mask}


def test_bilinear_sampling_matches_closed_form_and_grows_outside_the_image():
    img = torch.tensor([[0.0, 1.0], [2.0, 3.0]], dtype=torch.float64)
    # pixel centres at +0.5: (1.0, 1.0) is the middle of the four centres
    pts = torch.tensor([[0.5, 0.5], [1.5, 1.5], [1.0, 1.0], [1.0, 0.5], [-2.5, 0.5]], dtype=torch.float64)
    got = _bilinear(img, pts).numpy()
    np.testing.assert_allclose(got, [0.0, 3.0, 1.5, 0.5, 3.0], atol=1e-5)


def test_zero_at_the_true_pose_and_growing_with_the_offset(setup):
    px, d = setup["project"]([0.0, 0.0, 0.0])
    e0 = float(mesh_silhouette_energy(px, d, setup["faces"], setup["target"]))
    assert e0 < 0.01  # px^2: the mask is the mesh's own silhouette
    energies = []
    for dx in (0.01, 0.02, 0.04):
        px, d = setup["project"]([dx, 0.0, 0.0])
        energies.append(float(mesh_silhouette_energy(px, d, setup["faces"], setup["target"])))
    assert e0 < energies[0] < energies[1] < energies[2]
    # 4 cm is about 4 px sideways: vertices on the far side leave the mask by up to 4 px
    assert 0.3 < energies[2] < 16.0


def test_both_parts_present_and_weighted_by_a(setup):
    px, d = setup["project"]([0.03, 0.02, 0.0])
    V = px.shape[0]
    r = mesh_silhouette_residuals(px, d, setup["faces"], setup["target"], a=0.6)
    assert r.shape[0] > V  # uncovered mask pixels add residuals
    assert (r[:V] > 0).any() and (r[V:] > 0).all()
    r1 = mesh_silhouette_residuals(px, d, setup["faces"], setup["target"], a=1.0)
    assert r1.shape[0] == V
    np.testing.assert_allclose(r1.numpy(), r[:V].numpy() * np.sqrt(1.0 / 0.6), rtol=1e-10)


def test_a_given_rasterisation_gives_the_same_residuals(setup):
    px, d = setup["project"]([0.03, -0.02, 0.05])
    own = mesh_silhouette_residuals(px, d, setup["faces"], setup["target"], a=0.4, grid_step=4)
    raster = rasterize(px.numpy(), d.numpy(), setup["faces"], 240, 320, cull_backfaces=True)
    given = mesh_silhouette_residuals(px, d, setup["faces"], setup["target"], a=0.4, grid_step=4, raster=raster)
    assert own.shape[0] > px.shape[0]  # some of the mask is uncovered: both parts present
    assert torch.equal(own, given)


def test_gradient_matches_finite_differences(setup):
    px, d = setup["project"]([0.03, 0.02, 0.0])
    x = px.detach().clone().requires_grad_()
    e = mesh_silhouette_energy(x, d, setup["faces"], setup["target"], a=0.6)
    e.backward()
    g = x.grad.numpy()
    rng = np.random.default_rng(0)
    # vertices that matter: those with a non-zero gradient, plus a few others
    idx = np.flatnonzero(np.abs(g).sum(1) > 0)
    assert len(idx) > 20
    pick = np.concatenate([rng.choice(idx, 15, replace=False), rng.choice(len(g), 5, replace=False)])
    h = 1e-5
    for v in pick:
        for c in range(2):
            xp = px.detach().clone(); xp[v, c] += h
            xm = px.detach().clone(); xm[v, c] -= h
            fd = (float(mesh_silhouette_energy(xp, d, setup["faces"], setup["target"]))
                  - float(mesh_silhouette_energy(xm, d, setup["faces"], setup["target"]))) / (2 * h)
            assert abs(fd - g[v, c]) <= 1e-6 + 1e-4 * abs(g[v, c]), (v, c, fd, g[v, c])


def test_bad_arguments(setup):
    px, d = setup["project"]([0.0, 0.0, 0.0])
    with pytest.raises(InputError):
        mesh_silhouette_residuals(px, d, setup["faces"], setup["target"], a=1.5)
    with pytest.raises(InputError):
        mesh_silhouette_residuals(px[:, :1], d, setup["faces"], setup["target"])
    with pytest.raises(InputError):
        mesh_silhouette_residuals(px, d, setup["faces"], setup["target"], grid_step=0)


def test_nearest_vertex_by_scan_or_tree_gives_the_same_residuals(setup, monkeypatch):
    from scipy.spatial import cKDTree

    from flowmocap.fit import energies

    rng = np.random.default_rng(0)
    pts, queries = rng.uniform(0, 100, (500, 2)), rng.uniform(-10, 110, (40, 2))
    nn = np.empty(40, dtype=np.int64)
    energies._nearest_points(queries, pts, nn)
    np.testing.assert_array_equal(nn, cKDTree(pts).query(queries)[1])
    px, d = setup["project"]([0.05, 0.03, 0.1])
    for step in (2, 8):  # many uncovered samples (a k-d tree) and few (a scan)
        scanned = mesh_silhouette_residuals(px, d, setup["faces"], setup["target"], grid_step=step)
        monkeypatch.setattr(energies, "_BRUTE_FORCE_QUERIES", 0 if scanned.shape[0] - px.shape[0] <= 150 else 10**6)
        other = mesh_silhouette_residuals(px, d, setup["faces"], setup["target"], grid_step=step)
        monkeypatch.undo()
        assert scanned.shape[0] > px.shape[0]
        assert torch.equal(scanned, other)


def _residual_form(px, d, faces, target, **kw):
    x = px.detach().clone().requires_grad_()
    e = (mesh_silhouette_residuals(x, d, faces, target, **kw) ** 2).sum()
    e.backward()
    return float(e.detach()), x.grad.numpy()


def test_compiled_energy_equals_the_residual_form_with_its_gradient(setup):
    """mesh_silhouette_energy (one compiled pass) against the sum of squares of the torch
    residuals and autograd's gradient of it, float64: vertices inside and outside the mask,
    some outside the image (the chamfer map's border value plus the distance to it)."""
    rng = np.random.default_rng(3)
    for shift, a, step in (([0.03, 0.02, 0.0], 0.6, 4), ([0.05, -0.03, 0.1], 0.4, 8), ([0.02, 0.0, 0.0], 1.0, 4)):
        px, d = setup["project"](shift)
        px = px.detach().clone()
        if shift[2] > 0:  # a few vertices pushed outside the 320 x 240 image
            far = rng.choice(px.shape[0], 30, replace=False)
            px[far] += torch.as_tensor(rng.uniform(-400, 400, (30, 2)))
        want, want_grad = _residual_form(px, d, setup["faces"], setup["target"], a=a, grid_step=step)
        x = px.clone().requires_grad_()
        got = mesh_silhouette_energy(x, d, setup["faces"], setup["target"], a=a, grid_step=step)
        got.backward()
        assert want > 0.01
        assert got.dtype == torch.float64 and got.dim() == 0
        np.testing.assert_allclose(float(got.detach()), want, rtol=1e-10)
        np.testing.assert_allclose(x.grad.numpy(), want_grad, rtol=1e-8, atol=1e-12)


def test_compiled_energy_in_float32_follows_the_float64_one(setup):
    px, d = setup["project"]([0.03, 0.02, 0.0])
    x = px.detach().to(torch.float32).requires_grad_()
    target32 = silhouette_target(setup["mask"], dtype=torch.float32)
    e = mesh_silhouette_energy(x, d.to(torch.float32), setup["faces"], target32)
    e.backward()
    want, want_grad = _residual_form(px, d, setup["faces"], setup["target"])
    assert e.dtype == torch.float32 and x.grad.dtype == torch.float32
    np.testing.assert_allclose(float(e.detach()), want, rtol=1e-4)
    np.testing.assert_allclose(x.grad.numpy(), want_grad, rtol=1e-3, atol=1e-6)


def test_unknown_pixels_cost_nothing_to_cover(setup):
    """``silhouette_target(mask, unknown=U)``: the chamfer map is the distance to the mask
    or U (0 on both), the mask the body must cover stays the mask; a vertex over U adds
    nothing to the model-outside-the-mask part; a U of another shape is refused."""
    import numpy as np
    import pytest
    import torch

    from flowmocap.errors import InputError
    from flowmocap.fit.energies import mesh_silhouette_residuals, silhouette_target
    from flowmocap.vision.masks import chamfer_map

    mask = np.zeros((40, 60), bool)
    mask[10:30, 10:25] = True
    unknown = np.zeros_like(mask)
    unknown[5:35, 25:45] = True
    plain, aware = silhouette_target(mask), silhouette_target(mask, unknown=unknown)
    assert aware.count == plain.count == mask.sum() and torch.equal(aware.mask, plain.mask)
    np.testing.assert_array_equal(aware.chamfer.numpy(), chamfer_map(mask | unknown).astype(np.float32))
    assert float(aware.chamfer[20, 40]) == 0.0 and float(plain.chamfer[20, 40]) == pytest.approx(16.0)
    # one triangle, two vertices over the unknown pixels, one over the mask
    px = torch.tensor([[30.0, 12.0], [40.0, 20.0], [15.0, 20.0]], dtype=torch.float64)
    depth = torch.ones(3, dtype=torch.float64)
    faces = np.array([[0, 1, 2]])
    r_plain = mesh_silhouette_residuals(px, depth, faces, silhouette_target(mask, dtype=torch.float64), a=1.0)
    r_aware = mesh_silhouette_residuals(px, depth, faces, silhouette_target(mask, dtype=torch.float64,
                                                                            unknown=unknown), a=1.0)
    assert float(r_plain[:2].min()) > 0 and float(r_aware.abs().max()) == 0.0
    with pytest.raises(InputError, match="unknown must have the mask's shape"):
        silhouette_target(mask, unknown=unknown[:, :50])

"""Rasteriser, interpolation, silhouettes and shading (flowmocap.render)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import binary_dilation, binary_erosion

from flowmocap.errors import InputError
from flowmocap.render import body_mask, interpolate, prepare_faces, rasterize, shade, silhouette
from flowmocap.render.primitives import box, grid_mesh, icosphere, mannequin


def project(X: np.ndarray, f: float, cx: float, cy: float) -> np.ndarray:
    return np.stack([f * X[:, 0] / X[:, 2] + cx, f * X[:, 1] / X[:, 2] + cy], axis=1)


def brute_force(xy, z, faces, H, W):
    """Reference: test every pixel centre against every triangle (strictly inside),
    nearest perspective-correct depth wins, lowest index on ties."""
    fid = np.full((H, W), -1)
    bary = np.zeros((H, W, 3))
    depth = np.full((H, W), np.inf)
    for v in range(H):
        for u in range(W):
            p = np.array([u + 0.5, v + 0.5])
            for k, (a, b, c) in enumerate(faces):
                M = np.array([[xy[a, 0], xy[b, 0], xy[c, 0]], [xy[a, 1], xy[b, 1], xy[c, 1]], [1.0, 1.0, 1.0]])
                if abs(np.linalg.det(M)) < 1e-12:
                    continue
                lam = np.linalg.solve(M, [p[0], p[1], 1.0])
                if np.any(lam <= 0):
                    continue
                q = lam / z[[a, b, c]]
                d = 1.0 / q.sum()
                if d < depth[v, u]:
                    depth[v, u], fid[v, u], bary[v, u] = d, k, q * d
    return fid, bary, depth


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rasterize_matches_brute_force_on_random_soups(seed):
    rng = np.random.default_rng(seed)
    H, W, F = 17, 23, 12
    xy = rng.uniform([-4, -4], [W + 4, H + 4], size=(3 * F, 2))
    z = rng.uniform(1.0, 5.0, size=3 * F)
    faces = np.arange(3 * F).reshape(F, 3)
    r = rasterize(xy, z, faces, H, W)
    fid, bary, depth = brute_force(xy, z, faces, H, W)
    assert r.face_id.dtype == np.int32 and r.bary.dtype == np.float32 and r.depth.dtype == np.float32
    assert (r.face_id >= 0).sum() > 50  # overlapping soup covers a good part of the image
    np.testing.assert_array_equal(r.face_id, fid)
    vs, us = np.nonzero(fid >= 0)
    r0, r1, c0, c1 = r.bbox
    assert r0 <= vs.min() and vs.max() < r1 and c0 <= us.min() and us.max() < c1
    np.testing.assert_allclose(r.bary, bary, atol=2e-6)
    cov = fid >= 0
    np.testing.assert_allclose(r.depth[cov], depth[cov], rtol=1e-6)
    assert np.all(np.isinf(r.depth[~cov])) and np.all(r.bary[~cov] == 0)


def _coverage_count(xy, z, faces, H, W):
    count = np.zeros((H, W), dtype=int)
    for tri in faces:
        count += rasterize(xy, z, tri[None], H, W).face_id >= 0
    return count


def test_shared_edges_have_no_gaps_and_no_double_coverage():
    # a grid whose vertices and diagonals pass exactly through pixel centres
    H, W = 14, 16
    verts, faces = grid_mesh(5, 4, size=(10.0, 8.0))
    xy = verts[:, :2] + np.array([7.5, 6.5])  # vertices at pixel centres (x.5)
    z = np.ones(len(xy))
    count = _coverage_count(xy, z, faces, H, W)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    inside = (u > 2.5) & (u < 12.5) & (v > 2.5) & (v < 10.5)
    assert count.max() == 1
    np.testing.assert_array_equal(count[inside], 1)
    # a fan around a vertex sitting exactly on a pixel centre, edges through centres
    ang = np.linspace(0, 2 * np.pi, 9)[:-1]
    ring = np.stack([8.5 + 4 * np.round(np.cos(ang), 6), 6.5 + 4 * np.round(np.sin(ang), 6)], 1)
    xy2 = np.concatenate([[[8.5, 6.5]], ring])
    fan = np.array([[0, 1 + k, 1 + (k + 1) % 8] for k in range(8)])
    count2 = _coverage_count(xy2, np.ones(9), fan, H, W)
    assert count2.max() == 1 and count2[6, 8] == 1
    r = rasterize(xy2, np.ones(9), fan, H, W)
    np.testing.assert_array_equal(r.face_id >= 0, count2 == 1)


def test_backface_culling_and_orientation():
    verts, faces = icosphere(2)
    X = verts + np.array([0.0, 0.0, 4.0])
    xy = project(X, 40.0, 16.0, 16.0)
    full = rasterize(xy, X[:, 2], faces, 32, 32)
    culled = rasterize(xy, X[:, 2], faces, 32, 32, cull_backfaces=True)
    np.testing.assert_array_equal(full.face_id, culled.face_id)  # closed mesh: back faces hidden
    flipped = rasterize(xy, X[:, 2], faces[:, ::-1], 32, 32, cull_backfaces=True)
    # with reversed winding only the inside (far half) of the sphere is drawn
    cov = full.face_id >= 0
    np.testing.assert_array_equal(flipped.face_id >= 0, cov)
    assert np.all(flipped.depth[cov] > full.depth[cov])


def test_body_mask_is_the_silhouette_of_a_closed_mesh():
    verts, faces = mannequin(2)
    X = verts + np.array([0.0, -0.9, 3.0])
    xy = project(X, 60.0, 24.0, 32.0)
    mask = body_mask(torch.as_tensor(xy), torch.as_tensor(X[:, 2]), prepare_faces(faces), 64, 48)
    assert mask.dtype == bool and mask.shape == (64, 48) and 0 < mask.sum() < mask.size
    np.testing.assert_array_equal(mask, silhouette(rasterize(xy, X[:, 2], faces, 64, 48)))


def test_near_plane_skips_triangles():
    xy = np.array([[2.0, 2.0], [14.0, 2.0], [2.0, 14.0], [14.0, 14.0]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    r = rasterize(xy, np.array([1.0, 1.0, 1.0, 1e-4]), faces, 16, 16)
    assert set(np.unique(r.face_id)) == {-1, 0}
    r = rasterize(xy, np.array([1.0, 1.0, 1.0, -2.0]), faces, 16, 16, near=0.5)
    assert set(np.unique(r.face_id)) == {-1, 0}


def test_interpolate_gives_the_surface_point_on_the_pixel_ray():
    verts, faces = box((1.0, 0.8, 0.6))
    ang = 0.6
    R = np.array([[np.cos(ang), 0, np.sin(ang)], [0, 1, 0], [-np.sin(ang), 0, np.cos(ang)]])
    X = verts @ R.T + np.array([0.1, -0.05, 2.5])
    f, cx, cy = 30.0, 20.0, 15.0
    xy = project(X, f, cx, cy)
    r = rasterize(xy, X[:, 2], faces, 30, 40)
    P = interpolate(r, X, faces)
    cov = r.mask
    assert cov.sum() > 100
    vs, us = np.nonzero(cov)
    np.testing.assert_allclose(f * P[cov, 0] / P[cov, 2] + cx, us + 0.5, atol=1e-4)
    np.testing.assert_allclose(f * P[cov, 1] / P[cov, 2] + cy, vs + 0.5, atol=1e-4)
    np.testing.assert_allclose(P[cov, 2], r.depth[cov], rtol=1e-5)
    assert np.all(P[~cov] == 0)
    # torch path: same values, differentiable w.r.t. the attribute
    attr = torch.tensor(X, requires_grad=True)
    Pt = interpolate(r, attr, faces)
    np.testing.assert_allclose(Pt.detach().numpy(), P, atol=1e-6)
    Pt[..., 2].sum().backward()
    counts = np.bincount(faces[r.face_id[cov]].ravel(), weights=r.bary[cov].ravel(), minlength=8)
    np.testing.assert_allclose(attr.grad[:, 2].numpy(), counts, rtol=1e-5)
    assert silhouette(r).dtype == bool and silhouette(r, np.float32).sum() == cov.sum()


def test_prepared_faces_are_reused():
    verts, faces = icosphere(1)
    X = verts + np.array([0, 0, 3.0])
    xy = project(X, 20.0, 10.0, 10.0)
    pf = prepare_faces(faces)
    a = rasterize(xy, X[:, 2], pf, 20, 20)
    b = rasterize(xy, X[:, 2], faces, 20, 20)
    np.testing.assert_array_equal(a.face_id, b.face_id)


def test_bad_inputs_raise_input_error():
    xy = np.array([[1.0, 1.0], [5.0, 1.0], [1.0, 5.0]])
    z = np.ones(3)
    f = np.array([[0, 1, 2]])
    with pytest.raises(InputError):
        rasterize(xy[:, :1], z, f, 8, 8)
    with pytest.raises(InputError):
        rasterize(np.where(np.eye(3, 2) > 0, np.nan, xy), z, f, 8, 8)
    with pytest.raises(InputError):
        rasterize(xy, z[:2], f, 8, 8)
    with pytest.raises(InputError):
        rasterize(xy, np.array([1.0, np.inf, 1.0]), f, 8, 8)
    with pytest.raises(InputError):
        rasterize(xy, z, f, 0, 8)
    with pytest.raises(InputError):
        rasterize(xy, z, np.array([[0, 1, 3]]), 8, 8)
    with pytest.raises(InputError):
        rasterize(xy, z, np.array([[0, 1]]), 8, 8)
    with pytest.raises(InputError):
        rasterize(xy, z, f, 8, 8, near=0.0)
    r = rasterize(xy, z, f, 8, 8)
    with pytest.raises(InputError):
        interpolate(r, np.ones((2, 3)), f)
    with pytest.raises(InputError):
        interpolate(np.zeros((8, 8)), np.ones((3, 3)), f)
    with pytest.raises(InputError):
        shade(xy, z, f, np.c_[xy, z], colors=np.ones((3, 3)))  # no size, no background
    with pytest.raises(InputError):
        shade(xy, z, f, np.c_[xy, z], height=8, width=8)  # no colour source
    with pytest.raises(InputError):
        shade(xy, z, f, np.c_[xy, z], colors=np.ones((3, 3)), height=8, width=8, supersample=0)


def _scene():
    verts, faces = mannequin(2)
    X = verts * np.array([1.0, -1.0, -1.0]) + np.array([0.0, 0.88, 3.0])
    xy = project(X, 60.0, 32.0, 24.0)
    return verts, faces, X, xy


def test_shade_is_antialiased_and_composited():
    verts, faces, X, xy = _scene()
    H, W = 48, 64
    bg = np.zeros((H, W, 3), dtype=np.uint8)
    bg[..., 2] = 200
    bg[::2, :, 0] = 90
    white = np.ones((len(verts), 3))
    img1 = shade(xy, X[:, 2], faces, X, white, background=bg, supersample=1, ambient=1.0)
    img4 = shade(xy, X[:, 2], faces, X, white, background=bg, supersample=4, ambient=1.0)
    assert img4.dtype == np.uint8 and img4.shape == (H, W, 3)
    # without supersampling every pixel is either surface (255) or background
    g1 = img1[..., 1]
    assert set(np.unique(g1)) <= {0, 255}
    # with 4x4 samples the outline has intermediate (blended) values
    g4 = img4[..., 1]
    mixed = (g4 > 0) & (g4 < 255)
    assert mixed.sum() > 40
    # background untouched away from the body, fully covered pixels pure surface colour
    r = rasterize(xy, X[:, 2], faces, H, W)
    far = ~binary_dilation(r.mask, iterations=2)
    np.testing.assert_array_equal(img4[far], bg[far])
    inner = binary_erosion(r.mask, iterations=2)
    assert np.all(img4[inner] == 255)
    # mixed pixels blend the surface and background colours
    assert np.all(img4[mixed][:, 2] >= 200)


def test_shade_lambertian_and_pattern():
    verts, faces, X, xy = _scene()
    H, W = 48, 64
    grey = np.full((len(verts), 3), 0.8)
    lit = shade(xy, X[:, 2], faces, X, grey, height=H, width=W, light_dir=(0, 0, -1), ambient=0.0)
    r = rasterize(xy, X[:, 2], faces, H, W)
    inner = binary_erosion(r.mask, iterations=2)
    # facing the camera = brightest, never brighter than the albedo
    assert lit[inner].max() <= round(0.8 * 255) + 1 and lit[inner].max() >= 0.95 * 0.8 * 255
    pat = shade(xy, X[:, 2], faces, X, surface_coords=verts, height=H, width=W, supersample=2)
    # the procedural texture has plenty of local contrast for optical flow
    gray = pat.astype(float).mean(axis=2)
    gx = np.abs(np.diff(gray, axis=1))[inner[:, 1:] & inner[:, :-1]]
    assert np.median(gx) > 4.0
    # texture source gives the same as per-vertex colours for a constant texture
    tex = np.full((4, 4, 3), 204, dtype=np.uint8)
    uv = np.random.default_rng(0).random((len(verts), 2))
    t_img = shade(xy, X[:, 2], faces, X, uv=uv, texture=tex, height=H, width=W, light_dir=(0, 0, -1), ambient=0.0)
    assert np.abs(t_img.astype(int) - lit.astype(int)).max() <= 1

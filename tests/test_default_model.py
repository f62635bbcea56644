"""The bundled default body: topology, rest pose, shape space, joints, capsules."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flowmocap.body import JOINT_INDEX, body_capsules, load_body_model
from flowmocap.body.capsules import _vertex_sets, point_capsule_distance
from flowmocap.body.files import GENDERS, read_model_arrays


@pytest.fixture(scope="module", params=GENDERS)
def model(request):
    return load_body_model("default", gender=request.param, dtype=torch.float64)


def test_all_genders_share_topology():
    arrays = [read_model_arrays("default", g) for g in GENDERS]
    for a in arrays:
        assert 5000 <= a.v_template.shape[0] <= 8000
        np.testing.assert_array_equal(a.faces, arrays[0].faces)
        assert a.posedirs is None
    assert [a.gender for a in arrays] == list(GENDERS)


def test_surface_is_closed(model):
    import trimesh

    mesh = trimesh.Trimesh(model.v_template.numpy(), model.faces_np, process=False)
    assert mesh.is_watertight
    assert mesh.is_winding_consistent
    assert mesh.volume > 0.03  # outward normals, a person's volume (m^3)


def test_weights_and_regressor_are_convex(model):
    w, jr = model.weights, model.J_regressor
    assert (w >= 0).all() and torch.allclose(w.sum(1), torch.ones(w.shape[0], dtype=w.dtype), atol=1e-5)
    assert (jr >= 0).all() and torch.allclose(jr.sum(1), torch.ones(24, dtype=jr.dtype), atol=1e-5)


def test_rest_pose_is_smpl_tpose(model):
    j = model().joints[0]
    J = JOINT_INDEX
    assert j[J["left_hip"], 0] > 0 > j[J["right_hip"], 0]  # left = +x
    assert j[J["head"], 1] > j[J["neck"], 1] > j[J["pelvis"], 1] > j[J["left_knee"], 1] > j[J["left_ankle"], 1]
    # arms straight out sideways: wrist at shoulder height, far out in x
    for side in ("left", "right"):
        sh, wr = j[J[f"{side}_shoulder"]], j[J[f"{side}_wrist"]]
        assert abs(float(wr[1] - sh[1])) < 0.08
        assert abs(float(wr[0] - sh[0])) > 0.4
    # facing +z: toes ahead of ankles
    assert j[J["left_foot"], 2] > j[J["left_ankle"], 2] + 0.05
    torch.testing.assert_close(j[0], torch.zeros(3, dtype=j.dtype), atol=1e-3, rtol=0)


def test_joints_inside_the_body(model):
    """Joints sit inside the surface (at joint centres, not on the skin)."""
    joints = model().joints[0].numpy()
    inside = _winding_number(model.v_template.numpy(), model.faces_np, joints) > 0.5
    names = [n for n, ok in zip(model.joint_names, inside) if not ok]
    assert not names, f"joints outside the surface: {names}"


def _winding_number(verts, faces, points):
    """Generalised winding number (1 inside a closed outward-oriented surface, 0 outside),
    by the solid angles of the triangles (Van Oosterom and Strackee 1983)."""
    out = []
    for p in points:
        a, b, c = (verts[faces[:, i]] - p for i in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        num = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la \
            + np.einsum("ij,ij->i", c, a) * lb
        out.append(2.0 * np.arctan2(num, den).sum() / (4 * np.pi))
    return np.array(out)


@pytest.mark.parametrize("k", [0, 1])
def test_shape_space_is_plausible(k):
    m = load_body_model("default", gender="neutral", dtype=torch.float64)
    heights = []
    for value in (-3.0, 0.0, 3.0):
        betas = torch.zeros(1, 10, dtype=torch.float64)
        betas[0, k] = value
        v = m(betas=betas).vertices[0]
        heights.append(float(v[:, 1].max() - v[:, 1].min()))
    # anny's adult population mixes genders in the neutral model: -3..+3 sd of beta0
    # spans about 1.32..2.06 m (see body/data/ATTRIBUTION.md)
    assert all(1.25 < h < 2.15 for h in heights), heights
    if k == 0:
        assert 1.6 < heights[1] < 1.8


def test_shape_components_have_unit_variance_scale():
    """shapedirs are scaled like SMPL's: one unit of beta moves vertices by centimetres."""
    a = read_model_arrays("default", "neutral")
    rms = np.sqrt((a.shapedirs ** 2).sum(1).mean(0))  # per component, metres
    assert (rms[:3] > 0.005).all() and (rms < 0.2).all()


def test_capsules_fit_the_default_body(model):
    out = model()
    caps = body_capsules(model, out)
    d = point_capsule_distance(out.vertices, caps)[0]
    for k, idx in enumerate(_vertex_sets(model)):
        assert idx.numel() >= 4, caps.names[k]
        assert d[idx, k].abs().median() < 0.03, caps.names[k]

"""Body model: skinning, loaders, gradients, capsules."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from flowmocap.body import JOINT_INDEX, body_capsules, load_body_model
from flowmocap.body.capsules import point_capsule_distance
from flowmocap.body.files import read_model_arrays
from flowmocap.errors import InputError, ModelFileError
from flowmocap.geometry.rotations import axis_angle_to_matrix


def _descendants(j):
    from flowmocap.body.skeleton import PARENTS

    out = {j}
    changed = True
    while changed:
        changed = False
        for k, p in enumerate(PARENTS):
            if p in out and k not in out:
                out.add(k)
                changed = True
    return out


def test_zero_pose_returns_template(toy_model):
    out = toy_model()
    assert torch.allclose(out.vertices[0], toy_model.v_template, atol=1e-12)
    betas = torch.randn(2, 10, dtype=torch.float64)
    out = toy_model(betas=betas)
    expected = toy_model.v_template + torch.einsum("vcs,bs->bvc", toy_model.shapedirs, betas)
    assert torch.allclose(out.vertices, expected, atol=1e-12)


def test_joints_follow_regressor(toy_model):
    betas = torch.randn(3, 10, dtype=torch.float64)
    trans = torch.randn(3, 3, dtype=torch.float64)
    out = toy_model(betas=betas, trans=trans)
    regressed = torch.einsum("jv,bvc->bjc", toy_model.J_regressor, out.vertices)
    assert torch.allclose(out.joints, regressed, atol=1e-10)


def test_root_rotation_and_translation_move_rigidly(toy_model):
    torch.manual_seed(0)
    betas = torch.randn(1, 10, dtype=torch.float64)
    rest = toy_model(betas=betas)
    pose = torch.zeros(1, 72, dtype=torch.float64)
    pose[0, :3] = torch.tensor([0.3, -1.1, 0.7])
    trans = torch.tensor([[0.2, -0.5, 3.0]], dtype=torch.float64)
    out = toy_model(betas=betas, pose=pose, trans=trans)
    R = axis_angle_to_matrix(pose[0, :3])
    j0 = rest.joints[0, 0]
    expected = (rest.vertices[0] - j0) @ R.T + j0 + trans[0]
    assert torch.allclose(out.vertices[0], expected, atol=1e-10)
    expected_j = (rest.joints[0] - j0) @ R.T + j0 + trans[0]
    assert torch.allclose(out.joints[0], expected_j, atol=1e-10)


@pytest.mark.parametrize("joint", ["left_elbow", "right_knee", "spine2"])
def test_single_joint_moves_only_its_region(joint, toy_files):
    model = load_body_model(toy_files["npz"], dtype=torch.float64)
    model.posedirs = None  # pose correctives would move other vertices slightly
    j = JOINT_INDEX[joint]
    pose = torch.zeros(1, 72, dtype=torch.float64)
    pose[0, 3 * j : 3 * j + 3] = torch.tensor([0.4, 0.9, -0.3])
    moved = (model(pose=pose).vertices[0] - model.v_template).norm(dim=1) > 1e-9
    region = model.weights[:, sorted(_descendants(j))].sum(1) > 0
    assert moved.any()
    assert not (moved & ~region).any(), "vertices outside the joint's skinned region moved"
    # joints above the rotated one stay put
    out = model(pose=pose)
    rest = model()
    above = [k for k in range(24) if k not in _descendants(j) or k == j]
    assert torch.allclose(out.joints[0, above], rest.joints[0, above], atol=1e-12)


def test_pose_correctives_are_applied(toy_files, toy_arrays):
    model = load_body_model(toy_files["npz"], dtype=torch.float64)
    pose = torch.zeros(1, 72, dtype=torch.float64)
    pose[0, 3 * 4] = 0.5  # left knee
    with_pd = model(pose=pose).vertices
    model.posedirs = None
    without = model(pose=pose).vertices
    R = axis_angle_to_matrix(pose[0].reshape(24, 3))
    feat = (R[1:] - torch.eye(3, dtype=torch.float64)).reshape(-1)
    offsets = torch.einsum("vcp,p->vc", torch.as_tensor(toy_arrays["posedirs"]), feat)
    # with only the knee rotated, only knee descendants' transforms rotate; the rest are identity
    rigid = model.weights[:, sorted(_descendants(0) - _descendants(4))].sum(1) > 0.999
    assert torch.allclose((with_pd - without)[0, rigid], offsets[rigid], atol=1e-10)


def test_gradients_match_finite_differences(toy_model):
    torch.manual_seed(1)
    betas = (0.5 * torch.randn(1, 10, dtype=torch.float64)).requires_grad_()
    pose = (0.3 * torch.randn(1, 72, dtype=torch.float64)).requires_grad_()
    trans = torch.randn(1, 3, dtype=torch.float64).requires_grad_()
    sel = torch.arange(0, toy_model.num_vertices, 17)

    def f(b, p, t):
        out = toy_model(betas=b, pose=p, trans=t)
        return out.vertices[:, sel], out.joints

    assert torch.autograd.gradcheck(f, (betas, pose, trans), eps=1e-6, atol=1e-6)


def test_a_given_shaped_body_and_joints_only_give_the_same_pose(toy_model):
    torch.manual_seed(2)
    betas = 0.5 * torch.randn(1, 10, dtype=torch.float64)
    pose = (0.3 * torch.randn(3, 72, dtype=torch.float64)).requires_grad_()
    trans = torch.randn(3, 3, dtype=torch.float64)
    full = toy_model(betas=betas, pose=pose, trans=trans)
    shaped = toy_model.shaped(betas)
    given = toy_model(betas=betas, pose=pose, trans=trans, shaped=shaped)
    joints_only = toy_model(betas=betas, pose=pose, trans=trans, shaped=shaped, with_vertices=False)
    assert joints_only.vertices is None
    torch.testing.assert_close(given.vertices, full.vertices, rtol=1e-12, atol=1e-12)
    for out in (given, joints_only):
        torch.testing.assert_close(out.joints, full.joints, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out.transforms, full.transforms, rtol=1e-12, atol=1e-12)
    (g_full,) = torch.autograd.grad(full.joints.sum() + full.transforms.sum(), pose)
    (g_only,) = torch.autograd.grad(joints_only.joints.sum() + joints_only.transforms.sum(), pose)
    torch.testing.assert_close(g_only, g_full)


def test_batch_broadcast_and_pose_shapes(toy_model):
    pose = 0.2 * torch.randn(4, 24, 3, dtype=torch.float64)
    out = toy_model(betas=torch.zeros(10, dtype=torch.float64), pose=pose)
    assert out.vertices.shape == (4, toy_model.num_vertices, 3)
    assert out.joints.shape == (4, 24, 3)
    single = toy_model(pose=pose[2].reshape(72))
    assert torch.allclose(single.vertices[0], out.vertices[2])


def test_bad_inputs_raise(toy_model):
    with pytest.raises(InputError):
        toy_model(pose=torch.zeros(2, 70, dtype=torch.float64))
    with pytest.raises(InputError):
        toy_model(betas=torch.zeros(2, 10, dtype=torch.float64), pose=torch.zeros(3, 72, dtype=torch.float64))
    with pytest.raises(InputError):
        toy_model(trans=torch.tensor([[0.0, float("nan"), 0.0]], dtype=torch.float64))
    with pytest.raises(InputError):
        load_body_model("default", gender="other")


def test_pkl_and_npz_give_identical_vertices(toy_files):
    m_pkl = load_body_model(toy_files["pkl"], dtype=torch.float64)
    m_npz = load_body_model(toy_files["npz"], dtype=torch.float64)
    torch.manual_seed(2)
    betas, pose = torch.randn(2, 10, dtype=torch.float64), 0.4 * torch.randn(2, 72, dtype=torch.float64)
    a = m_pkl(betas=betas, pose=pose).vertices
    b = m_npz(betas=betas, pose=pose).vertices
    assert torch.equal(a, b)
    assert m_pkl.kind == "smpl"


def test_pkl_holds_chumpy_and_sparse_and_loads_without_chumpy(toy_files):
    import sys

    raw = toy_files["pkl"].read_bytes()
    assert b"chumpy.ch" in raw and b"scipy.sparse.csc" in raw
    assert "chumpy" not in sys.modules
    arrays = read_model_arrays(toy_files["pkl"])
    assert "chumpy" not in sys.modules
    assert arrays.J_regressor.shape == (24, arrays.v_template.shape[0])


def test_folder_lookup(toy_files):
    m = load_body_model(toy_files["dir"], gender="neutral", dtype=torch.float64)
    assert m.num_vertices > 0
    with pytest.raises(ModelFileError, match="No male body model"):
        load_body_model(toy_files["dir"], gender="male")


def test_malicious_pickle_is_refused(tmp_path):
    class Evil:
        def __reduce__(self):
            import os

            return (os.system, ("echo pwned > " + str(tmp_path / "pwned"),))

    p = tmp_path / "evil.pkl"
    p.write_bytes(pickle.dumps({"v_template": Evil()}, protocol=2))
    with pytest.raises(ModelFileError, match="refusing"):
        load_body_model(p)
    assert not (tmp_path / "pwned").exists()


def test_object_array_in_npz_is_read_safely(tmp_path, toy_arrays):
    import scipy.sparse as sp

    arrays = dict(toy_arrays)
    arrays["J_regressor"] = np.array(sp.csc_matrix(toy_arrays["J_regressor"]), dtype=object)
    p = tmp_path / "model.npz"
    np.savez(p, **arrays)
    a = read_model_arrays(p)
    np.testing.assert_allclose(a.J_regressor, toy_arrays["J_regressor"])


def test_wrong_kind_and_missing_files(tmp_path):
    with pytest.raises(ModelFileError, match="does not exist"):
        load_body_model(tmp_path / "nope.pkl")
    p = tmp_path / "not_a_model.npz"
    np.savez(p, weights=np.zeros((3, 3)))
    with pytest.raises(ModelFileError, match="lacks v_template"):
        load_body_model(p)
    p = tmp_path / "garbage.pkl"
    p.write_bytes(b"this is not a pickle")
    with pytest.raises(ModelFileError):
        load_body_model(p)
    p = tmp_path / "model.obj"
    p.write_text("v 0 0 0\n")
    with pytest.raises(ModelFileError, match="expected a .pkl or .npz"):
        load_body_model(p)


def _expand_layout(arrays, n_joints, hand_left, hand_right, extra_head=()):
    """Embed the toy model in an SMPL-H/SMPL-X-sized joint layout."""
    V = arrays["v_template"].shape[0]
    w = np.zeros((V, n_joints))
    w[:, :22] = arrays["weights"][:, :22]
    w[:, hand_left[0]] = 0.5 * arrays["weights"][:, 22]
    w[:, hand_left[3]] = 0.5 * arrays["weights"][:, 22]
    w[:, hand_right[0]] = arrays["weights"][:, 23]
    jr = np.zeros((n_joints, V))
    jr[:22] = arrays["J_regressor"][:22]
    jr[hand_left[3]] = arrays["J_regressor"][22]
    jr[hand_right[3]] = arrays["J_regressor"][23]
    for j in extra_head:
        jr[j] = arrays["J_regressor"][15]
    pd = np.zeros((V, 3, 9 * (n_joints - 1)))
    pd[:, :, :189] = arrays["posedirs"][:, :, :189]
    return dict(arrays, weights=w, J_regressor=jr, posedirs=pd,
                shapedirs=np.concatenate([arrays["shapedirs"], np.zeros((V, 3, 6))], axis=2))


@pytest.mark.parametrize("layout", ["smplh", "smplx"])
def test_smplh_smplx_body_part(layout, tmp_path, toy_arrays):
    if layout == "smplh":
        big = _expand_layout(toy_arrays, 52, list(range(22, 37)), list(range(37, 52)))
    else:
        big = _expand_layout(toy_arrays, 55, list(range(25, 40)), list(range(40, 55)), extra_head=(22, 23, 24))
    p = tmp_path / f"{layout}.npz"
    np.savez(p, **big)
    m = load_body_model(p, dtype=torch.float64)
    assert m.kind == layout
    ref_arrays = dict(toy_arrays)
    ref_arrays["posedirs"] = np.concatenate(
        [toy_arrays["posedirs"][:, :, :189], np.zeros((toy_arrays["v_template"].shape[0], 3, 18))], axis=2)
    ref_p = tmp_path / "ref.npz"
    np.savez(ref_p, **ref_arrays)
    ref = load_body_model(ref_p, dtype=torch.float64)
    torch.manual_seed(3)
    betas, pose = torch.randn(1, 10, dtype=torch.float64), 0.3 * torch.randn(1, 72, dtype=torch.float64)
    assert torch.allclose(m(betas=betas, pose=pose).vertices, ref(betas=betas, pose=pose).vertices, atol=1e-12)


def test_capsules_follow_the_body(toy_model):
    torch.manual_seed(4)
    pose = 0.3 * torch.randn(1, 72, dtype=torch.float64)
    trans = torch.tensor([[0.1, 0.2, 2.0]], dtype=torch.float64)
    out = toy_model(pose=pose, trans=trans)
    caps = body_capsules(toy_model, out)
    K = len(caps.names)
    assert caps.start.shape == (1, K, 3) and caps.radius.shape == (1, K)
    assert (caps.radius > 0).all()
    # each capsule keeps its shape under posing: length and radius as in the rest pose
    rest = body_capsules(toy_model, toy_model())
    torch.testing.assert_close((caps.end - caps.start).norm(dim=-1), (rest.end - rest.start).norm(dim=-1))
    torch.testing.assert_close(caps.radius, rest.radius)
    # in the rest pose, the vertices a capsule covers lie near its surface
    from flowmocap.body.capsules import _vertex_sets

    d = point_capsule_distance(toy_model().vertices, rest)[0]
    for k, idx in enumerate(_vertex_sets(toy_model)):
        if idx.numel():
            assert d[idx, k].abs().median() < 0.03


def test_capsule_gradients(toy_model):
    torch.manual_seed(5)
    betas = (0.5 * torch.randn(1, 10, dtype=torch.float64)).requires_grad_()
    pose = (0.3 * torch.randn(1, 72, dtype=torch.float64)).requires_grad_()

    def f(b, p):
        caps = body_capsules(toy_model, toy_model(betas=b, pose=p))
        return caps.start, caps.end, caps.radius

    assert torch.autograd.gradcheck(f, (betas, pose), eps=1e-6, atol=1e-6)


def test_point_capsule_distance_closed_form():
    from flowmocap.body.capsules import Capsules

    caps = Capsules(start=torch.tensor([[[0.0, 0, 0]]]), end=torch.tensor([[[1.0, 0, 0]]]), radius=torch.tensor([[0.1]]))
    pts = torch.tensor([[[0.5, 0.3, 0.0], [-0.4, 0.0, 0.3], [1.0, 0.0, 0.05]]])
    d = point_capsule_distance(pts, caps)[0, :, 0]
    torch.testing.assert_close(d, torch.tensor([0.2, 0.4, -0.05]))


class _SparseWithoutIndices:
    """Pickles as a scipy csc_matrix whose stored state lacks ``indices`` (a damaged file)."""

    def __reduce__(self):
        import copyreg

        import scipy.sparse as sp

        return (copyreg._reconstructor, (sp.csc_matrix, object, None), {"data": np.zeros(2)})


@pytest.mark.parametrize("damage", ["posedirs_size", "scalar_regressor", "nan_template", "truncated_object_member",
                                    "sparse_without_indices"])
def test_damaged_model_files_are_refused_with_a_model_file_error(damage, tmp_path, toy_arrays):
    """Model files of the right kind but damaged: posedirs of the wrong size, a scalar
    J_regressor, NaN in v_template, a truncated object-array member in an .npz, a sparse
    matrix whose pickled state lacks a field. Each is refused with ModelFileError naming the
    file (before, each raised a bare numpy/zipfile/scipy error, or NaN was accepted and
    failed later with a message about the camera)."""
    import io
    import pickle
    import zipfile

    p = tmp_path / "model.npz"
    if damage == "posedirs_size":
        np.savez(p, **dict(toy_arrays, posedirs=np.zeros(7)))
        match = "posedirs has 7 values"
    elif damage == "scalar_regressor":
        np.savez(p, **dict(toy_arrays, J_regressor=np.float64(1.0)))
        match = "inconsistent array shapes"
    elif damage == "nan_template":
        np.savez(p, **dict(toy_arrays, v_template=np.full_like(toy_arrays["v_template"], np.nan)))
        match = "v_template holds NaN"
    elif damage == "truncated_object_member":
        buf = io.BytesIO()
        np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)
        with zipfile.ZipFile(p, "w") as z:
            for k, v in toy_arrays.items():
                b = io.BytesIO()
                np.save(b, v)
                z.writestr(k + ".npy", b.getvalue())
            z.writestr("gender.npy", buf.getvalue()[:-5])
        match = "not a readable .npz file"
    else:
        p = tmp_path / "model.pkl"
        p.write_bytes(pickle.dumps(dict(toy_arrays, J_regressor=_SparseWithoutIndices()), protocol=2))
        match = "sparse matrix 'J_regressor' cannot be rebuilt"
    with pytest.raises(ModelFileError, match=match) as err:
        load_body_model(p)
    assert str(p) in str(err.value)

"""The skinned glTF export (flowmocap.export.gltf_skin): read back, validated, small."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from flowmocap.body import JOINT_NAMES, PARENTS, load_body_model
from flowmocap.cli import main
from flowmocap.export import export_result, load_fitted_motion
from flowmocap.export.gltf_skin import glb_joint_positions, read_skinned_glb, skin_influences, write_skinned_glb
from flowmocap.geometry.camera import PinholeCamera, look_at

from test_export import T, make_result

ROOT = Path(__file__).resolve().parents[1]
VALIDATE = ROOT / "tools" / "js" / "validate_gltf.js"


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    d = tmp_path_factory.mktemp("gltf") / "result"
    R, t = look_at([2.5, 1.2, 3.5], [0.2, 0.9, 0.1])
    return d, make_result(d, PinholeCamera.from_focal(96, 72, 100.0, R=R, t=t), seed=4)


@pytest.fixture(scope="module")
def glb(result, tmp_path_factory):
    folder, _ = result
    return export_result(folder, "glb", tmp_path_factory.mktemp("glb") / "m.glb")


def test_joint_positions_from_the_file_match_the_fit_within_1mm(result, glb):
    folder, _ = result
    motion = load_fitted_motion(folder)  # the ground frame, as the export
    times, pos = glb_joint_positions(glb)
    np.testing.assert_allclose(times, np.arange(T) / 25.0, atol=1e-6)
    err = np.linalg.norm(pos - motion.joints(), axis=-1)
    assert err.max() < 1e-3, err.max()
    assert pos[:, 15, 1].min() > pos[:, 0, 1].max() - 0.5  # sanity: the head is up there


def test_rig_has_the_fitted_bone_lengths_and_one_skin(result, glb):
    folder, truth = result
    gltf, read = read_skinned_glb(glb)
    assert len(gltf.skins) == 1 and len(gltf.meshes) == 1 and len(gltf.animations) == 1
    skin = gltf.skins[0]
    assert [gltf.nodes[j].name for j in skin.joints] == list(JOINT_NAMES)
    model = load_body_model("default", gender=truth["gender"])
    with torch.no_grad():
        rest = model(betas=torch.as_tensor(truth["betas"])).rest_joints[0].double().numpy()
    for j in range(1, 24):
        node = gltf.nodes[skin.joints[j]]
        assert skin.joints[PARENTS[j]] in [i for i, n in enumerate(gltf.nodes) if skin.joints[j] in (n.children or [])]
        np.testing.assert_allclose(node.translation, rest[j] - rest[PARENTS[j]], atol=1e-6)
    ibm = read(skin.inverseBindMatrices)
    np.testing.assert_allclose(ibm[:, :3, 3], -rest, atol=1e-6)
    np.testing.assert_allclose(ibm[:, :3, :3], np.tile(np.eye(3), (24, 1, 1)))
    anim = gltf.animations[0]
    paths = sorted((c.target.node, c.target.path) for c in anim.channels)
    assert len(paths) == 25 and (skin.joints[0], "translation") in paths
    assert all(s.interpolation == "LINEAR" for s in anim.samplers)


def test_skinning_the_file_gives_the_fitted_mesh(result, glb):
    """Linear blend skinning with the file's own data (bind mesh, weights, inverse bind
    matrices, animated joints) against the fitted body; they differ only by SMPL's pose
    correctives and the weights beyond the 4th."""
    folder, _ = result
    motion = load_fitted_motion(folder)
    gltf, read = read_skinned_glb(glb)
    prim = gltf.meshes[0].primitives[0]
    bind = read(prim.attributes.POSITION).astype(np.float64)
    jidx = read(prim.attributes.JOINTS_0).astype(np.int64)
    w = read(prim.attributes.WEIGHTS_0).astype(np.float64)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-6)
    ibm = read(gltf.skins[0].inverseBindMatrices).astype(np.float64)
    anim = gltf.animations[0]
    k = 3
    local = {}
    for ch in anim.channels:
        local[(ch.target.node, ch.target.path)] = read(anim.samplers[ch.sampler].output)[k].astype(np.float64)
    parent = {c: i for i, n in enumerate(gltf.nodes) for c in (n.children or [])}
    glob = {}
    for i in gltf.skins[0].joints:  # parents come first (SMPL order)
        M = np.eye(4)
        M[:3, :3] = Rotation.from_quat(local[(i, "rotation")]).as_matrix()
        M[:3, 3] = local.get((i, "translation"), gltf.nodes[i].translation)
        glob[i] = glob[parent[i]] @ M if i in parent and parent[i] in glob else M
    G = np.stack([glob[i] for i in gltf.skins[0].joints]) @ ibm  # (24, 4, 4)
    hom = np.concatenate([bind, np.ones((len(bind), 1))], 1)
    skinned = np.einsum("vk,vkab,vb->va", w, G[jidx], hom)[:, :3]
    fitted = motion.body(k, k + 1)[0][0]
    err = np.linalg.norm(skinned - fitted, axis=1)
    assert np.median(err) < 0.005 and err.max() < 0.05, (np.median(err), err.max())


def test_skin_influences_keep_the_largest_weights():
    rng = np.random.default_rng(0)
    w = rng.random((50, 24)) ** 8
    w /= w.sum(1, keepdims=True)
    j, top = skin_influences(w)
    assert j.dtype == np.uint8 and top.dtype == np.float32
    np.testing.assert_allclose(top.sum(1), 1.0, atol=1e-7)
    for v in range(50):
        best = np.argsort(-w[v])[:4]
        np.testing.assert_array_equal(np.sort(j[v]), np.sort(best))
        np.testing.assert_allclose(top[v], w[v, j[v]] / w[v, best].sum(), rtol=1e-5)
    j1, t1 = skin_influences(np.eye(24)[np.arange(6) % 24])  # one influence: the rest are joint 0, weight 0
    assert (t1[:, 1:] == 0).all() and (j1[:, 1:] == 0).all()


def test_size_per_minute_of_30fps_video_is_under_5MB_plus_the_mesh(tmp_path):
    model = load_body_model("default")
    with torch.no_grad():
        out = model()
    args = dict(rest_vertices=out.rest_vertices[0].numpy(), rest_joints=out.rest_joints[0].numpy(),
                faces=model.faces_np, weights=model.weights.numpy(), fps=30.0)
    rng = np.random.default_rng(0)
    one = write_skinned_glb(tmp_path / "1.glb", rng.normal(0, 0.2, (1, 72)), np.zeros((1, 3)), **args)
    minute = write_skinned_glb(tmp_path / "60.glb", rng.normal(0, 0.2, (1800, 72)), np.zeros((1800, 3)), **args)
    mesh = one.stat().st_size
    motion_bytes = minute.stat().st_size - mesh
    assert motion_bytes < 5e6, motion_bytes
    assert mesh < 1.5e6, mesh


def test_validator_reports_no_errors_or_warnings(glb):
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed (apt-get install nodejs); the Khronos validator runs on node")
    if not (ROOT / "tools" / "js" / "node_modules" / "gltf-validator").is_dir():
        pytest.skip("the npm package gltf-validator is not installed: npm install --prefix tools/js")
    run = subprocess.run([node, str(VALIDATE), str(glb)], capture_output=True, text=True, timeout=120)
    assert run.returncode in (0, 1), run.stderr
    report = json.loads(run.stdout)
    assert report["numErrors"] == 0 and report["numWarnings"] == 0, report["messages"][:5]
    assert report["info"]["hasSkins"] and report["info"]["animationCount"] == 1
    assert report["info"]["maxInfluences"] == 4
    # and it does find errors: a file with a broken weight sum fails
    gltf, read = read_skinned_glb(glb)
    blob = bytearray(gltf.binary_blob())
    acc = gltf.accessors[gltf.meshes[0].primitives[0].attributes.WEIGHTS_0]
    start = gltf.bufferViews[acc.bufferView].byteOffset
    blob[start:start + 4] = np.float32(3.0).tobytes()
    gltf.set_binary_blob(bytes(blob))
    bad = glb.parent / "bad.glb"
    bad.write_bytes(b"".join(gltf.save_to_bytes()))
    run = subprocess.run([node, str(VALIDATE), str(bad)], capture_output=True, text=True, timeout=120)
    assert json.loads(run.stdout)["numErrors"] > 0


def test_trimesh_reads_one_skinned_mesh(glb):
    import trimesh

    scene = trimesh.load(glb)
    assert len(scene.geometry) == 1
    mesh = next(iter(scene.geometry.values()))
    assert mesh.vertices.shape == (load_body_model("default").num_vertices, 3)


def test_cli_exports_a_smoothed_glb_in_the_ground_frame(result, tmp_path, capsys):
    folder, _ = result
    out = tmp_path / "s.glb"
    assert main(["export", str(folder), "--format", "glb", "--out", str(out), "--smooth", "0.2", "--quiet"]) == 0
    assert "MB" in capsys.readouterr().out
    gltf, _ = read_skinned_glb(out)
    extras = gltf.scenes[0].extras
    assert extras["frame"] == "ground" and extras["smoothed"]["window_s"] == 0.2
    _, pos = glb_joint_positions(out)
    smoothed = load_fitted_motion(folder, smooth={"window_s": 0.2}).joints()
    assert np.abs(pos - smoothed).max() < 1e-3
    assert np.abs(pos - load_fitted_motion(folder).joints()).max() > 1e-3  # it did smooth
    assert main(["export", str(folder), "--format", "glb", "--smooth", "soon"]) == 2

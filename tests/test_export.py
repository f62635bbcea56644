"""flowmocap export: BVH, glb, OBJ, JSON and AMASS npz from a result folder.

Most tests here compare with the result's own joints, so they export in the ``"up"`` frame
(a pure rotation of the result's world); the ground frame (the default) is tested in
tests/test_ground.py, the skinned glb in tests/test_export_gltf.py.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from flowmocap.io.motion_source import load_motion

from flowmocap.body import JOINT_NAMES, PARENTS, load_body_model
from flowmocap.cli import main
from flowmocap.errors import DataError, InputError
from flowmocap.export import export_result, load_fitted_motion
from flowmocap.export.motion import CAMERA_TO_Y_UP
from flowmocap.geometry.camera import PinholeCamera, look_at
from flowmocap.io.results import write_motion, write_run

T = 5


def _walk_poses(rng) -> np.ndarray:
    """(T, 72) a moving, non-trivial pose sequence (every joint bent)."""
    base = rng.normal(0.0, 0.25, (1, 72))
    steps = rng.normal(0.0, 0.05, (T, 72)).cumsum(0)
    poses = base + steps
    poses[:, :3] = [0.2, 2.5, 0.1]  # root turned towards the camera side
    return poses


def make_result(folder: Path, camera: PinholeCamera, seed: int = 0, gender: str = "female") -> dict:
    """A result folder written directly (motion.npz as the tracker writes it)."""
    rng = np.random.default_rng(seed)
    poses = _walk_poses(rng).astype(np.float32)
    trans = (np.array([0.1, 0.0, 0.0]) + np.linspace(0, 0.3, T)[:, None] * [1.0, 0.0, 0.5]).astype(np.float32)
    if np.allclose(camera.R, np.eye(3)):  # stand upright in the y-down camera frame, 4 m away
        from scipy.spatial.transform import Rotation

        root = Rotation.from_rotvec([np.pi, 0, 0]) * Rotation.from_rotvec(poses[:, :3].astype(np.float64))
        poses[:, :3] = root.as_rotvec()
        trans = trans + np.float32([0.0, 0.0, 4.0])
    betas = rng.normal(0, 1, 10).astype(np.float32)
    model = load_body_model("default", gender=gender)
    with torch.no_grad():
        out = model(betas=torch.as_tensor(betas), pose=torch.as_tensor(poses), trans=torch.as_tensor(trans))
    j3 = out.joints.numpy()
    write_motion(folder, {
        "poses": poses, "trans": trans, "betas": betas, "gender": np.array(gender), "fps": np.array(25.0),
        "camera": np.array(json.dumps(camera.to_dict())), "joints3d": j3,
        "joints2d": camera.project(j3).astype(np.float32), "energies": rng.random((T, 2)),
        "energy_names": np.array(["total", "flow"]), "frame_index": np.arange(3, 3 + T),
    })
    write_run(folder, {"input": str(folder / "missing_input"), "model": "default", "gender": gender})
    return {"joints3d": j3.astype(np.float64), "poses": poses, "trans": trans, "betas": betas, "gender": gender}


@pytest.fixture(scope="module")
def posed_result(tmp_path_factory):
    """A result whose camera was placed in a y-up world (as synthetic sequences are)."""
    d = tmp_path_factory.mktemp("posed") / "result"
    R, t = look_at([2.5, 1.2, 3.5], [0.2, 0.9, 0.1])
    cam = PinholeCamera.from_focal(96, 72, 100.0, R=R, t=t)
    return d, make_result(d, cam, seed=1)


@pytest.fixture(scope="module")
def camera_frame_result(tmp_path_factory):
    """A result tracked with only a focal length: world = camera frame (y down)."""
    d = tmp_path_factory.mktemp("camframe") / "result"
    return d, make_result(d, PinholeCamera.from_focal(96, 72, 100.0), seed=2, gender="male")


def _fk_from_bvh_package(path: Path) -> tuple[list[str], np.ndarray]:
    """Joint positions of a BVH file parsed by the third-party ``bvh`` package, with forward
    kinematics written here (scipy rotations), independent of flowmocap's BVH code."""
    bvh = pytest.importorskip("bvh")
    from scipy.spatial.transform import Rotation

    mocap = bvh.Bvh(path.read_text())
    names = mocap.get_joints_names()
    pos = np.zeros((mocap.nframes, len(names), 3))
    glob = np.zeros((mocap.nframes, len(names), 3, 3))
    for j, name in enumerate(names):
        chans = mocap.joint_channels(name)
        vals = np.asarray(mocap.frames_joint_channels(name, chans), np.float64)  # (T, C)
        rot_ch = [c for c in chans if c.endswith("rotation")]
        order = "".join(c[0] for c in rot_ch)
        angles = vals[:, [chans.index(c) for c in rot_ch]]
        local = Rotation.from_euler(order.upper(), angles, degrees=True).as_matrix()  # intrinsic
        offset = np.asarray(mocap.joint_offset(name), np.float64)
        parent = mocap.joint_parent(name)
        if parent is None:
            p = offset + vals[:, [chans.index(c) for c in ("Xposition", "Yposition", "Zposition")]]
            glob[:, j] = local
        else:
            pj = names.index(parent.name)
            p = pos[:, pj] + np.einsum("tab,b->ta", glob[:, pj], offset)
            glob[:, j] = glob[:, pj] @ local
        pos[:, j] = p
    return names, pos


def test_bvh_joint_positions_reproduce_the_fit_within_1mm(posed_result, tmp_path):
    folder, truth = posed_result
    path = export_result(folder, "bvh", tmp_path / "m.bvh", frame="up")
    names, pos = _fk_from_bvh_package(path)
    assert set(JOINT_NAMES) <= set(names)
    idx = [names.index(n) for n in JOINT_NAMES]
    err = np.linalg.norm(pos[:, idx] - truth["joints3d"], axis=-1)
    assert pos.shape[0] == T
    assert err.max() < 1e-3, err.max()


def test_bvh_bones_have_the_fitted_shapes_lengths(posed_result, tmp_path):
    """The skeleton's offsets are the rest joints of the fitted betas, not the mean shape's."""
    from flowmocap.io.mocap import read_bvh

    folder, truth = posed_result
    clip = read_bvh(export_result(folder, "bvh", tmp_path / "m.bvh", frame="up"), scale=1.0)
    model = load_body_model("default", gender=truth["gender"])
    with torch.no_grad():
        rest_fit = model(betas=torch.as_tensor(truth["betas"])).rest_joints[0].numpy()
        rest_mean = model().rest_joints[0].numpy()
    lengths = lambda r: np.array([np.linalg.norm(r[j] - r[PARENTS[j]]) for j in range(1, 24)])  # noqa: E731
    got = np.array([np.linalg.norm(clip.offsets[clip.index(n)]) for n in JOINT_NAMES[1:]])
    np.testing.assert_allclose(got, lengths(rest_fit), atol=1e-6)
    assert np.abs(got - lengths(rest_mean)).max() > 5e-3  # the shape matters, so the test can fail


def test_bvh_in_centimetres_and_read_by_our_reader(posed_result, tmp_path):
    from flowmocap.io.mocap import read_bvh

    folder, truth = posed_result
    assert main([
        "export", str(folder), "--format", "bvh", "--out", str(tmp_path / "cm.bvh"), "--bvh-unit", "cm", "--quiet", "--frame", "up",
    ]) == 0
    clip = read_bvh(tmp_path / "cm.bvh")  # the unit is guessed from the skeleton's height
    assert clip.info["unit"] == "cm"
    assert clip.fps == pytest.approx(25.0)
    idx = [clip.index(n) for n in JOINT_NAMES]
    assert np.abs(clip.positions[:, idx] - truth["joints3d"]).max() < 1e-3


def test_camera_frame_results_are_turned_upright(camera_frame_result, tmp_path):
    folder, truth = camera_frame_result
    up = load_fitted_motion(folder, frame="up")
    np.testing.assert_allclose(up.rotation, CAMERA_TO_Y_UP)
    expect = truth["joints3d"] @ CAMERA_TO_Y_UP.T
    np.testing.assert_allclose(up.joints(), expect, atol=1e-5)
    # head above the pelvis in the export (it was below in the y-down camera frame)
    assert (up.joints()[:, 15, 1] > up.joints()[:, 0, 1]).all()
    names, pos = _fk_from_bvh_package(export_result(folder, "bvh", tmp_path / "up.bvh", frame="up"))
    idx = [names.index(n) for n in JOINT_NAMES]
    assert np.abs(pos[:, idx] - expect).max() < 1e-3
    world = load_fitted_motion(folder, frame="world")
    np.testing.assert_allclose(world.joints(), truth["joints3d"], atol=1e-5)


def test_glb_frames_loads_with_trimesh_with_one_mesh_per_frame(posed_result, tmp_path):
    import trimesh

    folder, truth = posed_result
    path = export_result(folder, "glb-frames", tmp_path / "m.glb", frame="up")
    scene = trimesh.load(path)
    assert len(scene.geometry) == T
    model = load_body_model("default")
    for k in (0, T - 1):
        mesh = scene.geometry[f"frame_{k:06d}"]
        assert mesh.vertices.shape == (model.num_vertices, 3)
        assert len(mesh.faces) == model.faces.shape[0]
    # the animation switches frames on one after the other at the motion's rate
    raw = path.read_bytes()
    n = int.from_bytes(raw[12:16], "little")
    doc = json.loads(raw[20:20 + n])
    anim = doc["animations"][0]
    assert len(anim["channels"]) == T
    assert {c["target"]["path"] for c in anim["channels"]} == {"scale"}
    last = doc["accessors"][anim["samplers"][-1]["input"]]
    assert last["max"][0] == pytest.approx((T - 1) / 25.0)


def test_glb_frames_vertices_are_the_fitted_body(posed_result, tmp_path):
    import trimesh

    folder, truth = posed_result
    scene = trimesh.load(export_result(folder, "glb-frames", tmp_path / "m.glb", frame="up"))
    mesh = scene.geometry["frame_000002"]
    model = load_body_model("default", gender=truth["gender"])
    with torch.no_grad():
        v = model(betas=torch.as_tensor(truth["betas"]), pose=torch.as_tensor(truth["poses"][2]),
                  trans=torch.as_tensor(truth["trans"][2])).vertices[0].numpy()
    np.testing.assert_allclose(mesh.vertices, v, atol=1e-5)


def test_amass_npz_round_trips_through_our_loader(posed_result, camera_frame_result, tmp_path):
    from flowmocap.io.amass import read_amass_npz

    for k, (folder, truth) in enumerate((posed_result, camera_frame_result)):
        path = export_result(folder, "npz", tmp_path / f"amass{k}.npz", frame="up")
        with np.load(path) as z:
            assert z["poses"].shape == (T, 156)
            assert z["trans"].shape == (T, 3)
            assert float(z["mocap_framerate"]) == 25.0
            assert str(z["gender"]) == truth["gender"]
            np.testing.assert_allclose(z["betas"], truth["betas"], atol=1e-6)
        motion = read_amass_npz(path)
        via_loader = load_motion(path, load_body_model("default", gender=truth["gender"]))
        np.testing.assert_allclose(via_loader.poses, motion.poses, atol=0)
        assert motion.fps == 25.0 and motion.gender == truth["gender"] and motion.num_frames == T
        model = load_body_model("default", gender=motion.gender)
        with torch.no_grad():
            j = model(betas=torch.as_tensor(motion.betas), pose=torch.as_tensor(motion.poses),
                      trans=torch.as_tensor(motion.trans)).joints.numpy()
        expect = load_fitted_motion(folder, frame="up").joints()  # y up
        assert np.abs(j - expect).max() < 1e-4
        np.testing.assert_allclose(motion.poses[:, 3:], truth["poses"][:, 3:], atol=1e-5)


def test_amass_npz_is_z_up(posed_result, tmp_path):
    """AMASS worlds are z up: the head is above the pelvis along z in the file."""
    folder, truth = posed_result
    path = export_result(folder, "npz", tmp_path / "a.npz")
    with np.load(path) as z:
        poses, trans, betas = z["poses"], z["trans"], z["betas"]
    model = load_body_model("default", gender=truth["gender"])
    pose72 = np.concatenate([poses[:, :66], np.zeros((T, 6))], axis=1)
    with torch.no_grad():
        j = model(betas=torch.as_tensor(betas, dtype=torch.float32), pose=torch.as_tensor(pose72, dtype=torch.float32),
                  trans=torch.as_tensor(trans, dtype=torch.float32)).joints.numpy()
    assert (j[:, 15, 2] - j[:, 0, 2] > 0.3).all()


def test_obj_and_json(posed_result, tmp_path):
    folder, truth = posed_result
    obj_dir = export_result(folder, "obj", tmp_path / "obj")
    files = sorted(obj_dir.glob("*.obj"))
    assert [f.name for f in files] == [f"frame_{i:06d}.obj" for i in range(3, 3 + T)]
    text = files[1].read_text().splitlines()
    verts = np.array([[float(x) for x in ln.split()[1:]] for ln in text if ln.startswith("v ")])
    faces = np.array([[int(x) for x in ln.split()[1:]] for ln in text if ln.startswith("f ")])
    model = load_body_model("default", gender=truth["gender"])
    assert verts.shape == (model.num_vertices, 3) and faces.min() == 1
    np.testing.assert_array_equal(faces - 1, model.faces_np)
    doc = json.loads(export_result(folder, "json", tmp_path / "m.json", frame="up").read_text())
    assert doc["joint_names"] == list(JOINT_NAMES) and len(doc["frames"]) == T
    assert doc["frames"][0]["index"] == 3
    np.testing.assert_allclose(np.array(doc["frames"][4]["joints3d"]), truth["joints3d"][4], atol=1e-5)
    assert np.array(doc["frames"][4]["pose"]).shape == (72,)
    # the body's standing height: its mesh from sole to crown in the rest pose
    with torch.no_grad():
        rest = model(betas=torch.as_tensor(truth["betas"], dtype=torch.float32)[None]).vertices[0].numpy()
    assert doc["stature_m"] == pytest.approx(np.ptp(rest[:, 1]), abs=0.01)


def test_joints_without_the_mesh_are_the_posed_meshs_and_the_json_has_a_line_per_frame(posed_result, tmp_path):
    """A 10-minute result's joints are posed without the mesh, the shape made once (25 s and
    3 GB with the mesh), and its JSON is written frame by frame; neither changes the values."""
    folder, truth = posed_result
    m = load_fitted_motion(folder, frame="up")
    with_mesh = np.concatenate([m.body(s, s + 3)[1] for s in range(0, m.num_frames, 3)])
    np.testing.assert_allclose(m.joints(), with_mesh, rtol=0, atol=1e-12)
    np.testing.assert_allclose(m.joints(chunk=2), with_mesh, rtol=0, atol=1e-12)
    path = export_result(folder, "json", tmp_path / "m.json", frame="up")
    lines = path.read_text().splitlines()
    frames = [ln for ln in lines if ln.startswith('  {"index":')]
    assert len(frames) == T and json.loads(frames[-1].rstrip(","))["index"] == 3 + T - 1
    assert not path.with_name("m.json.part").exists()


def test_the_floor_does_not_depend_on_how_many_frames_are_posed_at_a_time(posed_result):
    """The floor's passes pose the mesh a chunk at a time (a long motion's foot vertices are
    never all held): the chunk changes nothing."""
    from flowmocap.export.world import world_frame

    folder, truth = posed_result
    m = load_fitted_motion(folder, frame="world")
    args = (m.poses, m.trans, m.betas, m.model, m.camera, m.fps)
    a, b = world_frame(*args), world_frame(*args, chunk=2)
    np.testing.assert_array_equal(a.contacts, b.contacts)
    np.testing.assert_allclose(a.rotation, b.rotation, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.offset, b.offset, rtol=0, atol=1e-12)


def test_json_carries_the_sources_disagreement_where_the_result_has_it(posed_result, tmp_path):
    import shutil

    from flowmocap.body.skeleton import EVAL_JOINTS
    from flowmocap.io.results import read_result

    folder, _ = posed_result
    doc = json.loads(export_result(folder, "json", tmp_path / "plain.json", frame="up").read_text())
    assert "disagreement" not in doc["frames"][0]  # a result without the lifter refit has none
    copy = tmp_path / "result"
    shutil.copytree(folder, copy)
    motion, _ = read_result(copy)
    dis = np.full((T, 24), np.nan, np.float32)
    dis[:, list(EVAL_JOINTS)] = np.linspace(0.01, 0.3, T * 13).reshape(T, 13)
    write_motion(copy, {**motion, "disagreement": dis})
    doc = json.loads(export_result(copy, "json", tmp_path / "m.json", frame="up").read_text())
    got = doc["frames"][2]["disagreement"]
    assert len(got) == 24 and all(got[j] is None for j in range(24) if j not in EVAL_JOINTS)
    np.testing.assert_allclose([got[j] for j in EVAL_JOINTS], dis[2, list(EVAL_JOINTS)], atol=1e-4)


def test_export_errors_tell_what_to_do(posed_result, tmp_path, capsys):
    folder, _ = posed_result
    with pytest.raises(InputError, match="choose one of"):
        export_result(folder, "fbx")
    with pytest.raises(DataError, match="does not exist"):
        export_result(tmp_path / "nothing", "bvh")
    assert main(["export", str(tmp_path / "nothing"), "--format", "bvh"]) == 2
    assert "flowmocap track" in capsys.readouterr().err
    assert main(["export", str(folder), "--format", "fbx"]) == 2
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="not a flowmocap result"):
        export_result(tmp_path / "empty", "json")


def _damaged_copy(folder: Path, dest: Path, **changes) -> Path:
    """A copy of the result ``folder`` whose motion.npz has ``changes`` (key -> array)."""
    import shutil

    from flowmocap.io.results import read_result

    shutil.copytree(folder, dest)
    motion, _ = read_result(dest)
    write_motion(dest, {**motion, **changes})
    return dest


@pytest.mark.parametrize("key, value, says", [
    ("poses", np.zeros((T, 10)), r"'poses' is \(5, 10\), expected \(T, 72\)"),
    ("poses", np.zeros(T * 72), r"'poses' is \(360,\), expected \(T, 72\)"),
    ("trans", np.zeros((T, 2)), r"'trans' is \(5, 2\), expected \(5, 3\)"),
    ("trans", np.zeros((T - 1, 3)), r"'trans' is \(4, 3\), expected \(5, 3\)"),
    ("betas", np.zeros(0), r"'betas' is empty"),
    ("betas", np.array(["a", "b"]), r"'betas' is not numeric"),
    ("frame_index", np.arange(T + 2), r"'frame_index' is \(7,\), expected \(5,\)"),
    ("camera", np.array("garbage"), r"'camera' is not the camera's JSON"),
])
def test_a_motion_npz_with_wrong_arrays_names_the_file_and_says_to_track_again(posed_result, tmp_path, key, value,
                                                                                says):
    """Arrays of the wrong shape (poses not (T, 72), trans not (T, 3) for the same T, no
    betas, frame_index of another length) or a camera that is not JSON are a DataError
    that names motion.npz, says what is wrong and to track again with --force."""
    folder, _ = posed_result
    copy = _damaged_copy(folder, tmp_path / "result", **{key: value})
    with pytest.raises(DataError, match=says + r".*--force") as e:
        load_fitted_motion(copy, frame="up")
    assert str(copy / "motion.npz") in str(e.value)


@pytest.mark.parametrize("key", ["poses", "trans"])
def test_nan_in_the_motion_is_a_data_error_that_names_the_file(posed_result, tmp_path, key):
    """NaN poses or translations are reported as a damaged motion.npz (file, array, row),
    not as a bare "pose contains NaN" from deep inside the body model."""
    folder, truth = posed_result
    bad = np.array(truth[key], np.float32)
    bad[2, 1] = np.nan
    copy = _damaged_copy(folder, tmp_path / "result", **{key: bad})
    says = rf"motion\.npz '{key}' holds NaN or infinite values \(first at row 2\).*--force"
    with pytest.raises(DataError, match=says):
        load_fitted_motion(copy)


def test_a_world_json_that_is_not_an_object_is_computed_again(posed_result, tmp_path):
    """A world.json cache holding a JSON list (or other non-object) is treated like any
    unreadable cache: the ground frame is computed again and the cache rewritten."""
    import shutil

    folder, _ = posed_result
    copy = tmp_path / "result"
    shutil.copytree(folder, copy)
    want = load_fitted_motion(copy)  # the ground frame, and its cache
    (copy / "world.json").write_text("[1, 2]")
    got = load_fitted_motion(copy)
    np.testing.assert_allclose(got.rotation, want.rotation, atol=1e-12)
    np.testing.assert_allclose(got.offset, want.offset, atol=1e-12)
    assert isinstance(json.loads((copy / "world.json").read_text()), dict)


@pytest.mark.parametrize("fmt, name", [("bvh", "m.bvh"), ("npz", "m.npz"), ("glb", "m.glb"), ("trc", "m.trc"), ("c3d", "m.c3d"),
                                       ("glb-frames", "f.glb"), ("obj", "obj")])
def test_an_interrupted_export_leaves_the_old_file_and_no_partial_one(posed_result, tmp_path, monkeypatch, fmt,
                                                                      name):
    """Every export is written through a temporary file renamed into place: interrupted
    (Ctrl-C) just before the rename, the old file under the final name is untouched and no
    temporary file is left behind (for obj, each frame's file)."""
    import os

    folder, _ = posed_result
    out = tmp_path / name
    old = (out / "frame_000003.obj") if fmt == "obj" else out
    old.parent.mkdir(parents=True, exist_ok=True)
    old.write_text("old")

    def interrupted(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        export_result(folder, fmt, out, frame="up")
    monkeypatch.undo()
    assert old.read_text() == "old"
    assert sorted(p.name for p in old.parent.iterdir()) == [old.name]


def test_names_of_the_wrong_kind_are_refused_before_the_work(posed_result, tmp_path, capsys):
    """export -f glb --out x.bvh wrote a glb under a BVH's name; an obj export into an
    existing file failed as a full disk would (exit 5, 'File exists'), and into a folder of an
    earlier export left its frames beside the new ones (a mix of two motions)."""
    from flowmocap.cli import main

    folder, _ = posed_result
    with pytest.raises(InputError, match=r"a glb export is a \.glb file; give a name ending in \.glb \(e\.g\. x\.glb\)"):
        export_result(folder, "glb", tmp_path / "x.bvh")
    assert not (tmp_path / "x.bvh").exists()
    export_result(folder, "bvh", tmp_path / "UPPER.BVH")  # the ending's case does not matter
    (tmp_path / "afile").write_text("mine")
    assert main(["export", str(folder), "-f", "obj", "--out", str(tmp_path / "afile"), "--quiet"]) == 2
    assert "is a file; the obj export writes a folder" in capsys.readouterr().err
    objs = tmp_path / "objs"
    objs.mkdir()
    (objs / "frame_999999.obj").write_text("an earlier export's frame")
    (objs / "notes.txt").write_text("mine")
    written = export_result(folder, "obj", objs)
    names = sorted(p.name for p in objs.iterdir())
    assert "frame_999999.obj" not in names and "notes.txt" in names
    assert len(names) == len(list(written.glob("frame_*.obj"))) + 1
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    # options that were ignored without a word
    capsys.readouterr()
    assert main(["export", str(folder), "-f", "json", "--out", str(tmp_path / "m.json"), "--bvh-unit", "cm"]) == 2
    assert "--bvh-unit sets the BVH's length unit" in capsys.readouterr().err
    assert main(["export", str(folder), "-f", "json", "--out", str(tmp_path / "m.json"), "--smooth-order", "3"]) == 2
    assert "give --smooth too" in capsys.readouterr().err
    assert main(["export", str(folder), "-f", "bvh", "--out", str(tmp_path / "m.bvh"), "--bvh-unit", "cm",
                 "--smooth", "0.2", "--smooth-order", "3", "--quiet"]) == 0


def test_an_obj_folder_gets_a_folders_usual_mode(posed_result, tmp_path):
    # it was 0700 (tempfile.mkdtemp's), so other users and services could not read the meshes
    import os

    folder, _ = posed_result
    umask = os.umask(0o022)
    try:
        assert (export_result(folder, "obj", tmp_path / "obj").stat().st_mode & 0o777) == 0o755
        (tmp_path / "obj").chmod(0o750)  # a mode the user chose is kept over a new export
        assert (export_result(folder, "obj", tmp_path / "obj").stat().st_mode & 0o777) == 0o750
    finally:
        os.umask(umask)


def test_an_obj_export_stopped_while_it_moves_in_leaves_the_earlier_one_whole(posed_result, tmp_path, monkeypatch):
    """The new frames were moved in one by one after the old ones were deleted: a stop there
    left 4 new frames and lost the rest of both exports. Now the folders trade places."""
    import os

    folder, _ = posed_result
    objs = tmp_path / "obj"
    first = sorted(p.name for p in export_result(folder, "obj", objs).iterdir())
    before = {p.name: p.read_bytes() for p in objs.iterdir()}
    real, calls = os.rename, []

    def stopped(src, dst):
        calls.append(dst)
        if Path(dst) == objs and calls.count(dst) == 1:  # the new export is about to take the name
            raise KeyboardInterrupt
        return real(src, dst)

    monkeypatch.setattr(os, "rename", stopped)
    with pytest.raises(KeyboardInterrupt):
        export_result(folder, "obj", objs, smooth=True)
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in objs.iterdir()} == before and sorted(before) == first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["obj"]  # no staging or old folder left
    again = export_result(folder, "obj", objs, smooth=True)
    assert sorted(p.name for p in again.iterdir()) == first and {p.name: p.read_bytes() for p in objs.iterdir()} != before


def test_an_export_made_now_equals_one_made_later_from_the_cached_world_frame(posed_result, tmp_path):
    """The first export used the world frame at full precision, later ones world.json's 9
    decimals: BVHs of the same result differed by up to 1.2e-8."""
    import shutil

    folder, _ = posed_result
    copy = tmp_path / "r"
    shutil.copytree(folder, copy)
    (copy / "world.json").unlink(missing_ok=True)
    first = export_result(copy, "bvh", tmp_path / "a.bvh").read_bytes()
    assert (copy / "world.json").exists()
    assert export_result(copy, "bvh", tmp_path / "b.bvh").read_bytes() == first


@pytest.mark.parametrize("unit, per_metre", [("m", 1.0), ("cm", 100.0)])
def test_flowmocaps_own_bvh_of_a_small_body_is_read_back_in_its_unit(posed_result, tmp_path, unit, per_metre):
    # a body under about 1.2 m (track --height takes 0.5-2.5) could not be read back, and in centimetres one of
    # about 0.55 m was taken as inches, 2.54x too large
    from flowmocap.io.mocap import read_bvh

    folder, _ = posed_result
    path = export_result(folder, "bvh", tmp_path / "m.bvh", frame="up", units_per_metre=per_metre)
    full = read_bvh(path)
    lines, motion, out = path.read_text().splitlines(), False, []
    for ln in lines:  # the same file for a body 0.3 times the size
        if ln.strip().startswith("OFFSET"):
            head, *nums = ln.split()
            ln = ln[:ln.index("OFFSET")] + " ".join([head] + [repr(float(v) * 0.3) for v in nums])
        elif motion and ln and not ln.startswith("Frame"):
            vals = ln.split()
            ln = " ".join([repr(float(v) * 0.3) for v in vals[:3]] + vals[3:])
        motion = motion or ln.startswith("MOTION")
        out.append(ln)
    small = tmp_path / "small.bvh"
    small.write_text("\n".join(out) + "\n")
    clip = read_bvh(small)
    assert clip.info["unit"] == unit
    np.testing.assert_allclose(clip.positions, 0.3 * full.positions, atol=1e-5)

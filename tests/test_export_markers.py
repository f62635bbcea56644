"""flowmocap export --format trc / c3d: the fitted joints as marker trajectories, read back
with independent third-party readers (``trc-data-reader`` for TRC, the pure-Python ``c3d``
package for C3D; ours writes C3D with ``ezc3d``)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from flowmocap.body import JOINT_NAMES
from flowmocap.cli import main
from flowmocap.errors import InputError
from flowmocap.export import export_result, load_fitted_motion
from flowmocap.export.markers import write_c3d, write_trc
from flowmocap.io.amass import Y_UP_TO_Z_UP

from test_export import T, camera_frame_result, posed_result  # noqa: F401  (fixtures)


def _read_trc(path):
    trc = pytest.importorskip("trc", reason="trc-data-reader is a test dependency ([test] extra)")
    doc = trc.TRCData()
    doc.load(str(path))
    return doc


def _read_c3d(path):
    c3d = pytest.importorskip("c3d", reason="the c3d package is a test dependency (via trc-data-reader)")
    with open(path, "rb") as f, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no analog data": we write none
        r = c3d.Reader(f)
        frames = [(i, pts.copy()) for i, pts, _ in r.read_frames()]
        events = []
        if r.get("EVENT:USED") is not None:
            events = list(zip([s.strip() for s in r.get("EVENT:CONTEXTS").string_array],
                              [s.strip() for s in r.get("EVENT:LABELS").string_array],
                              r.get("EVENT:TIMES").float_array[:, 1]))
        return {"first": r.header.first_frame, "rate": r.point_rate, "labels": [s.strip() for s in r.point_labels],
                "units": r.get("POINT:UNITS").string_value.strip(), "frames": frames,
                "events": events}  # (side, label, seconds)


def test_trc_holds_the_joints_in_metres_with_the_header_opensim_reads(posed_result, tmp_path):
    folder, truth = posed_result
    path = export_result(folder, "trc", tmp_path / "m.trc", frame="up")
    doc = _read_trc(path)
    assert doc["Markers"] == list(JOINT_NAMES)
    assert (doc["NumFrames"], doc["NumMarkers"], doc["Units"]) == (T, 24, "m")
    assert doc["DataRate"] == doc["CameraRate"] == 25.0
    assert doc["OrigDataStartFrame"] == 4  # the result starts at the input's frame 3 (0-based)
    assert doc["Frame#"] == list(range(1, T + 1))
    np.testing.assert_allclose(doc["Time"], np.arange(T) / 25.0, atol=1e-6)
    got = np.stack([np.asarray(doc[name], np.float64) for name in JOINT_NAMES], axis=1)  # (T, 24, 3)
    np.testing.assert_allclose(got, truth["joints3d"], atol=2e-6)  # 6 decimals, and float32 poses


def test_c3d_holds_the_joints_z_up_in_millimetres(posed_result, tmp_path):
    folder, truth = posed_result
    path = export_result(folder, "c3d", tmp_path / "m.c3d", frame="up")
    doc = _read_c3d(path)
    assert doc["labels"] == list(JOINT_NAMES)
    assert (doc["units"], doc["rate"], doc["first"]) == ("mm", 25.0, 4)
    assert [i for i, _ in doc["frames"]] == list(range(4, 4 + T))
    got = np.stack([pts[:, :3] for _, pts in doc["frames"]]) / 1000.0
    np.testing.assert_allclose(got, truth["joints3d"] @ Y_UP_TO_Z_UP.T, atol=1e-6)  # float32 mm
    assert all(np.all(pts[:, 3] >= 0) for _, pts in doc["frames"])  # every marker valid (residual >= 0)
    # z is up: the head is above the pelvis in every frame
    head, pelvis = JOINT_NAMES.index("head"), JOINT_NAMES.index("pelvis")
    assert np.all(got[:, head, 2] > got[:, pelvis, 2] + 0.3)


def test_the_ground_frame_is_the_default_and_world_is_written_as_it_is(camera_frame_result, tmp_path):
    folder, _ = camera_frame_result
    ground = load_fitted_motion(folder).joints()
    doc = _read_trc(export_result(folder, "trc", tmp_path / "g.trc"))
    got = np.stack([np.asarray(doc[name]) for name in JOINT_NAMES], axis=1)
    np.testing.assert_allclose(got, ground, atol=2e-6)
    world = load_fitted_motion(folder, frame="world").joints()
    doc = _read_c3d(export_result(folder, "c3d", tmp_path / "w.c3d", frame="world"))
    np.testing.assert_allclose(np.stack([p[:, :3] for _, p in doc["frames"]]) / 1000.0, world, atol=1e-5)


def test_the_command_line_writes_both_to_the_result_folder(posed_result, capsys):
    folder, _ = posed_result
    for fmt in ("trc", "c3d"):
        assert main(["export", str(folder), "--format", fmt, "--quiet"]) == 0
        assert (folder / "export" / f"motion.{fmt}").is_file()
        assert f"motion.{fmt} ({fmt}: marker trajectories (--markers)" in capsys.readouterr().out


def test_bad_trajectories_are_refused(tmp_path):
    good = np.zeros((2, 2, 3))
    with pytest.raises(InputError, match="one per name"):
        write_trc(tmp_path / "a.trc", good, ["a"], 30.0)
    with pytest.raises(InputError, match="NaN"):
        write_c3d(tmp_path / "a.c3d", np.full((2, 2, 3), np.nan), ["a", "b"], 30.0)
    with pytest.raises(InputError, match="frame rate"):
        write_trc(tmp_path / "a.trc", good, ["a", "b"], 0.0)
    with pytest.raises(InputError, match="white space"):
        write_trc(tmp_path / "a.trc", good, ["a", "left hip"], 30.0)
    with pytest.raises(InputError, match="up must be"):
        write_c3d(tmp_path / "a.c3d", good, ["a", "b"], 30.0, up="x")
    # C3D's header counts frames in 16 bits; ezc3d would cut a longer motion there unsaid
    end = _read_c3d(write_c3d(tmp_path / "end.c3d", np.zeros((3, 1, 3)), ["a"], 60.0, first_frame=65532))
    assert [i for i, _ in end["frames"]] == [65533, 65534, 65535]  # the last frame a header can number
    (tmp_path / "end.c3d").unlink()
    with pytest.raises(InputError, match="16 bits, up to 65535, and this motion runs to frame 65536"):
        write_c3d(tmp_path / "long.c3d", np.zeros((4, 1, 3)), ["a"], 60.0, first_frame=65532)
    assert not list(tmp_path.iterdir())


def test_a_trc_may_hold_missing_markers_as_nan_when_asked(tmp_path):
    pts = np.arange(4 * 2 * 3, dtype=np.float64).reshape(4, 2, 3) / 10.0
    pts[1, 0] = np.nan  # marker a missing in frame 1
    with pytest.raises(InputError, match="NaN"):
        write_trc(tmp_path / "m.trc", pts, ["a", "b"], 30.0)
    doc = _read_trc(write_trc(tmp_path / "m.trc", pts, ["a", "b"], 30.0, missing_ok=True))
    got = np.stack([np.asarray(doc[n], np.float64) for n in ("a", "b")], axis=1)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(pts))
    np.testing.assert_allclose(got[~np.isnan(pts)], pts[~np.isnan(pts)], atol=1e-6)
    pts[2, 1, 0] = np.inf
    with pytest.raises(InputError, match="infinite"):
        write_trc(tmp_path / "inf.trc", pts, ["a", "b"], 30.0, missing_ok=True)
    assert not (tmp_path / "inf.trc").exists()


def test_contact_events_are_the_contacts_changes():
    from flowmocap.export.markers import contact_events

    c = np.array([[1, 0], [1, 0], [0, 1], [0, 1], [1, 1], [1, 0]], bool)
    assert contact_events(c) == [(2, "Left", "Foot Off"), (2, "Right", "Foot Strike"),
                                 (4, "Left", "Foot Strike"), (5, "Right", "Foot Off")]
    assert contact_events(np.ones((4, 2), bool)) == []  # standing still: the start is no event


def test_the_ground_frames_c3d_carries_the_foot_contacts_as_gait_events(camera_frame_result, tmp_path):
    from flowmocap.export.markers import contact_events

    folder, _ = camera_frame_result
    motion = load_fitted_motion(folder)
    contacts = motion.world.contacts.copy()
    contacts[2:4, 0] = ~contacts[2:4, 0]  # make sure there are changes to see
    path = write_c3d(tmp_path / "g.c3d", motion.joints(), JOINT_NAMES, motion.fps,
                     first_frame=int(motion.frame_index[0]), contacts=contacts)
    want = contact_events(contacts)
    assert want
    events = _read_c3d(path)["events"]
    assert [(side, label) for side, label, _ in events] == [(side, label) for _, side, label in want]
    np.testing.assert_allclose([t for _, _, t in events], [(3 + k) / 25.0 for k, _, _ in want], atol=1e-6)
    # and the export command writes the result's own contacts
    doc = export_result(folder, "c3d", tmp_path / "e.c3d")
    assert len(_read_c3d(doc)["events"]) == len(contact_events(motion.world.contacts))
    with pytest.raises(InputError, match="contacts must be"):
        write_c3d(tmp_path / "x.c3d", motion.joints(), JOINT_NAMES, motion.fps, contacts=contacts[:2])


def _with_run(src, dst, **fields):
    """A copy of the result folder ``src`` whose run.json holds ``fields`` too."""
    import json
    import shutil

    shutil.copytree(src, dst)
    run = json.loads((dst / "run.json").read_text())
    (dst / "run.json").write_text(json.dumps({**run, **fields}))
    return dst


def test_frames_without_the_person_and_a_variable_rate_are_said_in_the_exports(posed_result, tmp_path, capsys):
    # every format gave the frames without the person as measured data (C3D gait events came from them), json time_s
    # counted from the first exported frame, and a variable-rate video's own times were not used anywhere
    import json

    folder, _ = posed_result  # frames 3..7 of the input at 25 fps
    stamps = [0.0, 0.04, 0.08, 0.12, 0.2, 0.28, 0.36, 0.40]  # frames 4-6 shown 80 ms apart
    vfr = _with_run(folder, tmp_path / "vfr", gaps=[{"frames": [5, 6], "why": "no person found"}],
                    video={"fps": 20.0, "variable_frame_rate": True, "timestamps": stamps})
    doc = json.loads(export_result(vfr, "json", tmp_path / "m.json", frame="up").read_text())
    assert [f["time_s"] for f in doc["frames"]] == stamps[3:8]
    assert [f["seen"] for f in doc["frames"]] == [True, True, False, False, True]
    plain = json.loads(export_result(folder, "json", tmp_path / "p.json", frame="up").read_text())
    assert [f["time_s"] for f in plain["frames"]] == [round(i / 25.0, 6) for i in range(3, 8)]  # the input's time
    assert all(f["seen"] for f in plain["frames"])
    # glb: keys at the video's own times from the first exported frame; the unseen frames named
    pygltflib = pytest.importorskip("pygltflib")
    glb = pygltflib.GLTF2().load(str(export_result(vfr, "glb", tmp_path / "m.glb", frame="up")))
    acc = glb.accessors[glb.animations[0].samplers[0].input]
    view = glb.bufferViews[acc.bufferView]
    keys = np.frombuffer(glb.binary_blob(), np.float32, acc.count, view.byteOffset + (acc.byteOffset or 0))
    np.testing.assert_allclose(keys, np.array(stamps[3:8]) - stamps[3], atol=1e-6)
    assert glb.scenes[0].extras["unseen_frames"] == [5, 6]
    # c3d: the unseen frames are gaps (invalid points), the file says its axes
    doc = _read_c3d(export_result(vfr, "c3d", tmp_path / "m.c3d", frame="up"))
    valid = [bool(np.all(pts[:, 3] >= 0)) for _, pts in doc["frames"]]
    assert valid == [True, True, False, False, True]
    import ezc3d

    params = ezc3d.c3d(str(tmp_path / "m.c3d"))["parameters"]["POINT"]
    assert (params["X_SCREEN"]["value"], params["Y_SCREEN"]["value"]) == (["+X"], ["+Z"])
    # the command says what a one-rate format does with the video's times; json keeps them
    assert main(["export", str(vfr), "-f", "bvh", "--out", str(tmp_path / "m.bvh"), "--quiet"]) == 0
    assert "the video's frame rate varies; bvh holds one rate" in capsys.readouterr().out
    assert main(["export", str(vfr), "-f", "json", "--out", str(tmp_path / "m2.json"), "--quiet"]) == 0
    assert "frame rate varies" not in capsys.readouterr().out


def test_c3d_events_leave_out_the_frames_without_the_person(tmp_path):
    j = np.zeros((6, 2, 3))
    j[..., 1] = np.arange(6)[:, None, None].repeat(2, 1)[..., 0] * 0.01
    contacts = np.array([[1, 0], [0, 0], [1, 0], [0, 0], [1, 0], [0, 0]], bool)
    seen = np.array([True, True, False, False, True, True])
    doc = _read_c3d(write_c3d(tmp_path / "e.c3d", j, ["a", "b"], 10.0, contacts=contacts, seen=seen))
    frames_of_events = sorted(round(t * 10) for _, _, t in doc["events"])
    assert frames_of_events and not set(frames_of_events) & {2, 3}
    with pytest.raises(InputError, match="seen must be"):
        write_c3d(tmp_path / "f.c3d", j, ["a", "b"], 10.0, seen=np.ones(5, bool))


def test_the_viewer_keys_a_variable_rate_video_as_its_page_steps_through_it(posed_result, tmp_path):
    # the page sets the animation's time to row / fps: keys at the video's own times showed another row's pose
    from flowmocap.commands.view import ViewerData

    folder, _ = posed_result
    stamps = [0.0, 0.04, 0.08, 0.12, 0.2, 0.28, 0.36, 0.40]
    vfr = _with_run(folder, tmp_path / "vfr", video={"fps": 20.0, "variable_frame_rate": True, "timestamps": stamps})
    pygltflib = pytest.importorskip("pygltflib")
    glb = pygltflib.GLTF2().load_from_bytes(ViewerData(vfr).glb)
    acc = glb.accessors[glb.animations[0].samplers[0].input]
    view = glb.bufferViews[acc.bufferView]
    keys = np.frombuffer(glb.binary_blob(), np.float32, acc.count, view.byteOffset + (acc.byteOffset or 0))
    np.testing.assert_allclose(keys, np.arange(T) / 25.0, atol=1e-6)
    assert ViewerData(vfr).meta()["times"] == stamps[3:8]  # the page's label: the video's own seconds
    assert ViewerData(folder).meta()["times"] == [round(i / 25.0, 6) for i in range(3, 8)]

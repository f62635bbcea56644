"""Marker sets of the trc / c3d exports: the HALPE_26 keypoints Pose2Sim's OpenSim model
names, where the body's geometry and the learned keypoint offsets put them."""

from __future__ import annotations

import types

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from flowmocap.body import load_body_model
from flowmocap.body.skeleton import JOINT_INDEX, JOINT_NAMES
from flowmocap.cli import main
from flowmocap.errors import InputError, ModelFileError
from flowmocap.export import export_result, load_fitted_motion
from flowmocap.export.marker_sets import HALPE26_NAMES, marker_names, marker_trajectories, surface_vertices
from flowmocap.io.amass import Y_UP_TO_Z_UP
from flowmocap.vision.keypoint_map import load_keypoint_map

from test_export import posed_result  # noqa: F401  (fixture)
from test_export_markers import _read_c3d, _read_trc


def test_halpe26_names_are_pose2sims_tree():
    # Pose2Sim.skeletons.HALPE_26: 22 nodes, the detector's eyes and ears left out
    assert len(HALPE26_NAMES) == len(set(HALPE26_NAMES)) == 22
    for side in "LR":
        for part in ("Hip", "Knee", "Ankle", "BigToe", "SmallToe", "Heel", "Shoulder", "Elbow", "Wrist"):
            assert side + part in HALPE26_NAMES
    assert {"Hip", "Neck", "Head", "Nose"} <= set(HALPE26_NAMES)
    assert marker_names("joints") == tuple(JOINT_NAMES)
    with pytest.raises(InputError, match="unknown marker set 'coco'"):
        marker_names("coco")


@pytest.mark.parametrize("gender", ["neutral", "male", "female"])
def test_surface_points_sit_where_their_names_say_on_every_bundled_body(gender):
    model = load_body_model("default", gender=gender, dtype=torch.float64)
    v = model.v_template.numpy()
    joints = model.J_regressor.numpy() @ v
    idx = surface_vertices(model)
    p = {name: v[i] for name, i in idx.items()}
    head, neck = joints[JOINT_INDEX["head"]], joints[JOINT_INDEX["neck"]]
    midline = np.abs(v[:, 0]) < 0.02
    assert p["Head"][1] == v[midline, 1].max() and p["Head"][1] > head[1] + 0.1  # the crown
    assert abs(p["Nose"][0]) < 0.02 and p["Nose"][2] > head[2] + 0.05  # forward, on the midline
    assert neck[1] < p["Nose"][1] < p["Head"][1]
    for s, side, sign in (("L", "left", 1.0), ("R", "right", -1.0)):
        ankle = joints[JOINT_INDEX[f"{side}_ankle"]]
        heel, big, small = p[f"{s}Heel"], p[f"{s}BigToe"], p[f"{s}SmallToe"]
        assert heel[2] < ankle[2] - 0.03 and heel[1] < ankle[1]  # behind and below the ankle
        for toe in (big, small):
            assert toe[2] > ankle[2] + 0.12 and toe[1] < ankle[1] - 0.03  # well forward, near the floor
            assert sign * toe[0] > 0  # on its own side
        assert sign * big[0] < sign * (small[0] - sign * 0.03)  # the big toe is medial, by a few cm
        assert big[2] > small[2]  # and further forward
    for name in ("Heel", "BigToe", "SmallToe"):  # left and right mirror each other (to the mesh's detail)
        mirrored = p["R" + name] * np.array([-1.0, 1.0, 1.0])
        assert np.linalg.norm(p["L" + name] - mirrored) < 0.02


def test_a_model_with_no_foot_or_face_is_refused():
    flat = types.SimpleNamespace(v_template=torch.zeros(30, 3, dtype=torch.float64),
                                 J_regressor=torch.full((24, 30), 1.0 / 30, dtype=torch.float64))
    with pytest.raises(ModelFileError, match="not an upright body"):
        surface_vertices(flat)


def test_halpe26_markers_are_the_detector_keypoints_and_mesh_points_of_the_fitted_body(posed_result):
    folder, truth = posed_result
    motion = load_fitted_motion(folder, frame="up")
    names, got = marker_trajectories(motion, "halpe26", chunk=2)  # several chunks
    assert names == HALPE26_NAMES and got.shape == (len(truth["poses"]), 22, 3)
    m = {n: got[:, k] for k, n in enumerate(names)}
    joints = truth["joints3d"]  # the result's own joints, y up
    kmap = load_keypoint_map()
    # keypoint = joint + R_part @ offset, with R_part the part's global rotation; the
    # pelvis's is the root rotation (independent of the body model's transforms)
    root = Rotation.from_rotvec(motion.poses[:, :3]).as_matrix()
    assert kmap.part[JOINT_INDEX["left_hip"]] == JOINT_INDEX["pelvis"]
    np.testing.assert_allclose(m["LHip"], joints[:, JOINT_INDEX["left_hip"]] + root @ kmap.offset[JOINT_INDEX["left_hip"]],
                               atol=1e-5)
    for name, joint in (("LShoulder", "left_shoulder"), ("RShoulder", "right_shoulder"), ("RKnee", "right_knee"),
                        ("LElbow", "left_elbow")):
        assert not kmap.offset[JOINT_INDEX[joint]].any()  # the detector's keypoint is the joint itself
        np.testing.assert_allclose(m[name], joints[:, JOINT_INDEX[joint]], atol=1e-5)
    for name, joint in (("RHip", "right_hip"), ("LKnee", "left_knee"), ("RAnkle", "right_ankle"),
                        ("RWrist", "right_wrist")):
        gap = np.linalg.norm(m[name] - joints[:, JOINT_INDEX[joint]], axis=1)
        np.testing.assert_allclose(gap, np.linalg.norm(kmap.offset[JOINT_INDEX[joint]]), atol=1e-5)
    np.testing.assert_allclose(m["Hip"], 0.5 * (m["LHip"] + m["RHip"]), atol=1e-12)
    np.testing.assert_allclose(m["Neck"], joints[:, JOINT_INDEX["neck"]], atol=1e-5)
    vertices = motion.body()[0]  # the posed mesh
    for name, index in surface_vertices(motion.model).items():
        np.testing.assert_allclose(m[name], vertices[:, index], atol=1e-9)
    # the foot's points stay a foot's length apart, and the head's above the nose
    foot = np.linalg.norm(m["LBigToe"] - m["LHeel"], axis=1)
    assert np.all((foot > 0.2) & (foot < 0.3))
    up = np.array([0.0, 1.0, 0.0])
    assert np.all(np.einsum("ti,ti->t", m["Head"] - m["Nose"], root @ up) > 0.1)


def test_trc_and_c3d_hold_the_halpe26_markers(posed_result, tmp_path, capsys):
    folder, _ = posed_result
    _, expected = marker_trajectories(load_fitted_motion(folder), "halpe26")  # the default ground frame
    doc = _read_trc(export_result(folder, "trc", tmp_path / "h.trc", markers="halpe26"))
    assert doc["Markers"] == list(HALPE26_NAMES) and doc["NumMarkers"] == 22
    got = np.stack([np.asarray(doc[name], np.float64) for name in HALPE26_NAMES], axis=1)
    np.testing.assert_allclose(got, expected, atol=2e-6)
    doc = _read_c3d(export_result(folder, "c3d", tmp_path / "h.c3d", markers="halpe26"))
    assert doc["labels"] == list(HALPE26_NAMES)
    got = np.stack([pts[:, :3] for _, pts in doc["frames"]]) / 1000.0
    np.testing.assert_allclose(got, expected @ Y_UP_TO_Z_UP.T, atol=1e-6)
    assert main(["export", str(folder), "--format", "trc", "--markers", "halpe26", "--quiet"]) == 0
    assert "\tLHeel\t" in (folder / "export" / "motion.trc").read_text()


def test_a_marker_set_is_refused_for_formats_without_markers(posed_result, tmp_path, capsys):
    folder, _ = posed_result
    with pytest.raises(InputError, match="is for the trc and c3d formats"):
        export_result(folder, "bvh", tmp_path / "m.bvh", markers="halpe26")
    with pytest.raises(InputError, match="unknown marker set"):
        export_result(folder, "trc", tmp_path / "m.trc", markers="coco17")
    assert not (tmp_path / "m.bvh").exists() and not (tmp_path / "m.trc").exists()
    assert main(["export", str(folder), "--format", "json", "--markers", "halpe26", "--quiet"]) == 2
    assert "is for the trc and c3d formats" in capsys.readouterr().err

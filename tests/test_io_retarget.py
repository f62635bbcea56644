"""Retargeting mocap onto the SMPL tree: structure, rigs, rest-pose independence (toy body)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from flowmocap.body import JOINT_INDEX, JOINT_NAMES, PARENTS, load_body_model
from flowmocap.errors import DataError, InputError
from flowmocap.io import read_bvh, read_mocap, resolve_joint_map, retarget, write_bvh
from flowmocap.io.mocap import _make_clip
from flowmocap.io.retarget import body_yaw, normalize_joint_name

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CMU = SHARED_DATA / "mocap" / "cmu"

# Bones whose direction the retargeting matches exactly (a mapped child along the chain).
# pelvis->hips and spine3->collars are fixed offsets of each skeleton and differ; the
# feet (ankle->toes) keep their rotation relative to the rest pose instead.
CHAIN_BONES = [(PARENTS[j], j) for j in range(1, 24)
               if JOINT_NAMES[j] not in ("left_hip", "right_hip", "spine1", "left_collar", "right_collar",
                                         "left_foot", "right_foot")]


@pytest.fixture(scope="module")
def cmu_clip():
    if not (CMU / "35_01.amc").exists():
        pytest.skip(f"CMU mocap not found at {CMU} (shared data absent)")
    return read_mocap(CMU / "35_01.amc")


@pytest.fixture(scope="module")
def toy(toy_files):
    return load_body_model(toy_files["npz"], dtype=torch.float64)


@pytest.fixture(scope="module")
def toy_motion(cmu_clip, toy):
    return retarget(cmu_clip, toy)


@pytest.fixture(scope="module")
def toy_motion40(cmu_clip, toy):
    """The first 40 frames retargeted on their own (facing and ground from those frames)."""
    return retarget(cmu_clip.slice(0, 40), toy)


def _run(model, motion):
    dt = model.v_template.dtype
    with torch.no_grad():
        out = model(betas=torch.as_tensor(motion.betas[None], dtype=dt),
                    pose=torch.as_tensor(motion.poses, dtype=dt),
                    trans=torch.as_tensor(motion.trans, dtype=dt))
    return out.joints.double().numpy(), out.vertices[..., 1].min(1).values.double().numpy()


def bone_errors_deg(joints, clip, motion, bones=CHAIN_BONES):
    """{bone: (T,) angle in degrees between the body's and the mocap's bone direction}."""
    a = motion.info["yaw_turn"]
    c, s = math.cos(a), math.sin(a)
    P = clip.positions @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T
    jm = motion.info["joint_map"]
    out = {}
    for p, j in bones:
        if JOINT_NAMES[p] not in jm or JOINT_NAMES[j] not in jm:
            continue
        u = joints[:, j] - joints[:, p]
        v = P[:, clip.index(jm[JOINT_NAMES[j]])] - P[:, clip.index(jm[JOINT_NAMES[p]])]
        cos = (u * v).sum(-1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)
        out[f"{JOINT_NAMES[p]}->{JOINT_NAMES[j]}"] = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    return out


def test_retarget_structure_ground_and_bones(cmu_clip, toy, toy_motion):
    m = toy_motion
    assert m.poses.shape == (358, 72) and m.trans.shape == (358, 3) and m.fps == 120.0
    assert m.info["rig"] == "cmu_asf"
    assert np.isfinite(m.poses).all() and np.isfinite(m.trans).all()
    joints, lowest = _run(toy, m)
    # Ground: the lowest vertex of the clip is on y = 0, none below.
    assert abs(lowest.min()) < 1e-5
    # Origin: the frame-0 pelvis is above x = z = 0; it walks along +z (facing 0).
    np.testing.assert_allclose(joints[0, 0, [0, 2]], 0, atol=1e-6)
    d = joints[-1, 0] - joints[0, 0]
    assert d[2] > 3.0 and abs(d[0]) < 0.3 * d[2]
    # Scale: the path is the mocap's scaled by the leg-length ratio.
    assert m.info["scale"] == pytest.approx(m.info["leg_length_body"] / m.info["leg_length_mocap"])
    mocap_d = cmu_clip.positions[-1, 0] - cmu_clip.positions[0, 0]
    assert np.hypot(d[0], d[2]) == pytest.approx(m.info["scale"] * np.hypot(mocap_d[0], mocap_d[2]), rel=0.02)
    errs = bone_errors_deg(joints, cmu_clip, m)
    assert len(errs) == 16
    for bone, e in errs.items():
        assert e.max() < 1e-3, bone


def test_retarget_options(cmu_clip, toy):
    clip = cmu_clip.slice(0, 60)
    # Without the feet's rest-relative rule, ankle->toe directions match too.
    m = retarget(clip, toy, rest_relative=(), ground="frame")
    joints, lowest = _run(toy, m)
    feet = [(JOINT_INDEX[f"{s}_ankle"], JOINT_INDEX[f"{s}_foot"]) for s in ("left", "right")]
    for bone, e in bone_errors_deg(joints, clip, m, bones=feet).items():
        assert e.max() < 1e-3, bone
    # ground="frame": the lowest vertex touches y = 0 in every frame.
    np.testing.assert_allclose(lowest, 0, atol=1e-6)
    with pytest.raises(InputError, match="rest_relative names unknown"):
        retarget(clip, toy, rest_relative=("left_toe",))


def test_retarget_facing_and_resampling(cmu_clip, toy, toy_motion):
    m = retarget(cmu_clip, toy, fps=30.0, facing=math.pi / 2, ground=None, origin=None)
    assert m.fps == 30.0 and m.num_frames == 90
    from flowmocap.geometry import axis_angle_to_matrix

    yaw = body_yaw(axis_angle_to_matrix(torch.as_tensor(m.poses[:30, :3], dtype=torch.float64)).numpy())
    assert math.atan2(np.sin(yaw).mean(), np.cos(yaw).mean()) == pytest.approx(math.pi / 2, abs=1e-6)
    joints, _ = _run(toy, m)
    d = joints[-1, 0] - joints[0, 0]
    assert d[0] > 3.0 and abs(d[2]) < 0.3 * d[0]  # now walking along +x
    # Same motion as the 120 Hz retarget up to the turn: joint angles (local poses
    # below the root) agree frame for frame (30 Hz frames coincide with every 4th).
    np.testing.assert_allclose(m.poses[:, 3:], toy_motion.poses[::4][:90, 3:], atol=1e-5)


ASF_TO_MIXAMO = {
    "root": "Hips", "lhipjoint": "LeftHipJoint", "lfemur": "LeftUpLeg", "ltibia": "LeftLeg",
    "lfoot": "LeftFoot", "ltoes": "LeftToeBase", "lowerback": "Spine", "upperback": "Spine1",
    "thorax": "Spine2", "lowerneck": "Neck", "upperneck": "Neck1", "head": "Head",
    "lclavicle": "LeftShoulder", "lhumerus": "LeftArm", "lradius": "LeftForeArm",
    "lwrist": "LeftHand", "lhand": "LeftHandMiddle1", "lfingers": "LeftHandMiddle2",
    "lthumb": "LeftHandThumb1",
}
ASF_TO_CMU_BVH = dict(ASF_TO_MIXAMO, lhipjoint="LHipJoint", lowerback="LowerBack",
                      upperback="Spine", thorax="Spine1", lhand="LeftFingerBase",
                      lfingers="LeftHandIndex1", lthumb="LThumb")
ASF_TO_BIOVISION = dict(ASF_TO_MIXAMO, lowerback="Abdomen", upperback="Chest", thorax="Chest2",
                        lfemur="LeftHip", ltibia="LeftKnee", lfoot="LeftAnkle", ltoes="LeftToe",
                        lclavicle="LeftCollar", lhumerus="LeftShoulder", lradius="LeftElbow",
                        lwrist="LeftWrist", lhand="LeftHandMiddle1")


def _rename(clip, table, prefix=""):
    full = dict(table)
    for k, v in table.items():
        if k.startswith("l"):
            full["r" + k[1:]] = v.replace("Left", "Right").replace("LHip", "RHip").replace("LThumb", "RThumb")
    names = []
    for n in clip.names:
        base = n[:-4] if n.endswith("_end") else n
        names.append(prefix + full[base] + ("_end" if n.endswith("_end") else ""))
    return replace(clip, names=tuple(names))


@pytest.mark.parametrize("rig,table,prefix", [
    ("mixamo", ASF_TO_MIXAMO, "mixamorig:"),
    ("cmu_bvh", ASF_TO_CMU_BVH, ""),
    ("biovision", ASF_TO_BIOVISION, ""),
])
def test_rig_name_maps(cmu_clip, toy, toy_motion40, rig, table, prefix):
    clip = _rename(cmu_clip.slice(0, 40), table, prefix)
    m = retarget(clip, toy)
    assert m.info["rig"] == rig
    same = [j for j in range(24) if rig != "cmu_bvh" or j < 20]  # CMU BVH: hand = lfingers
    np.testing.assert_allclose(m.poses.reshape(-1, 24, 3)[:, same],
                               toy_motion40.poses.reshape(-1, 24, 3)[:, same], atol=1e-5)


def test_unknown_rig_lists_joints(cmu_clip, toy):
    clip = replace(cmu_clip, names=tuple(f"bone{i}" for i in range(cmu_clip.num_joints)))
    with pytest.raises(DataError, match=r"unknown skeleton.*Joints found: bone0, bone1, bone2"):
        retarget(clip, toy)
    with pytest.raises(InputError, match="not in"):
        resolve_joint_map(cmu_clip, {"pelvis": "hips"})
    with pytest.raises(InputError, match="lacks"):
        resolve_joint_map(cmu_clip, {"pelvis": "root"})


def test_custom_joint_map(cmu_clip, toy, toy_motion):
    rig, mapping = resolve_joint_map(cmu_clip)
    rig2, mapping2 = resolve_joint_map(cmu_clip, {k: v.upper() for k, v in mapping.items()})
    assert rig2 == "custom" and mapping2 == mapping
    assert normalize_joint_name("mixamorig:Left_Fore-Arm") == "leftforearm"


def _rot(axis, deg):
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_rest_pose_independence(cmu_clip, toy, toy_motion40):
    """The same motion on a rig whose rest pose is an A-pose facing +x gives the same
    SMPL poses: the rest-pose differences are corrected per bone, not assumed away."""
    c = cmu_clip.slice(0, 40)
    yaw = _rot("y", 90)
    A = []
    for j, n in enumerate(c.names):
        chain, k = [], j
        while k >= 0:
            chain.append(c.names[k])
            k = c.parents[k]
        theta = 45.0 if "lhumerus" in chain else -45.0 if "rhumerus" in chain else 0.0
        A.append(_rot("z", theta) @ yaw)
    A = np.array(A)
    par = c.parents
    Ap = np.array([A[p] if p >= 0 else np.eye(3) for p in par])
    rot = np.swapaxes(Ap, -1, -2)[None] @ c.rotations @ A[None]
    offsets = np.einsum("jba,jb->ja", Ap, c.offsets)
    trans = np.einsum("jba,tjb->tja", Ap, c.translations)
    trans[:, 0] = c.translations[:, 0]
    offsets[0] = c.offsets[0]
    other = _make_clip(c.names, par, offsets, rot, trans, c.end_site, c.fps, "a-pose", {})
    np.testing.assert_allclose(other.positions, c.positions, atol=1e-9)
    rest = other.rest_positions()
    arm = rest[c.index("lradius")] - rest[c.index("lhumerus")]
    assert arm[1] < -0.5 * np.linalg.norm(arm)  # the rest arm points down
    assert abs(arm[2]) > abs(arm[0])  # and the rig faces +x (its left is -z)
    m = retarget(other, toy)
    np.testing.assert_allclose(m.poses, toy_motion40.poses, atol=1e-6)


def test_bvh_and_asf_retarget_alike(cmu_clip, toy, toy_motion40, tmp_path):
    path = write_bvh(cmu_clip.slice(0, 40), tmp_path / "35_01.bvh", units_per_metre=100)
    m = retarget(read_bvh(path), toy)
    np.testing.assert_allclose(m.poses, toy_motion40.poses, atol=1e-6)
    np.testing.assert_allclose(m.trans[:, [0, 2]], toy_motion40.trans[:, [0, 2]], atol=1e-5)


SMPL_TO_MIXAMO = {
    "pelvis": "Hips", "spine1": "Spine", "spine2": "Spine1", "spine3": "Spine2", "neck": "Neck",
    "head": "Head", "left_hip": "LeftUpLeg", "left_knee": "LeftLeg", "left_ankle": "LeftFoot",
    "left_foot": "LeftToeBase", "left_collar": "LeftShoulder", "left_shoulder": "LeftArm",
    "left_elbow": "LeftForeArm", "left_wrist": "LeftHand", "left_hand": "LeftHandMiddle1",
}


def test_smpl_motion_round_trip(toy, tmp_path):
    """A body's own motion written as a Mixamo-named BVH retargets back onto the same
    body unchanged (no shared data needed)."""
    from flowmocap.geometry import axis_angle_to_matrix
    from flowmocap.io import builtin_walk

    walk = builtin_walk(toy, fps=30, frames=20)
    with torch.no_grad():
        js = toy().rest_joints[0].numpy()
    names = ["mixamorig:" + SMPL_TO_MIXAMO[n] if n in SMPL_TO_MIXAMO
             else "mixamorig:" + SMPL_TO_MIXAMO[n.replace("right", "left")].replace("Left", "Right")
             for n in JOINT_NAMES]
    par = np.array(PARENTS)
    offsets = js - np.where(par[:, None] >= 0, js[np.maximum(par, 0)], 0.0)
    rot = axis_angle_to_matrix(torch.as_tensor(walk.poses.reshape(-1, 24, 3), dtype=torch.float64)).numpy()
    trans = np.broadcast_to(offsets, (20, 24, 3)).copy()
    trans[:, 0] = walk.trans + js[0]
    clip = _make_clip(names, par, offsets, rot, trans, np.zeros(24, bool), 30.0, "smpl", {})
    clip = read_bvh(write_bvh(clip, tmp_path / "walk.bvh", units_per_metre=100))
    m = retarget(clip, toy, facing=None, origin=None, ground=None)
    assert m.info["rig"] == "mixamo" and m.info["scale"] == pytest.approx(1.0)
    R0 = axis_angle_to_matrix(torch.as_tensor(walk.poses.reshape(-1, 24, 3), dtype=torch.float64))
    R1 = axis_angle_to_matrix(torch.as_tensor(m.poses.reshape(-1, 24, 3), dtype=torch.float64))
    assert (R0 - R1).abs().max() < 1e-5
    np.testing.assert_allclose(m.trans, walk.trans, atol=1e-5)

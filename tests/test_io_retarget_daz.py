"""Retargeting cgspeed's DAZ-friendly BVH conversion of the CMU database (rig ``"daz"``):
recognised by its joint names, bone directions matched, other rigs unchanged."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from flowmocap.body import JOINT_INDEX, load_body_model
from flowmocap.io import read_bvh, read_mocap, resolve_joint_map, retarget

PRIOR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mocap" / "prior"

# The DAZ figure's hierarchy (cm), as in every cmu_daz/*.bvh, fingers cut to two per hand.
DAZ_JOINTS = [  # name, parent, offset
    ("hip", None, (0.0, 0.0, 0.0)),
    ("abdomen", "hip", (0.0, 20.69, -0.73)), ("chest", "abdomen", (0.0, 11.7, -0.49)),
    ("neck", "chest", (0.0, 22.19, -2.19)), ("head", "neck", (-0.24, 7.07, 1.22)),
    ("rCollar", "chest", (-2.68, 19.26, -4.88)), ("rShldr", "rCollar", (-8.78, -1.95, 1.46)),
    ("rForeArm", "rShldr", (-28.17, -1.71, 0.49)), ("rHand", "rForeArm", (-22.59, 0.77, 7.07)),
    ("rIndex1", "rHand", (-7.76, 0.94, 5.61)), ("rMid1", "rHand", (-8.25, 1.18, 3.41)),
    ("lCollar", "chest", (2.68, 19.26, -4.88)), ("lShldr", "lCollar", (8.78, -1.95, 1.46)),
    ("lForeArm", "lShldr", (28.17, -1.71, 0.49)), ("lHand", "lForeArm", (22.59, 0.77, 7.07)),
    ("lIndex1", "lHand", (7.76, 0.94, 5.61)), ("lMid1", "lHand", (8.25, 1.18, 3.41)),
    ("rButtock", "hip", (-8.78, 4.35, 1.22)), ("rThigh", "rButtock", (0.0, -1.71, -2.19)),
    ("rShin", "rThigh", (0.0, -36.82, 0.73)), ("rFoot", "rShin", (0.73, -45.11, -5.12)),
    ("lButtock", "hip", (8.78, 4.35, 1.22)), ("lThigh", "lButtock", (0.0, -1.71, -2.19)),
    ("lShin", "lThigh", (0.0, -36.82, 0.73)), ("lFoot", "lShin", (-0.73, -45.11, -5.12)),
]
END_SITES = {"head": (0.0, 10.0, 0.0), "rIndex1": (-3.0, 0.0, 0.0), "rMid1": (-3.0, 0.0, 0.0),
             "lIndex1": (3.0, 0.0, 0.0), "lMid1": (3.0, 0.0, 0.0),
             "rFoot": (-1.12, -3.7, 12.1), "lFoot": (1.12, -3.7, 12.1)}

EXPECTED_MAP = {
    "pelvis": "hip", "spine1": "abdomen", "spine2": "chest", "neck": "neck", "head": "head",
    "left_hip": "lThigh", "left_knee": "lShin", "left_ankle": "lFoot", "left_collar": "lCollar",
    "left_shoulder": "lShldr", "left_elbow": "lForeArm", "left_wrist": "lHand", "left_hand": "lMid1",
    "right_hip": "rThigh", "right_knee": "rShin", "right_ankle": "rFoot", "right_collar": "rCollar",
    "right_shoulder": "rShldr", "right_elbow": "rForeArm", "right_wrist": "rHand", "right_hand": "rMid1",
}

# SMPL pairs whose direction the retargeting matches exactly for this rig (spine3 and the
# toes are unmapped: spine2 -> neck is matched instead of spine2 -> spine3 -> neck).
MATCHED = [("spine1", "spine2"), ("spine2", "neck"), ("neck", "head")] + [
    (f"{s}_{a}", f"{s}_{b}") for s in ("left", "right")
    for a, b in (("hip", "knee"), ("knee", "ankle"), ("collar", "shoulder"), ("shoulder", "elbow"),
                 ("elbow", "wrist"), ("wrist", "hand"))]


def _daz_bvh(path: Path, frames: int = 6, seed: int = 0) -> Path:
    """A BVH file in the DAZ layout (hip: 6 channels ZYX; others ZXY), random poses."""
    kids: dict[str | None, list[str]] = {}
    for n, p, _ in DAZ_JOINTS:
        kids.setdefault(p, []).append(n)
    off = {n: o for n, _, o in DAZ_JOINTS}
    lines = ["HIERARCHY"]

    def emit(name: str, depth: int) -> None:
        pad = "  " * depth
        lines.append(f"{pad}{'ROOT' if depth == 0 else 'JOINT'} {name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {' '.join(map(str, off[name]))}")
        if depth == 0:
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation")
        else:
            lines.append(f"{pad}  CHANNELS 3 Zrotation Xrotation Yrotation")
        for k in kids.get(name, []):
            emit(k, depth + 1)
        if name in END_SITES:
            lines.extend([f"{pad}  End Site", f"{pad}  {{",
                          f"{pad}    OFFSET {' '.join(map(str, END_SITES[name]))}", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    emit("hip", 0)
    rng = np.random.default_rng(seed)
    n_rot = len(DAZ_JOINTS)
    lines += ["MOTION", f"Frames: {frames}", "Frame Time: 0.0333333"]
    for t in range(frames):
        vals = [0.0, 86.0 + t, 5.0 * t] + list(rng.uniform(-35, 35, 3 * n_rot))
        lines.append(" ".join(f"{v:.4f}" for v in vals))
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def toy(toy_files):
    return load_body_model(toy_files["npz"], dtype=torch.float64)


def _bone_errors_deg(model, clip, motion) -> dict[str, float]:
    dt = model.v_template.dtype
    with torch.no_grad():
        J = model(betas=torch.as_tensor(motion.betas[None], dtype=dt), pose=torch.as_tensor(motion.poses, dtype=dt),
                  trans=torch.as_tensor(motion.trans, dtype=dt)).joints.double().numpy()
    a = motion.info["yaw_turn"]
    c, s = math.cos(a), math.sin(a)
    P = clip.positions @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T
    jm = motion.info["joint_map"]
    out = {}
    for p, j in MATCHED:
        u = J[:, JOINT_INDEX[j]] - J[:, JOINT_INDEX[p]]
        v = P[:, clip.index(jm[j])] - P[:, clip.index(jm[p])]
        cos = (u * v).sum(-1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)
        out[f"{p}->{j}"] = float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max())
    return out


def test_daz_rig_recognised_and_bones_matched(tmp_path, toy):
    clip = read_bvh(_daz_bvh(tmp_path / "daz.bvh"))
    rig, mapping = resolve_joint_map(clip)
    assert rig == "daz" and mapping == EXPECTED_MAP
    m = retarget(clip, toy)
    assert m.info["rig"] == "daz" and m.poses.shape == (6, 72) and np.isfinite(m.poses).all()
    errs = _bone_errors_deg(toy, clip, m)
    assert len(errs) == len(MATCHED)
    for bone, e in errs.items():
        assert e < 1e-3, (bone, e)
    # Unmapped SMPL joints follow their parent: identity local rotations.
    pose = m.poses.reshape(-1, 24, 3)
    for name in ("spine3", "left_foot", "right_foot"):
        np.testing.assert_allclose(pose[:, JOINT_INDEX[name]], 0, atol=1e-9)


def test_daz_real_file_and_mb_unchanged():
    """On the shared data: a DAZ walk retargets as "daz" with walking knee angles, and the
    MotionBuilder conversion still resolves as "cmu_bvh"."""
    daz, mb = PRIOR / "cmu_daz" / "12_01.bvh", PRIOR / "cmu_mb" / "07_01.bvh"
    if not (daz.exists() and mb.exists()):
        pytest.skip(f"CMU prior mocap not found at {PRIOR} (shared data absent)")
    model = load_body_model("default")
    for path, rig in ((daz, "daz"), (mb, "cmu_bvh")):
        clip = read_mocap(path).slice(0, 60)
        m = retarget(clip, model, origin=None, ground=None)
        assert m.info["rig"] == rig
        knee = np.degrees(np.linalg.norm(m.poses.reshape(-1, 24, 3)[:, [4, 5]], axis=-1))
        assert 40 < knee.max() < 90 and knee.min() < 20, (path.name, knee.min(), knee.max())
    assert resolve_joint_map(read_mocap(mb))[1]["spine1"] == "LowerBack"

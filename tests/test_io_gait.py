"""Gait checks of the retargeted CMU walk and the built-in walk: speed, stride, pelvis
height, knee flexion, feet on the ground, bone directions; smoothness and periodicity.

Figures for the default body are printed (run with ``-s`` to see them).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from flowmocap.body import JOINT_INDEX, load_body_model
from flowmocap.errors import InputError
from flowmocap.io import builtin_walk, load_motion, read_mocap, retarget, walk_poses

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CMU = SHARED_DATA / "mocap" / "cmu"


def _default_model():
    return load_body_model("default", gender="neutral", dtype=torch.float64)


def _cmu_clip():
    if not (CMU / "35_01.amc").exists():
        pytest.skip(f"CMU mocap not found at {CMU} (shared data absent)")
    return read_mocap(CMU / "35_01.amc")


def body_track(model, motion, chunk=64):
    """Joints (T, 24, 3) and the lowest vertex height per frame (T,), metres."""
    dt = model.v_template.dtype
    joints, low = [], []
    with torch.no_grad():
        for s in range(0, motion.num_frames, chunk):
            out = model(betas=torch.as_tensor(motion.betas[None], dtype=dt),
                        pose=torch.as_tensor(motion.poses[s:s + chunk], dtype=dt),
                        trans=torch.as_tensor(motion.trans[s:s + chunk], dtype=dt))
            joints.append(out.joints.double().numpy())
            low.append(out.vertices[..., 1].min(1).values.double().numpy())
    return np.concatenate(joints), np.concatenate(low)


def gait_figures(joints: np.ndarray, lowest: np.ndarray, fps: float) -> dict:
    """Walking speed (m/s), stride lengths (m), pelvis height (m), knee flexion (deg),
    lowest vertex (m) of a walking body's joints ``(T, 24, 3)``."""
    J = JOINT_INDEX
    T = joints.shape[0]
    pelvis = joints[:, J["pelvis"]]
    d = pelvis[-1] - pelvis[0]
    speed = float(np.hypot(d[0], d[2]) * fps / (T - 1))
    strides, knees = [], {}
    for side in ("left", "right"):
        ankle = joints[:, J[f"{side}_ankle"]][:, [0, 2]]
        v = np.linalg.norm(np.gradient(ankle, axis=0), axis=-1) * fps
        stance = v < 0.25 * speed
        # Centroids of the stance phases (runs of at least 0.1 s), a stride apart.
        runs, start = [], None
        for t in range(T + 1):
            if t < T and stance[t]:
                start = t if start is None else start
            elif start is not None:
                if t - start >= 0.1 * fps:
                    runs.append(ankle[start:t].mean(0))
                start = None
        strides += [float(np.linalg.norm(b - a)) for a, b in zip(runs, runs[1:])]
        u = joints[:, J[f"{side}_knee"]] - joints[:, J[f"{side}_hip"]]
        w = joints[:, J[f"{side}_ankle"]] - joints[:, J[f"{side}_knee"]]
        cos = (u * w).sum(-1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(w, axis=-1)
        knees[side] = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    knee = np.concatenate(list(knees.values()))
    return {
        "speed": speed, "strides": strides,
        "stride": float(np.median(strides)) if strides else float("nan"),
        "pelvis_height": float(pelvis[:, 1].mean()),
        "pelvis_bob": float(np.ptp(pelvis[:, 1])),
        "knee_min": float(knee.min()), "knee_max": float(knee.max()),
        "lowest": float(lowest.min()), "highest_lowest": float(lowest.max()),
    }


def _check_walk(f, speed, speed_tol):
    assert abs(f["speed"] - speed) < speed_tol, f
    assert len(f["strides"]) >= 2 and 1.1 < f["stride"] < 1.7, f
    assert 0.8 < f["pelvis_height"] < 1.1, f
    assert 0.01 < f["pelvis_bob"] < 0.1, f
    assert f["knee_min"] < 15 and 45 < f["knee_max"] < 80, f
    assert f["lowest"] > -0.02, f  # feet never sink more than 2 cm


# ------------------------------------------------------------------------ CMU 35_01


def test_cmu_walk_on_default_body():
    from test_io_retarget import bone_errors_deg

    clip = _cmu_clip()
    model = _default_model()
    motion = retarget(clip, model)
    joints, lowest = body_track(model, motion)
    f = gait_figures(joints, lowest, motion.fps)
    errs = bone_errors_deg(joints, clip, motion)
    chain = np.concatenate(list(errs.values()))
    f["bone_error_median_deg"] = float(np.median(chain))
    f["scale"] = motion.info["scale"]
    print("\nCMU 35_01 on the default body:", {k: (np.round(v, 3) if not isinstance(v, list) else np.round(v, 3).tolist()) for k, v in f.items()})
    # The mocap walks 1.29 m/s; scaled by the leg-length ratio of the two bodies.
    _check_walk(f, 1.27 * motion.info["scale"], 0.1)
    assert 0.8 < motion.info["scale"] < 1.2
    assert f["bone_error_median_deg"] < 0.01 and chain.max() < 0.01


# ------------------------------------------------------------------------ built-in


@pytest.fixture(scope="module")
def toy(toy_files):
    return load_body_model(toy_files["npz"], dtype=torch.float64)


def test_walk_poses_smooth_and_periodic():
    phase = np.linspace(0, 2, 401)
    p = walk_poses(phase)
    np.testing.assert_allclose(p[:200], p[200:400], atol=1e-9)  # period 1
    # Smooth: small second differences (no kinks) at 200 samples per cycle.
    assert np.abs(np.diff(p, 2, axis=0)).max() < 5e-3
    assert np.abs(np.diff(p, axis=0)).max() < 0.05


def test_builtin_walk_toy_structure(toy):
    m = builtin_walk(toy, fps=30, duration=3.0)
    assert m.poses.shape == (90, 72) and m.trans.shape == (90, 3)
    assert m.source == "builtin:walk" and m.fps == 30
    joints, lowest = body_track(toy, m)
    assert lowest.min() > -2e-3 and lowest.max() < 2e-3  # foot on the ground every frame
    np.testing.assert_allclose(joints[0, 0, [0, 2]], 0, atol=1e-9)
    f = gait_figures(joints, lowest, 30)
    assert abs(f["speed"] - 1.3) < 0.05, f
    # Periodic: a whole period later the pose repeats and the body has moved one stride.
    period = m.info["period_s"]
    m2 = builtin_walk(toy, fps=1 / period, frames=4)
    np.testing.assert_allclose(m2.poses[1:], m2.poses[:1].repeat(3, 0), atol=1e-6)
    np.testing.assert_allclose(np.diff(m2.trans[:, 2]), m.info["stride_m"], rtol=1e-6)
    np.testing.assert_allclose(np.diff(m2.trans[:, [0, 1]], axis=0), 0, atol=1e-6)
    # Facing +x walks along +x.
    m3 = builtin_walk(toy, fps=30, duration=2.0, facing=np.pi / 2)
    j3, _ = body_track(toy, m3)
    d = j3[-1, 0] - j3[0, 0]
    assert d[0] > 2.0 and abs(d[2]) < 0.05
    # Deterministic.
    np.testing.assert_array_equal(builtin_walk(toy, fps=30, duration=3.0).poses, m.poses)


def test_builtin_walk_on_default_body():
    model = _default_model()
    m = builtin_walk(model, fps=30, duration=4.0)
    joints, lowest = body_track(model, m)
    f = gait_figures(joints, lowest, m.fps)
    f.update({k: m.info[k] for k in ("period_s", "stride_m", "cadence_steps_per_min")})
    print("\nbuilt-in walk on the default body:", {k: (np.round(v, 3) if not isinstance(v, list) else np.round(v, 3).tolist()) for k, v in f.items()})
    _check_walk(f, 1.3, 0.05)
    assert 95 < m.info["cadence_steps_per_min"] < 130


def test_load_motion(toy):
    m = load_motion("builtin:walk", toy, fps=25, frames=10)
    assert m.num_frames == 10 and m.fps == 25 and m.source == "builtin:walk"
    with pytest.raises(InputError, match="available: builtin:walk"):
        load_motion("builtin:run", toy)
    if (CMU / "35_01.amc").exists():
        m = load_motion(CMU / "35_01.amc", toy, fps=30)
        assert m.fps == 30 and m.num_frames == 90 and m.info["rig"] == "cmu_asf"

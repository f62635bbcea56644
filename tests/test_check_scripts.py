"""Closed-form checks of the measures in two of issue 18's check scripts:
benchmarks/real3d_torso.py (the torso's yaw) and benchmarks/detector_runs_2d.py (the
detector runs' keypoints combined)."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def torso():
    return _load("real3d_torso")


NAMES = ("head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
         "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle")


def _body(rotvec: np.ndarray) -> np.ndarray:
    """A torso in SMPL's body axes (x the person's left, y up, z forward), turned by
    ``rotvec`` into the camera's axes and put 3 m in front of it: ``(1, 13, 3)``."""
    p = np.zeros((13, 3))
    i = {n: k for k, n in enumerate(NAMES)}
    p[i["left_shoulder"]], p[i["right_shoulder"]] = (0.18, 0.5, 0.0), (-0.18, 0.5, 0.0)
    p[i["left_hip"]], p[i["right_hip"]] = (0.1, 0.0, 0.02), (-0.1, 0.0, 0.02)
    return (Rotation.from_rotvec(rotvec).apply(p) + (0.0, 0.0, 3.0))[None]


@pytest.mark.parametrize("yaw", [0.0, 30.0, -75.0, 150.0, -170.0])
def test_torso_yaw_follows_the_facing_convention_of_the_automatic_init(torso, yaw):
    # facing_rotvec's global orientation for an upright body turned by `yaw`
    rotvec = (Rotation.from_euler("y", np.radians(yaw)) * Rotation.from_euler("x", np.pi)).as_rotvec()
    got = torso.torso_yaw(_body(rotvec), NAMES)[0]
    assert torso.angle_gap(np.array([got]), np.array([yaw]))[0] == pytest.approx(0.0, abs=1e-6)


def test_angle_gap_wraps(torso):
    got = torso.angle_gap(np.array([179.0, -170.0, 10.0]), np.array([-179.0, 170.0, 10.0]))
    assert got == pytest.approx([2, 20, 0])


def test_the_mirror_run_comes_back_with_left_and_right_exchanged():
    mod = _load("detector_runs_2d")

    class Landmark:
        def __init__(self, x, y):
            self.x, self.y, self.visibility = x, y, 1.0

    # a result whose every landmark sits at x = 0.25 of a 200-px-wide mirrored image, but
    # the left shoulder at 0.75: mirrored back, the person's left shoulder is at 50 px
    # and the right shoulder takes the other value
    lms = [Landmark(0.25, 0.5) for _ in range(33)]
    lms[mod.MEDIAPIPE_LANDMARKS["left_shoulder"]] = Landmark(0.75, 0.5)

    class Result:
        pose_landmarks = type("L", (), {"landmark": lms})

    kp = mod.landmarks(Result(), 200, 100, mirrored=True)
    names = list(mod.KEYPOINT_NAMES)
    assert kp[names.index("right_shoulder")] == pytest.approx([50.0, 50.0])
    assert kp[names.index("left_shoulder")] == pytest.approx([150.0, 50.0])


def test_hypotheses_combine_the_runs_given():
    mod = _load("detector_runs_2d")
    base = np.stack([np.arange(15.0), np.arange(15.0) * 2], 1) * 10.0  # a body about 220 px tall
    others = {"mirror": base + 2.0, "border": None, "single": base + 100.0}  # one run far off, one missing
    h = mod.hypotheses(base, others)
    K = mod.K
    assert h["border"] is None
    assert h["mean"] == pytest.approx((3 * base[:K] + 102.0) / 3)
    assert h["median"] == pytest.approx(base[:K] + 2.0)
    assert h["main_and_mirror"] == pytest.approx(base[:K] + 1.0)
    assert h["mean_of_agreeing"] == pytest.approx(base[:K] + 1.0)  # the run 100 px off is left out

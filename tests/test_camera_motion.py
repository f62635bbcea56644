"""Whether the camera turns (flowmocap.vision.camera_motion): a turning camera simulated by
warping a textured panorama with K R K^-1, a still one, a person moving in front of it left
out, and the run's note."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flowmocap.errors import InputError
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.vision.camera_motion import MOVING_DEG, camera_motion, frame_rotation

W, H, F = 320, 240, 300.0
CAM = PinholeCamera.from_focal(W, H, F)
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
PAD = 200  # the panorama reaches this far past the first frame on every side


def _panorama(seed: int = 0) -> np.ndarray:
    """A textured scene wider than the frame: blurred noise in colour blocks."""
    import cv2

    rng = np.random.default_rng(seed)
    img = rng.integers(0, 255, (H + 2 * PAD, W + 2 * PAD, 3)).astype(np.uint8)
    img = cv2.GaussianBlur(img, (0, 0), 2.0)
    for _ in range(60):
        x, y = rng.integers(0, W + 2 * PAD - 40), rng.integers(0, H + 2 * PAD - 40)
        img[y:y + rng.integers(10, 40), x:x + rng.integers(10, 40)] = rng.integers(0, 255, 3)
    return img


class Turning:
    """Frames of a camera that turns by ``rotations[i]`` (x_i = R_i x_0) about its centre;
    optionally a "person" (a textured block moving right 4 px a frame) in front, with masks."""

    def __init__(self, rotations, person: bool = False):
        self.rotations, self.person, self.pano = rotations, person, _panorama()
        self.masks = [None] * len(rotations) if person else None
        self.camera = None

    def __len__(self):
        return len(self.rotations)

    def _box(self, i):
        return 60 + 4 * i, 50, 160 + 4 * i, 230

    def frame(self, i):
        import cv2

        M = K @ self.rotations[i] @ np.linalg.inv(K) @ np.array([[1, 0, -PAD], [0, 1, -PAD], [0, 0, 1.0]])
        img = cv2.warpPerspective(self.pano, M, (W, H), flags=cv2.INTER_LINEAR)
        if self.person:
            x0, y0, x1, y1 = self._box(i)
            img[y0:y1, x0:x1] = _panorama(1)[y0:y1, x0 + 4 * i:x1 + 4 * i]  # its own texture, moving with it
        return img

    def mask(self, i):
        if not self.person:
            return None
        m = np.zeros((H, W), bool)
        x0, y0, x1, y1 = self._box(i)
        m[y0:y1, x0:x1] = True
        return m


def _pan(n, deg_per_frame, axis=(0, 1, 0)):
    return [Rotation.from_rotvec(np.radians(deg_per_frame * i) * np.asarray(axis, float)).as_matrix()
            for i in range(n)]


def test_a_camera_turning_half_a_degree_a_frame_is_found_to_turn_by_that():
    got = camera_motion(Turning(_pan(20, 0.5)), CAM)
    assert got.moving and not got.unknown
    np.testing.assert_allclose(got.turn_deg, 0.5 * np.arange(20), rtol=0.03, atol=0.1)  # within 3 %
    axis = Rotation.from_matrix(got.rotations[-1]).as_rotvec()
    assert abs(axis[1]) / np.linalg.norm(axis) > 0.99  # about the vertical (a pan)
    assert got.residual_px < 0.5
    doc = got.to_dict(rotations=True)
    assert doc["moving"] and doc["turn_deg_end"] == pytest.approx(9.5, rel=0.03) and len(doc["rotvecs"]) == 20


def test_a_still_camera_is_still_and_a_person_in_front_is_left_out():
    still = camera_motion(Turning(_pan(15, 0.0)), CAM)
    assert not still.moving and still.turn_deg.max() < 0.05
    # a textured person crossing 4 px a frame: with their mask left out, still still
    walking = camera_motion(Turning(_pan(15, 0.0), person=True), CAM)
    assert not walking.moving and walking.turn_deg.max() < 0.2
    # and a tilt with the person in front is found
    tilt = camera_motion(Turning(_pan(15, 0.4, axis=(1, 0, 0)), person=True), CAM)
    assert tilt.moving == (0.4 * 14 > MOVING_DEG) and tilt.turn_deg[-1] == pytest.approx(5.6, abs=0.3)


def test_frames_without_texture_are_unknown_and_bad_frames_are_refused():
    blank = np.zeros((H, W, 3), np.uint8)
    assert frame_rotation(blank, blank, K) is None

    class Blank:
        masks, camera = None, None

        def __len__(self):
            return 4

        def frame(self, i):
            return blank

    got = camera_motion(Blank(), CAM)
    assert got.unknown == [1, 2, 3] and not got.moving and np.allclose(got.rotations, np.eye(3))
    with pytest.raises(InputError, match="two RGB frames of one size"):
        frame_rotation(blank, blank[:10], K)


def test_a_run_on_a_turning_camera_says_so(tmp_path, monkeypatch, capsys):
    """flowmocap track on a video whose camera turns: run.json's camera_motion holds the
    rotation per frame and the run says what turns with the camera."""
    import json

    import flowmocap.vision.auto as auto
    import flowmocap.vision.detect as detect
    from flowmocap.cli import main
    from flowmocap.io.results import read_result
    from flowmocap.io.sequence import load_sequence
    from flowmocap.synth import synthesize

    from test_auto import GroundTruthDetector, Nobody
    from test_video import write_video

    d = tmp_path / "seq"
    synthesize("builtin:walk", d, fps=30, frames=6, size="320x240", seed=1, azimuth=80.0, distance=3.0, flow=False)
    seq = load_sequence(d)
    scene = Turning(_pan(6, 1.0))
    frames = []
    for i in range(6):  # the walker over the turning scene (a body that turns with the camera: enough here)
        img, body = scene.frame(i), seq.frame(i)
        m = seq.mask(i)
        img[m] = body[m]
        frames.append(img)
    video = write_video(tmp_path / "pan.mp4", frames)
    fake = GroundTruthDetector(seq, absent=set())
    monkeypatch.setattr(auto, "DETECT_IN_CHILD", False)
    monkeypatch.setattr(detect, "MediaPipePoseDetector", lambda augment=True, model="full": fake if augment else Nobody())
    cfg = tmp_path / "fast.json"
    cfg.write_text(json.dumps({"init_iterations": 8, "init_flow_iterations": 4, "iterations": 4}))
    out = tmp_path / "out"
    assert main(["track", str(video), "--out", str(out), "--config", str(cfg), "--focal", str(F)]) == 0
    _, run = read_result(out)
    cm = run["camera_motion"]
    assert cm["moving"] and cm["turn_deg_end"] == pytest.approx(5.0, rel=0.1) and len(cm["rotvecs"]) == 6
    assert "the camera turns (a pan or a tilt): up to 5 degrees" in capsys.readouterr().out

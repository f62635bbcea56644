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
    """Frames of a camera that turns by ``rotations[i]`` (x_i = R_i x_0) about its centre and
    optionally zooms (its focal length ``zooms[i]`` times the first's); optionally a "person" (a
    textured block moving right 4 px a frame) in front, with masks."""

    def __init__(self, rotations, person: bool = False, zooms=None):
        self.rotations, self.person, self.pano = rotations, person, _panorama()
        self.zooms = [1.0] * len(rotations) if zooms is None else list(zooms)
        self.masks = [None] * len(rotations) if person else None
        self.camera = None

    def __len__(self):
        return len(self.rotations)

    def _box(self, i):
        return 60 + 4 * i, 50, 160 + 4 * i, 230

    def frame(self, i):
        import cv2

        Z = np.diag([self.zooms[i], self.zooms[i], 1.0])  # the focal length scaled about the image's centre
        M = K @ Z @ self.rotations[i] @ np.linalg.inv(K) @ np.array([[1, 0, -PAD], [0, 1, -PAD], [0, 0, 1.0]])
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


def test_a_camera_zooming_out_while_it_pans_is_found_to_do_both():
    """A camera panning 0.3 degrees a frame while it zooms out 1 % a frame (20 frames, to 0.83
    of its focal length): each frame's turn and zoom are found together, within 0.5 % of the
    zoom and 3 % of the turn; the turn alone would leave the background pixels off. A still
    camera and one that only pans do not zoom. (The scene is one flat picture, which a move
    towards it would show alike, so the floor's move is not looked for here.)"""
    zooms = 0.99 ** np.arange(20)
    got = camera_motion(Turning(_pan(20, 0.3), zooms=zooms), CAM, sideways=False)
    assert got.moving and got.zooming and not got.unknown
    np.testing.assert_allclose(got.zooms, zooms, rtol=0.005)
    np.testing.assert_allclose(got.turn_deg, 0.3 * np.arange(20), rtol=0.03, atol=0.1)
    assert got.residual_px < 0.5
    doc = got.to_dict(rotations=True)
    assert doc["zooming"] and doc["zoom_min"] == pytest.approx(zooms[-1], rel=0.005) and len(doc["zooms"]) == 20
    assert frame_rotation(Turning([np.eye(3)] * 2, zooms=[1.0, 0.9]).frame(0),
                          Turning([np.eye(3)] * 2, zooms=[1.0, 0.9]).frame(1), K)[1] > 3.0  # a turn cannot
    for still in (camera_motion(Turning(_pan(15, 0.0)), CAM), camera_motion(Turning(_pan(15, 0.5)), CAM)):
        assert not still.zooming and np.abs(still.zooms - 1).max() < 0.002 and "zooms" not in still.to_dict(True)


def test_a_still_camera_is_still_and_a_person_in_front_is_left_out():
    still = camera_motion(Turning(_pan(15, 0.0)), CAM)
    assert not still.moving and still.turn_deg.max() < 0.05
    # a textured person crossing 4 px a frame: with their mask left out, still still
    walking = camera_motion(Turning(_pan(15, 0.0), person=True), CAM)
    assert not walking.moving and walking.turn_deg.max() < 0.2
    # the "person" not left out, over 40 frames: each frame's turn is found against a keyframe,
    # so the corners that move with them do not bend it frame after frame (no drift)
    unmasked = camera_motion(Turning(_pan(40, 0.0), person=True), CAM, masks=False, sideways=False)
    assert not unmasked.moving and unmasked.turn_deg.max() < 0.25  # a quarter of the frame moves
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

    class Cut(Turning):  # a still camera, frames 3-4 grey (a cut): no turn is made up across it
        def frame(self, i):
            return blank + 110 if i in (3, 4) else super().frame(i)

    cut = camera_motion(Cut(_pan(8, 0.0)), CAM)
    assert cut.unknown == [3, 4] and cut.turn_deg.max() < 0.05  # frame 5 is matched with the keyframe before the cut
    with pytest.raises(InputError, match="two RGB frames of one size"):
        frame_rotation(blank, blank[:10], K)


def _track_over(scene, tmp_path, monkeypatch, focal: bool = True) -> dict:
    """``flowmocap track`` on the built-in walker (6 frames) pasted over ``scene``'s frames
    (a body that does not move with the camera: enough for the camera's estimate), with a
    detector that gives the truth, and the true focal length given (``focal``) or not;
    returns run.json."""
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
    frames = []
    for i in range(6):
        img, body = scene.frame(i), seq.frame(i)
        m = seq.mask(i)
        img[m] = body[m]
        frames.append(img)
    video = write_video(tmp_path / "moving.mp4", frames)
    fake = GroundTruthDetector(seq, absent=set())
    monkeypatch.setattr(auto, "DETECT_IN_CHILD", False)
    monkeypatch.setattr(detect, "MediaPipePoseDetector", lambda augment=True, model="full": fake if augment else Nobody())
    cfg = tmp_path / "fast.json"
    cfg.write_text(json.dumps({"init_iterations": 8, "init_flow_iterations": 4, "iterations": 4}))
    out = tmp_path / "out"
    given = ["--focal", str(F)] if focal else []
    assert main(["track", str(video), "--out", str(out), "--config", str(cfg), *given]) == 0
    return read_result(out)[1]


def test_a_run_on_a_turning_camera_says_so(tmp_path, monkeypatch, capsys):
    """flowmocap track on a video whose camera turns: run.json's camera_motion holds the
    rotation per frame and the run says what turns with the camera. Everyone the detector
    saw besides the person is handed to the camera's motion to be left out."""
    from flowmocap.vision import camera_motion as module

    seen = {}

    def recording(*args, **kwargs):
        seen.update(kwargs)
        return camera_motion(*args, **kwargs)

    monkeypatch.setattr(module, "camera_motion", recording)
    cm = _track_over(Turning(_pan(6, 1.0)), tmp_path, monkeypatch)["camera_motion"]
    assert seen["others"].__self__.people_dir == tmp_path / "out" / "detections" / "people"
    assert seen["others"].__func__.__name__ == "people" and seen["others"](3) is None  # one person in view
    assert cm["moving"] and cm["turn_deg_end"] == pytest.approx(5.0, rel=0.1) and len(cm["rotvecs"]) == 6
    assert not cm["moving_sideways"] and "shifts" not in cm
    assert 0.0 < cm["seconds"] < 600.0  # the time its fit took, every pass together
    assert "the camera turns (a pan or a tilt): up to 5 degrees" in capsys.readouterr().out


@pytest.mark.parametrize("guess", [200.0, 300.0, 450.0])
@pytest.mark.parametrize("zoom", [False, True])
def test_a_turning_cameras_focal_length_is_read_from_its_background(guess, zoom):
    """A camera that pans 0.5 degrees a frame (30 frames, 14.5 degrees), zooming out 1 % a frame
    or not, fitted with a focal length a third short, right, or half again too long: the
    background's turns give the true 300 px within 4 %, and fitted again with that, within 1 %
    (as track does); the turn fitted with a wrong guess is off (why it matters: the world's
    directions come from it), with the estimate right. A still camera, or one that turns less
    than FOCAL_MIN_TURN_DEG, gives none."""
    from flowmocap.vision.camera_motion import FOCAL_MIN_TURN_DEG

    seq = Turning(_pan(30, 0.5), zooms=0.99 ** np.arange(30) if zoom else None)
    got = camera_motion(seq, PinholeCamera.from_focal(W, H, guess), sideways=False, focal=True)
    assert got.focal["focal_px"] == pytest.approx(F, rel=0.04)
    assert got.focal["used_px"] == guess
    assert got.focal["ratio"] == pytest.approx(got.focal["focal_px"] / guess, rel=1e-3)
    assert got.focal["sharpness"] > 1.5 and got.to_dict()["focal"] == got.focal
    again = camera_motion(seq, PinholeCamera.from_focal(W, H, got.focal["focal_px"]), sideways=False, focal=True)
    assert again.focal["focal_px"] == pytest.approx(F, rel=0.01)
    assert again.turn_deg[-1] == pytest.approx(14.5, rel=0.04)  # fitted with the first estimate
    if guess != F:
        assert abs(got.turn_deg[-1] - 14.5) > 1.0  # the turn itself is off with the guess
    still = camera_motion(Turning(_pan(30, 0.0)), PinholeCamera.from_focal(W, H, guess), sideways=False, focal=True)
    assert still.focal is None and "focal" not in still.to_dict()
    slight = Turning(_pan(30, 0.8 * FOCAL_MIN_TURN_DEG / 29))
    assert camera_motion(slight, CAM, sideways=False, focal=True).focal is None
    assert camera_motion(seq, CAM, sideways=False).focal is None  # not asked for


def test_a_run_without_a_focal_length_on_a_turning_camera_tracks_with_the_backgrounds(tmp_path, monkeypatch,
                                                                                      capsys):
    """flowmocap track with no focal length on a video whose camera pans 1.5 degrees a frame:
    the guess (0.9 x 320 = 288 px) is replaced by the focal length the background's turns
    give, within 1 % of the true 300 px; the body is tracked with it, the turns are fitted with
    it, and run.json and the log say so. With --focal given, or a still camera, the camera is
    the one given or guessed; where the camera also moves (carried over a floor, turning 1.5
    degrees a frame; an estimate of 400 px handed in, as the floor-only scene gives none) and
    its floor shows the move with the estimate too, the estimate is recorded but the guess kept."""
    run = _track_over(Turning(_pan(6, 1.5)), tmp_path, monkeypatch, focal=False)
    cm = run["camera_motion"]
    assert cm["focal"]["guess_px"] == pytest.approx(288.0) and run["camera"]["fx"] == pytest.approx(F, rel=0.01)
    assert cm["focal"]["used_px"] == pytest.approx(run["camera"]["fx"], abs=0.1)
    assert cm["focal"]["ratio_to_guess"] == pytest.approx(run["camera"]["fx"] / 288.0, rel=1e-3)
    assert cm["turn_deg_end"] == pytest.approx(7.5, rel=0.03)  # fitted with the found focal length
    said = capsys.readouterr().out
    assert "the background's turns give its focal length: 30" in said and "the body is tracked with it" in said
    assert "camera: focal length 30" in said and "from the background's turns" in said
    given = _track_over(Turning(_pan(6, 1.5)), tmp_path / "given", monkeypatch)
    assert given["camera"]["fx"] == F and "focal" not in given["camera_motion"]
    still = _track_over(Turning(_pan(6, 0.0)), tmp_path / "still", monkeypatch, focal=False)
    assert still["camera"]["fx"] == pytest.approx(288.0) and "focal" not in still["camera_motion"]
    capsys.readouterr()
    from flowmocap.vision import camera_motion as module

    def estimated(*args, **kwargs):
        got = camera_motion(*args, **kwargs)
        if kwargs.get("focal"):
            got.focal = {"focal_px": 400.0, "used_px": 288.0, "ratio": 1.3889, "pairs": 5, "sharpness": 2.0}
        return got

    monkeypatch.setattr(module, "camera_motion", estimated)
    carried = _track_over(Carried(6, (0.06, 0, 0), yaw=1.5), tmp_path / "carried", monkeypatch, focal=False)
    cm = carried["camera_motion"]
    assert cm["moving_sideways"] and cm["focal"]["applied"] is False and carried["camera"]["fx"] == pytest.approx(288.0)
    assert "a camera that moves bends that estimate, so the guess is kept" in capsys.readouterr().out


def test_a_pan_over_a_floor_seen_with_the_wrong_focal_length_is_not_taken_for_a_move(tmp_path, monkeypatch,
                                                                                       capsys):
    """A camera on a tripod 1.5 m above a floor, panning 2 degrees a frame, with a lens of 430 px
    (1.5 times the guess of 288): fitted with the guess, its floor shows a move (0.13 of its
    height) that is not there. track reads the focal length from the turns (within 5 % from five
    frame pairs of an encoded video, mostly floor), finds no move with it, and tracks with it."""
    from flowmocap.synth.carried import CarriedCamera

    true = 430.0
    K2 = np.array([[true, 0, W / 2], [0, true, H / 2], [0, 0, 1.0]])
    pan = CarriedCamera(6, (0.0, 0.0, 0.0), 2.0, K=K2, size=(W, H), pitch_deg=15.0)
    assert camera_motion(pan, PinholeCamera.from_focal(W, H, 288.0)).moving_sideways  # with the guess
    run = _track_over(pan, tmp_path, monkeypatch, focal=False)
    cm = run["camera_motion"]
    # five frame pairs of an encoded video, mostly floor: within 5 % (the guess is 33 % short)
    assert run["camera"]["fx"] == pytest.approx(true, rel=0.05) and cm["focal"]["applied"] is True
    assert not cm["moving_sideways"] and cm["turn_deg_end"] == pytest.approx(10.0, rel=0.05)
    assert "the background's turns give its focal length: 4" in capsys.readouterr().out


def test_a_run_on_a_zooming_camera_says_so(tmp_path, monkeypatch, capsys):
    """flowmocap track on a video whose camera zooms out 3 % a frame while it pans: run.json's
    camera_motion holds the zoom per frame and the run says what the export frames do with it.
    The scene is one flat picture: its floor's corners fit a move no better than a turn and a
    zoom, so no move is found and the zoom alone is said. Where a floor is taken to move all the
    same (here: the evidence asked for raised), that floor is 65 degrees from the walker's
    upright, so its move is refused and the turn and zoom undone (as on DAVIS with the guessed
    focal length)."""
    from flowmocap.vision import camera_motion as module

    cm = _track_over(Turning(_pan(6, 0.5), zooms=0.97 ** np.arange(6)), tmp_path, monkeypatch)["camera_motion"]
    assert cm["moving"] and cm["zooming"] and len(cm["zooms"]) == 6 and not cm["moving_sideways"]
    np.testing.assert_allclose(cm["zooms"], 0.97 ** np.arange(6), rtol=0.01)
    assert cm["move_share"] is None or cm["move_share"] > module.MOVE_EVIDENCE
    assert "the camera zooms: its focal length goes from 0.86 to 1.00 times the first frame's" in capsys.readouterr().out
    monkeypatch.setattr(module, "MOVE_EVIDENCE", 100.0)  # any move the floor shows is believed
    cm = _track_over(Turning(_pan(6, 0.5), zooms=0.97 ** np.arange(6)), tmp_path / "again", monkeypatch)["camera_motion"]
    assert cm["zooming"] and cm["moving_sideways"]
    said = capsys.readouterr().out
    assert "The background fits a zoom as well (the focal length from 0.86 to 1.00 times the first frame's)" in said
    assert ("the camera's move is not undone: the floor found in the images lies" in said and
            "its turn and zoom are undone instead (the camera's focal length goes from 0.86 to 1.00" in said)


def test_a_run_on_a_carried_camera_says_so(tmp_path, monkeypatch, capsys):
    """flowmocap track on a video whose camera is carried sideways over a floor (6 cm a
    frame, 1.5 m up): run.json's camera_motion holds its move per frame, in units of its
    height, and the floor's normal, and the run says the camera moves and that the export
    frames undo it."""
    scene = Carried(6, (0.06, 0, 0))
    cm = _track_over(scene, tmp_path, monkeypatch)["camera_motion"]
    centre, normal = scene.truth(5)
    assert cm["moving"] and cm["moving_sideways"] and len(cm["shifts"]) == 6
    # five frame pairs of an encoded video and only the floor below the walker's knees: within 15 % and 5 degrees
    assert cm["sideways_max"] == pytest.approx(np.linalg.norm(centre), rel=0.15)
    assert _angle_deg(cm["floor_normal"], normal) < 5.0
    said = capsys.readouterr().out
    assert "shows the camera moving: its centre goes up to 0.2 times its height above the floor" in said
    # the walker pasted in stands upright within 25 degrees of the floor found: the move is undone
    assert "export and view undo the camera's move: it stands" in said


def test_a_result_of_a_turning_camera_is_turned_back_into_the_world(tmp_path):
    """The built-in walk seen by a camera that pans 0.4 degrees a frame after the walker: the fit, in the turning
    camera's frame, walks a curve. With run.json's camera_motion the ground frame turns each
    frame back: the same walk, floor and foot contacts as from a still camera, and each frame's
    camera projects the body onto that frame's pixels."""
    import json

    from flowmocap.commands.view import ViewerData, gl_camera
    from flowmocap.export import export_result, load_fitted_motion
    from flowmocap.io.results import read_result, write_motion, write_run
    from flowmocap.io.smpl_motion import rotate_motion

    from test_ground import _walk_result

    still = tmp_path / "still"
    _walk_result(still, 10.0, height=1.5)
    m = load_fitted_motion(still, frame="world")  # the camera's frame (R = I)
    turns = np.stack(_pan(m.num_frames, -0.4))  # following the walker
    poses, trans = rotate_motion(m.poses, m.trans, m.rest_joints()[0], turns)  # as the turning camera saw it
    arrays, run = read_result(still)
    turned = tmp_path / "turned"
    seen = replace_motion(m, poses, trans)
    j = seen.joints()
    write_motion(turned, {**arrays, "poses": poses.astype(np.float32), "trans": trans.astype(np.float32),
                          "joints3d": j.astype(np.float32), "joints2d": m.camera.project(j).astype(np.float32)})
    rotvecs = Rotation.from_matrix(turns).as_rotvec()
    write_run(turned, {**run, "camera_motion": {"moving": True, "frames": list(range(m.num_frames)),
                                                 "rotvecs": rotvecs.tolist()}})
    a, b = load_fitted_motion(still, frame="ground"), load_fitted_motion(turned, frame="ground")
    np.testing.assert_allclose(b.joints(), a.joints(), atol=2e-4)  # the same walk in the world
    assert b.world.plane.method == "contacts" and (b.world.contacts == a.world.contacts).mean() > 0.95
    for k in (0, 40, m.num_frames - 1):  # each frame's camera puts the body on that frame's pixels
        np.testing.assert_allclose(b.camera_at(k).project(b.joints()[k]), m.camera.project(j[k]), atol=0.05)
    np.testing.assert_allclose(b.joints2d, m.camera.project(j), atol=0.05)
    # told nothing, the ground frame is the turning camera's: the walk bends by 30 degrees
    write_run(turned, run)
    c = load_fitted_motion(turned, frame="ground")
    assert c.turns is None and np.abs(c.joints() - a.joints()).max() > 0.3
    # the exports and the page carry each frame's camera
    write_run(turned, {**run, "camera_motion": {"moving": True, "frames": list(range(m.num_frames)),
                                                 "rotvecs": rotvecs.tolist()}})
    frames = json.loads(export_result(turned, "json", out=tmp_path / "m.json").read_text())["frames"]
    np.testing.assert_allclose(frames[40]["camera_R"], b.camera_at(40).R, atol=1e-6)
    data = ViewerData(turned)
    meta = data.meta()
    assert len(meta["gl_cameras"]) == m.num_frames
    np.testing.assert_allclose(meta["gl_cameras"][0], gl_camera(b.camera)["matrix_world"], atol=1e-6)
    assert ViewerData(still).meta()["gl_cameras"] is None
    # late in the pan the page draws the body where that frame's camera sees it
    own, first = _page_overlay(data, 40, [data.motion.camera_at(40), data.motion.camera], tmp_path)
    assert own > 0.85 and first < 0.5, (own, first)


def _page_overlay(data, k: int, cameras, tmp_path) -> list[float]:
    """The viewer's overlay of page frame ``k`` in headless Chromium against the body seen by
    each of ``cameras`` (``test_view._overlay_iou``; a small body, 100 px tall in 320 x 240);
    skipped where Chromium is not installed."""
    from test_view import _chromium, _overlay_iou, _serving

    if _chromium() is None:
        pytest.skip("chromium is not installed (apt-get install chromium); the viewer's browser test needs it")
    out = None
    for _, url in _serving(data):  # served while the loop runs, shut down after it
        out = _overlay_iou(data, url, k, tmp_path, cameras, min_share=0.01)
    return out


def test_a_result_of_a_zooming_camera_is_brought_back_to_its_depth(tmp_path):
    """The built-in walk seen by a camera that pans 0.2 degrees a frame and zooms out 0.5 % a
    frame (to 0.69 of its focal length): the tracker, keeping the first focal length, puts the
    walker further away frame by frame (1.45x at the end). With run.json's zooms the ground
    frame brings each frame's body to the depth its focal length gives and turns it back: the still camera's
    walk. Each frame's camera (its focal length zoomed) sees the body where the tracker did, the
    exports carry the focal lengths and the page each frame's projection."""
    import json

    from flowmocap.commands.view import ViewerData
    from flowmocap.export import export_result, load_fitted_motion
    from flowmocap.export.gltf_skin import read_skinned_glb
    from flowmocap.export.motion import zoomed_depth
    from flowmocap.io.results import read_result, write_motion, write_run
    from flowmocap.io.smpl_motion import rotate_motion

    from test_ground import _walk_result

    still = tmp_path / "still"
    _walk_result(still, 10.0, height=1.5)
    m = load_fitted_motion(still, frame="world")  # the camera's frame (R = I)
    T = m.num_frames
    turns, zooms = np.stack(_pan(T, -0.2)), 0.995 ** np.arange(T)
    poses, trans = rotate_motion(m.poses, m.trans, m.rest_joints()[0], turns)  # as the turning camera saw it
    trans = zoomed_depth(m.model, m.betas, trans, np.eye(3), np.zeros(3), 1.0 / zooms)  # and the tracker placed it
    seen = replace_motion(m, poses, trans)
    j = seen.joints()
    assert j[-1, 0, 2] / (m.joints()[-1, 0] @ turns[-1].T)[2] == pytest.approx(1 / zooms[-1])
    arrays, run = read_result(still)
    zoomed = tmp_path / "zoomed"
    write_motion(zoomed, {**arrays, "poses": poses.astype(np.float32), "trans": trans.astype(np.float32),
                          "joints3d": j.astype(np.float32), "joints2d": m.camera.project(j).astype(np.float32)})
    cm = {"moving": True, "frames": list(range(T)), "rotvecs": Rotation.from_matrix(turns).as_rotvec().tolist(),
          "zooms": zooms.tolist()}
    write_run(zoomed, {**run, "camera_motion": cm})
    a, b = load_fitted_motion(still, frame="ground"), load_fitted_motion(zoomed, frame="ground")
    np.testing.assert_allclose(b.zooms, zooms)
    np.testing.assert_allclose(b.joints(), a.joints(), atol=2e-4)  # the same walk in the world
    for k in (0, 40, T - 1):  # each frame's camera sees the body where the tracker did: the root exactly
        np.testing.assert_allclose(b.camera_at(k).project(b.joints()[k, :1]), m.camera.project(j[k, :1]), atol=1e-3)
        np.testing.assert_allclose(b.camera_at(k).project(b.joints()[k]), m.camera.project(j[k]), atol=2.0)
    # told only the turn, the walker walks away from the camera
    write_run(zoomed, {**run, "camera_motion": {**cm, "zooms": None}})
    c = load_fitted_motion(zoomed, frame="ground")
    assert c.zooms is None and np.abs(c.joints() - a.joints()).max() > 1.5
    write_run(zoomed, {**run, "camera_motion": cm})
    frames = json.loads(export_result(zoomed, "json", out=tmp_path / "m.json").read_text())["frames"]
    assert frames[40]["camera_focal_px"] == pytest.approx([F * zooms[40]] * 2, rel=1e-6)
    extras = read_skinned_glb(export_result(zoomed, "glb", out=tmp_path / "m.glb"))[0].scenes[0].extras
    np.testing.assert_allclose(extras["camera_zooms"], zooms, atol=1e-6)
    meta = ViewerData(zoomed).meta()
    assert len(meta["gl_projections"]) == T and meta["gl_projections"][0] == pytest.approx(meta["gl_camera"]["projection"])
    assert meta["gl_projections"][-1][0] == pytest.approx(meta["gl_camera"]["projection"][0] * zooms[-1])
    assert ViewerData(still).meta()["gl_projections"] is None
    write_run(zoomed, {**run, "camera_motion": {**cm, "zooms": cm["zooms"][:-1]}})
    from flowmocap.errors import DataError

    with pytest.raises(DataError, match="different number of frames and zooms"):
        load_fitted_motion(zoomed, frame="ground")
    from dataclasses import replace

    write_run(zoomed, {**run, "camera_motion": cm})
    data = ViewerData(zoomed)
    unzoomed = replace(data.motion, zooms=None).camera_at(60)  # that frame's turn, the first focal length
    # late in the zoom the page draws the body with that frame's focal length
    own, first = _page_overlay(data, 60, [data.motion.camera_at(60), unzoomed], tmp_path)
    assert own > 0.85 and first < 0.7, (own, first)


def replace_motion(m, poses, trans):
    from dataclasses import replace

    return replace(m, poses=poses, trans=trans)


def test_rotate_motion_turns_each_frame_by_its_own_rotation():
    """rotate_motion with (T, 3, 3): each frame's joints turned about the origin by its own
    rotation, exactly; the same rotation for all is the (3, 3) call."""
    import torch

    from flowmocap.body import load_body_model
    from flowmocap.io.smpl_motion import rotate_motion

    model = load_body_model("default")
    rng = np.random.default_rng(2)
    T = 4
    poses, trans = rng.normal(0, 0.3, (T, 72)), rng.normal(0, 1.0, (T, 3))
    betas = torch.zeros(1, 10, dtype=torch.float64)

    def joints(p, t):
        with torch.no_grad():
            return model(betas=betas, pose=torch.as_tensor(p), trans=torch.as_tensor(t)).joints.double().numpy()

    with torch.no_grad():
        J0 = model(betas=betas).rest_joints[0, 0].double().numpy()
    W = Rotation.from_rotvec(rng.normal(0, 1.0, (T, 3))).as_matrix()
    p, t = rotate_motion(poses, trans, J0, W)
    np.testing.assert_allclose(joints(p, t), np.einsum("tij,tnj->tni", W, joints(poses, trans)), atol=1e-6)
    same = rotate_motion(poses, trans, J0, np.repeat(W[:1], T, 0))
    one = rotate_motion(poses, trans, J0, W[0])
    np.testing.assert_allclose(same[0], one[0], atol=1e-12)
    np.testing.assert_allclose(same[1], one[1], atol=1e-12)


# --- a camera that moves: the floor's corners ---------------------------------------------

def Carried(n, velocity, yaw=0.0, pitch=15.0, zoom=1.0):
    """A camera 1.5 m above a textured floor, pitched down ``pitch`` degrees, moving ``velocity``
    m a frame, turning ``yaw`` degrees a frame and zooming by ``zoom`` a frame
    (:class:`flowmocap.synth.carried.CarriedCamera`)."""
    from flowmocap.synth.carried import CarriedCamera

    return CarriedCamera(n, velocity, yaw, K=K, size=(W, H), pitch_deg=pitch, zoom=zoom)


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


@pytest.mark.parametrize("velocity, yaw, pitch, path_share, turn_deg", [
    ((0.05, 0, 0), 0.0, 15.0, 0.05, 0.5), ((0.03, 0, 0.03), -0.4, 15.0, 0.05, 0.5),
    ((0.05, 0, 0), 0.0, 30.0, 0.08, 1.5)])
def test_a_camera_carried_over_a_floor_is_found_to_move_by_that(velocity, yaw, pitch, path_share, turn_deg):
    """A dolly sideways, one diagonal while it turns, and a dolly looking down 30 degrees (the
    near floor too smooth for the background's corners: weaker ones are taken): the floor's
    normal within 2 degrees, the camera's path within 5 % of its length (in units of its height
    above the floor) and the floor's turn within 0.5 degrees; looking down 8 % and 1.5 degrees
    (measured over these 20 frames: 6 % and 0.95 degrees)."""
    scene = Carried(20, velocity, yaw, pitch)
    got = camera_motion(scene, CAM)
    centre, normal = scene.truth(19)
    assert got.moving and got.moving_sideways and not got.floor_unknown
    assert _angle_deg(got.floor_normal, normal) < 2.0
    assert np.linalg.norm(got.centres()[-1] - centre) < path_share * np.linalg.norm(centre)
    np.testing.assert_allclose(got.centres()[0], 0.0, atol=1e-12)
    turned = np.degrees(np.linalg.norm(Rotation.from_matrix(got.floor_rotations[-1]).as_rotvec()))
    assert turned == pytest.approx(abs(yaw) * 19, abs=turn_deg)  # the floor's turn (the whole background's is bent)
    assert got.sideways == pytest.approx(np.linalg.norm(centre), rel=path_share)
    doc = got.to_dict(rotations=True)
    assert doc["moving_sideways"] and len(doc["shifts"]) == len(doc["floor_rotvecs"]) == 20
    assert 0.0 <= doc["move_share"] < 0.1  # the move explains the floor's corners far better than a turn alone
    assert len(doc["floor_normal"]) == 3


def test_a_floor_that_does_not_move_shows_no_move_whatever_its_homography():
    """A still floor's homography is fitted to noise and can decompose into any move (one
    pair of a still real3d camera, its corners 0.004 px apart, did). A pair is taken to show a
    move only where its corners move by at least MOVE_MIN_PX (median); the same homography
    with corners that do move is taken."""
    from flowmocap.vision.camera_motion import MOVE_MIN_PX, _moving_pairs

    n = np.array([0.0, np.cos(np.radians(15)), np.sin(np.radians(15))])  # down to the floor, pitched 15 degrees
    turn = Rotation.from_euler("y", 0.5, degrees=True).as_matrix()
    Hm = K @ (turn + np.outer([0.05, 0, 0.02], n)) @ np.linalg.inv(K)  # a move of 5 % sideways, 2 % forward
    rng = np.random.default_rng(0)
    a = np.c_[rng.uniform(0, W, 50), rng.uniform(150, H, 50)]
    moved = np.c_[a, np.ones(len(a))] @ Hm.T
    moved = moved[:, :2] / moved[:, 2:]
    chain = np.eye(3)[None]
    assert _moving_pairs([(a, moved, Hm)], chain, K) == [0]
    still = a + rng.normal(0, 0.003, a.shape)
    assert np.median(np.linalg.norm(still - a, axis=1)) < MOVE_MIN_PX
    assert _moving_pairs([(a, still, Hm)], chain, K) == []


@pytest.mark.parametrize("w", [(0.1, -0.2, 0.05), (2.0, 0.5, -1.0), (1e-6, 0.0, 2e-6), (0.0, 0.0, 0.0)])
def test_the_exponential_map_and_its_right_jacobian_against_scipy_and_finite_differences(w):
    """``_exp_so3``: the rotation is scipy's (Rodrigues) and ``J_r`` satisfies ``exp(w + d) =
    exp(w) exp(J_r d)`` to first order (central differences of ``log(exp(w)^T exp(w + d))``)."""
    from flowmocap.vision.camera_motion import _exp_so3

    w = np.asarray(w, np.float64)
    R, Jr = _exp_so3(w)
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-15)
    h = 1e-6
    numeric = np.stack([(Rotation.from_matrix(R.T @ Rotation.from_rotvec(w + h * e).as_matrix()).as_rotvec()
                         - Rotation.from_matrix(R.T @ Rotation.from_rotvec(w - h * e).as_matrix()).as_rotvec())
                        / (2 * h) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(Jr, numeric, atol=1e-8)


def test_the_background_turn_and_zoom_fit_is_the_floor_fits_model_without_a_move():
    """The background's turn and zoom (:func:`_turn_zoom_fit`, fitted with the floor fit's
    residuals and closed-form Jacobian, ``move`` off and ``zoom`` on) puts the corners where its
    own ``moved()`` does, for intrinsics with a principal point off the image's middle; and it
    finds a known turn and zoom from the corners they move."""
    from scipy.spatial.transform import Rotation

    from flowmocap.vision.camera_motion import _pair_residual, _rays, _turn_zoom_fit

    Kc = np.array([[260.0, 0.0, 150.0], [0.0, 260.0, 110.0], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(3)
    a = rng.uniform([0, 0], [320, 240], (40, 2))
    w, z = np.array([0.01, -0.02, 0.005]), 0.97
    R = Rotation.from_rotvec(w).as_matrix()
    H = Kc @ np.diag([z, z, 1.0]) @ R @ np.linalg.inv(Kc)  # Z about the principal point, in normalised coordinates
    p = np.c_[a, np.ones(len(a))] @ H.T
    b = p[:, :2] / p[:, 2:3]
    M = np.diag([z, z, 1.0]) @ R
    x, cost, moved = _turn_zoom_fit(a, b, M / np.cbrt(np.linalg.det(M)), Kc)
    np.testing.assert_allclose(x, np.r_[w, np.log(z)], atol=1e-9)
    assert cost < 1e-12
    probe = np.r_[w + 0.01, np.log(z) - 0.02]
    np.testing.assert_allclose(_pair_residual(probe, _rays(Kc, a), b, Kc, np.zeros(3), False, True),
                               (moved(probe, _rays(Kc, a)) - b).ravel(), atol=1e-9)


@pytest.mark.parametrize("zoom", [False, True])
@pytest.mark.parametrize("move", [True, False])
@pytest.mark.parametrize("x", [(0.1, -0.2, 0.05, 0.02, -0.01, 0.03, 0.05), (1e-7, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                               (0.3, 0.2, -0.1, 0.2, 0.1, -0.1, -0.2)])
def test_the_floor_pairs_jacobian_against_finite_differences(move, zoom, x):
    """The floor fit's residuals (pixels) carried through ``Z K (R + tau n^T)``: the closed-form
    Jacobian by the turn's rotation vector, the move and the zoom's log equals central differences."""
    from flowmocap.vision.camera_motion import _pair_jacobian, _pair_residual

    rng = np.random.default_rng(1)
    rays = np.c_[rng.uniform(-0.5, 0.5, (25, 2)), np.ones(25)]
    b = rng.uniform(0, 320, (25, 2))
    n = np.array([0.0, np.cos(np.radians(15)), np.sin(np.radians(15))])
    x = np.asarray((x[:6] if move else x[:3]) + (x[6:] if zoom else ()), np.float64)
    J = _pair_jacobian(x, rays, K, n, move, zoom)
    h = 1e-6
    numeric = np.stack([(_pair_residual(x + h * e, rays, b, K, n, move, zoom)
                         - _pair_residual(x - h * e, rays, b, K, n, move, zoom)) / (2 * h) for e in np.eye(len(x))], axis=1)
    assert J.shape == (50, (6 if move else 3) + zoom)
    np.testing.assert_allclose(J, numeric, rtol=1e-6, atol=1e-6 * np.abs(numeric).max())


def test_a_camera_that_only_turns_over_a_floor_does_not_move():
    """Over the same floor, a camera that pans and one that stands still: no move is made up
    (the floor's corners are no better explained with one), and the turn is the background's."""
    pan = camera_motion(Carried(15, (0, 0, 0), 0.5), CAM)
    assert pan.turning and not pan.moving_sideways and pan.shifts is None
    assert not pan.move_share <= 0.7  # NaN (no pair shows a move) or a move that explains little
    assert pan.turn_deg[-1] == pytest.approx(7.0, rel=0.05)
    still = camera_motion(Carried(10, (0, 0, 0)), CAM)
    assert not still.moving and not still.moving_sideways
    assert not camera_motion(Carried(10, (0.05, 0, 0)), CAM, sideways=False).moving_sideways


class PasserBy:
    """A still camera over the floor while someone walks past it near the camera: a textured
    block 100 x 90 px at the bottom of the frame moving right 5 px a frame, not the tracked
    person (no ``masks``), with their pixels as the detector stores them (``people``)."""

    masks = camera = None

    def __init__(self, frames: int):
        import cv2

        from flowmocap.synth.carried import floor_texture

        self.scene, self.n = Carried(frames, (0, 0, 0)), frames
        self.tex = cv2.GaussianBlur(floor_texture(seed=3, size=150)[:90, :100], (0, 0), 0.5)

    def __len__(self):
        return self.n

    def _box(self, i):
        return 20 + 5 * i, H - 95, min(W, 120 + 5 * i), H - 5

    def frame(self, i):
        img = self.scene.frame(i).copy()
        x0, y0, x1, y1 = self._box(i)
        img[y0:y1, x0:x1] = self.tex[:, :x1 - x0]
        return img

    def people(self, i):
        m = np.zeros((H, W), bool)
        x0, y0, x1, y1 = self._box(i)
        m[y0:y1, x0:x1] = True
        return m


@pytest.mark.parametrize("zoom, yaw", [(0.99, 0.5), (1.01, 0.0)])
def test_a_camera_on_a_tripod_that_zooms_over_a_floor_does_not_move(zoom, yaw):
    """A zoom moves a floor's corners much as a move forward does, and a floor fitted with one
    focal length took a tripod's zoom for a move of 0.26-0.33 of the camera's height, strongly
    believed (the move left 1 % of a turn's cost). Against a turn and a zoom it explains
    nothing (docs/experiments.md, "A zoom over a floor taken for a move"); the zoom is the
    background's."""
    got = camera_motion(Carried(20, (0, 0, 0), yaw, zoom=zoom), CAM)
    assert not got.moving_sideways and got.shifts is None
    assert not got.move_share <= 0.7  # NaN (no pair shows a move) or a move that explains less than a zoom
    assert got.zooms[-1] == pytest.approx(zoom ** 19, rel=0.02)


def test_a_camera_moving_forward_is_still_found_to_move_though_it_looks_like_a_zoom():
    """A move forward over a floor looks like a zoom to the background (its corners spread out),
    but the near floor moves more than the far one, which no zoom does: the move is still found."""
    scene = Carried(20, (0, 0, 0.05), 0.3)
    got = camera_motion(scene, CAM)
    centre, _ = scene.truth(19)
    assert got.moving_sideways and got.move_share < 0.3
    assert got.zooms.max() > 1.1  # the background takes it for a zoom
    assert np.linalg.norm(got.centres()[-1] - centre) < 0.08 * np.linalg.norm(centre)


def test_someone_walking_past_is_left_out_of_the_cameras_motion():
    """Someone else crossing the floor below the camera moves like the floor would under a
    camera carried the other way: taken for background, the still camera is found to turn and
    zoom (by 6 %; a camera that zooms is not searched for a move). With everyone else's pixels
    left out (the detector's ``people``), it stands still."""
    scene = PasserBy(30)
    fooled = camera_motion(scene, CAM, masks=False)
    assert fooled.moving and fooled.zooming
    still = camera_motion(scene, CAM, masks=False, others=scene.people)
    assert not still.moving and not still.moving_sideways and not still.zooming and still.turn_deg.max() < 0.1
    assert np.abs(still.zooms - 1).max() < 0.002


def _carried_walk(still, carried):
    """The built-in walk written to ``still`` and, as seen by a camera carried along beside
    the walker (1.4 m up, 1.2 m a second sideways, turning 0.2 degrees a frame), to
    ``carried`` with the camera's motion in run.json. Returns ``(R, m, j, run, cm)``: the walk's
    world rotation, the still motion (camera frame), the carried camera's joints, the still
    run.json and the carried one's ``camera_motion``."""
    from flowmocap.export import load_fitted_motion
    from flowmocap.io.results import read_result, write_motion, write_run
    from flowmocap.io.smpl_motion import rotate_motion

    from test_ground import _walk_result

    R, _, _, _ = _walk_result(still, 10.0, height=1.4)
    m = load_fitted_motion(still, frame="world")  # the camera's frame (R = I)
    T = m.num_frames
    turns = np.stack(_pan(T, 0.2))
    world_move = np.outer(np.arange(T), [0.04, 0.0, 0.0])  # the camera's centre, the walk's world axes
    shifts = -np.einsum("tij,jk,tk->ti", turns, R, world_move)  # x_t = turns_t x_0 + shifts_t
    poses, trans = rotate_motion(m.poses, m.trans, m.rest_joints()[0], turns)
    trans = trans + shifts
    seen = replace_motion(m, poses, trans)
    j = seen.joints()
    assert np.ptp(j[:, 0, 0]) < 0.5 * np.ptp(m.joints()[:, 0, 0])  # the carried camera keeps the walker in view
    arrays, run = read_result(still)
    write_motion(carried, {**arrays, "poses": poses.astype(np.float32), "trans": trans.astype(np.float32),
                           "joints3d": j.astype(np.float32), "joints2d": m.camera.project(j).astype(np.float32)})
    rotvecs = Rotation.from_matrix(turns).as_rotvec().tolist()
    cm = {"moving": True, "frames": list(range(T)), "rotvecs": np.zeros((T, 3)).tolist(), "floor_rotvecs": rotvecs,
          "shifts": (shifts / 1.4).tolist(), "floor_normal": (R @ [0, -1.0, 0]).tolist(), "moving_sideways": True}
    write_run(carried, {**run, "camera_motion": cm})
    return R, m, j, run, cm


def _tilted(R, deg=40.0):
    """A floor normal the images made up: ``deg`` from the walk's (world rotation ``R``) down."""
    return (Rotation.from_rotvec([np.radians(deg), 0, 0]).as_matrix() @ R @ [0, -1.0, 0]).tolist()


def test_a_result_of_a_carried_camera_is_moved_back_into_the_world(tmp_path):
    """The built-in walk seen by a camera carried along beside the walker (1.4 m up, 1.2 m a
    second sideways, turning 0.2 degrees a frame): in the carried camera's frame the walker
    walks nearly on the spot. With run.json's camera_motion (the move in units of the camera's
    height, the floor's normal) the ground frame finds the camera's height from the feet, moves
    each frame back and gives the still camera's walk; each frame's camera projects the body
    onto that frame's pixels, and the exports and the page carry it."""
    import json

    from flowmocap.commands.view import ViewerData
    from flowmocap.export import export_result, load_fitted_motion
    from flowmocap.io.results import write_run

    still, carried = tmp_path / "still", tmp_path / "carried"
    R, m, j, run, cm = _carried_walk(still, carried)
    T = m.num_frames
    rotvecs = cm["floor_rotvecs"]
    a, b = load_fitted_motion(still, frame="ground"), load_fitted_motion(carried, frame="ground")
    assert b.camera_height_m == pytest.approx(1.4, abs=0.01)
    np.testing.assert_allclose(b.joints(), a.joints(), atol=0.02)  # the same walk in the world
    assert b.world.plane.method == "contacts" and (b.world.contacts == a.world.contacts).mean() > 0.9
    for k in (0, 40, T - 1):  # each frame's camera puts the body on that frame's pixels
        np.testing.assert_allclose(b.camera_at(k).project(b.joints()[k]), m.camera.project(j[k]), atol=0.05)
    assert b.camera_move_refused is None
    # stood on another person's floor (export_people): scaled about the camera, the whole world
    # scales, the camera's path with it, and each frame's camera still sees the body where it did
    from flowmocap.export.floor import scaled_about_camera

    big = scaled_about_camera(b, 1.25)
    np.testing.assert_allclose(big.shifts, 1.25 * b.shifts, rtol=1e-12)
    assert big.camera_height_m == pytest.approx(1.25 * b.camera_height_m)
    for k in (0, 40, T - 1):
        np.testing.assert_allclose(big.camera_at(k).project(big.joints()[k, :1]),
                                   b.camera_at(k).project(b.joints()[k, :1]), atol=1e-3)  # the root, exactly
        np.testing.assert_allclose(big.joints2d[k], b.camera_at(k).project(b.joints()[k]), atol=3.0)
    # told only the turn, the walker stays near the spot
    write_run(carried, {**run, "camera_motion": {**cm, "rotvecs": rotvecs, "shifts": None}})
    c = load_fitted_motion(carried, frame="ground")
    assert c.shifts is None and np.abs(c.joints() - a.joints()).max() > 1.0
    # a floor the images made up, 40 degrees from the walker's upright: its move is refused and
    # the background's turn (here none) is all that is undone
    write_run(carried, {**run, "camera_motion": {**cm, "floor_normal": _tilted(R)}})
    d = load_fitted_motion(carried, frame="ground")
    assert d.shifts is None and d.camera_height_m is None
    assert "from the body's upright direction" in d.camera_move_refused
    np.testing.assert_allclose(d.turns, np.eye(3)[None].repeat(T, 0), atol=1e-12)
    write_run(carried, {**run, "camera_motion": cm})
    frames = json.loads(export_result(carried, "json", out=tmp_path / "m.json").read_text())["frames"]
    np.testing.assert_allclose(frames[40]["camera_t"], b.camera_at(40).t, atol=1e-6)
    from flowmocap.export.gltf_skin import read_skinned_glb

    extras = read_skinned_glb(export_result(carried, "glb", out=tmp_path / "m.glb"))[0].scenes[0].extras
    np.testing.assert_allclose(extras["camera_shifts_m"], b.shifts, atol=1e-6)
    assert extras["camera_height_m"] == pytest.approx(b.camera_height_m, abs=1e-4)
    gl = ViewerData(carried).meta()["gl_cameras"]
    centre = lambda g: np.asarray(g).reshape(4, 4).T[:3, 3]  # noqa: E731 -- column-major eye-to-world
    assert len(gl) == T and np.linalg.norm(centre(gl[-1]) - centre(gl[0])) == pytest.approx(
        0.04 * (T - 1), rel=0.02)  # the page's camera moves with the camera
    broken = {**cm, "shifts": cm["shifts"][:-1]}
    write_run(carried, {**run, "camera_motion": broken})
    from flowmocap.errors import DataError

    with pytest.raises(DataError, match="different number of frames and moves, or no floor normal or turns"):
        load_fitted_motion(carried, frame="ground")
    write_run(carried, {**run, "camera_motion": cm})
    data = ViewerData(carried)
    # late in the move the page draws the body where that frame's camera sees it
    own, first = _page_overlay(data, 60, [data.motion.camera_at(60), data.motion.camera], tmp_path)
    assert own > 0.85 and first < 0.5, (own, first)


def test_the_people_of_a_carried_camera_have_its_move_undone_alike(tmp_path):
    """Two people of one carried camera (here the same walk twice, so each should come out where
    the other does), each run with its own floor: person1's floor disagrees with its upright
    body, so alone its move would be refused while person0's is undone. In the people folder
    the camera's move is undone for both as for the person whose floor is shared, in the
    floor's fits, the page and the exports; not for a person tracked past the frames that
    person's run found the move in; where that person's own floor disagrees, it is undone for
    nobody. Exported in the owner's "world" frame (nothing turned back), no person
    is turned back either."""
    import json
    import shutil

    from flowmocap.commands.view import ViewerData
    from flowmocap.export import export_people, load_fitted_motion
    from flowmocap.export.floor import people_floor
    from flowmocap.io.results import write_run

    root = tmp_path / "people"
    R, m, j, run, cm = _carried_walk(tmp_path / "still", root / "person0")
    shutil.copytree(root / "person0", root / "person1")
    (root / "people.json").write_text(json.dumps({"input": "missing", "people": {
        "person0": {"rank": 0, "tracked": True}, "person1": {"rank": 1, "tracked": True}}}))
    write_run(root / "person1", {**run, "camera_motion": {**cm, "floor_normal": _tilted(R)}})
    alone = load_fitted_motion(root / "person1", frame="ground")
    assert alone.shifts is None and "upright" in alone.camera_move_refused  # alone: refused
    first = load_fitted_motion(root / "person0", frame="ground")
    fits = people_floor([root / "person0", root / "person1"])
    assert fits[0].camera_move is None and fits[1].scale == pytest.approx(1.0, abs=0.01)
    assert fits[1].camera_move.startswith("undone as for the person whose floor is shared")
    assert "camera's move undone" in fits[1].describe("person1", "person0")
    data = ViewerData(root)
    both = [p["motion"] for p in data.people]
    assert both[1].shifts is not None
    np.testing.assert_allclose(both[1].joints(), first.joints(), atol=0.02)  # the same walk, one world
    assert np.abs(alone.joints() - first.joints()).max() > 1.0  # as it was alone: left on the spot
    log = []
    paths = export_people(root, "json", log=log.append)
    assert any("undone as for" in line for line in log)
    assert json.loads((paths[1].parent / "floor.json").read_text())["people"]["person1"]["camera_move"]
    exported = [json.loads(p.read_text())["frames"] for p in paths]
    for k in (0, 40, m.num_frames - 1):
        np.testing.assert_allclose(exported[1][k]["joints3d"], exported[0][k]["joints3d"], atol=0.02)
        np.testing.assert_allclose(exported[1][k]["camera_t"], exported[0][k]["camera_t"], atol=0.02)
    # the owner's run found the move only up to 10 frames before person1's last: not undone for person1
    short = {k: (v[:-10] if isinstance(v, list) and len(v) == m.num_frames else v) for k, v in cm.items()}
    write_run(root / "person0", {**run, "camera_motion": short})
    fits = people_floor([root / "person0", root / "person1"])
    assert fits[1].camera_move.startswith(f"not undone: the move was found up to frame {m.num_frames - 11}")
    # the owner's floor disagrees and person1's agrees: undone for nobody
    write_run(root / "person0", {**run, "camera_motion": {**cm, "floor_normal": _tilted(R)}})
    write_run(root / "person1", {**run, "camera_motion": cm})
    fits = people_floor([root / "person0", root / "person1"])
    assert fits[1].camera_move.startswith("not undone: the person whose floor and frame are shared did not have it")
    data = ViewerData(root)
    assert all(p["motion"].shifts is None for p in data.people)
    # the owner's own world frame: nobody turned back (each at their own size: nothing else moves them)
    world = [json.loads(p.read_text())["frames"] for p in export_people(root, "json", frame="world", floor=False)]
    own = load_fitted_motion(root / "person1", frame="world").joints()
    np.testing.assert_allclose(world[1][40]["joints3d"], own[40], atol=1e-4)
    np.testing.assert_allclose(world[1][40]["joints3d"], world[0][40]["joints3d"], atol=1e-4)


def test_the_floor_is_looked_for_about_the_persons_feet():
    """floor_region: the rows below the person's lowest pixel less a tenth of their height, or
    without a person the lowest 40 % of the image."""
    from flowmocap.vision.camera_motion import floor_region

    mask = np.zeros((H, W), bool)
    mask[50:151, 100:140] = True  # rows 50-150: 100 px tall
    region = floor_region((H, W, 3), mask)
    assert region.shape == (H, W) and region[140:].all() and not region[:140].any()
    bare = floor_region((H, W, 3), None)
    assert bare[144:].all() and not bare[:144].any()
    np.testing.assert_array_equal(floor_region((H, W), np.zeros((H, W), bool)), bare)


def test_a_rendered_wall_given_its_facing_stays_put_while_the_camera_pans():
    """The synthetic scene's wall faces the camera's viewing direction unless told where it is
    (benchmarks/panned_walk.py tells it): a camera turned 3 degrees about the vertical over
    that fixed wall and floor is found to turn by that; with the wall turning with it, the
    background's corners (mostly the wall's) show almost none of the turn."""
    from flowmocap.synth.scene import render_background

    flip, centre = np.diag([-1.0, -1.0, 1.0]), np.array([0.0, 1.5, 0.0])  # y up to y down; 1.5 m above the floor
    pitch = Rotation.from_euler("x", 10.0, degrees=True).as_matrix()
    Rs = [pitch @ Rotation.from_euler("y", yaw, degrees=True).as_matrix() @ flip for yaw in (0.0, 3.0)]
    cams = [PinholeCamera(fx=F, fy=F, cx=W / 2, cy=H / 2, width=W, height=H, R=R, t=-R @ centre) for R in Rs]
    ahead = np.array([0.0, 0.0, 1.0])
    fixed = [render_background(c, supersample=1, wall_distance=3.0, wall_facing=ahead) for c in cams]
    R, residual = frame_rotation(fixed[0], fixed[1], K)
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(R).as_rotvec())) == pytest.approx(3.0, rel=0.03)
    turning = [render_background(c, supersample=1, wall_distance=3.0) for c in cams]
    got = frame_rotation(turning[0], turning[1], K)
    assert got is None or np.degrees(np.linalg.norm(Rotation.from_matrix(got[0]).as_rotvec())) < 0.5

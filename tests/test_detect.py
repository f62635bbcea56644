"""Person detection: the detector interface, MediaPipe (on a real frame when the shared
data is present), mask cleaning and person continuity."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from flowmocap.vision.detect import KEYPOINT_NAMES, SMPL_KEYPOINTS, Detection, PersonDetector
from flowmocap.vision.person import box_iou, clean_mask, person_box, same_person

DAVIS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "video" / "davis-dance-twirl"


def stick_keypoints(x0, y0, x1, y1) -> np.ndarray:
    """``(K, 2)`` keypoints of an upright person facing the camera inside a box."""
    w, h = x1 - x0, y1 - y0
    cx = (x0 + x1) / 2
    rel = {  # (x offset as a fraction of the width, y as a fraction of the height); left = image right
        "left_hip": (0.12, 0.5), "right_hip": (-0.12, 0.5), "left_knee": (0.12, 0.72),
        "right_knee": (-0.12, 0.72), "left_ankle": (0.12, 0.95), "right_ankle": (-0.12, 0.95),
        "left_shoulder": (0.2, 0.2), "right_shoulder": (-0.2, 0.2), "left_elbow": (0.3, 0.35),
        "right_elbow": (-0.3, 0.35), "left_wrist": (0.32, 0.48), "right_wrist": (-0.32, 0.48),
        "nose": (0.0, 0.08), "left_ear": (0.05, 0.06), "right_ear": (-0.05, 0.06),
    }
    return np.array([[cx + rel[n][0] * w, y0 + rel[n][1] * h] for n in KEYPOINT_NAMES])


class FakeDetector:
    """Person boxes per frame index; the mask is the box (with a speck elsewhere)."""

    name = "fake"

    def __init__(self, boxes: dict, size=(96, 128)):
        self.boxes = boxes
        self.size = size
        self.i = 0

    def reset(self):
        self.i = 0

    def detect(self, image_rgb):
        box = self.boxes.get(self.i)
        self.i += 1
        if box is None:
            return None
        H, W = image_rgb.shape[:2]
        x0, y0, x1, y1 = box
        mask = np.zeros((H, W), bool)
        mask[max(0, y0):y1, max(0, x0):x1] = True
        mask[0:2, 0:2] = True  # a speck far from the person
        kp = stick_keypoints(x0, y0, x1, y1)
        conf = np.where((kp[:, 0] >= 0) & (kp[:, 0] <= W) & (kp[:, 1] >= 0) & (kp[:, 1] <= H), 0.9, 0.0)
        return Detection(kp, conf, mask)


def test_fake_detector_satisfies_the_protocol():
    assert isinstance(FakeDetector({}), PersonDetector)
    assert len(KEYPOINT_NAMES) == 15 and KEYPOINT_NAMES[:12] == SMPL_KEYPOINTS


def test_clean_mask_keeps_the_person():
    H, W = 100, 120
    m = np.zeros((H, W), bool)
    m[20:90, 40:70] = True          # the person
    m[50:54, 50:54] = False         # a small hole (16 px < 1% of the person)
    m[20:90, 72:74] = True          # a cut-off arm next to it
    m[5:8, 5:8] = True              # a speck
    m[20:90, 100:115] = True        # someone else, away from the keypoints
    kp = stick_keypoints(40, 20, 74, 90)
    out = clean_mask(m, kp, np.full(len(kp), 0.9))
    assert out[52, 52] and out[50, 73]
    assert not out[6, 6] and not out[50, 105]
    assert not clean_mask(np.zeros((H, W), bool), kp, np.ones(len(kp))).any()


def test_clean_mask_fills_the_holes_binary_fill_holes_would():
    """The hole filling (one labelling of the background) against its definition with
    scipy's binary_fill_holes: the small enclosed background pieces are filled, the
    large ones and any touching the border are not, on blobby random masks."""
    from scipy import ndimage as ndi

    def reference(out, max_hole_fraction=0.01):
        holes = ndi.binary_fill_holes(out) & ~out
        hl, hn = ndi.label(holes)
        hs = ndi.sum(holes, hl, np.arange(1, hn + 1))
        return out | np.isin(hl, np.nonzero(hs <= max_hole_fraction * out.sum())[0] + 1)

    rng = np.random.default_rng(3)
    H, W = 90, 110
    kp = stick_keypoints(0, 0, W, H)
    filled = 0
    for _ in range(40):
        m = ndi.gaussian_filter(rng.random((H, W)), 2.5) > 0.5  # blobs with holes, some at the border
        m[30:60, 40:70] = True
        m[40:42, 50:52] = False  # a hole of 4 px for sure
        m = ndi.label(m)[0] == ndi.label(m)[0][45, 45]  # one component: clean_mask keeps it whole
        out = clean_mask(m, kp, np.full(len(kp), 0.9))
        np.testing.assert_array_equal(out, reference(m))
        filled += int((out & ~m).sum())
    assert filled > 0


def test_box_continuity():
    a = (10, 10, 30, 70)
    assert box_iou(a, a) == pytest.approx(1.0)
    assert same_person(a, (14, 10, 34, 70))
    assert not same_person(a, (90, 10, 110, 70))
    assert same_person(a, (60, 10, 80, 70), frames_apart=3)  # moving fast over a gap
    assert person_box(np.zeros((3, 2)), np.zeros(3)) is None


@pytest.mark.skipif(not DAVIS.exists(), reason=f"shared data not found at {DAVIS} (real frames for MediaPipe)")
def test_mediapipe_on_a_real_frame():
    from flowmocap.io.sequence import read_image
    from flowmocap.vision.detect import MediaPipePoseDetector
    from flowmocap.vision.masks import load_mask

    img = read_image(DAVIS / "JPEGImages" / "00000.jpg")
    gt = load_mask(DAVIS / "Annotations" / "00000.png")
    det = MediaPipePoseDetector().detect(img)
    assert det is not None and det.mask.shape == gt.shape
    iou = (det.mask & gt).sum() / (det.mask | gt).sum()
    assert iou > 0.75
    ok = det.confidence[:12] > 0.5
    assert ok.sum() >= 10
    xy = det.keypoints[:12][ok].astype(int)
    assert gt[xy[:, 1].clip(0, 479), xy[:, 0].clip(0, 853)].mean() > 0.7  # joints lie on the person
    # 3D joints in metres about the hips, camera axes: the hips ~0.2 m apart, the head above them
    assert det.world is not None and det.world.shape == (len(KEYPOINT_NAMES), 3)
    names = list(KEYPOINT_NAMES)
    hips = det.world[[names.index("left_hip"), names.index("right_hip")]]
    assert np.allclose(hips.mean(0), 0.0, atol=0.05) and 0.1 < np.linalg.norm(hips[0] - hips[1]) < 0.4
    assert det.world[names.index("nose"), 1] < -0.4  # y points down


def test_mediapipe_finds_nobody_in_an_empty_image():
    from flowmocap.vision.detect import MediaPipePoseDetector

    img = np.full((120, 160, 3), 90, np.uint8)
    assert MediaPipePoseDetector(augment=False).detect(img) is None


def test_mediapipe_prints_nothing_to_stderr(capfd):
    """MediaPipe's C++ log lines (TFLite's XNNPACK INFO, absl's W0000 feedback-manager
    warnings) are kept off the terminal: creating, running, resetting and closing."""
    pytest.importorskip("mediapipe")
    from flowmocap.vision.detect import MediaPipePoseDetector

    img = np.full((120, 160, 3), 90, np.uint8)
    det = MediaPipePoseDetector()
    for _ in range(2):
        det.detect(img)
    det.reset()
    det.detect(img)
    det.close()
    assert capfd.readouterr().err == ""


def test_the_heavy_model_ships_whole():
    from flowmocap.vision.detect import HEAVY_MD5, HEAVY_MODEL, _md5

    assert HEAVY_MODEL.is_file() and _md5(HEAVY_MODEL) == HEAVY_MD5


def test_the_heavy_model_is_linked_in_a_temporary_resource_folder(tmp_path, monkeypatch):
    """MediaPipe's legacy Pose reads ``mediapipe/modules/pose_landmark/pose_landmark_heavy.tflite``
    under its resource folder; a temporary one links MediaPipe's own files and the shipped
    model, writes nothing into MediaPipe's folder, and is gone after the block."""
    import os
    import tempfile

    from flowmocap.errors import InputError
    from flowmocap.vision.detect import HEAVY_MODEL, _heavy_resources

    fake = tmp_path / "site"  # a stand-in for site-packages
    (fake / "mediapipe" / "modules" / "pose_landmark").mkdir(parents=True)
    (fake / "mediapipe" / "modules" / "pose_detection").mkdir()
    (fake / "mediapipe" / "python").mkdir()
    (fake / "mediapipe" / "modules" / "pose_landmark" / "pose_landmark_cpu.binarypb").write_bytes(b"graph")
    (fake / "mediapipe" / "modules" / "pose_landmark" / "pose_landmark_heavy.tflite").write_bytes(b"old download")
    before = sorted(str(p) for p in fake.rglob("*"))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    cleanups = []
    monkeypatch.setattr("atexit.register", lambda f, *a: cleanups.append((f, a)))
    root = _heavy_resources(fake)
    pl = root / "mediapipe" / "modules" / "pose_landmark"
    assert (pl / "pose_landmark_heavy.tflite").resolve() == HEAVY_MODEL.resolve()
    assert (pl / "pose_landmark_cpu.binarypb").read_bytes() == b"graph"
    assert (root / "mediapipe" / "python").resolve() == (fake / "mediapipe" / "python").resolve()
    assert (root / "mediapipe" / "modules" / "pose_detection").resolve() == (
        fake / "mediapipe" / "modules" / "pose_detection").resolve()
    assert sorted(str(p) for p in fake.rglob("*")) == before  # MediaPipe's folder untouched
    for f, a in cleanups:  # as when the process ends
        f(*a)
    assert not root.exists() and not os.listdir(tmp_path / "tmp")
    monkeypatch.setattr(tempfile, "mkdtemp", lambda **kw: (_ for _ in ()).throw(PermissionError(13, "denied")))
    with pytest.raises(InputError, match="set TMPDIR to a writable folder, or use the detector model 'full'"):
        _heavy_resources(fake)


def test_a_resource_folder_a_killed_process_left_is_removed_by_the_next(tmp_path, monkeypatch):
    # cleaned at exit only: a detector process ended by SIGTERM (its parent gone) left its folder behind
    import os
    import subprocess
    import sys
    import tempfile

    from flowmocap.vision import detect

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead = tmp_path / f"flowmocap-mediapipe-{int(gone.stdout)}-abc"
    alive = tmp_path / f"flowmocap-mediapipe-{os.getpid()}-def"
    other = tmp_path / "flowmocap-mediapipe-notapid-x"
    for d in (dead, alive, other):
        (d / "mediapipe").mkdir(parents=True)
    detect._drop_dead_resources()
    assert not dead.exists() and alive.exists() and other.exists()


def test_check_model_files_refuses_what_cannot_run(tmp_path, monkeypatch):
    from flowmocap.errors import InputError
    from flowmocap.vision import detect

    with pytest.raises(InputError, match="unknown detector model 'huge'"):
        detect.check_model_files("huge")
    detect.check_model_files("full")
    detect.check_model_files("heavy")
    monkeypatch.setattr(detect, "HEAVY_MODEL", tmp_path / "missing.tflite")
    monkeypatch.setattr(detect, "_SHIPPED_OK", [])
    with pytest.raises(InputError, match="missing or damaged; reinstall flowmocap"):
        detect.check_model_files("heavy")
    detect.check_model_files("full")


@pytest.mark.skipif(not DAVIS.exists(), reason=f"shared data not found at {DAVIS} (real frames for MediaPipe)")
def test_the_heavy_graph_reads_the_shipped_model_and_leaves_mediapipes_folder_alone(monkeypatch):
    # the shipped file was copied into MediaPipe's own folder: a read-only install could not run "heavy"
    mp = pytest.importorskip("mediapipe")
    import subprocess
    import sys

    from flowmocap.io.sequence import read_image

    img = read_image(DAVIS / "JPEGImages" / "00000.jpg")
    pose_dir = Path(mp.__file__).parent / "modules" / "pose_landmark"
    listing = sorted((p.name, p.stat().st_mtime_ns) for p in pose_dir.iterdir())
    # a fresh process each: MediaPipe keeps a model it has loaded for the rest of the process
    script = (
        "import sys, numpy as np, mediapipe as mp\n"
        "from pathlib import Path\n"
        "from flowmocap.io.sequence import read_image\n"
        "from flowmocap.vision import detect\n"
        "if sys.argv[2] != '-':\n"
        "    detect.HEAVY_MODEL, detect._SHIPPED_OK = Path(sys.argv[2]), [True]\n"
        "p = detect._make_pose(mp, sys.argv[1], static_image_mode=True)\n"
        "r = p.process(read_image(sys.argv[3]))\n"
        "print(' '.join(f'{v:.6f}' for lm in r.pose_landmarks.landmark for v in (lm.x, lm.y)))\n")

    def landmarks(model, heavy_file="-"):
        out = subprocess.run([sys.executable, "-c", script, model, str(heavy_file), str(DAVIS / "JPEGImages" / "00000.jpg")],
                             capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        return np.array(out.stdout.split(), float)

    assert img.ndim == 3
    full, heavy = landmarks("full"), landmarks("heavy")
    assert np.abs(full - heavy).max() > 1e-3  # two different networks
    # the file linked in is the one read: the full network put in the heavy one's place gives full's answer
    np.testing.assert_allclose(landmarks("heavy", pose_dir / "pose_landmark_full.tflite"), full, atol=1e-6)
    assert sorted((p.name, p.stat().st_mtime_ns) for p in pose_dir.iterdir()) == listing


def test_the_detectors_name_says_its_model():
    pytest.importorskip("mediapipe")
    from flowmocap.errors import InputError
    from flowmocap.vision.detect import MediaPipePoseDetector

    full, heavy = (MediaPipePoseDetector.describe(augment=False, version="0.10.21", model=m) for m in ("full", "heavy"))
    assert "-full-3d" in full and "-heavy-v" in heavy  # heavy's tag names its visibility map (stored detections follow it)
    with pytest.raises(InputError, match="unknown detector model"):
        MediaPipePoseDetector(model="huge")


@pytest.mark.skipif(not DAVIS.exists(), reason=f"shared data not found at {DAVIS} (real frames for MediaPipe)")
def test_the_heavy_model_on_a_real_frame():
    """The heavy landmark model runs offline (from the shipped file) and finds the dancer's
    joints on her; its keypoints differ from the full model's (another network), by a few
    pixels on this clear frame."""
    from flowmocap.io.sequence import read_image
    from flowmocap.vision.detect import MediaPipePoseDetector
    from flowmocap.vision.masks import load_mask

    img = read_image(DAVIS / "JPEGImages" / "00000.jpg")
    gt = load_mask(DAVIS / "Annotations" / "00000.png")
    heavy = MediaPipePoseDetector(augment=False, model="heavy")
    assert "-heavy-" in heavy.name
    det = heavy.detect(img)
    full = MediaPipePoseDetector(augment=False).detect(img)
    assert det is not None and full is not None and det.world is not None
    ok = det.confidence[:12] > 0.5
    assert ok.sum() >= 10
    xy = det.keypoints[:12][ok].astype(int)
    assert gt[xy[:, 1].clip(0, 479), xy[:, 0].clip(0, 853)].mean() > 0.7
    d = np.linalg.norm(det.keypoints[:12] - full.keypoints[:12], axis=1)
    assert 0.0 < np.median(d) < 15.0


def test_the_heavy_models_visibility_map_is_monotone_from_0_to_1_and_checked(tmp_path, monkeypatch):
    from flowmocap.errors import InputError
    from flowmocap.vision import detect

    assert detect.visibility_map("full") is None
    x, y = detect.visibility_map("heavy")
    assert x[0] == y[0] == 0.0 and x[-1] == y[-1] == 1.0
    assert (np.diff(x) > 0).all() and (np.diff(y) >= 0).all()
    bad = tmp_path / "map.json"
    monkeypatch.setattr(detect, "HEAVY_VISIBILITY", bad)
    with pytest.raises(InputError, match="missing or damaged"):
        detect.visibility_map("heavy")
    bad.write_text('{"heavy": [0, 0.5, 1], "full": [0, 0.7, 0.6]}')  # not monotone
    with pytest.raises(InputError, match="not a monotone map"):
        detect.visibility_map("heavy")


def test_visibility_quantile_map_sends_one_distribution_onto_the_other():
    """tools/calibrate_visibility.py: the map sends the source sample's quantiles onto the
    target's, so as many values pass any threshold after it as in the target."""
    from conftest import load_script

    tool = load_script(Path(__file__).resolve().parents[1] / "tools" / "calibrate_visibility.py")
    rng = np.random.default_rng(0)
    target = rng.beta(5.0, 1.0, 20000)  # piled up near 1, like MediaPipe's visibilities
    source = target ** 2.5  # the same order, lower values (a more cautious model)
    x, y = tool.quantile_map(source, target)
    assert x[0] == y[0] == 0.0 and x[-1] == y[-1] == 1.0 and (np.diff(x) > 0).all() and (np.diff(y) >= 0).all()
    mapped = np.interp(source, x, y)
    for t in (0.3, 0.5, 0.8, 0.9):
        assert abs((mapped >= t).mean() - (target >= t).mean()) < 0.01
    assert abs((source >= 0.5).mean() - (target >= 0.5).mean()) > 0.1  # it had something to do
    # ties in the source (many exact ones) still give a strictly increasing x
    x, y = tool.quantile_map(np.minimum(source * 1.5, 1.0), target)
    assert (np.diff(x) > 0).all() and x[-1] == 1.0


def test_overlapping_quiet_blocks_in_two_threads_put_stderr_back():
    # each block saved and restored fd 2 on its own: interleaved in two threads, fd 2 stayed at /dev/null for good
    import os
    import threading

    from flowmocap.vision.detect import _native_stderr_to_devnull

    before = os.readlink("/proc/self/fd/2") if os.path.exists("/proc/self/fd/2") else None
    first_in, second_in, first_may_leave = threading.Event(), threading.Event(), threading.Event()

    def first():
        with _native_stderr_to_devnull():
            first_in.set()
            second_in.wait(5)
        first_may_leave.set()

    t = threading.Thread(target=first)
    t.start()
    first_in.wait(5)
    with _native_stderr_to_devnull():  # enters while the first is inside; leaves after it
        second_in.set()
        first_may_leave.wait(5)
        if before is not None:
            assert os.readlink("/proc/self/fd/2") == os.devnull
    t.join()
    if before is not None:
        assert os.readlink("/proc/self/fd/2") == before

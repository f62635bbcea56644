"""flowmocap.vision.lifter: the packaged 2D-to-3D keypoint lifter."""

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from flowmocap.body import load_body_model
from flowmocap.body.skeleton import EVAL_JOINTS, JOINT_INDEX
from flowmocap.errors import InputError, ModelFileError
from flowmocap.fit.config import TrackerConfig
from flowmocap.geometry.procrustes import similarity_procrustes
from flowmocap.vision.auto import PersonTrack
from flowmocap.vision.detect import KEYPOINT_NAMES
from flowmocap.vision.keypoint_map import load_keypoint_map
from flowmocap.vision.lifter import HIPS, POINTS, Lifter, LifterNet, lifted_track, load_lifter, normalise_2d, window_indices

from conftest import load_script


def _pose(**joints_deg):
    p = np.zeros(72)
    for name, rv in joints_deg.items():
        p[3 * JOINT_INDEX[name]:3 * JOINT_INDEX[name] + 3] = np.radians(rv)
    return p


def _prior_poses():
    """``(8, 72)`` typical poses not chosen by hand: the means of the packaged pose
    prior's mixture components (other joints at rest)."""
    from flowmocap.fit.pose_prior import PosePrior

    prior = PosePrior.load()
    out = np.zeros((prior.num_components, 72))
    out[:, prior.columns] = prior.means
    return out


#: hand-made poses with clear reach in depth: an arm forward, a stride, a knee raised
POSES = [
    _pose(left_shoulder=(0, 0, -70), right_shoulder=(0, 0, 70), left_elbow=(0, -30, 0)),
    _pose(left_hip=(-35, 0, 0), right_hip=(25, 0, 0), right_knee=(40, 0, 0), left_shoulder=(0, 0, -75),
          right_shoulder=(0, 0, 75)),
    _pose(right_hip=(-80, 0, 0), right_knee=(90, 0, 0), left_shoulder=(0, -60, -60), right_shoulder=(0, 0, 70),
          right_elbow=(0, 90, 0)),
]


def _points3d(poses):
    """``(N, 13, 3)`` the detector's points on the posed default body (y up), hip-centred."""
    model, kmap = load_body_model("default"), load_keypoint_map()
    with torch.no_grad():
        o = model(betas=torch.zeros(len(poses), 10), pose=torch.as_tensor(np.asarray(poses), dtype=torch.float32),
                  trans=torch.zeros(len(poses), 3))
    j, t = o.joints.double().numpy(), o.transforms.double().numpy()
    pts = kmap.apply(j, t)[:, list(EVAL_JOINTS)]
    pts[:, 0] = kmap.ears_middle(j, t)
    return pts - pts[:, 7:9].mean(1, keepdims=True)


def _view(pts, azimuth_deg, distance=4.0, f=600.0, c=(320.0, 240.0)):
    """Camera axes (x right, y down, z forward) and pixels of hip-centred ``pts (13, 3)`` seen
    from ``azimuth_deg`` about the vertical at ``distance`` m."""
    R = np.diag([1.0, -1.0, -1.0]) @ Rotation.from_euler("y", azimuth_deg, degrees=True).as_matrix()
    cam = pts @ R.T + (0, 0, distance)
    return cam, f * cam[:, :2] / cam[:, 2:] + c


def _keypoints(px13):
    """``(15, 2)`` detector keypoints from the 13 points (both ears at the head, nose too)."""
    kp = np.zeros((len(KEYPOINT_NAMES), 2))
    for k, name in enumerate(POINTS[1:], start=1):
        kp[KEYPOINT_NAMES.index(name)] = px13[k]
    for name in ("left_ear", "right_ear", "nose"):
        kp[KEYPOINT_NAMES.index(name)] = px13[0]
    return kp


def _lift_views(lifter, pts, azimuths):
    cams, kps = zip(*(_view(pts, a) for a in azimuths))
    kp = np.stack([_keypoints(p) for p in kps])
    world = lifter.lift(kp, np.ones(kp.shape[:2]))
    idx = [KEYPOINT_NAMES.index("left_ear")] + [KEYPOINT_NAMES.index(n) for n in POINTS[1:]]
    return np.stack(cams), world[:, idx]


def _aligned_cm(pred, ref):
    return 100 * np.linalg.norm(similarity_procrustes(pred, ref)[0] - ref, axis=-1).mean(-1)


def test_packaged_lifter_recovers_depth_from_any_side():
    lifter = load_lifter()
    assert lifter.info["train_subjects"] and not set(lifter.info["train_subjects"]) & {2, 8, 13, 61}
    azimuths = [0, 45, 90, 135, 180, 225, 270, 315]
    errs, flat = [], []
    for p in _points3d(np.concatenate([POSES, _prior_poses()])):
        cam, lifted = _lift_views(lifter, p, azimuths)
        errs.append(_aligned_cm(lifted, cam))
        flat_guess = cam.copy()
        flat_guess[..., 2] = cam[:, 7:9, 2].mean(1, keepdims=True)  # every point at the hips' depth
        flat.append(_aligned_cm(flat_guess, cam))
    errs, flat = np.array(errs), np.array(flat)
    # a few centimetres on clean 2D from every side, far better than knowing no depth at all
    assert np.median(errs) < 5.0, errs.round(1)
    assert errs.mean() < 0.5 * flat.mean(), (errs.mean(), flat.mean())
    # in metres, hip-centred, of a body's size
    _, lifted = _lift_views(lifter, _points3d(POSES[:1])[0], [30])
    assert np.abs(lifted[0, 7:9].mean(0)).max() < 1e-6
    assert 0.5 < np.linalg.norm(lifted[0, 0] - lifted[0, 11:13].mean(0)) < 2.2


def test_frames_without_hips_or_with_few_points_are_not_lifted():
    lifter = load_lifter()
    _, px = _view(_points3d(POSES[:1])[0], 20)
    kp = np.stack([_keypoints(px)] * 3)
    conf = np.ones(kp.shape[:2])
    conf[1, KEYPOINT_NAMES.index("left_hip")] = 0.1  # no hip
    conf[2, [KEYPOINT_NAMES.index(n) for n in ("left_knee", "right_knee", "left_ankle", "right_ankle",
                                               "left_wrist", "right_wrist")]] = 0.0  # 7 points left
    world = lifter.lift(kp, conf)
    assert np.isfinite(world[0]).all() and np.isnan(world[1]).all() and np.isnan(world[2]).all()
    # a dropped point is still given (the network fills it in), the others barely move
    conf2 = np.ones(kp.shape[:2])
    conf2[0, KEYPOINT_NAMES.index("left_wrist")] = 0.0
    w2 = lifter.lift(kp[:1], conf2[:1])
    assert np.isfinite(w2).all()
    with pytest.raises(InputError, match="keypoints must be"):
        lifter.lift(kp[:, :13], conf[:, :13])
    with pytest.raises(InputError, match="confidence must be"):
        lifter.lift(kp, conf[:, :3])


def test_lift_points_is_lift_on_the_13_points():
    lifter = load_lifter()
    pts = _points3d(POSES[:2])
    px = np.stack([_view(p, a)[1] for p, a in zip(pts, (20, 200))])
    mask = np.ones(px.shape[:2], bool)
    mask[1, POINTS.index("left_wrist")] = False
    y = lifter.lift_points(px, mask)
    conf = np.ones((2, len(KEYPOINT_NAMES)))
    conf[1, KEYPOINT_NAMES.index("left_wrist")] = 0.0
    world = lifter.lift(np.stack([_keypoints(p) for p in px]), conf)
    idx = [KEYPOINT_NAMES.index("left_ear")] + [KEYPOINT_NAMES.index(n) for n in POINTS[1:]]
    np.testing.assert_allclose(y, world[:, idx], atol=1e-12)
    mask[0, list(HIPS)] = False  # no hips: not lifted
    assert np.isnan(lifter.lift_points(px, mask)[0]).all()
    with pytest.raises(InputError, match="points must be"):
        lifter.lift_points(px[:, :12], mask[:, :12])
    with pytest.raises(InputError, match="mask must be"):
        lifter.lift_points(px, mask[:1])


def test_save_load_round_trip_and_wrong_files(tmp_path):
    lifter = load_lifter()
    path = tmp_path / "l.npz"
    lifter.save(path)
    again = Lifter.load(path)
    _, px = _view(_points3d(POSES[1:2])[0], 60)
    kp = _keypoints(px)[None]
    np.testing.assert_allclose(again.lift(kp, np.ones((1, 15))), lifter.lift(kp, np.ones((1, 15))), atol=1e-6)
    from flowmocap.fit.pose_prior import default_prior_path

    with pytest.raises(ModelFileError, match="not a"):
        Lifter.load(default_prior_path())  # an .npz of another kind
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ModelFileError, match="readable lifter"):
        Lifter.load(tmp_path / "junk.npz")
    with pytest.raises(ModelFileError):
        Lifter.load(tmp_path / "missing.npz")


def test_lifted_track_replaces_the_3d_only(tmp_path):
    _, px = _view(_points3d(POSES[2:3])[0], 200)
    kp = np.stack([_keypoints(px)] * 2).astype(np.float32)
    conf = np.ones((2, 15), np.float32)
    found = np.array([True, False])
    track = PersonTrack(kp, conf, found, [tmp_path / "a.png", tmp_path / "b.png"], {"detector": "x"},
                        np.zeros((2, 15, 3)))
    lifted = lifted_track(track)
    assert lifted.keypoints is track.keypoints and lifted.found is track.found
    assert np.isfinite(lifted.world[0]).all() and np.isnan(lifted.world[1]).all()
    j3d, c = lifted.smpl_joints3d(0)
    assert np.isfinite(j3d).all() and lifted.smpl_joints3d(1) is None
    assert not np.allclose(j3d, 0)


def test_config_names_the_3d_source():
    assert TrackerConfig().detector3d_source == "mediapipe"
    assert TrackerConfig(detector3d_source="lifter").detector3d_source == "lifter"
    with pytest.raises(InputError, match="detector3d_source"):
        TrackerConfig(detector3d_source="openpose")


def test_both_sources_average_the_lifter_and_the_detector(tmp_path):
    lifter = load_lifter()
    cam, px = _view(_points3d(POSES[1:2])[0], 120)
    kp = np.stack([_keypoints(px)] * 3).astype(np.float32)
    own = np.full((3, 15, 3), np.nan)
    for k, name in enumerate(POINTS[1:], start=1):  # the detector's 3D: the truth, scaled and shifted
        own[:2, KEYPOINT_NAMES.index(name)] = 0.9 * cam[k] + (0.1, 0.2, 0.3)
    for name in ("left_ear", "right_ear", "nose"):
        own[:2, KEYPOINT_NAMES.index(name)] = 0.9 * cam[0] + (0.1, 0.2, 0.3)
    track = PersonTrack(kp, np.ones((3, 15), np.float32), np.ones(3, bool), [tmp_path / "a.png"] * 3, {}, own)
    alone, both = lifted_track(track, lifter).world, lifted_track(track, lifter, mix=True).world
    limbs = [KEYPOINT_NAMES.index(n) for n in POINTS[1:]]
    truth = own[0, limbs]
    err = lambda w: np.linalg.norm(similarity_procrustes(w[limbs], truth)[0] - truth, axis=-1).mean()  # noqa: E731
    # the mean lies between the two: half the lifter's error against an exact detector
    assert err(both[0]) == pytest.approx(0.5 * err(alone[0]), rel=0.05) and err(alone[0]) > 0.005
    # in the detector's frame (its scale and origin); the lifter's alone where the detector has nothing
    np.testing.assert_allclose(both[0, limbs].mean(0), truth.mean(0), atol=1e-9)
    np.testing.assert_allclose(both[2], alone[2])


def _tiny_temporal(offsets=(-1, 0, 1)):
    torch.manual_seed(0)
    net = LifterNet(hidden=16, blocks=1, frames=len(offsets))
    return Lifter(net, {}, 1.0, offsets)


def _walk_keypoints(n=6):
    """``(n, 15, 2)`` keypoints of one pose drifting across the image, all confident."""
    _, px = _view(_points3d(POSES[:1])[0], 40)
    return np.stack([_keypoints(px + (7.0 * t, 2.0 * t)) + np.sin(t + np.arange(15))[:, None] for t in range(n)])


def test_window_indices_count_offsets_at_30_fps():
    idx, inside = window_indices(5, (-2, 0, 2), fps=60.0)  # 2 frames at 30 fps = 4 at 60
    np.testing.assert_array_equal(idx[2], [0, 2, 4])
    np.testing.assert_array_equal(inside[0], [False, True, True])
    np.testing.assert_array_equal(idx[0], [0, 0, 4])  # outside: clipped, and marked
    idx, inside = window_indices(5, (-3, 0, 3), fps=15.0)  # 3 frames at 30 fps = 1.5 at 15, rounded to 2
    np.testing.assert_array_equal(idx[2], [0, 2, 4])
    assert inside[2].all() and not inside[1, 0]


def test_a_temporal_lifter_reads_exactly_its_window():
    lifter = _tiny_temporal((-1, 0, 1))
    assert lifter.temporal
    kp = _walk_keypoints(6)
    conf = np.ones(kp.shape[:2])
    base = lifter.lift(kp, conf, fps=30.0)
    moved = kp.copy()
    moved[3] += np.random.default_rng(0).normal(0, 15, moved[3].shape)
    changed = ~np.isclose(lifter.lift(moved, conf, fps=30.0), base).all((1, 2))
    np.testing.assert_array_equal(np.flatnonzero(changed), [2, 3, 4])  # frame 3 is read by frames 2, 3 and 4
    base60 = lifter.lift(kp, conf, fps=60.0)
    changed = ~np.isclose(lifter.lift(moved, conf, fps=60.0), base60).all((1, 2))
    np.testing.assert_array_equal(np.flatnonzero(changed), [1, 3, 5])  # at 60 fps one step of the window is 2 frames
    # a neighbour without the person counts as one outside the sequence
    gone = conf.copy()
    gone[0] = 0.0
    np.testing.assert_allclose(lifter.lift(kp, gone, fps=30.0)[1], lifter.lift(kp[1:], conf[1:], fps=30.0)[0])
    assert np.isnan(lifter.lift(kp, gone, fps=30.0)[0]).all()
    with pytest.raises(InputError, match="frame rate"):
        lifter.lift(kp, conf)
    with pytest.raises(InputError, match="frame rate"):
        lifter.lift(kp, conf, fps=0.0)


def test_lifter_files_of_format_1_and_window_round_trip(tmp_path):
    import json

    lifter = _tiny_temporal((-2, 0, 3))
    lifter.save(tmp_path / "t.npz")
    again = Lifter.load(tmp_path / "t.npz")
    assert again.offsets == (-2, 0, 3)
    kp, conf = _walk_keypoints(7), np.ones((7, 15))
    np.testing.assert_allclose(again.lift(kp, conf, fps=25.0), lifter.lift(kp, conf, fps=25.0), atol=1e-2)
    # a one-frame file of the first format (no window in its metadata) still loads
    single = Lifter(LifterNet(hidden=16, blocks=1), {}, 1.0)
    single.save(tmp_path / "s.npz")
    with np.load(tmp_path / "s.npz") as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    meta["format"] = 1
    del meta["offsets"], meta["window_fps"]
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "v1.npz", **arrays)
    old = Lifter.load(tmp_path / "v1.npz")
    assert old.offsets == (0,) and not old.temporal
    assert np.isfinite(old.lift(kp, conf)).all()  # no frame rate needed for one frame
    with pytest.raises(ModelFileError, match="window"):
        Lifter(LifterNet(hidden=16, blocks=1, frames=2), {}, 1.0, (0, 1, 2))


PRIOR_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mocap" / "prior"


def _train_tool():
    import sys

    tools = Path(__file__).resolve().parents[1] / "tools"
    sys.path.insert(0, str(tools))  # it imports train_pose_prior beside it
    return load_script(tools / "train_lifter.py")


def test_training_windows_stay_inside_their_clip_and_target_the_middle_frame():
    tool = _train_tool()
    seq = tool.Sequences.__new__(tool.Sequences)  # two clips of 5 and 4 frames, each frame's points distinct
    seq.X = torch.randn(9, 13, 3) * 0.3
    seq.start = torch.tensor([0] * 5 + [5] * 4)
    seq.end = torch.tensor([5] * 5 + [9] * 4)
    offsets = torch.tensor([-2, -1, 0, 1, 2])
    g = torch.Generator().manual_seed(0)
    v, m, target, cam = tool.examples(seq, torch.tensor([0, 4, 5, 6]), offsets, g, 0.0, 0.0)
    given = m.amax(-1) > 0  # (B, F) which frames of each window are given
    np.testing.assert_array_equal(given.numpy(), [[0, 0, 1, 1, 1], [1, 1, 1, 0, 0], [0, 0, 1, 1, 1], [0, 1, 1, 1, 1]])
    assert (v[~given] == 0).all()
    # the target is the middle frame's 3D, hip-centred, in the units of its own 2D normalisation
    np.testing.assert_allclose(target[:, list(HIPS)].mean(1).numpy(), 0, atol=1e-6)
    z0 = cam[:, list(HIPS), 2].mean(1)
    uv = cam[..., :2] / cam[..., 2:]
    _, s = normalise_2d(uv, torch.ones(4, 13))
    np.testing.assert_allclose((target[..., :2] * (z0[:, None, None] * s)).numpy(),
                               (cam - cam[:, list(HIPS)].mean(1, keepdim=True))[..., :2].numpy(), atol=1e-5)
    # each frame of a window is seen from the window's one camera: same depth offset for a repeated frame
    seq.X[:] = seq.X[2]
    v, m, _, _ = tool.examples(seq, torch.tensor([2]), offsets, g, 0.0, 0.0)
    np.testing.assert_allclose(v[0].numpy(), v[0, :1].expand(5, -1, -1).numpy(), atol=1e-6)


def test_training_noise_that_persists_over_a_window():
    """``persist``: the noise between two frames of a window correlates at persist^2 (one
    shared draw scaled by persist, one own draw by sqrt(1 - persist^2)), its variance is
    kept, and a share persist of the windows drop the same points in every frame."""
    tool = _train_tool()
    seq = tool.Sequences.__new__(tool.Sequences)  # one still clip: every frame the same pose
    seq.X = (torch.randn(1, 13, 3) * 0.3).expand(7, -1, -1).clone()
    seq.start, seq.end = torch.zeros(7, dtype=torch.long), torch.full((7,), 7)
    offsets = torch.tensor([-1, 0, 1])
    centres = torch.full((4000,), 3)

    def noise(persist, drop=0.0):
        g = torch.Generator().manual_seed(1)
        clean, _, _, _ = tool.examples(seq, centres, offsets, g, 0.0, 0.0)
        g = torch.Generator().manual_seed(1)
        v, m, _, _ = tool.examples(seq, centres, offsets, g, 0.5, drop, persist=persist)
        return (v - clean * m[..., None]), m

    for persist in (0.0, 0.6, 1.0):
        e, _ = noise(persist)
        a, b = e[:, 0, 3:].reshape(-1), e[:, 2, 3:].reshape(-1)  # two frames, points off the hips
        corr = float(torch.corrcoef(torch.stack([a, b]))[0, 1])
        assert abs(corr - persist ** 2) < 0.05 if persist < 1 else corr > 0.999
    assert abs(float(noise(0.6)[0].var() / noise(0.0)[0].var()) - 1) < 0.05  # same size either way
    _, m = noise(0.0, drop=0.3)
    _, mp = noise(1.0, drop=0.3)
    assert (mp == mp[:, 1:2]).all() and not (m == m[:, 1:2]).all()


def test_training_outliers_move_a_few_points_onto_other_points():
    tool = _train_tool()
    g = torch.Generator().manual_seed(0)
    uv = torch.randn(4000, 13, 2)
    assert torch.equal(tool.outlying(uv, g, 0.0), uv)  # off: untouched
    out = tool.outlying(uv, g, 0.25)
    moved = (out != uv).any(-1)
    hit = moved.any(1)
    assert abs(hit.float().mean().item() - 0.25) < 0.03  # the share of frames
    assert not moved[:, list(HIPS)].any()  # the hips stay (they place the frame)
    assert moved[hit].sum(1).min() >= 1 and moved[hit].sum(1).max() <= 3
    # a moved point lies near some point of its frame (scatter a fifth of the frame's size)
    size = (uv - uv[:, list(HIPS)].mean(1, keepdim=True)).pow(2).sum(-1).mean(1).sqrt()
    r, j = moved.nonzero(as_tuple=True)
    near = (out[r, j][:, None] - uv[r]).norm(dim=-1).min(1).values / size[r]
    assert near.median() < 0.3


@pytest.mark.skipif(not (PRIOR_DATA / "index.csv").exists(),
                    reason=f"the mocap prior data is not at {PRIOR_DATA} (shared data absent)")
def test_the_training_tool_writes_a_loadable_temporal_lifter(tmp_path):
    tool = _train_tool()
    out = tmp_path / "l.npz"
    assert tool.main(["--out", str(out), "--max-clips", "1", "--epochs", "1", "--hidden", "32", "--blocks", "1",
                      "--offsets=-2,0,2", "--bodies", "1"]) == 0
    lifter = Lifter.load(out)
    assert lifter.offsets == (-2, 0, 2) and lifter.temporal
    assert np.isfinite(lifter.info["check_test_cm"]) and lifter.info["train_subjects"] == [1]
    assert np.isfinite(lifter.lift(_walk_keypoints(4), np.ones((4, 15)), fps=30.0)).all()


def test_flip_average_lifts_a_pose_and_its_mirror_image_alike():
    from flowmocap.vision.lifter import MIRROR

    assert all(POINTS[m] == POINTS[k].replace("left", "@").replace("right", "left").replace("@", "right")
               for k, m in enumerate(MIRROR))
    plain = load_lifter()
    lifter = Lifter(plain.net, plain.info, plain.metres, plain.offsets, flip_average=True)
    rng = np.random.default_rng(3)
    pts = np.array([320.0, 240.0]) + rng.normal(0, 60, (5, 13, 2))
    mask = np.ones((5, 13), bool)
    mask[1, 4] = False
    mirrored = pts[:, list(MIRROR)] * np.array([-1.0, 1.0]) + np.array([640.0, 0.0])  # image mirrored, relabelled
    a = lifter.lift_points(pts, mask)
    b = lifter.lift_points(mirrored, mask[:, list(MIRROR)])
    np.testing.assert_allclose(b[:, list(MIRROR)] * np.array([-1.0, 1.0, 1.0]), a, atol=1e-5)
    # and it is the mean of the plain lift of both
    p_a, p_b = plain.lift_points(pts, mask), plain.lift_points(mirrored, mask[:, list(MIRROR)])
    np.testing.assert_allclose(a, 0.5 * (p_a + p_b[:, list(MIRROR)] * np.array([-1.0, 1.0, 1.0])), atol=1e-5)
    assert np.abs(p_a - a).max() > 1e-3  # the plain lifter is not symmetric by itself


def _pair_file(path: Path, truth: np.ndarray, detected_2d: np.ndarray, clip: str) -> None:
    """A ``tools/render_detections.py`` file of ``truth (T, 13, 3)`` camera metres whose
    detection is ``detected_2d (T, 13, 2)`` pixels (f = 640, centre (320, 240))."""
    K = np.array([[640.0, 0, 320], [0, 640, 240], [0, 0, 1]])
    T = len(truth)
    kp = np.zeros((T, len(KEYPOINT_NAMES), 2))
    for k, name in enumerate(POINTS):
        for n in (("left_ear", "right_ear") if name == "head" else (name,)):
            kp[:, KEYPOINT_NAMES.index(n)] = detected_2d[:, k]
    uv = truth[..., :2] / truth[..., 2:] * 640 + [320, 240]
    np.savez(path, keypoints=kp, confidence=np.ones((T, len(KEYPOINT_NAMES))), truth=truth, truth_2d=uv, K=K,
             clip=clip)


def test_detection_pairs_target_the_truth_as_the_detection_labels_it(tmp_path):
    from flowmocap.vision.lifter import MIRROR

    tool = _train_tool()
    rng = np.random.default_rng(3)
    X = rng.normal(0, 0.3, (2, 13, 3))
    X[:, list(HIPS)] = [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]]
    X[..., 2] += 4.0  # the hips about the optical axis, 4 m away: the ray's axes are the camera's
    uv = X[..., :2] / X[..., 2:] * 640 + [320, 240]
    det = uv.copy()
    det[1] = uv[1][list(MIRROR)]  # frame 1: the detector turned the person about
    _pair_file(tmp_path / "a-v0.npz", X, det, "a.bvh")
    _pair_file(tmp_path / "b-v0.npz", X[:1], uv[:1], "b.bvh")
    pairs = tool.DetectionPairs(tmp_path)
    assert len(pairs) == 3 and pairs.turned == 1
    n = (uv - [320, 240]) / 640
    n -= n[:, list(HIPS)].mean(1, keepdims=True)
    s = np.sqrt((n ** 2).sum(-1).mean(1))
    want = (X - X[:, list(HIPS)].mean(1, keepdims=True)) / (4.0 * s[:, None, None])
    want[1] = want[1][list(MIRROR)]  # the 2D as labelled: the truth's mirror labelling
    np.testing.assert_allclose(pairs.Y[:2].numpy(), want, atol=1e-5)
    # the input is the detection normalised as at run time; a mirrored example mirrors all three
    v, m, y = pairs.batch(torch.arange(3), None, mirror=False)
    np.testing.assert_allclose(v[:, 0].numpy(), normalise_2d(pairs.P, pairs.M)[0].numpy(), atol=1e-6)
    g = torch.Generator().manual_seed(0)
    vs, ms, ys = zip(*(pairs.batch(torch.tensor([0]), g) for _ in range(20)))
    flipped = [k for k in range(20) if not torch.allclose(ys[k], y[:1])]
    assert 0 < len(flipped) < 20
    k = flipped[0]
    np.testing.assert_allclose(ys[k][0].numpy(), y[0][list(MIRROR)].numpy() * [-1, 1, 1], atol=1e-6)
    np.testing.assert_allclose(vs[k][0, 0].numpy(), v[0, 0][list(MIRROR)].numpy() * [-1, 1], atol=1e-6)
    train, held = pairs.split(2)  # clip 0 ("a") held back
    assert len(held) == 2 and len(train) == 1


def test_bridge_gaps_fills_short_runs_by_a_straight_line_and_leaves_the_rest():
    from flowmocap.vision.lifter import bridge_gaps

    T = 12
    t = np.arange(T, dtype=np.float64)
    pts = np.stack([np.stack([3.0 * t + 1.0, -2.0 * t], -1), np.stack([t ** 2, t], -1)], 1)  # (T, 2, 2)
    given = np.ones((T, 2), bool)
    given[[4, 5], 0] = False  # a run of 2 with both ends seen
    given[[0, 1], 1] = False  # at the start: no frame before it
    given[[6, 7, 8], 1] = False  # a run of 3
    given[11, 1] = False  # at the end
    noisy = pts.copy()
    noisy[~given] = 1e6  # what a missing point holds is never read
    noisy[9, 0] = np.nan  # a NaN point counts as missing (a run of 1)
    out, ok = bridge_gaps(noisy, given, max_frames=2)
    np.testing.assert_allclose(out[[4, 5], 0], pts[[4, 5], 0])  # a straight line in time: exact on a line
    np.testing.assert_allclose(out[9, 0], pts[9, 0])
    assert ok[:, 0].all()
    assert not ok[[0, 1, 6, 7, 8, 11], 1].any() and ok[[2, 3, 4, 5, 9, 10], 1].all()  # too long, or open-ended
    np.testing.assert_array_equal(out[[6, 7, 8], 1], noisy[[6, 7, 8], 1])
    out3, ok3 = bridge_gaps(noisy, given, max_frames=3)
    # the run of 3 filled on the line between frames 5 and 9: (t^2, t) at 5 and 9, so 25 + 14 (t - 5)
    np.testing.assert_allclose(out3[[6, 7, 8], 1], [[39.0, 6.0], [53.0, 7.0], [67.0, 8.0]])
    assert ok3[[6, 7, 8], 1].all()
    same, ok0 = bridge_gaps(noisy, given, max_frames=0)
    np.testing.assert_array_equal(ok0, given & np.isfinite(noisy).all(-1))
    assert same is not noisy and np.array_equal(same, noisy, equal_nan=True)  # a copy, unchanged
    with pytest.raises(InputError, match="max_frames"):
        bridge_gaps(noisy, given, max_frames=-1)
    with pytest.raises(InputError, match="given"):
        bridge_gaps(noisy, given[:, :1], max_frames=2)

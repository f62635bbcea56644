"""The depth-flip test of each limb (flowmocap.fit.flip): the mirrored limb projects to
the same pixels, is a change of the parent joint's rotation only, and a limb flipped
out of place is flipped back where the 3D terms say so."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flowmocap.body import JOINT_INDEX, load_body_model
from flowmocap.body.skeleton import PARENTS
from flowmocap.errors import InputError
from flowmocap.fit.config import DEPTH_CUES_OFF, TrackerConfig
from flowmocap.fit.energies import DEPTH_LIMBS
from flowmocap.fit.flip import flip_limbs, flipped_pose, limb_name, limb_rotation, mirror_child
from flowmocap.fit.objective import FrameData, FrameState, Scene, frame_energy
from flowmocap.geometry import PinholeCamera, look_at
from flowmocap.io import walk_poses

J = JOINT_INDEX
SHIN = (J["left_knee"], J["left_ankle"])


def _subtree(j: int) -> set[int]:
    """Joint ``j`` and every joint below it."""
    out = {j}
    for _ in range(len(PARENTS)):
        out |= {k for k in range(len(PARENTS)) if PARENTS[k] in out}
    return out


@pytest.fixture(scope="module")
def scene64():
    """The default body (float64), walking, seen from the front-left by a 320x240 camera."""
    model = load_body_model("default", dtype=torch.float64)
    R, t = look_at((1.2, 0.2, 2.8), (0.0, -0.1, 0.0))
    cam = PinholeCamera.from_focal(320, 240, 300.0, R, t)
    return Scene(model, torch.zeros(1, 10, dtype=torch.float64), cam)


@pytest.fixture(scope="module")
def pose():
    p = torch.tensor(walk_poses(np.array([0.3]))[0])
    p[3 * J["left_knee"]] += 0.6  # a clearly bent knee: the shin points out of the image plane
    p[3 * J["right_elbow"] + 1] += 0.8  # (inside the joint limits)
    return p


def test_mirror_child_closed_form():
    rng = np.random.default_rng(0)
    for _ in range(50):
        parent = rng.normal(size=3) * 0.3 + np.array([0.0, 0.0, 3.0])
        child = parent + rng.normal(size=3) * 0.3
        mirrored = mirror_child(parent, child)
        if mirrored is None:
            continue
        assert np.linalg.norm(np.cross(mirrored, child)) < 1e-12  # on the ray through the child
        assert mirrored[2] > 0 and mirrored @ child > 0  # in front of the camera
        np.testing.assert_allclose(np.linalg.norm(mirrored - parent), np.linalg.norm(child - parent))
        np.testing.assert_allclose(mirror_child(parent, mirrored), child)  # mirroring twice: back
    # a limb perpendicular to the ray through its child has no distinct mirror image
    b = (-3.0 + np.sqrt(9.0 - 4 * 0.4 ** 2)) / 2  # (C - P) . C = 0 for C = P + (0.4, 0, b)
    assert mirror_child(np.array([0.0, 0.0, 3.0]), np.array([0.4, 0.0, 3.0 + b])) is None
    assert mirror_child(np.array([0.0, 0.0, 3.0]), np.array([0.0, 0.0, -1.0])) is None  # behind the camera


def test_limb_rotation():
    rng = np.random.default_rng(1)
    for u, v in [rng.normal(size=(2, 3)) for _ in range(10)] + [(np.array([1.0, 0, 0]), np.array([-2.0, 0, 0]))]:
        R = limb_rotation(u, v)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) > 0
        np.testing.assert_allclose(R @ (u / np.linalg.norm(u)), v / np.linalg.norm(v), atol=1e-12)


def test_the_mirrored_limb_projects_to_the_same_points(scene64, pose):
    """For every limb: parent and child joints project to the same pixels, the bone keeps
    its length, its depth direction turns, only the parent joint's rotation changes, and
    only the joints below it move."""
    trans = torch.zeros(3, dtype=torch.float64)
    out, _, _ = scene64.forward(pose, trans)
    cam = scene64.camera
    tried = 0
    for limb in DEPTH_LIMBS:
        p, c = limb
        new = flipped_pose(scene64, pose, trans, limb)
        if new is None:
            continue
        tried += 1
        changed = torch.nonzero((new - pose).abs() > 0).flatten().tolist()
        assert set(changed) <= {3 * p, 3 * p + 1, 3 * p + 2}, limb_name(limb)
        out2, _, _ = scene64.forward(new, trans)
        j, j2 = out.joints[0], out2.joints[0]
        torch.testing.assert_close(cam.project(j2[[p, c]]), cam.project(j[[p, c]]), atol=1e-8, rtol=0)
        torch.testing.assert_close((j2[c] - j2[p]).norm(), (j[c] - j[p]).norm())
        dz, dz2 = (cam.to_camera(j[c]) - cam.to_camera(j[p]))[2], (cam.to_camera(j2[c]) - cam.to_camera(j2[p]))[2]
        assert float(dz) * float(dz2) < 0 or abs(float(dz2 - dz)) > 0.01  # it turned in depth
        moved = set(torch.nonzero((j2 - j).norm(dim=1) > 1e-9).flatten().tolist())
        assert c in moved and moved <= _subtree(c), limb_name(limb)
        back = flipped_pose(scene64, new, trans, limb)  # the mirror image of the mirror image
        torch.testing.assert_close(scene64.forward(back, trans)[0].joints[0][c], j[c], atol=1e-8, rtol=0)
    assert tried >= 6
    with pytest.raises(InputError):
        flipped_pose(scene64, pose, trans, (0, 1))  # the root is no limb's parent here
    with pytest.raises(InputError):
        flipped_pose(scene64, pose, trans, (4, 8))  # not a bone


@pytest.fixture(scope="module")
def scene32(scene64):
    return Scene(load_body_model("default"), torch.zeros(1, 10), scene64.camera)


def _truth3d(scene, pose, trans):
    with torch.no_grad():
        out, _, _ = scene.forward(pose, trans)
    return scene.camera.to_camera(out.joints[0]).double().numpy() - np.asarray(scene.camera.t), np.full(24, 0.9)


@pytest.mark.parametrize("term", ["limb_depth", "detector3d"])
def test_a_flipped_shin_is_flipped_back(scene32, pose, term):
    """The detector's 3D joints are the truth; the tracked frame has its left shin
    mirrored in depth (same 2D points). The energy (E_d or E_3d, with the joint limits)
    prefers the truth and the flip test restores it, recording the flip; without a 3D
    term nothing is flipped."""
    pose = pose.float()
    trans = torch.tensor([0.0, 0.0, 0.2])
    flipped = flipped_pose(scene32, pose, trans, SHIN)
    assert flipped is not None
    weights = {"limb_depth": {"limb_depth_weight": 2.0}, "detector3d": {"limb_depth_weight": 0.0,
                                                                       "detector3d_weight": 50.0}}[term]
    cfg = TrackerConfig(penetration_weight=0.0, **{**DEPTH_CUES_OFF, **weights})
    data = FrameData(mask=None, silhouette=None, person_pixels=1.0, joints3d=_truth3d(scene32, pose, trans))
    prev = FrameState(pose, trans)
    e_true, _ = frame_energy(scene32, FrameState(pose, trans), data, cfg, None, None, None)
    e_flip, _ = frame_energy(scene32, FrameState(flipped, trans), data, cfg, None, None, None)
    assert float(e_true) < float(e_flip)
    state, terms, events = flip_limbs(scene32, FrameState(flipped, trans), data, cfg, prev, None, frame=7)
    ankle = J["left_ankle"]
    with torch.no_grad():
        got = scene32.forward(state.pose, state.trans)[0].joints[0]
        want = scene32.forward(pose, trans)[0].joints[0]
    assert float((got[ankle] - want[ankle]).norm()) < 1e-3
    assert [e["limb"] for e in events] == [limb_name(SHIN)] and events[0]["frame"] == 7
    assert events[0]["energy_after"] < events[0]["energy_before"]
    assert terms["total"] == pytest.approx(float(e_true), rel=1e-4, abs=1e-6) and term in terms
    # nothing in the energy tells the two apart but the temporal term towards the flipped pose
    blind = TrackerConfig(limb_depth_weight=0.0, penetration_weight=0.0, limit_weight=0.0, **DEPTH_CUES_OFF)
    kept, _, none = flip_limbs(scene32, FrameState(flipped, trans), data, blind, prev, flipped)
    assert none == [] and torch.equal(kept.pose, flipped)


def test_given_terms_of_the_tracked_state_save_one_evaluation_and_change_nothing(scene32, pose, monkeypatch):
    """The tracker hands the flip test the energies it computed at the tracked state:
    the result (state, terms, events) is the same as when the test evaluates them itself,
    with one energy evaluation fewer; a non-finite given total is evaluated again."""
    import flowmocap.fit.flip as flip_mod

    pose = pose.float()
    trans = torch.tensor([0.0, 0.0, 0.2])
    flipped = flipped_pose(scene32, pose, trans, SHIN)
    cfg = TrackerConfig(penetration_weight=0.0, **{**DEPTH_CUES_OFF, "limb_depth_weight": 2.0})
    data = FrameData(mask=None, silhouette=None, person_pixels=1.0, joints3d=_truth3d(scene32, pose, trans))
    prev, start = FrameState(pose, trans), FrameState(flipped, trans)
    calls = []
    real = flip_mod.frame_energy
    monkeypatch.setattr(flip_mod, "frame_energy", lambda *a, **k: calls.append(1) or real(*a, **k))
    with torch.no_grad():
        total, known = real(scene32, start, data, cfg, len(cfg.stages) - 1, None, flipped)
    known["total"] = float(total)
    s1, t1, e1 = flip_limbs(scene32, start, data, cfg, prev, flipped, frame=3)
    n_own = len(calls)
    s2, t2, e2 = flip_limbs(scene32, start, data, cfg, prev, flipped, frame=3, terms=dict(known))
    assert len(calls) - n_own == n_own - 1
    assert torch.equal(s1.pose, s2.pose) and torch.equal(s1.trans, s2.trans)
    assert t1 == t2 and e1 == e2 and [e["limb"] for e in e1] == [limb_name(SHIN)]
    calls.clear()
    s3, t3, _ = flip_limbs(scene32, start, data, cfg, prev, flipped, frame=3, terms={**known, "total": float("nan")})
    assert len(calls) == n_own and torch.equal(s3.pose, s1.pose) and t3 == t1


def test_flip_with_a_few_iterations_polishes_the_mirrored_pose(scene32, pose):
    """With ``flip_iterations`` the unflipped state and each mirrored pose are optimised
    for that many iterations before the comparison. From a converged fit to 2D joints and
    E_d with the shin flipped (E_d saturates and the 2D joints hold the mirror image, so
    the optimiser alone leaves it there) the shin is flipped back to the truth's
    direction."""
    from flowmocap.fit.lbfgs import minimise

    pose = pose.float()
    trans = torch.tensor([0.0, 0.0, 0.2])
    with torch.no_grad():
        truth = scene32.forward(pose, trans)[0].joints[0]
    data = FrameData(mask=None, silhouette=None, person_pixels=1.0, joints3d=_truth3d(scene32, pose, trans),
                     keypoints=(scene32.camera.project(truth), torch.ones(24)))
    # the "detections" are the model's own joints: no keypoint offsets
    cfg = TrackerConfig(penetration_weight=0.0, limit_weight=0.0, limb_depth_weight=2.0, flip_iterations=3,
                        keypoint_offsets=False, **{**DEPTH_CUES_OFF, "flip_test": True})
    s = FrameState(flipped_pose(scene32, pose, trans, SHIN).requires_grad_(), trans.clone().requires_grad_())
    minimise([s.pose, s.trans], lambda: frame_energy(scene32, s, data, cfg, None, None, None)[0], 60)
    start = s.clone()
    knee, ankle = SHIN

    def shin(st):
        with torch.no_grad():
            j = scene32.camera.to_camera(scene32.forward(st.pose, st.trans)[0].joints[0])
        return (j[ankle] - j[knee]) / (j[ankle] - j[knee]).norm()

    want = (scene32.camera.to_camera(truth[ankle]) - scene32.camera.to_camera(truth[knee]))
    want = want / want.norm()
    assert float(shin(start) @ want) < 0.9  # still flipped after the optimisation
    e_start, _ = frame_energy(scene32, start, data, cfg, None, None, None)
    state, terms, ev = flip_limbs(scene32, start, data, cfg, FrameState(pose, trans), None)
    assert limb_name(SHIN) in [e["limb"] for e in ev]
    assert float(shin(state) @ want) > 0.98
    assert terms["limb_depth"] < 1e-3 and terms["total"] < 0.5 * float(e_start)


def test_a_flip_judged_without_the_temporal_term(scene32, pose):
    """The Kalman prediction (E_theta's reference) carries the flipped shin on, strongly
    enough that the total energy keeps the flip; judged without E_theta
    (``flip_without_temporal``) the detector's 3D joints win and the shin is flipped back,
    while the returned energies are still the full ones (E_theta included)."""
    pose = pose.float()
    trans = torch.tensor([0.0, 0.0, 0.2])
    flipped = flipped_pose(scene32, pose, trans, SHIN)
    data = FrameData(mask=None, silhouette=None, person_pixels=1.0, joints3d=_truth3d(scene32, pose, trans))
    base = dict(penetration_weight=0.0, temporal_weight=50.0, **{**DEPTH_CUES_OFF, "limb_depth_weight": 2.0})
    prev = FrameState(pose, trans)
    kept, _, none = flip_limbs(scene32, FrameState(flipped, trans), data, TrackerConfig(**base), prev, flipped)
    assert none == [] and torch.equal(kept.pose, flipped)
    cfg = TrackerConfig(**base, flip_without_temporal=True)
    state, terms, events = flip_limbs(scene32, FrameState(flipped, trans), data, cfg, prev, flipped)
    assert [e["limb"] for e in events] == [limb_name(SHIN)]
    with torch.no_grad():
        got = scene32.forward(state.pose, state.trans)[0].joints[0]
        want = scene32.forward(pose, trans)[0].joints[0]
    assert float((got[SHIN[1]] - want[SHIN[1]]).norm()) < 1e-3
    assert terms["temporal"] > 0
    assert terms["total"] == pytest.approx(sum(v for k, v in terms.items() if k != "total"), rel=1e-5)


THIGH = (J["left_hip"], J["left_knee"])


def _reach(scene, state, limb):
    with torch.no_grad():
        jc = scene.camera.to_camera(scene.forward(state.pose, state.trans)[0].joints[0]).double().numpy()
    return jc[limb[1], 2] - jc[limb[0], 2]


def test_the_trackers_vote_mirrors_a_limb_the_detector_sees_the_other_way_for_a_run_of_frames(scene32, pose):
    """``flip_vote_frames``: the detector's 3D (the truth) reaches with the left shin the other
    way from the tracked state; the limb is mirrored at the third frame in a row, not before,
    and the count starts again; the count survives a state_dict round trip."""
    from flowmocap.fit.tracker import SequenceTracker

    pose = pose.float()
    trans = torch.tensor([0.0, 0.0, 0.2])
    flipped = FrameState(flipped_pose(scene32, pose, trans, SHIN), trans)
    truth = FrameState(pose, trans)
    assert abs(_reach(scene32, truth, SHIN)) > 0.08 and np.sign(_reach(scene32, truth, SHIN)) != np.sign(
        _reach(scene32, flipped, SHIN))
    data = FrameData(mask=None, silhouette=None, person_pixels=1.0, joints3d=_truth3d(scene32, pose, trans))
    tracker = SequenceTracker(scene32, TrackerConfig(flip_vote_frames=3))
    tracker.prev = truth
    for i in (5, 6):
        state, events = tracker.vote_flips(flipped, data, i)
        assert events == [] and state is flipped
    k = [limb for limb in DEPTH_LIMBS].index(SHIN)
    assert tracker.votes[k] == 2
    again = SequenceTracker(scene32, TrackerConfig(flip_vote_frames=3))
    again.load_state_dict(tracker.state_dict())
    assert again.votes.tolist() == tracker.votes.tolist()
    state, events = again.vote_flips(flipped, data, 7)
    assert [(e["frame"], e["limb"]) for e in events] == [(7, limb_name(SHIN))]
    with torch.no_grad():
        got = scene32.forward(state.pose, state.trans)[0].joints[0]
        want = scene32.forward(pose, trans)[0].joints[0]
    assert float((got[J["left_ankle"]] - want[J["left_ankle"]]).norm()) < 1e-3
    assert again.votes[k] == 0
    # off, or without the detector's 3D: nothing
    assert SequenceTracker(scene32, TrackerConfig(flip_vote_frames=1)).vote_flips(
        flipped, FrameData(mask=None, silhouette=None, person_pixels=1.0), 7)[1] == []


def test_the_trackers_vote_keeps_a_thigh_whose_ankle_the_detector_sees_where_it_is(scene32, pose):
    """A thigh's mirror moves the ankle in the image: with the detected ankle where the
    tracked body has it, the vote is refused; with it where the truth has it, taken."""
    from flowmocap.fit.objective import keypoint_observation
    from flowmocap.fit.tracker import SequenceTracker

    pose = pose.float().clone()
    pose[3 * J["left_hip"]] -= 0.9  # the thigh raised forwards: it reaches in depth
    trans = torch.tensor([0.0, 0.0, 0.2])
    truth = FrameState(pose, trans)
    wrong = flipped_pose(scene32, pose, trans, THIGH)
    assert wrong is not None and abs(_reach(scene32, truth, THIGH)) > 0.08
    wrong = FrameState(wrong, trans)
    got = {}
    for image_of, st in (("truth", truth), ("tracked", wrong)):
        with torch.no_grad():
            px = scene32.camera.project(scene32.forward(st.pose, st.trans)[0].joints[0]).double().numpy()
        moved = np.linalg.norm(px[J["left_ankle"]] - scene32.camera.project(
            scene32.forward(wrong.pose, trans)[0].joints[0]).detach().double().numpy()[J["left_ankle"]])
        data = FrameData(mask=None, silhouette=None, person_pixels=1.0, joints3d=_truth3d(scene32, pose, trans),
                         keypoints=keypoint_observation(px, np.ones(24)))
        tracker = SequenceTracker(scene32, TrackerConfig(flip_vote_frames=1))
        got[image_of] = [e["limb"] for e in tracker.vote_flips(wrong, data, 0)[1]]
        if image_of == "truth":
            assert moved > 3  # the mirror moves the ankle's pixel
    assert got == {"truth": [limb_name(THIGH)], "tracked": []}

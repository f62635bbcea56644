"""Energy terms of the tracker (flowmocap.fit.energies) and the joint limit table."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from flowmocap.body import JOINT_INDEX, JOINT_NAMES, body_capsules, load_body_model
from flowmocap.body.capsules import CAPSULE_NAMES, Capsules
from flowmocap.errors import InputError, NoPersonError
from flowmocap.fit import (
    default_joint_limits,
    interpenetration_energy,
    interpenetration_pairs,
    interpenetration_residuals,
    joint_angles,
    joint_limit_energy,
    joint_limit_residuals,
    keypoint_energy,
    keypoint_residuals,
    pose_prior_energy,
    pose_prior_residuals,
    segment_segment_distance,
    shape_prior_energy,
    silhouette_energy,
    silhouette_residuals,
    silhouette_target,
    temporal_energy,
    temporal_residuals,
)
from flowmocap.fit.energies import DEFAULT_TOLERANCE, _project
from flowmocap.render import capsule_signed_distance
from flowmocap.fit.joint_limits import LIMITS_DEG
from flowmocap.geometry import PinholeCamera, look_at
from flowmocap.io import walk_poses

J = JOINT_INDEX


@pytest.fixture(scope="module")
def body():
    return load_body_model("default", dtype=torch.float64)


@pytest.fixture(scope="module")
def walk():
    return torch.tensor(walk_poses(np.linspace(0.0, 1.0, 24, endpoint=False)))


def _pose(*items, dtype=torch.float64):
    """A (1, 72) pose with the given (joint name, axis 0..2, degrees) rotations."""
    p = torch.zeros(1, 72, dtype=dtype)
    for name, axis, deg in items:
        p[0, 3 * J[name] + axis] = math.radians(deg)
    return p


# ------------------------------------------------------------------------ joint limits


def _moved(body, items, joint):
    """Where ``joint`` moves (metres, body axes) when the pose is set to ``items``."""
    rest = body().joints[0, J[joint]]
    return (body(pose=_pose(*items)).joints[0, J[joint]] - rest).numpy()


def test_sign_conventions_of_the_limit_table_on_the_default_body(body):
    # knee +x: the ankle goes back (-z) and up -- natural flexion
    d = _moved(body, [("left_knee", 0, 45)], "left_ankle")
    assert d[2] < -0.2 and d[1] > 0.1
    # hip -x: the knee goes forward -- flexion is -x
    assert _moved(body, [("left_hip", 0, -45)], "left_knee")[2] > 0.2
    # left elbow -y: the wrist goes forward -- flexion; right elbow mirrored (+y)
    assert _moved(body, [("left_elbow", 1, -45)], "left_wrist")[2] > 0.1
    assert _moved(body, [("right_elbow", 1, 45)], "right_wrist")[2] > 0.1
    # ankle +x: the toes go down -- plantar flexion
    assert _moved(body, [("left_ankle", 0, 45)], "left_foot")[1] < -0.05
    # left hip +z: the knee goes out (+x) -- abduction
    assert _moved(body, [("left_hip", 2, 45)], "left_knee")[0] > 0.2
    # left shoulder +z raises the arm; right shoulder mirrored
    assert _moved(body, [("left_shoulder", 2, 45)], "left_elbow")[1] > 0.15
    assert _moved(body, [("right_shoulder", 2, -45)], "right_elbow")[1] > 0.15
    # left wrist +z: the hand goes up (palm down): extension
    assert _moved(body, [("left_wrist", 2, 45)], "left_hand")[1] > 0.05
    # spine +x: the neck goes forward -- flexion
    assert _moved(body, [("spine1", 0, 30)], "neck")[2] > 0.1
    # the table follows: flexion ranges lie on these sides
    assert LIMITS_DEG["left_knee"][0] == (-5.0, 145.0)
    assert LIMITS_DEG["left_hip"][0][0] <= -120.0
    assert LIMITS_DEG["left_elbow"][1][0] <= -150.0 and LIMITS_DEG["right_elbow"][1][1] >= 150.0


def test_limit_table_is_complete_ordered_and_mirrored():
    lim = default_joint_limits()
    assert lim.limited.tolist() == list(range(1, 24))
    assert np.isinf(lim.lower[0]).all() and np.isinf(lim.upper[0]).all()
    assert (lim.lower[1:] < 0).all() and (lim.upper[1:] > 0).all()  # the rest pose is inside
    assert (np.abs(lim.lower[1:]) < math.pi).all() and (np.abs(lim.upper[1:]) < math.pi).all()
    for name in JOINT_NAMES:
        if name.startswith("left_"):
            (lx, ly, lz), (rx, ry, rz) = LIMITS_DEG[name], LIMITS_DEG["right_" + name[5:]]
            assert rx == lx and ry == (-ly[1], -ly[0]) and rz == (-lz[1], -lz[0])


def test_joint_angles_of_single_axis_rotations():
    # a pure hinge rotation is exactly one angle, in its SMPL axis column
    for name, axis, deg in [("left_knee", 0, 120), ("left_elbow", 1, -130), ("left_wrist", 2, -60),
                            ("spine2", 1, 20), ("left_shoulder", 2, -80), ("left_collar", 0, 15)]:
        th = joint_angles(_pose((name, axis, deg)))[0, J[name]]
        expected = torch.zeros(3, dtype=torch.float64)
        expected[axis] = math.radians(deg)
        torch.testing.assert_close(th, expected, atol=1e-9, rtol=0)
    # a flexed knee with a twist: the Euler chart (XZY) separates them, axis-angle mixes
    from flowmocap.geometry import euler_to_matrix, matrix_to_axis_angle

    R = euler_to_matrix(torch.tensor([math.radians(100), math.radians(8), math.radians(20)],
                                     dtype=torch.float64), "XZY")
    p = torch.zeros(1, 24, 3, dtype=torch.float64)
    p[0, J["left_knee"]] = matrix_to_axis_angle(R)
    th = joint_angles(p)[0, J["left_knee"]]
    torch.testing.assert_close(th, torch.tensor([100.0, 20.0, 8.0], dtype=torch.float64).deg2rad())


def test_joint_limit_energy_zero_inside_positive_outside(body, walk):
    assert joint_limit_energy(torch.zeros(1, 72)).item() == 0.0
    assert joint_limit_energy(walk).max().item() == 0.0
    assert joint_limit_energy(_pose(("left_knee", 1, 8), ("right_knee", 1, -8))).item() == 0.0  # a little tibial rotation
    natural = _pose(("left_knee", 0, 120), ("left_hip", 0, -90), ("left_elbow", 1, -120), ("right_elbow", 1, 90),
                    ("left_shoulder", 2, -80), ("left_ankle", 0, 30), ("spine2", 0, 20), ("neck", 1, 30))
    assert joint_limit_energy(natural).item() == 0.0
    for bad in [("left_knee", 0, -30), ("right_knee", 0, -30), ("left_elbow", 1, 40), ("right_elbow", 1, -40),
                ("left_hip", 2, -60), ("left_wrist", 2, 110), ("head", 0, 80), ("left_knee", 1, 30),
                ("right_knee", 1, -30)]:
        assert joint_limit_energy(_pose(bad)).item() > 0.05, bad
    # a knee bent backwards costs more the further it goes
    e = [joint_limit_energy(_pose(("left_knee", 0, -d))).item() for d in (6, 10, 20, 40)]
    assert e[0] > 0 and all(b > a for a, b in zip(e, e[1:]))


def test_joint_limit_residual_closed_form():
    lim = default_joint_limits()
    k = J["left_knee"]
    for angle, excess in [(lim.upper[k, 0] + 0.3, 0.3), (lim.lower[k, 0] - 0.2, 0.2)]:
        p = torch.zeros(1, 24, 3, dtype=torch.float64)
        p[0, k, 0] = angle
        r = joint_limit_residuals(p)
        assert r.shape == (1, 69)
        i = 3 * (k - 1)  # residuals skip the root
        torch.testing.assert_close(r[0, i], torch.tensor(math.expm1(excess), dtype=torch.float64))
        assert (r[0, torch.arange(69) != i] == 0).all()
        torch.testing.assert_close(joint_limit_energy(p)[0], r[0, i] ** 2)


def test_joint_limit_gradient_matches_finite_differences():
    g = torch.Generator().manual_seed(1)
    pose = (0.9 * torch.randn(2, 72, generator=g, dtype=torch.float64)).requires_grad_()
    assert joint_limit_energy(pose.detach()).min() > 0  # several angles outside the limits
    assert torch.autograd.gradcheck(joint_limit_residuals, (pose,), eps=1e-6, atol=1e-6)


def test_joint_limit_energy_is_left_right_symmetric(walk):
    g = torch.Generator().manual_seed(2)
    pose = 0.7 * torch.randn(4, 24, 3, generator=g, dtype=torch.float64)
    swap = [JOINT_NAMES.index(n.replace("left_", "#").replace("right_", "left_").replace("#", "right_"))
            for n in JOINT_NAMES]
    mirrored = pose[:, swap] * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
    torch.testing.assert_close(joint_limit_energy(mirrored), joint_limit_energy(pose))


def test_joint_limit_input_errors():
    with pytest.raises(InputError):
        joint_limit_energy(torch.zeros(1, 70))
    with pytest.raises(InputError):
        joint_limit_energy(np.zeros((1, 72)))


# -------------------------------------------------------------------- interpenetration


def _brute_segment_distance(p1, q1, p2, q2, n=20001):
    t = np.linspace(0, 1, n)[:, None]
    a, b = p1 + t * (q1 - p1), p2 + t * (q2 - p2)
    # distance of every sample of a to segment b (exact), then the minimum
    d = q2 - p2
    s = np.clip(((a - p2) @ d) / max(d @ d, 1e-300), 0, 1)
    da = np.linalg.norm(a - (p2 + s[:, None] * d), axis=1).min()
    d1 = q1 - p1
    s = np.clip(((b - p1) @ d1) / max(d1 @ d1, 1e-300), 0, 1)
    db = np.linalg.norm(b - (p1 + s[:, None] * d1), axis=1).min()
    return min(da, db)


def test_segment_distance_matches_brute_force_including_degenerate_cases():
    rng = np.random.default_rng(0)
    cases = [rng.normal(size=(4, 3)) for _ in range(30)]
    p, q = rng.normal(size=3), rng.normal(size=3)
    off = np.array([0.3, -0.2, 0.5])
    cases += [
        np.stack([p, q, p + off, q + off]),  # parallel, overlapping extent
        np.stack([p, q, q + 2 * (q - p), q + 3 * (q - p)]),  # collinear, apart
        np.stack([p, p, q, q + off]),  # first segment a point
        np.stack([p, q, off, off]),  # second segment a point
        np.stack([p, p, q, q]),  # two points
        np.stack([[0, 0, 0], [1, 0, 0], [0.5, -1, 0], [0.5, 1, 0]]),  # crossing: distance 0
    ]
    x = torch.tensor(np.stack(cases))
    d = segment_segment_distance(x[:, 0], x[:, 1], x[:, 2], x[:, 3]).numpy()
    ref = np.array([_brute_segment_distance(*c) for c in cases])
    np.testing.assert_allclose(d, ref, atol=2e-6)  # sqrt(d^2 + 1e-12) adds 1e-6 at 0


def _caps(start, end, radius):
    t = lambda v: torch.tensor(v, dtype=torch.float64)[None]  # noqa: E731
    return Capsules(t(start), t(end), t(radius))


def test_interpenetration_closed_form_for_crossing_capsules():
    # two perpendicular capsules whose axes pass 0.05 apart: overlap 0.1 + 0.08 - 0.05
    caps = _caps([[-1, 0, 0], [0, -1, 0.05]], [[1, 0, 0], [0, 1, 0.05]], [0.1, 0.08])
    r = interpenetration_residuals(caps, pairs=[(0, 1)], tolerance=0.0)
    torch.testing.assert_close(r, torch.tensor([[0.13]], dtype=torch.float64))
    e = interpenetration_energy(caps, pairs=[(0, 1)], tolerance=0.01)
    torch.testing.assert_close(e, torch.tensor([0.12 ** 2], dtype=torch.float64))
    apart = _caps([[-1, 0, 0], [0, -1, 0.5]], [[1, 0, 0], [0, 1, 0.5]], [0.1, 0.08])
    assert interpenetration_energy(apart, pairs=[(0, 1)]).item() == 0.0
    with pytest.raises(InputError):
        interpenetration_energy(caps, pairs=[(0, 2)])


def test_interpenetration_gradient_matches_finite_differences():
    rng = np.random.default_rng(3)
    K = 5
    start = torch.tensor(rng.normal(0, 0.15, (2, K, 3)), requires_grad=True)
    end = torch.tensor(rng.normal(0, 0.15, (2, K, 3)), requires_grad=True)
    radius = torch.tensor(rng.uniform(0.05, 0.12, (2, K)), requires_grad=True)
    pairs = [(i, j) for i in range(K) for j in range(i + 1, K)]

    def f(s, e, r):
        return interpenetration_residuals(Capsules(s, e, r), pairs=pairs, tolerance=0.01)

    assert (f(start, end, radius) > 0).sum() >= 5  # several pairs overlap
    assert torch.autograd.gradcheck(f, (start, end, radius), eps=1e-7, atol=1e-6)


def test_interpenetration_pairs_exclude_neighbours_keep_limbs(body):
    pairs = set(interpenetration_pairs())
    assert pairs == set(interpenetration_pairs(body))  # same rule, same body
    idx = {n: i for i, n in enumerate(CAPSULE_NAMES)}

    def has(a, b):
        i, j = sorted((idx[a], idx[b]))
        return (i, j) in pairs

    for a, b in [("left_upper_arm", "left_forearm"), ("left_forearm", "left_hand"), ("pelvis", "left_thigh"),
                 ("spine1", "left_thigh"), ("spine3", "left_upper_arm"), ("left_thigh", "left_shin"),
                 ("neck", "head"), ("spine2", "spine3")]:
        assert not has(a, b), (a, b)
    for a, b in [("left_thigh", "right_thigh"), ("left_hand", "spine2"), ("left_forearm", "pelvis"),
                 ("left_hand", "head"), ("left_hand", "right_hand"), ("left_shin", "right_shin"),
                 ("left_hand", "left_thigh"), ("left_upper_arm", "right_upper_arm")]:
        assert has(a, b), (a, b)
    assert len(pairs) == 150


def test_interpenetration_zero_at_rest_and_walking_positive_through_torso(body, walk):
    assert interpenetration_energy(body_capsules(body, body())).item() == 0.0
    assert interpenetration_energy(body_capsules(body, body(pose=walk))).max().item() == 0.0
    sitting = _pose(("left_hip", 0, -90), ("right_hip", 0, -90), ("left_knee", 0, 90), ("right_knee", 0, 90))
    assert interpenetration_energy(body_capsules(body, body(pose=sitting))).item() == 0.0
    # the arm hanging down, then pushed 40 degrees further, into the belly
    through = _pose(("left_shoulder", 2, -130))
    r = interpenetration_residuals(body_capsules(body, body(pose=through)))
    worst = interpenetration_pairs()[int(r[0].argmax())]
    assert r.max().item() > 0.04
    assert {CAPSULE_NAMES[worst[0]], CAPSULE_NAMES[worst[1]]} == {"spine2", "left_forearm"}
    # legs crossed through each other
    crossed = _pose(("left_hip", 2, -40))
    assert interpenetration_energy(body_capsules(body, body(pose=crossed))).item() > 1e-3


# -------------------------------------------------------------------------- silhouette


@pytest.fixture(scope="module")
def scene(body):
    H, W = 240, 320
    R, t = look_at((0.3, 0.2, 3.0), (0.0, -0.1, 0.0))
    cam = PinholeCamera.from_focal(W, H, 300.0, R, t)  # 1 cm = 1 px at the body
    pose = torch.tensor(walk_poses(np.array([0.3])))
    caps = body_capsules(body, body(pose=pose))
    s, e, r = _project(caps, cam)
    mask = (capsule_signed_distance(s, e, r, H, W, grid_step=1)[0] <= 0).numpy()
    return {"cam": cam, "pose": pose, "mask": mask, "target": silhouette_target(mask, dtype=torch.float64)}


def _sil_energy(body, scene, trans, **kw):
    caps = body_capsules(body, body(pose=scene["pose"], trans=trans))
    return silhouette_energy(caps, scene["cam"], scene["target"], **kw)


def test_silhouette_energy_near_zero_at_the_mask_and_grows_away(body, scene):
    zero = torch.zeros(1, 3, dtype=torch.float64)
    e0 = _sil_energy(body, scene, zero).item()
    es = [_sil_energy(body, scene, torch.tensor([[dx, 0.0, 0.0]], dtype=torch.float64)).item()
          for dx in (0.02, 0.05, 0.1, 0.2)]
    assert all(b > a for a, b in zip([e0] + es, es))
    assert e0 < 0.05 * es[1]  # the soft edge's floor is small against a 5 px shift
    # the minimum along x and y lies at the true translation (within a grid cell ~ 1 cm)
    for axis in (0, 1):
        steps = np.linspace(-0.03, 0.03, 13)
        vals = []
        for s in steps:
            tr = torch.zeros(1, 3, dtype=torch.float64)
            tr[0, axis] = s
            vals.append(_sil_energy(body, scene, tr).item())
        assert abs(steps[int(np.argmin(vals))]) <= 0.0051
    # a > 0.5 weighs the model leaving the mask: moving closer (bigger) costs more than away
    closer = _sil_energy(body, scene, torch.tensor([[0.0, 0.0, 0.3]], dtype=torch.float64)).item()
    farther = _sil_energy(body, scene, torch.tensor([[0.0, 0.0, -0.3]], dtype=torch.float64)).item()
    assert closer > farther


def test_silhouette_gradient_matches_finite_differences(body, scene):
    trans = torch.tensor([[0.03, -0.02, 0.05]], dtype=torch.float64, requires_grad=True)
    e = _sil_energy(body, scene, trans)
    (g,) = torch.autograd.grad(e.sum(), trans)
    h = 1e-5
    fd = []
    for k in range(3):
        dp = torch.zeros(1, 3, dtype=torch.float64)
        dp[0, k] = h
        fd.append((_sil_energy(body, scene, trans.detach() + dp) - _sil_energy(body, scene, trans.detach() - dp)).item()
                  / (2 * h))
    np.testing.assert_allclose(g[0].numpy(), fd, rtol=1e-4, atol=1e-6 * float(np.abs(fd).max()))


def test_silhouette_residuals_match_a_full_image_evaluation(body, scene):
    trans = torch.tensor([[0.05, 0.02, 0.1]], dtype=torch.float64)
    caps = body_capsules(body, body(pose=scene["pose"], trans=trans))
    cam, tgt = scene["cam"], scene["target"]
    r = silhouette_residuals(caps, cam, tgt, a=0.7, grid_step=2, softness=1.5)
    assert r.shape == (1, cam.height * cam.width)
    s, e, rad = _project(caps, cam)
    sd = capsule_signed_distance(s, e, rad, cam.height, cam.width, 2)[0]
    ref = (0.7 * torch.sigmoid(-sd / 1.5) * tgt.chamfer + 0.3 * tgt.mask * sd.clamp_min(0)) / math.sqrt(tgt.count)
    torch.testing.assert_close(r[0].reshape(cam.height, cam.width), ref, atol=1e-6, rtol=0)
    torch.testing.assert_close(silhouette_energy(caps, cam, tgt, a=0.7, grid_step=2, softness=1.5), (r ** 2).sum(1))


@pytest.mark.parametrize("step", [1, 3, 4])
def test_silhouette_energy_gradient_equals_that_of_its_residuals(body, scene, step):
    # the energy's compiled pass (value and gradient together) against autograd through
    # the residuals' torch form, with a shift that puts part of the body off the image
    for shift in ([0.03, -0.02, 0.05], [0.9, 0.1, 0.0]):
        trans = torch.tensor([shift], dtype=torch.float64, requires_grad=True)
        caps = body_capsules(body, body(pose=scene["pose"], trans=trans))
        kw = dict(a=0.7, grid_step=step, softness=1.5)
        e = silhouette_energy(caps, scene["cam"], scene["target"], **kw)
        ref = (silhouette_residuals(caps, scene["cam"], scene["target"], **kw) ** 2).sum(1)
        (g,) = torch.autograd.grad(e.sum(), trans, retain_graph=True)
        (g_ref,) = torch.autograd.grad(ref.sum(), trans)
        torch.testing.assert_close(e, ref, rtol=1e-12, atol=0)
        torch.testing.assert_close(g, g_ref, rtol=1e-10, atol=1e-12 * float(g_ref.abs().max()))


def test_silhouette_bad_input(body, scene):
    caps = body_capsules(body, body(pose=scene["pose"]))
    with pytest.raises(NoPersonError):
        silhouette_target(np.zeros((240, 320), bool))
    with pytest.raises(InputError):
        silhouette_energy(caps, scene["cam"], silhouette_target(np.ones((60, 80), bool)))
    with pytest.raises(InputError):
        silhouette_energy(caps, scene["cam"], scene["target"], a=1.5)


# ------------------------------------------------------------------ keypoints, priors


def test_keypoint_residuals_geman_mcclure_closed_form_and_missing_joints():
    pred = torch.tensor([[[10.0, 20.0], [30.0, 40.0], [0.0, 0.0]]], dtype=torch.float64)
    obs = torch.tensor([[13.0, 16.0], [1030.0, 40.0], [float("nan"), float("nan")]], dtype=torch.float64)
    conf = torch.tensor([1.0, 0.5, 1.0], dtype=torch.float64)
    sigma = 100.0
    r = keypoint_residuals(pred, obs, conf, sigma)
    x = (pred[0] - torch.nan_to_num(obs)).reshape(-1)
    c = conf.repeat_interleave(2)
    c[4:] = 0
    torch.testing.assert_close(r[0] ** 2, c * sigma ** 2 * x ** 2 / (sigma ** 2 + x ** 2))
    assert torch.sign(r[0, 0]) == -1  # signed: pred - obs
    # small residuals are quadratic, outliers saturate at c sigma^2
    assert abs(r[0, 1].item() ** 2 - 16.0) < 0.03
    assert 0.45 * sigma ** 2 < r[0, 2].item() ** 2 < 0.5 * sigma ** 2
    torch.testing.assert_close(keypoint_energy(pred, obs, conf, sigma), (r ** 2).sum(1))


def test_keypoint_gradient_matches_finite_differences():
    g = torch.Generator().manual_seed(6)
    pred = (100 * torch.randn(2, 12, 2, generator=g, dtype=torch.float64)).requires_grad_()
    obs = 100 * torch.randn(12, 2, generator=g, dtype=torch.float64)
    obs[3] = float("nan")
    conf = torch.rand(12, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda p: keypoint_residuals(p, obs, conf, 50.0), (pred,))
    with pytest.raises(InputError):
        keypoint_residuals(pred, obs[:5], conf)


def test_limb_depth_residuals_closed_form():
    """E_d compares the depth component of each limb's unit direction, whatever the
    detector's scale or origin; a limb mirrored in depth saturates at c sigma^2."""
    from flowmocap.fit.energies import DEPTH_LIMBS, limb_depth_energy, limb_depth_residuals

    g = torch.Generator().manual_seed(11)
    model = torch.randn(1, 24, 3, generator=g, dtype=torch.float64)
    obs = 0.7 * model[0].clone() + torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)  # scaled, moved
    conf = torch.ones(24, dtype=torch.float64)
    torch.testing.assert_close(limb_depth_residuals(model, obs, conf), torch.zeros(1, len(DEPTH_LIMBS), dtype=torch.float64))
    pa, ch = DEPTH_LIMBS[6]  # left knee -> ankle
    mirrored = obs.clone()
    mirrored[ch, 2] = 2 * obs[pa, 2] - obs[ch, 2]  # the shin mirrored in depth
    conf[ch] = 0.5
    sigma = 0.3
    r = limb_depth_residuals(model, mirrored, conf, sigma)
    v = model[0, ch] - model[0, pa]
    x = 2 * v[2] / v.norm()
    torch.testing.assert_close(r[0, 6] ** 2, 0.5 * sigma ** 2 * x ** 2 / (sigma ** 2 + x ** 2))
    assert torch.sign(r[0, 6]) == torch.sign(x)
    others = [k for k, (a, b) in enumerate(DEPTH_LIMBS) if ch not in (a, b)]
    assert torch.allclose(r[0, others], torch.zeros(len(others), dtype=torch.float64))
    torch.testing.assert_close(limb_depth_energy(model, mirrored, conf, sigma), (r ** 2).sum(1))
    missing = conf.clone()
    missing[ch] = 0.0
    assert limb_depth_residuals(model, mirrored, missing, sigma)[0, 6] == 0.0
    with pytest.raises(InputError):
        limb_depth_residuals(model, obs[:12], conf)
    with pytest.raises(InputError):
        limb_depth_residuals(model, obs, conf, sigma=0.0)


def test_limb_depth_gradient_matches_finite_differences():
    from flowmocap.fit.energies import limb_depth_residuals

    g = torch.Generator().manual_seed(12)
    joints = torch.randn(2, 24, 3, generator=g, dtype=torch.float64).requires_grad_()
    obs = torch.randn(24, 3, generator=g, dtype=torch.float64)
    conf = torch.rand(24, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda j: limb_depth_residuals(j, obs, conf, 0.3), (joints,))


def test_pose_and_shape_priors_closed_form():
    g = torch.Generator().manual_seed(7)
    pose = torch.randn(2, 72, generator=g, dtype=torch.float64)
    ref = torch.randn(72, generator=g, dtype=torch.float64)
    d = pose - ref
    torch.testing.assert_close(pose_prior_energy(pose, ref), (d[:, 3:] ** 2).sum(1))  # root weight 0
    w = torch.rand(24, generator=g, dtype=torch.float64)
    torch.testing.assert_close(pose_prior_energy(pose, ref, w), (w.repeat_interleave(3) * d ** 2).sum(1))
    torch.testing.assert_close(pose_prior_residuals(pose, ref, 4.0), 2.0 * d)
    betas = torch.randn(2, 10, generator=g, dtype=torch.float64)
    torch.testing.assert_close(shape_prior_energy(betas), (betas ** 2).sum(1))
    with pytest.raises(InputError):
        pose_prior_energy(pose, ref, torch.ones(5))


def test_temporal_energy_raw_joints_geodesic_root_across_the_wrap():
    g = torch.Generator().manual_seed(8)
    prev = 0.3 * torch.randn(1, 72, generator=g, dtype=torch.float64)
    cur = prev + 0.01 * torch.randn(1, 72, generator=g, dtype=torch.float64)
    r = temporal_residuals(cur, prev)
    torch.testing.assert_close(r[:, 3:], cur[:, 3:] - prev[:, 3:])
    torch.testing.assert_close(r[:, :3], cur[:, :3] - prev[:, :3], atol=2e-3, rtol=0)  # first order
    assert (temporal_residuals(cur, prev, include_root=False)[:, :3] == 0).all()
    # a person facing the camera: root near pi about y; 0.02 rad apart across the wrap
    a, b = prev.clone(), prev.clone()
    a[0, :3] = torch.tensor([0.0, math.pi - 0.01, 0.0])
    b[0, :3] = torch.tensor([0.0, -(math.pi - 0.01), 0.0])
    torch.testing.assert_close(temporal_energy(b, a), torch.tensor([0.02 ** 2], dtype=torch.float64))
    # gradients, also where the pose equals the previous one
    for p in (cur, prev):
        x = p.clone().requires_grad_()
        assert torch.autograd.gradcheck(lambda y: temporal_residuals(y, prev), (x,))


def test_silhouette_accepts_a_bare_mask_and_chamfer_map(body, scene):
    from flowmocap.vision import chamfer_map

    caps = body_capsules(body, body(pose=scene["pose"], trans=torch.tensor([[0.02, 0.0, 0.0]], dtype=torch.float64)))
    ref = silhouette_energy(caps, scene["cam"], scene["target"], a=0.65)
    mask = scene["mask"]
    torch.testing.assert_close(silhouette_energy(caps, scene["cam"], mask, a=0.65), ref)
    cham = torch.as_tensor(chamfer_map(mask))
    torch.testing.assert_close(silhouette_energy(caps, scene["cam"], mask, cham, a=0.65), ref)
    with pytest.raises(InputError):
        silhouette_energy(caps, scene["cam"], mask, cham[:10], a=0.65)


def test_pose_prior_on_joints_without_the_root():
    g = torch.Generator().manual_seed(9)
    pose = torch.randn(2, 72, generator=g, dtype=torch.float64)
    ref = torch.randn(72, generator=g, dtype=torch.float64)
    torch.testing.assert_close(pose_prior_energy(pose[:, 3:], ref[None, 3:]), pose_prior_energy(pose, ref))
    w = torch.rand(23, generator=g, dtype=torch.float64)
    torch.testing.assert_close(pose_prior_energy(pose[:, 3:], ref[3:], w),
                               pose_prior_energy(pose, ref, torch.cat([torch.zeros(1, dtype=torch.float64), w])))


# ------------------------------------------------------------ E_3d: detector 3D joints


def _similar(x, scale=0.7, angle=0.9, shift=(0.3, -1.0, 2.0)):
    """``x (24, 3)`` under a similarity: scaled, rotated about (1, 2, 3), moved."""
    from scipy.spatial.transform import Rotation

    R = torch.as_tensor(Rotation.from_rotvec(angle * np.array([1.0, 2.0, 3.0]) / math.sqrt(14)).as_matrix())
    return scale * x @ R.T + torch.tensor(shift, dtype=x.dtype)


def test_pseudo_huber_is_quadratic_near_zero_and_linear_far_away():
    from flowmocap.fit.energies import pseudo_huber

    s = 0.1
    r = torch.tensor([1e-4, 0.01, 0.1, 1.0, 10.0, 100.0], dtype=torch.float64)
    rho = pseudo_huber(r * r, s)
    torch.testing.assert_close(rho, 2 * s * s * (torch.sqrt(1 + (r / s) ** 2) - 1))  # the textbook form
    assert abs(rho[0] / r[0] ** 2 - 1) < 1e-6  # ~ r^2 below the scale
    torch.testing.assert_close(rho[-1] / (2 * s * r[-1]), torch.tensor(1.0, dtype=torch.float64), rtol=2e-3, atol=0)
    # the slope never vanishes: d rho / d r -> 2 s (Geman-McClure's -> 0)
    x = r.clone().requires_grad_()
    pseudo_huber(x * x, s).sum().backward()
    assert (x.grad[2:] > s).all() and abs(float(x.grad[-1]) - 2 * s) < 1e-3


def test_detector_joints_residuals_closed_form():
    """Zero for any similarity image of the model's joints; otherwise the pseudo-Huber
    cost of each joint's distance after the weighted similarity alignment of the
    detector onto the model; joints with confidence 0 (or NaN) take no part."""
    from flowmocap.fit.energies import detector_joints_energy, detector_joints_residuals, pseudo_huber
    from flowmocap.geometry.procrustes import similarity_procrustes

    g = torch.Generator().manual_seed(21)
    model = torch.randn(1, 24, 3, generator=g, dtype=torch.float64)
    conf = torch.rand(24, generator=g, dtype=torch.float64) * 0.5 + 0.5
    obs = _similar(model[0])
    assert detector_joints_residuals(model, obs, conf).abs().max() < 1e-10
    bent = obs.clone()
    bent[J["left_ankle"]] += torch.tensor([0.0, 0.0, 0.6], dtype=torch.float64)  # an ankle moved in depth
    r = detector_joints_residuals(model, bent, conf, scale=0.1)
    assert r.shape == (1, 72)
    aligned = similarity_procrustes(bent, model[0], weights=conf)[0]
    d2 = ((model[0] - aligned) ** 2).sum(-1)
    expected = (conf * pseudo_huber(d2, 0.1)).sum()
    torch.testing.assert_close(detector_joints_energy(model, bent, conf, 0.1)[0], expected)
    torch.testing.assert_close((r ** 2).sum(), expected)
    per_joint = (r.reshape(24, 3) ** 2).sum(-1)
    torch.testing.assert_close(per_joint, conf * pseudo_huber(d2, 0.1))
    # a joint the detector does not give (confidence 0, or NaN) changes nothing
    off, junk = conf.clone(), bent.clone()
    off[J["right_wrist"]] = 0.0
    junk[J["right_wrist"]] = torch.tensor([5.0, float("nan"), 1.0])
    torch.testing.assert_close(detector_joints_energy(model, junk, off), detector_joints_energy(model, bent, off))
    # fewer than MIN_DETECTOR_JOINTS confident joints: nothing to align, no term
    few = torch.zeros(24, dtype=torch.float64)
    few[:3] = 1.0
    assert (detector_joints_residuals(model, bent, few) == 0).all()


def test_detector_joints_term_keeps_pulling_a_flipped_limb_where_limb_depth_lets_go(body):
    """The ankle of a shin swung ever further out of place: E_d's cost saturates at
    c sigma^2 and its gradient vanishes, E_3d's cost keeps growing about linearly."""
    from flowmocap.fit.energies import detector_joints_energy, limb_depth_energy

    truth = body(pose=_pose(("left_knee", 0, 20.0))).joints  # (1, 24, 3), a slightly bent knee
    conf = torch.ones(24, dtype=torch.float64)
    e3, ed = [], []
    for deg in (40, 80, 120, 160):
        x = body(pose=_pose(("left_knee", 0, 20.0 - deg))).joints
        e3.append(float(detector_joints_energy(x, truth[0], conf, 0.1)))
        ed.append(float(limb_depth_energy(x, truth[0], conf, 0.3)))
    steps3 = np.diff(e3)
    assert (steps3 > 0).all() and steps3[-1] > 0.3 * steps3[0]  # still climbing at the end
    assert max(ed) <= 0.3 ** 2 + 1e-9  # one limb moved: E_d never exceeds c sigma^2


def test_detector_joints_gradient_matches_finite_differences():
    from flowmocap.fit.energies import detector_joints_residuals

    g = torch.Generator().manual_seed(22)
    joints = torch.randn(2, 24, 3, generator=g, dtype=torch.float64).requires_grad_()
    obs = torch.randn(24, 3, generator=g, dtype=torch.float64)
    conf = torch.rand(24, generator=g, dtype=torch.float64)
    conf[[0, 3, 9]] = 0.0
    # through the similarity alignment (its SVD) as well as the robust cost
    assert torch.autograd.gradcheck(lambda j: detector_joints_residuals(j, obs, conf, 0.2), (joints,))


def test_detector_joints_input_errors():
    from flowmocap.fit.energies import detector_joints_residuals

    x = torch.zeros(1, 24, 3, dtype=torch.float64)
    obs, conf = torch.zeros(24, 3), torch.ones(24)
    for args, kw in (((x[0], obs, conf), {}), ((x, obs[:12], conf), {}), ((x, obs, conf[:5]), {}),
                     ((x, obs, -conf), {}), ((x, obs, conf), {"scale": 0.0}), ((x, obs, conf), {"scale": float("nan")})):
        with pytest.raises(InputError):
            detector_joints_residuals(*args, **kw)


def test_silhouette_energy_in_one_node_equals_its_torch_composition(body, scene):
    """silhouette_energy runs the projection, window, exact samples and coverage as one
    autograd node (float64 numpy and compiled passes): equal to the composition of the
    torch pieces with the compiled coverage pass, value and gradient, for a batch of two
    bodies (one partly off the image) and in float32; a capsule behind the camera, and capsules
    off the CPU, are refused."""
    from flowmocap.body.capsules import Capsules
    from flowmocap.fit.energies import _as_target, _silhouette_energy_composed

    trans = torch.tensor([[0.03, -0.02, 0.05], [0.9, 0.1, 0.0]], dtype=torch.float64)
    caps = body_capsules(body, body(pose=scene["pose"].expand(2, -1), trans=trans))
    for dtype in (torch.float64, torch.float32):
        leaves = [x.detach().to(dtype).requires_grad_(True) for x in (caps.start, caps.end, caps.radius)]
        c = Capsules(*leaves)
        for a, step in ((0.6, 8), (0.3, 3)):
            e = silhouette_energy(c, scene["cam"], scene["target"], a=a, grid_step=step)
            ref = _silhouette_energy_composed(c, scene["cam"], _as_target(scene["target"], None, dtype), a, step, 1.0)
            g = torch.autograd.grad(e.sum(), leaves)
            g_ref = torch.autograd.grad(ref.sum(), leaves)
            assert e.dtype == dtype and all(x.dtype == dtype for x in g)
            tol = 1e-12 if dtype == torch.float64 else 1e-4
            torch.testing.assert_close(e, ref, rtol=tol, atol=0)
            for x, y in zip(g, g_ref):
                torch.testing.assert_close(x, y, rtol=tol * 100, atol=tol * float(y.abs().max()))
    at_the_eye = torch.tensor([0.3, 0.2, 3.0], dtype=torch.float64).expand_as(caps.start)  # the camera's centre
    behind = Capsules(at_the_eye, caps.end, caps.radius)
    with pytest.raises(InputError, match="in front of the camera"):
        silhouette_energy(behind, scene["cam"], scene["target"])
    off_cpu = Capsules(*(x.detach().to("meta") for x in (caps.start, caps.end, caps.radius)))
    with pytest.raises(InputError, match="runs on the CPU"):
        silhouette_energy(off_cpu, scene["cam"], scene["target"])


def test_interpenetration_energy_compiled_equals_its_residuals(body):
    """interpenetration_energy's compiled pass against the torch residuals' sum of squares,
    value and gradient (closest points held fixed in both), on bodies with limbs crossed,
    parallel and zero-length segments among the capsules, float64 and float32."""
    poses = torch.stack([_pose(("left_hip", 2, -40), ("right_shoulder", 0, 80), ("right_elbow", 1, 120))[0],
                         _pose(("left_shoulder", 2, 60), ("left_elbow", 1, -140))[0]])
    caps = body_capsules(body, body(pose=poses))
    K = caps.start.shape[1]
    pairs = [(a, b) for a in range(K) for b in range(a + 1, K)]
    for dtype in (torch.float64, torch.float32):
        leaves = [x.detach().to(dtype).requires_grad_(True) for x in (caps.start, caps.end, caps.radius)]
        # a zero-length segment and a parallel copy, the closest-point special cases
        with torch.no_grad():
            leaves[1][0, 3] = leaves[0][0, 3]
            leaves[0][1, 5] = leaves[0][1, 4] + 0.01
            leaves[1][1, 5] = leaves[1][1, 4] + 0.01
        c = Capsules(*leaves)
        for pr, tol in ((None, DEFAULT_TOLERANCE), (pairs, 0.0)):
            e = interpenetration_energy(c, pr, tol)
            ref = (interpenetration_residuals(c, pr, tol) ** 2).sum(1)
            assert float(ref.detach()[0]) > 0  # the crossed legs and the arm through the trunk
            g = torch.autograd.grad(e.sum(), leaves)
            g_ref = torch.autograd.grad(ref.sum(), leaves)
            tol_ = 1e-12 if dtype == torch.float64 else 2e-4
            torch.testing.assert_close(e, ref, rtol=tol_, atol=1e-12)
            for x, y in zip(g, g_ref):
                torch.testing.assert_close(x, y, rtol=tol_ * 10, atol=tol_ * float(y.abs().max()))


def test_coverage_pass_value_and_gradcheck_on_the_distance_grid():
    """_CoverageEnergy (the compiled E_c pass over the exact distance samples): its value
    against the torch form (bilinear upsampling as capsule_signed_distance, sigmoid and
    relu parts) and its gradient w.r.t. every sample by torch.autograd.gradcheck, B = 2."""
    import torch.nn.functional as F

    from flowmocap.fit.energies import _CoverageEnergy

    rng = np.random.default_rng(4)
    step, h, w = 3, 8, 10
    gh, gw = (h - 1) // step + 2, (w - 1) // step + 2
    grid = torch.tensor(rng.uniform(-4.0, 4.0, (2, gh, gw)), requires_grad=True)
    mask = (rng.random((h, w)) > 0.5).astype(np.float64)
    cham = np.where(mask > 0, 0.0, rng.uniform(0.5, 6.0, (h, w)))
    a, soft, scale = 0.6, 1.3, 1.0 / math.sqrt(mask.sum())

    up = F.interpolate(grid[:, None], size=((gh - 1) * step + 1, (gw - 1) * step + 1), mode="bilinear",
                       align_corners=True)[:, 0, :h, :w]
    m, c = torch.tensor(mask), torch.tensor(cham)
    ref = ((scale * (a * torch.sigmoid(-up / soft) * c + (1 - a) * m * torch.relu(up))) ** 2).sum((1, 2))
    e = _CoverageEnergy.apply(grid, mask, cham, step, a, soft, scale)
    torch.testing.assert_close(e, ref, rtol=1e-12, atol=0)
    assert torch.autograd.gradcheck(lambda g: _CoverageEnergy.apply(g, mask, cham, step, a, soft, scale), (grid,),
                                    eps=1e-6, atol=1e-7)


@pytest.mark.parametrize("silhouette_model", ["capsules", "mesh"])
def test_frame_energy_with_every_smooth_term_matches_finite_differences(silhouette_model):
    """The per-frame objective with E_c (the capsules' or, as the video profile has it, the
    mesh's), E_b, E_sp, E_theta, E_a, E_j, E_d, E_3d, the learned and uncovered priors and
    E_z all on (no E_f, whose occlusion-boundary part is by design not the derivative:
    tests/test_render_flow.py checks it against pixel steps): autograd through the compiled
    body, capsule and term passes against central differences in pose and trans."""
    from flowmocap.body import load_body_model
    from flowmocap.fit import energies as en
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.fit.objective import FrameData, FrameState, Scene, frame_energy, keypoint_observation
    from flowmocap.geometry import PinholeCamera, look_at
    from flowmocap.io import walk_poses

    R, t = look_at((0.3, 0.2, 3.0), (0.0, -0.1, 0.0))
    cam = PinholeCamera.from_focal(160, 120, 150.0, R, t)
    scene = Scene(load_body_model("default", dtype=torch.float64), torch.zeros(1, 10, dtype=torch.float64), cam)
    truth = torch.tensor(walk_poses(np.array([0.3]))[0])
    rng = np.random.default_rng(6)
    with torch.no_grad():
        out, px, _ = scene.forward(truth, torch.zeros(3, dtype=torch.float64))
        caps = scene.capsules(out)
        s, e, r = en._project(caps, cam)
        from flowmocap.render import capsule_signed_distance
        mask = (capsule_signed_distance(s, e, r, 120, 160, grid_step=1)[0] <= 0).numpy()
        j2d = cam.project(out.joints[0]).numpy() + rng.normal(0, 3.0, (24, 2))
        j3d = (out.joints[0].numpy() @ np.asarray(R).T) * 1.3 + rng.normal(0, 0.03, (24, 3))
    cfg = TrackerConfig(flow_weight=0.0, silhouette_weight=5.0, limit_weight=1.0, penetration_weight=10.0,
                        temporal_weight=2.0, anchor_weight=0.5, keypoint_weight=1.0, keypoint_offsets=False,
                        limb_depth_weight=3.0, detector3d_weight=4.0, pose_prior_weight=0.01,
                        uncovered_prior_weight=0.5, depth_temporal_weight=7.0, silhouette_model=silhouette_model)
    data = FrameData(mask=mask, silhouette=en.silhouette_target(mask, dtype=torch.float64),
                     person_pixels=float(mask.sum()),
                     keypoints=keypoint_observation(j2d, np.full(24, 0.9)), anchor=truth.clone(),
                     joints3d=(j3d, np.full(24, 0.8)),
                     depth_ref=(torch.tensor([0.01, 0.0, 0.02], dtype=torch.float64),
                                torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64)))
    pose0 = truth + torch.tensor(rng.normal(0, 0.05, 72))
    pose0[3 * 4] = -0.3  # the left knee bent backwards: E_b on
    trans0 = torch.tensor([0.02, -0.01, 0.03], dtype=torch.float64)
    ref_pose = truth.clone()

    def E(p, tr):
        return frame_energy(scene, FrameState(p, tr), data, cfg, None, None, ref_pose)

    p, tr = pose0.clone().requires_grad_(), trans0.clone().requires_grad_()
    total, terms = E(p, tr)
    assert min(terms.values()) > 0
    assert set(terms) >= {"silhouette", "limits", "temporal", "keypoints", "anchor", "limb_depth", "detector3d",
                          "learned_prior", "depth_temporal", "penetration"}
    gp, gt = torch.autograd.grad(total, (p, tr))
    # the mesh's coverage is piecewise smooth (a pixel centre crossing an edge is a kink the
    # size of one pixel's share): steps of 1e-4..1e-6 straddle kinks and move the difference
    # by up to 1e-3 relative; at 1e-7 it meets the local derivative
    h = 1e-6 if silhouette_model == "capsules" else 1e-7
    for which, k in [("t", 0), ("t", 2), ("p", 0), ("p", 4), ("p", 3 * 4), ("p", 3 * 18 + 1), ("p", 3 * 16 + 2),
                     ("p", 3 * 2)]:
        d = torch.zeros(72 if which == "p" else 3, dtype=torch.float64)
        d[k] = h
        if which == "p":
            fd = (float(E(pose0 + d, trans0)[0]) - float(E(pose0 - d, trans0)[0])) / (2 * h)
            g = float(gp[k])
        else:
            fd = (float(E(pose0, trans0 + d)[0]) - float(E(pose0, trans0 - d)[0])) / (2 * h)
            g = float(gt[k])
        assert g == pytest.approx(fd, rel=1e-5, abs=1e-6), (which, k, g, fd)

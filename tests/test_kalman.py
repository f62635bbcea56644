"""Tests for flowmocap.fit.kalman: SO(3) helpers, rotation EKF, translation KF, PoseFilter."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flowmocap.errors import InputError
from flowmocap.fit.kalman import (
    DEFAULTS,
    PoseFilter,
    RotationEKF,
    TranslationKF,
    error_transition,
    nearest_rotvec,
    so3_exp,
    so3_log,
    so3_right_jacobian,
)


def unit_axes(n, seed=0):
    a = np.random.default_rng(seed).normal(size=(n, 3))
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def angle_between(Ra, Rb):
    """Geodesic distance (rad) between rotation matrices."""
    return np.linalg.norm(so3_log(np.swapaxes(Ra, -1, -2) @ Rb), axis=-1)


AXES = np.concatenate([np.eye(3), -np.eye(3), unit_axes(40, seed=3)])
ANGLES = [0.0, 1e-12, 1e-8, 1e-5, 1e-3, 0.3, 0.999, 1.0, 1.001, 2.0, 3.0,
          math.pi - 1e-5, math.pi - 1e-9, math.pi]


# ------------------------------------------------------------------------------ SO(3)


@pytest.mark.parametrize("angle", ANGLES)
def test_so3_exp_log_match_scipy(angle):
    rv = AXES * angle
    R_ref = Rotation.from_rotvec(rv).as_matrix()
    np.testing.assert_allclose(so3_exp(rv), R_ref, atol=2e-15, rtol=0)
    log = so3_log(R_ref)
    ref = Rotation.from_matrix(R_ref).as_rotvec()
    if angle == math.pi:  # +-pi * axis are the same rotation
        ref = np.where((np.sum(log * ref, axis=1) < 0)[:, None], -ref, ref)
    np.testing.assert_allclose(log, ref, atol=2e-15 * max(1.0, angle), rtol=0)
    # round trip (angle <= pi: the log gives the same vector back)
    back = so3_log(so3_exp(rv))
    if angle == math.pi:
        back = np.where((np.sum(back * rv, axis=1) < 0)[:, None], -back, back)
    np.testing.assert_allclose(back, rv, atol=4e-15, rtol=0)


def test_so3_tiny_angles_are_exact():
    rv = AXES * 1e-7
    np.testing.assert_allclose(so3_log(so3_exp(rv)), rv, rtol=1e-14, atol=0)
    R = so3_exp(rv)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-15)


def test_so3_shapes_broadcast():
    rv = np.random.default_rng(1).normal(size=(2, 5, 3))
    assert so3_exp(rv).shape == (2, 5, 3, 3)
    assert so3_log(so3_exp(rv)).shape == (2, 5, 3)
    assert so3_right_jacobian(rv).shape == (2, 5, 3, 3)
    assert so3_exp(np.zeros(3)).shape == (3, 3)


@pytest.mark.parametrize("angle", [0.0, 1e-6, 0.5, 0.999, 1.001, 2.5, 3.1])
def test_right_jacobian_matches_finite_differences(angle):
    eps = 1e-6
    for phi in AXES[::5] * angle:
        E = so3_exp(phi)
        J = np.stack([
            (so3_log(E.T @ so3_exp(phi + eps * e)) - so3_log(E.T @ so3_exp(phi - eps * e)))
            / (2 * eps)
            for e in np.eye(3)], axis=1)
        np.testing.assert_allclose(so3_right_jacobian(phi), J, atol=1e-8)


def test_nearest_rotvec_keeps_numbers_continuous():
    u = np.array([0.0, 0.6, 0.8])
    # a measurement past pi, expressed continuously, and the same rotation from the log
    cont = 3.4 * u
    logged = so3_log(so3_exp(cont))
    assert np.linalg.norm(logged) <= math.pi
    np.testing.assert_allclose(nearest_rotvec(logged, 3.3 * u), cont, atol=1e-12)
    np.testing.assert_allclose(nearest_rotvec(logged, -2.8 * u), logged, atol=1e-12)
    np.testing.assert_allclose(nearest_rotvec(np.zeros(3), 6.2 * u), 2 * math.pi * u, atol=1e-12)
    np.testing.assert_allclose(nearest_rotvec(np.zeros(3), np.zeros(3)), np.zeros(3))


# ----------------------------------------------------------------- rotation EKF model


def error_dynamics(omega, dt, x):
    """The exact error-state map (dtheta, domega) -> (dtheta', domega') of one predict step."""
    dth, dw = x[:3], x[3:]
    nxt = so3_log(so3_exp(omega * dt).T @ so3_exp(dth) @ so3_exp((omega + dw) * dt))
    return np.concatenate([nxt, dw])


@pytest.mark.parametrize("speed", [0.0, 1e-7, 0.05, 0.4, 1.5, 2.9])
@pytest.mark.parametrize("dt", [1.0, 0.5])
def test_error_transition_matches_finite_differences(speed, dt):
    eps = 1e-6
    for axis in AXES[::7]:
        omega = speed * axis
        Fn = np.stack([
            (error_dynamics(omega, dt, eps * e) - error_dynamics(omega, dt, -eps * e)) / (2 * eps)
            for e in np.eye(6)], axis=1)
        F = error_transition(omega, dt)
        np.testing.assert_allclose(F, Fn, atol=1e-8)
        f = RotationEKF(np.array([0.3, -1.0, 2.0]), init_omega=omega, dt=dt)
        np.testing.assert_allclose(f.transition_jacobian(), F)


def constant_rotation(R0, world_rate, frames):
    """R_k = Exp(k * world_rate) R0: constant angular velocity about a parent-frame axis."""
    return np.stack([so3_exp(k * world_rate) @ R0 for k in range(frames)])


def test_ekf_predicts_constant_rotation_exactly_through_pi():
    # Rotation about z (0.25 rad/frame) of a rotation that starts 1 rad about x: the
    # angle of R_k passes pi near k = 22.6, where the axis-angle numbers jump to the
    # antipode.
    frames = 45
    R0 = so3_exp([0.0, 0.0, -2.5]) @ so3_exp([1.0, 0.0, 0.0])
    R = constant_rotation(R0, np.array([0.0, 0.0, 0.25]), frames)
    meas = so3_log(R)  # |meas| <= pi: what a log map would hand over
    norms = np.linalg.norm(meas, axis=1)
    jumps = np.linalg.norm(np.diff(meas, axis=0), axis=1)
    wrap = int(np.argmax(jumps)) + 1
    assert jumps.max() > 5.0 and norms.max() > 3.0 and wrap > 15  # the raw numbers do jump

    f = RotationEKF(meas[0])
    err, naive = {}, {}
    for k in range(1, frames):
        err[k] = angle_between(so3_exp(f.predict()), R[k])
        if k >= 2:
            naive[k] = angle_between(so3_exp(2 * meas[k - 1] - meas[k - 2]), R[k])
        f.update(meas[k])
    late = [err[k] for k in range(15, frames)]
    assert max(late) < 1e-6, late
    assert max(err[wrap], err[wrap + 1]) < 1e-6
    # the filter's angular velocity is the body-frame rate R0^T a (|a| = 0.25)
    np.testing.assert_allclose(np.linalg.norm(f.omega), 0.25, atol=1e-9)
    # naive component-wise extrapolation of axis-angle numbers: wrong everywhere the
    # axis turns, and much worse across the jump
    assert min(naive.values()) > 5e-3
    assert max(naive[wrap], naive[wrap + 1]) > 0.1
    assert max(naive[wrap], naive[wrap + 1]) > 8 * np.median(list(naive.values()))


def test_ekf_fixed_axis_through_identity_and_pi():
    # pure rotation about one axis, 0.3 rad/frame, angle runs 0 -> 13 rad (crosses pi,
    # 2 pi, 3 pi, 4 pi); measurements as matrices
    frames = 45
    u = unit_axes(1, seed=5)[0]
    R = constant_rotation(np.eye(3), 0.3 * u, frames)
    f = RotationEKF(np.eye(3))
    for k in range(1, frames):
        pred = f.predict()
        if k >= 15:
            assert angle_between(so3_exp(pred), R[k]) < 1e-6
        f.update(R[k])
    # continuous axis-angle output when the measurements are continuous past pi
    f = RotationEKF(0.0 * u)
    for k in range(1, frames):
        pred = f.predict()
        if k >= 15:
            np.testing.assert_allclose(pred, (0.3 * k) * u, atol=1e-6)
        f.update((0.3 * k) * u)


def test_ekf_velocity_converges_in_a_few_frames():
    rate = np.array([0.05, -0.08, 0.03])  # rad/frame
    R = constant_rotation(so3_exp([0.2, 0.4, -0.1]), rate, 12)
    f = RotationEKF(R[0])
    errs = []
    for k in range(1, 12):
        errs.append(angle_between(so3_exp(f.predict()), R[k]))
        f.update(R[k])
    assert errs[0] == pytest.approx(np.linalg.norm(rate), rel=1e-9)  # omega starts at 0
    assert errs[1] < 0.01 * errs[0]  # after two measurements
    assert errs[3] < 1e-3 * errs[0]


def test_ekf_noisy_prediction_beats_measurement_noise():
    """Constant angular velocity, noisy measurements: the tuned filter's prediction is
    more accurate than a raw measurement; the default filter's a-posteriori estimate too."""
    rng = np.random.default_rng(1234)
    sigma, frames, warm = 0.02, 400, 20
    R = constant_rotation(so3_exp([0.5, 1.0, -2.0]), np.array([0.02, 0.07, -0.04]), frames)
    Rm = R @ so3_exp(rng.normal(scale=sigma, size=(frames, 3)))
    tuned = RotationEKF(Rm[0], accel_noise=1e-4, meas_noise=sigma)
    default = RotationEKF(Rm[0])
    e_tuned, e_def_prior, e_def_post = [], [], []
    for k in range(1, frames):
        p1, p2 = tuned.predict(), default.predict()
        if k >= warm:
            e_tuned.append(angle_between(so3_exp(p1), R[k]))
            e_def_prior.append(angle_between(so3_exp(p2), R[k]))
        tuned.update(Rm[k])
        post = default.update(Rm[k])
        if k >= warm:
            e_def_post.append(angle_between(so3_exp(post), R[k]))
    rms = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    meas = rms(angle_between(Rm[warm:], R[warm:]))  # ~ sigma * sqrt(3)
    print(f"\nrotation RMS error (rad): measurement {meas:.4f}, tuned prediction "
          f"{rms(e_tuned):.4f}, default prediction {rms(e_def_prior):.4f}, "
          f"default a posteriori {rms(e_def_post):.4f}")
    assert meas == pytest.approx(sigma * math.sqrt(3), rel=0.1)
    assert rms(e_tuned) < 0.5 * meas
    assert rms(e_def_post) < meas


# ----------------------------------------------------------------------- translation


def test_translation_kf_predicts_constant_velocity_exactly():
    p0, v = np.array([0.1, 0.9, 3.0]), np.array([0.021, -0.003, 0.012])
    f = TranslationKF(p0)
    for k in range(1, 40):
        pred = f.predict()
        if k >= 15:
            np.testing.assert_allclose(pred, p0 + k * v, atol=1e-6, rtol=0)
        f.update(p0 + k * v)
    np.testing.assert_allclose(f.velocity, v, atol=1e-9)
    np.testing.assert_allclose(f.kf.F[:3, 3:], np.eye(3))


def test_translation_kf_noisy_prediction_beats_measurement_noise():
    rng = np.random.default_rng(99)
    sigma, frames, warm = 0.01, 400, 20
    p = np.array([0.0, 1.0, 4.0]) + np.arange(frames)[:, None] * np.array([0.02, 0.0, -0.01])
    z = p + rng.normal(scale=sigma, size=p.shape)
    f = TranslationKF(z[0], accel_noise=1e-5, meas_noise=sigma)
    err = []
    for k in range(1, frames):
        pred = f.predict()
        if k >= warm:
            err.append(np.linalg.norm(pred - p[k]))
        f.update(z[k])
    meas = float(np.sqrt(np.mean(np.sum((z[warm:] - p[warm:]) ** 2, axis=1))))
    pred_rms = float(np.sqrt(np.mean(np.square(err))))
    print(f"\ntranslation RMS error (m): measurement {meas:.4f}, prediction {pred_rms:.4f}")
    assert pred_rms < 0.5 * meas


# ------------------------------------------------------------------------ PoseFilter


def walk_like(frames, seed=0):
    """Smooth synthetic poses: each joint at its own constant body-frame angular velocity
    (the global orientation near pi, as for a person facing an OpenCV camera)."""
    rng = np.random.default_rng(seed)
    R0 = so3_exp(rng.normal(scale=0.4, size=(24, 3)))
    R0[0] = so3_exp([math.pi - 0.05, 0.0, 0.0])
    rate = rng.normal(scale=0.04, size=(24, 3))
    rate[0] = [0.0, 0.0, 0.03]
    R = np.stack([R0 @ so3_exp(k * rate) for k in range(frames)])
    trans = np.array([0.0, 0.9, 3.5]) + np.arange(frames)[:, None] * np.array([0.02, 0.0, 0.0])
    return R, trans


def test_pose_filter_predicts_constant_motion():
    R, trans = walk_like(30)
    poses = so3_log(R).reshape(30, 72)
    f = PoseFilter(poses[0], trans[0])
    for k in range(1, 30):
        pose, t = f.predict()
        assert pose.shape == (72,) and t.shape == (3,)
        if k >= 15:
            assert angle_between(so3_exp(pose.reshape(24, 3)), R[k]).max() < 1e-6
            np.testing.assert_allclose(t, trans[k], atol=1e-6)
        f.update(poses[k], trans[k])
    assert f.steps == 29


def test_pose_filter_equals_24_independent_joint_filters():
    R, trans = walk_like(12, seed=3)
    rng = np.random.default_rng(0)
    poses = (so3_log(R @ so3_exp(rng.normal(scale=0.01, size=R.shape[:-1])))).reshape(12, 72)
    accel = np.linspace(0.01, 0.05, 24)
    f = PoseFilter(poses[0], trans[0], rot_accel_noise=accel, rot_meas_noise=0.02)
    singles = [RotationEKF(poses[0, 3 * j:3 * j + 3], accel_noise=accel[j], meas_noise=0.02)
               for j in range(24)]
    for k in range(1, 12):
        pose, _ = f.predict()
        single = np.concatenate([s.predict() for s in singles])
        np.testing.assert_allclose(pose, single, atol=1e-12)
        f.update(poses[k], trans[k])
        for j, s in enumerate(singles):
            s.update(poses[k, 3 * j:3 * j + 3])
    for j in range(24):  # the per-joint views share the stacked state
        np.testing.assert_allclose(f.joints[j].omega, singles[j].omega, atol=1e-12)
        np.testing.assert_allclose(f.joints[j].covariance, singles[j].covariance, atol=1e-12)
        assert f.joints[j].accel_noise == accel[j]


def test_pose_filter_output_stays_continuous_near_pi():
    # global orientation measured continuously past pi (as an optimiser would move it)
    u = np.array([1.0, 0.0, 0.0])
    frames = 30
    poses = np.zeros((frames, 72))
    poses[:, :3] = (3.0 + 0.02 * np.arange(frames))[:, None] * u
    f = PoseFilter(poses[0], np.zeros(3))
    for k in range(1, frames):
        pose, _ = f.predict()
        assert np.linalg.norm(pose[:3] - poses[k, :3]) < 0.05  # no 2 pi jump
        f.update(poses[k], np.zeros(3))
    assert np.linalg.norm(f.pose[:3]) > math.pi


def test_state_dict_round_trip_is_exact():
    R, trans = walk_like(30, seed=7)
    rng = np.random.default_rng(2)
    poses = so3_log(R @ so3_exp(rng.normal(scale=0.01, size=R.shape[:-1]))).reshape(30, 72)
    trans = trans + rng.normal(scale=0.003, size=trans.shape)
    f = PoseFilter(poses[0], trans[0], rot_accel_noise=np.linspace(0.01, 0.03, 24))
    for k in range(1, 12):
        f.predict()
        f.update(poses[k], trans[k])
    g = PoseFilter.from_state_dict(json.loads(json.dumps(f.state_dict())))
    assert g.steps == f.steps
    for k in range(12, 30):
        pf, tf = f.predict()
        pg, tg = g.predict()
        np.testing.assert_array_equal(pf, pg)
        np.testing.assert_array_equal(tf, tg)
        uf, ug = f.update(poses[k], trans[k]), g.update(poses[k], trans[k])
        np.testing.assert_array_equal(uf[0], ug[0])
    assert json.dumps(f.state_dict()) == json.dumps(g.state_dict())

    r = RotationEKF([0.1, 0.2, 0.3])
    r.predict()
    r.update([0.12, 0.22, 0.31])
    r2 = RotationEKF.from_state_dict(json.loads(json.dumps(r.state_dict())))
    np.testing.assert_array_equal(r.predict(), r2.predict())
    t = TranslationKF([1.0, 2.0, 3.0])
    t.predict()
    t.update([1.01, 2.0, 3.02])
    t2 = TranslationKF.from_state_dict(json.loads(json.dumps(t.state_dict())))
    np.testing.assert_array_equal(t.predict(), t2.predict())


def test_defaults_are_documented_and_used():
    f = PoseFilter(np.zeros(72), np.zeros(3))
    assert f.joints[0].accel_noise == DEFAULTS["rot_accel_noise"]
    assert f.joints[5].meas_noise == DEFAULTS["rot_meas_noise"]
    assert f.translation.accel_noise == DEFAULTS["trans_accel_noise"]
    assert f.translation.meas_noise == DEFAULTS["trans_meas_noise"]
    # the optimised pose dominates the estimate: measurement noise below process noise
    assert DEFAULTS["rot_meas_noise"] <= DEFAULTS["rot_accel_noise"]
    assert DEFAULTS["trans_meas_noise"] <= DEFAULTS["trans_accel_noise"]


# ---------------------------------------------------------------------- bad inputs


@pytest.mark.parametrize("pose", [np.zeros(71), np.zeros((24, 2)), np.zeros((1, 72)), "abc",
                                  np.full(72, np.nan)])
def test_bad_pose_raises_input_error(pose):
    with pytest.raises(InputError):
        PoseFilter(pose, np.zeros(3))
    f = PoseFilter(np.zeros(72), np.zeros(3))
    f.predict()
    with pytest.raises(InputError):
        f.update(pose, np.zeros(3))


@pytest.mark.parametrize("trans", [np.zeros(2), np.zeros((1, 3)), [0.0, np.inf, 0.0], None])
def test_bad_trans_raises_input_error(trans):
    with pytest.raises(InputError):
        PoseFilter(np.zeros(72), trans)
    with pytest.raises(InputError):
        PoseFilter(np.zeros(72), np.zeros(3)).update(np.zeros(72), trans)
    with pytest.raises(InputError):
        TranslationKF(np.zeros(3)).update(trans)


def test_bad_rotation_and_settings_raise_input_error():
    with pytest.raises(InputError):
        RotationEKF(np.zeros(4))
    with pytest.raises(InputError):
        RotationEKF(2.0 * np.eye(3))  # not a rotation
    with pytest.raises(InputError):
        RotationEKF(np.diag([1.0, 1.0, -1.0]))  # a reflection
    with pytest.raises(InputError):
        RotationEKF(np.zeros(3)).update(np.zeros((2, 3)))
    with pytest.raises(InputError):
        RotationEKF(np.zeros(3), init_omega=np.zeros(2))
    for kw in ({"dt": 0.0}, {"accel_noise": -1.0}, {"meas_noise": float("nan")}):
        with pytest.raises(InputError):
            RotationEKF(np.zeros(3), **kw)
    with pytest.raises(InputError):
        PoseFilter(np.zeros(72), np.zeros(3), rot_accel_noise=np.ones(23))
    with pytest.raises(InputError):
        PoseFilter(np.zeros(72), np.zeros(3), trans_meas_noise=0.0)


def test_bad_state_dict_raises_input_error():
    good = PoseFilter(np.zeros(72), np.zeros(3)).state_dict()
    with pytest.raises(InputError):
        PoseFilter.from_state_dict({"format": "something else"})
    with pytest.raises(InputError):
        PoseFilter.from_state_dict({**good, "version": 99})
    broken = {**good, "P": np.zeros((24, 5, 5)).tolist()}
    with pytest.raises(InputError):
        PoseFilter.from_state_dict(broken)
    missing = dict(good)
    del missing["omega"]
    with pytest.raises(InputError):
        PoseFilter.from_state_dict(missing)
    with pytest.raises(InputError):
        RotationEKF.from_state_dict([1, 2, 3])
    with pytest.raises(InputError):
        TranslationKF.from_state_dict({"dt": 1.0})


def test_rotation_ekf_covariance_uses_the_tested_jacobians():
    """_ekf_predict builds F inline (a copy of error_transition, which tests/test_kalman.py
    checks against finite differences) and _ekf_update resets the covariance with
    G = diag(J_r(dx), I): predict and update against their closed forms with those
    matrices, and J_r(dx) against central differences of the reset map
    e -> Log(Exp(dx)^T Exp(dx + e))."""
    from flowmocap.fit.kalman import RotationEKF, error_transition, so3_exp, so3_log, so3_right_jacobian

    dt, sa, sm = 0.5, 0.3, 0.05
    f = RotationEKF(np.array([0.4, -1.1, 2.0]), init_omega=np.array([0.2, -0.5, 0.3]), dt=dt, accel_noise=sa,
                    meas_noise=sm, init_vel_std=0.2)
    f.update(so3_exp(np.array([0.45, -1.0, 2.05])))  # a full covariance
    # predict
    P0, w, R0 = f.covariance, f.omega, f.matrix
    F = error_transition(w, dt)
    np.testing.assert_allclose(f.transition_jacobian(), F)
    f.predict()
    Jr = so3_right_jacobian(w * dt)
    G = np.vstack([0.5 * dt * dt * Jr, dt * np.eye(3)])
    np.testing.assert_allclose(f.covariance, F @ P0 @ F.T + sa ** 2 * G @ G.T, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(f.matrix, R0 @ so3_exp(w * dt), atol=1e-14)
    # update
    P, R, w = f.covariance, f.matrix, f.omega
    Rm = so3_exp(so3_log(R) + np.array([0.03, -0.02, 0.04]))
    y = so3_log(R.T @ Rm)
    S = P[:3, :3] + sm ** 2 * np.eye(3)
    K = P[:, :3] @ np.linalg.inv(S)
    dx = K @ y
    IKH = np.eye(6)
    IKH[:, :3] -= K
    Pn = IKH @ P @ IKH.T + sm ** 2 * K @ K.T
    Gr = np.eye(6)
    Gr[:3, :3] = so3_right_jacobian(dx[:3])
    f.update(Rm)
    np.testing.assert_allclose(f.covariance, Gr @ Pn @ Gr.T, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(f.omega, w + dx[3:], atol=1e-14)
    np.testing.assert_allclose(f.matrix, R @ so3_exp(dx[:3]), atol=1e-12)
    # the reset Jacobian is that of the reset map
    reset = lambda e: so3_log(so3_exp(dx[:3]).T @ so3_exp(dx[:3] + e))  # noqa: E731
    h = 1e-6
    fd = np.stack([(reset(h * e) - reset(-h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(so3_right_jacobian(dx[:3]), fd, atol=1e-8)

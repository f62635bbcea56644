"""Tests for flowmocap.geometry: rotations against scipy, gradients, camera, Procrustes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from flowmocap.errors import InputError
from flowmocap.geometry import (
    PinholeCamera,
    axis_angle_to_matrix,
    axis_angle_to_quaternion,
    euler_to_matrix,
    look_at,
    matrix_to_axis_angle,
    matrix_to_euler,
    matrix_to_quaternion,
    matrix_to_rotation_6d,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_to_axis_angle,
    quaternion_to_matrix,
    rotation_6d_to_matrix,
    similarity_procrustes,
)

F64 = torch.float64
TAIT_BRYAN = ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"]
PROPER = ["XYX", "XZX", "YXY", "YZY", "ZXZ", "ZYZ"]


def rng(seed=0):
    return np.random.default_rng(seed)


def unit_axes(n, seed=0):
    a = rng(seed).normal(size=(n, 3))
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def random_rotvecs(n=64, seed=0, max_angle=math.pi):
    g = rng(seed)
    return unit_axes(n, seed + 1) * g.uniform(0, max_angle, size=(n, 1))


# Rotation vectors at the awkward angles, with random axes plus the coordinate axes.
SPECIAL_ANGLES = [0.0, 1e-8, 1e-4, 0.0999, 0.1001, math.pi - 1e-6, math.pi]


def special_rotvecs(angle):
    axes = np.concatenate([np.eye(3), -np.eye(3), unit_axes(10, seed=7)])
    return torch.tensor(axes * angle, dtype=F64)


def scipy_quat_wxyz(rotvec):
    xyzw = Rotation.from_rotvec(np.asarray(rotvec)).as_quat()
    return np.roll(xyzw, 1, axis=-1)


def same_rotation_quat(q1, q2, atol):
    """q and -q are the same rotation."""
    q1, q2 = np.asarray(q1), np.asarray(q2)
    d = np.minimum(np.abs(q1 - q2).max(-1), np.abs(q1 + q2).max(-1))
    return np.all(d < atol)


def skew_np(v):
    x, y, z = v
    return np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])


# ------------------------------------------------------------------ against scipy


def test_axis_angle_to_matrix_matches_scipy_random_including_beyond_pi():
    v = rng(1).normal(size=(200, 3)) * 2.0  # angles up to ~3 pi
    R = axis_angle_to_matrix(torch.tensor(v, dtype=F64)).numpy()
    np.testing.assert_allclose(R, Rotation.from_rotvec(v).as_matrix(), atol=1e-14)
    R32 = axis_angle_to_matrix(torch.tensor(v, dtype=torch.float32))
    assert R32.dtype == torch.float32
    np.testing.assert_allclose(R32.numpy(), Rotation.from_rotvec(v).as_matrix(), atol=2e-6)


@pytest.mark.parametrize("angle", SPECIAL_ANGLES)
def test_axis_angle_to_matrix_matches_scipy_special_angles(angle):
    v = special_rotvecs(angle)
    np.testing.assert_allclose(
        axis_angle_to_matrix(v).numpy(), Rotation.from_rotvec(v.numpy()).as_matrix(), atol=1e-15, rtol=0
    )


def test_matrix_to_axis_angle_matches_scipy_random():
    v = random_rotvecs(200, seed=3)
    R = torch.tensor(Rotation.from_rotvec(v).as_matrix())
    out = matrix_to_axis_angle(R).numpy()
    np.testing.assert_allclose(out, v, atol=1e-13)
    assert np.all(np.linalg.norm(out, axis=-1) <= math.pi + 1e-12)


def test_quaternions_match_scipy_scalar_last_rolled():
    v = random_rotvecs(100, seed=4)
    q_ref = scipy_quat_wxyz(v)  # scipy is (x, y, z, w); ours is (w, x, y, z)
    q = axis_angle_to_quaternion(torch.tensor(v)).numpy()
    np.testing.assert_allclose(q, q_ref * np.sign(q_ref[:, :1]), atol=1e-14)
    qm = matrix_to_quaternion(torch.tensor(Rotation.from_rotvec(v).as_matrix())).numpy()
    assert np.all(qm[:, 0] >= 0)
    assert same_rotation_quat(qm, q_ref, 1e-14)
    Rq = quaternion_to_matrix(torch.tensor(q_ref)).numpy()
    np.testing.assert_allclose(Rq, Rotation.from_rotvec(v).as_matrix(), atol=1e-14)
    rv = quaternion_to_axis_angle(torch.tensor(q_ref)).numpy()
    np.testing.assert_allclose(rv, v, atol=1e-13)


@pytest.mark.parametrize("order", TAIT_BRYAN + PROPER)
def test_euler_to_matrix_pinned_to_scipy(order):
    angles = rng(5).uniform(-math.pi, math.pi, size=(50, 3))
    t = torch.tensor(angles)
    # upper case: intrinsic, R = R_first @ R_second @ R_third (BVH / ASF channel order)
    np.testing.assert_allclose(
        euler_to_matrix(t, order).numpy(), Rotation.from_euler(order, angles).as_matrix(), atol=1e-14
    )
    # lower case: extrinsic, as scipy
    np.testing.assert_allclose(
        euler_to_matrix(t, order.lower()).numpy(),
        Rotation.from_euler(order.lower(), angles).as_matrix(), atol=1e-14,
    )
    # and the documented product forms
    e = [Rotation.from_euler(a.lower(), angles[:, k:k + 1]).as_matrix() for k, a in enumerate(order)]
    np.testing.assert_allclose(euler_to_matrix(t, order).numpy(), e[0] @ e[1] @ e[2], atol=1e-14)
    np.testing.assert_allclose(euler_to_matrix(t, order.lower()).numpy(), e[2] @ e[1] @ e[0], atol=1e-14)
    # intrinsic ABC == extrinsic cba with reversed angles
    np.testing.assert_allclose(
        euler_to_matrix(t, order).numpy(), euler_to_matrix(t.flip(-1), order[::-1].lower()).numpy(), atol=1e-14
    )


def test_euler_bvh_zxy_by_hand():
    z, x, y = 0.3, -0.7, 1.1
    c, s = math.cos, math.sin
    Rz = np.array([[c(z), -s(z), 0], [s(z), c(z), 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, c(x), -s(x)], [0, s(x), c(x)]])
    Ry = np.array([[c(y), 0, s(y)], [0, 1, 0], [-s(y), 0, c(y)]])
    out = euler_to_matrix(torch.tensor([z, x, y], dtype=F64), "ZXY").numpy()
    np.testing.assert_allclose(out, Rz @ Rx @ Ry, atol=1e-15)


@pytest.mark.parametrize("order", TAIT_BRYAN)
def test_matrix_to_euler_matches_scipy(order):
    R = Rotation.random(100, random_state=6)
    mats = torch.tensor(R.as_matrix())
    for o in (order, order.lower()):
        out = matrix_to_euler(mats, o).numpy()
        np.testing.assert_allclose(out, R.as_euler(o), atol=1e-10)
        np.testing.assert_allclose(euler_to_matrix(torch.tensor(out), o).numpy(), R.as_matrix(), atol=1e-13)


@pytest.mark.parametrize("order", ["XYZ", "zxy", "YZX", "xzy"])
def test_matrix_to_euler_gimbal_lock_round_trip(order):
    angles = torch.tensor([[0.4, math.pi / 2, -1.2], [-2.0, -math.pi / 2, 0.7]], dtype=F64)
    R = euler_to_matrix(angles, order)
    back = matrix_to_euler(R, order)
    assert torch.isfinite(back).all()
    np.testing.assert_allclose(euler_to_matrix(back, order).numpy(), R.numpy(), atol=1e-12)
    R32 = R.float()
    back32 = matrix_to_euler(R32, order)
    np.testing.assert_allclose(euler_to_matrix(back32, order).numpy(), R.numpy(), atol=1e-5)


def test_euler_order_validation():
    a = torch.zeros(3)
    for bad in ["XY", "XYZW", "XyZ", "XXY", "ABC", 3]:
        with pytest.raises(InputError):
            euler_to_matrix(a, bad)
    with pytest.raises(InputError):
        matrix_to_euler(torch.eye(3), "ZXZ")


# --------------------------------------------------------------------- round trips


@pytest.mark.parametrize("angle", SPECIAL_ANGLES)
def test_round_trips_special_angles(angle):
    v = special_rotvecs(angle)
    R = axis_angle_to_matrix(v)
    q = axis_angle_to_quaternion(v)

    def assert_rotvec_close(out):
        if angle < math.pi:
            np.testing.assert_allclose(out.numpy(), v.numpy(), atol=1e-14, rtol=0)
        else:  # at exactly pi, +axis*pi and -axis*pi are the same rotation
            d = np.minimum(np.abs(out.numpy() - v.numpy()).max(-1), np.abs(out.numpy() + v.numpy()).max(-1))
            assert np.all(d < 1e-14)
        assert np.all(np.linalg.norm(out.numpy(), axis=-1) <= math.pi + 1e-12)

    back = matrix_to_axis_angle(R)
    assert_rotvec_close(back)
    np.testing.assert_allclose(axis_angle_to_matrix(back).numpy(), R.numpy(), atol=1e-14)
    assert_rotvec_close(quaternion_to_axis_angle(q))
    np.testing.assert_allclose(quaternion_to_matrix(q).numpy(), R.numpy(), atol=1e-15)
    qm = matrix_to_quaternion(R)
    assert same_rotation_quat(qm.numpy(), q.numpy(), 1e-14)
    assert same_rotation_quat(q.numpy(), scipy_quat_wxyz(v.numpy()), 1e-15)
    np.testing.assert_allclose(rotation_6d_to_matrix(matrix_to_rotation_6d(R)).numpy(), R.numpy(), atol=1e-15)
    for order in ["XYZ", "zyx", "ZXY"]:
        np.testing.assert_allclose(
            euler_to_matrix(matrix_to_euler(R, order), order).numpy(), R.numpy(), atol=1e-12
        )


def test_round_trips_random_batched_shapes():
    v = torch.tensor(random_rotvecs(24, seed=8)).reshape(2, 3, 4, 3)
    R = axis_angle_to_matrix(v)
    assert R.shape == (2, 3, 4, 3, 3)
    np.testing.assert_allclose(matrix_to_axis_angle(R).numpy(), v.numpy(), atol=1e-13)
    q = matrix_to_quaternion(R)
    assert q.shape == (2, 3, 4, 4)
    np.testing.assert_allclose(quaternion_to_matrix(q).numpy(), R.numpy(), atol=1e-14)
    np.testing.assert_allclose(quaternion_to_axis_angle(q).numpy(), v.numpy(), atol=1e-13)
    d6 = matrix_to_rotation_6d(R)
    assert d6.shape == (2, 3, 4, 6)
    np.testing.assert_allclose(d6[0, 0, 0].numpy(), R[0, 0, 0].T[:2].reshape(-1).numpy())  # columns
    np.testing.assert_allclose(rotation_6d_to_matrix(d6).numpy(), R.numpy(), atol=1e-14)
    e = matrix_to_euler(R, "YXZ")
    np.testing.assert_allclose(euler_to_matrix(e, "YXZ").numpy(), R.numpy(), atol=1e-13)


def test_float32_accuracy_small_and_near_pi():
    for angle, tol in [(1e-8, 1e-12), (1e-4, 1e-9), (0.3, 1e-6), (math.pi - 1e-3, 1e-5)]:
        v = special_rotvecs(angle)
        R32 = axis_angle_to_matrix(v.float())
        np.testing.assert_allclose(R32.numpy(), axis_angle_to_matrix(v).numpy(), atol=5e-7)
        back = matrix_to_axis_angle(axis_angle_to_matrix(v).float())
        np.testing.assert_allclose(back.double().numpy(), v.numpy(), atol=max(tol, 1e-7 if angle > 1 else 0))
        np.testing.assert_allclose(
            quaternion_to_axis_angle(axis_angle_to_quaternion(v.float())).double().numpy(), v.numpy(),
            rtol=1e-6, atol=1e-6 * angle,
        )


def test_rotation_6d_projects_arbitrary_input_to_rotation():
    x = torch.tensor(rng(9).normal(size=(50, 6)))
    R = rotation_6d_to_matrix(x)
    eye = torch.eye(3, dtype=F64).expand(50, 3, 3)
    np.testing.assert_allclose((R @ R.transpose(-1, -2)).numpy(), eye.numpy(), atol=1e-14)
    np.testing.assert_allclose(torch.linalg.det(R).numpy(), 1.0, atol=1e-14)
    # first column is the normalised first 3-vector
    np.testing.assert_allclose(R[..., :, 0].numpy(), (x[:, :3] / x[:, :3].norm(dim=-1, keepdim=True)).numpy())


def test_quaternion_multiply_and_conjugate():
    qa = torch.tensor(scipy_quat_wxyz(random_rotvecs(30, seed=10)))
    qb = torch.tensor(scipy_quat_wxyz(random_rotvecs(30, seed=11)))
    np.testing.assert_allclose(
        quaternion_to_matrix(quaternion_multiply(qa, qb)).numpy(),
        (quaternion_to_matrix(qa) @ quaternion_to_matrix(qb)).numpy(), atol=1e-14,
    )
    ident = quaternion_multiply(qa, quaternion_conjugate(qa))
    np.testing.assert_allclose(ident.numpy(), np.tile([1.0, 0, 0, 0], (30, 1)), atol=1e-15)
    # broadcasting of leading dims
    assert quaternion_multiply(qa[:, None], qb[None, :5]).shape == (30, 5, 4)


def test_quaternion_to_axis_angle_shortest_and_scale_invariant():
    v = torch.tensor(random_rotvecs(40, seed=12))
    q = axis_angle_to_quaternion(v)
    np.testing.assert_allclose(quaternion_to_axis_angle(-q).numpy(), v.numpy(), atol=1e-13)
    np.testing.assert_allclose(quaternion_to_axis_angle(3.5 * q).numpy(), v.numpy(), atol=1e-13)
    # an angle beyond pi comes back as the shorter rotation the other way round
    axis = torch.tensor([0.0, 0.6, 0.8], dtype=F64)
    long = axis_angle_to_quaternion(axis * 1.5 * math.pi)
    assert long[0] < 0
    np.testing.assert_allclose(quaternion_to_axis_angle(long).numpy(), (-0.5 * math.pi * axis).numpy(), atol=1e-14)


def test_rotation_input_validation():
    with pytest.raises(InputError):
        axis_angle_to_matrix(torch.zeros(4))
    with pytest.raises(InputError):
        axis_angle_to_matrix(np.zeros(3))
    with pytest.raises(InputError):
        matrix_to_axis_angle(torch.zeros(3, 4))
    with pytest.raises(InputError):
        quaternion_to_matrix(torch.zeros(3))
    with pytest.raises(InputError):
        rotation_6d_to_matrix(torch.zeros(5))


# ---------------------------------------------------------------------- gradients


def _gradcheck(fn, x):
    assert torch.autograd.gradcheck(fn, (x.clone().requires_grad_(True),), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_gradcheck_axis_angle_to_matrix():
    _gradcheck(axis_angle_to_matrix, torch.tensor(random_rotvecs(8, seed=13, max_angle=3.0)))
    for scale in [0.0, 1e-8, 1e-4, 1e-2, 0.09, 0.11]:
        _gradcheck(axis_angle_to_matrix, torch.tensor(unit_axes(4, seed=14) * scale))
    _gradcheck(axis_angle_to_matrix, torch.tensor(unit_axes(4, seed=15) * (math.pi - 1e-6)))


def test_axis_angle_to_matrix_gradient_at_zero_is_skew():
    for dtype in (F64, torch.float32):
        J = torch.autograd.functional.jacobian(axis_angle_to_matrix, torch.zeros(3, dtype=dtype))
        assert torch.isfinite(J).all()
        for i in range(3):
            np.testing.assert_allclose(J[..., i].double().numpy(), skew_np(np.eye(3)[i]), atol=0)
    # batched backward through a loss at exactly zero
    v = torch.zeros(5, 3, dtype=torch.float32, requires_grad=True)
    (axis_angle_to_matrix(v) * torch.randn(5, 3, 3)).sum().backward()
    assert torch.isfinite(v.grad).all()


def test_gradients_finite_at_identity_float32_and_float64():
    for dtype in (torch.float32, F64):
        zero, ident = torch.zeros(3, dtype=dtype), torch.eye(3, dtype=dtype)
        q_id = torch.tensor([1.0, 0, 0, 0], dtype=dtype)
        for fn, x in [
            (axis_angle_to_quaternion, zero), (quaternion_to_axis_angle, q_id),
            (matrix_to_axis_angle, ident), (matrix_to_quaternion, ident),
            (lambda m: matrix_to_euler(m, "ZXY"), ident),
        ]:
            assert torch.isfinite(torch.autograd.functional.jacobian(fn, x)).all()
    J = torch.autograd.functional.jacobian(quaternion_to_axis_angle, torch.tensor([1.0, 0, 0, 0], dtype=F64))
    np.testing.assert_allclose(J[:, 1:].numpy(), 2 * np.eye(3))  # d rotvec / d (x, y, z) = 2 I at identity


def test_gradcheck_matrix_to_axis_angle():
    R = Rotation.from_rotvec(random_rotvecs(8, seed=16, max_angle=2.8)).as_matrix()
    _gradcheck(matrix_to_axis_angle, torch.tensor(R))
    R_small = Rotation.from_rotvec(unit_axes(4, seed=17) * 1e-3).as_matrix()
    _gradcheck(matrix_to_axis_angle, torch.tensor(R_small))
    J = torch.autograd.functional.jacobian(matrix_to_axis_angle, torch.eye(3, dtype=F64))
    assert torch.isfinite(J).all()


def test_gradcheck_quaternion_functions():
    v = torch.tensor(random_rotvecs(6, seed=18, max_angle=2.8))
    q = axis_angle_to_quaternion(v).detach()
    _gradcheck(axis_angle_to_quaternion, v)
    _gradcheck(axis_angle_to_quaternion, torch.tensor(unit_axes(4, seed=19) * 1e-5))
    _gradcheck(axis_angle_to_quaternion, torch.zeros(2, 3, dtype=F64))
    _gradcheck(quaternion_to_axis_angle, q)
    _gradcheck(quaternion_to_axis_angle, axis_angle_to_quaternion(torch.tensor(unit_axes(4, seed=20) * 1e-4)))
    _gradcheck(quaternion_to_axis_angle, torch.tensor([[1.0, 0, 0, 0]], dtype=F64))
    _gradcheck(quaternion_to_matrix, q * 1.3)
    _gradcheck(matrix_to_quaternion, axis_angle_to_matrix(v).detach())
    qb = axis_angle_to_quaternion(torch.tensor(random_rotvecs(6, seed=21))).detach()
    assert torch.autograd.gradcheck(
        quaternion_multiply, (q.clone().requires_grad_(True), qb.clone().requires_grad_(True))
    )
    _gradcheck(quaternion_conjugate, q)


def test_gradcheck_euler_and_6d():
    a = torch.tensor(rng(22).uniform(-1.2, 1.2, size=(5, 3)))
    _gradcheck(lambda x: euler_to_matrix(x, "ZXY"), a)
    R = euler_to_matrix(a, "xyz").detach()
    _gradcheck(lambda x: matrix_to_euler(x, "xyz"), R)
    _gradcheck(rotation_6d_to_matrix, torch.tensor(rng(23).normal(size=(5, 6))))


# ------------------------------------------------------------------------- camera


def test_project_known_point_by_hand():
    cam = PinholeCamera(fx=500.0, fy=600.0, cx=320.0, cy=240.0, width=640, height=480)
    p = torch.tensor([0.1, -0.2, 2.0], dtype=F64)
    np.testing.assert_allclose(cam.project(p).numpy(), [500 * 0.05 + 320, 600 * -0.1 + 240])
    # with a pose: R = 90 degrees about y, t = (0, 0, 1)
    R = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    cam = PinholeCamera(500.0, 600.0, 320.0, 240.0, 640, 480, R=R, t=[0.0, 0.0, 1.0])
    p = np.array([[-2.0, 0.5, 0.3]])  # camera frame: (0.3, 0.5, 3.0)
    np.testing.assert_allclose(cam.to_camera(p), [[0.3, 0.5, 3.0]])
    np.testing.assert_allclose(cam.depth(p), [3.0])
    out = cam.project(p)
    assert isinstance(out, np.ndarray) and out.shape == (1, 2)
    np.testing.assert_allclose(out, [[500 * 0.1 + 320, 600 * 0.5 / 3 + 240]])
    t32 = cam.project(torch.tensor(p, dtype=torch.float32))
    assert t32.dtype == torch.float32
    np.testing.assert_allclose(cam.center, -R.T @ np.array([0.0, 0.0, 1.0]))


def test_camera_constructors_and_K():
    cam = PinholeCamera.from_fov(640, 480, 90.0)
    assert cam.fx == pytest.approx(320.0) and cam.fy == pytest.approx(320.0)
    assert (cam.cx, cam.cy) == (320.0, 240.0)  # image centre; pixel centres at integer + 0.5
    cam_v = PinholeCamera.from_fov(640, 480, 90.0, axis="vertical")
    assert cam_v.fx == pytest.approx(240.0)
    cam_f = PinholeCamera.from_focal(641, 481, 1000.0)
    np.testing.assert_allclose(cam_f.K, [[1000, 0, 320.5], [0, 1000, 240.5], [0, 0, 1]])
    assert cam_f.K.shape == (3, 3) and isinstance(cam_f.K, np.ndarray)
    # the optical axis hits the centre of the middle pixel (320, 240) of a 641 x 481 image
    np.testing.assert_allclose(cam_f.project(np.array([0.0, 0.0, 5.0])), [320.5, 240.5])
    # a point on the left edge of a horizontal 90-degree fov lands on x = 0
    np.testing.assert_allclose(cam.project(np.array([-1.0, 0.0, 1.0])), [0.0, 240.0], atol=1e-9)


def test_project_batched_behind_camera_and_unproject():
    cam = PinholeCamera.from_focal(320, 240, 300.0, t=[0.1, 0.0, 0.5])
    pts = torch.tensor(rng(24).normal(size=(2, 5, 3)))
    pts[..., 2] += 4.0
    uv = cam.project(pts)
    assert uv.shape == (2, 5, 2)
    back = cam.unproject(uv, cam.depth(pts))
    np.testing.assert_allclose(back.numpy(), pts.numpy(), atol=1e-12)
    behind = np.array([0.2, 0.1, -1.5])  # projected anyway, mirrored through the principal point
    assert cam.depth(behind) < 0
    assert np.all(np.isfinite(cam.project(behind)))


def test_gradcheck_project():
    R, t = look_at([0.5, 1.5, 3.0], [0.0, 1.0, 0.0])
    cam = PinholeCamera.from_focal(640, 480, 700.0, R=R, t=t)
    pts = torch.tensor(rng(25).normal(size=(6, 3)) * 0.3)
    _gradcheck(cam.project, pts)


def test_look_at_target_at_centre_and_up_is_image_up():
    eye, target = np.array([1.0, 1.6, 4.0]), np.array([0.0, 1.0, 0.0])
    R, t = look_at(eye, target)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0)
    cam = PinholeCamera.from_fov(640, 480, 60.0, R=R, t=t)
    np.testing.assert_allclose(cam.center, eye, atol=1e-14)
    np.testing.assert_allclose(cam.project(target), [320.0, 240.0], atol=1e-9)
    assert cam.depth(target) == pytest.approx(np.linalg.norm(eye - target))
    up_pt = cam.project(target + np.array([0.0, 0.2, 0.0]))
    assert up_pt[1] < 240.0 - 1.0  # world up -> decreasing image y
    # camera on the +z side looking towards -z: world +x is image right, no roll
    R2, t2 = look_at([0.0, 1.0, 5.0], [0.0, 1.0, 0.0])
    cam2 = PinholeCamera.from_focal(640, 480, 500.0, R=R2, t=t2)
    right, up = cam2.project(np.array([[0.5, 1.0, 0.0], [0.0, 1.5, 0.0]]))
    assert right[0] > 320.0 and right[1] == pytest.approx(240.0)
    assert up[1] < 240.0 and up[0] == pytest.approx(320.0)


def test_look_at_degenerate_raises():
    with pytest.raises(InputError):
        look_at([0, 0, 0], [0, 0, 0])
    with pytest.raises(InputError):
        look_at([0, 5, 0], [0, 0, 0])  # straight down along the up axis
    with pytest.raises(InputError):
        look_at([0, 0], [0, 0, 1])


def test_camera_dict_round_trip_through_json():
    R, t = look_at([1.0, 2.0, 3.0], [0.0, 1.0, 0.0])
    cam = PinholeCamera(fx=512.5, fy=510.0, cx=321.0, cy=239.5, width=640, height=480, R=R, t=t)
    d = json.loads(json.dumps(cam.to_dict()))
    assert set(d) == {"fx", "fy", "cx", "cy", "width", "height", "R", "t"}
    cam2 = PinholeCamera.from_dict(d)
    assert cam2 == cam
    minimal = PinholeCamera.from_dict({"fx": 1, "fy": 1, "cx": 0, "cy": 0, "width": 4, "height": 3})
    np.testing.assert_array_equal(minimal.R, np.eye(3))
    np.testing.assert_array_equal(minimal.t, np.zeros(3))


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(fx=0.0), dict(fy=-1.0), dict(width=0), dict(height=-5), dict(width=640.5),
        dict(cx=float("nan")), dict(fx="big"), dict(R=np.eye(2)), dict(R=np.diag([1.0, 1.0, -1.0])),
        dict(R=2 * np.eye(3)), dict(t=[0.0, 1.0]), dict(t=[0.0, 1.0, float("inf")]),
    ],
)
def test_bad_camera_input_raises(kwargs):
    base = dict(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)
    base.update(kwargs)
    with pytest.raises(InputError):
        PinholeCamera(**base)


def test_bad_camera_constructor_and_dict_raise():
    with pytest.raises(InputError, match="missing"):
        PinholeCamera.from_dict({"fx": 1.0, "fy": 1.0})
    for fov in (0.0, 180.0, -10.0):
        with pytest.raises(InputError):
            PinholeCamera.from_fov(640, 480, fov)
    with pytest.raises(InputError):
        PinholeCamera.from_focal(640, 480, 0.0)
    cam = PinholeCamera.from_focal(640, 480, 500.0)
    with pytest.raises(InputError):
        cam.project(torch.zeros(4, 2))


# --------------------------------------------------------------------- Procrustes


def _random_similarity(seed, batch=()):
    g = rng(seed)
    n = int(np.prod(batch)) if batch else 1
    R = Rotation.random(n, random_state=seed).as_matrix().reshape(batch + (3, 3))
    s = g.uniform(0.5, 2.0, size=batch)
    t = g.normal(size=batch + (3,))
    return s, R, t


def test_procrustes_recovers_known_similarity_numpy_and_torch():
    s, R, t = _random_similarity(30)
    src = rng(31).normal(size=(20, 3))
    tgt = s * src @ R.T + t
    aligned, s_hat, R_hat, t_hat = similarity_procrustes(src, tgt)
    assert all(isinstance(x, np.ndarray) for x in (aligned, s_hat, R_hat, t_hat))
    assert s_hat.shape == () and R_hat.shape == (3, 3) and t_hat.shape == (3,)
    np.testing.assert_allclose(s_hat, s, atol=1e-12)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)
    np.testing.assert_allclose(t_hat, t, atol=1e-12)
    np.testing.assert_allclose(aligned, tgt, atol=1e-12)
    out = similarity_procrustes(torch.tensor(src), torch.tensor(tgt))
    assert all(isinstance(x, torch.Tensor) and x.dtype == F64 for x in out)
    np.testing.assert_allclose(out[0].numpy(), tgt, atol=1e-12)
    out32 = similarity_procrustes(src.astype(np.float32), tgt.astype(np.float32))
    assert out32[0].dtype == np.float32
    np.testing.assert_allclose(out32[1], s, atol=1e-5)


def test_procrustes_batched_and_weighted():
    s, R, t = _random_similarity(32, batch=(4,))
    src = rng(33).normal(size=(4, 15, 3))
    tgt = s[:, None, None] * src @ R.transpose(0, 2, 1) + t[:, None]
    aligned, s_hat, R_hat, t_hat = similarity_procrustes(torch.tensor(src), torch.tensor(tgt))
    assert aligned.shape == (4, 15, 3) and s_hat.shape == (4,) and R_hat.shape == (4, 3, 3)
    np.testing.assert_allclose(s_hat.numpy(), s, atol=1e-12)
    np.testing.assert_allclose(R_hat.numpy(), R, atol=1e-12)
    np.testing.assert_allclose(t_hat.numpy(), t, atol=1e-12)
    # outliers with zero weight do not disturb the fit; per-batch and shared (N,) weights
    bad = tgt.copy()
    bad[:, :3] += rng(34).normal(size=(4, 3, 3)) * 5.0
    w = np.ones(15)
    w[:3] = 0.0
    for weights in (w, np.tile(w, (4, 1)), torch.tensor(w)):
        _, s_w, R_w, t_w = similarity_procrustes(src, bad, weights=weights)
        np.testing.assert_allclose(s_w, s, atol=1e-12)
        np.testing.assert_allclose(R_w, R, atol=1e-12)
        np.testing.assert_allclose(t_w, t, atol=1e-12)
    # non-uniform positive weights on exact data still give the exact transform
    w2 = rng(35).uniform(0.1, 3.0, size=(4, 15))
    _, s_w, R_w, _ = similarity_procrustes(src, tgt, weights=w2)
    np.testing.assert_allclose(s_w, s, atol=1e-12)
    np.testing.assert_allclose(R_w, R, atol=1e-12)
    # rigid variant
    tgt_rigid = src @ R.transpose(0, 2, 1) + t[:, None]
    _, s_r, R_r, _ = similarity_procrustes(src, tgt_rigid, estimate_scale=False)
    np.testing.assert_allclose(s_r, 1.0)
    np.testing.assert_allclose(R_r, R, atol=1e-12)


def test_procrustes_never_returns_a_reflection():
    src = rng(36).normal(size=(6, 12, 3))
    mirror = np.diag([1.0, 1.0, -1.0])
    s, R, t = _random_similarity(37, batch=(6,))
    tgt = s[:, None, None] * src @ mirror @ R.transpose(0, 2, 1) + t[:, None]
    for a, b in ((src, tgt), (torch.tensor(src), torch.tensor(tgt))):
        aligned, s_hat, R_hat, _ = similarity_procrustes(a, b)
        det = np.linalg.det(np.asarray(R_hat))
        np.testing.assert_allclose(det, 1.0, atol=1e-12)
        assert np.all(np.asarray(s_hat) > 0)
        R_np = np.asarray(R_hat)
        np.testing.assert_allclose(R_np @ R_np.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (6, 3, 3)), atol=1e-12)
    # planar (rank-2) data: still a proper rotation and an exact fit
    flat = src[0].copy()
    flat[:, 2] = 0.0
    _, _, R_f, _ = similarity_procrustes(flat, flat @ mirror)
    assert np.linalg.det(R_f) == pytest.approx(1.0)


def test_procrustes_degenerate_source_gives_centroid():
    src = np.ones((4, 3))
    tgt = rng(38).normal(size=(4, 3))
    aligned, s_hat, R_hat, _ = similarity_procrustes(src, tgt)
    assert s_hat == 0.0 and np.linalg.det(R_hat) == pytest.approx(1.0)
    np.testing.assert_allclose(aligned, np.broadcast_to(tgt.mean(0), (4, 3)), atol=1e-12)


def test_procrustes_bad_input_raises():
    a = np.zeros((5, 3))
    with pytest.raises(InputError):
        similarity_procrustes(a, np.zeros((4, 3)))
    with pytest.raises(InputError):
        similarity_procrustes(np.zeros((5, 2)), np.zeros((5, 2)))
    with pytest.raises(InputError):
        similarity_procrustes(a, a, weights=-np.ones(5))
    with pytest.raises(InputError):
        similarity_procrustes(a, a, weights=np.zeros(5))
    with pytest.raises(InputError):
        similarity_procrustes(a, a, weights=np.ones(4))
    with pytest.raises(InputError):
        similarity_procrustes([[0, 0, 0]], a)


def test_ray_rotation_takes_the_optical_axis_to_the_pixel_ray():
    cam = PinholeCamera.from_focal(854, 480, 768.6)
    assert np.allclose(cam.ray_rotation(cam.cx, cam.cy), np.eye(3))
    for u, v in ((100.0, 50.0), (800.0, 400.0), (427.0, 10.0)):
        R = cam.ray_rotation(u, v)
        assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
        ray = R @ np.array([0.0, 0.0, 1.0])
        assert np.allclose(ray[:2] / ray[2], [(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy])
        # the smallest rotation: its axis lies in the image plane
        w, vecs = np.linalg.eig(R)
        axis = np.real(vecs[:, np.argmin(np.abs(w - 1.0))])
        assert abs(axis[2]) < 1e-9
        # a share of it: the same axis, the angle times the share (two halves make the whole)
        half = cam.ray_rotation(u, v, 0.5)
        np.testing.assert_allclose(half @ half, R, atol=1e-12)
        np.testing.assert_allclose(cam.ray_rotation(u, v, 0.0), np.eye(3), atol=1e-12)
        np.testing.assert_allclose(cam.ray_rotation(u, v, 1.0), R, atol=0)

"""Multi-view geometry: calibrated cameras with distortion, robust triangulation, time
offsets of unsynchronised views, and the Qualisys calibration reader."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flowmocap.errors import DataError, InputError
from flowmocap.geometry.triangulate import CalibratedCamera, estimate_offsets, reprojection_errors, triangulate
from flowmocap.io.calibration import parse_qualisys_calibration, read_qualisys_calibration


def ring_cameras(n=4, radius=4.0, height=1.8, dist=None, size=(1088, 1920)):
    """``n`` portrait cameras on a circle around the world origin (z up), looking at (0, 0, 1)."""
    cams = []
    W, H = size
    for k in range(n):
        a = 2 * np.pi * k / n + 0.3
        C = np.array([radius * np.cos(a), radius * np.sin(a), height])
        fwd = np.array([0.0, 0.0, 1.0]) - C
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        R = np.stack([right, down, fwd])  # rows: camera axes in the world (OpenCV)
        K = np.array([[1600.0 + 20 * k, 0, W / 2 + 7], [0, 1600.0 + 20 * k, H / 2 - 5], [0, 0, 1]])
        d = np.zeros(5) if dist is None else np.asarray(dist, float)
        cams.append(CalibratedCamera(f"cam{k + 1:02d}", K, d, R, -R @ C, W, H))
    return cams


def random_points(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.5, -0.5, 0.0], [0.5, 0.5, 1.9], size=(n, 3))


def project_all(cams, X):
    return np.stack([c.project(X) for c in cams])


def test_exact_without_noise():
    cams = ring_cameras()
    X = random_points()
    tri = triangulate(cams, project_all(cams, X))
    np.testing.assert_allclose(tri.points, X, atol=1e-9)
    assert tri.error_px.max() < 1e-6 and (tri.num_views == 4).all()
    assert tri.points.shape == (50, 3) and tri.used.shape == (50, 4)


def test_distortion_is_undone():
    dist = [-0.25, 0.12, 0.001, 0.0015, 0.01]
    cams = ring_cameras(dist=dist)
    X = random_points(seed=1)
    px = project_all(cams, X)
    plain = project_all(ring_cameras(), X)
    assert np.abs(px - plain).max() > 3.0  # the distortion moves points by pixels near the edges
    tri = triangulate(cams, px)
    np.testing.assert_allclose(tri.points, X, atol=1e-7)
    # and normalise() inverts project()
    xn = cams[0].normalise(px[0])
    Xc = X @ cams[0].R.T + cams[0].t
    np.testing.assert_allclose(xn, Xc[:, :2] / Xc[:, 2:], atol=1e-9)


def test_one_bad_view_is_dropped():
    cams = ring_cameras()
    X = random_points(seed=2)
    px = project_all(cams, X)
    rng = np.random.default_rng(3)
    bad = px.copy()
    bad[2] += rng.normal(0, 1, bad[2].shape) * 60 + 80  # view 2 sees something else (~100 px off)
    tri = triangulate(cams, bad, max_error_px=15.0)
    np.testing.assert_allclose(tri.points, X, atol=1e-7)
    assert not tri.used[:, 2].any() and tri.used[:, [0, 1, 3]].all()
    assert (tri.view_error_px[:, 2] > 15).all()
    # without the robust step the bad view pulls every point away
    plain = triangulate(cams, bad, max_error_px=None)
    assert np.linalg.norm(plain.points - X, axis=1).min() > 1e-3


def test_confidence_missing_views_and_too_few():
    cams = ring_cameras()
    X = random_points(5, seed=4)
    px = project_all(cams, X)
    conf = np.ones((4, 5))
    conf[1:, 0] = 0.1  # point 0: one confident view only
    px[0, 1] = np.nan  # point 1: view 0 missing
    noisy = px.copy()
    noisy[3, 2] += 40  # point 2: a wrong, unconfident observation is ignored
    conf[3, 2] = 0.2
    tri = triangulate(cams, noisy, conf)
    assert np.isnan(tri.points[0]).all() and tri.num_views[0] == 0
    np.testing.assert_allclose(tri.points[1:], X[1:], atol=1e-8)
    assert tri.num_views[1] == 3 and tri.num_views[2] == 3
    with pytest.raises(InputError, match=r"\(V, N, 2\)"):
        triangulate(cams, px[:3])
    with pytest.raises(InputError, match="min_views"):
        triangulate(cams, px, min_views=1)


def test_points_behind_a_camera_count_as_errors():
    cams = ring_cameras()
    X = random_points(4, seed=5)
    e = reprojection_errors(cams, X, project_all(cams, X))
    assert e.shape == (4, 4) and e.max() < 1e-6
    behind = cams[0].center + 2.0 * (cams[0].center - np.array([0, 0, 1.0]))
    assert np.isnan(cams[0].project(behind[None])).all()


def test_scaled_camera_projects_to_scaled_pixels():
    cam = ring_cameras(dist=[-0.05, 0.14, 0.0, 0.0, 0.0])[1]
    X = random_points(10, seed=6)
    small = cam.scaled(1 / 3)
    np.testing.assert_allclose(small.project(X), cam.project(X) / 3, atol=1e-9)
    assert (small.width, small.height) == (363, 640)


def moving_person(T=80, J=13, seed=0):
    """``(T, J, 3)`` joints swinging with a different phase each."""
    rng = np.random.default_rng(seed)
    base = rng.uniform([-0.3, -0.3, 0.1], [0.3, 0.3, 1.8], size=(J, 3))
    amp = rng.uniform(0.05, 0.3, size=(J, 3))
    phase = rng.uniform(0, 2 * np.pi, size=(J, 3))
    t = np.arange(T)[:, None, None] / 60.0
    return base + amp * np.sin(2 * np.pi * 0.8 * t + phase)


def test_offsets_of_shifted_views_are_recovered():
    cams = ring_cameras()
    truth = np.array([0, 3, -4, 2])
    X = moving_person(100)  # reference time 0..99
    rng = np.random.default_rng(1)
    tracks = []
    for v, cam in enumerate(cams):
        # view v's frame f is time f + offset: frames 0..79 from time offset + 10
        times = np.arange(10, 90) + truth[v]
        px = cam.project(X[times]) + rng.normal(0, 1.5, (80, X.shape[1], 2))
        conf = np.full(px.shape[:2], 0.9)
        tracks.append((px, conf))
    # frame numbers of each view start at time 10 + offset: shift by the common 10
    offsets, cost = estimate_offsets(cams, [tracks], search=range(-8, 9))
    assert offsets.tolist() == truth.tolist()
    assert cost.shape == (4, 17) and np.isnan(cost[0]).all()
    k = list(range(-8, 9)).index(3)
    assert cost[1, k] == np.nanmin(cost[1])
    # a view that does not see the person keeps offset 0 and does not disturb the others
    offsets, _ = estimate_offsets(cams, [tracks[:3] + [None]], search=range(-8, 9))
    assert offsets.tolist() == [0, 3, -4, 0]
    with pytest.raises(InputError, match="one track"):
        estimate_offsets(cams, [tracks[:3]])


# ------------------------------------------------------------------ calibration files

QCA = """<?xml version='1.0' encoding='ASCII'?>
<calibration created="x" source="test" type="regular">
  <cameras>
    <camera active="1" serial="camA">
      <fov_video bottom="1919" left="0" right="1087" top="0"/>
      <transform r11="{r11}" r12="{r12}" r13="{r13}" r21="{r21}" r22="{r22}" r23="{r23}" r31="{r31}" r32="{r32}"
                 r33="{r33}" x="1000.0" y="-2000.0" z="1500.0"/>
      <intrinsic centerPointU="34816" centerPointV="61440" focalLengthU="107520" focalLengthV="107584"
                 radialDistortion1="-0.046" radialDistortion2="0.139" radialDistortion3="0.001"
                 tangentalDistortion1="0.0006" tangentalDistortion2="0.0007"/>
    </camera>
  </cameras>
</calibration>
"""


def qca_text(M):
    return QCA.format(**{f"r{i + 1}{j + 1}": M[i, j] for i in range(3) for j in range(3)})


def test_qualisys_conventions():
    M = Rotation.from_euler("xyz", [20, -30, 110], degrees=True).as_matrix()
    cams = parse_qualisys_calibration(qca_text(M))
    cam = cams["camA"]
    assert list(cams) == ["camA"] and (cam.width, cam.height) == (1088, 1920)
    np.testing.assert_allclose(cam.K, [[1680.0, 0, 544.5], [0, 1681.0, 960.5], [0, 0, 1]])
    np.testing.assert_allclose(cam.dist, [-0.046, 0.139, 0.0006, 0.0007, 0.001])
    np.testing.assert_allclose(cam.R, np.diag([1, -1, -1]) @ M)
    np.testing.assert_allclose(cam.center, [1.0, -2.0, 1.5])  # millimetres -> metres
    # the file's camera looks down its -z row: a point in front of it lies at +z in OpenCV axes
    ahead = cam.center - M[2]
    assert (cam.R @ ahead + cam.t)[2] == pytest.approx(1.0)


@pytest.mark.parametrize("text, match", [
    ("not xml <", "not valid XML"),
    ("<calibration><cameras/></calibration>", "no <calibration><cameras><camera>"),
    (QCA.replace('focalLengthU="107520"', 'focalLengthU="abc"'), "focalLengthU is 'abc'"),
    (QCA.replace('<fov_video bottom="1919" left="0" right="1087" top="0"/>', ""), "fov_video> is missing"),
])
def test_corrupt_calibration_says_what_is_wrong(text, match):
    if "{r11}" in text:
        text = qca_text(np.eye(3))
        text = text.replace('focalLengthU="107520"', 'focalLengthU="abc"') if "abc" in match else \
            text.replace('<fov_video bottom="1919" left="0" right="1087" top="0"/>', "")
    with pytest.raises(DataError, match=match):
        parse_qualisys_calibration(text)


def test_not_a_rotation_and_missing_file(tmp_path):
    with pytest.raises(DataError, match="not a rotation"):
        parse_qualisys_calibration(qca_text(2 * np.eye(3)))
    with pytest.raises(DataError, match="does not exist"):
        read_qualisys_calibration(tmp_path / "nope.qca.txt")

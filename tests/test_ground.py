"""The ground plane and world frame (flowmocap.geometry.ground, flowmocap.export.world)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from flowmocap.body import load_body_model
from flowmocap.errors import InputError
from flowmocap.export import export_result, load_fitted_motion
from flowmocap.export.world import WORLD_FILE, camera_in_frame
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.geometry.ground import (GroundPlane, fit_ground_plane, foot_contacts, ground_frame,
                                       plane_prior_scatter)
from flowmocap.io.builtin_walk import builtin_walk
from flowmocap.io.results import write_motion, write_run


def _angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def test_plane_prior_scatter_closed_forms():
    rng = np.random.default_rng(0)
    n_true = np.array([0.2, 0.9, -0.3])
    n_true /= np.linalg.norm(n_true)
    basis = np.linalg.svd(n_true[None])[2][1:]  # two in-plane directions
    pts = rng.normal(size=(50, 2)) @ basis + 0.7 * n_true
    n, c = plane_prior_scatter(pts, np.ones(50), [0, 1, 0], 1e-6)
    assert _angle_deg(n, n_true) < 1e-3
    assert c @ n == pytest.approx(0.7, abs=1e-9)
    # points on one line leave the tilt about it open: the prior decides it, exactly
    d = np.array([1.0, 0.1, 0.0])
    d /= np.linalg.norm(d)
    line = np.linspace(-1, 1, 20)[:, None] * d
    prior = np.array([0.0, 1.0, 0.2])
    n, _ = plane_prior_scatter(line, np.ones(20), prior, 1e-8)  # prior weak next to the line's spread
    expect = prior / np.linalg.norm(prior)
    expect = expect - (expect @ d) * d
    assert _angle_deg(n, expect) < 1e-5
    # with a strong prior the normal is the prior itself, however the points lie
    n, _ = plane_prior_scatter(pts, np.ones(50), prior, 1e9)
    assert _angle_deg(n, prior) < 1e-3


def test_fit_ground_plane_ignores_outliers_and_falls_back():
    rng = np.random.default_rng(1)
    n_true = Rotation.from_rotvec([0.15, 0.0, -0.1]).apply([0.0, 1.0, 0.0])
    basis = np.linalg.svd(n_true[None])[2][1:]
    pts = rng.uniform(-2, 2, (80, 2)) @ basis - 1.2 * n_true + rng.normal(0, 0.005, (80, 1)) * n_true
    outliers = pts[:25] + rng.uniform(0.1, 0.4, (25, 1)) * n_true  # feet in the air, wrongly labelled
    plane = fit_ground_plane(np.concatenate([pts, outliers]), prior_up=[0, 1, 0])
    assert plane.method == "contacts"
    assert _angle_deg(plane.normal, n_true) < 0.5
    assert plane.height == pytest.approx(-1.2, abs=0.005)
    assert plane.inliers >= 75
    assert np.abs(plane.elevation(pts)).max() < 0.03
    # fewer than 3 points: the prior's normal through the lowest fallback point
    fb = fit_ground_plane(pts[:2], prior_up=[0, 2, 0], fallback_points=pts)
    assert fb.method == "fallback" and fb.inliers == 0
    np.testing.assert_allclose(fb.normal, [0, 1, 0])
    assert fb.height == pytest.approx((pts @ [0, 1, 0]).min())
    assert fit_ground_plane(np.zeros((0, 3)), [0, 1, 0], fallback_height=1.5).height == -1.5
    with pytest.raises(InputError, match="fallback"):
        fit_ground_plane(np.zeros((0, 3)), [0, 1, 0])
    with pytest.raises(InputError, match="non-zero"):
        fit_ground_plane(pts, prior_up=[0, 0, 0])


def test_foot_contacts_label_stance_and_not_a_still_foot_in_the_air():
    fps = 30.0
    T = 60
    t = np.arange(T) / fps
    feet = np.zeros((T, 2, 3))
    # foot 0 steps: still for 20 frames, then swings 0.5 m forward, lifted 0.1 m, in 10 frames
    swing = (np.arange(T) % 30) >= 20
    phase = np.where(swing, ((np.arange(T) % 30) - 20) / 10.0, 0.0)
    feet[:, 0, 2] = 0.5 * (np.arange(T) // 30) + 0.5 * phase
    feet[:, 0, 1] = 0.1 * np.sin(np.pi * phase)
    feet[:, 1] = [0.3, 0.4, 0.0]  # foot 1 held still 0.4 m up (a raised knee)
    feet[:T // 2, 1, 1] = 0.0  # ... after standing for the first half
    c = foot_contacts(feet, fps, up=[0, 1, 0])
    assert c.shape == (T, 2)
    stance = ~swing
    inner = np.convolve(stance, np.ones(3), "same") == 3  # away from the step's first/last frame
    assert c[inner, 0].all() and not c[swing & (phase > 0.15) & (phase < 0.85), 0].any()
    assert c[2:T // 2 - 2, 1].all() and not c[T // 2 + 1:, 1].any()
    with pytest.raises(InputError, match="fps"):
        foot_contacts(feet, 0.0, [0, 1, 0])
    assert t.size == T


def test_ground_frame_is_y_up_on_the_floor_facing_the_camera():
    plane = GroundPlane(normal=np.array([0.0, -1.0, 0.0]), height=-1.5, inliers=10, residual_m=0.01,
                        method="contacts")  # camera frame: up is -y, floor 1.5 m below the camera
    R, o = ground_frame(plane, origin=[0.3, 0.2, 4.0], toward=[0.0, 0.0, 0.0])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    f = lambda x: R @ np.asarray(x, float) + o  # noqa: E731
    np.testing.assert_allclose(f([5.0, 1.5, 9.0])[1], 0.0, atol=1e-12)  # any floor point: y = 0
    np.testing.assert_allclose(f([0.3, 1.5, 4.0]), 0.0, atol=1e-12)  # the origin under the person
    cam = f([0.0, 0.0, 0.0])
    assert cam[1] == pytest.approx(1.5) and abs(cam[0]) < 1e-12 and cam[2] > 0  # camera 1.5 m up, on +z


def _walk_result(folder, tilt_deg: float, height: float):
    """The built-in walk (feet on y = 0) seen by a camera ``height`` m up, pitched down by
    ``tilt_deg``; the result's world is that camera's frame (R = I), as for a real video."""
    model = load_body_model("default")
    walk = builtin_walk(model, fps=30.0, frames=75, facing=np.pi / 2)
    with torch.no_grad():
        out = model(pose=torch.as_tensor(walk.poses, dtype=torch.float32),
                    trans=torch.as_tensor(walk.trans, dtype=torch.float32))
    # camera at (1, height, 5) in the walk's world, looking towards -z, pitched down
    pitch = Rotation.from_rotvec([np.radians(tilt_deg), 0, 0]).as_matrix()
    R = pitch @ np.diag([1.0, -1.0, -1.0])  # world y up, z towards camera -> camera y down, z forward
    t = -R @ np.array([1.0, height, 5.0])
    from flowmocap.io.smpl_motion import rotate_motion

    rest0 = out.rest_joints[0, 0].double().numpy()
    poses, trans = rotate_motion(walk.poses, walk.trans, rest0, R)
    trans = trans + t
    cam = PinholeCamera.from_focal(320, 240, 300.0)
    j = out.joints.double().numpy() @ R.T + t
    write_motion(folder, {
        "poses": poses.astype(np.float32), "trans": trans.astype(np.float32), "betas": np.zeros(10, np.float32),
        "gender": np.array("neutral"), "fps": np.array(30.0), "camera": np.array(json.dumps(cam.to_dict())),
        "joints3d": j.astype(np.float32), "joints2d": cam.project(j).astype(np.float32),
        "frame_index": np.arange(75),
    })
    write_run(folder, {"model": "default", "gender": "neutral"})
    return R, t, out.joints.double().numpy(), out.vertices.double().numpy()


@pytest.mark.parametrize("tilt", [0.0, 15.0])
def test_world_frame_recovers_the_floor_of_a_walk_seen_by_a_pitched_camera(tmp_path, tilt):
    R, t, joints_world, verts_world = _walk_result(tmp_path, tilt, height=1.4)
    m = load_fitted_motion(tmp_path)  # the ground frame is the default
    w = m.world
    assert w.plane.method == "contacts"
    assert _angle_deg(w.plane.normal, R @ [0, 1, 0]) < 1.0  # gravity found in the camera's frame
    j = m.joints()
    # heights above the floor are the walk's own (its feet touch y = 0)
    np.testing.assert_allclose(j[..., 1], joints_world[..., 1], atol=0.02)
    # the camera keeps its place: 1.4 m above the floor, and it projects the body exactly
    assert m.camera.center[1] == pytest.approx(1.4, abs=0.03)
    np.testing.assert_allclose(m.camera.project(j), m.joints2d, atol=1e-3)
    # both feet have stance frames, and no frame has both feet in the air for long
    assert w.contacts.mean(0).min() > 0.2
    assert (tmp_path / WORLD_FILE).is_file()
    doc = json.loads((tmp_path / WORLD_FILE).read_text())
    assert doc["method"] == "contacts" and len(doc["contacts"]) == 75
    # the cache is used as long as the motion is the same ...
    (tmp_path / WORLD_FILE).write_text(json.dumps({**doc, "offset": [0.0, 5.0, 0.0]}))
    assert load_fitted_motion(tmp_path).joints()[0, 0, 1] > 4.0
    # ... and recomputed when it changes (a resumed or re-tracked result)
    with np.load(tmp_path / "motion.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["trans"] = arrays["trans"] + np.float32([0.0, 0.0, 0.5])
    write_motion(tmp_path, arrays)
    assert load_fitted_motion(tmp_path).joints()[0, 0, 1] < 1.5
    assert json.loads((tmp_path / WORLD_FILE).read_text())["fingerprint"] != doc["fingerprint"]


def test_camera_in_frame_projects_moved_points_to_the_same_pixels():
    rng = np.random.default_rng(3)
    cam = PinholeCamera.from_focal(64, 48, 80.0, R=Rotation.random(random_state=1).as_matrix(), t=[0.1, 0.2, 3.0])
    W = Rotation.random(random_state=2).as_matrix()
    o = rng.normal(size=3)
    x = rng.normal(size=(10, 3)) * 0.3
    moved = camera_in_frame(cam, W, o)
    np.testing.assert_allclose(moved.project(x @ W.T + o), cam.project(x), atol=1e-9)


def test_exports_stand_on_the_floor_by_default(tmp_path):
    _walk_result(tmp_path / "r", 10.0, height=1.6)
    doc = json.loads(export_result(tmp_path / "r", "json", tmp_path / "m.json").read_text())
    assert doc["frame"] == "ground"
    feet = np.array([f["joints3d"] for f in doc["frames"]])[:, [7, 8, 10, 11], 1]
    assert 0.0 < feet.min() < 0.12  # ankles/toes just above the floor, never under it by more than noise
    assert any(f["contact"][0] for f in doc["frames"]) and any(f["contact"][1] for f in doc["frames"])


# A calibrated camera's world may be y up (synthetic, look_at), z up (lab calibrations: Qualisys,
# Vicon) or y down (a checkerboard on a wall): the world's +y is not always up.
_WORLDS = {"y up": np.eye(3), "z up": Rotation.from_rotvec([np.pi / 2, 0, 0]).as_matrix(),
           "y down": np.diag([1.0, -1.0, -1.0])}


@pytest.mark.parametrize("world", list(_WORLDS))
def test_world_up_is_the_world_axis_nearest_the_image_up(world):
    from flowmocap.geometry.camera import world_up
    from flowmocap.export.motion import up_rotation

    M = _WORLDS[world]  # y-up world -> this world
    for pitch_deg in (0.0, 30.0, -40.0):  # a camera looking down or up, within 45 degrees of level
        for yaw_deg in (0.0, 70.0, 200.0):
            R0 = (Rotation.from_rotvec([np.radians(pitch_deg), 0, 0]) * Rotation.from_rotvec([0, np.radians(yaw_deg), 0])
                  ).as_matrix() @ np.diag([1.0, -1.0, -1.0])  # in the y-up world
            cam = PinholeCamera.from_focal(64, 48, 80.0, R=R0 @ M.T, t=[0.1, 0.2, 3.0])
            np.testing.assert_allclose(world_up(cam), M @ [0.0, 1.0, 0.0], atol=1e-12)
            U = up_rotation(cam)
            np.testing.assert_allclose(U @ U.T, np.eye(3), atol=1e-12)
            assert np.linalg.det(U) == pytest.approx(1.0)
            np.testing.assert_allclose(U @ M @ [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    up = M @ [0.0, 1.0, 0.0]
    side = M @ [0.0, 0.0, 1.0]  # a horizontal axis of this world
    for pitch_deg in (-60.0, 60.0, 68.0):  # steep: the image up nearer a horizontal axis; an upright body decides
        R0 = Rotation.from_rotvec([np.radians(pitch_deg), 0, 0]).as_matrix() @ np.diag([1.0, -1.0, -1.0])
        if world == "z up":  # its image up is then near +y, which is taken for up (the documented limit)
            continue
        np.testing.assert_allclose(world_up(R0 @ M.T, body_up=up + [0.03, 0.03, -0.03]), up, atol=1e-12)
    # a camera rolled on its side filming a person standing: right where the world is y up (elsewhere the
    # camera's image up outweighs the body, the documented limit)
    R0 = Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix() @ np.diag([1.0, -1.0, -1.0])
    if world == "y up":
        np.testing.assert_allclose(world_up(R0 @ M.T, body_up=up), up, atol=1e-12)
    # a body lying through the whole clip, filmed from 40 degrees above: the camera decides
    R0 = Rotation.from_rotvec([np.radians(40.0), 0, 0]).as_matrix() @ np.diag([1.0, -1.0, -1.0])
    np.testing.assert_allclose(world_up(R0 @ M.T, body_up=side), up, atol=1e-12)
    np.testing.assert_allclose(up_rotation(PinholeCamera.from_focal(64, 48, 80.0, R=R0 @ M.T), side) @ up, [0, 1, 0],
                               atol=1e-12)
    if world == "y up":  # a body lying head away from a camera 30 degrees above it: the world stays y up
        R0 = Rotation.from_rotvec([np.radians(30.0), 0, 0]).as_matrix() @ np.diag([1.0, -1.0, -1.0])
        away = -(R0.T @ [0.0, 0.0, 1.0]) * [1, 0, 1]
        np.testing.assert_allclose(world_up(R0, body_up=-away), [0.0, 1.0, 0.0], atol=1e-12)
    # no calibration: the camera's own frame, y down
    np.testing.assert_allclose(world_up(np.eye(3)), [0.0, -1.0, 0.0])
    np.testing.assert_allclose(world_up(np.eye(3), body_up=[1.0, 0.0, 0.0]), [0.0, -1.0, 0.0])


@pytest.mark.parametrize("world", list(_WORLDS))
def test_a_result_in_any_calibrated_world_stands_upright_on_the_floor(tmp_path, world):
    # a z-up lab calibration gave a body lying along -x in every export (its up taken as the world's +y)
    from flowmocap.io.smpl_motion import rotate_motion

    M = _WORLDS[world]
    model = load_body_model("default")
    walk = builtin_walk(model, fps=30.0, frames=60, facing=np.pi / 2)
    with torch.no_grad():
        out = model(pose=torch.as_tensor(walk.poses, dtype=torch.float32),
                    trans=torch.as_tensor(walk.trans, dtype=torch.float32))
    rest0 = out.rest_joints[0, 0].double().numpy()
    poses, trans = rotate_motion(walk.poses, walk.trans, rest0, M)
    R0 = Rotation.from_rotvec([np.radians(10.0), 0, 0]).as_matrix() @ np.diag([1.0, -1.0, -1.0])
    cam = PinholeCamera.from_focal(320, 240, 300.0, R=R0 @ M.T, t=-R0 @ np.array([1.0, 1.4, 5.0]))
    j = out.joints.double().numpy() @ M.T
    write_motion(tmp_path, {
        "poses": poses.astype(np.float32), "trans": trans.astype(np.float32), "betas": np.zeros(10, np.float32),
        "gender": np.array("neutral"), "fps": np.array(30.0), "camera": np.array(json.dumps(cam.to_dict())),
        "joints3d": j.astype(np.float32), "joints2d": cam.project(j).astype(np.float32), "frame_index": np.arange(60),
    })
    write_run(tmp_path, {"model": "default", "gender": "neutral"})
    truth = out.joints.double().numpy()  # y up, feet on y = 0
    for frame in ("ground", "up"):
        m = load_fitted_motion(tmp_path, frame=frame)
        got = m.joints()
        body_up = (got[:, 12] - 0.5 * (got[:, 7] + got[:, 8])).mean(0)
        assert _angle_deg(body_up, [0.0, 1.0, 0.0]) < 10.0, (frame, body_up)
        if frame == "ground":
            np.testing.assert_allclose(got[..., 1], truth[..., 1], atol=0.02)  # the walk's own heights
        else:  # a pure turn of the world: y up as the walk's own frame
            np.testing.assert_allclose(got, truth, atol=1e-4)
        np.testing.assert_allclose(m.camera.project(got), m.joints2d, atol=1e-3)

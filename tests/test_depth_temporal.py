"""E_z (issue 18): the root's motion along the camera ray away from a reference."""

import numpy as np
import pytest
import torch

from flowmocap.errors import InputError
from flowmocap.fit import energies as en
from flowmocap.fit.config import TrackerConfig
from flowmocap.geometry.camera import PinholeCamera


def _camera():
    R = torch.tensor([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])  # a proper rotation (det +1)
    assert np.isclose(np.linalg.det(R.numpy()), 1.0)
    return PinholeCamera(fx=500.0, fy=500.0, cx=160.0, cy=120.0, width=320, height=240,
                         R=R.numpy(), t=np.array([0.3, -0.2, 2.0]))


def test_camera_ray_points_from_the_centre_and_projects_to_one_pixel():
    cam = _camera()
    p = np.array([0.4, 0.9, -0.2])
    u = en.camera_ray(cam, p).double().numpy()
    centre = -np.asarray(cam.R).T @ np.asarray(cam.t)
    expected = (p - centre) / np.linalg.norm(p - centre)
    assert np.allclose(u, expected, atol=1e-6)
    # every point on the ray projects to the same pixel
    a = cam.project(torch.tensor(np.stack([p, p + 0.7 * u]), dtype=torch.float64)).numpy()
    assert np.allclose(a[0], a[1], atol=1e-4)


def test_camera_ray_refuses_the_centre_and_bad_points():
    cam = _camera()
    with pytest.raises(InputError):
        en.camera_ray(cam, -np.asarray(cam.R).T @ np.asarray(cam.t))
    with pytest.raises(InputError):
        en.camera_ray(cam, [0.0, np.nan, 1.0])


def test_depth_temporal_energy_closed_form_and_free_across_the_ray():
    ref = torch.tensor([0.1, 0.8, 3.0], dtype=torch.float64)
    u = torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64)
    along = ref + 0.05 * u
    across = ref + 0.05 * torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)  # perpendicular to u
    assert float(en.depth_temporal_energy(along, ref, u)[0]) == pytest.approx(0.05 ** 2, rel=1e-12)
    assert float(en.depth_temporal_energy(across, ref, u)[0]) == pytest.approx(0.0, abs=1e-20)
    assert en.depth_temporal_residuals(torch.stack([along, across]), ref, u).shape == (2, 1)


def test_depth_temporal_energy_gradient_matches_finite_differences():
    ref = torch.tensor([0.1, 0.8, 3.0], dtype=torch.float64)
    u = torch.tensor([0.2, -0.3, 0.9], dtype=torch.float64)
    u = u / u.norm()
    t = torch.tensor([0.15, 0.7, 3.2], dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(lambda x: en.depth_temporal_energy(x, ref, u), (t,))
    e = en.depth_temporal_energy(t, ref, u)[0]
    (g,) = torch.autograd.grad(e, t)
    assert torch.allclose(g, 2 * ((t - ref) @ u) * u)  # closed form


def test_depth_temporal_residuals_refuse_bad_shapes():
    with pytest.raises(InputError):
        en.depth_temporal_residuals(torch.zeros(4), torch.zeros(3), torch.ones(3))
    with pytest.raises(InputError):
        en.depth_temporal_residuals(torch.zeros(3), torch.zeros(2), torch.ones(3))


def test_config_checks_the_weight():
    assert TrackerConfig().depth_temporal_weight >= 0
    with pytest.raises(InputError):
        TrackerConfig(depth_temporal_weight=-1.0)


def test_frame_energy_and_tracker_reference(tmp_path):
    """``frame_energy`` adds ``depth_temporal_weight * E_z`` when the frame has a depth
    reference; the tracker's reference is the prediction's translation and the viewing ray
    through its root joint."""
    from flowmocap.body import load_body_model
    from flowmocap.fit.objective import FrameState, Scene, frame_data, frame_energy
    from flowmocap.fit.tracker import depth_reference

    model = load_body_model("default")
    cam = _camera()
    scene = Scene(model, torch.zeros(1, 10), cam)
    centre = -np.asarray(cam.R).T @ np.asarray(cam.t)
    ref = FrameState(torch.zeros(72), torch.as_tensor(centre + np.array([0.0, 0.0, 3.0]), dtype=torch.float32))
    trans, u = depth_reference(scene, ref)
    assert torch.equal(trans, ref.trans)
    with torch.no_grad():
        root = scene.forward(ref.pose, ref.trans)[0].joints[0, 0].double()
    pts = torch.stack([root, root + 0.5 * u.double()])
    px = cam.project(pts).numpy()
    assert np.allclose(px[0], px[1], atol=1e-3)

    off = {k: 0.0 for k in ("flow_weight", "silhouette_weight", "temporal_weight", "limit_weight",
                             "penetration_weight", "detector3d_weight", "pose_prior_weight", "limb_depth_weight")}
    cfg = TrackerConfig(depth_temporal_weight=250.0, **off)
    data = frame_data(None, None, cfg, 1.0)
    moved = FrameState(ref.pose.clone(), ref.trans + 0.04 * u)
    _, terms = frame_energy(scene, moved, data, cfg, 0, None, None)
    assert "depth_temporal" not in terms  # no reference: no term
    data.depth_ref = (trans, u)
    total, terms = frame_energy(scene, moved, data, cfg, 0, None, None)
    assert terms["depth_temporal"] == pytest.approx(250.0 * 0.04 ** 2, rel=1e-4)
    assert float(total) == pytest.approx(terms["depth_temporal"], rel=1e-6)
    # a move across the ray costs (almost) nothing
    side = torch.linalg.cross(u, torch.tensor([0.0, 1.0, 0.0]))
    side = side / side.norm()
    across = FrameState(ref.pose.clone(), ref.trans + 0.04 * side)
    _, terms = frame_energy(scene, across, data, cfg, 0, None, None)
    assert terms["depth_temporal"] < 1e-8


def test_the_reference_setting_is_checked():
    assert TrackerConfig(depth_temporal_reference="prediction").depth_temporal_reference == "prediction"
    with pytest.raises(InputError):
        TrackerConfig(depth_temporal_reference="next")

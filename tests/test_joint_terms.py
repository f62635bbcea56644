"""E_j and E_d in compiled passes (flowmocap.fit.joint_terms): values and gradients equal to
their torch definitions (keypoint_residuals of the projected joints, limb_depth_residuals of
the joints in the camera's axes), gradients against finite differences, missing joints and
limbs, float32 in and out."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from flowmocap.errors import InputError
from flowmocap.fit import energies as en
from flowmocap.fit.joint_terms import keypoint_energy_world, limb_depth_energy_world
from flowmocap.geometry.camera import PinholeCamera


def _camera(seed=0) -> PinholeCamera:
    rng = np.random.default_rng(seed)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    return PinholeCamera(fx=600.0, fy=606.0, cx=321.5, cy=238.0, width=640, height=480, R=R,
                         t=np.array([0.1, -0.2, 4.0]))


def _points(seed=0, B=2, dtype=torch.float64):
    rng = np.random.default_rng(seed)
    return torch.tensor(rng.normal(size=(B, 24, 3)) * 0.4, dtype=dtype, requires_grad=True)


def _grad(e, x):
    (g,) = torch.autograd.grad(e.sum(), x)
    return e.detach().numpy(), g.numpy()


@pytest.mark.parametrize("seed", range(3))
def test_keypoints_equal_to_the_torch_definition(seed):
    cam = _camera(seed)
    x = _points(seed)
    rng = np.random.default_rng(seed + 10)
    obs = cam.project(x.detach().numpy()[0]) + rng.normal(size=(24, 2)) * 30.0
    conf = rng.uniform(0.3, 1.0, 24)
    conf[rng.random(24) < 0.3] = 0.0
    n = int((conf > 0).sum())
    e0, g0 = _grad(en.keypoint_energy(cam.project(x), obs, conf, sigma=20.0) / n, x)
    e1, g1 = _grad(keypoint_energy_world(x, cam, obs, conf, 20.0, factor=1.0 / n), x)
    np.testing.assert_allclose(e1, e0, rtol=1e-12)
    np.testing.assert_allclose(g1, g0, rtol=1e-9, atol=1e-12)
    assert (g1[:, conf == 0] == 0).all()
    assert torch.autograd.gradcheck(lambda p: keypoint_energy_world(p, cam, obs, conf, 20.0), (x,), eps=1e-6, atol=1e-5)


def test_keypoints_with_a_scale_per_joint():
    """A ``(N,)`` sigma gives each joint its own Geman-McClure scale: the sum of the
    one-joint energies at their scales, with its gradient (finite differences)."""
    cam = _camera(4)
    x = _points(4)
    rng = np.random.default_rng(14)
    obs = cam.project(x.detach().numpy()[0]) + rng.normal(size=(24, 2)) * 40.0
    conf = rng.uniform(0.3, 1.0, 24)
    sigma = rng.uniform(10.0, 90.0, 24)
    e0 = sum(en.keypoint_energy(cam.project(x)[:, j:j + 1], obs[j:j + 1], conf[j:j + 1], sigma=float(sigma[j]))
             for j in range(24))
    e1 = keypoint_energy_world(x, cam, obs, conf, sigma)
    np.testing.assert_allclose(e1.detach().numpy(), e0.detach().numpy(), rtol=1e-12)
    assert torch.autograd.gradcheck(lambda p: keypoint_energy_world(p, cam, obs, conf, sigma), (x,), eps=1e-6,
                                    atol=1e-5)
    same = np.full(24, 20.0)  # a scale per joint, all equal: the scalar's arithmetic
    np.testing.assert_array_equal(keypoint_energy_world(x, cam, obs, conf, same).detach().numpy(),
                                  keypoint_energy_world(x, cam, obs, conf, 20.0).detach().numpy())
    with pytest.raises(ValueError, match="one per point"):
        keypoint_energy_world(x, cam, obs, conf, np.ones(5))


def _limb_case(seed, missing=0.25):
    rng = np.random.default_rng(seed)
    x = _points(seed)
    obs = x.detach().numpy()[0] @ np.linalg.qr(rng.normal(size=(3, 3)))[0].T + rng.normal(size=(24, 3)) * 0.1
    conf = rng.uniform(0.3, 1.0, 24)
    conf[rng.random(24) < missing] = 0.0
    obs[rng.random(24) < 0.1] = np.nan  # not given: those limbs count as undetected
    return x, obs, conf


@pytest.mark.parametrize("seed", range(3))
def test_limb_depth_equal_to_the_torch_definition(seed):
    cam = _camera(seed)
    x, obs, conf = _limb_case(seed)
    rot = torch.tensor(np.asarray(cam.R))
    e0, g0 = _grad(en.limb_depth_energy(x @ rot.T, obs, conf, sigma=0.3), x)
    e1, g1 = _grad(en.world_limb_depth_energy(x, cam, (obs, conf), 0.3), x)
    assert (e0 > 0).all()
    np.testing.assert_allclose(e1, e0, rtol=1e-12)
    np.testing.assert_allclose(g1, g0, rtol=1e-9, atol=1e-12)


def test_limb_depth_gradient_against_finite_differences_and_bad_input():
    cam = _camera(4)
    x, obs, conf = _limb_case(4, missing=0.0)
    limbs = np.array(en.DEPTH_LIMBS)
    oz = np.random.default_rng(1).uniform(-0.9, 0.9, len(limbs))
    c = np.ones(len(limbs))
    assert torch.autograd.gradcheck(lambda p: limb_depth_energy_world(p, cam.R, limbs, oz, c, 0.3), (x,),
                                    eps=1e-6, atol=1e-6)
    with pytest.raises(InputError, match="sigma"):
        en.world_limb_depth_energy(x, cam, (obs, conf), 0.0)
    with pytest.raises(InputError, match="joints3d_obs"):
        en.world_limb_depth_energy(x, cam, (obs[:3], conf), 0.3)


def test_float32_in_float32_out():
    cam = _camera(1)
    x, obs, conf = _limb_case(1)
    x32 = x.detach().float().requires_grad_(True)
    e = en.world_limb_depth_energy(x32, cam, (obs, conf), 0.3)
    e.sum().backward()
    assert e.dtype == torch.float32 and x32.grad.dtype == torch.float32
    e64, g64 = _grad(en.world_limb_depth_energy(x, cam, (obs, conf), 0.3), x)
    np.testing.assert_allclose(e.detach().numpy(), e64, rtol=1e-6)
    np.testing.assert_allclose(x32.grad.numpy(), g64, rtol=1e-5, atol=1e-6)
    kp = keypoint_energy_world(x32, cam, cam.project(x.detach().numpy()[0]) + 5.0, np.ones(24), 20.0)
    assert kp.dtype == torch.float32 and float(kp.detach()[0]) > 0


def test_the_trackers_keypoint_term_is_the_projected_energy():
    """objective.keypoint_term (E_j on the detector's points) equals keypoint_energy of the
    projected points divided by the detected joints, with its gradient."""
    from flowmocap.fit.objective import keypoint_term

    cam = _camera(2)
    x = _points(2, B=1)
    rng = np.random.default_rng(3)
    obs = cam.project(x.detach().numpy()[0]) + rng.normal(size=(24, 2)) * 15.0
    conf = rng.uniform(0.5, 1.0, 24)
    conf[:4] = 0.0
    obs[2] = np.nan  # a joint not given (and not confident): ignored
    scene = SimpleNamespace(camera=cam)
    out = SimpleNamespace(joints=x)
    cfg = SimpleNamespace(keypoint_offsets=False)
    kps = (torch.tensor(obs, dtype=torch.float32), torch.tensor(conf, dtype=torch.float32))
    e1, g1 = _grad(keypoint_term(scene, out, kps, 20.0, cfg)[None], x)
    ok = np.where(np.isfinite(obs).all(-1), conf, 0.0).astype(np.float32).astype(np.float64)
    e0, g0 = _grad(en.keypoint_energy(cam.project(x), np.float32(obs).astype(np.float64), ok, 20.0) /
                   float((conf > 0).sum()), x)
    np.testing.assert_allclose(e1, e0, rtol=1e-12)
    np.testing.assert_allclose(g1, g0, rtol=1e-9, atol=1e-12)

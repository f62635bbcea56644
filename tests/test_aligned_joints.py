"""``E_3d`` in one compiled pass (flowmocap.fit.aligned_joints): value and gradient equal to
the torch definition (``detector_joints_residuals``, differentiated by autograd through the
SVD), the gradient against finite differences, the reflection branch of the alignment,
missing joints, too few joints, coinciding detected joints, float32 input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flowmocap.errors import InputError
from flowmocap.fit import energies as en
from flowmocap.fit.aligned_joints import _aligned_kernel, aligned_joints_energy


def _reference(x, obs, conf, scale):
    """The torch definition's energy and gradient."""
    e = en._sum_sq(en.detector_joints_residuals(x, obs, conf, scale))
    (g,) = torch.autograd.grad(e.sum(), x)
    return e.detach(), g


def _compiled(x, obs, conf, scale):
    e = en.detector_joints_energy(x, obs, conf, scale)
    (g,) = torch.autograd.grad(e.sum(), x)
    return e.detach(), g


def _case(seed, mirrored=False, missing=0.3, B=2):
    rng = np.random.default_rng(seed)
    x = torch.tensor(rng.normal(size=(B, 24, 3)) * 0.3, dtype=torch.float64, requires_grad=True)
    base = x.detach().numpy()[0]
    # a bent copy of the model's joints, turned, scaled and moved: the detector's frame
    obs = (base + rng.normal(size=(24, 3)) * 0.08) @ np.linalg.qr(rng.normal(size=(3, 3)))[0].T * 1.7 + 0.4
    if mirrored:
        obs = base * np.array([-1.0, 1.0, 1.0]) + rng.normal(size=(24, 3)) * 0.01
    conf = rng.uniform(0.2, 1.0, 24)
    conf[rng.random(24) < missing] = 0.0
    obs[conf == 0] = np.nan  # a missing joint's position is not used, NaN included
    return x, obs, conf


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("scale", [0.05, 0.1, 1.0])
def test_equal_to_the_torch_definition(seed, scale):
    x, obs, conf = _case(seed)
    e0, g0 = _reference(x, obs, conf, scale)
    e1, g1 = _compiled(x, obs, conf, scale)
    assert e0.shape == e1.shape == (2,) and (e0 > 0).all()
    np.testing.assert_allclose(e1.numpy(), e0.numpy(), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(g1.numpy(), g0.numpy(), rtol=1e-9, atol=1e-13)
    assert (g1.numpy()[:, conf == 0] == 0).all()  # missing joints get no gradient


def test_the_reflection_branch():
    """A mirror image cannot be reached by a rotation: the alignment's last singular
    direction is flipped (det U det V < 0), and the gradient follows that branch too."""
    x, obs, conf = _case(7, mirrored=True, missing=0.0, B=1)
    ok = conf > 0
    xs = x.detach().numpy()[0]
    w = conf / conf.sum()
    cov = ((xs - w @ xs) * w[:, None]).T @ (obs - w @ obs)
    U, _, Vh = np.linalg.svd(cov)
    assert np.linalg.det(U) * np.linalg.det(Vh) < 0 and ok.all()
    e0, g0 = _reference(x, obs, conf, 0.1)
    e1, g1 = _compiled(x, obs, conf, 0.1)
    np.testing.assert_allclose(e1.numpy(), e0.numpy(), rtol=1e-12)
    np.testing.assert_allclose(g1.numpy(), g0.numpy(), rtol=1e-9, atol=1e-13)


def test_gradient_against_finite_differences():
    x, obs, conf = _case(3, B=1)
    ok = np.isfinite(obs).all(-1)
    c = np.where(ok, conf, 0.0)
    o = np.where(ok[:, None], obs, 0.0)
    assert torch.autograd.gradcheck(lambda t: aligned_joints_energy(t, o, c, 0.1), (x,), eps=1e-6, atol=1e-7)


def test_too_few_joints_and_coinciding_detections():
    x, obs, conf = _case(5, missing=0.0, B=1)
    few = np.zeros(24)
    few[:3] = 1.0
    e, g = _compiled(x, obs, few, 0.1)
    assert float(e) == 0.0 and not g.any()  # nothing to align, as the torch definition says
    e0, _ = _reference(x, obs, few, 0.1)
    assert float(e0) == 0.0
    same = np.tile(obs[:1], (24, 1))  # every detected joint at one point: scale 0, d_j = x_j - mean
    e1, g1 = _compiled(x, same, conf, 0.1)
    xs = x.detach().numpy()[0]
    r2 = ((xs - conf @ xs / conf.sum()) ** 2).sum(-1)
    assert float(e1) == pytest.approx(float((conf * 2 * 0.01 * (np.sqrt(1 + r2 / 0.01) - 1)).sum()), rel=1e-12)
    # autograd through the reference's SVD of a (rounding-)zero matrix may give up here (NaN
    # on some CPUs, finite on others); the written-out gradient is finite and right on all
    assert torch.isfinite(g1).all()
    assert torch.autograd.gradcheck(lambda t: aligned_joints_energy(t, same, conf, 0.1), (x,), eps=1e-6, atol=1e-7)


def test_float32_in_float32_out_and_bad_input():
    x, obs, conf = _case(2, B=1)
    x32 = x.detach().float().requires_grad_(True)
    e = en.detector_joints_energy(x32, obs, conf, 0.1)
    e.sum().backward()
    assert e.dtype == torch.float32 and x32.grad.dtype == torch.float32
    e64, g64 = _compiled(x, obs, conf, 0.1)
    np.testing.assert_allclose(e.detach().numpy(), e64.numpy(), rtol=1e-5)
    np.testing.assert_allclose(x32.grad.numpy(), g64.numpy(), rtol=1e-4, atol=1e-6)
    with pytest.raises(InputError, match="confidence"):
        en.detector_joints_energy(x, obs, -conf, 0.1)
    with pytest.raises(InputError, match="scale"):
        en.detector_joints_energy(x, obs, conf, 0.0)
    with pytest.raises(InputError, match="joints3d_obs"):
        en.detector_joints_energy(x, obs[:5], conf, 0.1)


def test_the_kernel_fills_every_batch():
    x, obs, conf = _case(1, B=3)
    ok = np.isfinite(obs).all(-1)
    energy, grad = np.full(3, np.nan), np.full((3, 24, 3), np.nan)
    _aligned_kernel(x.detach().numpy(), np.where(ok[:, None], obs, 0.0), np.where(ok, conf, 0.0), 0.1, energy, grad)
    assert np.isfinite(energy).all() and np.isfinite(grad).all()


def test_world_joints_turned_into_the_cameras_axes():
    """world_detector_joints_energy turns world joints by the camera's rotation inside the
    compiled pass and divides by the detected joints: the same as turning them first."""
    from types import SimpleNamespace

    x, obs, conf = _case(4, B=1)
    R = np.linalg.qr(np.random.default_rng(9).normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    camera = SimpleNamespace(R=R)  # all the term reads of a camera
    ref = en._sum_sq(en.detector_joints_residuals(x @ torch.tensor(R).T, obs, conf, 0.1)) / int((conf > 0).sum())
    (g_ref,) = torch.autograd.grad(ref.sum(), x)
    new = en.world_detector_joints_energy(x, camera, (obs, conf), 0.1)
    (g_new,) = torch.autograd.grad(new.sum(), x)
    np.testing.assert_allclose(new.detach().numpy(), ref.detach().numpy(), rtol=1e-12)
    np.testing.assert_allclose(g_new.numpy(), g_ref.numpy(), rtol=1e-9, atol=1e-13)

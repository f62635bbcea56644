"""The compiled joint-limit and root-difference kernels (fit.rotation_terms): the same
values and gradients as the torch-op definitions, Jacobians against finite differences."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from flowmocap.errors import InputError
from flowmocap.fit import energies as en
from flowmocap.fit import rotation_terms as rt
from flowmocap.fit.joint_limits import JointLimits, default_joint_limits


def _poses(scale: float, n: int = 6, seed: int = 0) -> torch.Tensor:
    return torch.as_tensor(np.random.default_rng(seed).normal(scale=scale, size=(n, 72)))


def _both(fn, pose: torch.Tensor, monkeypatch):
    """Values and vector-Jacobian products of ``fn`` by the kernel and by torch ops."""
    out = []
    g = None
    for compiled in (True, False):
        monkeypatch.setattr(en, "_COMPILED", compiled)
        p = pose.clone().requires_grad_()
        r = fn(p)
        if g is None:
            g = torch.as_tensor(np.random.default_rng(1).normal(size=r.shape))
        (r * g).sum().backward()
        out.append((r.detach(), p.grad))
    return out


@pytest.mark.parametrize("scale", [1e-4, 0.3, 1.0, 2.5])
def test_joint_limits_kernel_matches_the_torch_definition(scale, monkeypatch):
    pose = _poses(scale)
    (r1, g1), (r2, g2) = _both(en.joint_limit_residuals, pose, monkeypatch)
    if scale >= 1.0:
        assert (r1 != 0).sum() > 20  # the limits are exercised
    np.testing.assert_allclose(r1, r2, atol=1e-12 * max(1.0, float(r2.abs().max())))
    np.testing.assert_allclose(g1, g2, atol=1e-11 * max(1.0, float(g2.abs().max())))


@pytest.mark.parametrize("scale", [1e-5, 0.3, 1.5, 3.0])
def test_root_difference_kernel_matches_the_torch_definition(scale, monkeypatch):
    pose = _poses(scale)
    prev = _poses(scale, seed=7)
    (r1, g1), (r2, g2) = _both(lambda p: en.temporal_residuals(p, prev), pose, monkeypatch)
    np.testing.assert_allclose(r1, r2, atol=1e-12)
    np.testing.assert_allclose(g1, g2, atol=1e-10)


def test_root_difference_near_pi_and_identity():
    # a person facing an OpenCV camera: global rotation close to pi about x
    w = torch.tensor([[np.pi - 1e-3, 0.02, -0.01], [1e-9, 0.0, 0.0], [0.1, 0.2, 0.3]], dtype=torch.float64)
    ref = w + torch.tensor([[0.01, -0.02, 0.005], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    phi = rt.root_difference(w, ref)
    R = Rotation.from_rotvec(ref.numpy()).inv() * Rotation.from_rotvec(w.numpy())
    np.testing.assert_allclose(phi, R.as_rotvec(), atol=1e-12)
    assert 0.005 < float(phi[0].norm()) < 0.05
    np.testing.assert_allclose(phi[1:], 0.0, atol=1e-12)
    w = w.requires_grad_()
    ref = ref.clone().requires_grad_()
    assert torch.autograd.gradcheck(rt.root_difference, (w, ref))


def test_kernels_pass_gradcheck_in_both_arguments():
    p = _poses(0.9, n=2, seed=3).requires_grad_()
    q = _poses(0.9, n=2, seed=4).requires_grad_()
    assert torch.autograd.gradcheck(en.joint_limit_residuals, (p,))
    assert torch.autograd.gradcheck(en.temporal_residuals, (p, q))  # q: E_theta's reference may be optimised too


def test_joint_limit_jacobian_matches_finite_differences():
    pose = _poses(1.2, n=1, seed=5)[0].numpy()
    r, J = en.joint_limit_jacobian(pose)
    assert r.shape == (69,) and J.shape == (69, 72) and (r != 0).sum() > 5
    np.testing.assert_allclose(r, en.joint_limit_residuals(torch.as_tensor(pose)[None])[0].numpy(), atol=1e-14)
    h = 1e-6
    for col in range(3, 72):
        d = np.zeros(72)
        d[col] = h
        fd = (en.joint_limit_jacobian(pose + d)[0] - en.joint_limit_jacobian(pose - d)[0]) / (2 * h)
        np.testing.assert_allclose(J[:, col], fd, atol=1e-6 * max(1.0, np.abs(fd).max()), err_msg=f"column {col}")
    np.testing.assert_allclose(J[:, :3], 0.0)  # the root has no limits


def test_a_chart_the_kernel_cannot_use_is_refused():
    lim = default_joint_limits()
    charts = list(lim.charts)
    charts[4] = "XZX"  # proper Euler angles: no Tait-Bryan decomposition
    with pytest.raises(InputError, match="Tait-Bryan"):
        en.joint_limit_residuals(_poses(1.0, n=1), JointLimits(lim.lower, lim.upper, tuple(charts)))


@pytest.mark.parametrize("offset", [0.0, 1e-7])
def test_joint_limit_kernel_at_gimbal_lock_equals_the_torch_definition(offset, monkeypatch):
    """The locked branch of rotation_terms._limit_kernel (middle Euler angle at +-pi/2;
    random poses never lock) against the torch definition (joint_angles ->
    matrix_to_euler's locked branch): values and the vector-Jacobian product, inside the
    lock band and at the exact lock, where both floor the middle angle's cosine at the
    machine epsilon (without the floor the kernel's gradient there was rounding noise,
    entries up to 4 where the torch definition's are below 0.5)."""
    import math

    from flowmocap.geometry import euler_to_matrix, matrix_to_axis_angle

    pose = torch.zeros(1, 24, 3, dtype=torch.float64)
    # left knee (XZY), left elbow (YZX), left wrist (ZYX): middle angle pi/2 - offset
    for joint, order in ((4, "XZY"), (18, "YZX"), (20, "ZYX")):
        ang = torch.tensor([0.3, math.pi / 2 - offset, -0.2], dtype=torch.float64)
        pose[0, joint] = matrix_to_axis_angle(euler_to_matrix(ang, order))
    pose = pose.reshape(1, 72)
    out = []
    gvec = torch.tensor(np.random.default_rng(5).normal(size=(1, 69)))
    for compiled in (True, False):
        monkeypatch.setattr(en, "_COMPILED", compiled)
        p = pose.clone().requires_grad_()
        r = en.joint_limit_residuals(p)
        (r * gvec).sum().backward()
        out.append((r.detach(), p.grad))
    (r1, g1), (r0, g0) = out
    assert (r0 != 0).sum() >= 3
    np.testing.assert_allclose(r1.numpy(), r0.numpy(), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(g1.numpy(), g0.numpy(), rtol=1e-6, atol=1e-6 * float(g0.abs().max()))

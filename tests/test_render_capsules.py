"""The capsule model distance map C_M (paper Sec. 3.5) and capsule projection."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flowmocap.errors import InputError
from flowmocap.render import capsule_distance_map, project_capsules


def _exact_map(a, b, r, H, W):
    """Brute force in numpy: max(0, min_k dist(p, segment_k) - r_k) at every pixel centre."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    p = np.stack([u, v], -1)[:, :, None, :]  # (H, W, 1, 2)
    d = b - a
    t = np.clip(((p - a) * d).sum(-1) / (d * d).sum(-1), 0, 1)
    dist = np.linalg.norm(p - (a + t[..., None] * d), axis=-1)
    return np.maximum(0.0, (dist - r).min(-1))


def _capsules(seed=0, K=6, H=37, W=53):
    rng = np.random.default_rng(seed)
    a = rng.uniform([0, 0], [W, H], size=(K, 2))
    b = a + rng.normal(0, 8, size=(K, 2))
    r = rng.uniform(1.0, 4.0, size=K)
    return a, b, r


@pytest.mark.parametrize("step", [1, 3, 4])
def test_distance_map_is_exact_at_grid_points(step):
    H, W = 37, 53
    a, b, r = _capsules()
    d = capsule_distance_map(torch.tensor(a), torch.tensor(b), torch.tensor(r), H, W, grid_step=step)
    assert d.shape == (H, W) and d.dtype == torch.float64
    exact = _exact_map(a, b, r, H, W)
    np.testing.assert_allclose(d.numpy()[::step, ::step], exact[::step, ::step], atol=1e-9)
    assert (d >= 0).all()
    # between grid points: bilinear interpolation, within step/2 px of the exact map
    assert np.abs(d.numpy() - exact).max() <= step / 2 + 1e-9
    assert (d.numpy()[exact == 0] < step).all()


def test_distance_map_gradient_matches_finite_differences():
    H, W = 21, 26
    a, b, r = _capsules(1, K=3, H=H, W=W)
    inputs = tuple(torch.tensor(x, requires_grad=True) for x in (a, b, r))
    weights = torch.tensor(np.random.default_rng(2).random((H, W)))

    def f(a_, b_, r_):
        return (capsule_distance_map(a_, b_, r_, H, W, grid_step=3) * weights).sum()

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_float32_numpy_inputs_and_errors():
    a, b, r = _capsules()
    d32 = capsule_distance_map(torch.tensor(a, dtype=torch.float32), b, r, 37, 53)
    assert d32.dtype == torch.float32
    d_np = capsule_distance_map(a, b, r, 37, 53)
    assert d_np.dtype == torch.float64
    with pytest.raises(InputError):
        capsule_distance_map(a[:, :1], b, r, 37, 53)
    with pytest.raises(InputError):
        capsule_distance_map(a, b[:-1], r, 37, 53)
    with pytest.raises(InputError):
        capsule_distance_map(a, b, -r, 37, 53)
    with pytest.raises(InputError):
        capsule_distance_map(a, b, r, 0, 53)
    with pytest.raises(InputError):
        capsule_distance_map(a, b, r, 37, 53, grid_step=0)
    bad = a.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError):
        capsule_distance_map(bad, b, r, 37, 53)


def test_project_capsules():
    starts = torch.tensor([[0.1, -0.2, 2.0], [0.0, 0.3, 3.0]], dtype=torch.float64, requires_grad=True)
    ends = torch.tensor([[0.1, 0.2, 2.0], [0.2, 0.3, 3.5]], dtype=torch.float64)
    radii = torch.tensor([0.05, 0.1], dtype=torch.float64)
    a, b, r = project_capsules(starts, ends, radii, 500.0, 500.0, 320.0, 240.0)
    np.testing.assert_allclose(a.detach().numpy(), [[345.0, 190.0], [320.0, 290.0]])
    np.testing.assert_allclose(b.detach().numpy()[0], [345.0, 290.0])
    np.testing.assert_allclose(r.detach().numpy(), [500 * 0.05 / 2.0, 500 * 0.1 / 3.25])
    (a.sum() + r.sum()).backward()
    assert torch.isfinite(starts.grad).all()
    with pytest.raises(InputError):
        project_capsules(starts.detach() * torch.tensor([1, 1, -1.0]), ends, radii, 500, 500, 320, 240)

"""The capsule model's signed distance map (C_M, paper Sec. 3.5) and capsule projection."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flowmocap.errors import InputError
from flowmocap.render import capsule_signed_distance, project_capsules


def _exact_signed(a, b, r, H, W):
    """Brute force in numpy: min_k dist(p, segment_k) - r_k at every pixel centre."""
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    p = np.stack([u, v], -1)[:, :, None, :]  # (H, W, 1, 2)
    d = b - a
    t = np.clip(((p - a) * d).sum(-1) / (d * d).sum(-1), 0, 1)
    return (np.linalg.norm(p - (a + t[..., None] * d), axis=-1) - r).min(-1)


def _capsules(seed=0, B=1, K=6, H=37, W=53):
    rng = np.random.default_rng(seed)
    a = rng.uniform([0, 0], [W, H], size=(B, K, 2))
    b = a + rng.normal(0, 8, size=(B, K, 2))
    r = rng.uniform(1.0, 4.0, size=(B, K))
    return a, b, r


@pytest.mark.parametrize("step", [1, 3, 4])
def test_signed_distance_is_exact_at_grid_points(step):
    H, W = 37, 53
    a, b, r = _capsules(B=2)
    sd = capsule_signed_distance(torch.tensor(a), torch.tensor(b), torch.tensor(r), H, W, grid_step=step)
    assert sd.shape == (2, H, W) and sd.dtype == torch.float64
    for k in range(2):
        exact = _exact_signed(a[k], b[k], r[k], H, W)
        np.testing.assert_allclose(sd[k].numpy()[::step, ::step], exact[::step, ::step], atol=1e-9)
        # between grid points: bilinear interpolation of a 1-Lipschitz function
        assert np.abs(sd[k].numpy() - exact).max() <= step / np.sqrt(2) + 1e-9


def test_float32_capsules_give_a_float32_map_of_the_same_values():
    H, W = 37, 53
    a, b, r = _capsules(B=2)
    sd64 = capsule_signed_distance(torch.tensor(a), torch.tensor(b), torch.tensor(r), H, W, grid_step=4)
    sd32 = capsule_signed_distance(*(torch.tensor(x, dtype=torch.float32) for x in (a, b, r)), H, W, grid_step=4)
    assert sd32.dtype == torch.float32
    np.testing.assert_allclose(sd32.numpy(), sd64.numpy(), atol=1e-4)


def test_a_window_is_the_same_part_of_the_whole_map():
    H, W = 37, 53
    a, b, r = (torch.tensor(x) for x in _capsules())
    whole = capsule_signed_distance(a, b, r, H, W, grid_step=4)
    part = capsule_signed_distance(a, b, r, 13, 21, grid_step=4, origin=(8, 12))
    torch.testing.assert_close(part, whole[:, 8:21, 12:33])
    with pytest.raises(InputError):
        capsule_signed_distance(a, b, r, 13, 21, grid_step=4, origin=(6, 12))


def test_signed_distance_gradient_matches_finite_differences():
    H, W = 19, 23
    a, b, r = _capsules(5, B=2, K=3, H=H, W=W)
    inputs = tuple(torch.tensor(x, requires_grad=True) for x in (a, b, r))
    w = torch.tensor(np.random.default_rng(2).random((H, W)))
    f = lambda a_, b_, r_: (capsule_signed_distance(a_, b_, r_, H, W, 3) * w).sum((1, 2))  # noqa: E731
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6)


def test_signed_distance_errors():
    a, b, r = (torch.tensor(x) for x in _capsules())
    with pytest.raises(InputError):
        capsule_signed_distance(a[..., :1], b, r, 37, 53)
    with pytest.raises(InputError):
        capsule_signed_distance(a, b[:, :-1], r, 37, 53)
    with pytest.raises(InputError):
        capsule_signed_distance(a, b, r[:, :-1], 37, 53)
    with pytest.raises(InputError):
        capsule_signed_distance(a, b, r, 0, 53)
    with pytest.raises(InputError):
        capsule_signed_distance(a, b, r, 37, 53, grid_step=0)


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

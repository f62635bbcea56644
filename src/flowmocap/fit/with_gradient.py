"""Energies whose gradient is computed together with their value, as one autograd node.

The tracker's compiled terms (:mod:`flowmocap.fit.aligned_joints`,
:mod:`flowmocap.fit.joint_terms`, E_c with capsules and E_sp in
:mod:`flowmocap.fit.energies`) each compute a ``(B,)`` energy and its gradient with respect
to their input tensors in float64 NumPy and Numba; :func:`energy_with_gradient` wraps
such a computation so that autograd sees one node: the gradients are kept from the
forward pass and scaled by the incoming gradient in the backward pass.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

__all__ = ["energy_with_gradient"]


class _WithGradient(torch.autograd.Function):
    @staticmethod
    def forward(ctx, compute, *inputs):  # noqa: D102
        arrays = [np.ascontiguousarray(x.detach().to(torch.float64).numpy()) for x in inputs]
        energy, grads = compute(*arrays)
        ctx.save_for_backward(*(torch.from_numpy(np.asarray(g, np.float64)) for g in grads))
        ctx.dtypes = [x.dtype for x in inputs]
        return torch.from_numpy(np.asarray(energy, np.float64)).to(inputs[0].dtype)

    @staticmethod
    def backward(ctx, grad_out):  # noqa: D102
        go = grad_out.to(torch.float64)
        return (None, *((go.reshape((-1,) + (1,) * (g.dim() - 1)) * g).to(dt)
                        for g, dt in zip(ctx.saved_tensors, ctx.dtypes)))


def energy_with_gradient(compute: Callable, *inputs: torch.Tensor) -> torch.Tensor:
    """A ``(B,)`` energy of CPU tensors ``inputs`` (leading dimension ``B``) with its gradient.

    Args:
        compute: ``compute(*arrays) -> (energy (B,), grads)``: ``arrays`` are the inputs as
            C-contiguous float64 NumPy arrays; ``grads`` one float64 array per input, of
            its shape, ``d energy.sum() / d input`` (each batch row's gradient is that of
            its own energy).
        inputs: the tensors to differentiate (float32 or float64).

    Returns:
        ``(B,)`` in the first input's dtype; each input's gradient comes back in its dtype.
    """
    return _WithGradient.apply(compute, *inputs)

"""The per-frame optimiser: torch's L-BFGS with a strong-Wolfe line search that backs
off from points where the energy cannot be evaluated, and an optional stop once the
energy has stopped improving."""

from __future__ import annotations

from collections.abc import Callable

import torch

from flowmocap.errors import InputError, OptimizationError

#: Evaluations over which :func:`minimise`'s ``rel_tolerance`` measures the improvement.
STALL_WINDOW = 5


class _Stalled(Exception):
    """Raised inside the closure to end L-BFGS early (the energy stopped improving)."""


def minimise(params: list[torch.Tensor], closure_energy: Callable[[], torch.Tensor], iterations: int,
             rel_tolerance: float = 0.0) -> float:
    """L-BFGS (strong Wolfe) on ``params``, in place; raises OptimizationError on a
    non-finite energy or non-finite parameters at the end.

    A trial point of the line search where the energy cannot be evaluated (an
    :class:`~flowmocap.errors.InputError`, e.g. a step so long that part of the body
    ends up behind the camera) counts as an energy above every accepted one, with zero
    gradient, so the line search backs off towards the last good point instead of giving
    up the frame. Only a start that cannot be evaluated raises.

    With ``rel_tolerance`` > 0 the optimisation also stops as soon as the lowest energy
    seen has improved by less than ``rel_tolerance`` times its size over the last
    :data:`STALL_WINDOW` evaluations, and the parameters are set to the point of that
    lowest energy (the stop may come in the middle of a line search). L-BFGS spends most
    of a well-started frame's evaluations on improvements of a few parts in 10^5.

    Args:
        params: leaf tensors with ``requires_grad``; closure_energy: returns the scalar energy.
        iterations: L-BFGS iterations (``max_iter``; at most 1.25 times as many evaluations).
        rel_tolerance: the relative improvement below which it stops early; 0: never.

    Returns:
        the lowest energy evaluated with ``rel_tolerance``, else the last one (the
        parameters hold the result; callers that need the energy's terms at the result
        evaluate them themselves).
    """
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-7, tolerance_change=1e-9, history_size=20)
    last = [float("nan")]
    first = [None]
    best = [float("inf"), None]  # energy, parameters
    history: list[float] = []  # the lowest energy after each evaluation

    def closure():
        opt.zero_grad()
        try:
            e = closure_energy()
        except InputError as err:
            if first[0] is None:
                raise OptimizationError(f"the energy could not be evaluated at the start pose: {err}") from err
            # above every energy L-BFGS has accepted (they only decrease from the start),
            # so the Armijo test fails and the line search shrinks the step; not so high
            # that its cubic interpolation collapses the step to nothing
            wall = sum((p * 0.0).sum() for p in params) + first[0] + 1.0 + abs(first[0])
            wall.backward()  # zero gradients: nothing to follow past the wall
            return wall
        if not torch.isfinite(e):
            raise OptimizationError("the energy became non-finite (NaN or inf)")
        e.backward()
        last[0] = float(e.detach())
        if first[0] is None:
            first[0] = last[0]
        if rel_tolerance > 0:
            if last[0] < best[0]:
                best[0], best[1] = last[0], [p.detach().clone() for p in params]
            history.append(best[0])
            if len(history) > STALL_WINDOW and \
                    history[-1 - STALL_WINDOW] - best[0] <= rel_tolerance * abs(best[0]):
                raise _Stalled
        return e

    try:
        opt.step(closure)
    except _Stalled:
        pass
    except RuntimeError as err:  # torch's line search on values beyond the float range
        if "overflow" not in str(err):
            raise
        raise OptimizationError(f"the optimiser's step overflowed the float range ({err})") from err
    if best[1] is not None:
        with torch.no_grad():
            for p, b in zip(params, best[1]):
                p.copy_(b)
        last[0] = best[0]
    if not all(bool(torch.isfinite(p).all()) for p in params):
        raise OptimizationError("the optimiser left non-finite parameters (NaN or inf)")
    return last[0]

"""A body's stature (standing height) as a function of its shape, and the nearest shape of a given stature.

One camera leaves a body's absolute size open: a body 10 % larger placed 10 % further away
gives nearly the same image, so the fitted size (and with it every length and speed in
metres) is what the shape prior and the fit settle on. A user who knows the person's height
can state it (``flowmocap track --height 1.78``); the body is then given that stature and the
fit places it at the matching depth.

The stature is measured on the shaped body in the rest (T-) pose, from its sole to the top of
its head: the height of two fixed mesh vertices, the highest vertex within 2 cm of the body's
midline and the lowest vertex, both chosen once on the mean shape (:func:`stature_vertices`).
The shaped rest mesh is linear in the shape coefficients (``v = v_template + shapedirs @
betas``), so the stature is linear in them too, ``s(b) = s0 + a . b``, and the shape of a given
stature nearest to a fitted one is a closed-form projection (:func:`with_stature`).
"""

from __future__ import annotations

import numpy as np
import torch

from flowmocap.errors import InputError, ModelFileError

__all__ = ["STATURE_RANGE_M", "FITTED_STATURE_M", "MIDLINE_M", "stature_vertices", "stature", "with_stature",
           "scaled_shape", "held_stature", "check_height"]

#: Heights (metres) a stated stature must lie in: a small child to well past the tallest adults.
STATURE_RANGE_M = (0.5, 2.5)

#: Statures (metres) the first frame's shape fit is held within when no height is stated
#: (:func:`held_stature`). Over 337 trackings of the suites and real clips without a stated
#: height (the forty-third to forty-seventh sessions) the first frame's fit gave 1.51-1.71 m,
#: bar one: the Sports2D walk's man on the box, whose mask at his first frame took in a tree and
#: the sun's flare, 3.39 m. A fit outside this range is such a mask, not a person.
FITTED_STATURE_M = (1.0, 2.2)

#: Vertices within this of the body's midline (metres, ``|x|`` in the rest pose) are on it.
MIDLINE_M = 0.02


def check_height(height) -> float:
    """``height`` as a float in metres, or :class:`InputError` if it is not a number in
    :data:`STATURE_RANGE_M`."""
    try:
        h = float(height)
    except (TypeError, ValueError):
        h = float("nan")
    lo, hi = STATURE_RANGE_M
    if not lo <= h <= hi:
        raise InputError(f"height is the person's standing height in metres, between {lo:g} and {hi:g} "
                         f"(e.g. 1.75); got {height!r}.")
    return h


def stature_vertices(model) -> tuple[int, int]:
    """``(top, bottom)`` vertex indices: the highest vertex within :data:`MIDLINE_M` of the
    body's midline and the lowest vertex, on the mean shape's rest pose (y up, the SMPL axes).

    Raises:
        ModelFileError: no vertex on the midline (not an upright body in the SMPL axes).
    """
    v = model.v_template.detach().double().cpu().numpy()
    mid = np.flatnonzero(np.abs(v[:, 0]) < MIDLINE_M)
    if mid.size == 0:
        raise ModelFileError("no mesh vertex on the body's midline (|x| < 2 cm); the model is not an upright "
                             "body in the SMPL axes (y up, facing +z).")
    return int(mid[np.argmax(v[mid, 1])]), int(np.argmin(v[:, 1]))


def _linear(model) -> tuple[float, np.ndarray]:
    """``(s0, a)``: the stature is ``s0 + a @ betas`` (metres; ``a`` per shape coefficient)."""
    top, bottom = stature_vertices(model)
    vt = model.v_template.detach().double().cpu().numpy()
    sd = model.shapedirs.detach().double().cpu().numpy()
    return float(vt[top, 1] - vt[bottom, 1]), sd[top, 1, :] - sd[bottom, 1, :]


def stature(model, betas) -> float:
    """The stature (metres) of the body with shape ``betas`` (``(n,)`` or ``(1, n)``, fewer than
    the model's coefficients zero-padded)."""
    s0, a = _linear(model)
    b = np.zeros(a.size)
    given = np.asarray(torch.as_tensor(betas).detach().cpu().double().reshape(-1))
    b[: min(a.size, given.size)] = given[: a.size]
    return float(s0 + a @ b)


def with_stature(model, betas, height: float):
    """The shape nearest to ``betas`` whose stature is ``height`` metres.

    The shape coefficients are standard normal under the model's shape space, so "nearest"
    is the smallest change in them: ``b + a (h - s(b)) / |a|^2``, a move along the one
    direction that changes the stature, which leaves every direction that does not
    (proportions at a given height, girth) as fitted.

    Args:
        model: a :class:`~flowmocap.body.BodyModel`.
        betas: ``(1, n)`` or ``(n,)`` tensor (returned in the same shape and dtype).
        height: metres (:func:`check_height`).

    Returns:
        the new betas.
    """
    h = check_height(height)
    s0, a = _linear(model)
    b = torch.as_tensor(betas)
    flat = b.detach().cpu().double().reshape(-1).numpy().copy()
    n = min(a.size, flat.size)
    a_n = a[:n]
    if not np.any(a_n):
        raise ModelFileError("this body model's shape coefficients do not change its height; it cannot be given one.")
    flat[:n] += a_n * (h - (s0 + a_n @ flat[:n])) / (a_n @ a_n)
    return torch.as_tensor(flat, dtype=b.dtype).reshape(b.shape).to(b.device)


def scaled_shape(model, betas, scale: float) -> np.ndarray:
    """The shape whose rest mesh is nearest to the body of shape ``betas`` scaled by ``scale``
    about its root joint: every vertex's offset from the root ``scale`` times as long.

    The root-relative rest mesh is linear in the shape coefficients, so this is a linear
    least-squares fit over all vertices. A shape space holds no exact scaling: on the
    bundled body the fit is 5 mm from the scaled mesh at the median vertex for a factor of
    1.2 or 0.8 (10 mm at 1.4), where :func:`with_stature`, which moves only along the
    stature's direction and keeps the girth and the proportions, is 35 mm from it (70 at
    1.4). The coefficients may leave the range the shape prior expects (a factor far from
    1 is a body far from the mean's size).

    Args:
        model: a :class:`~flowmocap.body.BodyModel`.
        betas: ``(n,)`` or ``(1, n)`` shape (fewer than the model's coefficients zero-padded).
        scale: the factor (> 0).

    Returns:
        ``(S,)`` float64, S = the model's shape coefficients.
    """
    if not scale > 0:
        raise InputError(f"a scale must be positive; got {scale!r}.")
    vt = model.v_template.detach().double().cpu().numpy()
    sd = model.shapedirs.detach().double().cpu().numpy()  # (V, 3, S)
    root = model.J_regressor.detach().double().cpu().numpy()[0]  # (V,): the root joint's weights
    n = sd.shape[2]
    b = np.zeros(n)
    given = np.asarray(torch.as_tensor(betas).detach().cpu().double().reshape(-1))
    b[: min(n, given.size)] = given[:n]
    rel_t = vt - root @ vt  # (V, 3) the template's offsets from its root
    rel_d = sd - np.einsum("v,vcs->cs", root, sd)[None]  # (V, 3, S)
    target = scale * (rel_t + rel_d @ b)
    fit, *_ = np.linalg.lstsq(rel_d.reshape(-1, n), (target - rel_t).reshape(-1), rcond=None)
    return fit


def held_stature(model, betas, bounds: tuple[float, float] = FITTED_STATURE_M) -> float | None:
    """The stature (metres) a fitted shape is held at: the nearer of ``bounds`` when its own
    stature lies outside them, else None (the shape is kept).

    Args:
        model: a :class:`~flowmocap.body.BodyModel`; betas: ``(n,)`` or ``(1, n)``.
        bounds: ``(low, high)`` metres (:data:`FITTED_STATURE_M`).
    """
    own = stature(model, betas)
    if own < bounds[0]:
        return float(bounds[0])
    if own > bounds[1]:
        return float(bounds[1])
    return None

"""Rotations: axis-angle, rotation matrices, quaternions, Euler angles and the 6D form.

Every function is a pure torch function over leading-batch tensors (``(..., 3)``,
``(..., 4)``, ``(..., 3, 3)``), differentiable, and works in float32 and float64.
Angles are in radians.

Conventions
-----------
- **Rotation matrices** act on column vectors: ``x' = R @ x``. For row-vector point
  arrays ``(..., N, 3)`` that is ``points @ R.transpose(-1, -2)``.
- **Axis-angle** (rotation vector): ``rotvec = angle * axis`` with a unit ``axis``;
  the rotation is right-handed (counter-clockwise when the axis points at the viewer).
- **Quaternions** are ``(w, x, y, z)``, *scalar first* (as in roma's ``wxyz`` helpers,
  pytorch3d and Eigen's constructor; scipy's ``as_quat`` is scalar *last*, ``(x, y, z, w)``).
  ``q`` and ``-q`` are the same rotation; functions that return quaternions
  canonicalise to ``w >= 0``. ``quaternion_multiply(a, b)`` is the Hamilton product and
  matches ``quaternion_to_matrix(a) @ quaternion_to_matrix(b)``.
- **Euler angles**: see :func:`euler_to_matrix`.
- **6D**: the first two *columns* of ``R`` (Zhou et al., CVPR 2019), see
  :func:`rotation_6d_to_matrix`.

Small angles are handled with Taylor expansions (no ``norm + eps``), so values and
gradients are exact and finite at and near a zero angle.
"""

from __future__ import annotations

import torch

from flowmocap.errors import InputError

__all__ = [
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "axis_angle_to_quaternion",
    "quaternion_to_axis_angle",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "quaternion_multiply",
    "quaternion_conjugate",
    "euler_to_matrix",
    "matrix_to_euler",
    "rotation_6d_to_matrix",
    "matrix_to_rotation_6d",
]

# Below this squared angle (rad^2) the sin/cos ratios are evaluated by Taylor series.
# The series below are truncated after the theta^8 term; at theta^2 = 1e-2 the first
# omitted term is < 3e-18 relative, i.e. below float64 resolution.
SMALL_ANGLE_SQ = 1e-2
#: Taylor series in theta^2 of ``sin(theta) / theta`` and ``(1 - cos(theta)) / theta^2``
#: (Rodrigues' coefficients), used below :data:`SMALL_ANGLE_SQ`.
SINC_SERIES = (1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880)
VERSINE_SERIES = (1 / 2, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800)


def _check(x: torch.Tensor, tail: tuple[int, ...], name: str, what: str) -> None:
    if not isinstance(x, torch.Tensor):
        raise InputError(
            f"{name} must be a torch.Tensor of shape {what}, got {type(x).__name__}; "
            "wrap numpy arrays with torch.as_tensor(...)"
        )
    if x.dim() < len(tail) or tuple(x.shape[x.dim() - len(tail):]) != tail:
        raise InputError(f"{name} must have shape {what}, got {tuple(x.shape)}")


def _poly(x: torch.Tensor, coeffs: tuple[float, ...]) -> torch.Tensor:
    """sum_n coeffs[n] * x**n by Horner's rule."""
    out = torch.full_like(x, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        out = out * x + c
    return out


def _split_small(theta_sq: torch.Tensor, threshold: float = SMALL_ANGLE_SQ):
    """Mask of small squared angles, and safe inputs for the Taylor and exact branches.

    Each branch only sees values it is well defined on, so ``torch.where`` never routes
    an inf/NaN gradient from the discarded branch.
    """
    small = theta_sq < threshold
    theta_sq_small = torch.where(small, theta_sq, torch.zeros_like(theta_sq))
    theta_large = torch.sqrt(torch.where(small, torch.ones_like(theta_sq), theta_sq))
    return small, theta_sq_small, theta_large


def _skew(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrix, skew(v) @ u == cross(v, u)."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape + (3,))


# ---------------------------------------------------------------------------- axis-angle


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rotation vectors to rotation matrices (Rodrigues' formula).

    ``R = I + A(theta) K + B(theta) K^2`` with ``K = skew(rotvec)``, ``theta = |rotvec|``,
    ``A = sin(theta) / theta`` and ``B = (1 - cos(theta)) / theta^2``; ``A`` and ``B`` use
    Taylor series for ``theta^2 < 1e-2``, so the result and its gradient are exact and
    finite at ``theta = 0`` (where ``dR/drotvec_i = skew(e_i)``). Any angle is accepted,
    including ``theta >= pi``.

    Args:
        rotvec: ``(..., 3)`` axis * angle, radians.

    Returns:
        ``(..., 3, 3)`` rotation matrices (acting on column vectors).
    """
    _check(rotvec, (3,), "rotvec", "(..., 3)")
    theta_sq = (rotvec * rotvec).sum(-1)
    small, t2, theta = _split_small(theta_sq)
    a = torch.where(
        small,
        _poly(t2, SINC_SERIES),
        torch.sin(theta) / theta,
    )
    half_sinc = torch.sin(0.5 * theta) / theta  # B = 2 sin^2(theta/2) / theta^2, no cancellation
    b = torch.where(
        small,
        _poly(t2, VERSINE_SERIES),
        2.0 * half_sinc * half_sinc,
    )
    k = _skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def matrix_to_axis_angle(matrix: torch.Tensor) -> torch.Tensor:
    """Rotation matrices to rotation vectors with angles in ``[0, pi]``.

    Goes through :func:`matrix_to_quaternion` (Shepperd's largest-component branch), so
    the axis is recovered accurately near ``pi`` as well as near ``0``. At exactly ``pi``
    either of the two equivalent vectors ``+-pi * axis`` may be returned. The gradient is
    finite everywhere except at ``theta = pi`` exactly, where the map itself jumps.

    Args:
        matrix: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 3)`` axis * angle, radians, ``|rotvec| <= pi``.
    """
    return quaternion_to_axis_angle(matrix_to_quaternion(matrix))


def axis_angle_to_quaternion(rotvec: torch.Tensor) -> torch.Tensor:
    """Rotation vectors to unit quaternions ``(w, x, y, z)``.

    ``q = (cos(theta/2), sin(theta/2) * axis)``, with Taylor series near ``theta = 0``.
    The result is not sign-canonicalised: for ``theta > pi``, ``w < 0``.

    Args:
        rotvec: ``(..., 3)`` axis * angle, radians.

    Returns:
        ``(..., 4)`` unit quaternions, scalar first.
    """
    _check(rotvec, (3,), "rotvec", "(..., 3)")
    theta_sq = (rotvec * rotvec).sum(-1)
    small, t2, theta = _split_small(theta_sq)
    h2 = 0.25 * t2  # (theta/2)^2
    w = torch.where(
        small,
        _poly(h2, (1.0, -1 / 2, 1 / 24, -1 / 720, 1 / 40320)),
        torch.cos(0.5 * theta),
    )
    s = torch.where(  # sin(theta/2) / theta
        small,
        0.5 * _poly(h2, (1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880)),
        torch.sin(0.5 * theta) / theta,
    )
    return torch.cat([w[..., None], rotvec * s[..., None]], dim=-1)


def quaternion_to_axis_angle(quaternion: torch.Tensor) -> torch.Tensor:
    """Quaternions ``(w, x, y, z)`` to rotation vectors of the shortest rotation.

    The quaternion is first canonicalised to ``w >= 0``, so the angle is in ``[0, pi]``.
    It need not be unit length (the result depends only on its direction).
    ``rotvec = 2 * atan2(|v|, w) / |v| * v`` with ``v = (x, y, z)``; the ratio uses a
    Taylor series of ``atan(u) / u`` for small ``u = |v| / w``.

    Args:
        quaternion: ``(..., 4)`` quaternions, scalar first.

    Returns:
        ``(..., 3)`` axis * angle, radians.
    """
    _check(quaternion, (4,), "quaternion", "(..., 4)")
    sign = torch.where(quaternion[..., :1] < 0, -1.0, 1.0).to(quaternion.dtype)
    q = quaternion * sign
    w, v = q[..., 0], q[..., 1:]
    s_sq = (v * v).sum(-1)
    w_sq = w * w
    # small: |v| / w < 0.1, i.e. angle < ~0.2 rad. atan(u)/u = sum (-1)^n u^2n / (2n+1).
    small = s_sq < 1e-2 * w_sq
    u_sq = torch.where(small, s_sq / torch.where(small, w_sq, torch.ones_like(w_sq)), 0.0)
    w_safe = torch.where(small, w, torch.ones_like(w))
    series = _poly(u_sq, tuple((-1) ** n / (2 * n + 1) for n in range(9)))
    s = torch.sqrt(torch.where(small, torch.ones_like(s_sq), s_sq))
    w_large = torch.where(small, torch.ones_like(w), w)
    factor = torch.where(small, 2.0 * series / w_safe, 2.0 * torch.atan2(s, w_large) / s)
    return v * factor[..., None]


# --------------------------------------------------------------------------- quaternions


def quaternion_to_matrix(quaternion: torch.Tensor) -> torch.Tensor:
    """Quaternions ``(w, x, y, z)`` to rotation matrices.

    Non-unit quaternions are normalised implicitly (the formula divides by ``|q|^2``).

    Args:
        quaternion: ``(..., 4)`` quaternions, scalar first, non-zero.

    Returns:
        ``(..., 3, 3)`` rotation matrices.
    """
    _check(quaternion, (4,), "quaternion", "(..., 4)")
    w, x, y, z = quaternion.unbind(-1)
    two_s = 2.0 / (quaternion * quaternion).sum(-1)
    out = torch.stack(
        [
            1 - two_s * (y * y + z * z), two_s * (x * y - z * w), two_s * (x * z + y * w),
            two_s * (x * y + z * w), 1 - two_s * (x * x + z * z), two_s * (y * z - x * w),
            two_s * (x * z - y * w), two_s * (y * z + x * w), 1 - two_s * (x * x + y * y),
        ],
        dim=-1,
    )
    return out.reshape(quaternion.shape[:-1] + (3, 3))


def matrix_to_quaternion(matrix: torch.Tensor) -> torch.Tensor:
    """Rotation matrices to unit quaternions ``(w, x, y, z)`` with ``w >= 0``.

    Shepperd's method: of the four equivalent formulas, the one dividing by the largest
    of ``|w|, |x|, |y|, |z|`` is used, which is accurate for every rotation (near 0 and
    near pi). A slightly non-orthogonal input gives a normalised quaternion.

    Args:
        matrix: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 4)`` unit quaternions, scalar first, ``w >= 0``.
    """
    _check(matrix, (3, 3), "matrix", "(..., 3, 3)")
    m = matrix.reshape(matrix.shape[:-2] + (9,)).unbind(-1)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m
    four_sq = torch.stack(  # 4 w^2, 4 x^2, 4 y^2, 4 z^2; they sum to 4, so max >= 1
        [
            1 + m00 + m11 + m22,
            1 + m00 - m11 - m22,
            1 - m00 + m11 - m22,
            1 - m00 - m11 + m22,
        ],
        dim=-1,
    )
    # rows: 4 q_i * (w, x, y, z) for the branch of component i
    cands = torch.stack(
        [
            torch.stack([four_sq[..., 0], m21 - m12, m02 - m20, m10 - m01], dim=-1),
            torch.stack([m21 - m12, four_sq[..., 1], m10 + m01, m02 + m20], dim=-1),
            torch.stack([m02 - m20, m10 + m01, four_sq[..., 2], m12 + m21], dim=-1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, four_sq[..., 3]], dim=-1),
        ],
        dim=-2,
    )
    # unused branches may have tiny/negative 4 q_i^2; clamp keeps their (zero) gradient finite
    denom = 2.0 * torch.sqrt(four_sq.clamp_min(0.1))
    cands = cands / denom[..., None]
    best = torch.nn.functional.one_hot(four_sq.argmax(-1), 4).to(matrix.dtype)
    q = (cands * best[..., None]).sum(-2)
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0).to(q.dtype)


def quaternion_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a * b`` of quaternions ``(w, x, y, z)``.

    The rotation of ``a * b`` is "first ``b``, then ``a``":
    ``quaternion_to_matrix(a * b) == quaternion_to_matrix(a) @ quaternion_to_matrix(b)``.
    The result is not sign-canonicalised.

    Args:
        a: ``(..., 4)`` quaternions, scalar first.
        b: ``(..., 4)`` quaternions, scalar first; leading dims broadcast with ``a``.

    Returns:
        ``(..., 4)`` product.
    """
    _check(a, (4,), "a", "(..., 4)")
    _check(b, (4,), "b", "(..., 4)")
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quaternion_conjugate(quaternion: torch.Tensor) -> torch.Tensor:
    """Conjugate ``(w, -x, -y, -z)``; the inverse rotation for a unit quaternion.

    Args:
        quaternion: ``(..., 4)`` quaternions, scalar first.

    Returns:
        ``(..., 4)`` conjugates.
    """
    _check(quaternion, (4,), "quaternion", "(..., 4)")
    sign = torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=quaternion.dtype, device=quaternion.device)
    return quaternion * sign


# -------------------------------------------------------------------------------- Euler

_AXES = {"X": 0, "Y": 1, "Z": 2}


def _parse_order(order: str) -> tuple[list[int], bool]:
    """'XYZ' -> ([0, 1, 2], intrinsic=True); 'xyz' -> ([0, 1, 2], intrinsic=False)."""
    if not isinstance(order, str) or len(order) != 3:
        raise InputError(f"Euler order must be a 3-letter string like 'XYZ' or 'zxy', got {order!r}")
    if order.isupper():
        intrinsic = True
    elif order.islower():
        intrinsic = False
    else:
        raise InputError(
            f"Euler order {order!r} mixes upper and lower case; use upper case for "
            "intrinsic (R = R_first @ R_second @ R_third, as BVH/ASF channel orders) "
            "or lower case for extrinsic (scipy's convention)"
        )
    try:
        axes = [_AXES[c] for c in order.upper()]
    except KeyError:
        raise InputError(f"Euler order {order!r} may only use the letters X, Y, Z") from None
    if axes[0] == axes[1] or axes[1] == axes[2]:
        raise InputError(f"Euler order {order!r} repeats an axis in consecutive positions")
    return axes, intrinsic


def _elementary(axis: int, angle: torch.Tensor) -> torch.Tensor:
    """(...,) angle -> (..., 3, 3) right-handed rotation about the x, y or z axis."""
    c, s = torch.cos(angle), torch.sin(angle)
    o, i = torch.zeros_like(angle), torch.ones_like(angle)
    if axis == 0:
        rows = [i, o, o, o, c, -s, o, s, c]
    elif axis == 1:
        rows = [c, o, s, o, i, o, -s, o, c]
    else:
        rows = [c, -s, o, s, c, o, o, o, i]
    return torch.stack(rows, dim=-1).reshape(angle.shape + (3, 3))


def euler_to_matrix(angles: torch.Tensor, order: str) -> torch.Tensor:
    """Euler angles to rotation matrices; same convention as scipy's ``from_euler``.

    ``angles[..., k]`` is the angle about axis ``order[k]``. With ``R_a(t)`` the
    right-handed rotation by ``t`` about axis ``a``:

    - **Upper case = intrinsic** (rotating axes), e.g. ``"ZXY"``:
      ``R = R_Z(angles[..., 0]) @ R_X(angles[..., 1]) @ R_Y(angles[..., 2])``.
      This is how BVH ``CHANNELS ... Zrotation Xrotation Yrotation`` and ASF/AMC
      ``axis``/``order`` strings compose: the matrices in the order the channels are
      listed, ``R = R_first @ R_second @ R_third``. Pass the channel letters in listed
      order, with the angles in the same order.
    - **Lower case = extrinsic** (fixed axes), e.g. ``"zxy"``: the rotations are applied
      in the listed order about the fixed world axes, so
      ``R = R_third @ R_second @ R_first`` (here ``R_Y @ R_X @ R_Z``).

    So ``euler_to_matrix(a, "XYZ") == euler_to_matrix(a.flip(-1), "zyx")``. Repeated
    axes (proper Euler angles such as ``"ZXZ"``) are accepted; mixed case is rejected.

    Args:
        angles: ``(..., 3)`` angles in radians, in the order of ``order``.
        order: three letters from ``XYZ``, all upper (intrinsic) or all lower (extrinsic).

    Returns:
        ``(..., 3, 3)`` rotation matrices (acting on column vectors).
    """
    _check(angles, (3,), "angles", "(..., 3)")
    axes, intrinsic = _parse_order(order)
    r = [_elementary(ax, angles[..., k]) for k, ax in enumerate(axes)]
    return r[0] @ r[1] @ r[2] if intrinsic else r[2] @ r[1] @ r[0]


def matrix_to_euler(matrix: torch.Tensor, order: str) -> torch.Tensor:
    """Rotation matrices to Euler angles, the inverse of :func:`euler_to_matrix`.

    Only Tait-Bryan orders (three different axes, e.g. ``"ZXY"``, ``"xyz"``) are
    supported. The middle angle is in ``[-pi/2, pi/2]``, the others in ``(-pi, pi]``,
    as scipy's ``as_euler``. At gimbal lock (middle angle ``+-pi/2``) only the sum or
    difference of the outer angles is determined; the last angle applied to the axes
    (the third for intrinsic orders, the first for extrinsic) is then set to 0.

    Args:
        matrix: ``(..., 3, 3)`` rotation matrices.
        order: three different letters from ``XYZ``; upper case intrinsic, lower case
            extrinsic (see :func:`euler_to_matrix`).

    Returns:
        ``(..., 3)`` angles in radians, in the order of ``order``.
    """
    _check(matrix, (3, 3), "matrix", "(..., 3, 3)")
    axes, intrinsic = _parse_order(order)
    if len(set(axes)) != 3:
        raise InputError(f"matrix_to_euler supports only three different axes, got {order!r}")
    if not intrinsic:  # R_c R_b R_a == intrinsic "CBA" with the angles reversed
        axes = axes[::-1]
    i, j, k = axes
    sign = 1.0 if (j - i) % 3 == 1 else -1.0  # +1 for cyclic orders XYZ, YZX, ZXY
    r = lambda a, b: matrix[..., a, b]  # noqa: E731
    eps = torch.finfo(matrix.dtype).eps
    cos_b_sq = r(i, i) ** 2 + r(i, j) ** 2
    locked = cos_b_sq < 100.0 * eps  # cos(middle) below ~10 sqrt(eps)
    cos_b = torch.sqrt(cos_b_sq.clamp_min(eps * eps))
    middle = torch.atan2(sign * r(i, k), cos_b)

    def safe_atan2(y, x):
        return torch.atan2(torch.where(locked, torch.zeros_like(y), y),
                           torch.where(locked, torch.ones_like(x), x))

    first_free = safe_atan2(-sign * r(j, k), r(k, k))
    third_free = safe_atan2(-sign * r(i, j), r(i, i))
    first_locked = torch.atan2(
        torch.where(locked, sign * r(k, j), torch.zeros_like(cos_b)),
        torch.where(locked, r(j, j), torch.ones_like(cos_b)),
    )
    first = torch.where(locked, first_locked, first_free)
    third = torch.where(locked, torch.zeros_like(third_free), third_free)
    out = torch.stack([first, middle, third], dim=-1)
    return out if intrinsic else out.flip(-1)


# ----------------------------------------------------------------------------------- 6D


def rotation_6d_to_matrix(rot6d: torch.Tensor) -> torch.Tensor:
    """6D rotation representation to rotation matrices (Zhou et al., CVPR 2019).

    ``rot6d = (a1, a2)`` holds two 3-vectors, the unnormalised first and second
    *columns* of ``R``. Gram-Schmidt: ``b1 = a1/|a1|``, ``b2`` = normalised part of
    ``a2`` orthogonal to ``b1``, ``b3 = b1 x b2``; ``R = [b1 | b2 | b3]`` (columns).
    Continuous and differentiable wherever ``a1`` and ``a2`` are non-zero and not
    parallel, which makes it a good variable for optimisation.

    Args:
        rot6d: ``(..., 6)``, ``[R[:, 0], R[:, 1]]`` flattened, i.e.
            ``(R00, R10, R20, R01, R11, R21)`` for an exact rotation.

    Returns:
        ``(..., 3, 3)`` rotation matrices.
    """
    _check(rot6d, (6,), "rot6d", "(..., 6)")
    tiny = torch.finfo(rot6d.dtype).tiny
    a1, a2 = rot6d[..., :3], rot6d[..., 3:]
    b1 = a1 / torch.linalg.vector_norm(a1, dim=-1, keepdim=True).clamp_min(tiny)
    a2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = a2 / torch.linalg.vector_norm(a2, dim=-1, keepdim=True).clamp_min(tiny)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def matrix_to_rotation_6d(matrix: torch.Tensor) -> torch.Tensor:
    """Rotation matrices to the 6D representation (their first two columns).

    Args:
        matrix: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 6)``: ``(R00, R10, R20, R01, R11, R21)``.
    """
    _check(matrix, (3, 3), "matrix", "(..., 3, 3)")
    return matrix[..., :, :2].transpose(-1, -2).reshape(matrix.shape[:-2] + (6,))

"""Kalman prediction of the next pose (paper, Sec. 3.4): an EKF per joint, a KF for translation.

The tracker initialises every frame with the filters' *a-priori* prediction and, once
the frame is optimised, feeds the optimised pose back as a measurement::

    filt = PoseFilter(pose0, trans0)           # after the initialisation of frame 0
    for frame in range(1, T):
        pose, trans = filt.predict()           # a-priori pose: the optimiser's start
        pose, trans = optimise(frame, pose, trans)
        filt.update(pose, trans)               # the optimised pose is the measurement

Everything is numpy float64. Time is in frames by default (``dt = 1``), so angular
velocities are rad/frame, accelerations rad/frame^2, translations metres (m/frame,
m/frame^2); pass ``dt`` in seconds and give the noises per second instead if preferred.

Rotation filter: an error-state EKF on SO(3)
--------------------------------------------
Raw axis-angle numbers are a poor state: they jump by ``2 pi`` along the axis when the
angle passes ``pi`` (common for the global orientation, which sits near ``pi`` for a
person facing an OpenCV camera), and extrapolating them component-wise is wrong as
soon as the rotation axis is not fixed in the parametrisation. :class:`RotationEKF`
therefore keeps the rotation on the manifold:

- **Nominal state**: the rotation matrix ``R`` (3x3, maps the joint's frame into its
  parent's frame, as SMPL's ``Exp(theta_j)``) and the angular velocity ``omega`` (3,)
  in **body coordinates** (the joint's own, rotated frame), so the constant-velocity
  motion is ``R_{k+1} = R_k Exp(omega dt)``. A rotation about an axis that is fixed in
  the parent frame has a constant body-frame ``omega`` too (``Exp(a t) R0 = R0 Exp(R0^T a t)``),
  so "constant angular velocity" does not depend on the choice.
- **Error state** (6,): ``x = (dtheta, domega)`` with ``R_true = R Exp(dtheta)``
  (right / body-frame perturbation) and ``omega_true = omega + domega``; its 6x6
  covariance ``P``.
- **Predict**: ``R <- R Exp(omega dt)``, ``omega <- omega``. Substituting the true
  state, ``R Exp(dtheta) Exp((omega + domega) dt) = R Exp(omega dt) Exp(dtheta')`` gives
  ``dtheta' = Log(Exp(-omega dt) Exp(dtheta) Exp((omega + domega) dt))``; with
  ``Exp(-phi) Exp(d) Exp(phi) = Exp(Exp(-phi) d)`` and
  ``Exp(phi + e) ~ Exp(phi) Exp(J_r(phi) e)``, to first order::

      F = [[Exp(omega dt)^T, J_r(omega dt) dt],
           [0,               I               ]]

  where ``J_r(phi) = I - (1 - cos t)/t^2 [phi]x + (t - sin t)/t^3 [phi]x^2``
  (``t = |phi|``) is SO(3)'s right Jacobian. (:func:`error_transition`; the tests check
  it against finite differences of the exact error dynamics.)
- **Process noise**: white angular acceleration ``a ~ N(0, sigma_a^2 I)`` (body frame,
  rad/frame^2), held constant over a step (the "piecewise white noise" model of
  ``filterpy.common.Q_discrete_white_noise``): ``Q = sigma_a^2 G G^T`` with
  ``G = [0.5 dt^2 J_r(omega dt); dt I]``.
- **Update** with a measured rotation ``R_m`` (the optimised joint rotation, modelled
  as ``R_m = R_true Exp(v)``, ``v ~ N(0, sigma_m^2 I)``): innovation
  ``y = Log(R^T R_m)``, ``H = [I, 0]``, the usual gain ``K = P H^T (H P H^T + sigma_m^2 I)^-1``
  and Joseph-form covariance update. The correction ``dx = K y`` is injected,
  ``R <- R Exp(dx_theta)``, ``omega <- omega + dx_omega``, and the error state is reset
  to zero, which re-expresses the covariance about the new nominal rotation:
  ``P <- G P G^T``, ``G = diag(J_r(dx_theta), I)``.

Why not filterpy for the rotations: filterpy's ``ExtendedKalmanFilter`` adds the
correction to a vector state (``x + K y``) and has no injection/reset step, which is
exactly what the manifold needs, and it filters one joint at a time in Python. The
error-state EKF is ~30 lines of numpy here, and :class:`PoseFilter` runs the same code
batched over all 24 joints at once (the joints stay independent filters). The SO(3)
``exp``/``log`` come from scipy's ``Rotation`` and the right Jacobian is a small batched
numpy function below (series near 0), rather than the torch ones in
:mod:`flowmocap.geometry.rotations`: the filter is numpy end to end and runs on tiny
arrays where the torch call overhead would dominate.

Translation filter: :class:`TranslationKF` is a plain linear constant-velocity filter,
so it *is* ``filterpy.kalman.KalmanFilter`` (``F``, ``H``, ``R`` set here, ``Q`` from
``filterpy.common.Q_discrete_white_noise``).

Axis-angle outputs are chosen, among the equivalent vectors ``phi + 2 pi k phi/|phi|``
(``k`` integer), as the one nearest the last measured (or initial) axis-angle of
that joint, so the numbers handed to the optimiser (and to ``E_theta``) do not jump at
``pi`` when the optimiser's own numbers do not.

Defaults (frames at 30-60 fps, pose from the flow optimiser)
-------------------------------------------------------------
With ``dt = 1`` the filter's mean depends only on the ratio ``sigma_a / sigma_m`` (the
tracking index). The defaults use 1 for rotations (``sigma_a = 0.02 rad/frame^2``,
``sigma_m = 0.02 rad``, about the frame-to-frame jitter expected of the optimised pose)
and for translation (``0.005 m/frame^2``, ``0.005 m``). The optimised pose still
dominates the estimate (steady-state gain 0.75 on the rotation and position), the filter
is mainly a predictor: with the diffuse velocity prior the velocity is the difference
of the first two measurements after two updates, and a velocity error then halves
every frame.

The ratio was chosen on CMU 35_01 (retargeted, 60 and 30 fps) and the built-in walk,
with 0, 0.01 and 0.03 rad of white measurement noise per axis, by the mean a-priori
joint-angle error. Ratio 1 was within 6 % of the best ratio (of 0.1 ... 10) on CMU
without noise or with 0.01 rad, and within 33 % with 0.03 rad (where 0.25 is best); a
high ratio (5-10: nearly a two-point extrapolator) is best only on the perfectly smooth
built-in walk and amplifies jitter elsewhere (prediction error up to 3x). With noisy
measurements, constant-velocity prediction is *not* much better than "previous pose"
on real mocap (1.79 vs 1.67 deg at 60 fps, 0.01 rad noise); without noise it is
(1.08 vs 1.22 deg; 0.93 vs 1.40 on the walk). If the tracker's jitter is known, set
``rot_meas_noise`` to it. See :data:`DEFAULTS`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from scipy.spatial.transform import Rotation

from flowmocap.errors import InputError

__all__ = [
    "so3_hat",
    "so3_exp",
    "so3_log",
    "so3_right_jacobian",
    "nearest_rotvec",
    "error_transition",
    "DEFAULTS",
    "RotationEKF",
    "TranslationKF",
    "PoseFilter",
]

NUM_JOINTS = 24

#: Default noise levels (standard deviations). Time unit: one frame.
DEFAULTS: dict[str, float] = {
    # joint rotations
    "rot_accel_noise": 0.02,  # rad/frame^2: white angular acceleration
    "rot_meas_noise": 0.02,  # rad: frame-to-frame error of the optimised joint rotation
    "rot_init_vel_std": 0.5,  # rad/frame: prior on the unknown initial angular velocity
    # root translation
    "trans_accel_noise": 0.005,  # m/frame^2
    "trans_meas_noise": 0.005,  # m
    "trans_init_vel_std": 0.5,  # m/frame
}

_STATE_FORMAT = "flowmocap.fit.kalman.PoseFilter"
_STATE_VERSION = 1

# ----------------------------------------------------------------------------- SO(3)

# |phi|^2 below which the sin/cos ratios are evaluated by their Taylor series
# (10 terms: the first omitted one is < 1/21! ~ 2e-20 relative at |phi| = 1).
_SERIES_SQ = 1.0
_NTERMS = 10
# Columns: sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3 as power series in t^2.
_SERIES = np.array([[(-1) ** k / math.factorial(2 * k + 1 + j) for j in range(3)]
                    for k in range(_NTERMS)])
_POWERS = np.arange(_NTERMS, dtype=np.float64)


def _abc(theta_sq: np.ndarray):
    """``(sin t/t, (1 - cos t)/t^2, (t - sin t)/t^3)`` for ``t^2 = theta_sq``, exact at 0."""
    small = theta_sq < _SERIES_SQ
    series = np.power.outer(np.where(small, theta_sq, 0.0), _POWERS) @ _SERIES
    t = np.sqrt(np.where(small, 1.0, theta_sq))
    s = np.sin(t)
    hs = np.sin(0.5 * t) / t
    exact = (s / t, 2.0 * hs * hs, (t - s) / (t * t * t))
    return tuple(np.where(small, series[..., j], exact[j]) for j in range(3))


def so3_hat(v: np.ndarray) -> np.ndarray:
    """``(..., 3)`` -> ``(..., 3, 3)`` cross-product matrix: ``hat(v) @ u == cross(v, u)``."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape + (3,))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    out[..., 0, 1], out[..., 0, 2] = -z, y
    out[..., 1, 0], out[..., 1, 2] = z, -x
    out[..., 2, 0], out[..., 2, 1] = -y, x
    return out


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation vectors (radians, any angle) to rotation matrices (scipy's ``Rotation``).

    Args:
        rotvec: ``(..., 3)`` axis-angle, radians.

    Returns:
        ``(..., 3, 3)`` float64 rotation matrices (acting on column vectors).
    """
    v = np.asarray(rotvec, dtype=np.float64)
    return Rotation.from_rotvec(v.reshape(-1, 3)).as_matrix().reshape(v.shape[:-1] + (3, 3))


def so3_log(matrix: np.ndarray) -> np.ndarray:
    """Rotation matrices to rotation vectors with angle in ``[0, pi]`` (scipy's ``Rotation``).
    At exactly ``pi`` either of ``+-pi * axis`` may come back.

    Args:
        matrix: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 3)`` float64 axis * angle, radians.
    """
    m = np.asarray(matrix, dtype=np.float64)
    return Rotation.from_matrix(m.reshape(-1, 3, 3)).as_rotvec().reshape(m.shape[:-2] + (3,))


def so3_right_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """SO(3)'s right Jacobian ``J_r(phi)``: ``Exp(phi + e) ~ Exp(phi) Exp(J_r(phi) e)``.

    ``J_r(phi) = I - (1 - cos t)/t^2 K + (t - sin t)/t^3 K^2``, ``K = hat(phi)``, exact at 0.

    Args:
        rotvec: ``(..., 3)`` axis-angle, radians.

    Returns:
        ``(..., 3, 3)``.
    """
    v = np.asarray(rotvec, dtype=np.float64)
    _, b, c = _abc(np.einsum("...i,...i->...", v, v))
    k = so3_hat(v)
    return np.eye(3) - b[..., None, None] * k + c[..., None, None] * (k @ k)


def nearest_rotvec(rotvec: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The rotation vector equivalent to ``rotvec`` that is nearest ``reference``.

    The equivalents are ``(t + 2 pi k) u`` (``t u = rotvec``, ``u`` a unit axis, ``k``
    any integer); the nearest has ``k = round((u . reference - t) / 2 pi)``. A zero
    ``rotvec`` takes its axis from ``reference`` (so a reference near ``2 pi u`` gets
    ``2 pi u`` back). Use it to keep axis-angle numbers continuous over time.

    Args:
        rotvec: ``(..., 3)`` radians (typically from :func:`so3_log`, angle <= pi).
        reference: ``(..., 3)`` radians, broadcastable to ``rotvec``.

    Returns:
        ``(..., 3)`` the same rotations, radians.
    """
    v = np.asarray(rotvec, dtype=np.float64)
    ref = np.broadcast_to(np.asarray(reference, dtype=np.float64), v.shape)
    t = np.linalg.norm(v, axis=-1, keepdims=True)
    nr = np.linalg.norm(ref, axis=-1, keepdims=True)
    tiny = t < 1e-12
    u = np.where(tiny, ref / np.where(nr > 0.0, nr, 1.0), v / np.where(tiny, 1.0, t))
    along = np.sum(u * ref, axis=-1, keepdims=True)
    k = np.round((along - t) / (2.0 * math.pi))
    return v + (2.0 * math.pi) * k * u


def error_transition(omega: np.ndarray, dt: float = 1.0) -> np.ndarray:
    """Jacobian ``F`` of the rotation EKF's error dynamics for a step ``dt``.

    ``F = [[Exp(omega dt)^T, J_r(omega dt) dt], [0, I]]`` for the error state
    ``(dtheta, domega)`` defined by ``R_true = R Exp(dtheta)``, ``omega_true = omega + domega``
    (body-frame angular velocity, see the module docstring).

    Args:
        omega: ``(..., 3)`` angular velocity, radians per unit of ``dt``.
        dt: time step, in the unit ``omega`` is per (frames in the tracker's filters).

    Returns:
        ``(..., 6, 6)``.
    """
    w = np.asarray(omega, dtype=np.float64)
    phi = w * dt
    F = np.zeros(w.shape[:-1] + (6, 6))
    F[..., :3, :3] = np.swapaxes(so3_exp(phi), -1, -2)
    F[..., :3, 3:] = so3_right_jacobian(phi) * dt
    F[..., 3:, 3:] = np.eye(3)
    return F


# ------------------------------------------------------------ batched EKF core (N joints)


def _ekf_predict(R, w, P, dt, accel_std):
    """Predict N independent joints in place: R (N,3,3), w (N,3), P (N,6,6), accel_std (N,)."""
    phi = w * dt
    E = so3_exp(phi)
    Jr = so3_right_jacobian(phi)
    F = np.zeros(P.shape)
    F[:, :3, :3] = np.swapaxes(E, -1, -2)
    F[:, :3, 3:] = Jr * dt
    F[:, 3:, 3:] = np.eye(3)
    G = np.empty(P.shape[:-1] + (3,))
    G[:, :3] = (0.5 * dt * dt) * Jr
    G[:, 3:] = dt * np.eye(3)
    G *= accel_std[:, None, None]
    Pn = F @ P @ np.swapaxes(F, -1, -2) + G @ np.swapaxes(G, -1, -2)
    P[...] = 0.5 * (Pn + np.swapaxes(Pn, -1, -2))
    R[...] = R @ E


def _ekf_update(R, w, P, R_meas, meas_std):
    """One update for N joints with measured rotations R_meas (N,3,3), in place."""
    y = so3_log(np.swapaxes(R, -1, -2) @ R_meas)  # (N, 3)
    S = P[:, :3, :3] + (meas_std**2)[:, None, None] * np.eye(3)
    K = np.swapaxes(np.linalg.solve(S, P[:, :3, :]), -1, -2)  # (N, 6, 3); P, S symmetric
    dx = (K @ y[..., None])[..., 0]
    IKH = np.broadcast_to(np.eye(6), P.shape).copy()
    IKH[:, :, :3] -= K
    Kr = K * meas_std[:, None, None]
    Pn = IKH @ P @ np.swapaxes(IKH, -1, -2) + Kr @ np.swapaxes(Kr, -1, -2)
    # reset: re-express the covariance about the corrected rotation
    Gr = np.broadcast_to(np.eye(6), P.shape).copy()
    Gr[:, :3, :3] = so3_right_jacobian(dx[:, :3])
    Pn = Gr @ Pn @ np.swapaxes(Gr, -1, -2)
    P[...] = 0.5 * (Pn + np.swapaxes(Pn, -1, -2))
    Rn = R @ so3_exp(dx[:, :3])
    R[...] = Rn @ (1.5 * np.eye(3) - 0.5 * np.swapaxes(Rn, -1, -2) @ Rn)  # re-orthonormalise
    w += dx[:, 3:]


# ---------------------------------------------------------------------------- checks


def _array(x, shape: tuple[int, ...], name: str, hint: str = "") -> np.ndarray:
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name} must be numbers of shape {shape}, got {type(x).__name__}") from e
    if a.shape != shape:
        raise InputError(f"{name} must have shape {shape}, got {a.shape}{hint}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} must be finite, got non-finite values")
    return a


def _rotation_input(x, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """A rotation as (3,) axis-angle or (3, 3) matrix -> (matrix, rotvec or None)."""
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name} must be a (3,) axis-angle or (3, 3) rotation matrix") from e
    if a.shape == (3,):
        a = _array(a, (3,), name)
        return so3_exp(a), a
    if a.shape == (3, 3):
        a = _array(a, (3, 3), name)
        if not (np.allclose(a.T @ a, np.eye(3), atol=1e-6) and np.linalg.det(a) > 0):
            raise InputError(f"{name} is not a rotation matrix (R^T R != I or det(R) <= 0)")
        return a, None
    raise InputError(
        f"{name} must be a (3,) axis-angle or (3, 3) rotation matrix, got shape {a.shape}"
    )


def _positive(x, name: str, n: int | None = None) -> np.ndarray | float:
    if n is None:
        number = isinstance(x, (int, float, np.floating, np.integer))
        if not (number and math.isfinite(x) and x > 0):
            raise InputError(f"{name} must be a positive number, got {x!r}")
        return float(x)
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name} must be a positive number or {n} of them") from e
    if a.ndim == 0:
        a = np.full(n, float(a))
    if a.shape != (n,):
        raise InputError(f"{name} must be a positive number or {n} of them, got shape {a.shape}")
    if not np.all(np.isfinite(a) & (a > 0)):
        raise InputError(f"{name} must be positive and finite")
    return a


def _require(state: dict, keys: tuple[str, ...], owner: str) -> None:
    for key in keys:
        if key not in state:
            raise InputError(f"{owner} state has no {key!r}; pass what state_dict() returned")


def _mat(state: dict, key: str, shape: tuple[int, ...], owner: str) -> np.ndarray:
    _require(state, (key,), owner)
    return _array(state[key], shape, f"{owner} state {key!r}")


#: The constructor settings that RotationEKF and TranslationKF keep in their state dicts.
_SETTINGS = ("dt", "accel_noise", "meas_noise", "init_vel_std")


def _settings(filt: Any) -> dict[str, float]:
    """``filt``'s :data:`_SETTINGS`, the first entries of its ``state_dict()``."""
    return {key: getattr(filt, key) for key in _SETTINGS}


def _settings_from(state: Any, owner: str) -> dict[str, Any]:
    """The :data:`_SETTINGS` of a ``state_dict()`` as constructor keyword arguments."""
    if not isinstance(state, dict):
        raise InputError(f"{owner} state must be the dict state_dict() returned")
    _require(state, _SETTINGS, owner)
    return {key: state[key] for key in _SETTINGS}


# -------------------------------------------------------------------------- RotationEKF


class RotationEKF:
    """Error-state EKF for one joint rotation, constant angular velocity on SO(3).

    See the module docstring for the model and its Jacobians.

    Args:
        init_rotation: ``(3,)`` axis-angle (radians) or ``(3, 3)`` rotation matrix.
        init_omega: ``(3,)`` body-frame angular velocity, rad/frame (default 0).
        dt: time step (frames).
        accel_noise: std of the white angular acceleration, rad/frame^2.
        meas_noise: std of a measured rotation, rad (per axis).
        init_vel_std: std of the prior on ``init_omega``, rad/frame.

    The initial rotation's variance is ``meas_noise^2`` (it is a measurement).
    """

    def __init__(
        self,
        init_rotation,
        init_omega=None,
        dt: float = 1.0,
        accel_noise: float = DEFAULTS["rot_accel_noise"],
        meas_noise: float = DEFAULTS["rot_meas_noise"],
        init_vel_std: float = DEFAULTS["rot_init_vel_std"],
    ):
        R, rv = _rotation_input(init_rotation, "init_rotation")
        w = np.zeros(3) if init_omega is None else _array(init_omega, (3,), "init_omega")
        self.dt = _positive(dt, "dt")
        self._accel = np.array([_positive(accel_noise, "accel_noise")])
        self._meas = np.array([_positive(meas_noise, "meas_noise")])
        self.init_vel_std = _positive(init_vel_std, "init_vel_std")
        self._R = R.copy()
        self._w = w.copy()
        self._P = np.diag([self._meas[0] ** 2] * 3 + [self.init_vel_std**2] * 3)
        self._ref = rv.copy() if rv is not None else so3_log(R)

    @property
    def accel_noise(self) -> float:
        """Std of the white angular acceleration, rad/frame^2."""
        return float(self._accel[0])

    @property
    def meas_noise(self) -> float:
        """Std of a measured rotation, rad (per axis)."""
        return float(self._meas[0])

    @property
    def matrix(self) -> np.ndarray:
        """``(3, 3)`` current estimate (a priori after :meth:`predict`, a posteriori after
        :meth:`update`)."""
        return self._R.copy()

    @property
    def rotvec(self) -> np.ndarray:
        """``(3,)`` current estimate as axis-angle, nearest the last measured axis-angle."""
        return nearest_rotvec(so3_log(self._R), self._ref)

    @property
    def omega(self) -> np.ndarray:
        """``(3,)`` body-frame angular velocity estimate, rad/frame."""
        return self._w.copy()

    @property
    def covariance(self) -> np.ndarray:
        """``(6, 6)`` error-state covariance, order ``(dtheta, domega)``."""
        return self._P.copy()

    def transition_jacobian(self) -> np.ndarray:
        """``(6, 6)`` ``F`` that the next :meth:`predict` will use."""
        return error_transition(self._w, self.dt)

    def predict(self) -> np.ndarray:
        """Advance one step; returns the a-priori rotation as ``(3,)`` axis-angle."""
        _ekf_predict(self._R[None], self._w[None], self._P[None], self.dt, self._accel)
        return self.rotvec

    def update(self, measurement) -> np.ndarray:
        """Correct with a measured rotation (``(3,)`` axis-angle in radians or ``(3, 3)`` matrix).

        Returns the a-posteriori rotation as ``(3,)`` axis-angle, radians.
        """
        Rm, rv = _rotation_input(measurement, "measurement")
        _ekf_update(self._R[None], self._w[None], self._P[None], Rm[None], self._meas)
        self._ref[...] = rv if rv is not None else nearest_rotvec(so3_log(Rm), self._ref)
        return self.rotvec

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume exactly, as JSON-serialisable lists and floats."""
        return {
            **_settings(self),
            "R": self._R.tolist(),
            "omega": self._w.tolist(),
            "P": self._P.tolist(),
            "ref": self._ref.tolist(),
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> "RotationEKF":
        """Rebuild a filter from :meth:`state_dict` (also after a JSON round trip)."""
        settings = _settings_from(state, "RotationEKF")
        R = _mat(state, "R", (3, 3), "RotationEKF")
        f = cls(R, _mat(state, "omega", (3,), "RotationEKF"), **settings)
        f._R = R
        f._P = _mat(state, "P", (6, 6), "RotationEKF")
        f._ref = _mat(state, "ref", (3,), "RotationEKF")
        return f


# ------------------------------------------------------------------------ TranslationKF


class TranslationKF:
    """Linear constant-velocity Kalman filter for the root translation (``filterpy``).

    State ``(x, y, z, vx, vy, vz)`` (metres, m/frame), measurement ``(x, y, z)``.
    ``F = [[I, dt I], [0, I]]``, ``H = [I, 0]``,
    ``Q = Q_discrete_white_noise(2, dt, accel_noise^2, block_size=3, order_by_dim=False)``,
    ``R = meas_noise^2 I``, ``P0 = diag(meas_noise^2 I, init_vel_std^2 I)``.

    Args:
        init_trans: ``(3,)`` metres.
        init_velocity: ``(3,)`` m/frame (default 0).
        dt: time step (frames).
        accel_noise: std of the white acceleration, m/frame^2.
        meas_noise: std of a measured translation, m (per axis).
        init_vel_std: std of the prior on ``init_velocity``, m/frame.

    The underlying ``filterpy.kalman.KalmanFilter`` is :attr:`kf`.
    """

    def __init__(
        self,
        init_trans,
        init_velocity=None,
        dt: float = 1.0,
        accel_noise: float = DEFAULTS["trans_accel_noise"],
        meas_noise: float = DEFAULTS["trans_meas_noise"],
        init_vel_std: float = DEFAULTS["trans_init_vel_std"],
    ):
        p = _array(init_trans, (3,), "init_trans")
        v = np.zeros(3) if init_velocity is None else _array(init_velocity, (3,), "init_velocity")
        self.dt = _positive(dt, "dt")
        self.accel_noise = _positive(accel_noise, "accel_noise")
        self.meas_noise = _positive(meas_noise, "meas_noise")
        self.init_vel_std = _positive(init_vel_std, "init_vel_std")
        kf = KalmanFilter(dim_x=6, dim_z=3)
        kf.F = np.block([[np.eye(3), self.dt * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
        kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
        kf.Q = Q_discrete_white_noise(dim=2, dt=self.dt, var=self.accel_noise**2,
                                      block_size=3, order_by_dim=False)
        kf.R = self.meas_noise**2 * np.eye(3)
        kf.x = np.concatenate([p, v])[:, None]
        kf.P = np.diag([self.meas_noise**2] * 3 + [self.init_vel_std**2] * 3)
        self.kf = kf

    @property
    def position(self) -> np.ndarray:
        """``(3,)`` current estimate, metres."""
        return self.kf.x[:3, 0].copy()

    @property
    def velocity(self) -> np.ndarray:
        """``(3,)`` velocity estimate, m/frame."""
        return self.kf.x[3:, 0].copy()

    @property
    def covariance(self) -> np.ndarray:
        """``(6, 6)`` state covariance."""
        return self.kf.P.copy()

    def predict(self) -> np.ndarray:
        """Advance one step; returns the a-priori translation ``(3,)`` metres."""
        self.kf.predict()
        return self.position

    def update(self, trans) -> np.ndarray:
        """Correct with a measured translation ``(3,)`` metres; returns the a-posteriori
        one, ``(3,)`` metres."""
        self.kf.update(_array(trans, (3,), "trans")[:, None])
        return self.position

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume exactly, as JSON-serialisable lists and floats."""
        return {
            **_settings(self),
            "x": self.kf.x[:, 0].tolist(),
            "P": self.kf.P.tolist(),
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> "TranslationKF":
        """Rebuild a filter from :meth:`state_dict` (also after a JSON round trip)."""
        settings = _settings_from(state, "TranslationKF")
        x = _mat(state, "x", (6,), "TranslationKF")
        f = cls(x[:3], x[3:], **settings)
        f.kf.P = _mat(state, "P", (6, 6), "TranslationKF")
        return f


# --------------------------------------------------------------------------- PoseFilter


class PoseFilter:
    """24 joint-rotation EKFs (SMPL order, joint 0 = global orientation) + a translation KF.

    The 24 :class:`RotationEKF` s are independent; their states are stacked so that one
    batched numpy pass serves all of them (:attr:`joints` gives per-joint views that
    share this storage).

    Args:
        init_pose: ``(72,)`` or ``(24, 3)`` axis-angle, radians (the initialised frame).
        init_trans: ``(3,)`` metres.
        dt: time step (frames).
        rot_accel_noise: rad/frame^2, one number or ``(24,)`` per joint.
        rot_meas_noise: rad, one number or ``(24,)`` per joint.
        trans_accel_noise: m/frame^2.
        trans_meas_noise: m.
        rot_init_vel_std: rad/frame, one number or ``(24,)``: prior on the initial
            angular velocity (taken as 0).
        trans_init_vel_std: m/frame: prior on the initial velocity (taken as 0).

    Defaults: :data:`DEFAULTS`.
    """

    def __init__(
        self,
        init_pose,
        init_trans,
        dt: float = 1.0,
        rot_accel_noise=DEFAULTS["rot_accel_noise"],
        rot_meas_noise=DEFAULTS["rot_meas_noise"],
        trans_accel_noise: float = DEFAULTS["trans_accel_noise"],
        trans_meas_noise: float = DEFAULTS["trans_meas_noise"],
        rot_init_vel_std=DEFAULTS["rot_init_vel_std"],
        trans_init_vel_std: float = DEFAULTS["trans_init_vel_std"],
    ):
        pose = _pose_input(init_pose, "init_pose")
        self.dt = _positive(dt, "dt")
        self._accel = _positive(rot_accel_noise, "rot_accel_noise", NUM_JOINTS)
        self._meas = _positive(rot_meas_noise, "rot_meas_noise", NUM_JOINTS)
        self._vel0 = _positive(rot_init_vel_std, "rot_init_vel_std", NUM_JOINTS)
        self._R = so3_exp(pose)
        self._w = np.zeros((NUM_JOINTS, 3))
        self._P = np.zeros((NUM_JOINTS, 6, 6))
        self._P[:, [0, 1, 2], [0, 1, 2]] = (self._meas**2)[:, None]
        self._P[:, [3, 4, 5], [3, 4, 5]] = (self._vel0**2)[:, None]
        self._ref = pose.copy()
        self.translation = TranslationKF(init_trans, dt=self.dt, accel_noise=trans_accel_noise,
                                         meas_noise=trans_meas_noise,
                                         init_vel_std=trans_init_vel_std)
        self.steps = 0
        self._make_views()

    def _make_views(self) -> None:
        joints = []
        for j in range(NUM_JOINTS):
            f = RotationEKF.__new__(RotationEKF)
            f.dt = self.dt
            f._accel, f._meas = self._accel[j:j + 1], self._meas[j:j + 1]
            f.init_vel_std = float(self._vel0[j])
            f._R, f._w, f._P, f._ref = self._R[j], self._w[j], self._P[j], self._ref[j]
            joints.append(f)
        self.joints: tuple[RotationEKF, ...] = tuple(joints)
        """Per-joint :class:`RotationEKF` views of the stacked state (for inspection)."""

    # --------------------------------------------------------------- estimates
    @property
    def pose(self) -> np.ndarray:
        """``(72,)`` current pose estimate, axis-angle nearest the last measured pose."""
        return nearest_rotvec(so3_log(self._R), self._ref).reshape(-1)

    @property
    def trans(self) -> np.ndarray:
        """``(3,)`` current translation estimate, metres."""
        return self.translation.position

    @property
    def rotations(self) -> np.ndarray:
        """``(24, 3, 3)`` current joint rotation matrices."""
        return self._R.copy()

    # --------------------------------------------------------------- filtering
    def predict(self) -> tuple[np.ndarray, np.ndarray]:
        """Advance one frame; returns the a-priori ``(pose (72,), trans (3,))``.

        Call once per frame before optimising it; calling it twice without an update
        skips a frame (a two-step prediction).
        """
        _ekf_predict(self._R, self._w, self._P, self.dt, self._accel)
        self.translation.predict()
        self.steps += 1
        return self.pose, self.trans

    def update(self, pose, trans) -> tuple[np.ndarray, np.ndarray]:
        """Correct with the optimised ``pose`` (``(72,)`` or ``(24, 3)``) and ``trans`` ``(3,)``.

        Returns the a-posteriori (filtered) ``(pose (72,), trans (3,))``. The tracker
        keeps its optimised pose as the result; the filtered one is a lightly smoothed
        alternative.
        """
        p = _pose_input(pose, "pose")
        t = _array(trans, (3,), "trans")
        _ekf_update(self._R, self._w, self._P, so3_exp(p), self._meas)
        self._ref[...] = p
        self.translation.update(t)
        return self.pose, self.trans

    # --------------------------------------------------------------- persistence
    def state_dict(self) -> dict[str, Any]:
        """The complete filter state as plain lists/floats (``json.dumps``-able).

        :meth:`from_state_dict` rebuilds a filter whose predictions are bit-identical.
        """
        return {
            "format": _STATE_FORMAT,
            "version": _STATE_VERSION,
            "dt": self.dt,
            "steps": self.steps,
            "rot_accel_noise": self._accel.tolist(),
            "rot_meas_noise": self._meas.tolist(),
            "rot_init_vel_std": self._vel0.tolist(),
            "R": self._R.tolist(),
            "omega": self._w.tolist(),
            "P": self._P.tolist(),
            "ref": self._ref.tolist(),
            "translation": self.translation.state_dict(),
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> "PoseFilter":
        """Rebuild a :class:`PoseFilter` from :meth:`state_dict` (also after JSON)."""
        if not isinstance(state, dict) or state.get("format") != _STATE_FORMAT:
            raise InputError("not a PoseFilter state: pass the dict that state_dict() returned")
        if state.get("version") != _STATE_VERSION:
            raise InputError(f"PoseFilter state version {state.get('version')!r} is not "
                             f"supported (expected {_STATE_VERSION})")
        n = NUM_JOINTS
        _require(state, ("dt", "steps", "rot_accel_noise", "rot_meas_noise", "rot_init_vel_std",
                         "translation"), "PoseFilter")
        f = cls.__new__(cls)
        f.dt = _positive(state["dt"], "dt")
        f.steps = int(state["steps"])
        f._accel = _positive(state["rot_accel_noise"], "rot_accel_noise", n)
        f._meas = _positive(state["rot_meas_noise"], "rot_meas_noise", n)
        f._vel0 = _positive(state["rot_init_vel_std"], "rot_init_vel_std", n)
        f._R = _mat(state, "R", (n, 3, 3), "PoseFilter")
        f._w = _mat(state, "omega", (n, 3), "PoseFilter")
        f._P = _mat(state, "P", (n, 6, 6), "PoseFilter")
        f._ref = _mat(state, "ref", (n, 3), "PoseFilter")
        f.translation = TranslationKF.from_state_dict(state["translation"])
        f._make_views()
        return f


def _pose_input(x, name: str) -> np.ndarray:
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name} must be (72,) or (24, 3) axis-angle numbers") from e
    if a.shape not in ((72,), (NUM_JOINTS, 3)):
        raise InputError(f"{name} must have shape (72,) or (24, 3) (SMPL axis-angle pose), "
                         f"got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} must be finite, got non-finite values")
    return a.reshape(NUM_JOINTS, 3)

"""A procedural walk cycle (``builtin:walk``): SMPL poses and translations, no files needed.

Joint angles follow the shape of the normative sagittal-plane gait curves (Winter,
*Biomechanics and Motor Control of Human Movement*; Perry, *Gait Analysis*): hip
flexion +30 deg at heel strike to -10 deg at 50 % of the cycle; knee flexion with the
loading-response bump (~18 deg) and the swing peak (~62 deg at 72 %); ankle
plantar-flexion after heel strike and at toe-off (-18 deg at 62 %), dorsiflexion in
late stance (+10 deg); toe extension at push-off; pelvis rotation +-4 deg and obliquity
+-4 deg; thorax counter-rotation; arm swing opposite to the legs (shoulder -20..+10 deg)
with elbow flexion 18..32 deg. Each curve is a periodic cubic spline through key
points, so every angle is smooth and exactly periodic. Phase 0 is the left heel strike;
the right side lags by half a cycle.

The translation is not prescribed but follows from the legs: within a cycle the
lowest foot vertex is kept on the ground plane ``y = 0`` (so the pelvis bobs as the
legs dictate) and the stance foot's contact vertex does not slide (so the forward
speed is the one the stride allows). The cycle period is then chosen so the mean
speed is ``speed`` (default 1.3 m/s).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.interpolate import CubicSpline

from flowmocap.body.skeleton import JOINT_INDEX
from flowmocap.errors import InputError
from flowmocap.io.smpl_motion import SmplMotion, betas_tensor

__all__ = ["GAIT_KEYPOINTS", "gait_angles", "walk_poses", "builtin_walk", "BUILTIN_MOTIONS"]

BUILTIN_MOTIONS = ("walk",)

#: Key points ``(phase in [0, 1], degrees)`` of the left side's sagittal curves.
#: Signs: flexion positive (hip forward, knee bent, ankle/toes up = dorsiflexion).
GAIT_KEYPOINTS: dict[str, tuple[tuple[float, float], ...]] = {
    "hip_flexion": ((0.0, 30.0), (0.15, 22.0), (0.3, 6.0), (0.5, -10.0), (0.6, -4.0),
                    (0.75, 20.0), (0.87, 32.0)),
    "knee_flexion": ((0.0, 4.0), (0.15, 18.0), (0.38, 5.0), (0.5, 12.0), (0.6, 38.0),
                     (0.72, 62.0), (0.85, 35.0), (0.96, 3.0)),
    "ankle_dorsiflexion": ((0.0, 0.0), (0.07, -6.0), (0.3, 5.0), (0.45, 10.0), (0.62, -18.0),
                           (0.75, -2.0), (0.9, 2.0)),
    "toe_extension": ((0.0, 0.0), (0.4, 2.0), (0.55, 22.0), (0.63, 10.0), (0.72, 0.0)),
    "shoulder_flexion": ((0.0, -20.0), (0.25, -5.0), (0.5, 10.0), (0.75, -5.0)),
    "elbow_flexion": ((0.0, 18.0), (0.25, 25.0), (0.5, 32.0), (0.75, 25.0)),
}

# Whole-body values (degrees): amplitude of the pelvis's yaw and obliquity, the trunk's
# counter-rotation and lean, and the arms' hang from the T-pose (abduction 10 deg).
_PELVIS_YAW = 4.0
_PELVIS_OBLIQUITY = 4.0
_THORAX_COUNTER = 6.0
_TRUNK_LEAN = 3.0
_ARM_DOWN = 80.0

_SPLINES = {
    name: CubicSpline(
        np.array([p for p, _ in pts] + [pts[0][0] + 1.0]),
        np.array([v for _, v in pts] + [pts[0][1]]),
        bc_type="periodic",
    )
    for name, pts in GAIT_KEYPOINTS.items()
}


def gait_angles(phase: np.ndarray) -> dict[str, np.ndarray]:
    """The left side's gait curves at the given phases.

    Args:
        phase: ``(N,)`` gait phase in cycles (any real; 0 = left heel strike).

    Returns:
        ``{curve name: (N,) degrees}`` for the names in :data:`GAIT_KEYPOINTS`.
    """
    ph = np.mod(np.asarray(phase, dtype=np.float64), 1.0)
    return {name: s(ph) for name, s in _SPLINES.items()}


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    return np.stack([i, o, o, o, c, -s, o, s, c], -1).reshape(a.shape + (3, 3))


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    return np.stack([c, o, s, o, i, o, -s, o, c], -1).reshape(a.shape + (3, 3))


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    return np.stack([c, -s, o, s, c, o, o, o, i], -1).reshape(a.shape + (3, 3))


def walk_poses(phase: np.ndarray) -> np.ndarray:
    """SMPL poses of the walk cycle at the given phases (facing +z, no translation).

    Args:
        phase: ``(N,)`` gait phase in cycles (0 = left heel strike, period 1).

    Returns:
        ``(N, 72)`` float64 axis-angle poses in radians.
    """
    from flowmocap.geometry import matrix_to_axis_angle

    phase = np.asarray(phase, dtype=np.float64).reshape(-1)
    N = phase.shape[0]
    d = math.pi / 180.0
    L = gait_angles(phase)
    R = gait_angles(phase + 0.5)
    rot = np.broadcast_to(np.eye(3), (N, 24, 3, 3)).copy()
    J = JOINT_INDEX
    w = 2 * math.pi * phase
    # Pelvis: yaw brings the forward leg's hip forward; obliquity lifts the stance side.
    rot[:, J["pelvis"]] = (
        _ry(-_PELVIS_YAW * d * np.cos(w)) @ _rz(_PELVIS_OBLIQUITY * d * np.sin(w + 0.2 * math.pi))
    )
    lean = np.full(N, _TRUNK_LEAN * d / 2)
    rot[:, J["spine1"]] = _rx(lean) @ _rz(-0.5 * _PELVIS_OBLIQUITY * d * np.sin(w + 0.2 * math.pi))
    rot[:, J["spine2"]] = _rx(lean) @ _ry(0.5 * _THORAX_COUNTER * d * np.cos(w))
    rot[:, J["spine3"]] = _ry(0.5 * _THORAX_COUNTER * d * np.cos(w))
    rot[:, J["neck"]] = _rx(-lean) @ _ry(-0.5 * _THORAX_COUNTER * d * np.cos(w))
    rot[:, J["head"]] = _rx(-lean)
    for side, A, sgn in (("left", L, 1.0), ("right", R, -1.0)):
        rot[:, J[f"{side}_hip"]] = _rx(-A["hip_flexion"] * d)
        rot[:, J[f"{side}_knee"]] = _rx(A["knee_flexion"] * d)
        rot[:, J[f"{side}_ankle"]] = _rx(-A["ankle_dorsiflexion"] * d)
        rot[:, J[f"{side}_foot"]] = _rx(-A["toe_extension"] * d)
        # Arms: lower from the T-pose, then swing forward (flexion) about the body's x axis.
        rot[:, J[f"{side}_shoulder"]] = (
            _rx(-A["shoulder_flexion"] * d) @ _rz(np.full(N, -sgn * _ARM_DOWN * d))
        )
        rot[:, J[f"{side}_elbow"]] = _ry(-sgn * A["elbow_flexion"] * d)
    return matrix_to_axis_angle(torch.as_tensor(rot)).numpy().reshape(N, 72)


def _foot_vertices(model) -> tuple[np.ndarray, np.ndarray]:
    w = model.weights.detach().cpu().numpy()
    main = w.argmax(1)
    J = JOINT_INDEX
    left = np.flatnonzero(np.isin(main, [J["left_ankle"], J["left_foot"]]))
    right = np.flatnonzero(np.isin(main, [J["right_ankle"], J["right_foot"]]))
    if left.size == 0 or right.size == 0:
        raise InputError("the body model has no vertices skinned mainly to the ankles/feet")
    return left, right


def _cycle_path(model, betas_t, samples: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Translation over one cycle at ``samples`` phases: (samples+1, 3) and stride (m)."""
    phase = np.arange(samples) / samples
    poses = walk_poses(phase)
    dt = model.v_template.dtype
    with torch.no_grad():
        verts = model(betas=betas_t, pose=torch.as_tensor(poses, dtype=dt)).vertices.double().numpy()
    left, right = _foot_vertices(model)
    lowest_l = left[verts[:, left, 1].argmin(1)]
    lowest_r = right[verts[:, right, 1].argmin(1)]
    k = np.arange(samples)
    hl = verts[k, lowest_l, 1]
    hr = verts[k, lowest_r, 1]
    contact = np.where(hl <= hr, lowest_l, lowest_r)  # stance foot's lowest vertex
    ty = -np.minimum(hl, hr)
    # Horizontal: pin the contact vertex of sample k between samples k-1 and k.
    prev = np.roll(k, 1)
    dxz = -(verts[k, contact][:, [0, 2]] - verts[prev, contact][:, [0, 2]])  # (samples, 2)
    dxz[:, 0] -= dxz[:, 0].mean()  # no sideways drift from a slightly asymmetric body
    stride = float(dxz[:, 1].sum())
    xz = np.concatenate([np.zeros((1, 2)), np.cumsum(dxz[1:], axis=0)])  # position at sample k
    trans = np.zeros((samples + 1, 3))
    trans[:samples, [0, 2]] = xz
    trans[:samples, 1] = ty
    trans[samples] = trans[0] + np.array([dxz[:, 0].sum(), 0.0, stride])
    return poses, trans, stride


def builtin_walk(
    model,
    betas=None,
    fps: float = 30.0,
    frames: int | None = None,
    duration: float = 4.0,
    speed: float = 1.3,
    facing: float = 0.0,
    start_phase: float = 0.0,
    samples_per_cycle: int = 240,
) -> SmplMotion:
    """The built-in walk for a body: smooth, periodic, feet on the ground plane.

    Args:
        model: :class:`~flowmocap.body.BodyModel` the motion is made for (its legs set
            the stride).
        betas: ``(<=num_betas,)`` body shape (default: mean shape).
        fps: frame rate in Hz.
        frames: number of frames (default: ``duration * fps`` rounded, at least 2).
        duration: seconds, used when ``frames`` is None.
        speed: mean forward speed in m/s; the cycle period is ``stride / speed``.
        facing: walking direction, radians from +z towards +x (0 = +z).
        start_phase: gait phase of frame 0 in cycles (0 = left heel strike).
        samples_per_cycle: phases at which the ground contact is solved.

    Returns:
        :class:`~flowmocap.io.SmplMotion`: ``poses (T, 72)`` radians, ``trans (T, 3)``
        metres (frame-0 pelvis above x = z = 0, lowest foot vertex on y = 0 in every
        frame); ``info`` holds the period (s), stride (m) and cadence (steps/min).
    """
    for name, v in (("fps", fps), ("speed", speed), ("duration", duration)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise InputError(f"{name} must be a positive number, got {v!r}")
    T = int(frames) if frames is not None else max(2, int(round(duration * fps)))
    if T < 1:
        raise InputError(f"frames must be at least 1, got {frames}")
    dt = model.v_template.dtype
    betas_t = betas_tensor(model, betas)
    b = betas_t[0].double().numpy()

    _, cycle_trans, stride = _cycle_path(model, betas_t, samples_per_cycle)
    if stride <= 0:
        raise InputError("the walk cycle makes no forward progress with this body model")
    period = stride / speed
    phase = start_phase + np.arange(T) / (fps * period)
    poses = walk_poses(phase)

    # Translation: periodic part interpolated on the cycle grid, plus whole strides.
    grid = np.arange(samples_per_cycle + 1) / samples_per_cycle
    whole = np.floor(phase)
    frac = phase - whole
    per_cycle = cycle_trans[-1] - cycle_trans[0]
    trans = np.stack([np.interp(frac, grid, cycle_trans[:, k]) for k in range(3)], -1)
    trans += whole[:, None] * per_cycle[None]
    with torch.no_grad():
        pelvis0 = model(betas=betas_t, pose=torch.as_tensor(poses[:1], dtype=dt)).joints[0, 0].double().numpy()
    trans[:, [0, 2]] -= trans[0, [0, 2]] + pelvis0[[0, 2]]
    if facing:
        c, s = math.cos(facing), math.sin(facing)
        Ry = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
        from flowmocap.geometry import axis_angle_to_matrix, matrix_to_axis_angle

        root = axis_angle_to_matrix(torch.as_tensor(poses[:, :3])).numpy()
        poses[:, :3] = matrix_to_axis_angle(torch.as_tensor(Ry @ root)).numpy()
        # The pelvis sits at rest-pelvis + trans; turn its path about the vertical
        # through the frame-0 pelvis (the origin).
        trans = (trans + pelvis0) @ Ry.T - pelvis0
    info = {"period_s": period, "stride_m": stride, "speed_mps": speed,
            "cadence_steps_per_min": 120.0 / period, "start_phase": start_phase,
            "facing": facing}
    return SmplMotion(poses=poses, trans=trans, betas=b, gender=model.gender, fps=float(fps),
                      source="builtin:walk", info=info)

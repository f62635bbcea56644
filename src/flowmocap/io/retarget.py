"""Retargeting a :class:`~flowmocap.io.mocap.MocapClip` onto the 24-joint SMPL tree.

Method (per frame, walking down the SMPL tree):

1. Each SMPL joint ``j`` is paired with a mocap joint ``m(j)`` by a joint-name map (CMU
   ASF, CMU BVH, cgspeed's DAZ-friendly CMU BVH, Mixamo/generic and Biovision-style rigs
   are known; see :data:`RIGS`).
2. Its *primary* direction is a bone: SMPL ``j -> c`` (``c`` the next mapped joint down
   the chain) against the mocap's ``m(j) -> m(c)``, taken from the mocap's global
   joint positions, so bone directions match exactly even where the mocap has extra
   joints in between. For the pelvis the primary direction is right hip -> left hip.
   A joint with no mapped child (head, feet, hands) continues its incoming bone: the
   mocap's rest bone ``m(a) -> m(j)`` turned by ``m(j)``'s own global rotation.
3. Its *secondary* direction gives the twist about the bone: one of the body's rest
   axes (forward, else up, else left: the first one at more than ~37 deg from the bone
   in both rests) carried
   along by the mocap joint's global rotation. Both rest poses are thus related by the
   body axes, not assumed equal: a per-bone rest correction, whatever the rig's rest
   (assumed only: the rest limbs are not twisted about their own axes, as in T- and
   A-poses).
4. The SMPL global rotation maps the orthonormal frame of (primary, secondary) in the
   SMPL rest pose onto the same frame of the mocap at that frame; local rotations are
   ``G_parent^T G_j``, stored as axis-angle.
5. Exception, the feet (``REST_RELATIVE``: ankles and toes): they copy the mocap joint's
   rotation relative to its rest pose (turned into SMPL's body axes) instead of
   matching the ankle -> toe direction, because that vector's angle depends on where a
   skeleton puts its ankle and toe joints (CMU: 12 deg below the horizontal, SMPL's
   bodies: about 20 deg) while both rest poses stand on a flat foot. Matching the
   direction would tilt the sole by the difference.

The root's path is the mocap's hip midpoint scaled by ``SMPL leg length / mocap leg
length`` (hip-knee-ankle, rest pose, mean of both legs). The clip is turned about the
vertical so that the body faces ``facing`` (the pelvis's mean yaw over the first second,
so the pelvis's sway within a gait cycle does not tilt the path) and moved so that the
frame-0 pelvis is above the origin. Ground: one constant vertical shift for the whole
clip puts the lowest body vertex over all frames on ``y = 0`` (the vertical motion stays
the mocap's, jumps included; every frame's lowest vertex is then at ``y >= 0``, and
where the two skeletons' proportions differ -- CMU subject 35's right leg is 1.5 cm
longer than his left, SMPL's legs are equal -- a foot may hover 1-3 cm in its stance).
``ground="frame"`` instead puts the lowest vertex on ``y = 0`` in every frame (for
walks; it removes flight phases).
"""

from __future__ import annotations

import math
import re

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from flowmocap.body.skeleton import JOINT_INDEX, JOINT_NAMES, PARENTS, children
from flowmocap.errors import DataError, InputError
from flowmocap.geometry import matrix_to_axis_angle
from flowmocap.io.mocap import MocapClip, resample
from flowmocap.io.smpl_motion import SmplMotion, betas_tensor

__all__ = ["RIGS", "REST_RELATIVE", "retarget", "resolve_joint_map", "normalize_joint_name", "body_yaw"]

#: SMPL joints that copy the mocap's rotation relative to its rest pose (step 5 above).
REST_RELATIVE: tuple[str, ...] = ("left_ankle", "right_ankle", "left_foot", "right_foot")


def _sides(table: dict[str, tuple[str, ...]], left: str, right: str) -> dict[str, tuple[str, ...]]:
    """Add the right-side entries by replacing the ``left`` prefix of names with ``right``."""
    out = dict(table)
    for k, names in table.items():
        if k.startswith("left_"):
            out["right_" + k[5:]] = tuple(
                right + n[len(left):] if n.startswith(left) else n for n in names
            )
    return out


#: Joint-name maps: rig -> SMPL joint -> candidate mocap joint names (normalised with
#: :func:`normalize_joint_name`; the first present one is used). Tried in this order.
RIGS: dict[str, dict[str, tuple[str, ...]]] = {
    # CMU's Acclaim skeletons (mocap.cs.cmu.edu). lwrist starts at the end of the radius.
    "cmu_asf": _sides({
        "pelvis": ("root",), "spine1": ("lowerback",), "spine2": ("upperback",),
        "spine3": ("thorax",), "neck": ("lowerneck",), "head": ("head",),
        "left_hip": ("lfemur",), "left_knee": ("ltibia",), "left_ankle": ("lfoot",),
        "left_foot": ("ltoes",), "left_collar": ("lclavicle",), "left_shoulder": ("lhumerus",),
        "left_elbow": ("lradius",), "left_wrist": ("lwrist",), "left_hand": ("lhand",),
    }, "l", "r"),
    # The BVH conversions of the CMU database (Hips, LHipJoint, LowerBack, Spine, ...).
    "cmu_bvh": _sides({
        "pelvis": ("hips",), "spine1": ("lowerback",), "spine2": ("spine",),
        "spine3": ("spine1",), "neck": ("neck",), "head": ("head",),
        "left_hip": ("leftupleg",), "left_knee": ("leftleg",), "left_ankle": ("leftfoot",),
        "left_foot": ("lefttoebase",), "left_collar": ("leftshoulder",),
        "left_shoulder": ("leftarm",), "left_elbow": ("leftforearm",),
        "left_wrist": ("lefthand",), "left_hand": ("lefthandindex1", "leftfingerbase"),
    }, "left", "right"),
    # Biovision-style rigs where LeftCollar is the clavicle and LeftShoulder the upper arm.
    "biovision": _sides({
        "pelvis": ("hips", "hip", "pelvis"), "spine1": ("spine", "abdomen", "lowerback"),
        "spine2": ("spine1", "chest"), "spine3": ("spine2", "chest2", "upperchest"),
        "neck": ("neck",), "head": ("head",),
        "left_hip": ("lefthip", "leftupleg", "leftthigh"),
        "left_knee": ("leftknee", "leftlowleg", "leftleg", "leftshin"),
        "left_ankle": ("leftankle", "leftfoot"), "left_foot": ("lefttoe", "lefttoebase", "lefttoes"),
        "left_collar": ("leftcollar",), "left_shoulder": ("leftshoulder", "leftuparm", "leftupperarm"),
        "left_elbow": ("leftelbow", "leftlowarm", "leftforearm", "leftlowerarm"),
        "left_wrist": ("leftwrist", "lefthand"), "left_hand": ("lefthandmiddle1", "lefthandindex1"),
    }, "left", "right"),
    # Mixamo (mixamorig:Hips ...) and generic Hips/Spine/LeftUpLeg rigs.
    "mixamo": _sides({
        "pelvis": ("hips", "pelvis", "hip"), "spine1": ("spine", "spine0", "abdomen"),
        "spine2": ("spine1", "chest"), "spine3": ("spine2", "upperchest", "chest2"),
        "neck": ("neck", "neck1"), "head": ("head",),
        "left_hip": ("leftupleg", "leftthigh", "leftupperleg", "lefthip"),
        "left_knee": ("leftleg", "leftlowerleg", "leftshin", "leftknee", "leftlowleg"),
        "left_ankle": ("leftfoot", "leftankle"),
        "left_foot": ("lefttoebase", "lefttoe", "lefttoes"),
        "left_collar": ("leftshoulder", "leftclavicle", "leftcollar"),
        "left_shoulder": ("leftarm", "leftupperarm", "leftuparm"),
        "left_elbow": ("leftforearm", "leftlowerarm", "leftlowarm", "leftelbow"),
        "left_wrist": ("lefthand", "leftwrist"),
        "left_hand": ("lefthandmiddle1", "lefthandindex1"),
    }, "left", "right"),
    # cgspeed's "DAZ-friendly" BVH conversion of the CMU database (hip, abdomen, chest,
    # lThigh, lShldr, ...; no toe joint). Its two spine joints sit where the CMU BVH's
    # LowerBack and Spine do (35 % and 60 % of the way from the hips up to the collars),
    # so they drive spine1 and spine2 as in "cmu_bvh"; spine3 and the toes follow their
    # parents (identity local rotations).
    "daz": _sides({
        "pelvis": ("hip",), "spine1": ("abdomen",), "spine2": ("chest",),
        "neck": ("neck",), "head": ("head",),
        "left_hip": ("lthigh",), "left_knee": ("lshin",), "left_ankle": ("lfoot",),
        "left_collar": ("lcollar",), "left_shoulder": ("lshldr",),
        "left_elbow": ("lforearm",), "left_wrist": ("lhand",),
        "left_hand": ("lmid1", "lindex1"),
    }, "l", "r"),
}

# Joints a rig must provide (plus one spine joint and the neck or the head).
_REQUIRED = (
    "pelvis", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)
# Names a rig's mocap file must contain for that rig to be chosen (beyond _REQUIRED).
_RIG_MARKERS = {"cmu_asf": ("lfemur", "lowerback"), "cmu_bvh": ("lowerback",),
                "biovision": ("leftcollar",), "mixamo": (), "daz": ("abdomen", "lshldr")}


def normalize_joint_name(name: str) -> str:
    """Lower case, namespace (``mixamorig:``) and separators removed: ``"mixamorig:Left_Arm"
    -> "leftarm"``."""
    n = name.split(":")[-1].lower()
    n = re.sub(r"[\s_\-.]", "", n)
    if n.startswith("mixamorig"):
        n = n[len("mixamorig"):].lstrip("0123456789")
    return n


def resolve_joint_map(
    clip: MocapClip, joint_map: dict[str, str | None] | None = None
) -> tuple[str, dict[str, str]]:
    """Pair SMPL joints with the clip's joints.

    Args:
        clip: the mocap clip.
        joint_map: optional explicit map ``{smpl_joint_name: mocap_joint_name}``; SMPL
            joints left out (or mapped to None) follow their parent.

    Returns:
        ``(rig, mapping)``: the rig's name (``"custom"`` for an explicit map) and
        ``{smpl_joint_name: mocap_joint_name}`` (exact names from the clip).

    Raises:
        DataError: no known rig fits; the message lists the joint names found.
        InputError: an explicit map names unknown joints.
    """
    names = [n for n, e in zip(clip.names, clip.end_site) if not e]
    by_norm: dict[str, str] = {}
    for n in names:
        by_norm.setdefault(normalize_joint_name(n), n)
    if joint_map is not None:
        out = {}
        for smpl_name, mocap_name in joint_map.items():
            if smpl_name not in JOINT_INDEX:
                raise InputError(f"{smpl_name!r} is not an SMPL joint; SMPL joints: {', '.join(JOINT_NAMES)}")
            if mocap_name is None:
                continue
            found = mocap_name if mocap_name in names else by_norm.get(normalize_joint_name(mocap_name))
            if found is None:
                raise InputError(
                    f"joint_map maps {smpl_name} to {mocap_name!r}, which is not in {clip.source}; "
                    f"joints found: {', '.join(names)}"
                )
            out[smpl_name] = found
        _check_required(out, "custom", clip, names)
        return "custom", out
    for rig, table in RIGS.items():
        if not all(m in by_norm for m in _RIG_MARKERS[rig]):
            continue
        out = {}
        for smpl_name, cands in table.items():
            for c in cands:
                if c in by_norm:
                    out[smpl_name] = by_norm[c]
                    break
        if _missing(out):
            continue
        return rig, out
    raise DataError(
        f"unknown skeleton in {clip.source}: none of the known rigs ({', '.join(RIGS)}) fits. "
        f"Joints found: {', '.join(names)}. Pass joint_map={{smpl_joint: mocap_joint}} "
        f"naming at least {', '.join(_REQUIRED)}, one of spine1/spine2/spine3 and neck or head."
    )


def _missing(mapping: dict[str, str]) -> list[str]:
    miss = [k for k in _REQUIRED if k not in mapping]
    if not any(k in mapping for k in ("spine1", "spine2", "spine3")):
        miss.append("spine1|spine2|spine3")
    if not any(k in mapping for k in ("neck", "head")):
        miss.append("neck|head")
    return miss


def _check_required(mapping, rig, clip, names) -> None:
    miss = _missing(mapping)
    if miss:
        raise InputError(
            f"joint_map for {clip.source} lacks {', '.join(miss)}; joints found: {', '.join(names)}"
        )


# ----------------------------------------------------------------------------- maths


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _frame(p: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(..., 3) primary and secondary -> (..., 3, 3) orthonormal frames, columns (p, s', p x s')."""
    e1 = _unit(p)
    e2 = s - (s * e1).sum(-1, keepdims=True) * e1
    e2 = _unit(e2)
    e3 = np.cross(e1, e2)
    return np.stack([e1, e2, e3], axis=-1)


def _horizontal_unit(v: np.ndarray, what: str, source: str) -> np.ndarray:
    h = np.array([v[0], 0.0, v[2]])
    n = np.linalg.norm(h)
    if n < 1e-6:
        raise DataError(f"{source}: the {what} is vertical in the rest pose; cannot find the body's facing")
    return h / n


def body_yaw(pelvis_rotation: np.ndarray) -> np.ndarray:
    """Heading of SMPL bodies: yaw of the pelvis's forward axis (+z in the rest pose).

    Args:
        pelvis_rotation: ``(..., 3, 3)`` global rotation of SMPL joint 0.

    Returns:
        ``(...)`` radians, ``atan2(f_x, f_z)`` of the forward vector ``f`` (0 = facing +z,
        pi/2 = facing +x).
    """
    f = pelvis_rotation[..., :, 2]
    return np.arctan2(f[..., 0], f[..., 2])


def _mapped_descendant(j: int, m: np.ndarray, rest: np.ndarray) -> int | None:
    """First joint down j's primary chain that is mapped and apart from m(j) in the rest pose."""
    c = j
    while True:
        kids = children(c)
        if not kids:
            return None
        c = kids[0]
        if m[c] >= 0 and np.linalg.norm(rest[m[c]] - rest[m[j]]) > 1e-4:
            return c


def _mapped_ancestor(j: int, m: np.ndarray, rest: np.ndarray) -> int | None:
    a = PARENTS[j]
    while a >= 0:
        if m[a] >= 0 and np.linalg.norm(rest[m[j]] - rest[m[a]]) > 1e-4:
            return a
        a = PARENTS[a]
    return None


def _global_rotations(clip: MocapClip, m: np.ndarray, js: np.ndarray,
                      rest_relative: tuple[int, ...] = ()) -> np.ndarray:
    """(T, 24, 3, 3) SMPL global rotations following the clip (see the module docstring)."""
    G_m = clip.global_rotations()
    P = clip.positions
    P0 = clip.rest_positions()
    T = clip.num_frames
    up = np.array([0.0, 1.0, 0.0])
    lh, rh = JOINT_INDEX["left_hip"], JOINT_INDEX["right_hip"]
    left_s = _horizontal_unit(js[lh] - js[rh], "hip axis of the body model", "body model")
    left_m = _horizontal_unit(P0[m[lh]] - P0[m[rh]], "hip axis", clip.source)
    axes_s = [np.cross(left_s, up), up, left_s]
    axes_m = [np.cross(left_m, up), up, left_m]
    # SMPL's body axes -> the mocap's body axes (rest poses, turned about the vertical)
    B = np.stack(axes_m, -1) @ np.stack(axes_s, -1).T

    G = np.zeros((T, 24, 3, 3))
    for j in range(24):
        par = PARENTS[j]
        if m[j] < 0:
            G[:, j] = G[:, par]
            continue
        if j in rest_relative:
            G[:, j] = G_m[:, m[j]] @ B
            continue
        if j == 0:
            p_s, p_m0 = js[lh] - js[rh], P0[m[lh]] - P0[m[rh]]
            p_t = P[:, m[lh]] - P[:, m[rh]]
        else:
            c = _mapped_descendant(j, m, P0)
            if c is not None:
                p_s, p_m0 = js[c] - js[j], P0[m[c]] - P0[m[j]]
                p_t = P[:, m[c]] - P[:, m[j]]
            else:
                a = _mapped_ancestor(j, m, P0)
                if a is None:
                    G[:, j] = G[:, par]
                    continue
                p_s, p_m0 = js[j] - js[a], P0[m[j]] - P0[m[a]]
                p_t = G_m[:, m[j]] @ p_m0
        ps_u, pm_u = _unit(p_s), _unit(p_m0)
        score = [max(abs(ps_u @ a_s), abs(pm_u @ a_m)) for a_s, a_m in zip(axes_s, axes_m)]
        ok = [i for i, v in enumerate(score) if v < 0.8]
        k = ok[0] if ok else int(np.argmin(score))
        s_t = G_m[:, m[j]] @ axes_m[k]
        G[:, j] = _frame(p_t, s_t) @ _frame(p_s, axes_s[k]).T
    return G


def _leg_length(points: np.ndarray, idx) -> float:
    (lh, lk, la), (rh, rk, ra) = idx
    return 0.5 * (
        np.linalg.norm(points[lh] - points[lk]) + np.linalg.norm(points[lk] - points[la])
        + np.linalg.norm(points[rh] - points[rk]) + np.linalg.norm(points[rk] - points[ra])
    )


def _run_body(model, betas: torch.Tensor, poses: np.ndarray, trans=None, chunk: int = 64,
              vertices: bool = True):
    """Joints (T, 24, 3) and per-frame lowest vertex height (T,) of the body, float64."""
    dt = model.v_template.dtype
    joints, low = [], []
    with torch.no_grad():
        for s in range(0, poses.shape[0], chunk):
            p = torch.as_tensor(poses[s:s + chunk], dtype=dt)
            tr = None if trans is None else torch.as_tensor(trans[s:s + chunk], dtype=dt)
            out = model(betas=betas, pose=p, trans=tr)
            joints.append(out.joints.double().numpy())
            if vertices:
                low.append(out.vertices[..., 1].min(dim=1).values.double().numpy())
    return np.concatenate(joints), (np.concatenate(low) if vertices else None)


def retarget(
    clip: MocapClip,
    model,
    betas=None,
    fps: float | None = None,
    joint_map: dict[str, str | None] | None = None,
    facing: float | None = 0.0,
    origin: str | None = "start",
    ground: str | None = "clip",
    rest_relative: tuple[str, ...] = REST_RELATIVE,
) -> SmplMotion:
    """Retarget a mocap clip onto a body model's SMPL tree.

    Args:
        clip: the mocap clip (metres, y up), e.g. from :func:`~flowmocap.io.read_mocap`.
        model: a :class:`~flowmocap.body.BodyModel` (default body or real SMPL).
        betas: ``(<=num_betas,)`` shape of the body to retarget to (default: mean shape).
        fps: resample the clip to this frame rate in Hz first (default: keep).
        joint_map: explicit ``{smpl_joint: mocap_joint}`` map (default: detect the rig).
        facing: heading of the body over the first second in radians (circular mean of
            the pelvis's yaw, see :func:`body_yaw`), measured from +z towards +x (0:
            facing +z like SMPL's rest pose; ``pi/2``: facing +x); None keeps the
            mocap's heading.
        origin: ``"start"`` puts the frame-0 pelvis above ``x = z = 0``; None keeps the
            mocap's (scaled) horizontal position.
        ground: ``"clip"`` shifts the clip vertically so the lowest vertex over all
            frames is at ``y = 0``; ``"frame"`` shifts every frame so its lowest vertex
            is at ``y = 0`` (walking: no hovering foot, but no flight phase either);
            None keeps the mocap's (scaled) heights.
        rest_relative: SMPL joints that copy the mocap joint's rotation relative to
            its rest pose instead of matching a bone direction (default: the feet).

    Returns:
        :class:`~flowmocap.io.SmplMotion` with ``poses (T, 72)`` radians, ``trans (T, 3)``
        metres; ``info`` holds the rig, joint map, scale, yaw turn and ground offset.

    Raises:
        DataError: unknown rig (lists the joints found) or a degenerate rest pose.
        InputError: bad arguments.
    """
    from flowmocap.body import BodyModel

    if not isinstance(model, BodyModel):
        raise InputError(f"model must be a BodyModel (flowmocap.body.load_body_model('default')); got "
                         f"{type(model).__name__}.")
    try:
        facing_ok = facing is None or math.isfinite(float(facing))
    except (TypeError, ValueError):
        facing_ok = False
    if not facing_ok:
        raise InputError(f"facing must be a finite heading in radians, or None; got {facing!r}.")
    if origin not in ("start", None):
        raise InputError(f"origin must be 'start' or None, got {origin!r}")
    if ground not in ("clip", "frame", None):
        raise InputError(f"ground must be 'clip', 'frame' or None, got {ground!r}")
    bad = [n for n in rest_relative if n not in JOINT_INDEX]
    if bad:
        raise InputError(f"rest_relative names unknown SMPL joints {bad}; SMPL joints: {', '.join(JOINT_NAMES)}")
    if fps is not None:
        clip = resample(clip, fps)
    rig, mapping = resolve_joint_map(clip, joint_map)
    m = np.full(24, -1)
    for smpl_name, mocap_name in mapping.items():
        m[JOINT_INDEX[smpl_name]] = clip.index(mocap_name)

    betas_t = betas_tensor(model, betas)
    b = betas_t[0].double().numpy()
    with torch.no_grad():
        js = model(betas=betas_t).rest_joints[0].double().numpy()

    G = _global_rotations(clip, m, js, tuple(JOINT_INDEX[n] for n in rest_relative))
    yaw_turn = 0.0
    if facing is not None:
        n = max(1, min(clip.num_frames, int(round(clip.fps))))
        yaw = body_yaw(G[:n, 0])
        yaw_turn = float(facing) - math.atan2(np.sin(yaw).mean(), np.cos(yaw).mean())
    Ry = Rotation.from_euler("y", yaw_turn).as_matrix()
    G = Ry @ G
    local = G.copy()
    parents = np.asarray(PARENTS)
    local[:, 1:] = np.swapaxes(G[:, parents[1:]], -1, -2) @ G[:, 1:]
    poses = matrix_to_axis_angle(torch.as_tensor(local)).numpy().reshape(-1, 72)

    leg_idx = [(JOINT_INDEX[f"{s}_hip"], JOINT_INDEX[f"{s}_knee"], JOINT_INDEX[f"{s}_ankle"])
               for s in ("left", "right")]
    leg_s = _leg_length(js, leg_idx)
    P0 = clip.rest_positions()
    leg_m = _leg_length(P0, [tuple(m[i] for i in leg) for leg in leg_idx])
    if leg_m < 1e-6:
        raise DataError(f"{clip.source}: the mocap legs have zero length in the rest pose")
    scale = leg_s / leg_m
    lh, rh = leg_idx[0][0], leg_idx[1][0]
    mid_m = 0.5 * (clip.positions[:, m[lh]] + clip.positions[:, m[rh]])
    target = scale * mid_m @ Ry.T

    joints0, _ = _run_body(model, betas_t, poses, vertices=False)
    trans = target - 0.5 * (joints0[:, lh] + joints0[:, rh])
    if origin == "start":
        trans[:, [0, 2]] -= (trans[0] + joints0[0, 0])[[0, 2]]
    ground_offset = 0.0
    if ground is not None:
        _, low = _run_body(model, betas_t, poses, trans)
        if ground == "clip":
            ground_offset = -float(low.min())
            trans[:, 1] += ground_offset
        else:
            ground_offset = -float(low.mean())
            trans[:, 1] -= low

    info = {
        "rig": rig, "joint_map": mapping, "scale": scale, "yaw_turn": yaw_turn,
        "leg_length_body": leg_s, "leg_length_mocap": leg_m, "ground_offset": ground_offset,
        "mocap_fps": clip.info.get("resampled_from_fps", clip.fps), "facing": facing,
        "ground": ground, "rest_relative": list(rest_relative),
    }
    return SmplMotion(poses=poses, trans=trans, betas=b,
                      gender=model.gender, fps=clip.fps, source=clip.source, info=info)

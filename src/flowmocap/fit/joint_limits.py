"""Per-joint, per-axis joint angle limits for the SMPL tree (the paper's E_b, Sec. 3.4).

What the angles are
-------------------
A SMPL pose holds one axis-angle vector per joint, the rotation of the joint's frame
relative to its parent, in axes that are the body's rest axes (x to the body's left,
y up, z forward; the rest pose is a T-pose with the palms down). Raw axis-angle
components are only anatomical angles for small single-axis rotations, so the limits
are applied to a per-joint decomposition (:func:`joint_angles`):

* **Euler (Cardan) angles** for every joint except the shoulders, intrinsic, in an
  order that follows the joint coordinate systems of the ISB recommendations
  (Grood & Suntay 1983; Wu et al. 2002, 2005): first the joint's main
  flexion/extension axis, then the "floating" ab/adduction axis, last the axial
  rotation about the distal segment's long axis. The middle angle is the one with the
  smallest range (at most 45 degrees), so the chart's singularity (middle angle
  +-90 degrees) lies far outside the limits, and a pure hinge motion (knee, elbow) is
  exactly one angle. Orders (letters = SMPL rest axes):
  legs, spine, neck, head ``XZY``; elbows ``YZX`` (flexion about y in the T-pose,
  carrying angle, forearm rotation); collars, wrists and hands ``ZYX``.
* **The axis-angle components themselves** for the shoulders. The upper arm points in
  almost every direction of a sphere, so every Euler chart has its singularity at a
  common pose (arm straight forward or straight down); the rotation vector measured
  from the T-pose is singular only at 180 degrees (arm through the chest), which is
  never reached. Its components are the anatomical angles for single-plane motions
  from the T-pose and mix for combined ones, so the shoulder box is wide: it only
  rules out the clearly impossible (arm far behind the back, twisted past 90 degrees).

The root (pelvis = global orientation) has no limits.

Sign conventions (checked on the default body, ``load_body_model("default")``, by
rotating one joint by +45 degrees about one axis and watching its child joint; the
right side mirrors the left: same x, y and z negated)
------------------------------------------------------------------------------------
* knee ``+x``: the ankle moves back and up -- flexion. Hip ``+x``: the knee moves back
  -- extension (flexion is ``-x``). Ankle ``+x``: the toes go down -- plantar flexion.
  Toes ``-x``: extension. Spine/neck ``+x``: the head goes forward and down -- flexion.
* left hip ``+z``: the knee moves out (+x) -- abduction; left hip ``+y``: the front of
  the thigh turns out -- external rotation.
* left ankle ``+z``: the sole turns in -- inversion; left ankle ``+y``: toes out.
* left shoulder ``+z``: the arm rises (abduction past the T-pose; ``-90`` deg hangs it
  at the side); ``-y``: the arm swings forward (horizontal flexion); ``+x``: internal
  rotation (a forward-pointing forearm turns down).
* left elbow ``-y``: the forearm swings forward -- flexion; ``+y`` bends it backwards.
* left wrist ``+z``: the hand goes up (palm down) -- extension; ``+y``: towards the
  little finger -- ulnar deviation. Left collar ``+z``: the shoulder rises.

The table (degrees, left side; ``lo..hi`` per SMPL axis, signs as above)
------------------------------------------------------------------------
==============  ==========  ===========  ==========  ==========================================
joint            x           y            z           source
==============  ==========  ===========  ==========  ==========================================
hip              -120..30    -45..45      -30..45     AAOS: flexion 120, extension 30, abduction
                                                      45, adduction 30, internal/external
                                                      rotation 45; Roaas & Andersson: flexion 120
knee             -5..145     -10..10      -10..10     flexion 135 (AAOS), 143 (Roaas &
                                                      Andersson), ~140 (Soucie); a few degrees of
                                                      hyperextension are normal (Soucie); tibial
                                                      (y) rotation needs a flexed knee (~30-40
                                                      passively at 90 deg, ~0 extended: the
                                                      screw-home lock; Kapandji), so the soft box
                                                      keeps 10 (35 let the tracker twist shins
                                                      25-35 deg to explain flow errors);
                                                      varus/valgus laxity
ankle            -20..50     -30..30      -25..35     AAOS: dorsiflexion 20, plantar flexion 50,
                                                      inversion 35, eversion 15; y, z widened by
                                                      10 (SMPL's ankle also takes the hindfoot
                                                      and tibial rotation; a retargeted CMU walk,
                                                      35_01, reaches 28 and 23)
toes (foot)      -70..45     -20..20      -20..20     AAOS, first MTP: extension 70, flexion 45
spine1/2/3       -15..40     -25..25      -20..20     AAOS thoracolumbar: flexion 80, extension
                                                      25, lateral bending 35, rotation 45; half
                                                      of each per joint
neck, head       -35..35     -45..45      -35..35     AAOS cervical: flexion 45, extension 45,
                                                      lateral bending 45, rotation 60; 3/4 of
                                                      each per joint
collar           -30..30     -25..25      -10..35     sternoclavicular: elevation ~35,
                                                      depression ~10, protraction/retraction
                                                      ~25, axial rotation ~30 (Kapandji)
shoulder (a-a)   -90..70     -135..80     -110..95    AAOS: abduction 180 (+90 from the T-pose),
                                                      internal rotation 70, external 90,
                                                      horizontal flexion 135; extension 60 with
                                                      the arm down reads as y ~ +80 in this
                                                      chart; arm at the side z = -90, past it 20
elbow            -90..90     -150..5      -20..20     AAOS: flexion 150, extension 0 (+5 for
                                                      normal hyperextension, Soucie); pronation
                                                      and supination 80 each; carrying angle
wrist            -60..60     -20..30      -80..70     AAOS: flexion 80, extension 70, radial
                                                      deviation 20, ulnar 30
hand (MCP)       -20..20     -30..30      -90..45     AAOS, MCP: flexion 90, hyperextension 45
==============  ==========  ===========  ==========  ==========================================

Where SMPL splits one anatomical range over k joints (three spine joints, neck + head)
each joint gets ``1.5 / k`` of the total, so a pose that bends mostly at one of them is
not penalised. Forearm rotation (160 deg in all) is shared by the elbow and wrist ``x``
and the T-pose's palm-down zero is not the anatomical mid-position, hence the wide
symmetric ranges. Axes for which the literature gives no range (knee ab/adduction,
toe and hand side motion) get small ones. The limits are soft (the penalty is
``exp(excess) - 1``, about 0.19 at 10 degrees past a limit), so they are placed at the
normal active range rather than beyond it.

Sources
-------
* AAOS: American Academy of Orthopaedic Surgeons, *Joint Motion: Method of Measuring
  and Recording* (1965); Greene & Heckman (eds.), *The Clinical Measurement of Joint
  Motion*, AAOS (1994).
* Roaas A., Andersson G.B.J., "Normal range of motion of the hip, knee and ankle joints
  in male subjects, 30-40 years of age", Acta Orthop. Scand. 53:205-208 (1982).
* Soucie J.M. et al., "Range of motion measurements: reference values and a database
  for comparison studies", Haemophilia 17:500-507 (2011).
* Kapandji I.A., *The Physiology of the Joints*, vol. 1 (upper limb).
* Grood E.S., Suntay W.J., J. Biomech. Eng. 105:136-144 (1983); Wu G. et al., J.
  Biomech. 35:543-548 (2002) and 38:981-992 (2005) (ISB joint coordinate systems).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from flowmocap.body.skeleton import JOINT_INDEX, JOINT_NAMES, NUM_JOINTS
from flowmocap.errors import InputError
from flowmocap.geometry.rotations import axis_angle_to_matrix, matrix_to_euler

__all__ = ["JointLimits", "default_joint_limits", "joint_angles", "JOINT_CHARTS", "LIMITS_DEG"]

#: Per joint: the decomposition used for the limits -- an intrinsic Euler order
#: (upper case, see :func:`flowmocap.geometry.euler_to_matrix`), ``"axis_angle"`` (the
#: raw components) or ``None`` (no limits: the root).
JOINT_CHARTS: dict[str, str | None] = {"pelvis": None}
for _side in ("left", "right"):
    JOINT_CHARTS.update({
        f"{_side}_hip": "XZY", f"{_side}_knee": "XZY", f"{_side}_ankle": "XZY",
        f"{_side}_foot": "XZY", f"{_side}_collar": "ZYX", f"{_side}_shoulder": "axis_angle",
        f"{_side}_elbow": "YZX", f"{_side}_wrist": "ZYX", f"{_side}_hand": "ZYX",
    })
for _name in ("spine1", "spine2", "spine3", "neck", "head"):
    JOINT_CHARTS[_name] = "XZY"

_LEFT_DEG: dict[str, tuple[tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    # joint: ((x lo, x hi), (y lo, y hi), (z lo, z hi)) in degrees, body's left side
    "hip": ((-120.0, 30.0), (-45.0, 45.0), (-30.0, 45.0)),
    "knee": ((-5.0, 145.0), (-10.0, 10.0), (-10.0, 10.0)),
    "ankle": ((-20.0, 50.0), (-30.0, 30.0), (-25.0, 35.0)),
    "foot": ((-70.0, 45.0), (-20.0, 20.0), (-20.0, 20.0)),
    "collar": ((-30.0, 30.0), (-25.0, 25.0), (-10.0, 35.0)),
    "shoulder": ((-90.0, 70.0), (-135.0, 80.0), (-110.0, 95.0)),
    "elbow": ((-90.0, 90.0), (-150.0, 5.0), (-20.0, 20.0)),
    "wrist": ((-60.0, 60.0), (-20.0, 30.0), (-80.0, 70.0)),
    "hand": ((-20.0, 20.0), (-30.0, 30.0), (-90.0, 45.0)),
}
_CENTRAL_DEG = {
    "spine1": ((-15.0, 40.0), (-25.0, 25.0), (-20.0, 20.0)),
    "spine2": ((-15.0, 40.0), (-25.0, 25.0), (-20.0, 20.0)),
    "spine3": ((-15.0, 40.0), (-25.0, 25.0), (-20.0, 20.0)),
    "neck": ((-35.0, 35.0), (-45.0, 45.0), (-35.0, 35.0)),
    "head": ((-35.0, 35.0), (-45.0, 45.0), (-35.0, 35.0)),
}


def _mirror(limits):
    (xl, xh), (yl, yh), (zl, zh) = limits
    return ((xl, xh), (-yh, -yl), (-zh, -zl))


#: ``{joint name: ((x lo, x hi), (y lo, y hi), (z lo, z hi))}`` in degrees, all 23
#: non-root joints, right side mirrored from the left (x kept, y and z negated).
LIMITS_DEG: dict[str, tuple[tuple[float, float], ...]] = dict(_CENTRAL_DEG)
for _part, _lim in _LEFT_DEG.items():
    LIMITS_DEG[f"left_{_part}"] = _lim
    LIMITS_DEG[f"right_{_part}"] = _mirror(_lim)


@dataclass(frozen=True)
class JointLimits:
    """Soft joint limits in the charts of :data:`JOINT_CHARTS`.

    Attributes:
        lower: ``(24, 3)`` lower limits in radians per joint and axis (x, y, z);
            ``-inf`` where there is none (the root).
        upper: ``(24, 3)`` upper limits in radians; ``+inf`` where there is none.
        charts: per joint, the decomposition (see :data:`JOINT_CHARTS`).
    """

    lower: np.ndarray
    upper: np.ndarray
    charts: tuple[str | None, ...]

    def __post_init__(self) -> None:
        lo = np.asarray(self.lower, dtype=np.float64)
        hi = np.asarray(self.upper, dtype=np.float64)
        if lo.shape != (NUM_JOINTS, 3) or hi.shape != (NUM_JOINTS, 3):
            raise InputError(f"joint limits must be (24, 3) arrays, got {lo.shape} and {hi.shape}")
        if np.isnan(lo).any() or np.isnan(hi).any() or (lo > hi).any():
            raise InputError("joint limits must be numbers with lower <= upper")
        if len(self.charts) != NUM_JOINTS:
            raise InputError(f"joint limits need one chart per joint (24), got {len(self.charts)}")
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)

    @property
    def limited(self) -> np.ndarray:
        """Indices of the joints with a chart (all but the root), ``(23,)``."""
        return np.array([j for j, c in enumerate(self.charts) if c is not None])


def default_joint_limits() -> JointLimits:
    """The table of the module docstring as :class:`JointLimits` (radians)."""
    lo = np.full((NUM_JOINTS, 3), -np.inf)
    hi = np.full((NUM_JOINTS, 3), np.inf)
    for name, lim in LIMITS_DEG.items():
        j = JOINT_INDEX[name]
        lo[j] = [math.radians(a) for a, _ in lim]
        hi[j] = [math.radians(b) for _, b in lim]
    return JointLimits(lo, hi, tuple(JOINT_CHARTS[n] for n in JOINT_NAMES))


def joint_angles(pose: torch.Tensor, charts: tuple[str | None, ...] | None = None) -> torch.Tensor:
    """Per-joint angles in the charts the limits are defined in (differentiable).

    Args:
        pose: ``(B, 72)`` or ``(B, 24, 3)`` SMPL axis-angle pose, radians.
        charts: per joint, an intrinsic Euler order, ``"axis_angle"`` or None
            (default: :data:`JOINT_CHARTS`).

    Returns:
        ``(B, 24, 3)`` angles in radians, column k the angle about SMPL axis k (x, y,
        z) whatever the Euler order; joints with chart None (the root) and
        ``"axis_angle"`` joints hold their raw axis-angle components.
    """
    if not isinstance(pose, torch.Tensor):
        raise InputError(f"pose must be a torch.Tensor of shape (B, 72), got {type(pose).__name__}")
    if pose.dim() == 2 and pose.shape[1] == 3 * NUM_JOINTS:
        pose = pose.reshape(pose.shape[0], NUM_JOINTS, 3)
    if pose.dim() != 3 or pose.shape[1:] != (NUM_JOINTS, 3):
        raise InputError(f"pose must have shape (B, 72) or (B, 24, 3), got {tuple(pose.shape)}")
    charts = tuple(JOINT_CHARTS[n] for n in JOINT_NAMES) if charts is None else tuple(charts)
    if len(charts) != NUM_JOINTS:
        raise InputError(f"charts must name one chart per joint (24), got {len(charts)}")
    groups: dict[str, list[int]] = {}
    for j, c in enumerate(charts):
        groups.setdefault("raw" if c in (None, "axis_angle") else c, []).append(j)
    if list(groups) == ["raw"]:
        return pose
    euler = [(order, joints) for order, joints in groups.items() if order != "raw"]
    needed = torch.tensor([j for _, joints in euler for j in joints], device=pose.device)
    rot = axis_angle_to_matrix(pose[:, needed])  # (B, n, 3, 3), one call for all joints
    parts, order_of_rows, start = [], [], 0
    for order, joints in euler:
        ang = matrix_to_euler(rot[:, start:start + len(joints)], order)  # angles in `order`
        parts.append(ang[..., [order.index(a) for a in "XYZ"]])
        order_of_rows += joints
        start += len(joints)
    if "raw" in groups:
        parts.append(pose[:, groups["raw"]])
        order_of_rows += groups["raw"]
    inverse = torch.empty(NUM_JOINTS, dtype=torch.long)
    inverse[torch.tensor(order_of_rows)] = torch.arange(NUM_JOINTS)
    return torch.cat(parts, dim=1)[:, inverse.to(pose.device)]

"""Motion-capture files: Acclaim ASF/AMC and BVH readers, a BVH writer, resampling.

Both readers return one :class:`MocapClip`: a tree of joints with rest offsets, per-frame
local rotations and translations, and the per-frame global joint positions from the
clip's own forward kinematics, in **metres with y up**.

Conventions shared by every clip:

- A joint sits where its bone *starts* (where it rotates), as in BVH. An ASF bone
  ``lfemur`` becomes the joint ``lfemur`` at the hip; a leaf bone's far end becomes an
  extra end-site joint named ``<bone>_end`` (BVH ``End Site`` blocks likewise).
- Rest pose: every local rotation is the identity, so each joint's rest frame is
  aligned with the world axes and its rest offset is expressed in world axes.
- Forward kinematics: ``G_j = G_parent @ L_j`` and
  ``p_j = p_parent + G_parent @ t_j`` where ``t_j`` is the joint's local translation
  (its rest offset, unless the file animates it); the root's ``t`` is its global
  position and ``G_root = L_root``. Matrices act on column vectors.

ASF/AMC (CMU's format): lengths in the ASF's own unit, converted with the ``:units``
``length`` value as ``metres = value / length * 0.0254`` (CMU: ``length 0.45``, one unit
= 5.64 cm; subject 35 then stands about 1.6 m tall). Angles in degrees unless
``angle rad``. A bone's ``axis a b c XYZ`` gives the rotation ``C`` of its local frame
(rotations applied about the fixed axes in the listed order, ``C = Rz Ry Rx`` for
``XYZ``); the AMC values of its ``dof`` list make ``M`` the same way (listed order,
fixed axes); its local rotation in our rest-aligned convention is ``L = C M C^-1``.
This is the composition of CMU's own viewer (``glRotatef`` z, y, x).

BVH: ``CHANNELS ... Zrotation Xrotation Yrotation`` compose as ``R = Rz @ Rx @ Ry``
(listed order, intrinsic), see :func:`flowmocap.geometry.euler_to_matrix`. Position
channels *replace* the joint's offset (Blender's reading). The file's length unit is
guessed from the rest skeleton's height unless ``scale`` is given.
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from flowmocap.atomic import atomic_write
from flowmocap.errors import DataError, InputError
from flowmocap.geometry import matrix_to_euler

__all__ = [
    "MocapClip",
    "forward_kinematics",
    "read_asf_amc",
    "read_bvh",
    "read_mocap",
    "find_asf",
    "write_bvh",
    "resample",
    "BVH_UNITS",
]

INCH = 0.0254

#: Candidate BVH length units (metres per file unit) tried by :func:`read_bvh` when no
#: ``scale`` is given, with the name reported in the clip's ``info``.
BVH_UNITS: dict[str, float] = {
    "m": 1.0,
    "cm": 0.01,
    "mm": 0.001,
    "inch": INCH,
    "cmu_asf_unit": INCH / 0.45,
}

# Rest-pose heights (metres) accepted when guessing a BVH file's unit.
_HEIGHT_RANGE = (1.1, 2.2)
# The same for flowmocap's own BVH export, in metres or centimetres: its rest joints span
# about 0.93 of the body's stature, which flowmocap.body.stature.STATURE_RANGE_M bounds.
_OWN_SPAN = (0.4, 2.5)


# ----------------------------------------------------------------------------- the clip


@dataclass
class MocapClip:
    """A motion-capture clip: a joint tree and its motion; T frames, J joints.

    Attributes:
        names: ``J`` joint names, parents before children (end sites included).
        parents: ``(J,)`` int64 parent indices, ``-1`` for the root.
        offsets: ``(J, 3)`` float64 rest offsets in metres from the parent joint, in the
            parent's rest frame (= world axes, y up); the root's is its rest position.
        rotations: ``(T, J, 3, 3)`` float64 local rotations (parent frame <- joint
            frame); identity for end sites.
        translations: ``(T, J, 3)`` float64 local translations in metres: the root's
            global position, the others their offset (or animated position channels).
        positions: ``(T, J, 3)`` float64 global joint positions in metres, y up,
            computed by :func:`forward_kinematics`.
        end_site: ``(J,)`` bool, True for end sites (no rotation of their own).
        fps: frames per second (Hz).
        source: path(s) the clip was read from.
        info: free-form facts about the reading (units, rig, channel orders).
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    positions: np.ndarray
    end_site: np.ndarray
    fps: float
    source: str
    info: dict = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        """Number of frames T."""
        return int(self.rotations.shape[0])

    @property
    def num_joints(self) -> int:
        """Number of joints J, end sites included."""
        return len(self.names)

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame."""
        return (self.num_frames - 1) / self.fps

    def index(self, name: str) -> int:
        """Index of the joint called ``name`` (exact match); InputError listing the names otherwise."""
        try:
            return self.names.index(name)
        except ValueError:
            raise InputError(
                f"no joint {name!r} in {self.source}; joints: {', '.join(self.names)}"
            ) from None

    def global_rotations(self) -> np.ndarray:
        """``(T, J, 3, 3)`` world-from-joint rotations ``G_j`` (float64)."""
        return forward_kinematics(self.parents, self.rotations, self.translations)[0]

    def rest_positions(self) -> np.ndarray:
        """``(J, 3)`` joint positions in metres in the rest pose, root at its offset."""
        p = np.zeros((self.num_joints, 3))
        for j, par in enumerate(self.parents):
            p[j] = self.offsets[j] if par < 0 else p[par] + self.offsets[j]
        return p

    def slice(self, start: int = 0, stop: int | None = None) -> "MocapClip":
        """Frames ``start:stop`` as a new clip (same joints)."""
        s = slice(start, stop)
        if len(range(*s.indices(self.num_frames))) == 0:
            raise InputError(
                f"frames {start}:{stop} select nothing from a clip of {self.num_frames} frames"
            )
        return replace(
            self, rotations=self.rotations[s], translations=self.translations[s],
            positions=self.positions[s], info=dict(self.info),
        )


def forward_kinematics(
    parents: Sequence[int], rotations: np.ndarray, translations: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Global rotations and positions of a joint tree.

    Args:
        parents: ``(J,)`` parent indices, parents before children, ``-1`` for roots.
        rotations: ``(T, J, 3, 3)`` local rotations.
        translations: ``(T, J, 3)`` local translations in metres (root: global position).

    Returns:
        ``(G, P)``: ``(T, J, 3, 3)`` global rotations and ``(T, J, 3)`` global positions,
        with ``G_j = G_p @ L_j`` and ``P_j = P_p + G_p @ t_j``.
    """
    rotations = np.asarray(rotations, dtype=np.float64)
    translations = np.asarray(translations, dtype=np.float64)
    G = np.empty_like(rotations)
    P = np.empty_like(translations)
    for j, p in enumerate(parents):
        if p < 0:
            G[:, j] = rotations[:, j]
            P[:, j] = translations[:, j]
        else:
            if p >= j:
                raise InputError(f"joint {j} comes before its parent {p}; order parents first")
            G[:, j] = G[:, p] @ rotations[:, j]
            P[:, j] = P[:, p] + np.einsum("tab,tb->ta", G[:, p], translations[:, j])
    return G, P


def _make_clip(names, parents, offsets, rotations, translations, end_site, fps, source, info):
    parents = np.asarray(parents, dtype=np.int64)
    _, P = forward_kinematics(parents, rotations, translations)
    return MocapClip(
        names=tuple(names), parents=parents, offsets=np.asarray(offsets, dtype=np.float64),
        rotations=rotations, translations=translations, positions=P,
        end_site=np.asarray(end_site, dtype=bool), fps=float(fps), source=str(source), info=info,
    )


# ------------------------------------------------------------------------- rotations


def _euler(axes: str, angles: np.ndarray) -> np.ndarray:
    """``(..., len(axes))`` radians -> ``(..., 3, 3)`` by scipy's convention: lowercase
    ``axes`` are fixed axes applied in the listed order (``R = R_last ... R_first``),
    uppercase ones intrinsic; no axes give the identity."""
    angles = np.asarray(angles, dtype=np.float64)
    lead = angles.shape[:-1]
    if not axes:
        return np.broadcast_to(np.eye(3), lead + (3, 3)).copy()
    return Rotation.from_euler(axes, angles.reshape(-1, len(axes))).as_matrix().reshape(lead + (3, 3))


# ---------------------------------------------------------------------------- ASF/AMC


@dataclass
class _Bone:
    name: str
    line: int
    direction: np.ndarray | None = None
    length: float | None = None
    axis: np.ndarray | None = None
    axis_order: str = "xyz"
    dof: tuple[str, ...] = ()


def _read_text(path: Path, what: str) -> list[str]:
    path = Path(path)
    if not path.exists():
        raise DataError(f"{what} file not found: {path}")
    if path.is_dir():
        raise DataError(f"{what} path is a folder, not a file: {path}")
    try:
        return path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as e:
        raise DataError(f"cannot read {what} file {path}: {e}") from None


def _floats(tokens: Sequence[str], path, line: int, what: str) -> np.ndarray:
    try:
        return np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        raise DataError(f"{path}:{line}: expected numbers for {what}, got {' '.join(tokens)!r}") from None


def _parse_asf(path: Path):
    lines = _read_text(path, "ASF skeleton")
    units = {"length": 1.0, "angle": "deg", "mass": 1.0}
    root = {"order": None, "axis": "xyz", "position": np.zeros(3), "orientation": np.zeros(3)}
    bones: dict[str, _Bone] = {}
    children: dict[str, list[str]] = {}
    section = None
    bone: _Bone | None = None
    seen_sections = set()
    for lineno, raw in enumerate(lines, 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        tok = line.split()
        if tok[0].startswith(":"):
            section = tok[0][1:].lower()
            seen_sections.add(section)
            if section in ("version", "name", "documentation"):
                continue
            if section not in ("units", "root", "bonedata", "hierarchy"):
                continue
            if len(tok) > 1:
                raise DataError(f"{path}:{lineno}: unexpected text after {tok[0]!r}")
            continue
        key = tok[0].lower()
        if section == "units":
            if len(tok) < 2:
                raise DataError(f"{path}:{lineno}: units line needs a key and a value: {line!r}")
            if key == "angle":
                if tok[1].lower() not in ("deg", "rad"):
                    raise DataError(f"{path}:{lineno}: angle unit must be deg or rad, got {tok[1]!r}")
                units["angle"] = tok[1].lower()
            elif key in ("length", "mass"):
                units[key] = float(_floats(tok[1:2], path, lineno, key)[0])
        elif section == "root":
            if key == "order":
                root["order"] = [t.lower() for t in tok[1:]]
                bad = [t for t in root["order"] if t not in ("tx", "ty", "tz", "rx", "ry", "rz")]
                if bad:
                    raise DataError(f"{path}:{lineno}: unknown root channel(s) {bad}")
                root["order_line"] = lineno
            elif key == "axis":
                root["axis"] = _axis_order(tok[1] if len(tok) > 1 else "", path, lineno)
            elif key in ("position", "orientation"):
                v = _floats(tok[1:], path, lineno, f"root {key}")
                if v.shape != (3,):
                    raise DataError(f"{path}:{lineno}: root {key} needs 3 numbers")
                root[key] = v
        elif section == "bonedata":
            if key == "begin":
                bone = _Bone(name="", line=lineno)
            elif key == "end":
                if bone is None:
                    raise DataError(f"{path}:{lineno}: 'end' without 'begin' in :bonedata")
                if not bone.name:
                    raise DataError(f"{path}:{bone.line}: bone without a name")
                for attr in ("direction", "length"):
                    if getattr(bone, attr) is None:
                        raise DataError(f"{path}:{bone.line}: bone {bone.name!r} has no {attr}")
                if bone.axis is None:
                    bone.axis = np.zeros(3)
                if bone.name in bones or bone.name == "root":
                    raise DataError(f"{path}:{bone.line}: bone {bone.name!r} defined twice")
                bones[bone.name] = bone
                bone = None
            elif bone is None:
                raise DataError(f"{path}:{lineno}: {line!r} outside a begin/end block")
            elif key == "name":
                bone.name = tok[1] if len(tok) > 1 else ""
            elif key == "direction":
                v = _floats(tok[1:], path, lineno, "direction")
                if v.shape != (3,) or np.linalg.norm(v) == 0:
                    raise DataError(f"{path}:{lineno}: direction needs 3 numbers, not all zero")
                bone.direction = v / np.linalg.norm(v)
            elif key == "length":
                bone.length = float(_floats(tok[1:2], path, lineno, "length")[0])
            elif key == "axis":
                if len(tok) != 5:
                    raise DataError(f"{path}:{lineno}: axis needs 3 angles and an order like XYZ")
                bone.axis = _floats(tok[1:4], path, lineno, "axis")
                bone.axis_order = _axis_order(tok[4], path, lineno)
            elif key == "dof":
                dof = tuple(t.lower() for t in tok[1:])
                bad = [d for d in dof if d not in ("rx", "ry", "rz", "tx", "ty", "tz", "l")]
                if bad:
                    raise DataError(f"{path}:{lineno}: unknown dof {bad} of bone {bone.name!r}")
                bone.dof = dof
            # limits, bodymass, cofmass, id and limit continuation lines are not needed
        elif section == "hierarchy":
            if key in ("begin", "end"):
                continue
            parent = tok[0]
            for child in tok[1:]:
                children.setdefault(parent, []).append(child)
                children.setdefault(child, [])
                if child == "root":
                    raise DataError(f"{path}:{lineno}: the root cannot be a child")
            children.setdefault(parent, [])
            for name in tok:
                if name != "root" and name not in bones:
                    raise DataError(
                        f"{path}:{lineno}: hierarchy names bone {name!r} that :bonedata does not define"
                    )
    for needed in ("root", "bonedata", "hierarchy"):
        if needed not in seen_sections:
            raise DataError(f"{path}: not an ASF skeleton: no :{needed} section")
    if bone is not None:
        raise DataError(f"{path}:{bone.line}: bone block without 'end'")
    if root["order"] is None:
        raise DataError(f"{path}: the :root section has no 'order' line")
    if units["length"] <= 0:
        raise DataError(f"{path}: :units length must be positive, got {units['length']}")
    return units, root, bones, children


def _axis_order(text: str, path, lineno: int) -> str:
    order = text.lower()
    if not order or any(c not in "xyz" for c in order):
        raise DataError(f"{path}:{lineno}: axis order must be letters from XYZ, got {text!r}")
    return order


def read_asf_amc(
    asf_path: str | Path,
    amc_path: str | Path,
    fps: float = 120.0,
    length_unit_m: float | None = None,
) -> MocapClip:
    """Read an Acclaim skeleton (``.asf``) and motion (``.amc``) into a :class:`MocapClip`.

    Args:
        asf_path: the ``.asf`` skeleton file.
        amc_path: the ``.amc`` motion file.
        fps: frame rate in Hz; AMC files do not store it (CMU's are 120 Hz).
        length_unit_m: metres per ASF length unit; default ``0.0254 / length`` from the
            ASF ``:units`` section (CMU: ``length 0.45``, 5.64 cm per unit).

    Returns:
        :class:`MocapClip` with joints ``root``, one per bone (at the bone's start) and
        ``<bone>_end`` for each leaf bone's far end; positions in metres, y up.

    Raises:
        DataError: missing files, malformed ASF or AMC (with file and line).
    """
    asf_path, amc_path = Path(asf_path), Path(amc_path)
    if fps <= 0 or not math.isfinite(fps):
        raise InputError(f"fps must be a positive number of frames per second, got {fps}")
    units, root, bones, children = _parse_asf(asf_path)
    unit = INCH / units["length"] if length_unit_m is None else float(length_unit_m)
    to_rad = math.pi / 180.0 if units["angle"] == "deg" else 1.0

    # Joint list: root, then bones depth-first, each leaf bone followed by its end site.
    names, parents, offsets, end_site, bone_of = ["root"], [-1], [np.zeros(3)], [False], [None]
    stack = [(c, 0) for c in reversed(children.get("root", []))]
    visited = set()
    while stack:
        name, parent_joint = stack.pop()
        if name in visited:
            raise DataError(f"{asf_path}: bone {name!r} appears twice in the :hierarchy")
        visited.add(name)
        par_bone = bone_of[parent_joint]
        offset = np.zeros(3) if par_bone is None else par_bone.length * unit * par_bone.direction
        names.append(name)
        parents.append(parent_joint)
        offsets.append(offset)
        end_site.append(False)
        bone_of.append(bones[name])
        j = len(names) - 1
        kids = children.get(name, [])
        if not kids:
            b = bones[name]
            names.append(f"{name}_end")
            parents.append(j)
            offsets.append(b.length * unit * b.direction)
            end_site.append(True)
            bone_of.append(None)
        for c in reversed(kids):
            stack.append((c, j))
    unused = sorted(set(bones) - visited)
    if unused:
        warnings.warn(f"{asf_path}: bones not in the hierarchy are ignored: {', '.join(unused)}")

    frames = _parse_amc(amc_path, root, bones, visited)
    T, J = len(frames), len(names)
    rotations = np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy()
    translations = np.broadcast_to(np.asarray(offsets), (T, J, 3)).copy()

    # Root: channel order from the ASF, orientation axes from 'axis'.
    order = root["order"]
    vals = np.array([f["root"] for f in frames])  # (T, len(order))
    rot_axes = "".join(c[1] for c in order if c.startswith("r"))
    rot_vals = np.stack([vals[:, k] for k, c in enumerate(order) if c.startswith("r")], -1) if rot_axes else np.zeros((T, 0))
    pos = root["position"] * unit + np.zeros((T, 3))
    for k, c in enumerate(order):
        if c.startswith("t"):
            pos[:, "xyz".index(c[1])] = vals[:, k] * unit
    C = _euler(root["axis"], root["orientation"] * to_rad)
    M = _euler(rot_axes, rot_vals * to_rad)
    rotations[:, 0] = C @ M @ C.T
    translations[:, 0] = pos

    for j, b in enumerate(bone_of):
        if b is None:
            continue
        C = _euler(b.axis_order, b.axis * to_rad)
        rdofs = [(k, d[1]) for k, d in enumerate(b.dof) if d.startswith("r")]
        if not rdofs:
            continue
        v = np.array([f.get(b.name, np.zeros(len(b.dof))) for f in frames])  # (T, ndof)
        M = _euler("".join(a for _, a in rdofs), v[:, [k for k, _ in rdofs]] * to_rad)
        rotations[:, j] = C @ M @ C.T
    if any(d in ("tx", "ty", "tz", "l") for b in bones.values() for d in b.dof):
        warnings.warn(f"{asf_path}: translation/length dofs of bones are read but not applied")

    info = {"format": "asf/amc", "length_unit_m": unit, "angle_unit": units["angle"],
            "asf": str(asf_path), "amc": str(amc_path)}
    return _make_clip(names, parents, offsets, rotations, translations, end_site, fps,
                      f"{asf_path} + {amc_path}", info)


def _parse_amc(path: Path, root: dict, bones: dict[str, _Bone], used: set[str]) -> list[dict]:
    lines = _read_text(path, "AMC motion")
    frames: list[dict] = []
    current: dict | None = None
    expected_root = len(root["order"])
    for lineno, raw in enumerate(lines, 1):
        line = raw.split("#", 1)[0].strip()
        if not line or line.startswith(":"):
            continue
        tok = line.split()
        if len(tok) == 1:
            try:
                number = int(tok[0])
            except ValueError:
                raise DataError(f"{path}:{lineno}: expected a frame number, got {line!r}") from None
            if frames and number != frames[-1]["_number"] + 1:
                raise DataError(
                    f"{path}:{lineno}: frame {number} follows frame {frames[-1]['_number']}; "
                    "frames must be numbered consecutively"
                )
            current = {"_number": number, "_line": lineno}
            frames.append(current)
            continue
        if current is None:
            raise DataError(f"{path}:{lineno}: values before the first frame number: {line!r}")
        name = tok[0]
        v = _floats(tok[1:], path, lineno, f"bone {name!r}")
        if name == "root":
            if len(v) != expected_root:
                raise DataError(
                    f"{path}:{lineno}: root has {len(v)} values but the ASF order lists {expected_root}"
                )
        elif name in bones:
            if len(v) != len(bones[name].dof):
                raise DataError(
                    f"{path}:{lineno}: bone {name!r} has {len(v)} values but its ASF dof lists "
                    f"{len(bones[name].dof)} ({' '.join(bones[name].dof) or 'none'})"
                )
        else:
            raise DataError(f"{path}:{lineno}: bone {name!r} is not in the ASF skeleton (wrong .asf?)")
        current[name] = v
    if not frames:
        raise DataError(f"{path}: no frames found (not an AMC motion file?)")
    for f in frames:
        if "root" not in f:
            raise DataError(f"{path}:{f['_line']}: frame {f['_number']} has no root values")
    return frames


def find_asf(amc_path: str | Path) -> Path:
    """The ASF skeleton for an AMC file: ``<stem>.asf``, then CMU's ``<subject>.asf``
    (``35_01.amc`` -> ``35.asf``), then the only ``.asf`` in the same folder.

    Raises:
        DataError: none found, or several candidates.
    """
    amc_path = Path(amc_path)
    folder = amc_path.parent
    stem = amc_path.stem
    candidates = [folder / f"{stem}.asf"]
    if "_" in stem:
        candidates.append(folder / f"{stem.rsplit('_', 1)[0]}.asf")
    for c in candidates:
        if c.exists():
            return c
    found = sorted(folder.glob("*.asf")) if folder.is_dir() else []
    if len(found) == 1:
        return found[0]
    raise DataError(
        f"no ASF skeleton found for {amc_path}: looked for {', '.join(c.name for c in candidates)}"
        + (f" and found several .asf files ({', '.join(f.name for f in found)})" if found else "")
        + "; pass the skeleton explicitly (asf=...)"
    )


# ------------------------------------------------------------------------------- BVH

_BVH_CHANNELS = {
    "xposition": "px", "yposition": "py", "zposition": "pz",
    "xrotation": "rx", "yrotation": "ry", "zrotation": "rz",
}


def _bvh_tokens(lines: list[str]):
    for lineno, raw in enumerate(lines, 1):
        for t in raw.replace("{", " { ").replace("}", " } ").split():
            yield t, lineno


def read_bvh(
    path: str | Path,
    scale: float | None = None,
    up: str = "y",
) -> MocapClip:
    """Read a BVH file into a :class:`MocapClip` (metres, y up).

    Args:
        path: the ``.bvh`` file.
        scale: metres per file unit. Default: guessed from the rest skeleton's height
            (extent along ``up``), trying metres, cm, mm, inches and CMU's ASF unit
            (``0.0254 / 0.45``) and keeping the one that makes it 1.1-2.2 m tall.
        up: the file's up axis, ``"y"`` (BVH's usual) or ``"z"``; a z-up file is turned
            to y up (``(x, y, z) -> (x, z, -y)``).

    Returns:
        :class:`MocapClip`; end sites are named ``<joint>_end`` (or by their BVH
        name where one is given). ``info`` holds the unit used and each joint's channels.

    Raises:
        DataError: missing file, malformed hierarchy or motion (with line numbers),
            frame count mismatch, or a unit that cannot be guessed.
    """
    from flowmocap.errors import check_path

    check_path(path, "path", "a .bvh file")
    path = Path(path)
    if up not in ("y", "z"):
        raise InputError(f"up must be 'y' or 'z', got {up!r}")
    lines = _read_text(path, "BVH")
    toks = _bvh_tokens(lines)

    def nxt(expect: str | None = None):
        try:
            t, ln = next(toks)
        except StopIteration:
            raise DataError(f"{path}: unexpected end of file in the HIERARCHY section") from None
        if expect is not None and t.upper() != expect:
            raise DataError(f"{path}:{ln}: expected {expect!r}, got {t!r}")
        return t, ln

    t, ln = nxt()
    if t.upper() != "HIERARCHY":
        raise DataError(f"{path}:{ln}: a BVH file starts with HIERARCHY, got {t!r}")
    names, parents, offsets, channels, end_site = [], [], [], [], []
    t, ln = nxt()
    if t.upper() != "ROOT":
        raise DataError(f"{path}:{ln}: expected ROOT, got {t!r}")

    def parse_joint(parent: int, is_end: bool, ln_start: int):
        if is_end:
            # "End Site" -- the second word was read by the caller
            name = f"{names[parent]}_end"
        else:
            name, _ = nxt()
        j = len(names)
        names.append(name)
        parents.append(parent)
        end_site.append(is_end)
        channels.append([])
        offsets.append(np.zeros(3))
        nxt("{")
        while True:
            t, ln = nxt()
            key = t.upper()
            if key == "OFFSET":
                vals = [nxt()[0] for _ in range(3)]
                offsets[j] = _floats(vals, path, ln, "OFFSET")
            elif key == "CHANNELS":
                if is_end:
                    raise DataError(f"{path}:{ln}: an End Site cannot have CHANNELS")
                n_t, _ = nxt()
                try:
                    n = int(n_t)
                except ValueError:
                    raise DataError(f"{path}:{ln}: CHANNELS needs a count, got {n_t!r}") from None
                chans = []
                for _ in range(n):
                    c, lc = nxt()
                    if c.lower() not in _BVH_CHANNELS:
                        raise DataError(f"{path}:{lc}: unknown channel {c!r}")
                    chans.append(_BVH_CHANNELS[c.lower()])
                if len(set(chans)) != len(chans):
                    raise DataError(f"{path}:{ln}: repeated channel in {chans}")
                channels[j] = chans
            elif key == "JOINT":
                if is_end:
                    raise DataError(f"{path}:{ln}: an End Site cannot have children")
                parse_joint(j, False, ln)
            elif key == "END":
                w, lw = nxt()
                if w.upper() != "SITE":
                    raise DataError(f"{path}:{lw}: expected 'End Site', got 'End {w}'")
                parse_joint(j, True, ln)
            elif key == "}":
                return
            else:
                raise DataError(f"{path}:{ln}: unexpected {t!r} in joint {name!r}")

    parse_joint(-1, False, ln)
    t, ln = nxt()
    if t.upper() != "MOTION":
        raise DataError(f"{path}:{ln}: expected MOTION after the hierarchy, got {t!r}")
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise DataError(f"{path}: joint names used twice: {', '.join(dup)}")

    # MOTION: "Frames: N", "Frame Time: dt", then N lines.
    motion_line = ln
    body = [(i, l.strip()) for i, l in enumerate(lines[motion_line:], motion_line + 1) if l.strip()]
    if len(body) < 2:
        raise DataError(f"{path}:{motion_line}: MOTION needs 'Frames:' and 'Frame Time:' lines")
    m = re.fullmatch(r"frames\s*:\s*(\d+)", body[0][1], re.IGNORECASE)
    if not m:
        raise DataError(f"{path}:{body[0][0]}: expected 'Frames: N', got {body[0][1]!r}")
    n_frames = int(m.group(1))
    m = re.fullmatch(r"frame\s+time\s*:\s*(\S+)", body[1][1], re.IGNORECASE)
    if not m:
        raise DataError(f"{path}:{body[1][0]}: expected 'Frame Time: seconds', got {body[1][1]!r}")
    frame_time = float(_floats([m.group(1)], path, body[1][0], "Frame Time")[0])
    if not frame_time > 0:
        raise DataError(f"{path}:{body[1][0]}: Frame Time must be positive, got {frame_time}")
    rows = body[2:]
    if len(rows) != n_frames:
        raise DataError(
            f"{path}:{body[0][0]}: the header says {n_frames} frames but {len(rows)} frame lines follow"
        )
    if n_frames == 0:
        raise DataError(f"{path}:{body[0][0]}: the clip has no frames")
    n_ch = sum(len(c) for c in channels)
    data = np.empty((n_frames, n_ch))
    for k, (lineno, text) in enumerate(rows):
        vals = text.split()
        if len(vals) != n_ch:
            raise DataError(
                f"{path}:{lineno}: frame {k} has {len(vals)} values, the hierarchy declares {n_ch} channels"
            )
        data[k] = _floats(vals, path, lineno, f"frame {k}")

    offsets_arr = np.asarray(offsets)
    if scale is None:
        scale, unit_name = _guess_bvh_unit(names, parents, offsets_arr, up, path)
    else:
        if not (scale > 0 and math.isfinite(scale)):
            raise InputError(f"scale must be a positive number of metres per file unit, got {scale}")
        unit_name = "given"
    T, J = n_frames, len(names)
    rotations = np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy()
    translations = np.broadcast_to(offsets_arr * scale, (T, J, 3)).copy()
    col = 0
    for j, chans in enumerate(channels):
        block = data[:, col:col + len(chans)]
        col += len(chans)
        rot = [(k, c[1]) for k, c in enumerate(chans) if c.startswith("r")]
        if rot:
            order = "".join(a.upper() for _, a in rot)
            rotations[:, j] = _euler(order, np.deg2rad(block[:, [k for k, _ in rot]]))
        for k, c in enumerate(chans):
            if c.startswith("p"):
                translations[:, j, "xyz".index(c[1])] = block[:, k] * scale
    offsets_m = offsets_arr * scale
    if up == "z":
        A = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
        offsets_m = offsets_m @ A.T
        translations = translations @ A.T
        rotations = A @ rotations @ A.T
    info = {"format": "bvh", "unit": unit_name, "metres_per_unit": scale, "up": up,
            "channels": {n: c for n, c in zip(names, channels) if c}}
    return _make_clip(names, parents, offsets_m, rotations, translations, end_site,
                      1.0 / frame_time, path, info)


def _guess_bvh_unit(names, parents, offsets, up, path) -> tuple[float, str]:
    rest = np.zeros((len(names), 3))
    for j, p in enumerate(parents):
        rest[j] = offsets[j] if p < 0 else rest[p] + offsets[j]
    axis = 1 if up == "y" else 2
    height = float(rest[:, axis].max() - rest[:, axis].min())
    from flowmocap.body.skeleton import JOINT_NAMES

    if set(JOINT_NAMES) <= set(names):  # flowmocap's own export (SMPL's joints): metres or centimetres, any
        for name in ("m", "cm"):       # body --height takes (its joints span about 0.93 of the stature)
            if _OWN_SPAN[0] <= height * BVH_UNITS[name] <= _OWN_SPAN[1]:
                return BVH_UNITS[name], name
    for name, s in BVH_UNITS.items():
        if _HEIGHT_RANGE[0] <= height * s <= _HEIGHT_RANGE[1]:
            return s, name
    raise DataError(
        f"{path}: cannot tell the length unit: the rest skeleton is {height:.4g} file units tall "
        f"along {up}, which is no plausible human height in "
        f"{', '.join(BVH_UNITS)}; pass scale=<metres per unit> (and up='z' for z-up files)"
    )


# ---------------------------------------------------------------------------- dispatch


def read_mocap(
    path: str | Path,
    asf: str | Path | None = None,
    fps: float | None = None,
    scale: float | None = None,
) -> MocapClip:
    """Read a ``.bvh`` file or an ``.amc`` file (its ``.asf`` found by :func:`find_asf`).

    Args:
        path: ``.bvh`` or ``.amc`` file.
        asf: the ASF skeleton for an ``.amc`` file (default: found next to it).
        fps: frame rate for AMC files (default 120 Hz, CMU's); ignored for BVH.
        scale: metres per BVH file unit (default: guessed).

    Raises:
        DataError: missing file, unknown extension, malformed content.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".bvh":
        return read_bvh(path, scale=scale)
    if ext == ".amc":
        return read_asf_amc(asf if asf is not None else find_asf(path), path,
                            fps=120.0 if fps is None else fps)
    if ext == ".asf":
        raise DataError(f"{path} is a skeleton; pass the motion (.amc) file, its skeleton is found next to it")
    raise DataError(f"unknown mocap file type {path.suffix!r} ({path}); expected .bvh or .amc")


# ----------------------------------------------------------------------- BVH writing


def write_bvh(
    clip: MocapClip,
    path: str | Path,
    units_per_metre: float = 1.0,
    order: str = "ZYX",
) -> Path:
    """Write a clip as BVH: root with position + rotation channels, joints rotation only
    (plus position channels where the clip animates a joint's translation). Written
    atomically: an interrupted write leaves the old file, or none, never part of one.

    Args:
        clip: the clip (end sites become ``End Site`` blocks; a leaf that is not an end
            site gets a zero-length ``End Site``, which reads back as an extra joint).
        path: output ``.bvh`` file.
        units_per_metre: file units per metre (1 = metres, 100 = cm).
        order: rotation channel order, three different letters from ``XYZ``
            (intrinsic, listed order: ``"ZYX"`` writes ``Zrotation Yrotation Xrotation``).

    Returns:
        The path written.
    """
    path = Path(path)
    if len(order) != 3 or set(order) != set("XYZ"):
        raise InputError(f"order must be a permutation of XYZ, got {order!r}")
    J, T = clip.num_joints, clip.num_frames
    kids = [[c for c in range(J) if clip.parents[c] == j] for j in range(J)]
    animated_t = [
        j == 0 or (not clip.end_site[j] and not np.allclose(clip.translations[:, j], clip.offsets[j], atol=1e-12))
        for j in range(J)
    ]
    rot_names = " ".join(f"{a}rotation" for a in order)
    out: list[str] = ["HIERARCHY"]
    joint_order: list[int] = []

    def fmt(v):
        return " ".join(f"{x * units_per_metre:.10f}" for x in v)

    def emit(j: int, depth: int):
        ind = "  " * depth
        if clip.end_site[j]:
            out.extend([f"{ind}End Site", f"{ind}{{", f"{ind}  OFFSET {fmt(clip.offsets[j])}", f"{ind}}}"])
            return
        kw = "ROOT" if clip.parents[j] < 0 else "JOINT"
        out.extend([f"{ind}{kw} {clip.names[j]}", f"{ind}{{", f"{ind}  OFFSET {fmt(clip.offsets[j])}"])
        if animated_t[j]:
            out.append(f"{ind}  CHANNELS 6 Xposition Yposition Zposition {rot_names}")
        else:
            out.append(f"{ind}  CHANNELS 3 {rot_names}")
        joint_order.append(j)
        for c in kids[j]:
            emit(c, depth + 1)
        if not kids[j]:
            out.extend([f"{ind}  End Site", f"{ind}  {{", f"{ind}    OFFSET 0 0 0", f"{ind}  }}"])
        out.append(f"{ind}}}")

    roots = [j for j in range(J) if clip.parents[j] < 0]
    if len(roots) != 1:
        raise InputError(f"BVH needs exactly one root joint; the clip has {len(roots)}")
    emit(roots[0], 0)
    angles = np.rad2deg(
        matrix_to_euler(torch.as_tensor(clip.rotations[:, joint_order]), order).numpy()
    )  # (T, n, 3)
    out += ["MOTION", f"Frames: {T}", f"Frame Time: {1.0 / clip.fps:.10f}"]
    for t in range(T):
        vals = []
        for k, j in enumerate(joint_order):
            if animated_t[j]:
                vals.extend(clip.translations[t, j] * units_per_metre)
            vals.extend(angles[t, k])
        out.append(" ".join(f"{v:.10f}" for v in vals))
    text = "\n".join(out) + "\n"
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))  # never a cut-off file under the final name
    return path


# -------------------------------------------------------------------------- resampling


def resample(clip: MocapClip, fps: float) -> MocapClip:
    """Resample a clip to ``fps``: quaternion slerp of local rotations, linear translations.

    Output frame ``k`` is at time ``k / fps`` seconds, for every such time within the
    input's duration; joint positions are recomputed by forward kinematics.

    Args:
        clip: input clip.
        fps: target frame rate in Hz.

    Returns:
        A new :class:`MocapClip` at ``fps``.
    """
    if not (fps > 0 and math.isfinite(fps)):
        raise InputError(f"fps must be a positive number of frames per second, got {fps}")
    if abs(fps - clip.fps) < 1e-9 * fps:
        return replace(clip, info=dict(clip.info))
    n_out = int(math.floor(clip.duration * fps + 1e-9)) + 1
    src = np.arange(n_out) * (clip.fps / fps)  # fractional input frame index
    i0 = np.clip(np.floor(src).astype(int), 0, clip.num_frames - 1)
    i1 = np.minimum(i0 + 1, clip.num_frames - 1)
    w = src - i0
    # slerp: R0 Exp(w Log(R0^T R1)), the shorter arc
    r0 = Rotation.from_matrix(clip.rotations[i0].reshape(-1, 3, 3))
    step = (r0.inv() * Rotation.from_matrix(clip.rotations[i1].reshape(-1, 3, 3))).as_rotvec()
    rot = (r0 * Rotation.from_rotvec(step * np.repeat(w, clip.rotations.shape[1])[:, None])).as_matrix()
    rot = rot.reshape(n_out, -1, 3, 3)
    w = w[:, None, None]
    trans = (1 - w) * clip.translations[i0] + w * clip.translations[i1]
    _, P = forward_kinematics(clip.parents, rot, trans)
    info = dict(clip.info, resampled_from_fps=clip.fps)
    return replace(clip, rotations=rot, translations=trans, positions=P, fps=float(fps), info=info)

"""Input/output of motions: motion-capture files (BVH, ASF/AMC), retargeting onto the
SMPL tree of any body model, and the built-in procedural walk.

Public API:

- :class:`MocapClip`, :func:`read_mocap` (``.bvh`` / ``.amc``), :func:`read_bvh`,
  :func:`read_asf_amc`, :func:`find_asf`, :func:`write_bvh`, :func:`resample`,
  :func:`forward_kinematics` -- clips in metres, y up.
- :class:`SmplMotion` (poses ``(T, 72)``, trans ``(T, 3)``, betas, gender, fps),
  :func:`retarget`, :func:`resolve_joint_map`, :data:`RIGS`, :func:`body_yaw`.
- :func:`builtin_walk`, :func:`walk_poses` -- ``builtin:walk``.
- :func:`read_amass_npz`, :func:`write_amass_npz`, :data:`Y_UP_TO_Z_UP` -- AMASS-layout
  ``.npz`` (z up); :func:`rotate_motion` turns a SMPL motion rigidly.
- :func:`load_motion` -- any of the above by name or path.
"""

from __future__ import annotations

import importlib
import sys
import types

# Each name is imported from its module when first asked for (PEP 562), so that importing
# one module of this package (a video reader in the person detector's process, say) does
# not load the others, torch among them (about 190 MB resident).
_WHERE = {
    "Y_UP_TO_Z_UP": "amass", "read_amass_npz": "amass", "write_amass_npz": "amass",
    "builtin_walk": "builtin_walk", "walk_poses": "builtin_walk",
    "MocapClip": "mocap", "find_asf": "mocap", "forward_kinematics": "mocap", "read_asf_amc": "mocap",
    "read_bvh": "mocap", "read_mocap": "mocap", "resample": "mocap", "write_bvh": "mocap",
    "load_motion": "motion_source",
    "REST_RELATIVE": "retarget", "RIGS": "retarget", "body_yaw": "retarget", "resolve_joint_map": "retarget",
    "retarget": "retarget",
    "SmplMotion": "smpl_motion", "rotate_motion": "smpl_motion",
}


def __getattr__(name: str):
    if name in _WHERE:
        value = getattr(importlib.import_module(f"flowmocap.io.{_WHERE[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'flowmocap.io' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE))


class _Package(types.ModuleType):
    """``flowmocap.io.retarget`` and ``flowmocap.io.builtin_walk`` name both a module and
    its main function; the package's attribute stays the function (as when these were
    imported eagerly), not the module the import system would set when the module loads."""

    def __setattr__(self, name: str, value) -> None:
        if isinstance(value, types.ModuleType) and _WHERE.get(name) == name:
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


__all__ = list(_WHERE)  # the public names, one place

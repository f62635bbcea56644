"""Where the detector's keypoints sit on the body: learned offsets from the model's joints.

MediaPipe's landmarks are not the body model's joints: its hips sit higher and wider
than SMPL's hip joints, its shoulders nearer the surface, by 1.5-5 cm. A term that pulls
the model's joints onto them bends the body by that much. The :class:`KeypointMap` moves
each of the 12 model joints the detector gives
(:data:`~flowmocap.vision.detect.SMPL_KEYPOINTS`) to where the detector puts that
keypoint on such a body::

    keypoint_j = J_j + R_p(j) @ o_j

``J_j`` the posed joint (metres), ``R_p(j)`` the posed rotation of one body part (the
joint's own bone or its parent's), ``o_j`` a fixed offset (metres, in the rest pose's
axes). The offsets are learned by ``tools/learn_keypoint_offsets.py`` from MediaPipe run on
rendered ``train`` clips of the CMU collection with known poses, once for each of the
detector's landmark networks (:data:`~flowmocap.vision.detect.MODELS`: they place some
keypoints differently, e.g. the heavy network's elbows by 2 cm); they ship in
``vision/data/keypoint_offsets.json`` ("full") and ``keypoint_offsets_heavy.json``
("heavy"). The same files give the middle of the ears (the head of
:mod:`flowmocap.eval.real3d`'s reference) from the head joint.

The tracker uses the map where it compares the body with the detector's joints (``E_j``,
``E_d``, ``E_3d``, the refits and their verdicts) when ``TrackerConfig.keypoint_offsets``
is on (the default: docs/experiments.md, "Keypoint offsets"), with the offsets of the
network it runs (``TrackerConfig.detector_model``); joints given by the user
(``init.json``) are taken to be the body model's own.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from flowmocap.errors import ModelFileError

__all__ = ["KEYPOINT_OFFSETS_FILE", "KEYPOINT_OFFSETS_FILES", "KeypointMap", "load_keypoint_map", "detector_points"]

#: The learned offsets shipped with the package, of the "full" landmark network.
KEYPOINT_OFFSETS_FILE = Path(__file__).resolve().parent / "data" / "keypoint_offsets.json"
#: The offsets of each landmark network (:data:`flowmocap.vision.detect.MODELS`).
KEYPOINT_OFFSETS_FILES = {"full": KEYPOINT_OFFSETS_FILE,
                          "heavy": KEYPOINT_OFFSETS_FILE.with_name("keypoint_offsets_heavy.json")}


@dataclass(frozen=True)
class KeypointMap:
    """Offsets of the detector's keypoints from the body model's joints.

    Attributes:
        part: ``(24,)`` int, the body part whose posed rotation carries each joint's offset.
        offset: ``(24, 3)`` metres in the rest pose's axes (0 for joints without one).
        ears_part: the part (the head) carrying the middle of the ears' offset.
        ears_offset: ``(3,)`` metres, the middle of the ears from the head joint.
    """

    part: np.ndarray
    offset: np.ndarray
    ears_part: int
    ears_offset: np.ndarray

    def apply(self, joints, transforms):
        """The detector's keypoints on a posed body.

        Args:
            joints: ``(..., 24, 3)`` posed joints, metres (tensor or array).
            transforms: ``(..., 24, 4, 4)`` the body parts' posed transforms
                (:attr:`~flowmocap.body.model.BodyOutput.transforms`).

        Returns:
            ``(..., 24, 3)`` like ``joints``: joints with an offset moved by it, the others as given.
        """
        if isinstance(joints, torch.Tensor):
            rot = transforms[..., list(self.part), :3, :3]
            off = torch.as_tensor(self.offset, dtype=joints.dtype, device=joints.device)
            return joints + (rot @ off[..., None])[..., 0]
        rot = np.asarray(transforms)[..., self.part, :3, :3]
        return np.asarray(joints) + (rot @ self.offset[..., None])[..., 0]

    def ears_middle(self, joints, transforms):
        """``(..., 3)`` the middle of the ears (metres) from posed ``joints (..., 24, 3)``
        and ``transforms (..., 24, 4, 4)``."""
        from flowmocap.body.skeleton import JOINT_INDEX

        head = np.asarray(joints)[..., JOINT_INDEX["head"], :]
        rot = np.asarray(transforms)[..., self.ears_part, :3, :3]
        return head + rot @ self.ears_offset


def load_keypoint_map(path: str | Path | None = None, model: str = "full") -> KeypointMap:
    """Read a keypoint-offset file: ``path``, or the shipped offsets of the landmark network
    ``model`` (:data:`KEYPOINT_OFFSETS_FILES`; "full", the default, is the one the real-video
    reference of :mod:`flowmocap.eval.real3d` is triangulated from).

    Raises:
        ModelFileError: the file is missing or is not a keypoint-offset file.
        InputError: ``model`` is not a landmark network flowmocap knows.
    """
    from flowmocap.vision.detect import check_model

    return _read_keypoint_map(Path(path) if path is not None else KEYPOINT_OFFSETS_FILES[check_model(model)])


@lru_cache(maxsize=4)
def _read_keypoint_map(path: Path) -> KeypointMap:
    """:func:`load_keypoint_map` of one file, read once."""
    from flowmocap.body.skeleton import JOINT_INDEX

    try:
        doc = json.loads(path.read_text())
        entries = doc["keypoints"]
        part = np.arange(24)
        offset = np.zeros((24, 3))
        for name, e in entries.items():
            if name == "ears_middle":
                continue
            j = JOINT_INDEX[e["joint"]]
            part[j] = JOINT_INDEX[e["part"]]
            offset[j] = np.asarray(e["offset_m"], np.float64).reshape(3)
        ears = entries["ears_middle"]
        ears_part, ears_offset = JOINT_INDEX[ears["part"]], np.asarray(ears["offset_m"], np.float64).reshape(3)
    except FileNotFoundError as e:
        raise ModelFileError(f"keypoint offsets {path} not found; reinstall flowmocap, or make them with "
                         "tools/learn_keypoint_offsets.py of the source repository.") from e
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise ModelFileError(f"{path} is not a keypoint-offset file (the source repository's tools/learn_keypoint_offsets.py writes one): "
                         f"{type(e).__name__}: {e}") from e
    if not (np.isfinite(offset).all() and np.isfinite(ears_offset).all()) or np.abs(offset).max() > 0.2:
        raise ModelFileError(f"{path}: offsets must be finite and below 0.2 m; remake the file with "
                         "tools/learn_keypoint_offsets.py of the source repository.")
    return KeypointMap(part, offset, int(ears_part), ears_offset)


def detector_points(out, cfg) -> torch.Tensor:
    """``(B, 24, 3)`` where the detector would put the joints of body ``out`` (a
    :class:`~flowmocap.body.model.BodyOutput`): :meth:`KeypointMap.apply` with the offsets of
    ``cfg.detector_model``'s network when ``cfg.keypoint_offsets`` is on, else the joints
    themselves."""
    if not getattr(cfg, "keypoint_offsets", False):
        return out.joints
    return load_keypoint_map(model=getattr(cfg, "detector_model", "full")).apply(out.joints, out.transforms)

"""A body motion in SMPL parameters (poses, translations, shape, gender, frame rate), and
turning one rigidly about the world origin."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from flowmocap.errors import InputError

__all__ = ["SmplMotion", "rotate_motion"]


@dataclass
class SmplMotion:
    """T frames of SMPL parameters.

    Attributes:
        poses: ``(T, 72)`` float32 axis-angle in radians, SMPL joint order (joint 0 is
            the global orientation).
        trans: ``(T, 3)`` float32 translations in metres (y up, ground plane y = 0).
        betas: ``(num_betas,)`` float32 shape coefficients the motion was made for (10 for
            the default body and SMPL).
        gender: ``"neutral"``, ``"male"`` or ``"female"``.
        fps: frames per second (Hz).
        source: where the motion came from (a mocap path or ``builtin:walk``).
        info: facts about how it was made (rig, scale, ground offset, ...).
    """

    poses: np.ndarray
    trans: np.ndarray
    betas: np.ndarray
    gender: str
    fps: float
    source: str
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.poses = np.asarray(self.poses, dtype=np.float32)
        self.trans = np.asarray(self.trans, dtype=np.float32)
        self.betas = np.asarray(self.betas, dtype=np.float32).reshape(-1)
        T = self.poses.shape[0]
        if self.poses.shape != (T, 72) or self.trans.shape != (T, 3):
            raise InputError(
                f"poses must be (T, 72) and trans (T, 3); got {self.poses.shape} and {self.trans.shape}"
            )

    @property
    def num_frames(self) -> int:
        """Number of frames T."""
        return int(self.poses.shape[0])

    def slice(self, start: int = 0, stop: int | None = None, step: int = 1) -> "SmplMotion":
        """Frames ``start:stop:step`` as a new motion (``fps`` divided by ``step``)."""
        s = slice(start, stop, step)
        n = len(range(*s.indices(self.num_frames)))
        if n == 0:
            raise InputError(
                f"frames {start}:{stop}:{step} select nothing from a motion of {self.num_frames} frames"
            )
        return replace(self, poses=self.poses[s], trans=self.trans[s], fps=self.fps / step,
                       info=dict(self.info))


def betas_tensor(model, betas) -> torch.Tensor:
    """``(1, num_betas)`` tensor of ``model``'s dtype from ``betas`` (None = mean shape;
    fewer values are zero-padded).

    Raises:
        InputError: more values than the model has, or non-finite values.
    """
    nb = model.num_betas
    b = np.zeros(nb) if betas is None else np.asarray(betas, dtype=np.float64).reshape(-1)
    if b.shape[0] > nb or not np.all(np.isfinite(b)):
        raise InputError(f"betas must be at most {nb} finite numbers, got {b.shape[0]}")
    b = np.pad(b, (0, nb - b.shape[0]))
    return torch.as_tensor(b[None], dtype=model.v_template.dtype)


def rotate_motion(poses: np.ndarray, trans: np.ndarray, rest_pelvis: np.ndarray,
                  rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Turn a whole SMPL motion rigidly about the world origin.

    SMPL rotates the body about its rest pelvis ``J0``: ``x = R0 (x_rest - J0) + J0 + trans``.
    Turning everything by ``W`` gives ``R0' = W R0`` and ``trans' = W (J0 + trans) - J0``.

    Args:
        poses: ``(T, 72)`` axis-angle in radians (only the first 3, the root, change).
        trans: ``(T, 3)`` metres.
        rest_pelvis: ``(3,)`` pelvis of the shaped rest pose, metres.
        rotation: ``(3, 3)`` rotation ``W``, or ``(T, 3, 3)``: one per frame.

    Returns:
        ``poses (T, 72)``, ``trans (T, 3)``, float64.
    """
    from scipy.spatial.transform import Rotation

    W = np.asarray(rotation, np.float64)
    poses = np.array(poses, np.float64).reshape(-1, 72)
    trans = np.asarray(trans, np.float64).reshape(-1, 3)
    J0 = np.asarray(rest_pelvis, np.float64).reshape(3)
    root = Rotation.from_matrix(W @ Rotation.from_rotvec(poses[:, :3]).as_matrix())
    poses[:, :3] = root.as_rotvec()
    if W.ndim == 3:
        return poses, np.einsum("tij,tj->ti", W, trans + J0) - J0
    return poses, (trans + J0) @ W.T - J0

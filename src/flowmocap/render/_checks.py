"""Checking and converting the inputs of the render ops.

Every public op calls these first, so that a user error (a wrong shape, a NaN vertex,
an empty image) raises :class:`flowmocap.errors.InputError` with a message that says
what to fix, instead of failing deep inside a Numba kernel. The kernels themselves only
ever see C-contiguous float64 / int32 numpy arrays (one compiled specialisation each).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from flowmocap.errors import InputError


@dataclass(frozen=True, eq=False)
class Faces:
    """A mesh's triangle list, checked once and kept in the kernels' layout.

    Build it with :func:`prepare_faces` and pass it instead of the raw ``(F, 3)`` array
    to call the render ops repeatedly on one mesh without re-checking it.

    Attributes:
        array: ``(F, 3)`` int32, C-contiguous, read-only vertex indices.
        num_vertices_min: the smallest vertex count the faces are valid for
            (``max index + 1``).
    """

    array: np.ndarray
    num_vertices_min: int

    @property
    def num_faces(self) -> int:
        """Number of triangles F."""
        return int(self.array.shape[0])


def prepare_faces(faces: Any) -> Faces:
    """Check a triangle list once, for repeated use with the render ops.

    Args:
        faces: ``(F, 3)`` integer vertex indices (numpy, torch or nested lists), or a
            :class:`Faces` (returned unchanged).

    Returns:
        :class:`Faces` holding an int32 ``(F, 3)`` read-only copy.

    Raises:
        InputError: wrong shape, non-integer values, negative indices, or ``F == 0``.
    """
    if isinstance(faces, Faces):
        return faces
    arr = to_numpy(faces, "faces")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"faces must have shape (F, 3) (vertex indices of triangles), got {arr.shape}")
    if arr.shape[0] == 0:
        raise InputError("faces is empty: the mesh needs at least one triangle")
    if not np.issubdtype(arr.dtype, np.integer):
        if np.issubdtype(arr.dtype, np.floating) and np.all(np.isfinite(arr)) and np.all(arr == np.round(arr)):
            arr = arr.astype(np.int64)
        else:
            raise InputError(f"faces must hold integer vertex indices, got dtype {arr.dtype}")
    lo, hi = int(arr.min()), int(arr.max())
    if lo < 0:
        raise InputError(f"faces holds a negative vertex index ({lo}); indices start at 0")
    if hi >= 2**31 - 1:
        raise InputError(f"faces holds a vertex index too large for int32 ({hi})")
    out = np.ascontiguousarray(arr, dtype=np.int32)
    out.setflags(write=False)
    return Faces(out, hi + 1)


def to_numpy(x: Any, name: str) -> np.ndarray:
    """``x`` as a numpy array (torch tensors are detached and moved to the CPU), of
    ``x``'s shape and dtype; ``name`` names it in the InputError raised when numpy cannot
    read it."""
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    try:
        return np.asarray(x)
    except Exception:  # noqa: BLE001 - anything numpy cannot read is a user error here
        raise InputError(f"{name} must be an array (numpy or torch), got {type(x).__name__}") from None


def check_faces(faces: Any, num_vertices: int) -> np.ndarray:
    """``(F, 3)`` int32 array of ``faces`` after checking every index is ``< num_vertices``."""
    f = prepare_faces(faces)
    if f.num_vertices_min > num_vertices:
        raise InputError(
            f"faces refers to vertex {f.num_vertices_min - 1} but only {num_vertices} vertices "
            "were given; pass the vertices of the same mesh as the faces"
        )
    return f.array


def check_points(x: Any, name: str, dim: int, num: int | None = None) -> np.ndarray:
    """``(N, dim)`` float64 C-contiguous array with finite values.

    Args:
        x: ``(N, dim)`` real numbers, numpy or torch, in the caller's unit (e.g. pixels
            for ``dim = 2``, metres for ``dim = 3``); converted, not rescaled.
        name: the argument's name for the error message.
        dim: the number of columns.
        num: the number of rows ``N`` required (one per vertex), or None for any.

    Raises:
        InputError: wrong shape or dtype, or a NaN or infinite value.
    """
    arr = to_numpy(x, name)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise InputError(f"{name} must have shape (V, {dim}), got {arr.shape}")
    if num is not None and arr.shape[0] != num:
        raise InputError(f"{name} must have {num} rows (one per vertex), got {arr.shape[0]}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise InputError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    out = np.ascontiguousarray(arr, dtype=np.float64)
    if not np.all(np.isfinite(out)):
        raise InputError(f"{name} holds NaN or infinite values; check the vertices that produced them")
    return out


def check_vector(x: Any, name: str, num: int, positive: bool = False) -> np.ndarray:
    """``(num,)`` float64 C-contiguous array with finite values (and ``> 0`` if asked).

    Args:
        x: ``(num,)`` real numbers, numpy or torch (e.g. per-vertex depths in metres).
        name: the argument's name for the error message.
        num: the length required (one value per vertex).
        positive: require every value ``> 0`` (depths in front of the camera).

    Raises:
        InputError: wrong shape or dtype, a NaN or infinite value, or a value ``<= 0``
            with ``positive``.
    """
    arr = to_numpy(x, name)
    if arr.shape != (num,):
        raise InputError(f"{name} must have shape ({num},) (one value per vertex), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise InputError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    out = np.ascontiguousarray(arr, dtype=np.float64)
    if not np.all(np.isfinite(out)):
        raise InputError(f"{name} holds NaN or infinite values")
    if positive and np.any(out <= 0):
        raise InputError(f"{name} must be positive (depth in front of the camera, metres)")
    return out


def check_size(height: Any, width: Any) -> tuple[int, int]:
    """``(height, width)`` as positive Python ints."""
    try:
        h, w = int(height), int(width)
    except (TypeError, ValueError):
        raise InputError(f"height and width must be integers, got {height!r}, {width!r}") from None
    if h != height or w != width:
        raise InputError(f"height and width must be integers, got {height!r}, {width!r}")
    if h <= 0 or w <= 0:
        raise InputError(f"the image must not be empty: got height={h}, width={w}")
    if h * w > 2**30:
        raise InputError(f"image of {h}x{w} pixels is too large")
    return h, w

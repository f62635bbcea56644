"""Result folders: ``motion.npz`` and ``run.json``, written frame by frame.

Every write goes to a temporary file that is then renamed over the old one, so an
interrupted run always leaves the last finished frame on disk, and ``--resume`` picks up
from there.

``motion.npz``: ``poses (T, 72)`` axis-angle radians, ``trans (T, 3)`` metres,
``betas (10,)``, ``gender``, ``fps``, ``camera`` (JSON of PinholeCamera.to_dict()),
``joints3d (T, 24, 3)`` metres (camera/world frame of the camera), ``joints2d (T, 24, 2)``
pixels, ``energies (T, K)`` and ``energy_names (K,)``, ``frame_index (T,)`` (the input's
frame numbers).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from flowmocap.atomic import atomic_write
from flowmocap.errors import DataError


def write_motion(out_dir: Path, arrays: dict) -> None:
    """Atomically write ``out_dir/motion.npz`` from a dict of arrays."""

    def write(tmp):
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)

    atomic_write(Path(out_dir) / "motion.npz", write)


def write_run(out_dir: Path, info: dict) -> None:
    """Atomically write ``out_dir/run.json``."""

    def write(tmp):
        Path(tmp).write_text(json.dumps(info, indent=2, default=json_default))

    atomic_write(Path(out_dir) / "run.json", write)


def json_default(x):
    """``json.dumps(default=...)`` for numpy arrays and numbers and paths (lists, Python
    numbers, strings); TypeError for anything else."""
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def read_result(out_dir: str | Path) -> tuple[dict, dict]:
    """``(motion arrays, run info)`` of a result folder.

    Raises:
        DataError: missing or unreadable files.
    """
    out_dir = Path(out_dir)
    try:
        with np.load(out_dir / "motion.npz", allow_pickle=False) as z:
            motion = {k: z[k] for k in z.files}
        run = json.loads((out_dir / "run.json").read_text())
    except FileNotFoundError as e:
        raise DataError(f"{out_dir} is not a flowmocap result folder ({e.filename} is missing).") from None
    except (ValueError, OSError) as e:
        raise DataError(f"{out_dir} holds an unreadable result ({e}).") from None
    return motion, run

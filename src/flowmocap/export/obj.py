"""Wavefront OBJ export: one mesh per frame in a folder."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from flowmocap.atomic import atomic_write

__all__ = ["write_obj", "write_obj_sequence"]


def write_obj(path: str | Path, vertices: np.ndarray, faces: np.ndarray, comment: str = "") -> Path:
    """Write one triangle mesh as OBJ (``v`` and 1-based ``f`` lines), atomically (an
    interrupted write leaves the old file, or none, never part of one).

    Args:
        path: output ``.obj`` file.
        vertices: ``(V, 3)`` positions in metres.
        faces: ``(F, 3)`` 0-based triangle indices, counter-clockwise seen from outside.
        comment: one line written as a ``#`` comment at the top.

    Returns:
        The path written.
    """
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    f = np.asarray(faces, np.int64).reshape(-1, 3) + 1
    lines = [f"# {comment}"] if comment else []
    lines.append("\n".join("v %.6f %.6f %.6f" % tuple(p) for p in v))
    lines.append("\n".join("f %d %d %d" % tuple(t) for t in f))
    path = Path(path)
    text = "\n".join(lines) + "\n"
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))  # never a cut-off .obj under the final name
    return path


def write_obj_sequence(folder: str | Path, frames, faces: np.ndarray, frame_numbers, num_frames: int,
                       progress: bool = False) -> list[Path]:
    """Write ``frame_<number>.obj`` per frame into ``folder``, in place of the
    ``frame_*.obj`` of an earlier export there: written beside it first, then the folders
    trade places (a stop leaves one whole export; where the folder holds other files too,
    the frames are replaced in it one by one).

    Args:
        folder: output folder (created).
        frames: iterable of ``(V, 3)`` vertex arrays in metres.
        faces: ``(F, 3)`` triangle indices.
        frame_numbers: ``(T,)`` the input video's frame numbers (used in the file names).
        num_frames: the number of arrays ``frames`` yields (for the progress bar).
        progress: show a progress bar.

    Returns:
        The paths written, in order.

    Raises:
        InputError: ``folder`` is a file.
    """
    from tqdm import tqdm

    from flowmocap.errors import InputError

    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{folder} is a file; the obj export writes a folder of OBJ files (one a frame): give a "
                         "folder's path.")
    folder.parent.mkdir(parents=True, exist_ok=True)
    # every frame into a folder of its own beside this one first: a stop or a full disk part of
    # the way leaves the earlier export as it was, never a mix of two motions
    staging = Path(tempfile.mkdtemp(dir=folder.parent, prefix=folder.name + ".", suffix=".tmp"))
    try:
        made = []
        for verts, n in zip(tqdm(frames, total=num_frames, disable=not progress, unit="frame", desc="obj"),
                            frame_numbers):
            made.append(write_obj(staging / f"frame_{int(n):06d}.obj", verts, faces,
                                  comment=f"flowmocap frame {int(n)}, metres"))
        names = [p.name for p in made]
        # mkdtemp makes 0700: the earlier folder's mode, else a new folder's (set once the frames are in, so a
        # read-only earlier folder does not stop them)
        if folder.is_dir():
            mode = folder.stat().st_mode & 0o7777
        else:
            from flowmocap.atomic import current_umask

            mode = 0o777 & ~current_umask()
        os.chmod(staging, mode)
        if not folder.exists():
            os.rename(staging, folder)
        elif all(p.name.startswith("frame_") and p.suffix == ".obj" for p in folder.iterdir()):
            # only an earlier export's frames: the folders trade places, so a stop leaves one whole
            # export under the name (the earlier one is put back if the new one is not in yet)
            old = Path(tempfile.mkdtemp(dir=folder.parent, prefix=folder.name + ".old.", suffix=".tmp"))
            os.rmdir(old)
            os.rename(folder, old)
            try:
                os.rename(staging, folder)
            except BaseException:
                os.rename(old, folder)
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:  # a folder that holds files of the user's as well: the frames are replaced in it
            for p in folder.glob("frame_*.obj"):
                p.unlink()
            for p in made:
                os.replace(p, folder / p.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return [folder / n for n in names]

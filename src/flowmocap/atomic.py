"""Atomic file writes: a file is written under a temporary name beside its place and then
renamed over it, so a reader (or a resumed run) sees the old file or the new one, never
half of one. The file gets a normal file's permissions (``0o666`` less the umask)."""

from __future__ import annotations

import os
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

_UMASK_LOCK = threading.Lock()


def current_umask() -> int:
    """The process's umask, read without changing it where the system says it
    (``/proc/self/status`` on Linux); elsewhere set and put back under a lock. (Reading it
    by ``os.umask(0)`` then ``os.umask(old)`` from two threads at once, as the tracker's
    flow-cache and frame writes did, could leave it at 0 for good.)"""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _UMASK_LOCK:
        mask = os.umask(0o077)
        os.umask(mask)
    return mask


def check_file_path(path: str | Path) -> None:
    """Refuse a path to write a file at that is a folder, or lies under a file
    (``InputError``: the user's mistake, not a failed write).

    Args:
        path: the file to be written.
    """
    from flowmocap.errors import InputError

    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path} is a folder; give the path of the file to write.")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"{parent} is a file, so {path} cannot be written under it; give another path.")
            break


def atomic_write(path: str | Path, write: Callable[[str], None]) -> None:
    """Write ``path`` atomically: ``write(tmp)`` fills a temporary file in the same folder
    (created if needed), which then replaces ``path``; on any error the temporary file is
    removed and ``path`` is left as it was."""
    path = Path(path)
    check_file_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    os.close(fd)
    os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp makes 0600
    try:
        write(tmp)
        os.replace(tmp, path)
    except OSError as e:
        if e.filename is None and e.errno is not None:  # say which file could not be written (a full disk names none)
            raise OSError(e.errno, e.strerror, str(path)) from e
        raise
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def atomic_write_npz(path: str | Path, **arrays) -> None:
    """Write ``arrays`` as an uncompressed ``.npz`` at ``path``, atomically (:func:`atomic_write`).

    The archive is made in memory first: numpy's zip writer, left open when a write to the
    disk fails (a full disk, a file size limit), complains again when it is collected, and
    ``np.savez`` would add ``.npz`` to a temporary file's name.

    Args:
        path: the file to write.
        **arrays: name -> array, as for ``np.savez``.
    """
    import io

    import numpy as np

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(buf.getvalue()))

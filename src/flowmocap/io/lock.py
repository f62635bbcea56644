"""One writer per result folder: an exclusive lock held while a run writes.

The lock is an operating-system file lock on ``RESULT/.lock`` (the ``filelock`` package:
``flock`` on POSIX, ``msvcrt`` locking on Windows), so it is released when its process
ends however it ends (``kill -9`` included): a lock left by a dead run is never in the
way. Beside it ``.lock.json`` says who holds it (pid, host, start time), for the message
another run gets.
"""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path

import filelock

from flowmocap.errors import FolderBusyError, InputError


class FolderLock:
    """The exclusive lock of a result folder; a context manager.

    Args:
        out_dir: the result folder (created if missing).

    Raises (on entering):
        FolderBusyError: another run holds it.
        InputError: the folder cannot be created or written.
    """

    def __init__(self, out_dir: str | Path):
        self.out_dir = Path(out_dir)
        self._lock: filelock.BaseFileLock | None = None
        self._made = False

    def __enter__(self) -> FolderLock:
        self._made = not self.out_dir.exists()
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            raise InputError(f"{self.out_dir} is a file; --out must be a folder (new, or a flowmocap result).") from None
        except OSError as e:
            raise InputError(f"cannot create the result folder {self.out_dir}: {e.strerror or e}.") from None
        lock = filelock.FileLock(self.out_dir / ".lock", timeout=0)
        try:
            lock.acquire()
        except filelock.Timeout:
            raise FolderBusyError(f"{self.out_dir} is in use by another flowmocap run ({_owner(self.out_dir)}); "
                                  "wait for it to end or choose another folder.") from None
        except OSError as e:
            raise InputError(f"cannot write to the result folder {self.out_dir}: {e.strerror or e}.") from None
        self._lock = lock
        try:
            (self.out_dir / ".lock.json").write_text(json.dumps(
                {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%d %H:%M:%S")}))
        except OSError as e:
            lock.release()
            self._lock = None
            raise InputError(f"cannot write to the result folder {self.out_dir}: {e.strerror or e}.") from None
        return self

    def __exit__(self, *exc) -> None:
        if self._lock is not None:
            (self.out_dir / ".lock.json").unlink(missing_ok=True)
            self._lock.release()
            self._lock = None
            if self._made and {p.name for p in self.out_dir.iterdir()} <= {".lock"}:
                # a folder this lock made for a run that wrote nothing (refused at once): not left behind
                (self.out_dir / ".lock").unlink(missing_ok=True)
                try:
                    self.out_dir.rmdir()
                except OSError:  # something appeared in it meanwhile: it stays
                    pass


def is_locked(out_dir: str | Path) -> bool:
    """Whether a run holds ``out_dir`` now."""
    path = Path(out_dir) / ".lock"
    if not path.exists():
        return False
    lock = filelock.FileLock(path, timeout=0)
    try:
        lock.acquire()
    except filelock.Timeout:
        return True
    except OSError:
        return False
    lock.release()
    return False


def _owner(out_dir: Path) -> str:
    try:
        info = json.loads((out_dir / ".lock.json").read_text())
        return f"pid {info['pid']} on {info['host']}, since {info['since']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "owner unknown"

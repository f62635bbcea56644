"""The person detector in a process of its own: ``python -m flowmocap.vision.detect_worker TASK``.

:func:`~flowmocap.vision.auto.detect_sequence` runs MediaPipe here, one stretch of
:data:`~flowmocap.vision.auto.DETECT_CHUNK` frames per process, so the tracking process
never loads it and the memory MediaPipe gathers while it runs is given back when each
stretch ends. ``TASK`` is a pickle the parent wrote (the sequence, the detectors' settings,
the stretch, where to store its candidates: :func:`~flowmocap.vision.auto.run_chunk`).
Imports no torch (``import flowmocap`` loads the tracker lazily).

Exit status 0 with the stretch stored; 3 with ``TASK``'s ``.error.json`` beside it
(``{"type", "message"}`` of one of the project's errors, raised again by the parent);
130 when interrupted; anything else is a crash the parent reports as a
:class:`~flowmocap.errors.DetectorError`.
"""

from __future__ import annotations

import json
import pickle
import sys
from pathlib import Path


def main(argv: list[str]) -> int:
    from flowmocap.errors import FlowMocapError
    from flowmocap.vision.auto import WRITE_FAILED, run_chunk

    import signal

    job = Path(argv[0])
    # SIGTERM (sent when the tracking process is gone, or by a service manager) as an exit, so the exit
    # handlers run (the heavy model's temporary resource folder is removed by one)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    _end_with_parent()
    _native_logs_to_devnull()
    try:
        with open(job, "rb") as f:
            task = pickle.load(f)
        run_chunk(task)
    except FlowMocapError as e:
        job.with_name(job.name[: -len(".pkl")] + ".error.json").write_text(
            json.dumps({"type": type(e).__name__, "message": str(e)}))
        return 3
    except OSError as e:  # a full disk or a file size limit while the stretch's detections are written
        try:
            job.with_name(job.name[: -len(".pkl")] + ".error.json").write_text(json.dumps(
                {"type": "OutputError", "message": f"could not write the detections ({e.filename or 'a file'}: "
                 f"{e.strerror or e})"}))
        except OSError:  # the disk is too full even for that: the exit status says it
            pass
        return WRITE_FAILED
    except KeyboardInterrupt:
        return 130
    return 0



#: The environment variable the parent sets to its process id (:func:`_end_with_parent`).
PARENT_ENV = "FLOWMOCAP_DETECT_PARENT"


def _end_with_parent() -> None:
    """:func:`end_with_parent` with the parent's id from :data:`PARENT_ENV`: a tracking
    process killed outright (``kill -9``, SIGTERM) used to leave its detector running on,
    outside the result folder's lock."""
    import os

    parent = os.environ.get(PARENT_ENV)
    end_with_parent(int(parent) if parent and parent.isdigit() else None)


def end_with_parent(parent: int | None = None) -> None:
    """Have the kernel stop this process (SIGTERM) when the one that started it ends
    (Linux's ``PR_SET_PDEATHSIG``). A ``parent`` already gone by now (its id no longer this
    process's parent) ends it at once (exit 130). Elsewhere than Linux: nothing (the
    parent's Ctrl-C still reaches the process group).

    Args:
        parent: the process id of the parent that started this one, or None (not checked).
    """
    import os
    import signal

    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if parent is not None and os.getppid() != parent:
        sys.exit(130)


def _native_logs_to_devnull() -> None:
    """Send what native code writes to the standard error (MediaPipe's and TensorFlow
    Lite's log lines, from threads of their own) to /dev/null, and keep Python's own
    standard error (the progress bar, a traceback) on the parent's."""
    import os

    try:
        keep = os.dup(2)
        sys.stderr = os.fdopen(keep, "w", buffering=1, encoding=sys.stderr.encoding, errors="backslashreplace")
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 2)
        os.close(null)
    except OSError:  # no standard error to begin with: nothing to quiet
        pass


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

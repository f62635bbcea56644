"""flowmocap: 3D human motion and shape from monocular video via optical flow.

    import flowmocap
    result = flowmocap.track("video.mp4", out="result/")   # automatic masks, joints, init, camera
    result.poses, result.trans, result.joints3d             # (T, 72) rad, (T, 3) m, (T, 24, 3) m
    same = flowmocap.load_result("result/")

Layers (a layer imports only from layers above it): geometry, body, render, vision, fit,
io, export, synth, pipeline, eval, viz, commands, cli. See the README and docs/.
"""

import os as _os


def _own_folder(name: str, home_cache: str | None) -> str | None:
    """A folder for ``name`` that only this user can write: ``home_cache/flowmocap/name``
    (where ``home_cache`` is given), else ``flowmocap-name-UID`` in the temporary folder, else a new temporary folder of
    this process's own (None where none can be made). A folder found there must be a real
    folder of this user's that no one else can write (numba loads pickles from its own)."""
    import stat
    import tempfile

    uid = _os.getuid() if hasattr(_os, "getuid") else None
    for folder in ([_os.path.join(home_cache, "flowmocap", name)] if home_cache else []) + [
            _os.path.join(tempfile.gettempdir(), f"flowmocap-{name}-{uid if uid is not None else 0}")]:
        try:
            _os.makedirs(folder, mode=0o700, exist_ok=True)
            st = _os.lstat(folder)
        except OSError:
            continue
        if (stat.S_ISDIR(st.st_mode) and (uid is None or st.st_uid == uid) and not st.st_mode & 0o022
                and _os.access(folder, _os.W_OK)):
            return folder
    try:  # a folder of this process's own; its contents are made again in the next
        return tempfile.mkdtemp(prefix=f"flowmocap-{name}-")
    except OSError:
        return None


def _numba_cache_dir() -> str | None:
    """Where numba should keep the compiled kernels (``@njit(cache=True)``) when it could
    not itself: numba writes next to the sources, else under the user's cache folder, and
    fails on the first kernel (``--help`` included) where neither can be written, as in a
    container whose site-packages and home are read-only. None: numba's own choice works
    (or the user set ``NUMBA_CACHE_DIR``)."""
    if _os.environ.get("NUMBA_CACHE_DIR") or _os.access(_os.path.dirname(__file__), _os.W_OK):
        return None
    home_cache = _os.environ.get("XDG_CACHE_HOME") or _os.path.join(_os.path.expanduser("~"), ".cache")
    return _own_folder("numba", home_cache)


def _matplotlib_config_dir() -> str | None:
    """Matplotlib's config and cache folder where the home's cannot be written (it warns on
    every run otherwise: "mkdir -p failed ... set the MPLCONFIGDIR"); None where it can, or
    the user set ``MPLCONFIGDIR``."""
    if _os.environ.get("MPLCONFIGDIR"):
        return None
    config = _os.environ.get("XDG_CONFIG_HOME") or _os.path.join(_os.path.expanduser("~"), ".config")
    probe = config
    while not _os.path.exists(probe) and _os.path.dirname(probe) != probe:  # the nearest folder that exists
        probe = _os.path.dirname(probe)
    if _os.access(probe, _os.W_OK):
        return None
    return _own_folder("matplotlib", None)


if (_cache := _numba_cache_dir()) is not None:
    _os.environ["NUMBA_CACHE_DIR"] = _cache  # read when numba is first imported (flowmocap imports it lazily)
    if "numba" in __import__("sys").modules:  # imported before flowmocap: read its settings again
        __import__("numba.core.config").core.config.reload_config()
if "matplotlib" not in __import__("sys").modules and (_mpl := _matplotlib_config_dir()) is not None:
    _os.environ["MPLCONFIGDIR"] = _mpl  # read when matplotlib is first imported

from flowmocap.errors import (  # noqa: E402  (after the cache folder is chosen)
    DataError,
    FlowMocapError,
    InputError,
    ModelFileError,
    NoPersonError,
    OptimizationError,
)
from flowmocap.version import __version__  # noqa: E402

#: Imported on first use (PEP 562), so that ``import flowmocap.vision...`` in a helper
#: process (the person detector's, :mod:`flowmocap.vision.detect_worker`) does not load
#: the tracker and torch.
_LAZY = {"track": "flowmocap.pipeline", "load_result": "flowmocap.pipeline", "Result": "flowmocap.pipeline"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'flowmocap' has no attribute {name!r}")


__all__ = [
    "__version__",
    "track",
    "load_result",
    "Result",
    "FlowMocapError",
    "InputError",
    "ModelFileError",
    "DataError",
    "NoPersonError",
    "OptimizationError",
]

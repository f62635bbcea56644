"""The project's exception hierarchy.

Every error a user can cause (a missing file, a model file of the wrong kind, bad
input sizes, no person found, a diverging optimiser) is raised as one of these, with a
message that says what went wrong and what to do about it.
"""

from __future__ import annotations


class FlowMocapError(Exception):
    """Base class of every error flowmocap raises on purpose. ``exit_code`` is the
    command line's exit status for it (see :data:`EXIT_CODES`)."""

    exit_code = 2


class InputError(FlowMocapError, ValueError):
    """Arguments of the wrong shape, type, size or value."""


class ModelFileError(FlowMocapError):
    """A body model file is missing, unreadable or not a body model of a known kind."""


class DataError(FlowMocapError):
    """An input file (video, frames, masks, mocap, sequence folder) is missing or corrupt."""


class NoPersonError(FlowMocapError):
    """No person could be found where one was needed (empty mask, no 2D joints)."""


class OptimizationError(FlowMocapError):
    """The optimiser produced non-finite values or failed to make progress."""

    exit_code = 3


class FolderBusyError(FlowMocapError):
    """Another run holds the result folder (its lock)."""

    exit_code = 4


class OutputError(FlowMocapError):
    """A result could not be written (no space, no permission, a file in the way)."""

    exit_code = 5


class DetectorError(FlowMocapError):
    """The person detector's own process failed (killed, e.g. out of memory, or crashed);
    the stretches of frames it finished are kept and a rerun (``--resume``) goes on."""

    exit_code = 7


#: The command line's exit statuses (also in docs/errors.md).
EXIT_CODES = {
    0: "success",
    1: "an unexpected error (a bug: please report it with the traceback)",
    2: "bad input or usage: a missing or corrupt file, a wrong setting, no person found (InputError, DataError, "
       "ModelFileError, NoPersonError)",
    3: "the optimiser failed (OptimizationError); the frames finished before stay in the result folder",
    4: "the result folder is in use by another run (FolderBusyError)",
    5: "a result file could not be written: disk full, no permission (OutputError); finished frames are kept",
    6: "some inputs of a batch failed (flowmocap track with several inputs); the others finished",
    7: "the person detector's process failed (DetectorError); the frames it finished are kept and --resume continues",
    130: "interrupted (Ctrl-C); the finished frames are kept and --resume continues",
}


def check_path(value, name: str, what: str = "a file or folder") -> None:
    """Refuse an argument that should be a path but is not one (``InputError`` naming the
    argument, where pathlib would raise a bare ``TypeError`` deep inside).

    Args:
        value: the argument.
        name: its name, for the message.
        what: what the path should point to, for the message.
    """
    import os

    if not isinstance(value, (str, os.PathLike)):
        raise InputError(f"{name} must be the path of {what} (a str or a Path); got {type(value).__name__}.")


__all__ = [
    "FlowMocapError",
    "InputError",
    "ModelFileError",
    "DataError",
    "NoPersonError",
    "OptimizationError",
    "FolderBusyError",
    "OutputError",
    "DetectorError",
    "EXIT_CODES",
    "check_path",
]

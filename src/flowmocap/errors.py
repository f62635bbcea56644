"""The project's exception hierarchy.

Every error a user can cause (a missing file, a model file of the wrong kind, bad
input sizes, no person found, a diverging optimiser) is raised as one of these, with a
message that says what went wrong and what to do about it.
"""

from __future__ import annotations


class FlowMocapError(Exception):
    """Base class of every error flowmocap raises on purpose."""


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


__all__ = [
    "FlowMocapError",
    "InputError",
    "ModelFileError",
    "DataError",
    "NoPersonError",
    "OptimizationError",
]

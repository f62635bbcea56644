"""One entry point for body motions: a mocap file (retargeted), an AMASS ``.npz`` or a
built-in motion."""

from __future__ import annotations

from pathlib import Path

from flowmocap.errors import InputError
from flowmocap.io.amass import read_amass_npz
from flowmocap.io.builtin_walk import BUILTIN_MOTIONS, builtin_walk
from flowmocap.io.mocap import read_mocap
from flowmocap.io.retarget import retarget
from flowmocap.io.smpl_motion import SmplMotion

__all__ = ["load_motion", "BUILTIN_PREFIX"]

BUILTIN_PREFIX = "builtin:"


def load_motion(
    source: str | Path,
    model,
    betas=None,
    fps: float | None = None,
    frames: int | None = None,
    facing: float = 0.0,
    asf: str | Path | None = None,
) -> SmplMotion:
    """SMPL motion from ``builtin:walk``, a ``.bvh`` file, a CMU ``.amc`` file or an
    AMASS-layout ``.npz`` (SMPL parameters, e.g. a ``flowmocap export --format npz``).

    Args:
        source: ``"builtin:walk"`` or a mocap file path (``.amc``: its ``.asf`` is found
            next to it unless ``asf`` is given).
        model: the :class:`~flowmocap.body.BodyModel` to move.
        betas: ``(<=num_betas,)`` body shape (default: mean shape).
        fps: frame rate in Hz (mocap is resampled; default: the file's own rate, 30 Hz
            for built-in motions).
        frames: number of frames of a built-in motion (default 4 s worth); mocap files
            give all their frames.
        facing: heading at the start, radians from +z towards +x (0 = walking along +z).
        asf: ASF skeleton for an ``.amc`` file.

    Returns:
        :class:`~flowmocap.io.SmplMotion`, ground plane ``y = 0``, frame-0 pelvis above
        the origin.

    Raises:
        InputError: unknown built-in motion. DataError: unreadable mocap file.
    """
    text = str(source)
    if text.startswith(BUILTIN_PREFIX):
        name = text[len(BUILTIN_PREFIX):]
        if name not in BUILTIN_MOTIONS:
            raise InputError(
                f"unknown built-in motion {text!r}; available: "
                + ", ".join(BUILTIN_PREFIX + n for n in BUILTIN_MOTIONS)
            )
        rate = 30.0 if fps is None else float(fps)
        return builtin_walk(model, betas=betas, fps=rate, frames=frames, facing=facing)
    if Path(text).suffix.lower() == ".npz":
        motion = read_amass_npz(text, model)
        if fps is not None and abs(float(fps) - motion.fps) > 1e-6:
            raise InputError(f"{text} holds SMPL parameters at {motion.fps:g} fps and is not resampled; "
                             f"ask for fps={motion.fps:g} (or leave it unset).")
        return motion
    clip = read_mocap(source, asf=asf)
    return retarget(clip, model, betas=betas, fps=fps, facing=facing)

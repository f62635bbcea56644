"""Marker trajectories of the fitted body, for biomechanics tools.

Two formats, each holding named points frame by frame: by default the 24 body joints, named by
:data:`flowmocap.body.skeleton.JOINT_NAMES` (``pelvis``, ``left_hip``, ...), or another marker
set of :mod:`flowmocap.export.marker_sets` (Pose2Sim's HALPE_26 keypoints):

- ``.trc`` (Motion Analysis's track-row-column text, read by OpenSim, Pose2Sim and most
  biomechanics software): tab-separated, metres, the export frame as it is (the ground
  frame is y up, OpenSim's own convention).
- ``.c3d`` (the binary motion-capture standard: Vicon, Qualisys, Visual3D, Mokka, Blender's
  importer), written with the ``ezc3d`` library: millimetres (the unit motion-capture
  systems write and some readers assume) and **z up**, as labs record, turned from the
  y-up export frame by +90 degrees about x (``(x, y, z) -> (x, -z, y)``, as the AMASS
  export). The file's ``POINT:UNITS`` says ``mm``.

In the ground frame the C3D also carries the foot contacts
(:mod:`flowmocap.export.world`: rough hints) as gait events, "Foot Strike" and "Foot Off"
for the left and right foot. Frame numbers start at 1 in both, as the formats expect; the input video's frame number of
the first one is stored, plus one (TRC ``OrigDataStartFrame``, the C3D header's first
frame), so a clip tracked from frame 200 can be lined up with the video. Both are written atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from flowmocap.atomic import atomic_write
from flowmocap.errors import InputError

__all__ = ["write_trc", "write_c3d", "contact_events", "C3D_UNITS_PER_METRE", "C3D_MAX_FRAME"]

#: C3D points are written in millimetres.
C3D_UNITS_PER_METRE = 1000.0

#: The last frame number a C3D header can hold (16 bits): 18 minutes at 60 fps. ``ezc3d``
#: would cut a longer motion there without a word, so :func:`write_c3d` refuses it.
C3D_MAX_FRAME = 65535


def _checked(joints: np.ndarray, names, fps: float, missing_ok: bool = False) -> np.ndarray:
    j = np.asarray(joints, np.float64)
    if j.ndim != 3 or j.shape[2] != 3 or j.shape[0] < 1 or j.shape[1] != len(names):
        raise InputError(f"marker trajectories must be (T >= 1, {len(names)}, 3) metres, one per name; "
                         f"got shape {j.shape}.")
    if missing_ok:
        if np.isinf(j).any():
            raise InputError("marker trajectories hold infinite positions; a missing marker is NaN.")
    elif not np.all(np.isfinite(j)):
        raise InputError("marker trajectories hold NaN or infinite positions; the result is damaged: track again.")
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"the frame rate must be a positive number of frames per second; got {fps!r}.")
    return j


def write_trc(path: str | Path, joints: np.ndarray, names, fps: float, first_frame: int = 0,
              missing_ok: bool = False) -> Path:
    """Write joint trajectories as an OpenSim ``.trc`` file, atomically.

    Args:
        path: output file (``.trc``).
        joints: ``(T, M, 3)`` positions in metres.
        names: ``M`` marker names (no white space in them).
        fps: frames per second (Hz); frame ``k`` is at ``k / fps`` seconds.
        first_frame: the input video's frame number of frame 0 (stored 1-based as
            ``OrigDataStartFrame``).
        missing_ok: allow NaN positions (a marker missing in a frame), written as ``NaN``,
            which OpenSim's tools leave out of that frame.

    Returns:
        The path written.

    Raises:
        InputError: wrong shapes, non-finite positions (NaN allowed with ``missing_ok``)
            or frame rate.
    """
    j = _checked(joints, names, fps, missing_ok)
    names = [str(n) for n in names]
    if any(not n or any(c.isspace() for c in n) for n in names):
        raise InputError(f"TRC marker names must be non-empty and hold no white space; got {names}.")
    T, M, _ = j.shape
    path = Path(path)
    rate = f"{float(fps):.6g}"
    head = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate}\t{rate}\t{T}\t{M}\tm\t{rate}\t{int(first_frame) + 1}\t{T}",
        "Frame#\tTime\t" + "\t\t\t".join(names),
        "\t\t" + "\t".join(f"X{m}\tY{m}\tZ{m}" for m in range(1, M + 1)),
        "",
    ]

    def write(tmp):
        with open(tmp, "w", newline="\n") as f:
            f.write("\n".join(head) + "\n")
            rows = np.round(j.reshape(T, -1), 6) + 0.0  # + 0.0: no "-0.000000"
            for k in range(T):
                f.write(f"{k + 1}\t{k / fps:.6f}\t" + "\t".join("NaN" if v != v else f"{v:.6f}" for v in rows[k])
                        + "\n")

    atomic_write(path, write)
    return path


def contact_events(contacts: np.ndarray) -> list[tuple[int, str, str]]:
    """Gait events from per-frame foot contacts: a foot strike where a foot comes onto the
    floor, a foot off where it leaves it (none at the first frame: its state has no start).

    Args:
        contacts: ``(T, 2)`` bool, left and right foot on the floor per frame.

    Returns:
        ``(frame, side, label)`` sorted by frame: ``frame`` the 0-based index into the
        motion, ``side`` ``"Left"`` or ``"Right"``, ``label`` ``"Foot Strike"`` or ``"Foot Off"``
        (the names Vicon, Visual3D and Mokka use).
    """
    c = np.asarray(contacts, bool).reshape(-1, 2)
    events = []
    for side, name in enumerate(("Left", "Right")):
        change = np.flatnonzero(c[1:, side] != c[:-1, side]) + 1
        events += [(int(k), name, "Foot Strike" if c[k, side] else "Foot Off") for k in change]
    return sorted(events)


def _check_written_c3d(own: str, frames: int, points: int, path: Path) -> None:
    """Check that a just-written C3D file holds all it should: ezc3d does not report a failed
    write (a full disk, a file size limit) and would leave a cut-off file, and reading such a
    file back with ezc3d crashes the process. So the file's own header is read (C3D's
    512-byte header block, 16-bit little-endian words: 2 points per frame, 4-5 first and last
    frame, 7-8 the scale, negative for float data, 9 the data's first 512-byte block) and the
    file must be as long as the data it announces.

    Args:
        own: the written file.
        frames, points: the frames and markers it must hold.
        path: the name it is written for, for the message.

    Raises:
        OSError: naming ``path``, when the file is shorter or announces other data.
    """
    import errno
    import struct

    size = os.path.getsize(own)
    whole = size >= 512
    if whole:
        with open(own, "rb") as f:
            head = f.read(512)
        words = struct.unpack("<256H", head)
        scale = struct.unpack("<f", head[12:16])[0]
        n_points, analog, first, last, data_block = words[1], words[2], words[3], words[4], words[8]
        per_value = 4 if scale < 0 else 2
        need = (data_block - 1) * 512 + (last - first + 1) * (4 * n_points + analog) * per_value
        whole = n_points == points and last - first + 1 == frames and data_block >= 2 and size >= need
    if not whole:
        raise OSError(errno.EIO, f"the C3D file came out {size} bytes, short of what it holds (a full disk or a "
                                 "file size limit?); nothing was put under the name", str(path))


def write_c3d(path: str | Path, joints: np.ndarray, names, fps: float, first_frame: int = 0,
              up: str = "y", contacts: np.ndarray | None = None, seen: np.ndarray | None = None) -> Path:
    """Write joint trajectories as a ``.c3d`` file (via ``ezc3d``), atomically.

    Args:
        path: output file (``.c3d``).
        joints: ``(T, M, 3)`` positions in metres, in a frame whose up axis is ``up``.
        names: ``M`` marker names.
        fps: frames per second (Hz).
        first_frame: the input video's frame number of frame 0 (the file's first frame
            is this plus 1).
        up: ``"y"`` (the joints are y up: turned to z up on the way out) or ``"none"``
            (written as given, e.g. a camera-frame export).
        contacts: optional ``(T, 2)`` bool, left/right foot on the floor per frame: written
            as the file's gait events (:func:`contact_events`), at ``(first_frame + k) / fps``
            seconds, the time of the file's frame ``first_frame + k + 1``; none in unseen frames.
        seen: optional ``(T,)`` bool, False for frames in which the person was not seen
            (their points were not measured but carried by the flow, held or filled in):
            written as invalid points (residual -1), the gaps a motion-capture tool fills
            by its own means.

    Returns:
        The path written. Points are in millimetres (``POINT:UNITS`` ``mm``), the z-up axes
        named in ``POINT:X_SCREEN`` ``+X`` and ``POINT:Y_SCREEN`` ``+Z`` (Vicon's, Mokka's).

    Raises:
        InputError: wrong shapes, non-finite positions or frame rate, unknown ``up``, or a
            last frame number past :data:`C3D_MAX_FRAME`.
    """
    import ezc3d

    from flowmocap.io.amass import Y_UP_TO_Z_UP

    j = _checked(joints, names, fps)
    if up not in ("y", "none"):
        raise InputError(f"up must be 'y' or 'none'; got {up!r}.")
    if up == "y":
        j = j @ Y_UP_TO_Z_UP.T
    T, M, _ = j.shape
    if int(first_frame) + T > C3D_MAX_FRAME:
        raise InputError(
            f"a C3D file numbers its frames in 16 bits, up to {C3D_MAX_FRAME}, and this motion runs to frame "
            f"{int(first_frame) + T}; export it as trc or json, or track a shorter stretch (--frames A:B).")
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [float(fps)]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = tuple(str(n) for n in names)
    c3d["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    points = np.ones((4, M, T))
    points[:3] = np.transpose(j * C3D_UNITS_PER_METRE, (2, 1, 0))
    c3d["data"]["points"] = points
    seen = np.ones(T, bool) if seen is None else np.asarray(seen, bool)
    if seen.shape != (T,):
        raise InputError(f"seen must be (T,) = ({T},), one flag per frame; got {seen.shape}.")
    if not seen.all():  # the frames without the person: invalid points (residual -1)
        c3d["data"]["meta_points"] = {"residuals": np.where(seen, 0.0, -1.0)[None, None, :].repeat(M, 1),
                                      "camera_masks": np.zeros((7, M, T), bool)}
    c3d["header"]["points"]["first_frame"] = int(first_frame)
    c3d.add_parameter("MANUFACTURER", "SOFTWARE", "flowmocap")
    if up == "y":  # the axes the file's points are in, for the tools that read them (Vicon, Mokka, BTK)
        c3d.add_parameter("POINT", "X_SCREEN", "+X")
        c3d.add_parameter("POINT", "Y_SCREEN", "+Z")
    if contacts is not None:
        if np.shape(contacts) != (T, 2):
            raise InputError(f"contacts must be (T, 2) = ({T}, 2), one left/right pair per frame; "
                             f"got {np.shape(contacts)}.")
        for k, side, label in contact_events(contacts):
            if not seen[k]:  # a contact of frames without the person is a guess, not an event
                continue
            c3d.add_event([0, (int(first_frame) + k) / float(fps)], context=side, label=label,
                          description="from the fitted foot's contact with the floor (a rough estimate)")
    path = Path(path)

    def write(tmp):
        own = tmp + ".c3d"  # ezc3d adds .c3d to a name without it
        try:
            c3d.write(own)
            _check_written_c3d(own, T, M, path)
            os.replace(own, tmp)
        finally:
            if os.path.exists(own):
                os.remove(own)

    atomic_write(path, write)
    return path

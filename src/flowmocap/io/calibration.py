"""Multi-camera calibration files: Qualisys ``.qca.txt`` (XML), as Pose2Sim ships them.

:func:`read_qualisys_calibration` returns one
:class:`~flowmocap.geometry.triangulate.CalibratedCamera` per ``<camera>``, converted to
the project's conventions:

- ``focalLengthU/V`` and ``centerPointU/V`` are in 1/64 pixel (divided by 64); the
  principal point gets the project's +0.5 pixel-centre offset, and is taken relative to
  the ``fov_video`` window's top-left corner;
- ``<transform>``: the camera centre ``x, y, z`` in world millimetres and a row-major
  matrix ``M`` whose rows are the camera's axes in the world for a camera with x right,
  y up, z backward. For OpenCV axes (x right, y down, z forward): ``R = diag(1, -1, -1) @ M``
  and ``t = -R @ C / 1000`` (metres). (Using ``M``'s transpose instead reprojects
  hundreds of pixels off; the tests check the convention on the Pose2Sim recording.)
- ``radialDistortion1/2/3``, ``tangentalDistortion1/2`` are OpenCV's ``k1, k2, k3, p1, p2``;
- the image size is the ``fov_video`` window (``right - left + 1`` x ``bottom - top + 1``).

The world keeps the file's axes (z up for Qualisys), in metres.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from flowmocap.errors import DataError, InputError
from flowmocap.geometry.triangulate import CalibratedCamera

__all__ = ["read_qualisys_calibration", "parse_qualisys_calibration"]

_INTRINSIC = ("focalLengthU", "focalLengthV", "centerPointU", "centerPointV", "radialDistortion1",
              "radialDistortion2", "radialDistortion3", "tangentalDistortion1", "tangentalDistortion2")
_TRANSFORM = ("x", "y", "z") + tuple(f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3))


def read_qualisys_calibration(path: str | Path) -> dict[str, CalibratedCamera]:
    """The cameras of a Qualisys calibration file, by serial (``{"cam01": camera, ...}``,
    in the file's order).

    Raises:
        DataError: the file is missing, not XML, or not a Qualisys calibration (the
            message names the camera and attribute at fault).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8", errors="strict")
    except FileNotFoundError:
        raise DataError(f"calibration file {p} does not exist; give the Qualisys .qca.txt of the recording.") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"cannot read the calibration file {p} ({e}); give the Qualisys .qca.txt of the "
                        "recording.") from None
    return parse_qualisys_calibration(text, source=str(p))


def parse_qualisys_calibration(text: str, source: str = "the calibration") -> dict[str, CalibratedCamera]:
    """:func:`read_qualisys_calibration` on the file's text (XML)."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        raise DataError(f"{source} is not valid XML ({e}); it should be a Qualisys calibration export "
                        "(<calibration><cameras><camera ...>).") from None
    cams = root.findall("./cameras/camera") if root.tag == "calibration" else []
    if not cams:
        raise DataError(f"{source} holds no <calibration><cameras><camera> elements; it is not a Qualisys "
                        "calibration export (.qca.txt).")
    out: dict[str, CalibratedCamera] = {}
    for k, cam in enumerate(cams):
        name = cam.get("serial") or f"camera{k + 1}"
        where = f"{source}, camera {name!r}"
        if name in out:
            raise DataError(f"{where}: the serial appears twice; each camera needs its own serial.")
        intr = _numbers(cam.find("intrinsic"), _INTRINSIC, f"{where}, <intrinsic>")
        tr = _numbers(cam.find("transform"), _TRANSFORM, f"{where}, <transform>")
        fov = _numbers(cam.find("fov_video"), ("left", "top", "right", "bottom"), f"{where}, <fov_video>")
        width, height = int(fov["right"] - fov["left"] + 1), int(fov["bottom"] - fov["top"] + 1)
        K = np.array([[intr["focalLengthU"] / 64.0, 0.0, intr["centerPointU"] / 64.0 - fov["left"] + 0.5],
                      [0.0, intr["focalLengthV"] / 64.0, intr["centerPointV"] / 64.0 - fov["top"] + 0.5],
                      [0.0, 0.0, 1.0]])
        M = np.array([[tr[f"r{i}{j}"] for j in (1, 2, 3)] for i in (1, 2, 3)])
        R = np.diag([1.0, -1.0, -1.0]) @ M
        C = np.array([tr["x"], tr["y"], tr["z"]]) / 1000.0
        dist = np.array([intr["radialDistortion1"], intr["radialDistortion2"], intr["tangentalDistortion1"],
                         intr["tangentalDistortion2"], intr["radialDistortion3"]])
        try:
            out[name] = CalibratedCamera(name, K, dist, R, -R @ C, width, height)
        except InputError as e:
            raise DataError(f"{where}: {e}; the file is corrupt or not in the Qualisys convention.") from None
    return out


def _numbers(elem, keys: tuple[str, ...], where: str) -> dict[str, float]:
    if elem is None:
        raise DataError(f"{where} is missing; the file is not a complete Qualisys calibration.")
    out = {}
    for k in keys:
        v = elem.get(k)
        try:
            out[k] = float(v)
        except (TypeError, ValueError):
            raise DataError(f"{where}: attribute {k} is {'missing' if v is None else repr(v)}, not a number; "
                            "the file is corrupt or not a Qualisys calibration.") from None
        if not np.isfinite(out[k]):
            raise DataError(f"{where}: attribute {k} is not finite ({v}).")
    return out

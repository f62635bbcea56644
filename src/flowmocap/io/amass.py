"""AMASS-layout ``.npz``: the SMPL ecosystem's motion file, written and read back.

Keys written (AMASS's, Mahmood et al. 2019): ``poses (T, 156)`` axis-angle radians in
SMPL-H order (root, 21 body joints, 30 finger joints: zero here, we fit none),
``trans (T, 3)`` metres, ``betas (10,)``, ``gender`` (string), ``mocap_framerate``
(Hz), and the SMPL-X-era names ``root_orient (T, 3)``, ``pose_body (T, 63)``,
``pose_hand (T, 90)``, ``mocap_frame_rate``. AMASS worlds are **z up**; the y-up motion
is turned by +90 degrees about x (``(x, y, z) -> (x, -z, y)``) on the way out and back
on the way in. SMPL's own two hand joints (22, 23), which SMPL-H replaces by fingers,
are kept in ``smpl_hand_pose (T, 6)`` so :func:`read_amass_npz` restores the exact
72-value pose; ``surface_model_type`` is ``"smpl"``. The betas are the fitted body
model's own shape coefficients (the real SMPL's only when tracking used SMPL).
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from flowmocap.atomic import atomic_write_npz
from flowmocap.errors import DataError
from flowmocap.io.smpl_motion import SmplMotion, rotate_motion

__all__ = ["Y_UP_TO_Z_UP", "write_amass_npz", "read_amass_npz"]

#: +90 degrees about x: a y-up frame to AMASS's z-up one.
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def write_amass_npz(path: str | Path, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray, gender: str,
                    fps: float, rest_pelvis: np.ndarray, **extra) -> Path:
    """Write a y-up SMPL motion in the AMASS layout (z up), atomically (an interrupted
    write leaves the old file, or none, never part of one).

    Args:
        path: output ``.npz``.
        poses: ``(T, 72)`` SMPL axis-angle in radians, y-up world.
        trans: ``(T, 3)`` metres, y-up world.
        betas: ``(10,)`` shape coefficients.
        gender: ``"neutral"``, ``"male"`` or ``"female"``.
        fps: frames per second (Hz).
        rest_pelvis: ``(3,)`` pelvis of the shaped rest pose in metres (needed to turn
            the motion, see :func:`flowmocap.io.smpl_motion.rotate_motion`).
        **extra: more arrays to store (e.g. ``frame_index``).

    Returns:
        The path written.
    """
    p, t = rotate_motion(poses, trans, rest_pelvis, Y_UP_TO_Z_UP)
    T = p.shape[0]
    smplh = np.zeros((T, 156), np.float64)
    smplh[:, :66] = p[:, :66]
    path = Path(path)

    atomic_write_npz(path, poses=smplh, trans=t, betas=np.asarray(betas, np.float64).reshape(-1),
                     gender=np.array(str(gender)), mocap_framerate=np.array(float(fps)),
                     mocap_frame_rate=np.array(float(fps)), root_orient=p[:, :3], pose_body=p[:, 3:66],
                     pose_hand=smplh[:, 66:], smpl_hand_pose=p[:, 66:72], surface_model_type=np.array("smpl"),
                     **extra)
    return path


def read_amass_npz(path: str | Path, model=None):
    """Read an AMASS-layout ``.npz`` (ours or AMASS's own) as a y-up SMPL motion.

    Args:
        path: the ``.npz`` file with ``poses (T, 72 | 156 | 165)``, ``trans (T, 3)``,
            ``betas``, ``gender`` and ``mocap_framerate`` (or ``mocap_frame_rate``).
        model: the body model the betas belong to (default: the bundled default body
            of the file's gender); its rest pelvis is needed to turn the motion to y up.

    Returns:
        :class:`~flowmocap.io.SmplMotion` in a y-up world: ``poses (T, 72)`` (SMPL's hand
        joints from ``smpl_hand_pose`` when present, else zero), ``trans (T, 3)``,
        ``betas`` (first 10), ``gender``, ``fps``.

    Raises:
        DataError: missing or unreadable file, or keys of the wrong shape.
    """
    import torch

    from flowmocap.body import load_body_model

    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise DataError(f"AMASS file {path} does not exist.") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:  # cut off or empty: the last two
        raise DataError(f"cannot read {path} as an AMASS .npz ({type(e).__name__}: {e}).") from None
    if "energy_names" in data and "frame_index" in data:  # a flowmocap result's own motion.npz: y down, not z up
        raise DataError(f"{path} is a flowmocap result's motion.npz, not an AMASS file; export it as one with "
                        "`flowmocap export RESULT -f npz` (motion_amass.npz), or read it with flowmocap.load_result.")
    missing = [k for k in ("poses", "trans") if k not in data]
    if missing:
        raise DataError(f"{path} lacks {', '.join(missing)}; an AMASS file has poses, trans, betas, "
                        "gender and mocap_framerate.")

    def numbers(key, default=None):
        try:
            a = np.asarray(data.get(key, default), np.float64)
        except (TypeError, ValueError):
            raise DataError(f"{path}: {key} is not numbers (dtype {np.asarray(data[key]).dtype}).") from None
        if not np.isfinite(a).all():
            raise DataError(f"{path}: {key} holds NaN or infinite values; the file is damaged.")
        return a

    poses = numbers("poses")
    if poses.ndim != 2 or poses.shape[1] not in (72, 156, 165):
        raise DataError(f"{path}: poses must be (T, 72), (T, 156) or (T, 165); got {poses.shape}.")
    T = poses.shape[0]
    smpl = np.zeros((T, 72))
    if poses.shape[1] == 72:
        smpl[:] = poses
    else:
        smpl[:, :66] = poses[:, :66]
        if "smpl_hand_pose" in data and np.shape(data["smpl_hand_pose"]) == (T, 6):
            smpl[:, 66:] = numbers("smpl_hand_pose")
    trans = numbers("trans")
    if trans.shape != (T, 3):
        raise DataError(f"{path}: trans must be (T, 3) = ({T}, 3), one per pose; got {trans.shape}.")
    betas = numbers("betas", np.zeros(10)).reshape(-1)[:10]
    gender = str(data.get("gender", "neutral"))
    gender = gender if gender in ("neutral", "male", "female") else "neutral"
    rate = numbers("mocap_framerate" if "mocap_framerate" in data else "mocap_frame_rate", 30.0)
    if rate.size != 1 or not rate.reshape(-1)[0] > 0:
        raise DataError(f"{path}: the frame rate (mocap_framerate) must be one positive number; got {rate!r}.")
    fps = float(rate.reshape(-1)[0])
    if model is None:
        model = load_body_model("default", gender=gender)
    with torch.no_grad():
        b = torch.zeros(1, model.num_betas, dtype=model.v_template.dtype)
        b[0, : betas.shape[0]] = torch.as_tensor(betas[: model.num_betas])
        pelvis = model(betas=b).rest_joints[0, 0].double().numpy()
    p, t = rotate_motion(smpl, trans, pelvis, Y_UP_TO_Z_UP.T)
    return SmplMotion(poses=p, trans=t, betas=betas, gender=gender, fps=fps, source=str(path),
                      info={"format": "amass", "poses_width": int(poses.shape[1])})

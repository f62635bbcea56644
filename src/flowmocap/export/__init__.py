"""Exports of a result folder to animation and research formats (``flowmocap export``).

Formats (:data:`FORMATS`): ``bvh`` (skeleton with the fitted bone lengths),
``glb`` (one skinned mesh, a 24-joint rig and keyframed joint rotations,
:mod:`flowmocap.export.gltf_skin`), ``glb-frames`` (a flipbook: one full mesh per frame,
exact vertices, large), ``obj`` (one mesh per frame in a folder), ``json`` (per-frame
joints and parameters), ``npz`` (AMASS layout), ``trc`` and ``c3d`` (marker trajectories
for biomechanics tools, :mod:`flowmocap.export.markers`: the 24 joints, or Pose2Sim's HALPE_26
keypoints, :mod:`flowmocap.export.marker_sets`). All 3D output
is in metres, by default in the ground frame of :mod:`flowmocap.export.world` (gravity up,
y up, the floor at 0); see :mod:`flowmocap.export.motion` for the other frames (the AMASS
file is z up, as AMASS's own; the C3D file is z up and in millimetres, as labs write it). ``smooth=True`` smooths the motion first (:mod:`flowmocap.fit.smooth`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from flowmocap.errors import DataError, InputError
from flowmocap.export.motion import (FRAMES, FittedMotion, load_fitted_motion, motion_in_frame_of, rotate_motion,
                                     up_rotation)

__all__ = ["FORMATS", "export_result", "write_motion_glb", "default_output", "write_json", "FittedMotion", "load_fitted_motion",
           "motion_in_frame_of", "rotate_motion", "up_rotation", "FRAMES", "export_people"]

#: format name -> default output name inside the result folder.
FORMATS: dict[str, str] = {
    "bvh": "motion.bvh",
    "glb": "motion.glb",
    "glb-frames": "motion_frames.glb",
    "obj": "obj",
    "json": "motion.json",
    "npz": "motion_amass.npz",
    "trc": "motion.trc",
    "c3d": "motion.c3d",
}


def default_output(result_dir: str | Path, fmt: str) -> Path:
    """Where ``fmt`` goes when no output path is given: ``RESULT/export/<name>``."""
    _check_format(fmt)
    return Path(result_dir) / "export" / FORMATS[fmt]


def _check_format(fmt: str) -> None:
    if fmt not in FORMATS:
        raise InputError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}.")


def _vertex_frames(motion: FittedMotion, chunk: int = 32):
    for s in range(0, motion.num_frames, chunk):
        yield from motion.body(s, s + chunk)[0]


def write_json(path: str | Path, motion: FittedMotion) -> Path:
    """Per-frame joints and parameters as JSON.

    Layout: ``{"format": "flowmocap-motion", "fps", "gender", "betas" (10), "stature_m" (the
    body's standing height, sole to crown, :mod:`flowmocap.body.stature`; null for a model
    without a midline to measure), "joint_names" (24), "parents" (24), "frame" ("up" | "world"), "rotation" (3x3 applied
    to the result's world), "camera" (the result's camera, world frame), "units",
    "frames": [{"index" (the input's frame number), "time_s" (seconds since the input's first frame: the
    video's own time stamps where its rate varies, else index / fps), "seen" (false where the detector found
    no person in the frame: the pose there was carried by the flow, held or filled in; ``run.json`` ``gaps``),
    "pose" (72, radians), "trans" (3, metres),
    "joints3d" (24 x 3, metres), "joints2d" (24 x 2, pixels of the tracked frames: the camera's), and where the result
    has them "contact" (left, right foot on the ground) and "disagreement" (24, metres,
    null outside the 13 scored joints: how far the run's 3D sources part,
    :mod:`flowmocap.fit.disagreement`) and, where the camera turned during the clip (the
    motion turned back into the world, :mod:`flowmocap.export.motion`), "camera_R" (3x3) and
    "camera_t" (3): that frame's camera; the top-level "camera" is then the first frame's; and
    where it zoomed, "camera_focal_px" (fx, fy)}, ...]}``.
    """
    from flowmocap.body.skeleton import JOINT_NAMES, PARENTS
    from flowmocap.body.stature import stature
    from flowmocap.errors import ModelFileError

    j3d = motion.joints()
    try:
        tall = round(stature(motion.model, motion.betas), 4)
    except ModelFileError:
        tall = None
    r = lambda a, n=6: np.round(np.asarray(a, np.float64), n).tolist()  # noqa: E731
    contacts = motion.foot_contacts
    times, seen = motion.times, motion.seen

    def frame(k):
        cam = motion.camera_at(k) if motion.turns is not None else None  # this frame's camera, built once
        return {
            "index": int(motion.frame_index[k]),
            "time_s": round(float(times[k]), 6),
            "seen": bool(seen[k]),
            "pose": r(motion.poses[k]),
            "trans": r(motion.trans[k]),
            "joints3d": r(j3d[k]),
            "joints2d": r(motion.joints2d[k], 3),
            **({"contact": [bool(c) for c in contacts[k]]} if contacts is not None else {}),
            **({"disagreement": [None if not np.isfinite(v) else round(float(v), 4) for v in motion.disagreement[k]]}
               if motion.disagreement is not None else {}),
            # where the camera turned, this frame's camera (the top-level one is the first frame's)
            **({"camera_R": r(cam.R, 9), "camera_t": r(cam.t, 9)} if cam is not None else {}),
            # where the camera zoomed, this frame's focal lengths (pixels)
            **({"camera_focal_px": r([cam.fx, cam.fy], 4)} if cam is not None and motion.zooms is not None else {}),
        }

    doc = {
        "format": "flowmocap-motion", "version": 1, "fps": motion.fps, "gender": motion.gender,
        "betas": r(motion.betas), "stature_m": tall, "joint_names": list(JOINT_NAMES), "parents": list(PARENTS),
        "frame": motion.frame,
        "rotation": r(motion.rotation, 9), "offset": r(motion.offset, 9), "camera": motion.camera.to_dict(),
        "smoothed": motion.smoothed,
        "units": "metres, radians, pixels (joints2d); y up unless frame is 'world'",
    }
    from flowmocap.atomic import atomic_write

    path = Path(path)
    # written frame by frame, one line each: a 10-minute motion never exists as one string
    head = json.dumps(doc, indent=1)

    def write(tmp):  # an interrupted or failed write leaves no partial file under the name
        with open(tmp, "w") as f:
            f.write(head[:-2] + ',\n "frames": [')
            for k in range(motion.num_frames):
                f.write(("\n  " if k == 0 else ",\n  ") + json.dumps(frame(k), separators=(",", ":")))
            f.write("\n ]\n}\n")

    atomic_write(path, write)
    return path


def write_motion_glb(path: str | Path, motion: FittedMotion, own_times: bool = True) -> Path:
    """A :class:`FittedMotion` as a skinned, animated ``.glb``
    (:func:`flowmocap.export.gltf_skin.write_skinned_glb`); the scene's ``extras`` hold the
    camera in the motion's frame, the frame's name, the input's frame numbers, where the camera
    turned, moved or zoomed its turns, moves and zooms per frame, and, in the ground frame,
    the floor and the per-frame foot contacts. ``own_times``: a variable-rate video's rows
    keyed at its own times (else, and for any other input, row ``k`` at ``k / fps``, as the
    viewer's page steps through them)."""
    import torch

    from flowmocap.export.gltf_skin import write_skinned_glb

    with torch.no_grad():
        out = motion.model(betas=torch.as_tensor(motion.betas[None], dtype=motion.model.v_template.dtype))
    extras = {"frame": motion.frame, "camera": motion.camera.to_dict(),
              "frame_index": [int(i) for i in motion.frame_index], "smoothed": motion.smoothed}
    if motion.turns is not None:  # the camera turned: "camera" is the first frame's, turned by these
        from scipy.spatial.transform import Rotation

        extras["camera_turns_rotvec"] = np.round(Rotation.from_matrix(motion.turns).as_rotvec(), 6).tolist()
        if motion.shifts is not None:  # and moved: each frame's camera is "camera" turned, then moved by these (m)
            extras["camera_shifts_m"] = np.round(motion.shifts, 6).tolist()
            extras["camera_height_m"] = round(float(motion.camera_height_m), 4)
        if motion.zooms is not None:  # and zoomed: each frame's focal length is "camera"'s times these
            extras["camera_zooms"] = np.round(motion.zooms, 6).tolist()
    if motion.world is not None:
        extras["floor"] = {"method": motion.world.plane.method, "contact_points": motion.world.plane.inliers}
    if motion.foot_contacts is not None:
        extras["contacts"] = motion.foot_contacts.astype(int).tolist()
    seen = motion.seen
    if not seen.all():  # the input's frame numbers without the person (carried by the flow, held or filled in)
        extras["unseen_frames"] = [int(i) for i in motion.frame_index[~seen]]
    times = None
    if own_times and motion.variable_rate:  # the keys at the video's own times (glTF keys need not be evenly spaced)
        times = motion.times - motion.times[0]
        extras["variable_frame_rate"] = True
    return write_skinned_glb(path, motion.poses, motion.trans, out.rest_vertices[0].double().numpy(),
                             out.rest_joints[0].double().numpy(), motion.model.faces_np,
                             motion.model.weights.double().numpy(), motion.fps, extras=extras, times=times)


def export_result(result_dir: str | Path, fmt: str, out: str | Path | None = None, frame: str = "ground",
                  model=None, units_per_metre: float = 1.0, progress: bool = False,
                  smooth: bool | dict = False, markers: str = "joints",
                  frame_of: FittedMotion | None = None, scale: float | None = None) -> Path:
    """Export a result folder.

    Args:
        result_dir: the result folder (``motion.npz``, ``run.json``).
        fmt: one of :data:`FORMATS`.
        out: output file (a folder for ``obj``); default :func:`default_output`.
        frame: ``"ground"`` (y up, floor at 0; writes ``RESULT/world.json``), ``"up"`` (y
            up) or ``"world"`` (the result's own world frame).
        smooth: False, True or a dict of :func:`flowmocap.fit.smooth.smooth_motion`'s
            keyword arguments (``window_s``, ``order``).
        model: body model override (default: the one recorded in ``run.json``).
        units_per_metre: BVH length unit (1 = metres, 100 = centimetres).
        progress: progress bars for the per-frame formats.
        markers: the marker set of ``trc`` and ``c3d``
            (:data:`flowmocap.export.marker_sets.MARKER_SETS`: ``"joints"``, the 24 joint
            centres, or ``"halpe26"``, Pose2Sim's keypoints); other formats take only the default.
        frame_of: another result of the same input, loaded: export in its frame instead
            (:func:`~flowmocap.export.motion.motion_in_frame_of`; ``frame`` is then not used;
            the foot contacts are the result's own). The camera's turn is undone as in
            ``frame_of`` (not at all in its ``"world"`` frame) and its move where
            ``frame_of``'s was (:func:`~flowmocap.export.motion.shared_move_refusal`).
        scale: with ``frame_of``, scale the body about the camera centre by this first
            (:func:`~flowmocap.export.floor.scaled_about_camera`; e.g. the factor that
            stands it on ``frame_of``'s floor, :func:`~flowmocap.export.floor.floor_scale`).

    Returns:
        The path written (file or folder).

    Raises:
        InputError: unknown format, frame or marker set, a marker set for a format without
            markers, or an ``out`` whose ending is not the format's (``.bvh``, ...) or, for
            ``obj``, that is a file. DataError: not a result folder.
    """
    from flowmocap.export.marker_sets import marker_names
    from flowmocap.io.results import result_folder

    result_dir = result_folder(result_dir)
    _check_format(fmt)
    marker_names(markers)
    if markers != "joints" and fmt not in ("trc", "c3d"):
        raise InputError(f"a marker set ({markers!r}) is for the trc and c3d formats; {fmt!r} holds the body itself.")
    if out is not None and not isinstance(out, (str, os.PathLike)):
        raise InputError(f"out must be the path of the file to write (a str or a Path), or None; got "
                         f"{type(out).__name__}.")
    out = Path(out) if out is not None else default_output(result_dir, fmt)
    ending = Path(FORMATS[fmt]).suffix
    if ending and out.suffix.lower() != ending:  # a .glb under a .bvh name opens in nothing
        raise InputError(f"{out}: a {fmt} export is a {ending} file; give a name ending in {ending} "
                         f"(e.g. {out.with_suffix(ending).name}).")
    if scale is not None and frame_of is None:
        raise InputError("a scale moves a person onto another's floor: give the other's motion too (frame_of).")
    if frame_of is not None:  # loaded in its own ground frame for its foot contacts, then moved
        motion = load_fitted_motion(result_dir, frame="ground", model=model, smooth=smooth, camera_move_of=frame_of)
        if frame_of.frame == "world" and motion.turns is not None:  # frame_of is not turned back: nor is this one
            motion = replace(load_fitted_motion(result_dir, frame="world", model=model, smooth=smooth),
                             contacts=motion.foot_contacts)
        if scale is not None:
            from flowmocap.export.floor import scaled_about_camera

            motion = scaled_about_camera(motion, scale)
        motion = motion_in_frame_of(motion, frame_of)
        frame = frame_of.frame
    else:
        motion = load_fitted_motion(result_dir, frame=frame, model=model, smooth=smooth)
    rest = motion.rest_joints()
    if fmt == "bvh":
        from flowmocap.export.bvh import write_motion_bvh

        return write_motion_bvh(out, motion.poses, motion.trans, rest, motion.fps, units_per_metre=units_per_metre)
    if fmt == "glb":
        return write_motion_glb(out, motion)
    if fmt == "glb-frames":
        from flowmocap.export.glb import write_mesh_sequence_glb

        return write_mesh_sequence_glb(out, _vertex_frames(motion), motion.model.faces_np, motion.fps,
                                       motion.num_frames, progress=progress)
    if fmt == "obj":
        from flowmocap.export.obj import write_obj_sequence

        write_obj_sequence(out, _vertex_frames(motion), motion.model.faces_np, motion.frame_index,
                           motion.num_frames, progress=progress)
        return out
    if fmt == "json":
        return write_json(out, motion)
    if fmt in ("trc", "c3d"):
        from flowmocap.export.marker_sets import marker_trajectories
        from flowmocap.export.markers import write_c3d, write_trc

        first = int(motion.frame_index[0]) if motion.num_frames else 0
        names, points = marker_trajectories(motion, markers)
        if fmt == "trc":
            return write_trc(out, points, names, motion.fps, first_frame=first)
        # --frame world: the result's own axes as they are (a lab's calibrated world, z up, stays the lab's)
        return write_c3d(out, points, names, motion.fps, first_frame=first, up="none" if frame == "world" else "y",
                         contacts=motion.foot_contacts, seen=motion.seen)
    from flowmocap.io.amass import write_amass_npz

    if frame == "world":
        raise InputError("the AMASS layout is always z up; use --frame ground (the default) or up for --format npz.")
    return write_amass_npz(out, motion.poses, motion.trans, motion.betas, motion.gender, motion.fps, rest[0],
                           frame_index=motion.frame_index)


def export_people(root: str | Path, fmt: str, out: str | Path | None = None, frame: str = "ground", model=None,
                  units_per_metre: float = 1.0, progress: bool = False, smooth: bool | dict = False,
                  markers: str = "joints", floor: bool = True,
                  log: Callable[[str], None] | None = None) -> list[Path]:
    """Export every tracked person of a ``track --person all`` folder, all in one frame: the
    first person's ``frame`` (by default their ground frame; with ``floor``, that of the
    person whose floor is shared, :func:`~flowmocap.export.floor.people_floor`), each other
    person moved there through the camera they share
    (:func:`~flowmocap.export.motion.motion_in_frame_of`), so the files line up when
    imported together.

    Args:
        root: the ``track --person all`` folder (``people.json``, ``person0/``, ...).
        fmt, frame, model, units_per_metre, progress, smooth, markers: as :func:`export_result`.
        out: the folder for the files (default ``ROOT/export``); each is named after its
            person: ``person0.bvh``, ``person1_frames.glb``, ``person0_obj/``, ...
        floor: stand everyone on the first person's floor, or where they never stand still
            the next standing person's (:mod:`flowmocap.export.floor`: each other person
            scaled about the camera centre, where the factor is accepted);
            what was done is written to ``floor.json`` beside the files. False: each keeps
            their own fit's size and distance.
        log: where to say, one line per person, how they were put on the floor.

    Returns:
        The paths written, one per tracked person, by rank; each person's files carry their
        own foot contacts (json, c3d, glb).

    Raises:
        DataError: not a people folder, or nobody tracked yet. InputError: as :func:`export_result`.
    """
    from flowmocap.io.results import PEOPLE_MANIFEST, people_results

    _check_format(fmt)
    root = Path(root)
    people = people_results(root)
    if not people:
        raise DataError(f"{root} holds no {PEOPLE_MANIFEST}: it is not the folder of `flowmocap track --person all`.")
    folder = Path(out) if out is not None else root / "export"
    from flowmocap.export.floor import floor_owner, people_floor, write_floor

    fits = None
    if floor:
        fits = people_floor([d for _, d in people], model=model)
    owner = floor_owner(fits)  # whose floor is shared holds everyone in their frame
    for (name, _), fit in zip(people, fits or []):
        if log is not None:
            log(fit.describe(name, people[owner][0]))
    holder = load_fitted_motion(people[owner][1], frame=frame, model=model, smooth=smooth)
    paths = []
    for k, (name, result) in enumerate(people):
        target = folder / FORMATS[fmt].replace("motion", name, 1) if FORMATS[fmt].startswith("motion") else \
            folder / f"{name}_{FORMATS[fmt]}"
        paths.append(export_result(result, fmt, out=target, frame=frame, model=model, units_per_metre=units_per_metre,
                                   progress=progress, smooth=smooth, markers=markers,
                                   frame_of=None if k == owner else holder,
                                   scale=None if k == owner or fits is None else fits[k].scale))
    write_floor(folder / "floor.json", [n for n, _ in people], fits)
    return paths

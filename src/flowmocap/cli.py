"""The ``flowmocap`` command."""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import threading
from pathlib import Path


def _stopped_while_starting(signum, frame) -> None:
    """Ctrl-C while the libraries below load (a second or two): nothing has started, so
    say so and end, where a KeyboardInterrupt inside an import came out as its traceback
    (scipy's 'ImportError: initialization failed', exit 1)."""
    sys.stderr.write("flowmocap: interrupted\n")
    os._exit(130)


_LOADING = (threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler)  # not where SIGINT is ignored
if _LOADING:
    signal.signal(signal.SIGINT, _stopped_while_starting)

from flowmocap.batch import (BATCH_FAILED, expand_inputs, is_batch, summary_table, track_many, track_people,
                             track_people_many)
from flowmocap.commands import register_all
from flowmocap.errors import FlowMocapError, InputError, OutputError
from flowmocap.export.marker_sets import MARKER_SETS
from flowmocap.eval.demo import run_demo
from flowmocap.pipeline import track
from flowmocap.synth import synthesize
from flowmocap.version import __version__
from flowmocap.vision.flow import FLOW_METHODS
from flowmocap.viz.body_figure import POSES, body_sheet, render_body

if _LOADING:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def _parse_betas(text: str | None) -> list[float]:
    if not text:
        return [0.0] * 10
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError as e:
        raise InputError(f"--betas must be numbers separated by commas; got {text!r}.") from e
    if len(values) > 10:
        raise InputError(f"--betas takes at most 10 values; got {len(values)}.")
    from flowmocap.synth.sequence import MAX_ABS_BETA

    if not all(math.isfinite(v) and abs(v) <= MAX_ABS_BETA for v in values):
        raise InputError(f"--betas are standard deviations of the body's shape, finite and within +-{MAX_ABS_BETA:g} "
                         f"(people lie within about +-3); got {text!r}.")
    return values + [0.0] * (10 - len(values))


def cmd_body(args) -> int:
    _check_picture_path(Path(args.out))  # before the work
    image = render_body(
        model=args.model, gender=args.gender, betas=_parse_betas(args.betas),
        pose=args.pose, width=args.width, height=args.height, view=args.view,
    )
    _write_png(Path(args.out), image)
    print(f"wrote {args.out} ({args.width}x{args.height}, pose {args.pose}, poses available: {', '.join(POSES)})")
    return 0


def cmd_demo(args) -> int:
    from flowmocap.eval.demo import check_demo

    check_demo(args.out, args.num_frames, args.size, args.seed)  # before anything is written
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    _write_png(out / "default_body.png", body_sheet())
    print(f"wrote {out / 'default_body.png'} (the default body)")
    print(f"synthesising the built-in walk ({args.num_frames} frames, {args.size}) and tracking it "
          "from a perturbed initialisation ...")
    scores = run_demo(out, frames=args.num_frames, size=args.size, seed=args.seed, progress=not args.quiet)
    print(f"3D joint error on the paper's 13 joints: local (per-frame Procrustes) "
          f"{scores['local_cm']:.2f} cm, global (per-sequence Procrustes) {scores['global_cm']:.2f} cm, "
          f"MPJPE {scores['mpjpe_cm']:.2f} cm; "
          + (f"{scores['s_per_frame']:.2f} s per frame (median)" if scores.get("s_per_frame") is not None
             else "no frame past the start tracked, so no time per frame"))
    print("paper's targets (HumanEva walking): local <= 5.5 cm, global <= 7.6 cm; ours: <= 1 s per frame")
    print(f"wrote {out / 'eval.json'}, the sequence in {out / 'sequence'} and the result in {out / 'result'}")
    print(f"next: flowmocap render {out / 'result'} (overlay video, figures); "
          f"flowmocap export {out / 'result'} --format bvh|glb|obj|json|npz|trc|c3d; "
          f"flowmocap eval {out / 'result'} --gt {out / 'sequence'}")
    return 0


def cmd_track(args) -> int:
    if args.camera and args.focal is not None:
        raise InputError(f"give --camera ({args.camera}) or --focal ({args.focal:g}), not both: the camera file holds "
                         "its own focal length.")
    settings = {"init": args.init or "auto", "masks": args.masks, "camera": args.camera or args.focal,
                "config": args.config, "frames": args.frames, "profile": args.profile, "model": args.model,
                "gender": args.gender, "flow": args.flow, "max_size": args.max_size, "reinit": not args.no_reinit,
                "joints3d": args.joints3d, "person": args.person, "keep_flow": args.keep_flow,
                "fast": args.fast, "height": args.height, "detector": args.detector}
    if args.fps is not None:  # only where given: a batch's inputs otherwise keep their own rates
        settings["fps"] = args.fps
    lists = [args.list] if args.list else []
    if not args.input and not lists:
        raise InputError("track needs an input: a video file, a folder of frames, a sequence folder, or a batch "
                         "(several of them, a folder of videos, @LIST or --list FILE).")
    if args.workers < 1:
        raise InputError(f"--workers must be at least 1; got {args.workers}.")
    if args.ray and Path(args.ray).exists():
        raise InputError(f"--ray took {args.ray!r} for the Ray cluster's address; put --ray after the inputs, or "
                         "write --ray=ADDRESS.")
    formats = _export_formats(None if args.export is None else ",".join(args.export), args.export_markers)
    ray = False if args.ray is None else (args.ray or True)
    if str(args.person).strip().lower() == "all":
        del settings["person"]
        if is_batch(args.input, lists):  # OUT/<name>/personN for each input
            items = track_people_many(expand_inputs(args.input, lists), args.out, workers=args.workers, ray=ray,
                                      force=args.force, progress=not args.quiet, **settings)
            print(summary_table(items, args.out, noun="people"))
            status = 0
            for name in dict.fromkeys(it.name.split("/")[0] for it in items):
                mine = [it for it in items if it.name.split("/")[0] == name]
                status = max(status, _export_people(Path(args.out) / name, mine, formats, args))
            return status
        items = track_people(args.input[0], args.out, workers=args.workers, ray=ray, force=args.force,
                             progress=not args.quiet, **settings)
        print(summary_table(items, args.out, noun="people"))
        if all(it.status == "failed" for it in items):  # nobody tracked: the failure's own kind, as a single run
            print(f"flowmocap: error: {items[0].error}", file=sys.stderr)
            return items[0].exit_code or 1
        return _export_people(args.out, items, formats, args)
    if not is_batch(args.input, lists):
        if args.workers > 1 or args.ray is not None:
            print("one input: tracking it in this process (--workers and --ray share out several inputs)")
        track(args.input[0], args.out, resume=args.resume, progress=not args.quiet, force=args.force, **settings)
        _export_all(args.out, formats, quiet=args.quiet, markers=args.export_markers)
        return 0
    if args.masks not in (None, "auto"):
        raise InputError(f"--masks {args.masks} holds one video's masks; with several inputs leave --masks at auto "
                         "(a sequence folder brings its own masks/), or track that video on its own.")
    if args.init not in (None, "auto"):
        print(f"note: every input starts from the 2D joints of {args.init}")
    if "," in str(args.person):
        print(f"note: in every input, the person at pixel {args.person} is tracked")
    items = track_many(expand_inputs(args.input, lists), args.out, workers=args.workers, ray=ray, force=args.force,
                       progress=not args.quiet, **settings)
    print(summary_table(items, args.out))
    return _export_items(items, formats, args)


def _export_people(root, items, formats: list[str], args) -> int:
    """``track --person all --export``: every tracked person in each format, in one frame
    (:func:`flowmocap.export.export_people`, into ``ROOT/export``); the exit status."""
    from flowmocap.export import export_people

    failed = any(it.status == "failed" for it in items)
    if any(it.ok for it in items):
        for k, fmt in enumerate(formats):
            try:  # how everyone was stood on one floor: said with the first format's files
                for path in export_people(root, fmt, progress=not args.quiet,
                                          markers=args.export_markers if fmt in ("trc", "c3d") else "joints",
                                          log=print if k == 0 else None):
                    print(f"wrote {path} ({fmt})")
            except FlowMocapError as e:  # the tracked results are kept
                print(f"export ({fmt}) of {root} failed: {e}", file=sys.stderr)
                failed = True
    return BATCH_FAILED if failed else 0


def _export_items(items, formats: list[str], args) -> int:
    """Export every finished result of a batch (or of ``--person all``); the exit status."""
    export_failed = False
    for it in items:
        if it.ok:
            try:
                _export_all(it.out, formats, quiet=args.quiet, markers=args.export_markers)
            except FlowMocapError as e:  # the others still get theirs; the tracked result is kept
                print(f"export of {it.out} failed: {e}", file=sys.stderr)
                export_failed = True
    return BATCH_FAILED if export_failed or any(it.status == "failed" for it in items) else 0


def _export_formats(text: str | None, markers: str = "joints") -> list[str]:
    """The formats of ``track --export`` and its ``--export-markers`` set (checked before any tracking)."""
    from flowmocap.export import FORMATS
    from flowmocap.export.marker_sets import marker_names

    marker_names(markers)
    formats = [f.strip() for f in str(text or "").split(",") if f.strip()]
    unknown = [f for f in formats if f not in FORMATS]
    if text and (unknown or not formats):
        raise InputError(f"--export takes export formats separated by commas, of: {', '.join(FORMATS)}; "
                         f"got {text!r}.")
    if markers != "joints" and not {"trc", "c3d"} & set(formats):
        raise InputError(f"--export-markers {markers} sets the markers of the trc and c3d exports; add one of them "
                         "to --export (e.g. --export trc).")
    return list(dict.fromkeys(formats))


def _export_all(result: str | Path, formats: list[str], quiet: bool, markers: str = "joints") -> None:
    """Export a finished result in each format, to ``RESULT/export/`` (as ``flowmocap export``),
    the trc and c3d files with the ``markers`` set. A format that fails does not stop the
    others; then the first failure's kind of error (an ``OSError``: ``OutputError``) says that
    the result is finished and which formats to export again."""
    from flowmocap.commands.export import rate_note
    from flowmocap.export import export_result

    failed: list[tuple[str, BaseException]] = []
    for fmt in formats:
        rate = rate_note(result, fmt)
        if rate:
            print(rate)
        try:
            path = export_result(result, fmt, progress=not quiet,
                                 markers=markers if fmt in ("trc", "c3d") else "joints")
        except (FlowMocapError, OSError) as e:
            failed.append((fmt, e))
            continue
        print(f"wrote {path} ({fmt})")
    if failed:
        fmt, first = failed[0]
        cls = type(first) if isinstance(first, FlowMocapError) else OutputError
        reason = (f"{first.strerror} ({first.filename})" if isinstance(first, OSError) and first.strerror
                  else str(first))
        names = ", ".join(f for f, _ in failed)
        raise cls(f"{result} is tracked and finished, but its export to {names} failed ({fmt}: {reason}); "
                  f"export it again with `flowmocap export {result} -f FMT`"
                  + (" once there is space" if isinstance(first, OSError) else "") + ".")


def cmd_synth(args) -> int:
    placed = [f"--{k}" for k in ("focal", "distance", "azimuth", "elevation") if getattr(args, k) is not None]
    if args.camera and placed:
        raise InputError(f"--camera places the camera; leave out {', '.join(placed)} (they place it otherwise).")
    size = args.size if args.size is not None else (None if args.camera else "640x480")
    res = synthesize(
        args.motion, args.out, fps=args.fps, start=args.start, frames=args.num_frames, size=size,
        focal=args.focal, distance=args.distance, azimuth=60.0 if args.azimuth is None else args.azimuth,
        elevation=8.0 if args.elevation is None else args.elevation,
        camera=args.camera, betas=args.betas, gender=args.gender, seed=args.seed,
        model=args.model, asf=args.asf, flow=not args.no_flow, overwrite=args.overwrite,
    )
    meta = res.meta
    print(f"wrote {res.out_dir}: {meta['num_frames']} frames, {meta['size'][0]}x{meta['size'][1]} at "
          f"{meta['fps']:g} fps from {meta['source']} ({meta['seconds']:.1f} s)")
    return 0


#: The picture formats ``body`` and ``demo`` write, by the name's ending.
PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg")


def _check_picture_path(path: Path) -> None:
    """Refuse a picture's path before the work: a folder, a path under a file, or a name
    ending in none of :data:`PICTURE_SUFFIXES` (``InputError``)."""
    from flowmocap.atomic import check_file_path

    check_file_path(path)
    if path.suffix.lower() not in PICTURE_SUFFIXES:
        raise InputError(f"{path}: a picture is written as PNG or JPEG; give a name ending in "
                         f"{' or '.join(PICTURE_SUFFIXES)}.")


def _write_png(path: Path, image) -> None:
    """Write ``image`` at ``path`` (PNG or JPEG by its name) through a temporary file: a failed
    write leaves the old file, never a cut-off one."""
    import imageio.v3 as iio

    from flowmocap.atomic import atomic_write

    _check_picture_path(path)
    atomic_write(path, lambda tmp: iio.imwrite(tmp, image, extension=path.suffix.lower()))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="flowmocap",
        description="3D human motion and body shape from monocular video by matching rendered "
        "and observed optical flow (Alldieck et al. 2017).",
    )
    p.add_argument("--version", action="version", version=f"flowmocap {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    d = sub.add_parser("demo", help="synthesise the built-in walk, track it, print the 3D error",
                       description="The whole job on a built-in synthetic clip with known ground truth: render the "
                       "built-in walk onto a random body, track it from a perturbed first-frame init (as a user's "
                       "init.json would give it), and print the 3D joint error against the truth. Writes the "
                       "sequence, the result and eval.json under --out; re-running resumes.")
    d.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    d.add_argument("--num-frames", type=int, default=30, help="number of frames to synthesise and track (default 30)")
    d.add_argument("--size", default="640x480", help="WxH in pixels (default 640x480)")
    d.add_argument("--seed", type=int, default=0, help="seed of the random body shape and the init noise (default 0)")
    d.add_argument("--quiet", action="store_true", help="no progress bars")
    d.set_defaults(func=cmd_demo)

    t = sub.add_parser("track", help="fit the body to a video or frame sequence by optical flow",
                       description="Track the person in a video, a folder of frames or a sequence folder and write "
                       "a result folder (motion.npz, run.json). Everything not given is automatic: masks, 2D and 3D "
                       "joints, initialisation and camera. Results are written after every frame; --resume "
                       "continues an interrupted run. Several inputs (or a folder of videos, or a list file) make a "
                       "batch: one result folder per input under --out, named after the input (--out/batch.json "
                       "says which is which); run again, it skips finished inputs (--force: tracks them anew) and "
                       "resumes interrupted ones, and one input's failure does not stop the others. --person all "
                       "tracks every person in one input the same way, one result folder each.",
                       epilog=f"Exit status: 0 when every input has a finished result; {BATCH_FAILED} when some inputs "
                       "of a batch (or people of --person all) failed (the others are done; the summary says why; "
                       "run again to retry them); "
                       "other non-zero values on an error that stopped the command.")
    t.add_argument("input", nargs="*", help="a video file, a sequence folder (frames/, masks/, camera.json) or a "
                   "folder of frames; for a batch: several of them, a folder of videos and sequence folders, or "
                   "@LIST (a text file, one input per line)")
    t.add_argument("--out", required=True, help="result folder (motion.npz, run.json, detections/); for a batch, "
                   "the folder of the result folders")
    t.add_argument("--list", metavar="FILE", help="a text file of inputs, one per line (# comments; relative paths "
                   "are relative to the file's folder): a batch")
    t.add_argument("--workers", type=int, default=1, help="batch: track this many inputs at once, each in its own "
                   "process on this machine, sharing its cores (default 1: one after the other)")
    t.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS", help="batch: track each input as "
                   "a task on a Ray cluster (pip install 'flowmocap[cluster]'): ADDRESS as ray.init takes it (auto, "
                   "HOST:PORT, ray://HOST:10001); without it, the cluster RAY_ADDRESS names, else a new one on this "
                   "machine. The cluster's nodes need flowmocap, and the inputs and --out at the same paths. Put it "
                   "after the inputs or write --ray=ADDRESS")
    t.add_argument("--init", default=None, help="'auto' (default: 2D joints found by MediaPipe on the first frame "
                   "with a person) or init.json: 2D joints of the first frame, optional rough pose")
    t.add_argument("--masks", default=None, help="'auto' (MediaPipe person segmentation; the default for a video "
                   "or a folder without masks/) or a folder of person masks, one per frame (default: INPUT/masks)")
    t.add_argument("--profile", default=None, choices=["video", "synthetic"], help="settings profile (default: "
                   "'video' when the masks come from the detector, else 'synthetic'); printed and recorded in run.json")
    t.add_argument("--focal", type=float, help="focal length in pixels of the video's frames (default: from the "
                   "video's metadata, else 0.9 x the long side, a 58 degree field of view, or where the camera "
                   "turns by 5 degrees or more without moving, the focal length its background's turns give)")
    t.add_argument("--camera", help="camera.json (default: INPUT/camera.json)")
    t.add_argument("--max-size", type=int, default=640, help="scale video frames (and a plain folder's frames) down "
                   "so that the long side is at most this many pixels (default 640; 0 keeps their size)")
    t.add_argument("--no-reinit", action="store_true", help="do not re-initialise from the detector when "
                   "tracking fails (re-initialisation runs when the detector is used, i.e. with automatic init or masks)")
    t.add_argument("--joints3d", default="auto", choices=["auto", "off"], help="'auto' (default): the detector's "
                   "3D joints tell each limb's direction in depth (E_d); with your own init.json and masks the "
                   "detector then runs for them (MediaPipe, about 0.05 s per frame), and its 2D joints are used too (the "
                   "detector_keypoints setting, on by default). 'off': no E_d, and with your own init.json and masks no "
                   "detector at all")
    t.add_argument("--person", default="largest", help="who to track when several people are in view: 'largest' "
                   "(default: the person seen biggest, nearest and longest), N (the N-th by that measure, 0 = the "
                   "largest), x,y (a pixel of the video's frames, before --max-size, on the person in the first "
                   "frame they appear in), or all (every person the detector follows in at least a quarter as many "
                   "frames as the largest, each into --out/personN by that rank, listed in --out/people.json; "
                   "with several inputs --out/<name>/personN; --workers and --ray share them out); recorded in "
                   "run.json")
    t.add_argument("--model", default="default", help="'default' or an SMPL .pkl/.npz or folder")
    t.add_argument("--gender", default="neutral", choices=["neutral", "male", "female"],
                   help="which body of the model file (default neutral)")
    t.add_argument("--flow", default=None, choices=list(FLOW_METHODS), help="observed flow (default: the "
                   "settings' flow_method)")
    t.add_argument("--config", help="JSON file of tracker settings over the profile's (fields of "
                   "flowmocap.fit.config.TrackerConfig; see docs/settings.md)")
    t.add_argument("--frames", help="A:B, the frames to track: A to B - 1 (2: from frame 2 on, :50 the first 50; default: all with the "
                   "person)")
    t.add_argument("--fps", type=float, default=None, metavar="N",
                   help="frames per second of a folder of frames (a video states its own): it sets every time and "
                   "speed of the result and its exports (default: the folder's meta.json, else 30, with a note)")
    t.add_argument("--height", type=float, default=None, metavar="METRES",
                   help="the person's standing height in metres, if known (e.g. 1.78): the body is given that "
                   "height and placed at the depth that goes with it, so lengths, speeds and positions come out in "
                   "the person's metres (one camera leaves the size open; default: the fit's own estimate, "
                   "recorded in run.json as body.stature_m). In a batch it applies to every input; with "
                   "--person all to the largest person, and the others' sizes follow from standing on their floor "
                   "in render, view and export")
    t.add_argument("--resume", action="store_true", help="continue an interrupted run in --out (same input and "
                   "set-up only; it ends exactly as an uninterrupted run would)")
    t.add_argument("--keep-flow", action=argparse.BooleanOptionalAction, default=None, help="store the observed "
                   "flows in OUT/flow_cache for a resume or render to reuse (default: for frame folders, not for "
                   "videos: about 2.5 MB a frame at 640x480; --no-keep-flow for a frame folder on a small disk)")
    t.add_argument("--detector", default=None, choices=["full", "heavy"],
                   help="MediaPipe's landmark model for the 2D and 3D joints: 'heavy' (the default: nearer the "
                        "truth, about 0.03 s more a frame) or 'full' (MediaPipe's own wheel's; --fast's), each with the "
                        "confidence thresholds set for it (NETWORK_SETTINGS, docs/settings.md)")
    t.add_argument("--fast", action="store_true", help="faster, at some cost in the 2D fit: every optimisation "
                   "stops at a coarser stall, refits take fewer iterations, a refit turned down waits longer "
                   "before the next and the detector runs MediaPipe's full network (not the heavy one) without its "
                   "mask augmentation (docs/settings.md has the measurements)")
    t.add_argument("--force", action="store_true", help="write into --out even if it is a non-empty folder that "
                   "holds no flowmocap result, or start the result in it over")
    t.add_argument("--export", metavar="FMT[,FMT...]", action="append", help="after tracking, also export each "
                   "finished result "
                   "into OUT/export/ as `flowmocap export` does with its defaults (ground frame): any of bvh, glb, "
                   "glb-frames, obj, json, npz, trc, c3d")
    t.add_argument("--export-markers", default="joints", choices=list(MARKER_SETS),
                   help="the markers of the trc and c3d exports: joints (the 24 joint centres, default) or "
                   "halpe26 (Pose2Sim's HALPE_26 keypoints, for its OpenSim model)")
    t.add_argument("--quiet", action="store_true", help="no progress bars")
    t.set_defaults(func=cmd_track)

    b = sub.add_parser("body", help="render a body model to a PNG",
                       description="Render the default body (or an SMPL file) in a named pose to a PNG.")
    b.add_argument("--model", default="default", help="'default' or a path to an SMPL .pkl/.npz or folder")
    b.add_argument("--gender", default="neutral", choices=["neutral", "male", "female"],
                   help="which body of the model file (default neutral)")
    b.add_argument("--betas", default=None, help="up to 10 shape values, comma separated")
    b.add_argument("--pose", default="rest", help="named pose: rest, walk, wave (default rest)")
    b.add_argument("--view", default="front", choices=["front", "side", "three-quarter"], help="camera view")
    b.add_argument("--width", type=int, default=320, help="image width in pixels (default 320)")
    b.add_argument("--height", type=int, default=480, help="image height in pixels (default 480)")
    b.add_argument("--out", default="body.png", help="PNG to write (default body.png)")
    b.set_defaults(func=cmd_body)
    s = sub.add_parser("synth", help="render a synthetic sequence with ground truth from mocap or builtin:walk",
                       description="Retarget a mocap clip (or the built-in walk) onto a body, render it with a "
                       "textured body over a textured background, and write a sequence folder with exact masks, "
                       "camera.json and the ground truth (gt.npz).")
    s.add_argument("motion", help="builtin:walk, a .bvh file, or a CMU .amc file (its .asf beside it)")
    s.add_argument("--out", required=True, help="sequence folder to write")
    s.add_argument("--fps", type=float, default=30.0, help="frame rate to resample the motion to (default 30)")
    s.add_argument("--start", type=int, default=0, help="first frame (at --fps)")
    s.add_argument("--num-frames", type=int, help="number of frames (default: all)")
    s.add_argument("--size", help="WxH in pixels (default 640x480, or the camera's)")
    s.add_argument("--focal", type=float, help="focal length in pixels")
    s.add_argument("--distance", type=float, help="camera distance in metres (default: frame the whole path)")
    s.add_argument("--azimuth", type=float, help="degrees; 0 = in front of the body's start facing (default 60)")
    s.add_argument("--elevation", type=float, help="degrees above the horizon (default 8)")
    s.add_argument("--camera", help="camera.json to use instead of the placement options")
    s.add_argument("--betas", help="'random' or up to 10 comma-separated shape values")
    s.add_argument("--gender", choices=["neutral", "male", "female"], default="neutral", help="body gender")
    s.add_argument("--seed", type=int, default=0, help="seed of a random body shape (default 0)")
    s.add_argument("--model", default="default", help="'default' or an SMPL .pkl/.npz or folder")
    s.add_argument("--asf", help="ASF skeleton for an .amc file (default: found beside it)")
    s.add_argument("--no-flow", action="store_true", help="do not write the true flow")
    s.add_argument("--overwrite", action="store_true", help="replace an existing sequence folder")
    s.set_defaults(func=cmd_synth)

    register_all(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):  # no command: say which there are, as for any other usage error
        parser.print_help(sys.stderr)
        return 2
    def terminated(signum, frame):  # SIGTERM (kill, a service manager) stops as cleanly as Ctrl-C
        raise KeyboardInterrupt

    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, terminated) if main_thread else None
    try:
        return args.func(args)
    except FlowMocapError as e:
        print(f"flowmocap: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("flowmocap: interrupted; finished frames are kept (track --resume continues)" if args.command == "track"
              else "flowmocap: interrupted" + ("; the sequence is not finished: make it again with --overwrite"
                                               if args.command == "synth" else ""), file=sys.stderr)
        return 130
    except OSError as e:  # a file the command writes outside the result folder's own handling
        import errno

        where = f" ({e.filename})" if getattr(e, "filename", None) else ""
        full = e.errno in (errno.ENOSPC, errno.EFBIG, getattr(errno, "EDQUOT", errno.ENOSPC))
        print(f"flowmocap: error: could not read or write a file{where}: {e.strerror or e}"
              + ("; free space (or raise the file size limit) and run the command again" if full else ""),
              file=sys.stderr)
        return OutputError.exit_code
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())

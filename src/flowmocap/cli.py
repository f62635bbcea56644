"""The ``flowmocap`` command."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from flowmocap import __version__
from flowmocap.errors import FlowMocapError, InputError



def _parse_betas(text: str | None) -> list[float]:
    if not text:
        return [0.0] * 10
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError as e:
        raise InputError(f"--betas must be numbers separated by commas; got {text!r}.") from e
    if len(values) > 10:
        raise InputError(f"--betas takes at most 10 values; got {len(values)}.")
    return values + [0.0] * (10 - len(values))


def cmd_body(args) -> int:
    from flowmocap.viz.body_figure import POSES, render_body

    image = render_body(
        model=args.model, gender=args.gender, betas=_parse_betas(args.betas),
        pose=args.pose, width=args.width, height=args.height, view=args.view,
    )
    _write_png(Path(args.out), image)
    print(f"wrote {args.out} ({args.width}x{args.height}, pose {args.pose}, poses available: {', '.join(POSES)})")
    return 0


def cmd_demo(args) -> int:
    from flowmocap.eval.demo import run_demo
    from flowmocap.viz.body_figure import body_sheet

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    _write_png(out / "default_body.png", body_sheet())
    print(f"wrote {out / 'default_body.png'} (the default body)")
    print(f"synthesising the built-in walk ({args.frames} frames, {args.size}) and tracking it "
          "from a perturbed initialisation ...")
    scores = run_demo(out, frames=args.frames, size=args.size, seed=args.seed, progress=not args.quiet)
    print(f"3D joint error on the paper's 13 joints: local (per-frame Procrustes) "
          f"{scores['local_cm']:.2f} cm, global (per-sequence Procrustes) {scores['global_cm']:.2f} cm, "
          f"MPJPE {scores['mpjpe_cm']:.2f} cm; {scores['s_per_frame']:.2f} s per frame (median)")
    print("paper's targets (HumanEva walking): local <= 5.5 cm, global <= 7.6 cm; ours: <= 1 s per frame")
    print(f"wrote {out / 'eval.json'}, the sequence in {out / 'sequence'} and the result in {out / 'result'}")
    print(f"next: flowmocap render {out / 'result'} (overlay video, figures); "
          f"flowmocap export {out / 'result'} --format bvh|glb|obj|json|npz; "
          f"flowmocap eval {out / 'result'} --gt {out / 'sequence'}")
    return 0


def cmd_track(args) -> int:
    from flowmocap.body import load_body_model
    from flowmocap.fit.config import REAL_VIDEO, TrackerConfig
    from flowmocap.fit.init import parse_init
    from flowmocap.fit.tracker import track_sequence
    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.io.results import write_run
    from flowmocap.io.sequence import load_sequence
    from flowmocap.io.video import VIDEO_SUFFIXES, default_camera, load_video

    src = Path(args.input)
    out = Path(args.out)
    if (out / "motion.npz").exists() and not args.resume:
        raise InputError(f"{out} already holds a result; pass --resume to continue it or choose another folder.")
    auto_masks = args.masks == "auto"
    user_masks = None if args.masks in (None, "auto") else args.masks
    is_video = src.is_file() or src.suffix.lower() in VIDEO_SUFFIXES
    if is_video:
        seq = load_video(src, masks=user_masks, max_side=args.max_size or None)
    else:
        seq = load_sequence(src, masks=user_masks)
    auto_masks = auto_masks or seq.masks is None
    auto_init = args.init in (None, "auto")
    if len(seq) < 2:
        raise InputError(f"{src} holds only {len(seq)} frame; tracking needs at least 2 frames "
                         "(the flow is measured between neighbouring frames).")
    scale = float(seq.meta.get("scale", 1.0))
    if args.camera:
        from flowmocap.synth import read_camera_json

        camera = read_camera_json(args.camera)
        if (camera.width, camera.height) != tuple(seq.size):
            raise InputError(f"{args.camera} is for {camera.width}x{camera.height} images but the frames are "
                             f"{seq.size[0]}x{seq.size[1]}" + (" (scaled by --max-size; pass --max-size 0 to keep "
                                                             "the video's size)" if scale != 1.0 else "") + ".")
        camera_source = f"--camera {args.camera}"
    elif args.focal:
        camera = PinholeCamera.from_focal(seq.size[0], seq.size[1], args.focal * scale)
        camera_source = f"--focal {args.focal:g} px" + (f" (x {scale:.4g} for the scaled frames)" if scale != 1.0 else "")
    elif seq.camera is not None:
        camera, camera_source = seq.camera, f"{src / 'camera.json'}"
    else:
        camera, camera_source = default_camera(seq.size[0], seq.size[1], seq.meta.get("focal_35mm"))
    cfg = TrackerConfig.load(args.config, base=REAL_VIDEO if auto_masks else None, flow_method=args.flow)
    model = load_body_model(args.model, gender=args.gender)

    track = None
    if auto_masks or auto_init:  # the detections also drive re-initialisation
        from flowmocap.vision.auto import detect_sequence

        print(f"finding the person in {len(seq)} frames (MediaPipe pose; stored in {out / 'detections'}) ...")
        track = detect_sequence(seq, out, progress=not args.quiet)
        if auto_masks:
            seq.masks = list(track.mask_paths)
    frames = args.frames
    notes: dict = {"camera_source": camera_source, "masks": "automatic" if auto_masks else str(user_masks or "input"),
                   "init": "automatic" if auto_init else str(args.init),
                   "config_base": ("flowmocap.fit.config.REAL_VIDEO (automatic masks), then --config" if auto_masks
                                   else "the defaults, then --config")}
    if auto_init:
        spec, frames, range_note = _auto_start(track, frames, len(seq), out, seq.size)
        notes["frame_range"] = range_note
    else:
        spec = parse_init(args.init, *seq.size)
    if track is not None:
        notes["detections"] = {k: track.info[k] for k in ("detector", "frames_with_person", "no_person",
                                                          "ignored_people")}
    if is_video:
        notes["video"] = {k: seq.meta[k] for k in ("fps", "variable_frame_rate", "rotation", "decoded_size", "size",
                                                   "scale", "focal_35mm", "timestamps") if k in seq.meta}
        notes["video"]["max_side"] = args.max_size or None
    out.mkdir(parents=True, exist_ok=True)
    (out / "input.json").write_text(json.dumps(notes, indent=2))
    monitor = None
    if track is not None and not args.no_reinit:
        from flowmocap.fit.reinit import ReinitMonitor

        monitor = ReinitMonitor(track, cfg, out)
    detected = joints3d = None
    if track is not None:  # the detector's joints also pull the body (E_j, cfg.keypoint_weight)
        def detected(i: int):
            return track.smpl_joints(i) if i < len(track) and track.found[i] else None
        def joints3d(i: int):
            return track.smpl_joints3d(i, camera)
    elif args.joints3d == "auto" and cfg.limb_depth_weight > 0:
        from flowmocap.vision.auto import detect_joints3d

        print(f"finding the person's 3D joints in {len(seq)} frames (MediaPipe pose; for E_d) ...")
        joints3d, notes["joints3d"] = detect_joints3d(seq, out, camera, progress=not args.quiet)
        (out / "input.json").write_text(json.dumps(notes, indent=2))
    run = track_sequence(seq, out, model, camera, spec, cfg=cfg, frames=frames, resume=args.resume,
                         progress=not args.quiet, monitor=monitor, keypoints=detected, joints3d=joints3d)
    if track is not None:
        a, b = run["frames"]
        notes["gaps"] = [{"frames": r, "why": "no person found: tracked by flow alone, no silhouette term"}
                         for r in _runs([i for i in range(a, b) if not track.found[i]])]
    run.update(notes)
    write_run(out, run)
    t = run["timings"]
    reinits = sum(1 for e in run["events"] if e.get("event") == "re-initialised")
    print(f"tracked frames {run['frames'][0]}:{run['frames'][1]} of {len(seq)} into {args.out} "
          f"({t.get('s_per_frame_median', float('nan')):.2f} s per frame median; "
          f"{len(run['events'])} recorded events, {reinits} re-initialisations)")
    print(f"camera: {camera_source}")
    if "frame_range" in notes:
        print(notes["frame_range"])
    return 0


def _auto_start(track, frames, n: int, out: Path, size) -> tuple:
    """Automatic initialisation: the InitSpec, the frame range and a sentence about it."""
    from flowmocap.errors import NoPersonError
    from flowmocap.fit.init import parse_init
    from flowmocap.vision.auto import auto_init, first_person_frame

    if frames:
        from flowmocap.fit.tracker import _frame_range

        a, b = _frame_range(frames, n)
    else:
        found = [i for i in range(n) if track.found[i]]
        a, b = 0, (found[-1] + 1 if found else n)
    first = first_person_frame(track, a)
    if first is None or first >= b - 1:
        raise NoPersonError(f"no frame in {a}:{b} shows a whole enough person to start on (hips, shoulders and "
                            "at least 8 of the 12 main joints, each with confidence >= 0.5) before the last frame; "
                            "give --init init.json with the 2D joints of the first frame.")
    init = auto_init(track, first)
    (out / "init_auto.json").write_text(json.dumps(init, indent=2))
    note = f"frames {first}:{b}"
    if first > a:
        note += f"; started at frame {first}, the first with a confidently detected person (frames {a}..{first - 1} skipped)"
    if not frames and b < n:
        note += f"; stopped after frame {b - 1}, the last with the person (frames {b}..{n - 1} skipped)"
    return parse_init(init, *size), f"{first}:{b}", note


def _runs(idx: list[int]) -> list[list[int]]:
    out: list[list[int]] = []
    for i in idx:
        if out and out[-1][1] == i - 1:
            out[-1][1] = i
        else:
            out.append([i, i])
    return out


def cmd_synth(args) -> int:
    from flowmocap.synth import synthesize

    size = args.size if args.size else (None if args.camera else "640x480")
    res = synthesize(
        args.motion, args.out, fps=args.fps, start=args.start, frames=args.frames, size=size,
        focal=args.focal, distance=args.distance, azimuth=args.azimuth, elevation=args.elevation,
        camera=args.camera, betas=args.betas, gender=args.gender, seed=args.seed,
        model=args.model, asf=args.asf, flow=not args.no_flow, overwrite=args.overwrite,
    )
    meta = res.meta
    print(f"wrote {res.out_dir}: {meta['num_frames']} frames, {meta['size'][0]}x{meta['size'][1]} at "
          f"{meta['fps']:g} fps from {meta['source']} ({meta['seconds']:.1f} s)")
    return 0


def _write_png(path: Path, image) -> None:
    import imageio.v3 as iio

    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, image)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="flowmocap",
        description="3D human motion and body shape from monocular video by matching rendered "
        "and observed optical flow (Alldieck et al. 2017).",
    )
    p.add_argument("--version", action="version", version=f"flowmocap {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    d = sub.add_parser("demo", help="synthesise the built-in walk, track it, print the 3D error")
    d.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    d.add_argument("--frames", type=int, default=30)
    d.add_argument("--size", default="640x480", help="WxH (default 640x480)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.set_defaults(func=cmd_demo)

    t = sub.add_parser("track", help="fit the body to a video or frame sequence by optical flow")
    t.add_argument("input", help="a video file, a sequence folder (frames/, masks/, camera.json) or a folder of frames")
    t.add_argument("--out", required=True, help="result folder (motion.npz, run.json, detections/)")
    t.add_argument("--init", default=None, help="'auto' (default: 2D joints found by MediaPipe on the first frame "
                   "with a person) or init.json: 2D joints of the first frame, optional rough pose")
    t.add_argument("--masks", default=None, help="'auto' (MediaPipe person segmentation; the default for a video "
                   "or a folder without masks/) or a folder of person masks, one per frame (default: INPUT/masks)")
    t.add_argument("--focal", type=float, help="focal length in pixels of the video's frames (default: from the "
                   "video's metadata, else 0.9 x the long side, a 58 degree field of view)")
    t.add_argument("--camera", help="camera.json (default: INPUT/camera.json)")
    t.add_argument("--max-size", type=int, default=1280, help="scale video frames down so that the long side is "
                   "at most this many pixels (default 1280; 0 keeps the video's size)")
    t.add_argument("--no-reinit", action="store_true", help="do not re-initialise from the detector when "
                   "tracking fails (re-initialisation runs when the detector is used, i.e. with automatic init or masks)")
    t.add_argument("--joints3d", default="auto", choices=["auto", "off"], help="'auto' (default): the detector's "
                   "3D joints tell each limb's direction in depth (E_d); with your own init.json and masks the "
                   "detector then runs for them alone (MediaPipe, about 0.05 s per frame). 'off': no E_d")
    t.add_argument("--model", default="default", help="'default' or an SMPL .pkl/.npz or folder")
    t.add_argument("--gender", default="neutral", choices=["neutral", "male", "female"])
    t.add_argument("--flow", default=None, help="observed flow: dis, dis-fine, deepflow, tvl1, rlof, farneback (default: the config's flow_method)")
    t.add_argument("--config", help="JSON file overriding tracker settings (flowmocap.fit.config; with automatic "
                                    "masks it overrides the real-video settings REAL_VIDEO, which override the "
                                    "defaults)")
    t.add_argument("--frames", help="A:B, the frames to track (default: all with the person)")
    t.add_argument("--resume", action="store_true", help="continue an interrupted run in --out")
    t.add_argument("--quiet", action="store_true", help="no progress bars")
    t.set_defaults(func=cmd_track)

    b = sub.add_parser("body", help="render a body model to a PNG")
    b.add_argument("--model", default="default", help="'default' or a path to an SMPL .pkl/.npz or folder")
    b.add_argument("--gender", default="neutral", choices=["neutral", "male", "female"])
    b.add_argument("--betas", default=None, help="up to 10 shape values, comma separated")
    b.add_argument("--pose", default="rest", help="named pose: rest, walk, wave (default rest)")
    b.add_argument("--view", default="front", choices=["front", "side", "three-quarter"])
    b.add_argument("--width", type=int, default=320)
    b.add_argument("--height", type=int, default=480)
    b.add_argument("--out", default="body.png")
    b.set_defaults(func=cmd_body)
    s = sub.add_parser("synth", help="render a synthetic sequence with ground truth from mocap or builtin:walk")
    s.add_argument("motion", help="builtin:walk, a .bvh file, or a CMU .amc file (its .asf beside it)")
    s.add_argument("--out", required=True, help="sequence folder to write")
    s.add_argument("--fps", type=float, default=30.0)
    s.add_argument("--start", type=int, default=0, help="first frame (at --fps)")
    s.add_argument("--frames", type=int, help="number of frames (default: all)")
    s.add_argument("--size", help="WxH in pixels (default 640x480, or the camera's)")
    s.add_argument("--focal", type=float, help="focal length in pixels")
    s.add_argument("--distance", type=float, help="camera distance in metres (default: frame the whole path)")
    s.add_argument("--azimuth", type=float, default=60.0, help="degrees; 0 = in front of the body's start facing")
    s.add_argument("--elevation", type=float, default=8.0, help="degrees above the horizon")
    s.add_argument("--camera", help="camera.json to use instead of the placement options")
    s.add_argument("--betas", help="'random' or up to 10 comma-separated shape values")
    s.add_argument("--gender", choices=["neutral", "male", "female"], default="neutral")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--model", default="default")
    s.add_argument("--asf", help="ASF skeleton for an .amc file (default: found beside it)")
    s.add_argument("--no-flow", action="store_true", help="do not write the true flow")
    s.add_argument("--overwrite", action="store_true")
    s.set_defaults(func=cmd_synth)

    from flowmocap.commands import register_all

    register_all(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        return args.func(args)
    except FlowMocapError as e:
        print(f"flowmocap: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

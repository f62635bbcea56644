"""The ``flowmocap`` command."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from flowmocap import __version__
from flowmocap.errors import FlowMocapError, InputError

NOT_BUILT_YET = (
    "Not built yet: the tracker (flowmocap track), evaluation (flowmocap eval/bench), "
    "automatic masks and joints for real video, and exports. This demo only shows the "
    "body model; synthetic sequences with ground truth are available (flowmocap synth)."
)


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
    from flowmocap.body import load_body_model
    from flowmocap.viz.body_figure import body_sheet

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model = load_body_model("default", gender="neutral")
    print(f"default body model: {model.num_vertices} vertices, {model.faces.shape[0]} faces, "
          f"{model.num_betas} shape components ({model.source})")
    sheet = body_sheet()
    path = out / "default_body.png"
    _write_png(path, sheet)
    info = {"image": str(path), "vertices": model.num_vertices, "faces": int(model.faces.shape[0]),
            "built": ["body model", "geometry", "renderer", "mocap retargeting", "synth"],
            "not_built": NOT_BUILT_YET}
    (out / "demo.json").write_text(json.dumps(info, indent=2))
    print(f"wrote {path}")
    print(NOT_BUILT_YET)
    return 0


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

    d = sub.add_parser("demo", help="run the built-in demo (for now: renders the default body)")
    d.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    d.set_defaults(func=cmd_demo)

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

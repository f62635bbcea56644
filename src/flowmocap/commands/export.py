"""``flowmocap export RESULT --format FMT``: a result in animation and research formats."""

from __future__ import annotations

FORMAT_HELP = {
    "bvh": "skeleton with the fitted bone lengths (Blender, Maya, MotionBuilder, Unity)",
    "glb": "animated mesh sequence, glTF binary (Blender, three.js, web viewers)",
    "obj": "one .obj mesh per frame in a folder",
    "json": "per-frame joints (3D, 2D) and parameters",
    "npz": "AMASS layout (poses, trans, betas, gender, mocap_framerate; z up)",
}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export", help="write a result as BVH, glTF (.glb), OBJ, JSON or AMASS .npz",
        description="Export a result folder of `flowmocap track` (or demo's result/). 3D output is in "
        "metres with y up (a result tracked with only --focal lives in the camera frame and is turned "
        "upright); --frame world keeps the result's own world frame. Formats: "
        + "; ".join(f"{k}: {v}" for k, v in FORMAT_HELP.items()) + ".")
    p.add_argument("result", help="result folder (motion.npz, run.json)")
    p.add_argument("--format", "-f", required=True, dest="fmt", metavar="FMT",
                   help="one of: " + ", ".join(FORMAT_HELP))
    p.add_argument("--out", "-o", help="output file (a folder for obj); default RESULT/export/motion.<ext>")
    p.add_argument("--frame", default="up", choices=["up", "world"],
                   help="up: y up (default); world: the result's own world frame")
    p.add_argument("--model", default=None,
                   help="body model (default: the one recorded in run.json, else the bundled default)")
    p.add_argument("--bvh-unit", default="m", choices=["m", "cm"], help="BVH length unit (default m)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_export)


def run_export(args) -> int:
    from flowmocap.export import export_result

    path = export_result(args.result, args.fmt, out=args.out, frame=args.frame, model=args.model,
                         units_per_metre=100.0 if args.bvh_unit == "cm" else 1.0, progress=not args.quiet)
    print(f"wrote {path} ({args.fmt}: {FORMAT_HELP.get(args.fmt, '')})")
    return 0

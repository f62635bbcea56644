"""``flowmocap export RESULT --format FMT``: a result in animation and research formats."""

from __future__ import annotations

from pathlib import Path

from flowmocap.export.marker_sets import MARKER_SETS

FORMAT_HELP = {
    "bvh": "skeleton with the fitted bone lengths (Blender, Maya, MotionBuilder, Unity)",
    "glb": "glTF binary: one skinned mesh, 24-joint rig, keyframed joint rotations (Blender, three.js, engines)",
    "glb-frames": "glTF binary flipbook: one full mesh per frame (exact vertices, about 165 kB per frame)",
    "obj": "one .obj mesh per frame in a folder",
    "json": "per-frame joints (3D, 2D), parameters and foot contacts",
    "npz": "AMASS layout (poses, trans, betas, gender, mocap_framerate; z up)",
    "trc": "marker trajectories (--markers), OpenSim's text format (metres, y up: OpenSim, Pose2Sim)",
    "c3d": "marker trajectories (--markers), the motion-capture binary standard (millimetres, z up; --frame "
           "world: the result's own axes; frames without the person as gaps: Vicon, Visual3D, Mokka)",
}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export", help="write a result as BVH, glTF (.glb), OBJ, JSON, AMASS .npz, TRC or C3D",
        description="Export a result folder of `flowmocap track` (or demo's result/). 3D output is in "
        "metres in the ground frame: gravity up (+y), the floor at y = 0, estimated from the fitted feet "
        "(cached in RESULT/world.json with per-frame foot contacts); --frame up only turns the result "
        "y up, --frame world keeps the result's own world frame. Given the folder of `track --person all` "
        "(people.json), every tracked person is exported into DIR/export/personN.<ext> (or --out, a folder), all "
        "in the first person's frame (or, where the first never stands still, that of the person whose floor "
        "everyone is stood on), so the files line up. Formats: "
        + "; ".join(f"{k}: {v}" for k, v in FORMAT_HELP.items()) + ".")
    p.add_argument("result", help="result folder (motion.npz, run.json), or a `track --person all` folder")
    p.add_argument("--format", "-f", required=True, dest="fmt", metavar="FMT", action="append",
                   help="one of: " + ", ".join(FORMAT_HELP))
    p.add_argument("--out", "-o", help="output file (a folder for obj); default RESULT/export/motion.<ext> (motion_frames.glb, "
                   "motion_amass.npz, obj/ for glb-frames, npz, obj)")
    p.add_argument("--frame", default="ground", choices=["ground", "up", "world"],
                   help="ground: y up, floor at 0 (default); up: turned y up only; world: the result's own frame")
    p.add_argument("--smooth", nargs="?", const="default", default=None, metavar="SECONDS",
                   help="smooth the motion offline first (Savitzky-Golay on SO(3), flowmocap.fit.smooth); "
                   "optional window length in seconds (default 0.3)")
    p.add_argument("--smooth-order", type=int, default=None, help="polynomial degree of --smooth (default 2)")
    p.add_argument("--model", default=None,
                   help="body model (default: the one recorded in run.json, else the bundled default)")
    p.add_argument("--markers", default="joints", choices=list(MARKER_SETS),
                   help="trc and c3d: joints (the 24 joint centres, named pelvis, left_hip, ...; default) or "
                   "halpe26 (Pose2Sim's HALPE_26 keypoints Hip, RHip, ..., RHeel, as its OpenSim model "
                   "Model_Pose2Sim_Halpe26 names them: where a detector puts them on the fitted body)")
    p.add_argument("--bvh-unit", default=None, choices=["m", "cm"], help="BVH length unit (default m)")
    p.add_argument("--own-size", action="store_true",
                   help="a `track --person all` folder: each person keeps the size and distance of their own fit "
                        "(by default everyone after the first is scaled about the camera to stand on the first "
                        "person's floor)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_export)


def smooth_option(text: str | None, order: int) -> dict | bool:
    """``--smooth [SECONDS]`` and ``--smooth-order`` as the ``smooth`` argument of the API."""
    from flowmocap.errors import InputError
    from flowmocap.fit.smooth import DEFAULT_WINDOW_S

    if text is None:
        return False
    try:
        window = DEFAULT_WINDOW_S if text == "default" else float(text)
    except ValueError:
        raise InputError(f"--smooth takes a window length in seconds, e.g. 0.3; got {text!r}.") from None
    return {"window_s": window, "order": order}


def _says_finished(folder) -> bool:
    """Whether ``folder``'s ``run.json`` says its run finished, with no run in progress."""
    import json

    try:
        run = json.loads((folder / "run.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(run, dict) and run.get("status") == "finished" and not (folder / "progress.json").exists()


def rate_note(folder, fmt: str) -> str | None:
    """:func:`~flowmocap.export.motion.variable_rate_note` for ``folder``'s ``run.json``."""
    import json

    from flowmocap.export.motion import variable_rate_note

    try:
        run = json.loads((Path(folder) / "run.json").read_text())
    except (OSError, ValueError):
        return None
    return variable_rate_note(run, fmt) if isinstance(run, dict) else None


def run_export(args) -> int:
    from pathlib import Path

    from flowmocap.errors import InputError
    from flowmocap.export import export_people, export_result
    from flowmocap.io.results import PEOPLE_MANIFEST, people_results, read_result, unfinished_words

    if len(args.fmt) > 1:  # -f bvh -f json wrote json alone
        raise InputError(f"export writes one format at a time; got {', '.join(args.fmt)}: run it once for each (or "
                         "give them all to track --export, which writes each into RESULT/export/).")
    args.fmt = args.fmt[0]
    if args.bvh_unit is not None and args.fmt != "bvh":  # was ignored without a word
        raise InputError(f"--bvh-unit sets the BVH's length unit; the {args.fmt} export is in metres.")
    if args.smooth_order is not None and args.smooth is None:
        raise InputError("--smooth-order is the degree of --smooth's polynomial; give --smooth too.")
    args.smooth_order = 2 if args.smooth_order is None else args.smooth_order

    said = set()
    for _, folder in people_results(args.result) or [("", args.result)]:  # say first what is not finished
        rate = rate_note(folder, args.fmt)
        if rate and rate not in said:  # once for the people of one video
            said.add(rate)
            print(rate)
        if _says_finished(Path(folder)):  # the usual case: the export reads the motion itself, once
            continue
        motion, run = read_result(folder)
        note = unfinished_words(folder, run, len(motion["poses"]))
        if note:
            print(note)
    if (Path(args.result) / PEOPLE_MANIFEST).exists():
        paths = export_people(args.result, args.fmt, out=args.out, frame=args.frame, model=args.model,
                              units_per_metre=100.0 if args.bvh_unit == "cm" else 1.0, progress=not args.quiet,
                              smooth=smooth_option(args.smooth, args.smooth_order), markers=args.markers,
                              floor=not args.own_size, log=print)
        for path in paths:
            print(f"wrote {path} ({args.fmt}: {FORMAT_HELP.get(args.fmt, '')})")
        import json

        from flowmocap.export.floor import FLOOR_FILE

        holder = json.loads((paths[0].parent / FLOOR_FILE).read_text())["first"] if paths else None
        print(f"{len(paths)} people in one frame: {holder}'s ({args.frame})"
              + ("" if args.own_size else "; on one floor (floor.json)"))
        return 0
    if args.own_size:
        raise InputError(f"--own-size is for the folder of `track --person all`; {args.result} is one result.")
    path = export_result(args.result, args.fmt, out=args.out, frame=args.frame, model=args.model,
                         units_per_metre=100.0 if args.bvh_unit == "cm" else 1.0, progress=not args.quiet,
                         smooth=smooth_option(args.smooth, args.smooth_order), markers=args.markers)
    size = ""
    if path.is_file():
        size = f", {path.stat().st_size / 1e6:.2f} MB"
    print(f"wrote {path} ({args.fmt}: {FORMAT_HELP.get(args.fmt, '')}{size})")
    return 0

"""``flowmocap render RESULT``: overlay video, Fig.-1 flow panels, joint traces, energy plot."""

from __future__ import annotations

from pathlib import Path

from flowmocap.io.results import RENDER_OUTPUTS as OUTPUTS  # the names render writes


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help="draw a result: body-over-video MP4, flow figure, joint traces, energy plot",
        description="Render a result folder of `flowmocap track` (or demo's result/). Without any of "
        "--video/--figure1/--traces/--plot all four are written into RESULT/render/ (or --out). Each "
        "option takes an optional output path. Given the folder of `track --person all` (people.json), "
        "it writes one overlay video with every tracked person's body in its own colour.")
    p.add_argument("result", help="result folder (motion.npz, run.json), or a `track --person all` folder")
    p.add_argument("--out", help="folder for outputs given without a path (default RESULT/render)")
    p.add_argument("--video", nargs="?", const="", metavar="MP4",
                   help="the fitted body over the input video (H.264 MP4 at the tracked frames' size, after any "
                   "--max-size, one pixel more where that is odd; one frame for each of the result's)")
    p.add_argument("--side", action="store_true", help="add a side view to the video: the body as it moves in the world (the "
                   "camera's own turns, zoom and moves undone), from a camera orbited 90 degrees about the "
                   "middle of its path, far enough back to keep it in view")
    p.add_argument("--alpha", type=float, default=0.6, help="body opacity in the video, 0..1 (default 0.6)")
    p.add_argument("--figure1", nargs="?", const="", metavar="PNG",
                   help="the paper's Fig. 1 (input, observed flow, rendered flow, pose, colour key) per frame")
    p.add_argument("--traces", nargs="?", const="", metavar="PNG",
                   help="the paper's Fig. 3: fitted pose with the history of the 13 evaluated joints")
    p.add_argument("--plot", nargs="?", const="", metavar="PNG",
                   help="per-frame energies and, with ground truth, the 3D joint error")
    p.add_argument("--frames", help="input frame numbers for --figure1 and --traces, comma separated "
                   "(default: 4 spread over the result; Fig. 1 uses the middle one)")
    p.add_argument("--history", type=int, default=None, help="frames of joint history to draw (default all)")
    p.add_argument("--input", help="the tracked video or sequence folder, if it moved since tracking")
    p.add_argument("--model", default=None, help="body model (default: the one recorded in run.json)")
    p.add_argument("--own-size", action="store_true",
                   help="a `track --person all` folder: each person keeps the size and distance of their own fit "
                        "(by default everyone after the first is scaled about the camera to stand on the first "
                        "person's floor)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_render)


def _frames(text: str | None) -> list[int] | None:
    from flowmocap.errors import InputError

    if not text:
        return None
    try:
        return [int(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise InputError(f"--frames must be frame numbers separated by commas, e.g. 10,20; got {text!r}.") from None


def run_render(args) -> int:
    import imageio.v3 as iio

    from flowmocap.errors import InputError
    from flowmocap.viz.result_render import (ResultScene, default_frames, energy_figure, figure1, joint_traces,
                                             overlay_video)

    if not 0.0 <= args.alpha <= 1.0:
        raise InputError(f"--alpha must be between 0 and 1, got {args.alpha}.")
    from flowmocap.io.results import PEOPLE_MANIFEST

    wanted = {k: getattr(args, k) for k in OUTPUTS}
    if (Path(args.result) / PEOPLE_MANIFEST).exists():
        return _render_people(args, wanted)
    if args.own_size:
        raise InputError(f"--own-size is for the folder of `track --person all`; {args.result} is one result.")
    every = all(v is None for v in wanted.values())
    if every:
        wanted = {k: "" for k in OUTPUTS}
    out_dir = Path(args.out) if args.out else Path(args.result) / "render"
    paths = {k: Path(v) if v else out_dir / OUTPUTS[k] for k, v in wanted.items() if v is not None}
    _check_output_names(paths)  # before the work
    scene = ResultScene(args.result, input=args.input, model=args.model)
    from flowmocap.io.results import unfinished_words

    note = unfinished_words(args.result, scene.run, scene.num_frames)
    if note:
        print(note)
    if "video" in paths:
        from flowmocap.export.motion import variable_rate_note

        rate = variable_rate_note(scene.run, "overlay video")
        if rate:
            print(rate)
    if scene.decoded_otherwise:
        print(scene.decoded_otherwise)
    if scene.input_differs:
        print(f"note: {args.input or 'the input'} is not the input that was tracked (its content differs from the "
              "one in run.json's fingerprint); the body is drawn over it all the same")
    if every and scene.num_frames < 2:  # the figure's flow is between a frame and the one before it
        del paths["figure1"]
        print(f"{args.result} holds one frame: no Fig. 1 (its flow needs the frame before); the rest follows")
    frames = _frames(args.frames)
    written = []

    def save(key, image):  # through a temporary file: never a cut-off image under the name
        from flowmocap.atomic import atomic_write

        atomic_write(paths[key], lambda tmp: iio.imwrite(tmp, image, extension=paths[key].suffix or ".png"))
        written.append(f"{paths[key]} ({image.shape[1]}x{image.shape[0]})")

    if "figure1" in paths:
        f1 = frames or [default_frames(scene, 3)[1] if scene.num_frames > 2 else default_frames(scene, 1)[-1]]
        save("figure1", figure1(scene, f1))
    if "traces" in paths:
        save("traces", joint_traces(scene, frames or default_frames(scene, 4), history=args.history))
    if "plot" in paths:
        save("plot", energy_figure(scene))
    if "video" in paths:
        overlay_video(scene, paths["video"], alpha=args.alpha, side=args.side, progress=not args.quiet)
        written.append(f"{paths['video']} ({scene.num_frames} frames at {scene.motion.fps:g} fps)")
    for w in written:
        print(f"wrote {w}")
    return 0


#: The picture files ``render`` writes, by the name's ending (imageio's writers for them).
PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


def _check_output_names(paths: dict) -> None:
    """Refuse, before any drawing, an output whose name's ending is not a picture's (a
    video's for ``video``) or that is a folder: a ``.xyz`` failed after the work as if the
    disk were full, and ``v.png`` for the video got an MP4 under a picture's name.

    Args:
        paths: output key (:data:`OUTPUTS`) -> the file to write.

    Raises:
        InputError: a name of the wrong kind, or a folder.
    """
    from flowmocap.atomic import check_file_path
    from flowmocap.errors import InputError
    from flowmocap.viz.video import CONTAINERS

    for key, path in paths.items():
        check_file_path(path)
        ok = CONTAINERS if key == "video" else PICTURE_SUFFIXES
        if path.suffix.lower() not in ok:
            raise InputError(f"--{key} {path}: give a name ending in {', '.join(ok)} "
                             f"({'a video' if key == 'video' else 'a picture'}).")


def _render_people(args, wanted: dict) -> int:
    """``flowmocap render DIR`` on a ``track --person all`` folder: the people's overlay video."""
    from flowmocap.errors import InputError
    from flowmocap.io.results import PEOPLE_MANIFEST, people_results
    from flowmocap.viz.result_render import ResultScene, people_overlay_video

    root = Path(args.result)
    others = [f"--{k}" for k, v in wanted.items() if v is not None and k != "video"] + (["--side"] if args.side else [])
    if others:
        raise InputError(f"{root} holds several people's results ({PEOPLE_MANIFEST}); {', '.join(others)} draw one "
                         f"result: render a person's folder ({root / 'person0'}, ...) for them.")
    path = Path(wanted["video"]) if wanted.get("video") else (Path(args.out) if args.out else root / "render") / \
        OUTPUTS["video"]
    _check_output_names({"video": path})
    scenes, names = [], []
    folders = people_results(root)
    for name, folder in folders:
        scenes.append(ResultScene(folder, input=args.input, model=args.model))
        names.append(name)
    if not args.own_size and len(folders) > 1:  # everyone stood on one floor: who is nearer is drawn
        from flowmocap.export.floor import floor_owner, people_floor, scaled_about_camera

        fits = people_floor([d for _, d in folders], model=args.model)
        owner = floor_owner(fits)
        for k, fit in enumerate(fits):
            print(fit.describe(names[k], names[owner]))
            if k != owner and fit.scale is not None:
                scenes[k].motion = scaled_about_camera(scenes[k].motion, fit.scale)
    path.parent.mkdir(parents=True, exist_ok=True)
    from flowmocap.export.motion import variable_rate_note

    for note in dict.fromkeys([variable_rate_note(scenes[0].run, "overlay video"), scenes[0].decoded_otherwise]):
        if note:
            print(note)
    people_overlay_video(scenes, path, names=names, alpha=args.alpha, progress=not args.quiet)
    first = min(int(sc.motion.frame_index.min()) for sc in scenes)
    last = max(int(sc.motion.frame_index.max()) for sc in scenes)
    print(f"wrote {path} ({', '.join(names)}; frames {first}-{last} at {scenes[0].motion.fps:g} fps)")
    return 0

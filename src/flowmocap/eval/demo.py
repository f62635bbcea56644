"""The built-in demo: synthesise the built-in walk, track it from a perturbed init, score it."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from flowmocap.errors import InputError
from flowmocap.eval.protocol import evaluate, noisy_init
from flowmocap.io.results import has_result
from flowmocap.io.sequence import load_sequence
from flowmocap.pipeline import track
from flowmocap.synth import synthesize


#: What a demo folder holds (besides nothing): a folder with other files is the user's.
DEMO_FILES = ("sequence", "result", "init.json", "eval.json", "default_body.png")


def _own_temporary(name: str) -> bool:
    """Whether ``name`` is the temporary of one of the demo's files (``NAME.XXXX.tmp``,
    :func:`flowmocap.atomic.atomic_write`), left by a demo killed while it wrote it."""
    return name.endswith(".tmp") and any(name.startswith(f"{f}.") for f in DEMO_FILES)


def check_demo(out_dir: str | Path, frames: int, size: str, seed: int, fps: float = 30.0) -> None:
    """Refuse the demo's arguments before anything is written (``InputError``): an empty or
    file ``out_dir``, one that holds files other than a demo's (:data:`DEMO_FILES`), fewer
    than 2 frames (tracking needs two), a bad size, a seed that is not a whole number >= 0,
    and what :func:`flowmocap.synth.synthesize` refuses of the frame count and rate."""
    from flowmocap.synth.sequence import MAX_SYNTH_FRAMES, SYNTH_FPS_RANGE, parse_size

    if not str(out_dir).strip():
        raise InputError("the demo's folder (--out) is empty; give the path of a new folder.")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out} is a file; the demo writes into a folder: give a new folder.")
    others = sorted(p.name for p in out.iterdir() if p.name not in DEMO_FILES and not _own_temporary(p.name)
                    ) if out.is_dir() else []
    if others:
        shown = ", ".join(others[:5]) + (", ..." if len(others) > 5 else "")
        raise InputError(f"{out} is not empty ({shown}) and holds no flowmocap demo; give a new or empty folder.")
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or not 2 <= frames <= MAX_SYNTH_FRAMES:
        raise InputError(f"the demo tracks 2..{MAX_SYNTH_FRAMES} frames (the flow is between neighbouring frames); "
                         f"got {frames!r}.")
    parse_size(size)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be a whole number >= 0; got {seed!r}.")
    if not SYNTH_FPS_RANGE[0] <= fps <= SYNTH_FPS_RANGE[1]:
        raise InputError(f"fps must be {SYNTH_FPS_RANGE[0]:g}..{SYNTH_FPS_RANGE[1]:g}; got {fps!r}.")


def run_demo(out_dir: str | Path = "demo_out", frames: int = 40, size: str = "640x480", fps: float = 30.0,
             seed: int = 0, progress: bool = True, config: dict | None = None) -> dict:
    """Synthesise ``builtin:walk`` with a random body shape, track it, write ``eval.json``.

    The tracker starts from the mean shape, the ground-truth 2D joints of frame 0 with
    3 px noise and a rough pose with 15 degrees of noise on the main joints, through
    :func:`flowmocap.pipeline.track` as ``flowmocap track SEQ --init init.json`` does
    (``config``: settings over the ``synthetic`` profile).

    Returns:
        the contents of ``out_dir/eval.json``: ``local_cm``, ``global_cm``, ``mpjpe_cm``,
        ``s_per_frame`` (median), ``frames`` and the settings.
    """
    check_demo(out_dir, frames, size, seed, fps)
    out_dir = Path(out_dir)
    for p in out_dir.glob("*.tmp") if out_dir.is_dir() else []:  # a stopped demo's half-written file
        if _own_temporary(p.name):
            p.unlink(missing_ok=True)
    seq_dir, res_dir = out_dir / "sequence", out_dir / "result"
    t0 = time.perf_counter()
    fresh = not _same_clip(seq_dir, frames, size, seed, fps)
    if fresh:  # none yet, or one made with other settings: (re)made, and the result with it
        synthesize("builtin:walk", seq_dir, fps=fps, frames=frames, size=size, betas="random", seed=seed,
                   azimuth=60.0, flow=False, overwrite=True)
    synth_s = time.perf_counter() - t0
    seq = load_sequence(seq_dir)
    init = noisy_init(seq.gt, frame=0, seed=seed)
    (out_dir / "init.json").write_text(json.dumps(init, indent=2))
    t1 = time.perf_counter()
    kw = dict(init=init, config=config, gender=str(seq.meta.get("gender", "neutral")), progress=progress, log=None)
    try:
        result = track(seq_dir, res_dir, resume=has_result(res_dir) and not fresh, force=fresh, **kw)
    except InputError as e:
        if not str(e).startswith("cannot resume"):
            raise
        # the demo's own earlier result, made with other settings (e.g. by an older version): start over
        result = track(seq_dir, res_dir, force=True, **kw)
    track_s = time.perf_counter() - t1
    run, motion = result.run, result.motion
    scores = evaluate(motion, seq.gt)
    scores.update({
        "s_per_frame": run["timings"].get("s_per_frame_median"),
        "init_s": run["timings"].get("init_s"),
        "synth_s": synth_s,
        "track_s": track_s,
        "size": seq.size,
        "fps": fps,
        "seed": seed,
        "gt_betas": np.asarray(seq.gt["betas"]).round(3).tolist(),
        "fitted_betas": np.asarray(motion["betas"]).round(3).tolist(),
        "events": run.get("events", []),
    })
    (out_dir / "eval.json").write_text(json.dumps(scores, indent=2))
    return scores


def _same_clip(seq_dir: Path, frames: int, size: str, seed: int, fps: float) -> bool:
    """Whether ``seq_dir`` holds the demo's clip made with these settings (its ``meta.json``)."""
    from flowmocap.synth.sequence import parse_size

    try:
        meta = json.loads((seq_dir / "meta.json").read_text())
    except (OSError, ValueError):
        return False
    return ((seq_dir / "gt.npz").exists() and isinstance(meta, dict) and meta.get("num_frames") == frames
            and meta.get("size") == list(parse_size(size)) and meta.get("seed") == seed
            and meta.get("fps") == fps and meta.get("source") == "builtin:walk")


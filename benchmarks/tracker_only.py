"""The diverse suite with other tracker settings, tracker only: a quarter faster than
``flowmocap bench`` because the per-frame baseline is not fitted again.

The baseline does not depend on the tracker's settings, so its rows are taken from a
reference ``bench.json`` of the same suite (``--reference``; the sequences' settings must
match, or the script stops). Each sequence is synthesised (unless present) and tracked
exactly as ``flowmocap bench --suite diverse --config CFG`` does it
(:func:`flowmocap.eval.bench.run_method`, one fresh process per sequence, ``--jobs`` at
once); the detector-3D row is scored again from the run's own detections. Writes
``OUT/bench.json`` and ``OUT/bench.md`` in the bench's format, so
``benchmarks/compare_bench.py REF OUT/bench.json`` compares the two. Re-running resumes
(finished tracks are kept).

Usage: python benchmarks/tracker_only.py --config cfg.json --out DIR
       [--reference benchmarks/results/diverse_after_speed.json] [--jobs 2] [--suite diverse|tune]

``--suite tune``: the train clips of ``flowmocap bench --suite tune`` instead (tracker
only, no baseline rows, no reference needed).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _synthesise(spec, seq_dir: Path) -> None:
    from flowmocap.errors import InputError
    from flowmocap.synth import synthesize

    kw = dict(fps=spec.fps, size=spec.size, betas="random", seed=spec.seed, azimuth=spec.azimuth,
              distance=spec.distance, flow=False, overwrite=True, start=spec.start)
    try:
        synthesize(spec.motion, seq_dir, frames=spec.frames, **kw)
    except InputError as e:  # as the bench does: a motion shorter than the window is used whole
        if "requested but the motion has" not in str(e):
            raise
        synthesize(spec.motion, seq_dir, frames=None, **kw)


def track_one(spec, out: str, cfg: dict | None) -> dict:
    """Synthesise (unless present), track (unless finished) and score one sequence;
    returns ``{"name", "flowmocap", "detector3d", "wall_s"}`` or ``{"name", "error"}``."""
    from flowmocap.eval.bench import METRICS, _finished, run_method
    from flowmocap.eval.protocol import noisy_init
    from flowmocap.eval.scoring import score_detector3d, score_result
    from flowmocap.io.sequence import load_sequence

    t0 = time.perf_counter()
    try:
        d = Path(out) / spec.name
        if not (d / "sequence" / "gt.npz").exists():
            _synthesise(spec, d / "sequence")
        seq = load_sequence(d / "sequence")
        init = noisy_init(seq.gt, frame=0, seed=spec.seed)
        (d / "init.json").write_text(json.dumps(init, indent=2))
        if not _finished(d / "flowmocap"):
            run_method(method="flowmocap", seq_dir=str(d / "sequence"), res_dir=str(d / "flowmocap"), init=init,
                       baseline_seed=spec.seed + 1, progress=False, tracker_config=cfg)
        s = score_result(d / "flowmocap", seq)
        s.pop("local_cm_per_frame", None)
        s.pop("iou_per_frame", None)
        det = score_detector3d(d / "flowmocap", seq)
        if det is not None:
            det.pop("local_cm_per_frame", None)
        entry = {**{k: s.get(k) for k in METRICS}, **{k: v for k, v in s.items() if k not in METRICS}}
        return {"name": spec.name, "flowmocap": entry, "detector3d": det, "wall_s": time.perf_counter() - t0}
    except Exception as e:  # noqa: BLE001 -- reported per sequence; the others go on
        return {"name": spec.name, "error": f"{type(e).__name__}: {e}"}


def main() -> int:
    from flowmocap.eval.bench import _write, commit, diverse_specs, format_table, summarise, tune_specs
    from flowmocap.fit.config import TrackerConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", required=True, help="tracker settings JSON (fields of TrackerConfig)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--reference", default=str(ROOT / "benchmarks" / "results" / "diverse_after_speed.json"),
                    help="a bench.json of the diverse suite: its baseline rows are reused")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--suite", choices=("diverse", "tune"), default="diverse",
                    help="tune: the train clips of flowmocap bench --suite tune, without baseline rows "
                         "(--reference is not read)")
    args = ap.parse_args()
    cfg = json.loads(Path(args.config).read_text())
    TrackerConfig.load(None, **cfg)  # a bad setting stops here, not in a worker
    if args.suite == "tune":
        ref = {"settings": {"suite": "tune"}, "commit": None,
               "sequences": {s.name: {"settings": asdict(s)} for s in tune_specs()}}
        specs = tune_specs()
    else:
        ref = json.loads(Path(args.reference).read_text())
        specs = diverse_specs()
    for spec in specs:
        theirs = (ref["sequences"].get(spec.name) or {}).get("settings", {})
        ours = {k: v for k, v in asdict(spec).items() if k != "frames"}
        if {k: theirs.get(k) for k in ours} != ours:
            raise SystemExit(f"{args.reference} was not made from the same {spec.name} ({theirs} against {ours}); "
                             "run the whole bench instead.")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with ProcessPoolExecutor(args.jobs, mp_context=mp.get_context("spawn")) as ex:
        done = list(ex.map(track_one, specs, [str(out)] * len(specs), [cfg] * len(specs)))
    result = {"commit": commit(), "suite": args.suite, "settings": {
        **ref["settings"], "tracker": TrackerConfig.load(None, **cfg).to_dict(),
        "baseline_rows_from": f"{args.reference} (commit {ref.get('commit')}): benchmarks/tracker_only.py"},
        "sequences": {}}
    for spec, r in zip(specs, done):
        if "error" in r:
            print(f"[{spec.name}] failed: {r['error']}")
            continue
        entry = dict(ref["sequences"][spec.name])
        entry.update(flowmocap=r["flowmocap"], detector3d=r["detector3d"], wall_s=round(r["wall_s"], 1))
        result["sequences"][spec.name] = entry
    result["summary"] = summarise(result)
    _write(out, result)
    print(format_table(result))
    return 0 if len(result["sequences"]) == len(specs) else 1


if __name__ == "__main__":
    raise SystemExit(main())

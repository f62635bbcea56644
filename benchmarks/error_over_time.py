"""How a suite's local error runs through each clip: the start against the rest (issue 18).

The diverse protocol gives the tracker a noisy true start; a run tracked as a user's video
(``--as-video``) starts from the detector. This script splits each clip's per-frame local
error (a similarity Procrustes per frame on the paper's 13 joints, as ``flowmocap bench``
scores it) by time: the first ``--head`` frames, then the clip in thirds. It prints, for each
bench folder given, the part means per clip and their medians over the clips, and writes them
to JSON. Each folder's median is over its own finished clips; clips are not paired across folders.

Usage: python benchmarks/error_over_time.py DIR [DIR ...] [--labels A,B,...] [--head 10] [--json F]
  DIR: a ``flowmocap bench --suite diverse|tune [--as-video]`` folder (each clip's
  ``sequence/gt.npz`` and ``flowmocap/motion.npz``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

PARTS = 3


def parts(errors: np.ndarray, head: int = 10, count: int = PARTS) -> list[float]:
    """``[mean of the first head frames, mean of each of count equal stretches]`` of a clip's
    per-frame errors ``(T,)`` (any unit; :func:`numpy.array_split` cuts the stretches, so
    the first ones take the extra frame)."""
    e = np.asarray(errors, np.float64).reshape(-1)
    if e.size < max(count, 1):
        raise ValueError(f"a clip of {e.size} frames cannot be cut into {count} parts")
    return [float(e[:head].mean())] + [float(c.mean()) for c in np.array_split(e, count)]


def clip_errors(clip_dir: Path) -> np.ndarray:
    """``(T,)`` the per-frame local error (cm) of a bench clip folder's flowmocap run."""
    from flowmocap.eval import metrics
    from flowmocap.io.results import read_result
    from flowmocap.io.sequence import load_sequence

    motion, _ = read_result(clip_dir / "flowmocap")
    idx = np.asarray(motion["frame_index"], int)
    gt = np.asarray(load_sequence(clip_dir / "sequence").gt["joints3d"], np.float64)[idx]
    return 100.0 * metrics.local_procrustes_error(np.asarray(motion["joints3d"], np.float64), gt)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+", type=Path)
    ap.add_argument("--labels", default=None, help="comma-separated names of the folders (default: their names)")
    ap.add_argument("--head", type=int, default=10, help="frames counted as the start (default 10)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    labels = a.labels.split(",") if a.labels else [d.name for d in a.dirs]
    if len(labels) != len(a.dirs):
        ap.error("give one label per folder")
    cols = [f"first {a.head}"] + [f"part {k + 1}/{PARTS}" for k in range(PARTS)]
    out = {"head": a.head, "columns": cols, "runs": {}}
    for label, d in zip(labels, a.dirs):
        clips = {c.name: parts(clip_errors(c), a.head) for c in sorted(d.iterdir())
                 if (c / "flowmocap" / "motion.npz").exists() and (c / "sequence").is_dir()}
        if not clips:
            raise SystemExit(f"{d} holds no finished bench clips (CLIP/flowmocap/motion.npz with CLIP/sequence)")
        med = np.median(np.array(list(clips.values())), axis=0)
        out["runs"][label] = {"dir": str(d), "clips": clips, "median": med.tolist()}
    print("| run | clips | " + " | ".join(cols) + " |")
    print("|---|---:|" + "---:|" * len(cols))
    for label, r in out["runs"].items():
        print(f"| {label} | {len(r['clips'])} | " + " | ".join(f"{v:.2f}" for v in r["median"]) + " |")
    print("\nmedian over the clips of each part's mean local error, cm")
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()

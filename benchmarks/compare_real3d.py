"""Two `flowmocap bench --suite real3d` runs side by side (e.g. a setting off and on).

Prints a Markdown table: per person-view, flowmocap's per-frame and per-sequence
PA-MPJPE (mm) in run A and run B and the detector-3D row's (MediaPipe's world landmarks,
from run B: it does not depend on the tracker's settings); the means over the person-views
both runs scored; issue 18's target figures for each run (mean per-frame error over the
detector's, and on how many person-views it is worse than the detector); then how many
person-views B makes better and worse than A by more than ``--chance`` mm (per frame and
per sequence) with a Wilcoxon signed-rank p of the per-view differences.

The tracker is chaotic: a rounding-level change of one weight (``flow_weight`` 1.000001)
moves single person-views by tens of millimetres (docs/experiments.md, "How much real3d
moves by chance"), so with 8 person-views only a change that beats that spread on most of
them means something. Writes the same as JSON with ``--json``.

Usage: python benchmarks/compare_real3d.py A/real3d.json B/real3d.json [--names a,b] [--chance 10] [--json out.json]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy.stats import wilcoxon

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_bench import read_pair  # noqa: E402  (benchmarks/, the script's own folder)

#: mm: per-person-view moves below this are counted as no change (see the module docstring)
CHANCE_MM = 10.0
KEYS = ("per_frame_mm", "per_sequence_mm")


def rows(a: dict, b: dict) -> list[dict]:
    """One row per person-view scored in both runs: ``name``, ``a_*`` / ``b_*`` for the
    two :data:`KEYS` (flowmocap), ``detector_per_frame_mm`` and ``detector_per_sequence_mm``
    (from ``b``), ``frames`` (B's frames scored)."""
    def scored(run):
        return {f"{r['person']}@{r['view']}": r for r in run["rows"]
                if isinstance(r.get("flowmocap"), dict) and not r.get("failed")}

    ra, rb = scored(a), scored(b)
    out = []
    for name, x in ra.items():
        y = rb.get(name)
        if y is None:
            continue
        row = {"name": name, "frames": y.get("frames_scored")}
        for k in KEYS:
            row[f"a_{k}"] = x["flowmocap"][k]
            row[f"b_{k}"] = y["flowmocap"][k]
            row[f"detector_{k}"] = (y.get("detector3d") or {}).get(k)
        out.append(row)
    return out


def paired(table: list[dict], chance_mm: float = CHANCE_MM) -> dict:
    """B against A per person-view, for each of :data:`KEYS`: how many B makes better /
    worse by more than ``chance_mm``, the median difference B - A (mm) and the two-sided
    Wilcoxon signed-rank p (None below 6 person-views or when all differences are 0)."""
    out = {"chance_mm": chance_mm}
    for k in KEYS:
        d = np.array([r[f"b_{k}"] - r[f"a_{k}"] for r in table], float)
        p = float(wilcoxon(d).pvalue) if d.size >= 6 and np.any(d != 0) else None
        out[k] = {"better": int((d < -chance_mm).sum()), "worse": int((d > chance_mm).sum()),
                  "median_difference_mm": float(np.median(d)) if d.size else None,
                  "largest_move_mm": float(np.abs(d).max()) if d.size else None, "wilcoxon_p": p}
    return out


def summary(table: list[dict]) -> dict:
    """Means over the person-views; per run the target figures of issue 18: mean
    per-frame error over the detector's (``ratio``) and the views worse than it."""
    s = {"person_views": len(table)}
    for k in [f"{r}_{key}" for r in ("a", "b", "detector") for key in KEYS]:
        v = [r[k] for r in table if r[k] is not None]
        s[f"mean_{k}"] = float(np.mean(v)) if v else None
    det = s["mean_detector_per_frame_mm"]
    for run in ("a", "b"):
        s[f"{run}_ratio"] = s[f"mean_{run}_per_frame_mm"] / det if det else None
        s[f"{run}_worse_than_detector"] = sum(1 for r in table if r["detector_per_frame_mm"] is not None
                                              and r[f"{run}_per_frame_mm"] > r["detector_per_frame_mm"])
    return s


def main() -> int:
    args, a, b, na, nb = read_pair(__doc__.splitlines()[0], CHANCE_MM,
                                   "mm: per-person-view differences counted as a change only beyond this")
    table = rows(a, b)
    if not table:
        raise SystemExit("no person-view is scored in both runs")
    s = summary(table)

    def f(v):
        return "--" if v is None else f"{v:.1f}"

    print(f"| person-view | frames | {na} per-frame | {nb} per-frame | detector-3D per-frame | "
          f"{na} per-sequence | {nb} per-sequence | detector-3D per-sequence |")
    print("|---|---:|" + "---:|" * 6)
    for r in table:
        print(f"| {r['name']} | {r['frames']} | {f(r['a_per_frame_mm'])} | {f(r['b_per_frame_mm'])} | "
              f"{f(r['detector_per_frame_mm'])} | {f(r['a_per_sequence_mm'])} | {f(r['b_per_sequence_mm'])} | "
              f"{f(r['detector_per_sequence_mm'])} |")
    print(f"| **mean** ({s['person_views']}) | | " + " | ".join(
        f(s[f"mean_{k}"]) for k in ("a_per_frame_mm", "b_per_frame_mm", "detector_per_frame_mm", "a_per_sequence_mm",
                                     "b_per_sequence_mm", "detector_per_sequence_mm")) + " |")
    for run, name in (("a", na), ("b", nb)):
        print(f"\n{name}: per-frame mean / detector-3D's {s[f'{run}_ratio']:.2f}; worse than the detector on "
              f"{s[f'{run}_worse_than_detector']} of {len(table)} person-views")
    pr = paired(table, args.chance)
    for k in KEYS:
        q = pr[k]
        pv = "--" if q["wilcoxon_p"] is None else f"{q['wilcoxon_p']:.2f}"
        print(f"\n{nb} against {na}, {k[:-3].replace('_', '-')}: better on {q['better']}, worse on {q['worse']} of "
              f"{len(table)} by more than {args.chance:g} mm; median difference {q['median_difference_mm']:+.1f} mm, "
              f"largest move {q['largest_move_mm']:.1f}; Wilcoxon signed-rank p {pv}")
    if args.json:
        Path(args.json).write_text(json.dumps({"a": args.a, "b": args.b, "names": [na, nb], "rows": table,
                                               "summary": s, "paired": pr}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Two `flowmocap bench` runs of one suite side by side (e.g. a setting off and on).

Prints a Markdown table: per sequence, flowmocap's local / global error (cm) and 2D error
(px) in run A and run B, with the baseline's and the detector-3D row's local / global
error (from run A: they do not depend on the tracker's settings); then the medians and
means over the sequences both runs finished, and the ratios the issue-18 targets are
stated in; then how many sequences B makes better and worse than A by more than
``--chance`` cm (local and global) with a Wilcoxon signed-rank test of the per-sequence
differences. The tracker is chaotic: a rounding-level change of one weight moved 5 of the
16 diverse clips by more than 0.4 cm local, up to 2.6 cm, and even gave a signed-rank p of
0.07 (docs/experiments.md, "How much the diverse suite moves by chance"), so a difference
is worth believing only well beyond that. Writes the same as JSON with ``--json``.

Usage: python benchmarks/compare_bench.py A/bench.json B/bench.json [--names off,on] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.stats import wilcoxon

#: cm: per-sequence moves below this are within a rounding-level perturbation's spread for
#: most clips (docs/experiments.md, "How much the diverse suite moves by chance").
CHANCE_CM = 0.4


def rows(a: dict, b: dict) -> list[dict]:
    out = []
    for name, ea in a["sequences"].items():
        eb = b["sequences"].get(name)
        fa, fb = ea.get("flowmocap"), (eb or {}).get("flowmocap")
        if not (isinstance(fa, dict) and isinstance(fb, dict) and fa.get("local_cm") is not None
                and fb.get("local_cm") is not None):
            continue
        det = ea.get("detector3d") or {}
        base = ea.get("baseline") or {}
        out.append({"sequence": name, "kind": ea.get("settings", {}).get("kind", ""),
                    "a_local": fa["local_cm"], "a_global": fa["global_cm"], "a_px": fa.get("px2d"),
                    "b_local": fb["local_cm"], "b_global": fb["global_cm"], "b_px": fb.get("px2d"),
                    "baseline_local": base.get("local_cm"), "baseline_global": base.get("global_cm"),
                    "detector3d_local": det.get("local_cm")})
    return out


def summary(table: list[dict]) -> dict:
    def col(k):
        return np.array([r[k] for r in table if r[k] is not None], float)

    s = {f"{stat}_{k}": (float(fn(col(k))) if col(k).size else None)
         for k in table[0] if k not in ("sequence", "kind") for stat, fn in (("median", np.median), ("mean", np.mean))}
    for run in ("a", "b"):
        s[f"{run}_global_vs_baseline"] = s[f"median_{run}_global"] / s["median_baseline_global"]
        det = s["median_detector3d_local"]
        s[f"{run}_local_vs_detector3d"] = s[f"median_{run}_local"] / det if det else None
    s["sequences"] = len(table)
    return s


def paired(table: list[dict], chance_cm: float = CHANCE_CM) -> dict:
    """B against A per sequence: for ``local`` and ``global``, the number of sequences B
    makes better / worse by more than ``chance_cm`` cm, the median difference B - A (cm)
    and the two-sided Wilcoxon signed-rank p of the differences (None below 6 sequences
    or when all differences are 0)."""
    out = {"chance_cm": chance_cm}
    for k in ("local", "global"):
        d = np.array([r[f"b_{k}"] - r[f"a_{k}"] for r in table], float)
        p = None
        if d.size >= 6 and np.any(d != 0):
            p = float(wilcoxon(d).pvalue)
        out[k] = {"better": int((d < -chance_cm).sum()), "worse": int((d > chance_cm).sum()),
                  "median_difference_cm": float(np.median(d)), "wilcoxon_p": p}
    return out


def read_pair(description: str, chance: float, chance_help: str):
    """The command line of a two-run comparison (``A B [--names a,b] [--json F] [--chance X]``):
    ``(args, run A, run B, name A, name B)``, the runs read from their JSON files."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--names", default="A,B")
    ap.add_argument("--json", default=None)
    ap.add_argument("--chance", type=float, default=chance, help=chance_help)
    args = ap.parse_args()
    a, b = (json.loads(Path(p).read_text()) for p in (args.a, args.b))
    na, nb = args.names.split(",")
    return args, a, b, na, nb


def main() -> int:
    args, a, b, na, nb = read_pair(__doc__.splitlines()[0], CHANCE_CM,
                                   "cm: per-sequence differences counted as a change only beyond this")
    table = rows(a, b)
    if not table:
        raise SystemExit("no sequence is finished in both runs")
    s = summary(table)

    def f(v):
        return "--" if v is None else f"{v:.1f}"

    print(f"| sequence | kind | {na} local | {na} global | {na} 2D px | {nb} local | {nb} global | {nb} 2D px | "
          "baseline local | baseline global | detector-3D local |")
    print("|---|---|" + "---:|" * 9)
    for r in table:
        print(f"| {r['sequence']} | {r['kind']} | {f(r['a_local'])} | {f(r['a_global'])} | {f(r['a_px'])} | "
              f"{f(r['b_local'])} | {f(r['b_global'])} | {f(r['b_px'])} | {f(r['baseline_local'])} | "
              f"{f(r['baseline_global'])} | {f(r['detector3d_local'])} |")
    for stat in ("median", "mean"):
        print(f"| **{stat}** ({s['sequences']}) | | " + " | ".join(
            f(s[f"{stat}_{k}"]) for k in ("a_local", "a_global", "a_px", "b_local", "b_global", "b_px",
                                           "baseline_local", "baseline_global", "detector3d_local")) + " |")
    for run, name in (("a", na), ("b", nb)):
        print(f"\n{name}: global / baseline global (medians) {s[f'{run}_global_vs_baseline']:.2f}; local / "
              f"detector-3D local (medians) {s[f'{run}_local_vs_detector3d']:.2f}")
    pr = paired(table, args.chance)
    for k in ("local", "global"):
        q = pr[k]
        pv = "--" if q["wilcoxon_p"] is None else f"{q['wilcoxon_p']:.2f}"
        print(f"\n{nb} against {na}, {k}: better on {q['better']}, worse on {q['worse']} of {len(table)} by more "
              f"than {args.chance:g} cm; median difference {q['median_difference_cm']:+.2f} cm; "
              f"Wilcoxon signed-rank p {pv}")
    if args.json:
        Path(args.json).write_text(json.dumps({"a": args.a, "b": args.b, "names": [na, nb], "rows": table,
                                               "summary": s, "paired": pr}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

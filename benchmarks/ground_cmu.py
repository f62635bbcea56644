"""How well the floor is found (flowmocap.export.world) on finished synthetic protocol runs.

The synthetic sequences live in a y-up world whose floor is level, so the floor's normal
should be +y. For every run folder ``RUNS/*/`` (``sequence/`` with ``gt.npz`` and a result
in ``new/result``, ``result`` or ``flowmocap``) the world frame is computed twice, from the
fitted motion and from the ground-truth motion of the same frames, and the angle between
each floor normal and +y is reported, with the fraction of frames labelled as foot contacts
and how the fit's contact labels agree with those computed from the true motion.

    python benchmarks/ground_cmu.py --runs RUNS --out benchmarks/results/ground_cmu.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from flowmocap.body import load_body_model
from flowmocap.export import load_fitted_motion
from flowmocap.export.world import world_frame
from flowmocap.io.sequence import load_sequence


def _tilt_deg(n) -> float:
    n = np.asarray(n, np.float64)
    return float(np.degrees(np.arccos(np.clip(n[1] / np.linalg.norm(n), -1.0, 1.0))))


def run(runs: Path) -> list[dict]:
    rows = []
    for d in sorted(p for p in runs.iterdir() if p.is_dir()):
        result = next((p for p in (d / "new" / "result", d / "result", d / "flowmocap")
                       if (p / "motion.npz").is_file()), None)
        if result is None or not (d / "sequence" / "gt.npz").is_file():
            continue
        m = load_fitted_motion(result, frame="world", cache_world=False)
        fit = world_frame(m.poses, m.trans, m.betas, m.model, m.camera, m.fps)
        gt = load_sequence(d / "sequence").gt
        model = load_body_model("default", gender=str(gt.get("gender", m.gender)), dtype=torch.float64)
        idx = m.frame_index
        truth = world_frame(gt["poses"][idx], gt["trans"][idx], gt["betas"], model, m.camera, m.fps)
        rows.append({"run": d.name, "method": fit.plane.method, "fit_tilt_deg": _tilt_deg(fit.plane.normal),
                     "fit_prior_tilt_deg": _tilt_deg(fit.prior_up), "gt_tilt_deg": _tilt_deg(truth.plane.normal),
                     "fit_residual_mm": 1000 * fit.plane.residual_m, "fit_contacts": float(fit.contacts.mean()),
                     "gt_contacts": float(truth.contacts.mean()),
                     # agreement of the fit's per-frame contact labels with the true motion's
                     "tp": int((fit.contacts & truth.contacts).sum()), "fp": int((fit.contacts & ~truth.contacts).sum()),
                     "fn": int((~fit.contacts & truth.contacts).sum())})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", required=True, help="folder of run folders, each with sequence/ (gt.npz) and a result "
                    "in new/result, result or flowmocap")
    ap.add_argument("--out", default="benchmarks/results/ground_cmu.json", help="JSON output")
    args = ap.parse_args()
    rows = run(Path(args.runs))
    print("| run | floor from | tilt of the fit's floor (deg) | body-up prior (deg) | tilt from the truth's motion (deg) "
          "| contact frames fit / truth |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['run']} | {r['method']} | {r['fit_tilt_deg']:.2f} | {r['fit_prior_tilt_deg']:.2f} | "
              f"{r['gt_tilt_deg']:.2f} | {r['fit_contacts']:.2f} / {r['gt_contacts']:.2f} |")
    med = {k: float(np.median([r[k] for r in rows])) for k in ("fit_tilt_deg", "gt_tilt_deg")}
    tp, fp, fn = (sum(r[k] for r in rows) for k in ("tp", "fp", "fn"))
    med["contact_precision"] = tp / max(tp + fp, 1)
    med["contact_recall"] = tp / max(tp + fn, 1)
    print(f"median tilt: fit {med['fit_tilt_deg']:.2f} deg, truth's motion {med['gt_tilt_deg']:.2f} deg "
          f"({len(rows)} runs); contact labels of the fit against the true motion's: precision "
          f"{med['contact_precision']:.2f}, recall {med['contact_recall']:.2f}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"rows": rows, "median": med}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""The two people of the four-camera recording, seen from one camera, stood on one floor.

``flowmocap track VIDEO --person all`` fits each person alone, so each body's size (and with
it its distance from the camera) is its own fit's. ``flowmocap export / view / render`` on the
people folder then scale every person after the first about the camera centre so that their
standing feet rest on the first person's floor (:mod:`flowmocap.export.floor`). This script
measures that step against the four-camera reference of ``flowmocap bench --suite real3d``:
for every camera and each choice of whose floor is shared, on the frames both people are
scored in,

- **depth ratio**: the median over frames of ``|log((z_o / z_f) / (z_o_ref / z_f_ref))|``,
  ``z`` the depth of a person's hip centre in that camera (``f`` the person whose floor is
  shared, ``o`` the other); 0 when the two are at the right relative depths, whatever the
  overall scale (one camera and a guessed focal length leave that open);
- **gap**: the median over frames of ``| |h_o - h_f| / z_f - (the same, reference) |``, the
  distance between the two hip centres as a share of the first person's depth;
- **size**: the other person's bone lengths over the first's (median over the 14 bones of
  :data:`flowmocap.eval.real3d.BONES`), against the reference's;
- **image**: how far the other person's joints move in the image (px, median and 90th
  percentile), which the scaling should leave where they were.

Usage::

    python benchmarks/people_floor.py REAL3D_DIR [REAL3D_DIR ...] [--out benchmarks/results/people_floor]

Each ``REAL3D_DIR`` is a finished ``flowmocap bench --suite real3d`` folder (e.g. the draws of
``benchmarks/real3d_draws.py``); seconds each. Prints a table and writes ``OUT.md`` /
``OUT.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def pair_measures(hips_f: np.ndarray, hips_o: np.ndarray, ref_f: np.ndarray, ref_o: np.ndarray) -> dict:
    """The depth-ratio and gap errors of two people's hip centres against a reference.

    Args:
        hips_f, hips_o: ``(F, 3)`` the first and the other person's hip centres, camera
            coordinates (metres; any common scale).
        ref_f, ref_o: ``(F, 3)`` the same from the reference, in the same camera.

    Returns:
        ``{"depth_ratio": float, "gap": float}`` (medians over the F frames; see the module
        docstring).
    """
    ratio = (hips_o[:, 2] / hips_f[:, 2]) / (ref_o[:, 2] / ref_f[:, 2])
    gap = np.linalg.norm(hips_o - hips_f, axis=1) / hips_f[:, 2]
    gap_ref = np.linalg.norm(ref_o - ref_f, axis=1) / ref_f[:, 2]
    return {"depth_ratio": float(np.median(np.abs(np.log(ratio)))), "gap": float(np.median(np.abs(gap - gap_ref)))}


def _hips_in_camera(motion, frames: list[int]) -> np.ndarray:
    rows = {int(f): k for k, f in enumerate(motion.frame_index)}
    j = motion.joints()[[rows[f] for f in frames]][:, [1, 2]].mean(1)  # SMPL's left and right hip
    return j @ np.asarray(motion.camera.R).T + np.asarray(motion.camera.t)


def measure(bench_dir: Path) -> list[dict]:
    """One row per camera and whose floor is shared, for a finished real3d folder."""
    from flowmocap.eval import real3d as R
    from flowmocap.export.floor import floor_scale, scaled_about_camera
    from flowmocap.export.motion import load_fitted_motion

    ref = R.build_reference(bench_dir, progress=False, log=None)
    runs = {(p, v): (res, d) for res, p, v, d in R.scored_runs(bench_dir, ref)}
    hips = [R.EVAL_NAMES.index("left_hip"), R.EVAL_NAMES.index("right_hip")]
    bones = {p: R.bone_lengths(R.eval_points(ref["people"][p]["all"]["points"])) for p in ref["people"]}
    rows = []
    for view in R.VIEWS:
        for first, other in (("person1", "person2"), ("person2", "person1")):
            if (first, view) not in runs or (other, view) not in runs:
                continue
            (res_f, d_f), (res_o, d_o) = runs[(first, view)], runs[(other, view)]
            common = sorted(set(d_f["used"]) & set(d_o["used"]))
            if not common:
                continue
            cam = ref["cameras"][view]
            to_cam = lambda p: p @ np.asarray(cam.R).T + np.asarray(cam.t)  # noqa: E731 -- world -> this camera
            ref_f = to_cam(d_f["ref_all"][[d_f["used"].index(f) for f in common]][:, hips].mean(1))
            ref_o = to_cam(d_o["ref_all"][[d_o["used"].index(f) for f in common]][:, hips].mean(1))
            m_f, m_o = load_fitted_motion(res_f, frame="ground"), load_fitted_motion(res_o, frame="ground")
            fit = floor_scale(m_o, m_f)
            on_floor = scaled_about_camera(m_o, fit.scale) if fit.scale is not None else m_o
            h_f = _hips_in_camera(m_f, common)
            alone = pair_measures(h_f, _hips_in_camera(m_o, common), ref_f, ref_o)
            shared = pair_measures(h_f, _hips_in_camera(on_floor, common), ref_f, ref_o)
            ours_bones = [R.bone_lengths(d["ours"]) for d in (d_f, d_o)]
            size_alone = float(np.nanmedian(ours_bones[1] / ours_bones[0]))
            moved = np.linalg.norm(on_floor.joints2d - m_o.camera.project(m_o.joints()), axis=-1)
            rows.append({
                "draw": bench_dir.name, "view": view, "floor_of": first, "frames": len(common),
                "scale": fit.scale, "why": fit.why, "points": fit.points,
                "depth_ratio": [alone["depth_ratio"], shared["depth_ratio"]], "gap": [alone["gap"], shared["gap"]],
                "size": [size_alone, size_alone * (fit.scale or 1.0),
                         float(np.nanmedian(bones[other] / bones[first]))],
                "image_px": [float(np.nanmedian(moved)), float(np.nanpercentile(moved, 90))],
            })
    return rows


def table(rows: list[dict]) -> str:
    lines = ["| draw | camera | floor of | factor | depth ratio error, alone -> one floor | gap error, alone -> one "
             "floor | other's size / first's: alone, one floor, reference | image moves px (median, 90th) |",
             "|---|---|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        f = "refused" if r["scale"] is None else f"{r['scale']:.3f}"
        lines.append(f"| {r['draw']} | {r['view']} | {r['floor_of']} | {f} | {r['depth_ratio'][0]:.3f} -> "
                     f"{r['depth_ratio'][1]:.3f} | {r['gap'][0]:.3f} -> {r['gap'][1]:.3f} | {r['size'][0]:.2f}, "
                     f"{r['size'][1]:.2f}, {r['size'][2]:.2f} | {r['image_px'][0]:.2f}, {r['image_px'][1]:.2f} |")
    mean = lambda k, i: float(np.mean([r[k][i] for r in rows]))  # noqa: E731
    better = lambda k: sum(r[k][1] < r[k][0] for r in rows)  # noqa: E731
    lines += ["", f"Over {len(rows)} camera / floor pairs: depth ratio error mean {mean('depth_ratio', 0):.3f} -> "
              f"{mean('depth_ratio', 1):.3f} (nearer the reference in {better('depth_ratio')}); gap error mean "
              f"{mean('gap', 0):.3f} -> {mean('gap', 1):.3f} (nearer in {better('gap')}); size error mean "
              f"{np.mean([abs(np.log(r['size'][0] / r['size'][2])) for r in rows]):.3f} -> "
              f"{np.mean([abs(np.log(r['size'][1] / r['size'][2])) for r in rows]):.3f} (|log| of the ratios); "
              f"the image moves {np.median([r['image_px'][0] for r in rows]):.2f} px at the median joint."]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bench", nargs="+", type=Path, help="finished `flowmocap bench --suite real3d` folders")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "people_floor")
    args = ap.parse_args(argv)
    rows = [r for b in args.bench for r in measure(b)]
    text = ("# The two people of the four-camera recording on one floor\n\n`python benchmarks/people_floor.py "
            + " ".join(str(b) for b in args.bench) + "`\n\n" + table(rows) + "\n")
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".md").write_text(text)
    args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

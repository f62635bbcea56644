"""Joint angles in OpenSim from one camera, against the multi-view reference (the real3d suite).

What a biomechanics user does with a track: export the HALPE_26 markers
(`flowmocap export RESULT --format trc --markers halpe26`), scale Pose2Sim's OpenSim model to
them and run OpenSim's inverse kinematics. This script does that for every person-view of a
`flowmocap bench --suite real3d` folder and for two other marker sources on the same frames,
and compares the joint angles OpenSim gives:

- ``reference``: the four-camera recording's triangulation WITHOUT the view tracked (the
  suite's reference: MediaPipe's keypoints, 12 limb points, plus ``Hip`` between the hips);
- ``ours``: flowmocap's fit at the same 13 points (the detector's keypoints on the fitted
  body, as the suite scores it);
- ``mediapipe``: MediaPipe's own per-frame 3D (world landmarks) at the same points: what a
  user gets from the detector alone;
- ``ours_22``: the full HALPE_26 export (22 markers: heels, toes, neck, head, nose too), what
  a user would give Pose2Sim, with its own scaling.

Each source is scaled (Pose2Sim's ``Scaling_Setup_Pose2Sim_Halpe26.xml``, only the
measurements whose markers it has) and solved (``IK_Setup_Pose2Sim_Halpe26.xml``, only its
markers' tasks) on ``Model_Pose2Sim_simple.osim`` with ``Markers_Halpe26.xml``. The angles
compared are those 13 points decide: hip flexion / adduction / rotation, knee, the lumbar
joint's three, shoulder flexion / adduction / rotation, elbow flexion (the pelvis's pose is
the camera's frame, the ankles, wrists and neck need markers the reference lacks). The error
is the mean absolute difference to the reference's angle (degrees) over the frames where the
reference has all 13 points, averaged over left and right and over the person-views.

Two steps, in two environments: OpenSim's wheel needs numpy >= 2, flowmocap numpy < 2.

    # 1. flowmocap's environment: the TRC files (reads the suite's runs and reference)
    python benchmarks/opensim_angles.py export BENCH_DIR --work WORK
    # 2. an environment with OpenSim and Pose2Sim's setup files (nothing else of Pose2Sim is used):
    #      python3 -m venv /tmp/osim && /tmp/osim/bin/pip install opensim && /tmp/osim/bin/pip install --no-deps pose2sim
    /tmp/osim/bin/python benchmarks/opensim_angles.py ik WORK --json benchmarks/results/opensim_angles_real3d.json

``ik`` prints a Markdown table and writes the JSON; ``--setup DIR`` points at an
``OpenSim_Setup`` folder instead of the installed Pose2Sim package's.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

#: The reference's 12 limb points (the suite's 13 less the head, the middle of the ears,
#: which is not HALPE_26's ``Head``, the top of the head) as HALPE_26 names, and ``Hip``.
LIMB_MARKERS = {
    "left_shoulder": "LShoulder", "right_shoulder": "RShoulder", "left_elbow": "LElbow",
    "right_elbow": "RElbow", "left_wrist": "LWrist", "right_wrist": "RWrist", "left_hip": "LHip",
    "right_hip": "RHip", "left_knee": "LKnee", "right_knee": "RKnee", "left_ankle": "LAnkle",
    "right_ankle": "RAnkle",
}
SOURCES = ("reference", "ours", "mediapipe", "ours_22")
#: OpenSim coordinates compared (the model's names); ``_r`` / ``_l`` are averaged.
ANGLES = ("hip_flexion", "hip_adduction", "hip_rotation", "knee_angle", "L5_S1_Flex_Ext",
          "L5_S1_Lat_Bending", "L5_S1_axial_rotation", "arm_flex", "arm_add", "arm_rot", "elbow_flex")
MODEL = "Model_Pose2Sim_simple.osim"
MARKERS = "Markers_Halpe26.xml"
SCALING = "Scaling_Setup_Pose2Sim_Halpe26.xml"
IK = "IK_Setup_Pose2Sim_Halpe26.xml"


# --- step 1: flowmocap's environment ------------------------------------------------------

def export(bench: Path, work: Path) -> None:
    """Write ``WORK/<person>-<view>/{reference,ours,mediapipe,ours_22}.trc`` (y up, metres,
    the scored frames only, a reference point that failed its checks as NaN) and
    ``frames.json`` (the run's frame numbers of the rows)."""
    from flowmocap.eval.real3d import EVAL_NAMES, scored_runs
    from flowmocap.export import load_fitted_motion
    from flowmocap.export.marker_sets import marker_trajectories
    from flowmocap.export.markers import write_trc
    from flowmocap.export.motion import CAMERA_TO_Y_UP
    from flowmocap.io.amass import Y_UP_TO_Z_UP

    cols = [EVAL_NAMES.index(j) for j in LIMB_MARKERS]
    names = ["Hip", *LIMB_MARKERS.values()]

    def markers(p13: np.ndarray, rot: np.ndarray) -> np.ndarray:
        limbs = p13[:, cols] @ rot.T
        hip = 0.5 * (limbs[:, names.index("LHip") - 1] + limbs[:, names.index("RHip") - 1])
        return np.concatenate([hip[:, None], limbs], axis=1)

    work.mkdir(parents=True, exist_ok=True)
    for res, person, view, d in scored_runs(bench):
        out = work / f"{person}-{view}"
        out.mkdir(exist_ok=True)
        motion = load_fitted_motion(res, frame="up")
        fps = float(motion.fps)
        ref = np.where(d["valid"][..., None], d["ref"], np.nan)
        sources = {
            "reference": markers(ref, Y_UP_TO_Z_UP.T),  # the recording's world is z up
            "ours": markers(d["ours_kp"], motion.rotation),  # the run's world (the camera's) turned y up
            "mediapipe": markers(d["detector"], CAMERA_TO_Y_UP),  # the detector's camera-like axes
        }
        for src, pts in sources.items():
            write_trc(out / f"{src}.trc", pts, names, fps, missing_ok=True)
        rows = {int(f): k for k, f in enumerate(motion.frame_index)}
        full_names, full = marker_trajectories(motion, "halpe26")
        write_trc(out / "ours_22.trc", full[[rows[f] for f in d["used"]]], full_names, fps)
        (out / "frames.json").write_text(json.dumps({"frames": [int(f) for f in d["used"]], "fps": fps,
                                                     "result": str(res)}))
        print(f"{out.name}: {len(d['used'])} frames")


# --- step 2: OpenSim's environment ---------------------------------------------------------

def _setup_dir(given: str | None) -> Path:
    if given:
        return Path(given)
    import importlib.util

    spec = importlib.util.find_spec("Pose2Sim")  # finds the package without importing it
    if spec is None or not spec.submodule_search_locations:
        sys.exit("Pose2Sim's OpenSim setup files are needed: pip install --no-deps pose2sim, or --setup DIR")
    return Path(list(spec.submodule_search_locations)[0]) / "OpenSim_Setup"


def _trc_markers(path: Path) -> set[str]:
    """The markers of a TRC with at least one finite position."""
    lines = path.read_text().splitlines()
    names = [n for n in lines[3].split("\t")[2:] if n]
    data = np.genfromtxt(lines[6:], delimiter="\t")[:, 2:]
    seen = np.isfinite(data).reshape(len(data), len(names), 3).all(-1).any(0)
    return {n for n, s in zip(names, seen) if s}


def _complete_rows(trc: Path, out: Path) -> Path:
    """A copy of ``trc`` with only the frames where every marker it has is present: OpenSim's
    scaling averages the markers' distances over its frames and a missing marker in one of
    them spoils that average."""
    lines = trc.read_text().splitlines()
    present = _trc_markers(trc)
    names = [n for n in lines[3].split("\t")[2:] if n]
    keep = [k for k, n in enumerate(names) if n in present]
    rows = [r for r in lines[6:] if r.strip()]
    data = np.genfromtxt(rows, delimiter="\t")[:, 2:].reshape(len(rows), len(names), 3)
    full = np.isfinite(data[:, keep]).all((1, 2))
    if not full.any():
        raise RuntimeError(f"{trc}: no frame has all its markers; nothing to scale to")
    head = lines[:6]
    fields = head[2].split("\t")
    fields[2] = fields[7] = str(int(full.sum()))
    head[2] = "\t".join(fields)
    out.write_text("\n".join(head + [r for r, ok in zip(rows, full) if ok]) + "\n")
    return out


def read_sto(path: Path) -> dict[str, np.ndarray]:
    """Columns of an OpenSim ``.mot`` / ``.sto`` file by name."""
    lines = path.read_text().splitlines()
    head = next(k for k, line in enumerate(lines) if line.strip() == "endheader")
    names = lines[head + 1].split("\t")
    data = np.atleast_2d(np.loadtxt(lines[head + 2:]))
    return {n.strip(): data[:, k] for k, n in enumerate(names)}


def scale_and_solve(osim, setup: Path, trc: Path, out: Path) -> dict:
    """Scale the generic model to ``trc`` and run IK in ``out``; returns the coordinates
    (degrees), the per-frame marker errors (metres) and the markers used."""
    import os

    present = _trc_markers(trc)
    out.mkdir(parents=True, exist_ok=True)
    for name in (SCALING, IK):  # OpenSim resolves a setup's file names against the setup's own folder
        shutil.copy(setup / name, out / name)
    shutil.copy(trc, out / "markers.trc")
    _complete_rows(trc, out / "scale.trc")
    here = os.getcwd()
    os.chdir(out)
    try:
        model = osim.Model(str(setup / MODEL))
        model.set_MarkerSet(osim.MarkerSet(str(setup / MARKERS)))
        model.initSystem()
        model.printToXML("generic.osim")
        times = osim.TimeSeriesTableVec3("markers.trc").getIndependentColumn()
        scale_times = osim.TimeSeriesTableVec3("scale.trc").getIndependentColumn()
        scale = osim.ScaleTool(SCALING)
        scale.getGenericModelMaker().setModelFileName("generic.osim")
        scale.getGenericModelMaker().setMarkerSetFileName("Unassigned")
        scaler = scale.getModelScaler()
        measurements = scaler.getMeasurementSet()
        for k in range(measurements.getSize()):  # only the measurements whose markers the source has
            m = measurements.get(k)
            pairs = m.getMarkerPairSet()
            used = {pairs.get(i).getMarkerName(j) for i in range(pairs.getSize()) for j in (0, 1)}
            if not used <= present:
                m.setApply(False)
        scaler.setMarkerFileName("scale.trc")
        span = osim.ArrayDouble()
        span.append(scale_times[0])
        span.append(scale_times[-1])
        scaler.setTimeRange(span)
        scaler.setOutputModelFileName("scaled.osim")
        scale.getMarkerPlacer().setApply(False)
        scale.run()
        if not Path("scaled.osim").is_file():
            raise RuntimeError(f"OpenSim's scaling wrote no model for {trc}")
        ik = osim.InverseKinematicsTool(IK)
        tasks = ik.getIKTaskSet()
        for k in range(tasks.getSize()):
            tasks.get(k).setApply(tasks.get(k).getName() in present)
        model = osim.Model("scaled.osim")
        model.initSystem()
        ik.setModel(model)
        ik.setMarkerDataFileName("markers.trc")
        ik.setStartTime(times[0])
        ik.setEndTime(times[-1])
        ik.setOutputMotionFileName("ik.mot")
        ik.setResultsDir(".")
        if not ik.run():
            raise RuntimeError(f"OpenSim's inverse kinematics failed on {trc}")
    finally:
        os.chdir(here)
    errors = read_sto(out / "_ik_marker_errors.sto")
    return {"coordinates": read_sto(out / "ik.mot"), "rms_m": errors["marker_error_RMS"],
            "max_m": errors["marker_error_max"], "markers": sorted(present)}


def _wrapped(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def compare(work: Path, setup: Path) -> dict:
    """Scale and IK for every source of every person-view in ``work``; per person-view and
    angle the mean absolute difference (degrees) of each source to the reference."""
    import opensim as osim

    osim.Logger.setLevelString("warn")
    views = {}
    for pv in sorted(p for p in work.iterdir() if (p / "frames.json").is_file()):
        solved = {src: scale_and_solve(osim, setup, pv / f"{src}.trc", pv / "ik" / src) for src in SOURCES}
        ref_lines = (pv / "reference.trc").read_text().splitlines()[6:]
        ref = np.genfromtxt(ref_lines, delimiter="\t")[:, 2:]
        complete = np.isfinite(ref).all(1)  # frames where the reference has all 13 points
        row = {"frames": int(len(ref)), "complete_frames": int(complete.sum()), "angles": {},
               "ik_rms_mm": {src: float(np.median(s["rms_m"]) * 1000) for src, s in solved.items()},
               "ik_max_mm": {src: float(np.median(s["max_m"]) * 1000) for src, s in solved.items()}}
        for angle in ANGLES:
            cols = [angle] if angle.startswith("L5") else [f"{angle}_r", f"{angle}_l"]
            truth = np.stack([solved["reference"]["coordinates"][c] for c in cols], 1)[complete]
            row["angles"][angle] = {
                src: float(np.mean(np.abs(_wrapped(np.stack([solved[src]["coordinates"][c] for c in cols], 1)[complete]
                                                   - truth))))
                for src in SOURCES if src != "reference"}
        views[pv.name] = row
        print(f"{pv.name}: {row['complete_frames']} frames; IK marker RMS (mm) "
              + ", ".join(f"{s} {v:.1f}" for s, v in row["ik_rms_mm"].items()), flush=True)
    summary = {angle: {src: float(np.mean([v["angles"][angle][src] for v in views.values()]))
                       for src in SOURCES if src != "reference"} for angle in ANGLES}
    overall = {src: float(np.mean([summary[a][src] for a in ANGLES])) for src in SOURCES if src != "reference"}
    return {"views": views, "angles": summary, "overall": overall, "setup": str(setup),
            "opensim": osim.GetVersion()}


def table(result: dict) -> str:
    srcs = [s for s in SOURCES if s != "reference"]
    lines = ["| angle | " + " | ".join(srcs) + " |", "|---|" + "---:|" * len(srcs)]
    for angle, row in result["angles"].items():
        lines.append(f"| {angle} | " + " | ".join(f"{row[s]:.1f}" for s in srcs) + " |")
    lines.append("| **mean** | " + " | ".join(f"**{result['overall'][s]:.1f}**" for s in srcs) + " |")
    lines += ["", "| person-view | frames | " + " | ".join(f"{s} mean" for s in srcs)
              + " | IK marker RMS mm: " + " / ".join(SOURCES) + " |", "|---|---:|" + "---:|" * (len(srcs) + 1)]
    for name, v in result["views"].items():
        means = [np.mean([v["angles"][a][s] for a in v["angles"]]) for s in srcs]
        lines.append(f"| {name} | {v['complete_frames']} | " + " | ".join(f"{m:.1f}" for m in means) + " | "
                     + " / ".join(f"{v['ik_rms_mm'][s]:.1f}" for s in SOURCES) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="step", required=True)
    e = sub.add_parser("export", help="flowmocap's environment: write the TRC files")
    e.add_argument("bench", type=Path, help="a `flowmocap bench --suite real3d` folder (runs/, reference/)")
    e.add_argument("--work", type=Path, required=True)
    i = sub.add_parser("ik", help="OpenSim's environment: scale, IK, compare")
    i.add_argument("work", type=Path)
    i.add_argument("--setup", help="Pose2Sim's OpenSim_Setup folder (default: the installed Pose2Sim package's)")
    i.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    if args.step == "export":
        export(args.bench, args.work)
        return 0
    result = compare(args.work, _setup_dir(args.setup))
    print(table(result))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
        args.json.with_suffix(".md").write_text(table(result) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

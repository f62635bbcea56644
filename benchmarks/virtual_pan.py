"""A camera that turns (and zooms) over real footage with a real 3D reference: the real3d
recording's still views turned into a panning camera, whose every turn and focal length is
known.

Each of the four-camera recording's views is a still, calibrated camera. A camera that only
turns about its centre sees nothing new, only the same rays elsewhere in its image, so a
turning camera can be made from a still one exactly: each frame of the view is undistorted
(its calibration) and seen through a narrower virtual pinhole camera that turns by ``V_t``
(a pan from ``-pan`` to ``+pan`` degrees about the image's vertical, and a tilt of ``tilt``
degrees up and back) and optionally zooms (its focal length from 1 to ``zoom`` times the
first frame's), ``m = --narrow`` times the view's focal length, centred principal point
(OpenCV's ``initUndistortRectifyMap`` and ``remap``). The frames are real: the people, the
background, its people walking, the compression; only the camera's motion is made. The
truth: the first frame's focal length (pixels of the tracked size), each frame's turn since
the first (``V_t V_0^T``) and zoom.

For each person-view asked, the virtual video is written (H.264, 60 fps, the tracked size),
tracked like the real3d suite's runs (``flowmocap.pipeline.track(video, person='x,y')``, the
person's pixel carried into the virtual frame) and scored:

- **the camera**: the focal length ``track`` reads from the turns (``run.json`` ``camera``)
  against the truth and the 0.9 x long side guess; the turn's error per frame (degrees between
  ``camera_motion``'s rotation and the truth); the zoom's;
- **the body**: per-frame PA-MPJPE against the reference triangulated without the view
  (:func:`flowmocap.eval.real3d.score_run`: a similarity per frame, so blind to the camera's
  turn), beside the still view's own run in ``--bench`` (the same person-view tracked as the
  suite does) and MediaPipe's 3D on the virtual frames; per-sequence (root-relative joints, one
  similarity over the sequence) of the result's own frame (the turning camera's) and of the
  export's ``"up"`` frame, where each frame's turn (and zoom) is undone; and the body's distance
  from the camera, relative to its first scored frame, against the reference's (the median
  over frames of the ratio's error, percent): as tracked (with the first frame's focal length
  throughout, a zoom out puts the body further) and with each frame's zoom undone (the export).

Usage::

    python benchmarks/virtual_pan.py BENCH [--views person1@cam02,person1@cam04] [--pan 4] [--tilt 2]
        [--zoom 1.0] [--narrow 1.3] [--work DIR] [--out benchmarks/results/virtual_pan]

``BENCH`` is a ``flowmocap bench --suite real3d`` folder (its reference and its runs of the
still views). Prints a table and writes ``OUT.md`` / ``OUT.json``. About two minutes a
person-view.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# the camera-motion module's own: K with its focal lengths scaled (the principal point kept), and a
# rotation's angle in degrees
from flowmocap.vision.camera_motion import _angle
from flowmocap.vision.camera_motion import _zoomed as zoomed


def turns(T: int, pan_deg: float, tilt_deg: float) -> np.ndarray:
    """``(T, 3, 3)``: the virtual camera's turn from the still camera's axes in each frame
    (``x_virtual = V_t x_still``): a pan about the camera's vertical (y) from ``-pan_deg`` to
    ``+pan_deg`` (smooth start and stop) and a tilt about its x axis of ``tilt_deg`` up and back."""
    from scipy.spatial.transform import Rotation

    s = np.linspace(0.0, 1.0, T)
    pan = np.radians(pan_deg) * (2.0 * (3 * s ** 2 - 2 * s ** 3) - 1.0)
    tilt = np.radians(tilt_deg) * np.sin(np.pi * s)
    return np.stack([Rotation.from_euler("yx", [p, t]).as_matrix() for p, t in zip(pan, tilt)])


def virtual_intrinsics(K_still: np.ndarray, full: tuple[int, int], size: tuple[int, int], narrow: float) -> np.ndarray:
    """``(3, 3)`` the virtual camera's first-frame intrinsics at ``size`` ``(W, H)``: the still
    view's focal length (full resolution ``full``) scaled to ``size``, times ``narrow``; the
    principal point in the image's middle."""
    f = 0.5 * (K_still[0, 0] + K_still[1, 1]) * size[1] / full[1] * narrow
    return np.array([[f, 0.0, size[0] / 2.0], [0.0, f, size[1] / 2.0], [0.0, 0.0, 1.0]])


def write_virtual(video: Path, cam, V: np.ndarray, Kv: list, size: tuple[int, int], out: Path, fps: float) -> dict:
    """Write the virtual camera's frames of ``video`` to ``out`` (H.264); returns how much of
    any frame fell outside the still view (``outside_share``, the largest over frames: 0 when the
    virtual camera stays within the still one's view)."""
    import cv2

    from flowmocap.io.video import load_video
    from flowmocap.viz.video import VideoWriter

    seq = load_video(video, max_side=0)
    K, dist = np.asarray(cam.K, np.float64), np.asarray(cam.dist, np.float64)
    worst = 0.0
    with VideoWriter(out, fps) as w:
        for i in range(len(seq)):
            img = seq.frame(i)
            mx, my = cv2.initUndistortRectifyMap(K, dist, V[i], Kv[i], size, cv2.CV_32FC1)
            outside = (mx < 0) | (my < 0) | (mx > img.shape[1] - 1) | (my > img.shape[0] - 1)
            worst = max(worst, float(outside.mean()))
            w.write(cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT))
    return {"outside_share": worst, "frames": len(seq)}


def virtual_pixel(cam, px: tuple[float, float], V: np.ndarray, Kv: np.ndarray) -> tuple[float, float]:
    """A pixel of the still view (full resolution) where the virtual camera ``(V, Kv)`` sees it."""
    import cv2

    p = cv2.undistortPoints(np.array([[px]], np.float64), np.asarray(cam.K, np.float64),
                            np.asarray(cam.dist, np.float64), R=V, P=Kv)
    return float(p[0, 0, 0]), float(p[0, 0, 1])


def score_view(res: Path, still: Path, reference: dict, person: str, view: str, truth: dict) -> dict:
    """The camera's and the body's scores of one virtual run (see the module's docstring)."""
    from scipy.spatial.transform import Rotation

    from flowmocap.eval.real3d import EVAL_JOINTS, EVAL_NAMES, pa_mpjpe, score_run, scored_frames
    from flowmocap.export.motion import load_fitted_motion

    run = json.loads((res / "run.json").read_text())
    cm = run.get("camera_motion") or {}
    row: dict = {"person": person, "view": view, "focal_true_px": truth["focal_px"],
                 "focal_used_px": float(run["camera"]["fx"]), "focal_guess_px": 0.9 * max(truth["size"]),
                 "focal_found": cm.get("focal"), "turn_deg_true": float(truth["turn_deg"].max()),
                 "turn_deg_found": cm.get("turn_deg_max"), "moving_sideways": cm.get("moving_sideways")}
    if cm.get("rotvecs"):
        frames = np.asarray(cm["frames"], int)
        R = Rotation.from_rotvec(np.asarray(cm["rotvecs"], np.float64)).as_matrix()
        err = _angle(np.einsum("tji,tjk->tik", R, truth["R"][frames]))  # the angle of R^T R_true
        row.update(turn_error_deg_median=float(np.median(err)), turn_error_deg_max=float(err.max()))
        if cm.get("zooms"):
            z = np.asarray(cm["zooms"], np.float64)
            row["zoom_error_max"] = float(np.abs(z - truth["zooms"][frames]).max())
        else:
            row["zoom_error_max"] = float(np.abs(truth["zooms"] - 1.0).max())
    virtual = score_run(res, reference, person, view)
    row["virtual"] = {k: virtual[k]["per_frame_mm"] for k in ("flowmocap", "flowmocap_kp", "detector3d")
                      if virtual.get(k)}
    row["frames_scored"] = virtual["frames_scored"]
    if (still / "motion.npz").exists():
        s = score_run(still, reference, person, view)
        row["still"] = {k: s[k]["per_frame_mm"] for k in ("flowmocap", "flowmocap_kp", "detector3d") if s.get(k)}
        row["still"]["per_sequence_mm"] = s["flowmocap"]["per_sequence_mm"]
    # per sequence: the result's own frame (the turning camera's) against the export's, the turns undone
    d = scored_frames(res, reference, person, view)
    up = load_fitted_motion(res, frame="up", cache_world=False)
    rows = {int(f): k for k, f in enumerate(up.frame_index)}
    joints_up = up.joints()[[rows[f] for f in d["used"]]][:, list(EVAL_JOINTS)]
    row["per_sequence_mm"] = {"camera_frame": pa_mpjpe(d["ours"], d["ref"], d["valid"])[1],
                              "turns_undone": pa_mpjpe(joints_up, d["ref"], d["valid"])[1]}
    # the body's distance from the camera over time, relative to its first scored frame (one camera
    # leaves the size, so the distance, open): the tracked one (the first frame's focal length
    # throughout) and the export's (each frame's zoom undone) against the reference's
    hips = [EVAL_NAMES.index("left_hip"), EVAL_NAMES.index("right_hip")]
    centre = np.asarray(reference["cameras"][view].center, np.float64)
    ref_d = np.linalg.norm(d["ref"][:, hips].mean(1) - centre, axis=1)

    def off(dist):  # median over frames of |log| of the distance ratio's error, percent
        return float(100 * np.median(np.abs(np.log(dist / dist[0] / (ref_d / ref_d[0])))))

    row["distance_error_pct"] = {"tracked": off(np.linalg.norm(d["ours"][:, hips].mean(1), axis=1)),
                                 "zoom_undone": off(np.linalg.norm(joints_up[:, hips].mean(1), axis=1))}
    return row


def run(bench: Path, views: list[str], pan: float, tilt: float, zoom: float, narrow: float, work: Path,
        log=print) -> dict:
    from flowmocap.eval.real3d import DATA, build_reference, person_pixel
    from flowmocap.io.results import has_result
    from flowmocap.pipeline import track

    reference = build_reference(bench, DATA, progress=False, log=None)
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for pv in views:
        person, view = pv.split("@")
        cam = reference["cameras"][view]
        full = (int(cam.width), int(cam.height))
        scale = 640.0 / max(full)
        size = (int(round(full[0] * scale)), int(round(full[1] * scale)))
        size = (size[0] + size[0] % 2, size[1] + size[1] % 2)  # even sizes for the H.264 writer
        video = Path(DATA) / "videos" / f"{view}.mp4"
        from flowmocap.io.video import load_video

        T = len(load_video(video, max_side=640))
        V = turns(T, pan, tilt)
        K0 = virtual_intrinsics(np.asarray(cam.K), full, size, narrow)
        zs = np.exp(np.linspace(0.0, np.log(zoom), T))
        Kv = [zoomed(K0, z) for z in zs]
        truth = {"focal_px": float(K0[0, 0]), "size": size, "R": np.einsum("tij,kj->tik", V, V[0]),
                 "zooms": zs / zs[0]}
        truth["turn_deg"] = _angle(truth["R"])
        clip = work / f"{person}-{view}.mp4"
        res = work / "runs" / f"{person}-{view}"
        if not clip.exists():
            log(f"[{pv}] writing the virtual camera's frames to {clip} ...")
            info = write_virtual(video, cam, V, Kv, size, clip, 60.0)
            if info["outside_share"] > 0:
                log(f"[{pv}] {100 * info['outside_share']:.1f} % of a frame falls outside the still view (black)")
        first, px = person_pixel(*reference["people"][person]["tracks"][view])
        x, y = virtual_pixel(cam, px, V[first], Kv[first])
        t0 = time.perf_counter()
        if not (res / "motion.npz").exists():
            log(f"[{pv}] flowmocap track {clip} --person {x:.0f},{y:.0f} ...")
            track(clip, res, person=f"{x:.0f},{y:.0f}", max_size=640, resume=has_result(res), progress=False, log=None)
        row = score_view(res, bench / "runs" / f"{person}-{view}", reference, person, view, truth)
        row["seconds"] = time.perf_counter() - t0
        log(f"[{pv}] {json.dumps(row, default=float)}")
        rows.append(row)
    return {"settings": {"bench": str(bench), "pan_deg": pan, "tilt_deg": tilt, "zoom": zoom, "narrow": narrow},
            "rows": rows}


def table(result: dict) -> str:
    s = result["settings"]
    lines = [f"# A turning camera over real footage: `python benchmarks/virtual_pan.py`", "",
             f"The real3d views seen by a virtual camera {s['narrow']} times their focal length that pans "
             f"from -{s['pan_deg']} to +{s['pan_deg']} degrees and tilts {s['tilt_deg']} degrees up and back"
             + (f", zooming to {s['zoom']} times its first focal length" if s["zoom"] != 1 else "") +
             f"; still runs from `{s['bench']}`. Focal lengths in pixels of the 640-pixel frames; per-frame and "
             "per-sequence PA-MPJPE in mm against the reference without the view.", "",
             "| person-view | focal true / found (guess) | turn true deg | turn error deg median / max | zoom error "
             "| per frame: virtual / still | at keypoints: virtual / still | MediaPipe: virtual / still "
             "| per sequence: camera's frame / turns undone / still | distance's change, error %: tracked / zoom undone |",
             "|---|---|---:|---|---:|---|---|---|---|---|"]
    f = lambda v: "" if v is None else f"{v:.1f}"  # noqa: E731
    for r in result["rows"]:
        found = (r.get("focal_found") or {}).get("focal_px")
        st, vi = r.get("still", {}), r["virtual"]
        lines.append(
            f"| {r['person']}@{r['view']} | {r['focal_true_px']:.0f} / {f(found) or 'none'} ({r['focal_guess_px']:.0f}; "
            f"tracked with {r['focal_used_px']:.0f}) | {r['turn_deg_true']:.1f} | "
            f"{r.get('turn_error_deg_median', float('nan')):.2f} / {r.get('turn_error_deg_max', float('nan')):.2f} | "
            f"{r.get('zoom_error_max', float('nan')):.3f} | {f(vi.get('flowmocap'))} / {f(st.get('flowmocap'))} | "
            f"{f(vi.get('flowmocap_kp'))} / {f(st.get('flowmocap_kp'))} | {f(vi.get('detector3d'))} / "
            f"{f(st.get('detector3d'))} | {f(r['per_sequence_mm']['camera_frame'])} / "
            f"{f(r['per_sequence_mm']['turns_undone'])} / {f(st.get('per_sequence_mm'))} | "
            f"{f(r['distance_error_pct']['tracked'])} / {f(r['distance_error_pct']['zoom_undone'])} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bench", type=Path, help="a flowmocap bench --suite real3d folder")
    ap.add_argument("--views", default="person1@cam02,person1@cam04,person1@cam01")
    ap.add_argument("--pan", type=float, default=4.0, help="degrees either side")
    ap.add_argument("--tilt", type=float, default=2.0, help="degrees up and back")
    ap.add_argument("--zoom", type=float, default=1.0, help="the last frame's focal length over the first's")
    ap.add_argument("--narrow", type=float, default=1.3, help="the virtual focal length over the still view's")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "flowmocap_virtual_pan",
                    help="where the virtual videos and their runs go (kept: a second call reuses them)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/virtual_pan"))
    a = ap.parse_args(argv)
    result = run(a.bench, a.views.split(","), a.pan, a.tilt, a.zoom, a.narrow, a.work)
    text = table(result)
    print(text)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.with_suffix(".md").write_text(text)
    a.out.with_suffix(".json").write_text(json.dumps(result, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())

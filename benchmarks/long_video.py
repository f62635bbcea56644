"""Long videos: memory, disk and time per frame along a long 640x480 video (issue 19).

Makes a video of the built-in walk played forwards and backwards in turn (a continuous
motion of any length) at 30 fps, 640x480: ``flowmocap synth`` renders one cycle, PyAV
encodes the ping-pong of it (H.264). Then ``flowmocap track VIDEO --out DIR`` runs in a
child process while this script samples, once a second, the child's resident memory
(``VmRSS``, and ``VmHWM`` its peak; summed over the child and its own children, the
person detector's processes) and the frames it has committed (``progress.json``).
Prints a table at each minute mark of the video (and the end), the peak, the result
folder's size, and the seconds per frame of each stretch, and writes JSON.

``--masks auto`` (default) is what a user gets: MediaPipe finds the person (a pass over
the whole video before tracking) and the ``video`` profile tracks. ``--masks given``
passes the rendered masks and an init.json (the ``synthetic`` profile, no detector).

The same command again goes on with a run that was stopped (``--stop-after``) or
killed: the tracker resumes its result folder and the samples of every invocation are
kept beside it (``RESULT.trace.jsonl``), so the marks and the peak cover the whole video
(each row says which invocation, that is which process, it was measured in; the
seconds per frame of a stretch that spans a restart include the restart).

Usage: python benchmarks/long_video.py [--minutes 10] [--work DIR] [--masks auto|given] [--fast]
       [--out benchmarks/results/long_video.json] [--cycle 60] [--stop-after SECONDS]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FPS = 30


def make_video(work: Path, minutes: float, cycle: int, size: str) -> tuple[Path, Path, Path]:
    """The ping-pong video, a masks folder (hard links to the cycle's masks) and an
    init.json of its first frame."""
    import av
    import numpy as np

    from flowmocap.eval.protocol import noisy_init
    from flowmocap.io.sequence import load_sequence
    from flowmocap.synth import synthesize

    seq_dir = work / "cycle"
    if not (seq_dir / "gt.npz").exists():
        synthesize("builtin:walk", seq_dir, fps=FPS, frames=cycle, size=size, betas="random", seed=0, azimuth=60.0,
                   flow=False)
    seq = load_sequence(seq_dir)
    order = list(range(cycle)) + list(range(cycle - 2, 0, -1))  # forwards, then backwards: no jump
    total = int(round(minutes * 60 * FPS))
    index = [order[k % len(order)] for k in range(total)]
    video = work / f"walk_{minutes:g}min.mp4"
    if not video.exists():
        frames = [seq.frame(i) for i in range(cycle)]
        tmp = video.with_suffix(".part.mp4")
        with av.open(str(tmp), "w") as c:
            s = c.add_stream("libx264", rate=FPS)
            s.width, s.height, s.pix_fmt = frames[0].shape[1], frames[0].shape[0], "yuv420p"
            s.options = {"crf": "18", "preset": "veryfast"}
            for i in index:
                for p in s.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frames[i]), format="rgb24")):
                    c.mux(p)
            for p in s.encode():
                c.mux(p)
        tmp.rename(video)
    masks = work / f"masks_{minutes:g}min"
    if not masks.exists():
        part = masks.with_name(masks.name + ".part")
        part.mkdir(exist_ok=True)
        for k, i in enumerate(index):
            dst = part / f"{k:06d}.png"
            if not dst.exists():
                os.link(seq.masks[i], dst)
        part.rename(masks)
    init = work / "init.json"
    init.write_text(json.dumps(noisy_init(seq.gt, frame=0, seed=0)))
    return video, masks, init


def rss_mb(pid: int) -> tuple[float, float]:
    """``(VmRSS, VmHWM)`` of a process in MB (0 when it has ended)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0.0, 0.0
    vals = {}
    for line in text.splitlines():
        if line.startswith(("VmRSS:", "VmHWM:")):
            key, kb = line.split()[:2]
            vals[key[:-1]] = int(kb) / 1024
    return vals.get("VmRSS", 0.0), vals.get("VmHWM", 0.0)


def tree_rss_mb(pid: int) -> tuple[float, float, float]:
    """``(VmRSS, VmHWM, Pss)`` in MB summed over ``pid`` and its descendants (the detector's
    processes, :mod:`flowmocap.vision.detect_worker`), read from ``/proc``."""
    parent = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                parent[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    tree, grew = {pid}, True
    while grew:
        more = {p for p, pp in parent.items() if pp in tree} - tree
        tree |= more
        grew = bool(more)
    rss = hwm = 0.0
    for p in tree:
        r, h = rss_mb(p)
        rss, hwm = rss + r, hwm + h
    return rss, hwm, sum(pss_mb(p) for p in tree)


def pss_mb(pid: int) -> float:
    """A process's proportional set size in MB (``smaps_rollup``): its own pages plus its
    share of the pages it shares (libraries). Summed over processes it counts a shared
    page once (shared with processes outside them, e.g. a benchmark beside, it counts less)."""
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0.0


def folder_mb(path: Path) -> float:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 2 ** 20


def committed(res: Path) -> int:
    try:
        return int(json.loads((res / "progress.json").read_text())["rows"])
    except (OSError, ValueError, KeyError):
        return -1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="length of the video (default 10)")
    ap.add_argument("--cycle", type=int, default=60, help="frames of the rendered walk cycle (default 60)")
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--masks", default="auto", choices=["auto", "given"])
    ap.add_argument("--work", default=str(ROOT / "benchmarks" / "work" / "long_video"))
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "long_video.json"))
    ap.add_argument("--fast", action="store_true", help="track with --fast (docs/settings.md)")
    ap.add_argument("--stop-after", type=float, default=None, help="stop tracking after this many seconds and "
                    "report the frames reached (the result resumes with the same command)")
    args = ap.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    video, masks, init = make_video(work, args.minutes, args.cycle, args.size)
    print(f"video {video} ({video.stat().st_size / 2 ** 20:.1f} MB) made in {time.time() - t0:.0f} s", flush=True)
    res = work / f"result_{args.minutes:g}min_{args.masks}{'_fast' if args.fast else ''}"
    cmd = [sys.executable, "-m", "flowmocap.cli", "track", str(video), "--out", str(res), "--quiet"]
    if args.fast:
        cmd.append("--fast")
    if args.masks == "given":
        cmd += ["--masks", str(masks), "--init", str(init)]
    if (res / "run.json").exists():
        cmd.append("--resume")
    print(" ".join(cmd), flush=True)
    # the samples of every invocation on this result (a run stopped by --stop-after, or
    # killed, goes on with the same command): seconds count on from the previous ones
    trace = res.parent / f"{res.name}.trace.jsonl"
    earlier = [json.loads(line) for line in trace.read_text().splitlines()] if trace.exists() else []
    invocation = 1 + max((e["run"] for e in earlier), default=-1)
    offset = max((e["t"] for e in earlier), default=0.0) + 1.0
    samples = [(e["t"], e["frames"], e["rss"], e["peak"], e["folder"], e["run"], e.get("pss", 0.0)) for e in earlier]
    start = time.time()
    proc = subprocess.Popen(cmd)
    stopped = False
    with trace.open("a") as log:
        while proc.poll() is None:
            if args.stop_after is not None and time.time() - start > args.stop_after:
                proc.kill()  # the commit point holds every finished frame
                proc.wait()
                stopped = True
                break
            rss, hwm, pss = tree_rss_mb(proc.pid)  # the tracker and its detector process, together
            n = committed(res)
            size = folder_mb(res) if res.exists() and len(samples) % 30 == 0 else (samples[-1][4] if samples else 0.0)
            samples.append((offset + time.time() - start, n, rss, hwm, size, invocation, pss))
            log.write(json.dumps(dict(zip(("t", "frames", "rss", "peak", "folder", "run", "pss"),
                                          (round(samples[-1][0], 1), n, round(rss, 1), round(hwm, 1),
                                           round(size, 2), invocation, round(pss, 1))))) + "\n")
            log.flush()
            time.sleep(1.0)
    wall = time.time() - start
    if proc.returncode != 0 and not stopped:
        print(f"tracking failed with exit status {proc.returncode}")
        return proc.returncode
    run = json.loads((res / "run.json").read_text())
    total = int(round(args.minutes * 60 * FPS))
    reached = max((s[1] for s in samples), default=0)
    stopped = stopped or reached < total
    quarters = {int(reached * q / 4) for q in (1, 2, 3)} if stopped else set()
    marks = sorted(({min(total, int(m * 60 * FPS)) for m in [1, 5, 10] if m <= args.minutes} | {total} | quarters)
                   & set(range(3, reached + 1)) | ({reached} if stopped else set()))
    rows = []
    tracking = [s for s in samples if s[1] >= 2]
    for m in marks:
        at = next((s for s in tracking if s[1] >= m - 1), tracking[-1] if tracking else None)
        if at is None:
            continue
        rows.append({"video_minutes": round(m / (60 * FPS), 2), "frame": m, "rss_mb": round(at[2], 1),
                     "peak_mb": round(at[3], 1), "pss_mb": round(at[6], 1), "folder_mb": round(at[4], 1), "seconds": round(at[0], 1),
                     "invocation": at[5]})
    for a, b in zip([None] + rows[:-1], rows):
        t_a, f_a = (next(s[0] for s in tracking), 2) if a is None else (a["seconds"], a["frame"])
        b["s_per_frame"] = round((b["seconds"] - t_a) / max(1, b["frame"] - f_a), 3)
    result = {
        "video": str(video), "frames": total, "size": args.size, "masks": args.masks, "fast": args.fast,
        "wall_s": round(wall, 1), "invocations": invocation + 1,
        "peak_rss_mb": round(max((s[3] for s in samples), default=0.0), 1),  # summed peaks: an upper bound
        "peak_rss_sampled_mb": round(max((s[2] for s in samples), default=0.0), 1),  # the largest 1-s sample
        "peak_pss_mb": round(max((s[6] for s in samples), default=0.0), 1),
        "detection": {"peak_rss_sampled_mb": round(max((s[2] for s in samples if s[1] < 2), default=0.0), 1),
                      "peak_pss_mb": round(max((s[6] for s in samples if s[1] < 2), default=0.0), 1)},
        "result_folder_mb": round(folder_mb(res), 2), "video_mb": round(video.stat().st_size / 2 ** 20, 1),
        "s_per_frame_median": run.get("timings", {}).get("s_per_frame_median"), "marks": rows,
        "stopped_after_s": args.stop_after if stopped else None, "frames_reached": reached,
        "rss_trace": [(round(s[0]), s[1], round(s[2])) for s in samples[:: max(1, len(samples) // 200)]],
        "machine": f"{os.cpu_count()} cores",
    }
    print(f"\n{'video min':>9}{'frame':>8}{'RSS MB':>9}{'peak MB':>9}{'PSS MB':>9}{'folder MB':>11}{'s/frame':>9}")
    for r in rows:
        print(f"{r['video_minutes']:>9}{r['frame']:>8}{r['rss_mb']:>9}{r['peak_mb']:>9}{r['pss_mb']:>9}"
              f"{r['folder_mb']:>11}{r['s_per_frame']:>9}")
    print(f"detection pass: largest sample {result['detection']['peak_rss_sampled_mb']} MB RSS, "
          f"{result['detection']['peak_pss_mb']} MB PSS (tracker and detector processes together)")
    print(f"peak RSS {result['peak_rss_mb']} MB (summed peaks), largest sample {result['peak_rss_sampled_mb']} MB, "
          f"PSS {result['peak_pss_mb']} MB; result folder {result['result_folder_mb']} MB; wall {wall:.0f} s")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

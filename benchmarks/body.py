"""Body model speed: forward and forward+backward at batch 1 and 16.

Usage: python benchmarks/body.py [--model default] [--repeats 30] [--threads N]
Prints a table and writes benchmarks/results/body.json (medians over repeats, ms).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import time
from pathlib import Path

import torch

from flowmocap.body import body_capsules, load_body_model


def _time(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="default")
    ap.add_argument("--gender", default="neutral")
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "body.json"))
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    model = load_body_model(args.model, gender=args.gender)
    rows = []
    for B in (1, 16):
        torch.manual_seed(0)
        betas = torch.randn(B, 10)
        pose = 0.3 * torch.randn(B, 72)
        trans = torch.randn(B, 3)

        def fwd():
            with torch.no_grad():
                model(betas=betas, pose=pose, trans=trans)

        def fwd_bwd():
            b, p, t = (x.clone().requires_grad_() for x in (betas, pose, trans))
            out = model(betas=b, pose=p, trans=t)
            (out.vertices.square().sum() + out.joints.square().sum()).backward()

        def caps():
            with torch.no_grad():
                body_capsules(model, model(betas=betas, pose=pose, trans=trans))

        rows.append({
            "batch": B,
            "forward_ms": _time(fwd, args.repeats),
            "forward_backward_ms": _time(fwd_bwd, args.repeats),
            "forward_capsules_ms": _time(caps, args.repeats),
        })
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).parent).stdout.strip()
    except OSError:
        commit = None
    result = {
        "benchmark": "body",
        "commit": commit,
        "model": args.model,
        "vertices": model.num_vertices,
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu": platform.processor() or platform.machine(),
        "repeats": args.repeats,
        "rows": rows,
    }
    print(f"body model '{args.model}' ({model.num_vertices} vertices), torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, median of {args.repeats}")
    print(f"{'batch':>5} {'forward ms':>11} {'fwd+bwd ms':>11} {'fwd+capsules ms':>16}")
    for r in rows:
        print(f"{r['batch']:>5} {r['forward_ms']:>11.2f} {r['forward_backward_ms']:>11.2f} {r['forward_capsules_ms']:>16.2f}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

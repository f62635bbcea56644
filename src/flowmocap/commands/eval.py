"""``flowmocap eval RESULT --gt SEQ``: all metrics of a result against a sequence."""

from __future__ import annotations


def register(subparsers) -> None:
    e = subparsers.add_parser(
        "eval", help="score a result folder against a sequence (3D/2D joint errors, accel, IoU, speed)",
        description="Print the metrics of a result against a sequence folder with gt.npz and/or masks, and "
        "write them as JSON. Metrics that need what the sequence lacks are null.")
    e.add_argument("result", help="result folder (motion.npz, run.json)")
    e.add_argument("--gt", required=True, metavar="SEQ", help="sequence folder (gt.npz and/or masks/)")
    e.add_argument("--masks", default=None, help="mask folder overriding SEQ/masks")
    e.add_argument("--model", default=None, help="body model of the result, for the silhouettes (default: the one "
                   "it was tracked with, from run.json)")
    e.add_argument("--out", default=None, help="JSON file to write (default: RESULT/eval.json)")
    e.set_defaults(func=cmd_eval)


def cmd_eval(args) -> int:
    from pathlib import Path

    from flowmocap.atomic import check_file_path
    from flowmocap.body import load_body_model
    from flowmocap.eval.scoring import format_scores, score_result
    from flowmocap.io.results import read_result, write_json
    from flowmocap.io.sequence import load_sequence

    out = Path(args.out) if args.out else Path(args.result) / "eval.json"
    check_file_path(out)  # before the scoring, which may take a while
    seq = load_sequence(args.gt, masks=args.masks)
    motion, _ = read_result(args.result)
    model = None if args.model is None else load_body_model(args.model, gender=str(motion.get("gender", "neutral")))
    scores = score_result(args.result, seq, model=model)
    print(format_scores(scores))
    write_json(out, scores)  # atomically: a failed write keeps an earlier eval.json whole
    print(f"wrote {out}")
    return 0

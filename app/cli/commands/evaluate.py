"""``aerialreg evaluate``: the paper's Table 2 and per-frame error statistics for a result."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from app.cli.common import UsageError, check_output_file, emit_json
from app.progress import ProgressBar

NAME = "evaluate"
HELP = (
    "Measure a registration result: Table 2 (paper section 6) and per-frame errors, against a "
    "simulator's ground truth (--truth) or hand-marked points (--points)."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", metavar="OUT", help="result folder written by 'aerialreg register'")
    p.add_argument("--truth", metavar="DIR", help="simulated sequence folder with truth.json")
    p.add_argument(
        "--points",
        metavar="POINTS.csv",
        help="hand-marked ground points: CSV with header point,frame,x,y (x, y raw pixels of "
        "frame 'frame'; see registration.evaluation.points.read_points_csv)",
    )
    p.add_argument(
        "--frames-for-table",
        type=int,
        default=10,
        help="frames spread evenly over the sequence for Table 2 with --truth (default 10, the paper's)",
    )
    p.add_argument(
        "--grid-step",
        type=float,
        default=16.0,
        help="spacing of the dense grid of ground points with --truth, base px (default 16)",
    )
    p.add_argument(
        "--anchor",
        choices=("reference", "mean"),
        default="reference",
        help="with --points, measure each point's motion from its position in the reference frame "
        "(default; the reference frame must be marked) or from its mean position",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--markdown", metavar="FILE", help="also write the markdown report to FILE")
    p.add_argument("--csv", metavar="FILE", help="also write Table 2 as CSV to FILE")
    p.add_argument("--frames-csv", metavar="FILE", help="also write per-frame statistics as CSV")
    p.add_argument(
        "--force",
        action="store_true",
        help="overwrite existing --markdown/--csv/--frames-csv files",
    )


def _protected(out: Path) -> tuple[list[Path], list[Path]]:
    """Folders and files no output may be written into or onto: the result's records and
    the run's inputs (from its result.json, when readable)."""
    import json

    from registration.io import input_locations

    try:
        meta = json.loads((out / "result.json").read_text())
    except (OSError, ValueError):
        meta = {}
    folders, files = input_locations(meta.get("frames_source"), meta.get("base_path"))
    own = [out / name for name in ("result.json", "mid_base.png", "mid_base_valid.png")]
    return [*folders, out / "frames", out / "registered"], [*files, *own]


def run(args: argparse.Namespace) -> int:
    import registration
    from registration import evaluation
    from registration.io import check_not_an_input, write_bytes_atomic

    if (args.truth is None) == (args.points is None):
        raise UsageError("give exactly one of --truth DIR or --points POINTS.csv")
    if args.frames_for_table < 1:
        raise UsageError(f"--frames-for-table must be >= 1, got {args.frames_for_table}")
    if not (1 <= args.grid_step < math.inf):
        # Below 1 px the grid only repeats points, and its size grows without bound.
        raise UsageError(f"--grid-step must be a number >= 1 (base px), got {args.grid_step}")
    inputs = (
        args.points,
        args.truth and Path(args.truth) / "truth.json",
        Path(args.out) / "result.json",
    )
    outputs = {"--markdown": args.markdown, "--csv": args.csv, "--frames-csv": args.frames_csv}
    protected = _protected(Path(args.out))
    for flag, path in outputs.items():
        if path is not None:
            check_output_file(path, flag, force=args.force, inputs=inputs)
            check_not_an_input(path, *protected, flag)
    named = [Path(p).resolve() for p in outputs.values() if p is not None]
    if len(set(named)) < len(named):
        raise UsageError("--markdown, --csv and --frames-csv must name different files")
    config = evaluation.EvaluationConfig(
        grid_step_px=args.grid_step, table_frames=args.frames_for_table, anchor=args.anchor
    )
    result = registration.load(args.out)
    if args.truth is not None:
        from registration.synth import load_truth

        truth = load_truth(args.truth)
        evaluation.check_compatible(result, truth)
        with ProgressBar(result.n_frames, "evaluate") as bar:
            report = evaluation.evaluate_truth(
                result, truth, config, progress=lambda d, t: bar.update(d - bar.done)
            )
    else:
        marks = evaluation.read_points_csv(args.points, result.n_frames, result.frame_size)
        report = evaluation.evaluate_points(result, marks, config)
    markdown = report.to_markdown()
    if args.markdown:
        write_bytes_atomic(Path(args.markdown), markdown.encode("utf-8"))
    if args.csv:
        write_bytes_atomic(Path(args.csv), report.table.to_csv().encode("utf-8"))
    if args.frames_csv:
        write_bytes_atomic(Path(args.frames_csv), report.per_frame_csv().encode("utf-8"))
    if args.json:
        emit_json(report.to_dict())
    else:
        sys.stdout.write(markdown)
    return 0

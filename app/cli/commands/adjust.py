"""``aerialreg adjust``: the analyst's map points of a registered result (a point of a frame and
where it lies on the map), and the sequence adjustment of the frames they touch."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from app.cli.common import emit_json
from app.progress import LazyProgressBar

NAME = "adjust"
HELP = (
    "Add or remove map points (frame K's raw pixel FX,FY lies at base pixel BX,BY) on a result "
    "registered with the sequence adjustment, and adjust the frames they touch again."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", metavar="OUT", help="result folder written by 'aerialreg register'")
    p.add_argument(
        "--add",
        action="append",
        default=[],
        metavar="K,FX,FY,BX,BY",
        help="a map point: frame K's raw pixel (FX, FY) shows the ground at base pixel (BX, BY) "
        "(repeat for more)",
    )
    p.add_argument(
        "--sigma",
        type=float,
        default=1.0,
        help="the added points' noise in base px (default 1: two careful clicks)",
    )
    p.add_argument(
        "--remove", action="append", default=[], type=int, metavar="K",
        help="remove frame K's map points (repeat for more)",
    )  # fmt: skip
    p.add_argument("--clear", action="store_true", help="remove every map point")
    p.add_argument(
        "--frames",
        help="the registered video / image folder / glob (default: the one recorded in OUT)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object with the summary")


def parse_point(text: str, sigma: float):
    """``K,FX,FY,BX,BY`` as a :class:`registration.adjustment.MapPoint`."""
    from registration.adjustment import MapPoint

    parts = text.split(",")
    try:
        k, fx, fy, bx, by = int(parts[0]), *(float(v) for v in parts[1:])
    except ValueError:
        raise ValueError(f"--add must be K,FX,FY,BX,BY, got {text!r}") from None
    return MapPoint(k, (fx, fy), (bx, by), sigma)


def run(args: argparse.Namespace) -> int:
    import registration
    from registration.io import check_result_frames, open_frames
    from registration.run import adjust_folder, read_map_points, set_map_points

    added = [parse_point(t, args.sigma) for t in args.add]
    result = registration.load(args.out)
    # The frames first: points changed for frames that cannot be read would leave the frames
    # they touch to adjust again, with nothing to adjust them from.
    frames = open_frames(args.frames or result.meta["frames_source"])
    check_result_frames(frames, result)
    points = [] if args.clear else read_map_points(args.out)
    points = [p for p in points if p.k not in set(args.remove)] + added
    undone = set_map_points(args.out, points)
    progress = LazyProgressBar("adjust")
    try:
        n = adjust_folder(args.out, frames, progress)
    finally:
        progress.close()
    result = registration.load(args.out)
    touched = sorted({p.k for p in points} | {p.k for p in added})
    frames_out = []
    for k in touched:
        adj = result.records[k].stats.get("adjustment") or {}
        frames_out.append({
            "frame": k,
            "n_map_points": adj.get("n_map_points", 0),
            "map_point_rms_px": adj.get("map_point_rms_px"),
            "predicted_error_px": adj.get("predicted_error_px"),
            "flagged": adj.get("flagged", ""),
            "note": adj.get("note", ""),
        })  # fmt: skip
    summary = {
        "out": str(Path(args.out).resolve()),
        "n_map_points": len(points),
        "n_readjusted": n,
        "first_readjusted": undone[0] if undone else None,
        "frames": frames_out,
    }
    if args.json:
        emit_json(summary)
        return 0
    sys.stdout.write(
        f"{len(points)} map point(s) in {summary['out']}; adjusted {n} frame(s) again\n"
    )
    for f in frames_out:
        line = f"  frame {f['frame']}: {f['n_map_points']} map point(s)"
        if f["n_map_points"]:
            line += (
                f", {f['map_point_rms_px']:.2f} base px from them, predicted error "
                f"{f['predicted_error_px']:.2f} base px"
            )
        if f["flagged"]:
            line += f"; flagged: {f['flagged']}"
        if f["note"]:
            line += f"; {f['note']}"
        sys.stdout.write(line + "\n")
    return 0

"""``aerialreg calibrate``: estimate the Harris γ that makes straight lines straight.

With ``--lines LINES.json`` γ is fitted to polylines traced along straight world features (the
format is documented in :mod:`registration.calibration`); without it, long edges are detected in
the image and γ is fitted robustly to them.
"""

from __future__ import annotations

import argparse
import sys

from app.cli import UsageError, emit_json
from app.commands.undistort import read_image
from registration.calibration import (
    estimate_gamma_auto,
    estimate_gamma_from_lines,
    load_lines,
)

NAME = "calibrate"
HELP = "Estimate the Harris distortion parameter γ from straight lines (drawn or detected)."


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("image", metavar="IMAGE", help="raw (distorted) image file")
    p.add_argument(
        "--lines",
        metavar="LINES.json",
        help='polylines along straight world features, in raw pixels: {"version": 1, '
        '"image_size": [W, H], "lines": [[[x, y], ...], ...]}, each line >= 3 points (as the '
        "GUI saves them); without it, edges are detected automatically",
    )
    p.add_argument(
        "--gamma-range",
        metavar="LO,HI",
        help="search γ only in this range (default: -1 up to the frame's validity limit, ~1.0); write --gamma-range=-0.5,1 when LO is negative",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object: gamma, uncertainty, n_lines, method, residuals and the "
        "residual-versus-gamma curve",
    )


def _parse_range(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise UsageError(f"--gamma-range must look like -0.5,1.0, got {text!r}") from None
    if not lo < hi:
        raise UsageError(f"--gamma-range needs LO < HI, got {text!r}")
    return lo, hi


def run(args: argparse.Namespace) -> int:
    gamma_range = _parse_range(args.gamma_range)
    image = read_image(args.image)
    h, w = image.shape[:2]
    if args.lines:
        lines = load_lines(args.lines)
        if tuple(lines.image_size) != (w, h):
            raise UsageError(
                f"{args.lines} is for a {lines.image_size[0]}x{lines.image_size[1]} image but "
                f"{args.image} is {w}x{h}"
            )
        est = estimate_gamma_from_lines(lines.lines, w, h, gamma_range=gamma_range)
    else:
        est = estimate_gamma_auto(image, gamma_range=gamma_range)
    if args.json:
        emit_json(est.to_dict())
    else:
        sys.stdout.write(f"gamma {est.gamma:.4f} ± {est.uncertainty:.4f}\n")
        sys.stderr.write(
            f"{est.method}: {est.n_lines} lines ({est.n_rejected} rejected as not straight), "
            f"straightness {est.residual:.2f} px RMS at gamma {est.gamma:.3f} "
            f"(uncorrected {est.residual_uncorrected:.2f} px); uncertainty by {est.uncertainty_method}\n"
        )
    return 0

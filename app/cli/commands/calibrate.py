"""``aerialreg calibrate``: estimate the Harris γ that makes straight lines straight.

With ``--lines LINES.json`` γ is fitted to polylines traced along straight world features (the
format is documented in :mod:`registration.lens.lines_file`); without it, long edges are detected in
the image and γ is fitted robustly to them. With ``--frames`` (a video, a folder of frames or a
glob, instead of IMAGE) γ is fitted to the SIFT matches between frame pairs of the flight
(:mod:`registration.lens.gamma_from_motion`): through the right γ they obey one homography per pair.
Besides γ and its uncertainty the command reports whether the estimate is confident, and for
lines where they put the distortion centre (:func:`registration.lens.centre_fit.fit_center`; used with
``--center auto`` when the lines support it) and whether one parameter is enough
(:func:`registration.lens.centre_fit.check_one_parameter`).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from app.cli.commands.undistort import parse_center, read_image
from app.cli.common import UsageError, emit_json
from registration.lens import (
    DEFAULT_PAIRS,
    HARRIS_GAMMA_MIN,
    check_one_parameter,
    estimate_gamma_auto,
    estimate_gamma_from_lines,
    fit_center,
    load_lines,
)

NAME = "calibrate"
HELP = (
    "Estimate the Harris distortion parameter γ from straight lines (drawn or detected) or "
    "from the frames' motion."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("image", metavar="IMAGE", nargs="?", help="raw (distorted) image file")
    p.add_argument(
        "--frames",
        metavar="FRAMES",
        help="instead of IMAGE: the flight's raw frames (video file, folder of images or glob); "
        "γ is fitted to the matches between frame pairs, which needs no straight lines",
    )
    p.add_argument(
        "--pairs",
        type=int,
        default=DEFAULT_PAIRS,
        metavar="N",
        help=f"with --frames: frame pairs, spread over the flight (default {DEFAULT_PAIRS}; 3 or "
        "more let the uncertainty see a rolling shutter)",
    )
    p.add_argument(
        "--step",
        type=int,
        default=None,
        metavar="K",
        help="with --frames: frames apart within a pair (default: the smallest power of 2 at "
        "which the ground moves a quarter of the frame width, from the first frame)",
    )
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
        help=f"search γ only in this range (default: {HARRIS_GAMMA_MIN:g} up to the frame's "
        "validity limit, ~1.0); write --gamma-range=-0.5,1 when LO is negative",
    )
    p.add_argument(
        "--center",
        default="frame",
        metavar="frame|auto|X,Y",
        help="distortion centre: 'frame' = the frame centre, as the rest of aerialreg uses "
        "(default); 'auto' = fitted together with γ where the lines locate it and put it "
        "significantly off the frame centre, else the frame centre (the output says which); "
        "X,Y = this centre in raw pixels",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object: gamma, uncertainty, confident, evidence, center, "
        "center_source, center_fit, model_check, n_lines, method, residuals and the "
        "residual-versus-gamma curve",
    )


def _parse_range(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise UsageError(f"--gamma-range must look like -0.5,1.0, got {text!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi)) or not lo < hi:
        raise UsageError(f"--gamma-range needs finite LO < HI, got {text!r}")
    if lo < HARRIS_GAMMA_MIN:
        raise UsageError(
            f"--gamma-range {text!r} starts below {HARRIS_GAMMA_MIN:g}, the strongest "
            f"pincushion correction aerialreg accepts"
        )
    return lo, hi


def _check_motion_args(args: argparse.Namespace) -> None:
    if args.image is not None:
        raise UsageError(f"give IMAGE or --frames, not both (got {args.image!r} and --frames)")
    if args.lines:
        raise UsageError("--lines is for one IMAGE; γ from --frames uses the frames' motion")
    if args.center != "frame":
        raise UsageError(
            f"--center {args.center!r} is for straight lines; γ from --frames assumes the frame "
            "centre (conventions.md)"
        )
    if args.pairs < 1:
        raise UsageError(f"--pairs must be >= 1, got {args.pairs}")
    if args.step is not None and args.step < 1:
        raise UsageError(f"--step must be >= 1, got {args.step}")


def _run_motion(args: argparse.Namespace, gamma_range) -> int:
    from app.progress import ProgressBar
    from registration.io import open_frames
    from registration.lens import estimate_gamma_from_flight

    _check_motion_args(args)
    src = open_frames(args.frames)
    if len(src) < 2:
        raise UsageError(
            f"--frames {args.frames!r} has {len(src)} frame; γ from motion needs 2 or more"
        )
    with ProgressBar(args.pairs, "calibrate (matching frame pairs)") as bar:
        est = estimate_gamma_from_flight(
            src.get,
            len(src),
            n_pairs=args.pairs,
            step=args.step,
            gamma_range=gamma_range,
            progress=lambda done, total: bar.update(1),
        )
    if args.json:
        emit_json(est.to_dict())
        return 0
    sys.stdout.write(f"gamma {est.gamma:.4f} ± {est.uncertainty:.4f}\n")
    sys.stderr.write(motion_summary(est) + "\n")
    return 0


def motion_summary(est) -> str:
    """Two lines on a :class:`registration.lens.gamma_from_motion.MotionGammaEstimate` of a flight."""
    pair_text = ", ".join(f"{i}-{j}" for i, j in est.frame_pairs)
    return (
        f"motion: {est.n_pairs} of {len(est.frame_pairs)} frame pairs ({pair_text}; {est.step} "
        f"apart), {est.n_inliers} of {sum(est.pair_matches)} matches kept; transfer error "
        f"{est.residual:.2f} px RMS at gamma {est.gamma:.3f} (uncorrected "
        f"{est.residual_uncorrected:.2f} px)\n"
        f"{'confident' if est.confident else 'NOT confident'}: {est.evidence}"
    )


def run(args: argparse.Namespace) -> int:
    gamma_range = _parse_range(args.gamma_range)
    if args.frames is not None:
        return _run_motion(args, gamma_range)
    if args.image is None:
        raise UsageError("give a raw IMAGE, or the flight's frames with --frames")
    mode = args.center
    fixed_center = None if mode in ("frame", "auto") else parse_center(mode)
    image = read_image(args.image)
    h, w = image.shape[:2]
    lines = None
    if args.lines:
        lines = load_lines(args.lines)
        if tuple(lines.image_size) != (w, h):
            raise UsageError(
                f"{args.lines} is for a {lines.image_size[0]}x{lines.image_size[1]} image but "
                f"{args.image} is {w}x{h}"
            )

    def estimate(center):
        if lines is not None:
            return estimate_gamma_from_lines(
                lines.lines, w, h, center=center, gamma_range=gamma_range
            )
        return estimate_gamma_auto(image, center=center, gamma_range=gamma_range)

    est = estimate(fixed_center)
    source = "given" if fixed_center is not None else "frame"
    center_fit = fit_center(est) if est.n_lines >= 2 else None
    if mode == "auto" and center_fit is not None and center_fit.supported:
        est = estimate(center_fit.center)
        source = "estimated"
    check = check_one_parameter(est) if est.n_lines >= 2 else None
    if args.json:
        d = est.to_dict()
        d["center_source"] = source
        d["center_fit"] = center_fit.to_dict() if center_fit else None
        d["model_check"] = check.to_dict() if check else None
        emit_json(d)
        return 0
    c = est.model().c
    sys.stdout.write(f"gamma {est.gamma:.4f} ± {est.uncertainty:.4f}\n")
    sys.stderr.write(
        f"{est.method}: {est.n_lines} lines ({est.n_rejected} rejected as not straight), "
        f"straightness {est.residual:.2f} px RMS at gamma {est.gamma:.3f} "
        f"(uncorrected {est.residual_uncorrected:.2f} px)\n"
        f"{'confident' if est.confident else 'NOT confident'}: {est.evidence}\n"
        f"centre ({c[0]:.1f}, {c[1]:.1f}) [{source}]"
        + (f"; centre fit: {center_fit.message}" if center_fit else "")
        + "\n"
        + (f"{check.message}\n" if check else "")
    )
    return 0

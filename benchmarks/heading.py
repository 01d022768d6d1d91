"""Inter-sensor registration of the reference frame at any heading and map resolution: one
simulated frame against its base map turned by 0-330° and resampled to 0.5x, 1x and 2x
(``registration.synth.rebasing``; the truth stays exact), registered with one click 2 px off the
true position and with no click, against plain OpenCV (full-frame SIFT + FLANN + MAGSAC on the
radially corrected frame) in the same run.

Error: mean distance over a 17x13 grid of the raw frame between the registered and the true
base position, divided by the map's scale (so it is in frame pixels at every resolution);
``inf`` where a pipeline refuses the frame.
"""

from __future__ import annotations

import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

TITLE = "Reference frame at any heading and map resolution (one click, no click, OpenCV)"
HEADINGS = tuple(range(0, 360, 30))
SCALES = (0.5, 1.0, 2.0)
SEED_ERROR_PX = 2.0


def _opencv_error(frame, base, gamma, grid, truth_xy, scale) -> tuple[float, float]:
    """Plain OpenCV's error (frame px) and time (s) for one frame and map."""
    from registration.evaluation import BaselineConfig, apply_homography, homography, sift_features
    from registration.global_registration import corrected_grey
    from registration.lens import HarrisModel
    from registration.matching import to_grey

    t = time.perf_counter()
    h = homography(
        sift_features(corrected_grey(frame, gamma)), sift_features(to_grey(base)), BaselineConfig()
    )
    elapsed = time.perf_counter() - t
    if h is None:
        return float("inf"), elapsed
    w, hh = frame.shape[1], frame.shape[0]
    est = apply_homography(h, HarrisModel(gamma, w, hh).corrected_from_raw(grid))
    err = np.hypot(*(est - truth_xy).T)
    return (float(np.mean(err)) / scale if np.isfinite(err).all() else float("inf")), elapsed


def run(args) -> dict:
    from registration.global_registration import coarse_register, fine_register_reference
    from registration.io import open_frames, read_image
    from registration.lens import HarrisModel
    from registration.run import get_preset
    from registration.synth import SimConfig, load_truth, rebase, simulate

    w, h = args.size_wh
    tmp = Path(tempfile.mkdtemp(prefix="aerialreg-bench-"))
    src = tmp / "src"
    simulate(src, SimConfig(frame_size=(w, h), n_frames=1, seed=args.seed, video=False))
    cfg = get_preset("default")
    rng = np.random.default_rng(args.seed)
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 17), np.linspace(0, h - 1, 13))
    grid = np.c_[gx.ravel(), gy.ravel()]
    seed_frame = np.array([w * 0.45, h * 0.55])
    errors: dict[tuple[float, int, str], float] = {}
    times: dict[str, list[float]] = {"one click": [], "no click": [], "OpenCV": []}
    for scale in SCALES:
        for heading in HEADINGS:
            out = rebase(src, tmp / f"h{heading}_s{scale:g}", heading, scale)
            truth = load_truth(out)
            frame = open_frames(out / "frames").get(0)
            base = read_image(out / "base.png")
            valid = base.max(axis=2) > 0
            truth_xy = truth.frame_to_base(0, grid)
            a = rng.uniform(0, 2 * math.pi)
            seed_base = truth.frame_to_base(0, seed_frame[None])[0] + SEED_ERROR_PX * np.array(
                [math.cos(a), math.sin(a)]
            )
            for mode, seed in (("one click", (*seed_frame, *seed_base)), ("no click", None)):
                t = time.perf_counter()
                coarse = coarse_register(
                    frame, base, truth.gamma, seed, cfg.coarse, match_in=cfg.match_in,
                    base_valid=valid, rng=0,
                )  # fmt: skip
                fine = None
                if coarse:
                    fine = fine_register_reference(
                        frame, base, truth.gamma, coarse, cfg.fine, match_in=cfg.match_in,
                        base_valid=valid,
                    )  # fmt: skip
                times[mode].append(time.perf_counter() - t)
                if not fine:
                    errors[(scale, heading, mode)] = float("inf")
                    continue
                est = fine.base_from_corrected.apply(
                    HarrisModel(truth.gamma, w, h).corrected_from_raw(grid)
                )
                errors[(scale, heading, mode)] = (
                    float(np.mean(np.hypot(*(est - truth_xy).T))) / scale
                )
            err, elapsed = _opencv_error(frame, base, truth.gamma, grid, truth_xy, scale)
            errors[(scale, heading, "OpenCV")] = err
            times["OpenCV"].append(elapsed)
            sys.stderr.write(
                f"bench heading: {heading:3d}° x{scale:g}: one click "
                f"{errors[(scale, heading, 'one click')]:.2f}, no click "
                f"{errors[(scale, heading, 'no click')]:.2f}, OpenCV {err:.2f} px\n"
            )
    modes = ("one click", "no click", "OpenCV")
    lines = [
        f"One simulated {w}x{h} frame (seed {args.seed}) against its base map turned and "
        "resampled; mean error over a 17x13 grid of the frame, frame px (inf: refused). One "
        f"click is {SEED_ERROR_PX:g} px off the true position.",
        "",
        "| map resolution | pipeline | " + " | ".join(f"{d}°" for d in HEADINGS) + " |",
        "|---|---|" + "---:|" * len(HEADINGS),
    ]
    for scale in SCALES:
        for mode in modes:
            cells = " | ".join(f"{errors[(scale, d, mode)]:.2f}" for d in HEADINGS)
            lines.append(f"| {scale:g}x | {mode} | {cells} |")
    summary = {}
    for mode in modes:
        vals = np.array([errors[(s, d, mode)] for s in SCALES for d in HEADINGS])
        summary[mode] = {
            "registered": int(np.sum(vals < 2.0)),
            "worst_px": float(np.max(vals)),
            "mean_time_s": float(np.mean(times[mode])),
        }
    n = len(SCALES) * len(HEADINGS)
    lines += [
        "",
        "| pipeline | under 2 px | worst px | mean time s |",
        "|---|---:|---:|---:|",
    ]
    for mode in modes:
        s = summary[mode]
        lines.append(
            f"| {mode} | {s['registered']}/{n} | {s['worst_px']:.2f} | {s['mean_time_s']:.2f} |"
        )
    return {
        "size": [w, h],
        "errors": {f"{s:g}x {d} {m}": v for (s, d, m), v in errors.items()},
        "summary": summary,
        "markdown": "\n".join(lines),
    }

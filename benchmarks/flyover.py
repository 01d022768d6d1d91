"""The real flyover, the project's end-to-end case: a 20 s drone video (852x480, 600 frames at
29.97 fps) registered to a real GeoTIFF orthophoto of another season with one analyst's click
(``../shared/data/nust-flyover-video``, its SOURCE.md), scored from the images alone, as there is
no truth (:mod:`registration.evaluation.consistency`):

* frame-to-frame consistency: ground points of frame k carried into frame k+1 and k+5 through
  the registration and the map, found there by normalised cross-correlation; the distance between
  prediction and measurement (median and 90th percentile over all points), against the floor a
  homography fitted to the measured points leaves; also at the frames re-anchored to the map;
* agreement with the map: normalised correlation of gradient magnitudes of the registered frame
  and the map in 48 px windows (median per frame, then over the frames scored);
* frames registered.

aerialreg's default preset registers every frame and then adjusts the sequence (``--adjust``):
both are scored, each frame's own registration (``RegistrationResult.unadjusted``) and the
adjusted one, global and local stage; CPU of the adjusted rows includes the registration's.
In the same run: plain OpenCV per
frame (each frame matched to the map on its own: SIFT, FLANN, MAGSAC) and chained (frame 0 to the
map, each later frame to the one before it). ``--frames N`` takes the video's first N frames
(default all 600). The video's burnt-in logo (top left) is left out of the probes.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

TITLE = "Real flyover video against a real orthophoto of another season (images only)"
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
VIDEO = "nust-flyover-video/flyover_450-1049.mp4"
MAP = "georef-orthophoto-nust/ortho_utm43n_0.5m.tif"
CLICK = (585.0, 255.0, 1049.7, 996.2)  # SOURCE.md: frame 0 raw px <-> map px
LOGO = (15.0, 15.0, 97.0, 70.0)  # SOURCE.md: about x 20-92, y 20-65
STEPS = (1, 5)
AGREEMENT_EVERY = 10  # frames scored against the map


def _decode(n: int, out: Path) -> int:
    """The video's first ``n`` frames as PNGs in ``out`` (lossless: the same pixels)."""
    import cv2

    from registration.io import open_frames

    out.mkdir(parents=True)
    frames = open_frames(DATA / VIDEO)
    count = 0
    for k, frame in frames.iter():
        if k >= n:
            break
        cv2.imwrite(str(out / f"{k:06d}.png"), frame)
        count += 1
    frames.close()
    return count


def _consistency(result, greys, stage: str, anchors: set[int]) -> dict:
    from registration.evaluation.consistency import (
        ConsistencyConfig,
        pair_consistency,
        summarise,
    )
    from registration.matching import ProbeConfig

    cfg = ConsistencyConfig(probes=ProbeConfig(exclude=(LOGO,)))
    out = {}
    for step in STEPS:
        pairs = [
            pair_consistency(result, greys[k], greys[k + step], k, step, stage=stage, config=cfg)
            for k in range(len(greys) - step)
            if _ok(result, k) and _ok(result, k + step)
        ]
        s = summarise(pairs)
        at = [c for c in pairs if step == 1 and (c.k + 1) in anchors]
        s["at_anchors"] = summarise(at) if at else None
        out[step] = s
    return out


def _ok(result, k: int) -> bool:
    is_ok = getattr(result, "is_ok", None)
    if is_ok is not None:
        return is_ok(k)
    return result.homographies[k] is not None


def _agreement(result, frames, base_grey, base_valid, stage: str) -> dict[int, float]:
    """The map agreement of every ``AGREEMENT_EVERY``-th registered frame, by frame."""
    from registration.coords import bbox_of
    from registration.evaluation.consistency import map_agreement
    from registration.geometry import pixel_grid, remap

    hb, wb = base_grey.shape
    w, h = frames.size
    outline = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float)
    scores = {}
    for k in range(0, len(frames), AGREEMENT_EVERY):
        if not _ok(result, k):
            continue
        corners = result.frame_to_base(k, outline, stage)
        if not np.isfinite(corners).all():
            continue
        x0, y0, x1, y1 = bbox_of(corners, (wb, hb), 0)
        if x1 - x0 < 48 or y1 - y0 < 48:
            continue
        grid = pixel_grid(x1 - x0, y1 - y0) + (x0, y0)
        src = result.base_to_frame(k, grid.reshape(-1, 2), stage).reshape(grid.shape)
        grey = frames.get(k)
        registered = remap(grey, src)
        valid = remap(np.full(grey.shape[:2], 255, np.uint8), src, interpolation="nearest") > 0
        score = map_agreement(registered, valid, base_grey[y0:y1, x0:x1], base_valid[y0:y1, x0:x1])
        if score is not None:
            scores[k] = float(score)
    return scores


def paired_difference(scores: dict[int, float], reference: dict[int, float]) -> dict | None:
    """``scores`` against ``reference`` on the frames both scored: the median of the per-frame
    differences with its 95 % bootstrap interval (2000 resamples, seeded), their mean with its
    standard error, and how many frames are lower (higher) by more than 0.01. None without
    common frames."""
    common = sorted(set(scores) & set(reference))
    if not common:
        return None
    d = np.array([scores[k] - reference[k] for k in common])
    rng = np.random.default_rng(0)
    boot = np.median(d[rng.integers(0, len(d), (2000, len(d)))], axis=1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return {
        "n_frames": len(d),
        "median": float(np.median(d)),
        "ci95": [float(lo), float(hi)],
        "mean": float(np.mean(d)),
        "mean_se": float(np.std(d, ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan"),
        "n_lower": int(np.sum(d < -0.01)),
        "n_higher": int(np.sum(d > 0.01)),
    }


def _row(name: str, n_ok: int, n: int, cons: dict, agree, cpu_s: float | None) -> str:
    def f(v, nd=2):
        return "–" if v is None else f"{v:.{nd}f}"

    c1, c5 = cons[1], cons[5]
    anc = c1.get("at_anchors")
    return (
        f"| {name} | {n_ok}/{n} | {f(c1['median_px'])} | {f(c1['p90_px'])} "
        f"| {f(c1['floor_p90_px'])} | {f(c1['p90_over_floor'])}x "
        f"| {f(anc['p90_px']) if anc else '–'} "
        f"| {f(c5['p90_px'])} | {f(c5['floor_p90_px'])} | {f(c5['p90_over_floor'])}x "
        f"| {f(agree, 3)} | {f(cpu_s, 3)} |"
    )


def run(args) -> dict:
    import dataclasses

    import registration
    from benchmarks.register import links_cpu_per_frame
    from registration.adjustment import SequenceAdjustConfig
    from registration.evaluation import register_chained, register_per_frame
    from registration.gis import read_base_map
    from registration.io import open_frames
    from registration.matching import ProbeConfig, to_grey
    from registration.run import ANCHOR_STAGE, get_preset, register_sequence

    if not (DATA / VIDEO).is_file():
        msg = f"the real flyover is not available: {DATA / VIDEO} is absent"
        sys.stderr.write(f"bench flyover: {msg}\n")
        return {"skipped": msg, "markdown": f"(skipped: {msg})"}
    tmp = Path(tempfile.mkdtemp(prefix="aerialreg-bench-flyover-"))
    n = _decode(args.frames, tmp / "frames")
    frames = open_frames(tmp / "frames")
    base_map = read_base_map(DATA / MAP, nodata="auto")
    base_grey, base_valid = to_grey(base_map.image), base_map.valid
    greys = [to_grey(frames.get(k)) for k in range(n)]

    runs = {}
    # One run registers every frame (the default preset) and then adjusts the sequence: the
    # folder keeps each frame's own registration beside the adjusted one.
    adjust = SequenceAdjustConfig(probes=ProbeConfig(exclude=(LOGO,)))
    config = dataclasses.replace(get_preset("default"), adjust=adjust)
    cpu = time.process_time()
    adjust_started = []

    def adjust_progress(done, total):
        if not adjust_started:
            adjust_started.append(time.process_time())

    register_sequence(
        frames, base_map.image, 0.0, tmp / "reg", config=config, preset="default", seed=CLICK,
        base_valid=base_valid, adjust_progress=adjust_progress,
    )  # fmt: skip
    end = time.process_time()
    split = adjust_started[0] if adjust_started else end
    ours_cpu, adjust_cpu = (split - cpu) / n, (end - split) / n
    adjusted = registration.load(tmp / "reg")
    # The links the adjustment uses are measured as frames are registered: theirs is the
    # adjustment's CPU.
    links_cpu = links_cpu_per_frame(adjusted)
    ours_cpu, adjust_cpu = ours_cpu - links_cpu, adjust_cpu + links_cpu
    ours = adjusted.unadjusted()
    anchors = {k for k in range(n) if ours.records[k].stage == ANCHOR_STAGE}
    for stage in ("global", "local"):
        runs[f"aerialreg, each frame alone, {stage}"] = (ours, stage, ours_cpu)
    for stage in ("global", "local"):
        runs[f"aerialreg default (adjusted), {stage}"] = (adjusted, stage, ours_cpu + adjust_cpu)
    for name, fn in (
        ("OpenCV per frame", register_per_frame),
        ("OpenCV chained", register_chained),
    ):
        cpu = time.process_time()
        res = fn(frames, base_map.image, 0.0, base_valid=base_valid)
        runs[name] = (res, "global", (time.process_time() - cpu) / n)

    rows, figures = [], {}
    for name, (res, stage, cpu_s) in runs.items():
        sys.stderr.write(f"bench flyover: scoring {name} ...\n")
        n_ok = sum(_ok(res, k) for k in range(n))
        cons = _consistency(res, greys, stage, anchors)
        scores = _agreement(res, frames, base_grey, base_valid, stage)
        agree = float(np.median(list(scores.values()))) if scores else None
        figures[name] = {
            "frames_ok": n_ok, "consistency": cons, "map_agreement": agree,
            "map_agreement_by_frame": scores, "cpu_s_per_frame": cpu_s,
        }  # fmt: skip
        rows.append(_row(name, n_ok, n, cons, agree, cpu_s))
    paired = {
        stage: paired_difference(
            figures[f"aerialreg default (adjusted), {stage}"]["map_agreement_by_frame"],
            figures[f"aerialreg, each frame alone, {stage}"]["map_agreement_by_frame"],
        )
        for stage in ("global", "local")
    }
    head = (
        f"{n} frames 852x480, one click, map of another season; {len(anchors)} frames "
        "re-anchored to the map by aerialreg. Consistency in frame px (median / 90th "
        "percentile of |prediction - measurement| over all probes), its floor (what a homography "
        "fitted to the measured points leaves) and their ratio; 'at anchors': k -> k+1 where "
        "k+1 was re-anchored; map agreement: median gradient NCC with the map (every "
        f"{AGREEMENT_EVERY}th frame); CPU s per frame (process time, this process).\n\n"
        "| method | frames | k+1 median | k+1 p90 | floor p90 | p90/floor | p90 at anchors "
        "| k+5 p90 | floor p90 | p90/floor | map agreement | CPU s/frame |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    flagged = [
        k for k in range(n) if adjusted.records[k].stats.get("adjustment", {}).get("flagged")
    ]
    predicted = [
        adjusted.records[k].stats["adjustment"]["predicted_error_px"]
        for k in range(n)
        if "adjustment" in adjusted.records[k].stats
    ]
    tail = (
        (
            f"\n\nAdjusted: {len(flagged)} frames flagged; predicted error (base px) median "
            f"{np.median(predicted):.3f}, 90th percentile {np.percentile(predicted, 90):.3f}, "
            f"largest {np.max(predicted):.3f}; the adjustment's own CPU {adjust_cpu:.3f} s per frame "
            f"({100 * adjust_cpu / ours_cpu:.0f} % of the registration's), of which "
            f"{links_cpu:.3f} measuring the links as the frames are registered."
            + "".join(
                f" Map agreement adjusted minus alone, {stage}, frame by frame: median "
                f"{p['median']:+.4f} (95 % interval {p['ci95'][0]:+.4f} to {p['ci95'][1]:+.4f}), "
                f"mean {p['mean']:+.4f} ± {p['mean_se']:.4f}, "
                f"{p['n_lower']} of {p['n_frames']} frames lower by more than 0.01, "
                f"{p['n_higher']} higher."
                for stage, p in paired.items()
                if p
            )
        )
        if predicted
        else ""
    )
    return {
        "n_frames": n,
        "anchors": sorted(anchors),
        "flagged": flagged,
        "adjust_cpu_s_per_frame": adjust_cpu,
        "map_agreement_adjusted_minus_alone": paired,
        "methods": figures,
        "markdown": head + "\n".join(rows) + tail,
    }

"""Inter-sensor registration on the 200 real SRIF optical pairs (two dates four years apart,
rotations up to 360°, scales 0.25-2, black no-data corners, ground-truth similarity), ours
seeded and unseeded against the plain OpenCV pipeline, in the same run.

Seeded: one click taken from the ground truth with a 2 px error (direction drawn per pair, seed
0), at a point of image 1 that lies inside image 2's content, as an analyst would click.
Unseeded: the coarse step searches all headings and scales. Success: the mean error at image
1's four corners, against the ground truth, under 10 px and under 5 px. The corners often fall
where image 2 has no data, so every model extrapolates there; the coarse and the fine models
are scored separately. Image 2's no-data corners are given as the base's validity mask.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

TITLE = "Inter-sensor registration on 200 real SRIF pairs"
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "srif-optical-optical"
THRESHOLDS_PX = (10.0, 5.0)
SEED_ERROR_PX = 2.0


def corner_error(mapping, gt: np.ndarray, w: int, h: int) -> float:
    """Mean distance at image 1's corners between ``mapping`` and the ground truth (px of
    image 2); inf when the mapping is undefined there."""
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    truth = corners @ gt[:, :2].T + gt[:, 2]
    err = np.linalg.norm(mapping(corners) - truth, axis=1)
    return float(np.mean(err)) if np.isfinite(err).all() else float("inf")


# A pair's images hold another plane than its truth's when at least this many patches agree on a
# correction moving image 1's corners more than this many px, and at least this many times as
# many patches follow it as follow the published truth (within 2 px).
PLANE_MIN_PATCHES = 15
PLANE_MIN_OFFSET_PX = 10.0
PLANE_MIN_RATIO = 2.0


def dominant_plane(im1, im2, valid, gt: np.ndarray) -> tuple[int, int, float, np.ndarray]:
    """Which plane most of the images' texture follows, independently of our pipeline: image 1
    warped by the truth is cut into 48 px patches on a 16 px grid, each searched for in image 2
    within +-24 px (normalised correlation >= 0.5; both images' content only), and a similarity
    RANSAC (2 px) on the patch shifts gives the correction most patches agree on.

    On SRIF this finds the roofs of large buildings, not errors of the truth: on pairs 19, 94
    and 145 (corrections of 15-17 px, inspected at full resolution) rails and parking-lot
    markings line up under the published truth and are doubled under the correction, while the
    roofs do the opposite (relief displacement between two viewpoints). A registration that
    lands on the correction has followed the roofs, not the ground.

    Returns ``(patches agreeing on the correction, patches agreeing with the truth within 2 px,
    the correction's mean displacement of image 1's corners px, the corrected truth 2x3)``;
    ``(n, 0, nan, gt)`` with under 8 patches."""
    g1 = cv2.cvtColor(im1, cv2.COLOR_BGR2GRAY)
    g2 = cv2.cvtColor(im2, cv2.COLOR_BGR2GRAY)
    hb, wb = g2.shape
    warped = cv2.warpAffine(g1, gt, (wb, hb), flags=cv2.INTER_LINEAR)
    inside = cv2.warpAffine(np.ones_like(g1), gt, (wb, hb)) > 0
    both = inside & valid
    r, m = 24, 48  # search radius, half the search window
    src, dst = [], []
    for y in range(m, hb - m, 16):
        for x in range(m, wb - m, 16):
            if not both[y - m : y + m, x - m : x + m].all():
                continue
            patch = warped[y - 24 : y + 24, x - 24 : x + 24]
            if patch.std() < 8:
                continue
            score = cv2.matchTemplate(g2[y - m : y + m, x - m : x + m], patch,
                                      cv2.TM_CCOEFF_NORMED)  # fmt: skip
            _, top, _, (dx, dy) = cv2.minMaxLoc(score)
            if top >= 0.5:
                src.append((x, y))
                dst.append((x + dx - r, y + dy - r))
    if len(src) < 8:
        return len(src), 0, float("nan"), gt
    src, dst = np.array(src, float), np.array(dst, float)
    with_truth = int(np.count_nonzero(np.hypot(*(dst - src).T) < 2.0))
    # OpenCV's RANSAC seeds its own generator the same way on every call: reproducible.
    fix, inliers = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC,
                                               ransacReprojThreshold=2.0)  # fmt: skip
    if fix is None:
        return 0, with_truth, float("nan"), gt
    h, w = g1.shape
    corrected = fix[:, :2] @ gt + np.c_[np.zeros((2, 2)), fix[:, 2]]
    shift = corner_error(lambda p: p @ corrected[:, :2].T + corrected[:, 2], gt, w, h)
    return int(inliers.sum()), with_truth, shift, corrected


def follows_another_plane(n_plane: int, n_truth: int, shift_px: float) -> bool:
    """Whether :func:`dominant_plane`'s figures say most texture follows another plane."""
    return (
        n_plane >= PLANE_MIN_PATCHES
        and shift_px > PLANE_MIN_OFFSET_PX
        and n_plane >= PLANE_MIN_RATIO * n_truth
    )


def pair_ids() -> list[int]:
    return sorted(int(p.stem.split("_")[1]) for p in DATA.glob("gt_*.txt"))


def load_pair(i: int):
    """``(image 1, image 2, image 2's content mask, gt 2x3)``."""
    im1 = cv2.imread(str(DATA / f"pair{i}_1.jpg"))
    im2 = cv2.imread(str(DATA / f"pair{i}_2.jpg"))
    gt = np.loadtxt(DATA / f"gt_{i}.txt").reshape(2, 3)
    valid = cv2.cvtColor(im2, cv2.COLOR_BGR2GRAY) > 0
    return im1, im2, valid, gt


def seed_click(i: int, im1, valid, gt, error_px: float = SEED_ERROR_PX):
    """A click an analyst could make: a point in image 1's central 60 % whose true position in
    image 2 lies at least 15 px inside image 2's content, the image-2 side off by ``error_px``
    in a random direction (seeded by the pair id). None when no such point exists."""
    rng = np.random.default_rng(i)
    h1, w1 = im1.shape[:2]
    inner = cv2.erode(valid.astype(np.uint8), np.ones((31, 31), np.uint8))
    hb, wb = inner.shape
    for _ in range(2000):
        p = rng.uniform([0.2 * w1, 0.2 * h1], [0.8 * w1, 0.8 * h1])
        q = p @ gt[:, :2].T + gt[:, 2]
        x, y = int(round(q[0])), int(round(q[1]))
        if 0 <= x < wb and 0 <= y < hb and inner[y, x]:
            a = rng.uniform(0, 2 * np.pi)
            q = q + error_px * np.array([np.cos(a), np.sin(a)])
            return (float(p[0]), float(p[1]), float(q[0]), float(q[1]))
    return None


def register_pair(im1, im2, valid, seed, config, rng: int):
    """Our coarse and fine steps on one pair: ``(coarse, fine or None, seconds)``."""
    from registration.global_registration import coarse_register, fine_register_reference

    t0 = time.perf_counter()
    coarse = coarse_register(
        im1, im2, 0.0, seed, config.coarse, match_in=config.match_in, base_valid=valid, rng=rng
    )
    fine = None
    if coarse:
        fine = fine_register_reference(
            im1, im2, 0.0, coarse, config.fine, match_in=config.match_in, base_valid=valid
        )
        fine = fine or None
    return coarse, fine, time.perf_counter() - t0


def _rates(err: np.ndarray) -> dict:
    out = {f"success_{int(t)}px": float(np.mean(err < t)) for t in THRESHOLDS_PX}
    out["median_px"] = float(np.median(err))
    return out


def run(args) -> dict:
    from registration.evaluation import BaselineConfig, apply_homography, homography, sift_features
    from registration.run import get_preset

    if not DATA.is_dir():
        return {"skipped": f"{DATA} is absent", "markdown": f"skipped: {DATA} is absent"}
    config = get_preset("default")
    pairs = pair_ids()
    if getattr(args, "frames", None) and args.frames < len(pairs) and args.frames != 6:
        pairs = pairs[: args.frames]  # `--frames N` limits the pairs for a quick look
    keys = ("seeded_coarse", "seeded_fine", "unseeded_coarse", "unseeded_fine", "opencv")
    errs = {k: [] for k in keys}
    plane_errs = {k: [] for k in keys}  # against the other plane's correction, where flagged
    times = {k: [] for k in ("seeded", "unseeded", "opencv")}
    failures: dict[str, int] = {}
    other_plane: list[tuple[int, int, int, float]] = []
    on_other_plane: list[bool] = []  # per pair, whether its texture follows another plane
    for n, i in enumerate(pairs):
        im1, im2, valid, gt = load_pair(i)
        h, w = im1.shape[:2]
        n_plane, n_truth, offset, corrected = dominant_plane(im1, im2, valid, gt)
        flagged = follows_another_plane(n_plane, n_truth, offset)
        on_other_plane.append(flagged)
        if flagged:
            other_plane.append((i, n_plane, n_truth, offset))

        def record(key, mapping, size=(w, h), gt=gt, flagged=flagged, corrected=corrected):
            errs[key].append(float("inf") if mapping is None else corner_error(mapping, gt, *size))
            near = flagged and mapping is not None
            plane_errs[key].append(corner_error(mapping, corrected, *size) if near else np.nan)

        seed = seed_click(i, im1, valid, gt)
        for mode, s in (("seeded", seed), ("unseeded", None)):
            if mode == "seeded" and s is None:
                record("seeded_coarse", None)
                record("seeded_fine", None)
                continue
            coarse, fine, elapsed = register_pair(im1, im2, valid, s, config, i)
            times[mode].append(elapsed)
            record(f"{mode}_coarse", coarse.base_from_corrected.apply if coarse else None)
            if not coarse:
                reason = coarse.reason.split(":")[1].strip()[:40] if ":" in coarse.reason else ""
                failures[f"{mode}: {reason}"] = failures.get(f"{mode}: {reason}", 0) + 1
            record(f"{mode}_fine", None if fine is None else fine.base_from_corrected.apply)
        t0 = time.perf_counter()
        hmat = homography(sift_features(im1), sift_features(im2), BaselineConfig())
        times["opencv"].append(time.perf_counter() - t0)
        record("opencv", None if hmat is None else lambda p, m=hmat: apply_homography(m, p))
        if n % 20 == 0:
            sys.stderr.write(f"bench srif: {n + 1}/{len(pairs)}\n")
    arr = {k: np.array(v) for k, v in errs.items()}
    time_of = {"seeded_coarse": "seeded", "seeded_fine": "seeded", "unseeded_coarse": "unseeded",
               "unseeded_fine": "unseeded", "opencv": "opencv"}  # fmt: skip
    rows = {k: {**_rates(arr[k]), "time_s": float(np.mean(times[time_of[k]]))} for k in arr}
    for k in rows:
        miss = arr[k] >= 10.0  # failures included (inf)
        rows[k]["misses_on_other_plane_pairs"] = int(np.count_nonzero(miss & on_other_plane))
        rows[k]["misses_on_the_other_plane"] = int(
            np.count_nonzero(miss & (np.array(plane_errs[k]) < 10.0))
        )
    labels = {
        "seeded_coarse": "ours, one click (2 px off), coarse",
        "seeded_fine": "ours, one click (2 px off), coarse + fine",
        "unseeded_coarse": "ours, no click, coarse",
        "unseeded_fine": "ours, no click, coarse + fine",
        "opencv": "plain OpenCV (full-scale SIFT + FLANN + USAC_MAGSAC), no click",
    }
    md = [
        f"{len(pairs)} pairs; success = mean corner error under 10 px / 5 px against the "
        "ground-truth similarity; time per pair = coarse + fine for ours. The last column: of "
        f"the misses, how many are on the {len(other_plane)} pairs whose texture mostly follows "
        "another plane than the truth's (large roofs; `dominant_plane`), and how many of those "
        "lie within 10 px of that plane (the registration followed the roofs).",
        "",
        "| pipeline | success < 10 px | success < 5 px | median corner error px | time per pair s "
        "| misses on roof-plane pairs (on the roofs) |",
        "|---|---:|---:|---:|---:|---:|",
        *(
            f"| {labels[k]} | {100 * r['success_10px']:.1f} % | {100 * r['success_5px']:.1f} % "
            f"| {r['median_px']:.2f} | {r['time_s']:.3f} | {r['misses_on_other_plane_pairs']} "
            f"({r['misses_on_the_other_plane']}) |"
            for k, r in rows.items()
        ),
        "",
        "Texture following another plane than the truth (pair: patches with it / with the "
        "truth, corner shift px): "
        + (", ".join(f"{i}: {n}/{t}, {off:.1f}" for i, n, t, off in other_plane) or "none"),
    ]
    if failures:
        md += ["", "Refusals: " + "; ".join(f"{k} ({v})" for k, v in sorted(failures.items()))]
    return {
        "rows": rows,
        "n_pairs": len(pairs),
        "failures": failures,
        "other_plane": [
            {"pair": i, "patches": n, "patches_with_truth": t, "shift_px": o}
            for i, n, t, o in other_plane
        ],
        "markdown": "\n".join(md),
    }

"""Where a marked ground point lies in another frame, for Table 2 (paper section 6), and which
points are worth marking.

Table 2 measures the registration only if every mark is the same ground point. A proposal
therefore starts where the registration predicts the point (the point's own mark, mapped
frame -> base -> frame) and is refined by image matching only where the image can say where
the point is:

* the patch around the point constrains both directions: the structure tensor of the patch (as
  resampled into the target frame) has a smallest eigenvalue at least ``min_isotropy`` of the
  largest, and at least ``min_texture`` (a corner or a blob, not an edge or bland ground);
* the correlation peak is unique: no second peak, ``peak_exclusion_px`` or more from the best,
  reaches ``max_second_peak`` of it (repeated road markings, lane dashes);
* the peak is inside the search window and correlates at ``min_score`` or better.

Otherwise the proposal stays at the prediction, is marked *not refined* and says why: a
prediction is the registration's own answer and measures nothing, so it must never count in
Table 2 (the app refuses to confirm it). The template is always cut from the frame the analyst
marked and resampled into the target frame's geometry through the registration, so proposals
never chain on earlier proposals (chained correlation slid 6 px along a road in six steps).

Refinement is normalised cross-correlation for the integer peak, then OpenCV's ECC
(``cv2.findTransformECC``, translation) for the sub-pixel position.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.evaluation.truth import table_points
from registration.geometry.warp import remap


@dataclass(frozen=True)
class ProposalConfig:
    """How proposals are made and judged.

    Attributes:
        template_px: side of the patch matched around the point, raw px (odd).
        search_px: how far from the prediction the point is looked for, raw px.
        min_score: smallest normalised cross-correlation of an accepted match.
        min_isotropy: smallest ratio of the patch's structure-tensor eigenvalues (small
            eigenvalue / large one); below it the patch is an edge and slides along it.
        min_texture: smallest square root of the small eigenvalue, grey levels per px (mean over
            the patch); below it the ground is too bland to locate.
        max_second_peak: largest ratio of the second correlation peak to the best.
        peak_exclusion_px: the second peak is looked for this far or farther from the best, px.
    """

    template_px: int = 31
    search_px: int = 12
    min_score: float = 0.9
    min_isotropy: float = 0.15
    min_texture: float = 2.0
    max_second_peak: float = 0.9
    peak_exclusion_px: int = 3

    def __post_init__(self) -> None:
        if self.template_px < 7 or self.template_px % 2 == 0:
            raise ValueError(f"template_px must be odd and at least 7, got {self.template_px}")
        if self.search_px < 2:
            raise ValueError(f"search_px must be at least 2, got {self.search_px}")
        if self.peak_exclusion_px < 1:
            raise ValueError(f"peak_exclusion_px must be at least 1, got {self.peak_exclusion_px}")


@dataclass(frozen=True)
class MarkProposal:
    """A proposed mark in a target frame.

    Attributes:
        xy: ``(2,)`` raw px of the target frame: the refined position when ``refined``, else the
            prediction (NaN when there is no prediction).
        predicted: ``(2,)`` raw px where the registration puts the point.
        offset_px: distance from the prediction to the refined position, raw px (NaN when not
            refined): how far the registration is off there, as the image sees it.
        score: the correlation of the best match (NaN when not matched).
        refined: True when the image located the point (the proposal may be confirmed).
        reason: why not refined (empty when refined).
    """

    xy: NDArray[np.float64]
    predicted: NDArray[np.float64]
    offset_px: float
    score: float
    refined: bool
    reason: str = ""


@dataclass(frozen=True)
class PatchStructure:
    """How well a patch locates a point: ``isotropy`` (small / large structure-tensor
    eigenvalue, 0..1) and ``texture`` (square root of the small one, grey levels per px)."""

    isotropy: float
    texture: float

    def problem(self, config: ProposalConfig) -> str:
        """Why the patch cannot locate a point ("" when it can)."""
        if not np.isfinite(self.texture) or self.texture < config.min_texture:
            return (
                f"bland ground: texture {self.texture:.1f} < {config.min_texture:g} grey levels/px"
            )
        if self.isotropy < config.min_isotropy:
            return (
                f"along an edge: the patch fixes one direction only "
                f"(isotropy {self.isotropy:.2f} < {config.min_isotropy:g})"
            )
        return ""


def patch_structure(patch: NDArray) -> PatchStructure:
    """The structure tensor of ``patch`` (``(h, w)`` grey, any dtype), Gaussian-weighted towards
    its centre (sigma a quarter of its side)."""
    p = np.asarray(patch, np.float32)
    if p.ndim != 2 or min(p.shape) < 5 or not np.isfinite(p).all():
        return PatchStructure(0.0, float("nan"))
    gx = cv2.Scharr(p, cv2.CV_32F, 1, 0) / 32.0  # Scharr's kernel sums to 32 (grey levels/px)
    gy = cv2.Scharr(p, cv2.CV_32F, 0, 1) / 32.0
    h, w = p.shape
    gy_w = cv2.getGaussianKernel(h, h / 4.0)
    gx_w = cv2.getGaussianKernel(w, w / 4.0)
    weight = (gy_w @ gx_w.T)[1:-1, 1:-1]  # leave out the border row, where Scharr extrapolates
    weight = weight / weight.sum()
    gx, gy = gx[1:-1, 1:-1], gy[1:-1, 1:-1]
    a = float((weight * gx * gx).sum())
    b = float((weight * gx * gy).sum())
    c = float((weight * gy * gy).sum())
    root = np.hypot(0.5 * (a - c), b)
    big, small = 0.5 * (a + c) + root, max(0.5 * (a + c) - root, 0.0)
    return PatchStructure(small / big if big > 0 else 0.0, float(np.sqrt(small)))


def _grey(image: NDArray) -> NDArray[np.uint8] | NDArray:
    img = np.asarray(image)
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img  # frames are BGR


def propose_mark(
    image_from: NDArray,
    image_to: NDArray,
    predicted: ArrayLike,
    from_of_to: Callable[[NDArray], NDArray],
    config: ProposalConfig = ProposalConfig(),
) -> MarkProposal:
    """Refine a predicted mark in ``image_to`` against the marked frame ``image_from``.

    Args:
        image_from, image_to: ``(H, W[, 3])`` raw frames (uint8 or float).
        predicted: ``(2,)`` raw px of ``image_to`` where the point is predicted.
        from_of_to: maps ``(N, 2)`` raw px of ``image_to`` to raw px of ``image_from`` (through
            the registration); ``from_of_to(predicted)`` is the analyst's mark.
        config: :class:`ProposalConfig`.

    Returns:
        A :class:`MarkProposal` (module docstring for when it is refined).
    """
    pred = np.asarray(predicted, float).reshape(2)
    if not np.isfinite(pred).all():
        return _unrefined(pred, "the registration does not map the point into this frame")
    a, b = _grey(image_from), _grey(image_to)
    h = config.template_px // 2
    u = np.arange(-h, h + 1, dtype=float)
    grid = np.stack(np.meshgrid(pred[0] + u, pred[1] + u), axis=-1).reshape(-1, 2)
    src = np.asarray(from_of_to(grid), float).reshape(-1, 2)
    hb, wb = a.shape[:2]
    inside = np.isfinite(src).all(axis=1)
    inside &= (src[:, 0] >= 0) & (src[:, 0] <= wb - 1) & (src[:, 1] >= 0) & (src[:, 1] <= hb - 1)
    if not inside.all():
        return _unrefined(pred, "the patch leaves the marked frame")
    side = 2 * h + 1
    template = remap(
        np.asarray(a, np.float32),
        src.reshape(side, side, 2).astype(np.float32),
        interpolation="cubic",
    )
    problem = patch_structure(template).problem(config)
    if problem:
        return _unrefined(pred, problem)
    # The search window: whole pixels of image_to around the prediction.
    s = config.search_px
    x0, y0 = int(np.floor(pred[0])) - h - s, int(np.floor(pred[1])) - h - s
    x1, y1 = x0 + side + 2 * s + 1, y0 + side + 2 * s + 1
    if x0 < 0 or y0 < 0 or x1 > b.shape[1] or y1 > b.shape[0]:
        return _unrefined(pred, "the search window leaves this frame")
    window = np.asarray(b[y0:y1, x0:x1], np.float32)
    ncc = cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED)
    _, best, _, (px, py) = cv2.minMaxLoc(ncc)
    if not np.isfinite(best) or best < config.min_score:
        return _unrefined(pred, f"no match: correlation {best:.2f} < {config.min_score:g}", best)
    if px in (0, ncc.shape[1] - 1) or py in (0, ncc.shape[0] - 1):
        return _unrefined(pred, f"the best match lies at the search limit ({s} px)", best)
    second = _second_peak(ncc, px, py, config.peak_exclusion_px)
    if second >= config.max_second_peak * best:
        return _unrefined(
            pred,
            f"ambiguous: a second match correlates {second:.2f} against {best:.2f}",
            best,
        )
    xy = _ecc_refine(template, window, px, py)
    if xy is None or np.hypot(xy[0] - px, xy[1] - py) > 1.0:
        return _unrefined(pred, "sub-pixel refinement did not converge", best)
    # The template's centre is the mark; the window's pixel (px + h, py + h) holds it.
    found = np.array([x0 + xy[0] + h, y0 + xy[1] + h])
    return MarkProposal(
        xy=found,
        predicted=pred,
        offset_px=float(np.hypot(*(found - pred))),
        score=float(best),
        refined=True,
    )


def _second_peak(ncc: NDArray, px: int, py: int, exclusion: int) -> float:
    """The highest local maximum of ``ncc`` at least ``exclusion`` px (Chebyshev) from the best
    at ``(px, py)`` (-1 when there is none): a look-alike, not the best peak's own shoulder."""
    local_max = ncc >= cv2.dilate(ncc, np.ones((3, 3), np.uint8))
    yy, xx = np.nonzero(local_max)
    far = np.maximum(np.abs(xx - px), np.abs(yy - py)) >= exclusion
    return float(ncc[yy[far], xx[far]].max()) if far.any() else -1.0


def _ecc_refine(template: NDArray, window: NDArray, px: int, py: int) -> NDArray | None:
    """Sub-pixel top-left of ``template`` in ``window`` by ECC (translation), from ``(px, py)``."""
    warp = np.array([[1, 0, px], [0, 1, py]], np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
    try:
        _, warp = cv2.findTransformECC(
            template, window, warp, cv2.MOTION_TRANSLATION, criteria, None, 1
        )
    except cv2.error:
        return None
    return np.array([float(warp[0, 2]), float(warp[1, 2])])


def _unrefined(pred: NDArray, reason: str, score: float = float("nan")) -> MarkProposal:
    return MarkProposal(
        xy=pred.copy(),
        predicted=pred.copy(),
        offset_px=float("nan"),
        score=float(score),
        refined=False,
        reason=reason,
    )


def propose_through(
    mapping,
    image_from: NDArray,
    k_from: int,
    xy_from: ArrayLike,
    image_to: NDArray,
    k_to: int,
    config: ProposalConfig = ProposalConfig(),
    *,
    stage: str = "local",
) -> MarkProposal:
    """:func:`propose_mark` with the prediction and the resampling from a registration.

    Args:
        mapping: a registration result (``registration.load``) or any ``SequenceMapping``.
        image_from: frame ``k_from`` (raw), where the analyst marked the point at ``xy_from``
            (``(2,)`` raw px).
        image_to: frame ``k_to`` (raw).
        stage: the registration stage that predicts ("global" or "local").
    """
    xy = np.asarray(xy_from, float).reshape(1, 2)
    pred = mapping.base_to_frame(k_to, mapping.frame_to_base(k_from, xy, stage), stage)[0]

    def from_of_to(q: NDArray) -> NDArray:
        return mapping.base_to_frame(k_from, mapping.frame_to_base(k_to, q, stage), stage)

    return propose_mark(image_from, image_to, pred, from_of_to, config)


def propose_unregistered(
    image_from: NDArray,
    xy_from: ArrayLike,
    image_to: NDArray,
    config: ProposalConfig = ProposalConfig(search_px=64),
) -> MarkProposal:
    """:func:`propose_mark` before any registration: predicted where it was marked (the frames
    taken as unmoved), searched over ``config.search_px``."""
    xy = np.asarray(xy_from, float).reshape(2)
    return propose_mark(image_from, image_to, xy, lambda q: np.asarray(q, float), config)


@dataclass(frozen=True)
class SuggestedPoint:
    """A ground point worth marking: ``location`` (one of the paper's NW, NE, Center, SW, SE),
    ``xy`` (2,) raw px in the frame it was found in, the patch's ``structure``, and
    ``n_frames`` (how many frames the registration maps it into, with the patch inside)."""

    location: str
    xy: NDArray[np.float64]
    structure: PatchStructure
    n_frames: int


def suggest_points(
    mapping,
    frames: Callable[[int], NDArray],
    k: int,
    config: ProposalConfig = ProposalConfig(),
    *,
    inset: float = 0.2,
    radius: float = 0.12,
    min_frames: int = 2,
    min_score: float = 0.95,
    n_checks: int = 6,
    stage: str = "local",
) -> list[SuggestedPoint]:
    """Points worth marking in frame ``k``, one near each of the paper's five locations.

    Candidates are corners (``cv2.goodFeaturesToTrack``, the smallest structure-tensor
    eigenvalue) within ``radius`` of the frame's diagonal from each location (``inset`` of the
    size in from the corners, as the truth mode's Table 2). Each must pass the tests a proposal
    is refined by (structure, no look-alike around it), be mapped with its search window inside
    into at least ``min_frames`` frames, and be refined from frame ``k`` with a correlation of
    ``min_score`` or more in ``n_checks`` frames spread over those (which rejects vehicles, and
    points that vehicles pass over, and whatever else changes). The most frames
    win, then the most isotropic patch. Locations without such a point are left out.

    Whether a point is on the ground (not a roof with relief) is not checked: the analyst judges.

    Args:
        mapping: a registration result or any ``SequenceMapping``.
        frames: ``frames(j)`` returns raw frame ``j`` (``(H, W[, 3])``).

    Returns:
        ``list[SuggestedPoint]`` in the paper's order (NW, NE, Center, SW, SE).
    """
    from registration.evaluation.table2 import LOCATIONS

    image = frames(k)
    grey = _grey(image)
    hgt, wid = grey.shape[:2]
    grey8 = np.asarray(
        grey if grey.dtype == np.uint8 else cv2.normalize(grey, None, 0, 255, cv2.NORM_MINMAX),
        np.uint8,
    )
    r_px = radius * np.hypot(wid, hgt)
    # Candidates of every location first, then one pass over the frames maps them all.
    candidates: list[tuple[str, NDArray, PatchStructure]] = []
    for loc, (cx, cy) in zip(LOCATIONS, table_points((wid, hgt), inset), strict=True):
        mask = np.zeros_like(grey8)
        cv2.circle(mask, (int(round(cx)), int(round(cy))), int(round(r_px)), 255, -1)
        corners = cv2.goodFeaturesToTrack(
            grey8, maxCorners=40, qualityLevel=0.05, minDistance=config.template_px, mask=mask
        )
        for x, y in (corners if corners is not None else np.zeros((0, 2))).reshape(-1, 2):
            structure = _candidate_structure(grey, (float(x), float(y)), config)
            if structure is not None:
                candidates.append((loc, np.array([x, y], float), structure))
    seen = _frames_seeing(mapping, k, [c[1] for c in candidates], config, (wid, hgt), stage)
    out = []
    for loc in LOCATIONS:
        mine = [(c[1], seen[i], c[2]) for i, c in enumerate(candidates) if c[0] == loc]
        mine = [c for c in mine if len(c[1]) >= min_frames]
        mine.sort(key=lambda c: (-len(c[1]), -c[2].isotropy))
        for xy, frames_in, structure in mine:
            others = [j for j in frames_in if j != k]
            picks = np.linspace(0, len(others) - 1, n_checks).round().astype(int) if others else []
            if all(
                _stable(mapping, image, k, xy, frames(j), j, config, stage, min_score)
                for j in sorted({others[i] for i in picks})
            ):
                out.append(SuggestedPoint(loc, xy, structure, len(frames_in)))
                break
    return out


def _stable(mapping, image, k, xy, image_j, j, config, stage, min_score) -> bool:
    """Whether the point of frame ``k`` is refined in frame ``j`` at ``min_score`` or more."""
    p = propose_through(mapping, image, k, xy, image_j, j, config, stage=stage)
    return p.refined and p.score >= min_score


def _margin(config: ProposalConfig) -> int:
    """How far inside a frame a point must lie for its patch and search window, px."""
    return config.template_px // 2 + config.search_px + 1


def _candidate_structure(grey, xy, config: ProposalConfig) -> PatchStructure | None:
    """The patch structure of a candidate point, or None when the patch cannot locate it, has a
    look-alike nearby or does not fit in the frame with its search window."""
    h, s, m = config.template_px // 2, config.search_px, _margin(config)
    x, y = int(round(xy[0])), int(round(xy[1]))
    hgt, wid = grey.shape[:2]
    if x - m < 0 or y - m < 0 or x + m + 1 > wid or y + m + 1 > hgt:
        return None
    patch = np.asarray(grey[y - h : y + h + 1, x - h : x + h + 1], np.float32)
    structure = patch_structure(patch)
    if structure.problem(config):
        return None
    window = np.asarray(grey[y - m : y + m + 1, x - m : x + m + 1], np.float32)
    ncc = cv2.matchTemplate(window, patch, cv2.TM_CCOEFF_NORMED)
    if _second_peak(ncc, s + 1, s + 1, config.peak_exclusion_px) >= config.max_second_peak:
        return None
    return structure


def _frames_seeing(mapping, k, points, config, frame_size, stage) -> list[list[int]]:
    """Per point of frame ``k``: the frames the registration maps it into, patch and search
    window inside."""
    if not points:
        return []
    wid, hgt = frame_size
    m = _margin(config)
    base = mapping.frame_to_base(k, np.asarray(points, float), stage)
    seen: list[list[int]] = [[] for _ in points]
    for j in range(mapping.n_frames):
        p = mapping.base_to_frame(j, base, stage)
        ok = np.isfinite(p).all(axis=1)
        ok[ok] &= (p[ok, 0] >= m) & (p[ok, 0] <= wid - 1 - m)
        ok[ok] &= (p[ok, 1] >= m) & (p[ok, 1] <= hgt - 1 - m)
        for i in np.flatnonzero(ok):
            seen[i].append(j)
    return seen

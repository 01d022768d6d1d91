"""Template control points (paper 4.3.2): a grid of templates cut from the frame, matched by
normalised cross-correlation in the reference around where the current model puts them, refined
to sub-pixel and by the dithered re-correlation.

:func:`template_control_points` runs these named steps:

1. **grid selection** (:func:`template_grid`, :func:`edge_ring`): the template centres, and
   the ones whose predicted position is defined and invertible (:func:`_usable_centres`);
2. **search-image preparation** (:func:`prepare_search`): the reference warped once into the
   frame's geometry (beyond the paper), with where it has no content; a second reference
   (the previous frame, paper 4.4) only for templates the first cannot take
   (:func:`_assign_windows`);
3. **correlation** (:func:`_correlate`): ``cv2.matchTemplate`` over the search window, in
   parallel threads;
4. **sub-pixel refinement** (:func:`_refine_peak`): a quadratic fit of the peak and the
   dithered re-correlation.

Points are ``(N, 2)`` float64 ``(x, y)`` pixels with pixel centres at integer coordinates
(``conventions.md``); transforms are plain callables ``(N, 2) -> (N, 2)``.
"""

from __future__ import annotations

import logging
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from registration import coords
from registration.geometry import warp
from registration.matching.control_points import ControlPoints, PointFunction, call_points
from registration.matching.grey import to_grey
from registration.matching.gridded_sift import GriddedReference
from registration.matching.ncc_peaks import _refine_peak, _structure_centroid

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TemplateConfig:
    """The fine inter-sensor control points (paper 4.3.2).

    Attributes:
        spacing_px: distance between template centres, frame px (50, paper 4.3.2).
        template_px: template side, frame px (75, paper 4.3.2); an even value is rounded up to
            the next odd one so that the centre is a pixel.
        search_px: side of the searched neighbourhood, px (20, paper 4.3.2 "20 x 20
            neighborhood"): offsets ``-search_px//2 .. +search_px//2`` are tried in both axes.
        min_score: NCC peak below which a template is dropped (0.5; beyond the paper, which
            leaves all mismatches to REQCON; -1 keeps every peak).
        subpixel: peak refinement: ``"quadratic"`` (least-squares 2-D quadratic over the 3x3
            neighbourhood of the integer peak), ``"parabolic"`` (separate 3-point parabolas in x
            and y) or ``"none"``. The paper says only "sub-pixel"; quadratic by default.
        warp_reference: True (beyond the paper): warp the reference once into frame geometry
            with the current ``ref_from_frame`` and correlate there, so the ~10° rotation and
            ~20 % scale difference (paper 4.3.2) no longer decorrelate the templates. False =
            the paper: direct correlation in reference pixels around the predicted position
            (measured on a 1/4-scale real frame at 10° and 1.2x: NCC peaks 0.25-0.5 and ~90 %
            mismatches, as the paper expected, so :meth:`paper` also sets ``min_score=-1``).
        dither_iterations: the paper's "dithered" NCC, in our reading (the paper does not define
            it): after the integer peak and its sub-pixel fit, the search window is resampled
            (bilinear) at the estimated sub-pixel offset, i.e. dithered by the fractional part,
            and the template is correlated again over +-1 px; the new sub-pixel fit is added. A
            peak fitted near an integer is much less biased than one between pixels (measured on
            a real 1/4-scale Songdo frame with a fractional offset of (3.3, -2.6) px: median error
            0.083 -> 0.026 px, 90th percentile 0.32 -> 0.05 px; bicubic resampling was no better
            and costs twice as much). Number of such rounds; 1 (paper: "dithered"), 0 disables
            it. Costs about 0.4x the main correlation.
        jitter_px: beyond the paper, off by default: each template centre is moved off the
            regular grid by a seeded, reproducible integer offset, uniform in
            ``[-jitter_px, jitter_px]`` in x and y, so that templates do not sample periodic
            scene structure (lane markings, roof rows, parking bays) at one fixed phase and
            successive calls with different ``jitter_seed`` use different lattices.
        jitter_seed: seed of the jitter offsets.
        anchor: which frame point a template's match is attributed to (only with
            ``warp_reference``). ``"centre"``: the template centre (the paper). ``"structure"``
            (beyond the paper): the structure-tensor-weighted centroid ``c + M^-1 sum G(x)(x - c)``
            with ``G = grad grad^T`` per pixel and ``M = sum G``. Correlation measures the
            texture-weighted mean displacement over the template, which for a locally affine
            error of the current model is exactly the displacement at that centroid, not at the
            centre (measured on a 1/4-scale real frame, model off by 0.4 % scale and 0.2°:
            median error 0.158 -> ~0.12 px).
        min_template_std: texture check (beyond the paper): templates whose grey-level standard
            deviation is below this (grey levels 0..255) are skipped, because flat asphalt,
            roofs and water give flat NCC surfaces with spurious peaks. Applied to the frame
            template and to the searched reference window alike.
        reject_border_peaks: drop templates whose integer peak lies on the border of the search
            range (the true peak may lie outside it, and no sub-pixel fit is possible there).
        map_step_px: evaluation step of ``ref_from_frame`` when the reference is warped into
            frame geometry (8 px, see :func:`registration.geometry.warp.source_map_from_function`); a
            match's ``dst`` is read through the same lattice.
        max_roundtrip_px: with ``frame_from_ref`` given, templates whose centre does not come
            back within this distance through ``frame_from_ref(ref_from_frame(c))`` are skipped
            (the model is not invertible there). Frame px.
        min_templates: beyond the paper: when the grid at ``spacing_px`` holds fewer templates
            than this (small frames), the spacing shrinks until it holds this many (or reaches
            1 px); the edge ring uses the same spacing. 0 = always ``spacing_px``.
        signal: what is correlated: ``"intensity"`` (grey levels, the paper) or ``"gradient"``
            (beyond the paper: the gradient magnitude of each image, each scaled to 0..255 by
            its own 99th percentile). Another date, season or sensor changes brightness,
            colour and the contrast of materials, and can invert it (a roof darker than the
            street in one, lighter in the other); the edges of streets, kerbs and buildings stay
            where they are, so their gradient magnitude correlates across sensors where the
            intensities do not (measured on the OrthoLoC UAV photo against the official
            orthophoto of another date, from a one-click similarity: intensity NCC 52 px mean
            error after four rounds, gradient NCC 2.7 px).
        edge_template_px: beyond the paper: when > 0, a ring of extra templates of this size
            along the frame border (corners included, ``spacing_px`` apart, each as close to the
            edge as it fits). The main grid stops ``template_px / 2`` from the border; after a
            strong radial correction that is far from the corners in corrected pixels (at
            γ = 0.7 the correction stretches the raw corners about 6x), so without the ring the
            global model extrapolates there. 0 = no ring (the paper).
        change_log_ratio: beyond the paper, 0 (off) in the paper's choices; only for windows
            of a reference taken by another sensor or at another time (the base map; see
            :func:`template_control_points`'s ``ref_other_sensor``): after the peak is
            found, the template is compared with the window at the peak, pixel by pixel. A line
            (gain and offset) predicts the window's brightness from the template's (fitted
            three times, each to the pixels the last left unchanged); where the brightness
            departs from it by more than this (natural-log ratio, after a slight blur), the
            scene changed between the two images (a shadow cast by another sun, a car that came
            or went). Those pixels, widened by 2 px, are left out of a masked correlation within
            3 px of the first peak (and its dithered re-correlation), and the test is made once
            more at the masked peak. A moved shadow edge is a real edge in both images, so
            unmasked it pulls the peak towards itself: on the simulated map of another date (the
            sun 5° and 2° away), the reference frame's control points carried a (-0.07, +0.35)
            px mean bias and 0.418 px median error unmasked; 0.236 px median with a constant
            ratio instead of the line (one round, 0.2); 0.129 px with the line, two rounds and
            0.1 (the points REQCON kept: mean y bias +0.25 -> +0.14 px; after the local stage
            the frame's error 0.331 -> 0.268 px). Where less than ``change_min_share`` of a
            template is left, the peak found so far stands. Not for the edge ring's small
            templates: what the test leaves of 31 px scattered their peaks, and the frames along
            a long flight's leading edge, matched there against the map, jumped (frame-to-frame
            motion after global 0.67 -> 2.26 px).
        change_min_share: see ``change_log_ratio`` (0.4).
    """

    spacing_px: int = 50
    template_px: int = 75
    search_px: int = 20
    min_score: float = 0.5
    subpixel: Literal["quadratic", "parabolic", "none"] = "quadratic"
    warp_reference: bool = True
    dither_iterations: int = 1
    jitter_px: float = 0.0
    jitter_seed: int = 0
    anchor: Literal["centre", "structure"] = "structure"
    min_template_std: float = 4.0
    reject_border_peaks: bool = True
    map_step_px: int = 8
    max_roundtrip_px: float = 1.0
    min_templates: int = 0
    edge_template_px: int = 0
    signal: Literal["intensity", "gradient"] = "intensity"
    change_log_ratio: float = 0.0
    change_min_share: float = 0.4

    def __post_init__(self) -> None:
        if self.spacing_px < 1 or self.template_px < 3 or self.search_px < 2:
            raise ValueError(
                "TemplateConfig needs spacing_px >= 1, template_px >= 3, search_px >= 2, got "
                f"{self.spacing_px}, {self.template_px}, {self.search_px}"
            )
        if self.signal not in ("intensity", "gradient"):
            raise ValueError(
                f"TemplateConfig.signal must be 'intensity' or 'gradient', got {self.signal!r}"
            )
        if self.anchor not in ("centre", "structure"):
            raise ValueError(
                f"TemplateConfig.anchor must be 'centre' or 'structure', got {self.anchor!r}"
            )
        if self.subpixel not in ("quadratic", "parabolic", "none"):
            raise ValueError(
                f"TemplateConfig.subpixel must be 'quadratic', 'parabolic' or 'none', got {self.subpixel!r}"
            )
        if (
            self.jitter_px < 0
            or self.min_template_std < 0
            or self.map_step_px < 1
            or self.dither_iterations < 0
            or self.change_log_ratio < 0
            or not 0.0 <= self.change_min_share < 1.0
        ):
            raise ValueError(
                "TemplateConfig.jitter_px, min_template_std, dither_iterations and "
                "change_log_ratio must be >= 0, map_step_px >= 1 and change_min_share in [0, 1), "
                f"got {self.jitter_px}, {self.min_template_std}, {self.dither_iterations}, "
                f"{self.change_log_ratio}, {self.map_step_px}, {self.change_min_share}"
            )

    @classmethod
    def paper(cls) -> TemplateConfig:
        """Exactly the paper's choices (4.3.2): direct correlation in reference pixels, every
        peak kept for REQCON, no texture check; the dithered NCC and sub-pixel peak as above."""
        return cls(warp_reference=False, min_score=-1.0, min_template_std=0.0, anchor="centre")

    @property
    def half_template(self) -> int:
        return self.template_px // 2

    @property
    def search_radius(self) -> int:
        return self.search_px // 2


def template_grid(
    width: int, height: int, config: TemplateConfig = TemplateConfig()
) -> NDArray[np.int64]:
    """Integer template centres for a ``width`` x ``height`` frame, ``(N, 2)`` int64 (x, y).

    A regular grid with ``config.spacing_px`` spacing, centred in the frame, with every template
    fully inside it; then moved by the seeded jitter (``config.jitter_px``) and clipped so the
    templates stay inside. Empty when the frame is smaller than one template.
    """
    h = config.half_template
    spacing = grid_spacing(width, height, config)
    axes = []
    for n_px in (width, height):
        span = n_px - 1 - 2 * h
        if span < 0:
            return np.zeros((0, 2), np.int64)
        count = span // spacing + 1
        first = h + (span - (count - 1) * spacing) // 2
        axes.append(first + spacing * np.arange(count))
    gx, gy = np.meshgrid(axes[0], axes[1], indexing="xy")
    centres = np.stack([gx.ravel(), gy.ravel()], axis=1).astype(np.int64)
    if config.jitter_px > 0:
        rng = np.random.default_rng(config.jitter_seed)
        d = int(math.floor(config.jitter_px))
        centres = centres + rng.integers(-d, d + 1, size=centres.shape)
        centres[:, 0] = np.clip(centres[:, 0], h, width - 1 - h)
        centres[:, 1] = np.clip(centres[:, 1], h, height - 1 - h)
    return centres


def grid_spacing(width: int, height: int, config: TemplateConfig) -> int:
    """The template spacing for a ``width`` x ``height`` frame: ``spacing_px``, or less when
    that leaves fewer than ``min_templates`` templates (see :class:`TemplateConfig`)."""
    spacing = config.spacing_px
    span_x = width - 1 - 2 * config.half_template
    span_y = height - 1 - 2 * config.half_template
    if span_x < 0 or span_y < 0:
        return spacing
    while spacing > 1 and (span_x // spacing + 1) * (span_y // spacing + 1) < config.min_templates:
        spacing -= 1
    return spacing


def edge_ring(width: int, height: int, template_px: int, spacing_px: int) -> NDArray[np.int64]:
    """Integer centres of ``template_px`` templates along the border of a ``width`` x ``height``
    frame, as close to the edge as they fit, about ``spacing_px`` apart, corners included;
    ``(N, 2)`` int64, empty when the frame is smaller than one template."""
    h = template_px // 2
    lo_x, hi_x, lo_y, hi_y = h, width - 1 - h, h, height - 1 - h
    if hi_x < lo_x or hi_y < lo_y:
        return np.zeros((0, 2), np.int64)
    nx = max(1, round((hi_x - lo_x) / spacing_px))
    ny = max(1, round((hi_y - lo_y) / spacing_px))
    xs = np.round(np.linspace(lo_x, hi_x, nx + 1)).astype(np.int64)
    ys = np.round(np.linspace(lo_y, hi_y, ny + 1)).astype(np.int64)
    ring = [np.c_[xs, np.full_like(xs, lo_y)], np.c_[xs, np.full_like(xs, hi_y)]]
    if len(ys) > 2:
        inner = ys[1:-1]
        ring += [np.c_[np.full_like(inner, lo_x), inner], np.c_[np.full_like(inner, hi_x), inner]]
    return np.unique(np.vstack(ring).astype(np.int64), axis=0)


def gradient_magnitude(grey: NDArray) -> NDArray[np.uint8]:
    """Sobel gradient magnitude of an image, scaled so that its 99th percentile is 255 (uint8,
    same shape): the ``"gradient"`` signal of :class:`TemplateConfig`."""
    g = to_grey(grey)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    mag = cv2.magnitude(gx, gy)
    top = _percentile(mag, 99.0) if mag.size else 0.0
    return np.clip(mag * np.float32(255.0 / max(top, 1e-6)), 0, 255).astype(np.uint8)


def _percentile(values: NDArray, q: float) -> float:
    """NumPy's default (linear) percentile of a non-empty array, from its exact order statistics
    interpolated in float64: the same value under every NumPy release (2.4 changed the float32
    interpolation, which moved a gradient image's scaling by one grey level in a few pixels and
    flipped a real SRIF pair from 2 to 16 px)."""
    flat = values.ravel()
    pos = q / 100.0 * (flat.size - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, flat.size - 1)
    part = np.partition(flat, (lo, hi))
    a, b = float(part[lo]), float(part[hi])
    return a + (pos - lo) * (b - a)


def _signal(image: NDArray, config: TemplateConfig) -> NDArray[np.uint8]:
    return gradient_magnitude(image) if config.signal == "gradient" else to_grey(image)


@dataclass
class SearchImage:
    """A reference resampled into the frame's geometry on a canvas padded by ``pad`` px:
    canvas pixel ``(i, j)`` shows what frame pixel ``(i - pad, j - pad)`` maps to.

    Attributes:
        image: the warped reference, ``(H + 2 pad, W + 2 pad)`` uint8.
        invalid: ``(H + 2 pad, W + 2 pad)`` bool, canvas pixels without reference content.
        pad: the padding (the search radius), px.
        ref_from_frame: the map that was used, frame px -> reference px.
    """

    image: NDArray[np.uint8]
    invalid: NDArray[np.bool_]
    pad: int
    ref_from_frame: PointFunction


def prepare_search(
    ref: NDArray,
    ref_from_frame: PointFunction,
    frame_size: tuple[int, int],
    pad: int,
    config: TemplateConfig,
    ref_valid: NDArray | None = None,
) -> SearchImage:
    """Warp ``ref`` into the geometry of a ``frame_size`` = ``(W, H)`` frame (step 2; see
    :class:`SearchImage`), sampling ``ref_from_frame`` every ``config.map_step_px`` px
    (:func:`registration.geometry.warp.source_map_from_function`), bilinear. ``ref_valid``: where the
    reference has content."""
    fw, fh = frame_size
    smap = warp.source_map_from_function(
        ref_from_frame, fw + 2 * pad, fh + 2 * pad, step=config.map_step_px, origin=(-pad, -pad)
    )
    image = warp.remap(ref, smap, interpolation="linear")
    return SearchImage(image, _invalid(smap, ref.shape, ref_valid), pad, ref_from_frame)


def _invalid(smap: NDArray, ref_shape: tuple[int, ...], ref_valid: NDArray | None) -> NDArray:
    """Pixels of a source map without reference content: outside the reference (NaN fails
    every comparison, so pixels without a source too) or where ``ref_valid`` is False."""
    rh, rw = ref_shape[:2]
    # One pass of OpenCV over the (H, W, 2) map instead of four numpy comparisons (6 against
    # 13 ms on a 2560x1920 frame's map); bounds inclusive, NaN out of range, as they were.
    invalid = cv2.inRange(smap, (0.0, 0.0), (rw - 1.0, rh - 1.0)) == 0
    if ref_valid is not None:
        invalid |= warp.remap(warp.as_uint8_mask(ref_valid), smap, interpolation="nearest") == 0
    return invalid


def template_control_points(
    frame_grey: NDArray,
    ref_grey: NDArray,
    ref_from_frame: PointFunction,
    frame_from_ref: PointFunction | None = None,
    config: TemplateConfig = TemplateConfig(),
    *,
    centres: NDArray[np.int64] | None = None,
    ref_valid: NDArray | None = None,
    fallback: GriddedReference | list[GriddedReference] | None = None,
    ref_other_sensor: bool = True,
) -> ControlPoints:
    """Template grid control points (paper 4.3.2 steps 1, 3, 4; module doc for the steps).

    A grid of ``template_px`` templates every ``spacing_px`` (plus, with
    ``edge_template_px``, a ring of smaller ones along the frame's border) is cut from the
    frame; each is searched by normalised cross-correlation (``cv2.matchTemplate``,
    ``TM_CCOEFF_NORMED``) over offsets ``+-search_px // 2`` around the position
    ``ref_from_frame`` predicts; the integer peak is refined to sub-pixel (``subpixel``) and by
    the dithered re-correlation (``dither_iterations``). The template centre (or its structure
    centroid, ``anchor``) becomes ``src`` and the matched reference position ``dst``.

    With ``config.warp_reference`` the reference is first resampled into frame geometry once
    (:func:`prepare_search`); a peak at frame offset ``d`` means frame point ``s`` shows the
    reference content that the warp put at ``s + d``: ``ref_from_frame`` there as interpolated
    between the warp's lattice nodes (:func:`registration.geometry.warp.lattice_source`), which is
    ``dst``. Without it (the paper) the search runs directly in reference pixels around
    ``round(ref_from_frame(c))`` and ``dst`` is that position plus the peak offset.

    Templates are skipped when they or their search window are too flat
    (``min_template_std``), when the search window leaves the reference, when the model is
    undefined or not invertible there, when the peak is below ``min_score`` or on the border of
    the search range. Correlation runs in ``min(cv2.getNumThreads(), CPUs)`` threads (OpenCV
    releases the GIL); results do not depend on the thread count.

    Args:
        frame_grey: the frame, anything :func:`to_grey` accepts, ``(H, W)``.
        ref_grey: the reference (base map), likewise.
        ref_from_frame: current model, frame px -> reference px, ``(N, 2) -> (N, 2)``.
        frame_from_ref: its inverse, used only for the round-trip check; None skips the check.
        config: grid and search settings.
        centres: template centres to use instead of the grid (integer frame px, each template
            fully inside the frame); the edge ring is then not added.
        ref_valid: ``(Hr, Wr)`` bool, where the reference has content (e.g. the mid base
            image); a template whose search window touches anything else is not searched there.
        fallback: further references (image, ``ref_from_frame`` and optional ``valid``), or a
            list of them, each searched by the templates that the ones before cannot take
            (paper 4.4: the previous frame completes the mid base image; beyond the paper, the
            base map itself completes both at a flight's leading edge). Only with
            ``warp_reference``; each is warped only when some template needs it.
        ref_other_sensor: whether ``ref_grey`` was taken by another sensor or at another time
            than the frame (a base map): ``config.change_log_ratio`` applies to the windows
            searched in it (and in fallbacks marked ``other_sensor``) only.

    Returns:
        :class:`ControlPoints`: ``src`` frame px (template centres or their structure centroids,
        ``config.anchor``), ``dst`` reference px (``source`` = 0 for ``ref_grey``, ``i + 1``
        for the ``i``-th fallback, in that reference's pixels),
        ``score`` = NCC peak value; empty when nothing matched.
    """
    fallbacks = _fallback_list(fallback, config)
    frame = _signal(frame_grey, config)
    ref = _signal(ref_grey, config)
    fw, fh = coords.image_size(frame)
    sets = _template_sets(fw, fh, config, centres)
    # The grid and the ring search the same warped references: prepare each at most once.
    searches = _Searches(ref, ref_from_frame, ref_valid, fallbacks, (fw, fh), config)
    other_sensor = np.array([ref_other_sensor] + [fb.other_sensor for fb in fallbacks])
    # fmt: off
    return ControlPoints.concatenate([
        _match_set(frame, c, cfg, ref, ref_from_frame, frame_from_ref, ref_valid, fallbacks,
                   searches, other_sensor)
        for c, cfg in sets
    ])
    # fmt: on


def _fallback_list(
    fallback: GriddedReference | list[GriddedReference] | None, config: TemplateConfig
) -> list[GriddedReference]:
    """``fallback`` as a list (empty for None); ValueError when there is one without
    ``warp_reference``."""
    fallbacks = (
        [] if fallback is None else [fallback] if not isinstance(fallback, list) else fallback
    )
    if fallbacks and not config.warp_reference:
        raise ValueError("template_control_points: a fallback reference needs warp_reference=True")
    return fallbacks


def _template_sets(
    fw: int, fh: int, config: TemplateConfig, centres: NDArray[np.int64] | None
) -> list[tuple[NDArray[np.int64], TemplateConfig]]:
    """``[(centres, config), ...]``: the template sets of one size each searched for a
    ``fw`` x ``fh`` frame: the grid (or the given ``centres``) and, with ``edge_template_px``
    and no given centres, the ring of smaller templates along the border (no change test:
    too small for it, :class:`TemplateConfig`)."""
    sets = [(template_grid(fw, fh, config) if centres is None else centres, config)]
    if centres is None and config.edge_template_px > 0:
        ring = edge_ring(fw, fh, config.edge_template_px, grid_spacing(fw, fh, config))
        sets.append(
            (
                ring,
                replace(
                    config,
                    template_px=config.edge_template_px,
                    edge_template_px=0,
                    change_log_ratio=0.0,  # too small for it (TemplateConfig)
                ),
            )
        )
    return sets


class _Searches:
    """The warped reference, prepared on first use and shared by template sets (their padding
    is the search radius, the same for every set), and the fallbacks, warped over the windows
    each set needs."""

    def __init__(self, ref, ref_from_frame, ref_valid, fallbacks, frame_size, config):
        self._args = (ref, ref_from_frame, ref_valid, frame_size, config)
        self.fallbacks = fallbacks
        self._ref: SearchImage | None = None
        self._fallback_images: dict[int, NDArray] = {}

    def ref(self) -> SearchImage:
        if self._ref is None:
            ref, fn, valid, size, cfg = self._args
            self._ref = prepare_search(ref, fn, size, cfg.search_radius, cfg, valid)
        return self._ref

    def windowed(self, n_windows: int, win: int) -> bool:
        """Whether warping the reference over ``n_windows`` search windows of side ``2 win + 1``
        costs less than over the whole canvas: they cover under half of it (an intra-sensor
        frame's sparse grid; not the reference frame's dense one, whose windows overlap)."""
        if self._ref is not None:
            return False
        _, _, _, (fw, fh), cfg = self._args
        pad = cfg.search_radius
        return n_windows * (2 * win + 1) ** 2 < 0.5 * (fw + 2 * pad) * (fh + 2 * pad)

    def ref_windows(self, win_centres: NDArray[np.int64], win: int):
        """The reference warped over the search windows only (:meth:`_warp_windows`)."""
        ref, fn, valid, _, _ = self._args
        return self._warp_windows(ref, fn, valid, win_centres, win)

    def fallback_windows(
        self, i: int, win_centres: NDArray[np.int64], win: int
    ) -> tuple[list[NDArray[np.uint8]], NDArray[np.bool_]]:
        """The ``i``-th fallback warped over the search windows only (:meth:`_warp_windows`). A
        fallback completes the reference at a few windows, usually along one or two edges of
        the frame, so the model (a numerical inverse for the previous frame) is evaluated and
        the image resampled only there."""
        cfg = self._args[4]
        fb = self.fallbacks[i]
        image = self._fallback_images.get(i)
        if image is None:
            image = self._fallback_images[i] = _signal(fb.image, cfg)
        return self._warp_windows(image, fb.ref_from_frame, fb.valid, win_centres, win)

    def _warp_windows(
        self, image, ref_from_frame, valid, win_centres: NDArray[np.int64], win: int
    ) -> tuple[list[NDArray[np.uint8]], NDArray[np.bool_]]:
        """``image`` warped into frame geometry over the search windows of side ``2 win + 1``
        around ``win_centres`` (padded-canvas px) only, pixel for pixel as
        :func:`prepare_search` would warp it over the whole canvas: ``(windows, unusable)``,
        ``unusable`` where a window touches pixels without content."""
        _, _, _, (fw, fh), cfg = self._args
        pad = cfg.search_radius
        boxes = np.c_[win_centres - win, win_centres + win + 1]
        maps = warp.source_maps_in_boxes(
            ref_from_frame, fw + 2 * pad, fh + 2 * pad, boxes, step=cfg.map_step_px,
            origin=(-pad, -pad),
        )  # fmt: skip
        # All windows (one size) stacked into one map: one remap instead of one per window.
        side = 2 * win + 1
        stacked = np.stack(maps).reshape(len(maps) * side, side, 2)
        windows = warp.remap(image, stacked, interpolation="linear").reshape(-1, side, side)
        unusable = _invalid(stacked, image.shape, valid).reshape(-1, side * side).any(axis=1)
        return list(windows), unusable


def _usable_centres(centres, ref_from_frame, frame_from_ref, config):
    """Step 1: the centres whose predicted reference position is defined (and, with the
    inverse, comes back within ``max_roundtrip_px``), with those positions."""
    pred = call_points(ref_from_frame, centres.astype(np.float64), "ref_from_frame")
    keep = np.isfinite(pred).all(axis=1)
    if frame_from_ref is not None and keep.any():
        back = call_points(frame_from_ref, pred[keep], "frame_from_ref")
        err = np.hypot(*(back - centres[keep]).T)
        keep[np.flatnonzero(keep)[~(err <= config.max_roundtrip_px)]] = False
    return centres[keep], pred[keep]


def _assign_windows(centres, pred, ref, ref_valid, fallbacks, searches, config):
    """Step 2: for each template, the window of the image it is searched in: ``(windows,
    which, window_centres)``, ``windows[k]`` an array (or None: not searched), ``which[k]`` -1
    (not searched), 0 (the reference) or ``i + 1`` (the ``i``-th fallback), and the windows'
    centres in the reference's pixels (the paper's direct search) or the padded canvas's."""
    half, rad = config.half_template, config.search_radius
    win = half + rad  # half-size of the searched window
    which = np.full(len(centres), -1, np.int64)
    if config.warp_reference:
        win_centres = centres + rad
        if searches.windowed(len(win_centres), win):
            found, unusable = searches.ref_windows(win_centres, win)
            which[~unusable] = 0
            windows = [w if not bad else None for w, bad in zip(found, unusable, strict=True)]
        else:
            ref_search = searches.ref()
            which[~_box_any(ref_search.invalid, win_centres, win)] = 0
            windows = [
                _window(ref_search.image, c, win) if w == 0 else None
                for c, w in zip(win_centres, which, strict=True)
            ]
        for i in range(len(fallbacks)):
            todo = np.flatnonzero(which < 0)
            if len(todo) == 0:
                break
            found, unusable = searches.fallback_windows(i, win_centres[todo], win)
            for k, window, bad in zip(todo, found, unusable, strict=True):
                if not bad:
                    which[k], windows[k] = i + 1, window
        return windows, which, win_centres
    rw, rh = coords.image_size(ref)
    win_centres = np.round(pred).astype(np.int64)
    ok = (
        (win_centres[:, 0] - win >= 0)
        & (win_centres[:, 0] + win <= rw - 1)
        & (win_centres[:, 1] - win >= 0)
        & (win_centres[:, 1] + win <= rh - 1)
    )
    if ref_valid is not None and ok.any():
        ok[ok] = ~_box_any(~np.asarray(ref_valid, bool), win_centres[ok], win)
    which[ok] = 0
    windows = [
        _window(ref, c, win) if w == 0 else None for c, w in zip(win_centres, which, strict=True)
    ]
    return windows, which, win_centres


def _window(image: NDArray, centre: NDArray, win: int) -> NDArray:
    """The ``2 win + 1`` square of ``image`` around ``centre`` (a view)."""
    x, y = centre
    return image[y - win : y + win + 1, x - win : x + win + 1]


def _match_set(frame, centres, config, ref, ref_from_frame, frame_from_ref, ref_valid, fallbacks,
               searches, other_sensor) -> ControlPoints:  # fmt: skip
    """Steps 1-4 for one set of template centres of one size; ``other_sensor[i]``: whether the
    change test applies to windows of source ``i`` (0 the reference, ``i`` the fallbacks)."""
    if len(centres) == 0:
        return ControlPoints.empty()
    centres, pred = _usable_centres(centres, ref_from_frame, frame_from_ref, config)
    if len(centres) == 0:
        return ControlPoints.empty()
    windows, which, win_centres = _assign_windows(
        centres, pred, ref, ref_valid, fallbacks, searches, config
    )
    idx = np.flatnonzero(which >= 0)
    if len(idx) == 0:
        return ControlPoints.empty()
    scores, offsets, anchors = _correlate(
        frame, centres[idx], [windows[k] for k in idx], config, other_sensor[which[idx]]
    )
    good = np.isfinite(scores) & (scores >= config.min_score)
    if not good.any():
        return ControlPoints.empty()
    idx, scores, offset, anchor = idx[good], scores[good], offsets[good], anchors[good]
    src = centres[idx].astype(np.float64) + anchor
    source = which[idx]
    if config.warp_reference:
        # Where the warped reference showed the match: its map between lattice nodes, not the
        # model itself (they part by tenths of a px in a strongly corrected frame's corners).
        dst = np.full_like(src, np.nan)
        lattice = {"step": config.map_step_px, "origin": (-config.search_radius,) * 2}
        for k, fn in enumerate([ref_from_frame] + [fb.ref_from_frame for fb in fallbacks]):
            sel = source == k
            if sel.any():
                dst[sel] = warp.lattice_source(
                    lambda q, fn=fn: call_points(fn, q, "ref_from_frame"),
                    src[sel] + offset[sel], **lattice,
                )  # fmt: skip
    else:
        dst = win_centres[idx] + offset
    fin = np.isfinite(dst).all(axis=1)
    logger.debug("template control points: %d of %d matched", int(fin.sum()), len(centres))
    return ControlPoints(src[fin], dst[fin], scores[fin], source[fin])


def _correlate(frame, centres, windows, config, mask_changes):
    """Step 3: NCC of each template over its window (``windows[k]``, the searched part of the
    reference around template ``k``), then step 4 (with the change test where
    ``mask_changes[k]``); ``(scores, offsets, anchors)``, NaN scores where a template or window
    is too flat or the peak unusable."""
    half = config.half_template
    n = len(centres)
    scores = np.full(n, np.nan)
    offsets = np.full((n, 2), np.nan)
    anchors = np.zeros((n, 2))
    use_structure = config.warp_reference and config.anchor == "structure"
    ramp = np.arange(-half, half + 1, dtype=np.float32)
    min_std = config.min_template_std

    def run(chunk: NDArray[np.int64]) -> None:
        # Fills rows ``chunk``; chunks are disjoint, so threads do not collide, and cv2
        # releases the GIL inside matchTemplate.
        for k in chunk:
            cx, cy = centres[k]
            tpl = frame[cy - half : cy + half + 1, cx - half : cx + half + 1]
            window = windows[k]
            # Texture check on both sides: a flat template or window has no reliable peak.
            if cv2.meanStdDev(tpl)[1][0, 0] < min_std or cv2.meanStdDev(window)[1][0, 0] < min_std:
                continue
            peak = _refine_peak(tpl, window, config, bool(mask_changes[k]))
            if peak is None:
                continue
            scores[k], offsets[k] = peak
            if use_structure:
                anchors[k] = _structure_centroid(tpl, ramp)

    n_threads = max(1, min(_n_threads(), n // 64))
    chunks = np.array_split(np.arange(n), n_threads)
    if n_threads == 1:
        run(chunks[0])
    else:
        with ThreadPoolExecutor(n_threads) as pool:
            list(pool.map(run, chunks))
    return scores, offsets, anchors


def _box_any(mask: NDArray[np.bool_], centres: NDArray[np.int64], half: int) -> NDArray[np.bool_]:
    """Whether any ``mask`` pixel lies in the boxes around ``centres`` (inside the image)."""
    s = cv2.integral(mask.astype(np.uint8), sdepth=cv2.CV_32S)
    x0, y0 = centres[:, 0] - half, centres[:, 1] - half
    x1, y1 = centres[:, 0] + half + 1, centres[:, 1] + half + 1
    return (s[y1, x1] - s[y0, x1] - s[y1, x0] + s[y0, x0]) > 0


def _n_threads() -> int:
    """Worker threads for per-template correlation: OpenCV's thread setting, at most the CPUs."""
    return max(1, min(cv2.getNumThreads(), os.cpu_count() or 1))

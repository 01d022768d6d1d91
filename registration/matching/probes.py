"""Probes: small patches of one image found in another near where a registration predicts them
(beyond the paper). A probe counts only where its patch pins both directions (the smaller
eigenvalue of its structure tensor) and its correlation peak is clear, single and not on the
search border, so that edges and blank roofs do not slide.

Used to link consecutive frames of a sequence (:mod:`registration.adjustment`) and to measure a
registration's frame-to-frame consistency from the images alone
(:mod:`registration.evaluation.consistency`). Points are ``(N, 2)`` float64 ``(x, y)`` px with
pixel centres at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.matching.ncc_peaks import subpixel_peak


@dataclass(frozen=True)
class ProbeConfig:
    """Where probes are cut and when a measurement counts. Lengths in px of the images.

    Attributes:
        grid_px: spacing of the probes.
        template_px: side of the patch cut around each probe (odd).
        search_px: the patch is searched this far around the prediction in each direction; a
            prediction further off than this is not measured.
        margin_px: probes closer than this to the image border are left out.
        min_ncc: the correlation peak must reach this for a measurement to count.
        min_structure: the smaller eigenvalue of the patch's structure tensor (mean of the
            squared Scharr gradients / 16, grey levels² per px²) must reach this: along an edge
            the peak slides.
        peak_margin: a second peak more than 2 px from the first must be lower by this.
        exclude: boxes ``(x0, y0, x1, y1)`` whose probes are left out (a burnt-in logo).
    """

    grid_px: int = 24
    template_px: int = 31
    search_px: int = 8
    margin_px: int = 20
    min_ncc: float = 0.8
    min_structure: float = 40.0
    peak_margin: float = 0.05
    exclude: tuple[tuple[float, float, float, float], ...] = ()

    def __post_init__(self) -> None:
        if self.template_px < 5 or self.template_px % 2 == 0:
            raise ValueError(f"template_px must be odd and at least 5, got {self.template_px}")
        for name in ("grid_px", "search_px", "margin_px"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")


def probe_grid(size: tuple[int, int], config: ProbeConfig) -> NDArray[np.float64]:
    """``(N, 2)`` px on a ``grid_px`` lattice inside the margin, outside ``exclude``."""
    w, h = size
    g, m = config.grid_px, max(config.margin_px, config.template_px // 2 + 1)
    xs = np.arange(m, w - m, g, dtype=np.float64)
    ys = np.arange(m, h - m, g, dtype=np.float64)
    p = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    keep = np.ones(len(p), bool)
    for x0, y0, x1, y1 in config.exclude:
        keep &= ~((p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1))
    return p[keep]


# Patches covering less than this share of the image are filtered one by one, else the image.
PATCHWISE_BELOW = 0.5


def structure_strength(grey: NDArray, points: NDArray, half: int) -> NDArray[np.float64]:
    """The smaller eigenvalue of the structure tensor of the ``(2 half + 1)²`` patch around each
    of ``points`` (integer px), grey levels² per px²: how well a patch pins both directions.

    Scharr gradients (``/ 16``) averaged over each patch: on the patches alone where they cover
    little of the image (a 2560x1920 frame's 713 probes of 31 px, a sixth of it: 0.019 s of CPU
    against 0.087 s for the whole image's filters), else on the whole image (a 852x480 frame's
    overlapping probes: patch by patch was 1.6x slower). The two agree to 1.4e-6 relative and
    kept the same probes at the 40.0 threshold on 420,634 probes of 662 real and simulated
    frames."""
    h, w = grey.shape[:2]
    if len(points) * (2 * half + 3) ** 2 >= PATCHWISE_BELOW * h * w:
        return _image_strength(grey, points, half)
    return _patch_strength(grey, points, half)


# Rows of probes per band of :func:`_image_strength`.
BAND_ROWS = 128


def _image_strength(grey: NDArray, points: NDArray, half: int) -> NDArray[np.float64]:
    """:func:`structure_strength` from whole-image filters, band by band of ``BAND_ROWS`` rows
    (each with the ``half + 2`` rows beyond it that its patches and gradients read): the same
    values to the bit as the whole image at once (OpenCV's box filter sums float images in
    double; tested), at half the CPU (a 1280x960 frame's 2028 probes: 16.3 -> 7.8 ms), as the
    band's arrays are small enough to be reused where the whole image's were faulted in afresh
    by every call."""
    h = grey.shape[0]
    k = 2 * half + 1
    margin = half + 2
    xi, yi = points[:, 0].astype(int), points[:, 1].astype(int)
    out = np.full(len(points), np.nan)  # NaN (never textured) for a point off the image
    for b0 in range(0, h, BAND_ROWS):
        sel = np.flatnonzero((yi >= b0) & (yi < b0 + BAND_ROWS))
        if not len(sel):
            continue
        r0 = max(0, b0 - margin)
        g = grey[r0 : min(h, b0 + BAND_ROWS + margin)].astype(np.float32)
        gx = cv2.Scharr(g, cv2.CV_32F, 1, 0, scale=1.0 / 16.0)
        gy = cv2.Scharr(g, cv2.CV_32F, 0, 1, scale=1.0 / 16.0)
        sxx = cv2.boxFilter(gx * gx, -1, (k, k))
        syy = cv2.boxFilter(gy * gy, -1, (k, k))
        sxy = cv2.boxFilter(gx * gy, -1, (k, k))
        rows, cols = yi[sel] - r0, xi[sel]
        a, c, b = sxx[rows, cols], syy[rows, cols], sxy[rows, cols]
        out[sel] = 0.5 * (a + c - np.sqrt((a - c) ** 2 + 4 * b * b))
    return out


def _patch_strength(grey: NDArray, points: NDArray, half: int) -> NDArray[np.float64]:
    """:func:`structure_strength` on the patches alone; pixels beyond the image's edge repeat its
    border (the probes keep their patch inside the image)."""
    h, w = grey.shape[:2]
    span = np.arange(-half - 1, half + 2)
    xi, yi = points[:, 0].astype(int), points[:, 1].astype(int)
    rows = np.clip(yi[:, None] + span, 0, h - 1)[:, :, None]
    cols = np.clip(xi[:, None] + span, 0, w - 1)[:, None, :]
    g = grey[rows, cols].astype(np.float32)  # (N, 2 half + 3, 2 half + 3)
    dx = g[:, :, 2:] - g[:, :, :-2]
    dy = g[:, 2:, :] - g[:, :-2, :]
    gx = (3 * dx[:, :-2] + 10 * dx[:, 1:-1] + 3 * dx[:, 2:]) / np.float32(16)
    gy = (3 * dy[:, :, :-2] + 10 * dy[:, :, 1:-1] + 3 * dy[:, :, 2:]) / np.float32(16)
    a = (gx * gx).mean(axis=(1, 2), dtype=np.float64)
    c = (gy * gy).mean(axis=(1, 2), dtype=np.float64)
    b = (gx * gy).mean(axis=(1, 2), dtype=np.float64)
    return 0.5 * (a + c - np.sqrt((a - c) ** 2 + 4 * b * b))


def textured_probes(grey: NDArray, config: ProbeConfig) -> NDArray[np.float64]:
    """The probes of :func:`probe_grid` whose patch in ``grey`` pins both directions."""
    h, w = grey.shape
    p = probe_grid((w, h), config)
    if not len(p):
        return p
    return p[structure_strength(grey, p, config.template_px // 2) >= config.min_structure]


def find_probes(
    grey_a: NDArray, grey_b: NDArray, p: NDArray, q: NDArray, config: ProbeConfig
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Where each patch of ``grey_a`` around ``p`` (integer px) lies in ``grey_b``, searched
    around the predictions ``q`` (both ``(N, 2)``): ``(N, 2)`` px (NaN where not measured) and
    the ``(N,)`` mask of the measured ones."""
    half, r = config.template_px // 2, config.search_px
    hb, wb = grey_b.shape
    out = np.full((len(p), 2), np.nan)
    ok = np.zeros(len(p), bool)
    peaks = np.zeros((len(p), 3, 3))
    for i, ((px, py), (qx, qy)) in enumerate(zip(p.astype(int), q, strict=True)):
        cx, cy = int(round(qx)), int(round(qy))
        x0, y0 = cx - half - r, cy - half - r
        x1, y1 = cx + half + r + 1, cy + half + r + 1
        if x0 < 0 or y0 < 0 or x1 > wb or y1 > hb:
            continue
        tmpl = grey_a[py - half : py + half + 1, px - half : px + half + 1]
        ncc = cv2.matchTemplate(grey_b[y0:y1, x0:x1], tmpl, cv2.TM_CCOEFF_NORMED)
        _, best, _, (bx, by) = cv2.minMaxLoc(ncc)
        if not best >= config.min_ncc or bx in (0, 2 * r) or by in (0, 2 * r):
            continue  # weak, or on the search border (the true peak may lie outside)
        rival = ncc.copy()
        rival[max(0, by - 2) : by + 3, max(0, bx - 2) : bx + 3] = -1.0
        if rival.max() > best - config.peak_margin:
            continue  # two places look alike: the measurement is not unique
        peaks[i] = ncc[by - 1 : by + 2, bx - 1 : bx + 2]
        out[i] = (x0 + half + bx, y0 + half + by)
        ok[i] = True
    if ok.any():  # sub-pixel refinement of every peak at once
        out[ok] += subpixel_peak(peaks[ok])
    return out, ok

"""Local displacement-field refinement (paper section 5).

After the global (polyprojective) registration a frame still differs from the mid base image by a
few pixels that vary over the image (rolling shutter, non-planar city, residual optics). The paper
removes them with a field of displacement vectors: the registered frame and the mid base image are
cut into 200x200 neighbourhoods with centres 200 px apart, SIFT keypoints are matched inside each
neighbourhood, REQCON turns the matches into one consensus vector per neighbourhood, and the grid
of vectors is interpolated to every pixel (no smoothing).

Layout and direction (fixed by the project brief):

* :class:`DisplacementField` holds a regular grid: node ``(i, j)`` (row ``i``, column ``j``) sits at
  base pixel ``origin + (j, i) * spacing``; ``vectors`` is ``(Gy, Gx, 2)`` float32 ``(dx, dy)`` in
  base px; ``valid`` is ``(Gy, Gx)`` bool and marks the nodes whose vector was *measured*; vectors
  of the other nodes are filled from their neighbours, so ``vectors`` is always complete.
* ``registered_local(x) = registered_global(x + d(x))``: ``d(x)`` says where, in the globally
  registered frame (base coordinates), the content that belongs at base pixel ``x`` actually is.
  Hence ``base_to_frame_local(x) = base_to_frame_global(x + d(x))`` and ``frame_to_base_local(q)``
  solves ``x + d(x) = frame_to_base_global(q)`` (:func:`local_frame_to_base`).

Moving cars (the paper's warning, section 5): a neighbourhood's vector must come from the ground.
Three defences, each documented in :class:`LocalConfig`: neighbourhoods much larger than a road,
matches gated to a small displacement (the global residual is a few px, a car between two frames
moves more), and a guard that rejects a cell (i) whose rejected matches contain a second coherent
motion of similar support (two motions, we cannot tell which is the ground) or (ii) whose vector
disagrees with the median of its neighbours by more than a tolerance (a cell dominated by a
column of cars that all move alike). Rejected cells are filled from their neighbours.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration import features, warp
from registration.camera import Camera
from registration.coords import as_points, bbox_of, frame_outline, rescale

log = logging.getLogger(__name__)

# Per-cell status codes (FieldStats.cell_status); index = code.
STATUS = (
    "ok",  # measured consensus vector
    "outside",  # too little of the neighbourhood lies where both images have data
    "few_matches",  # fewer than min_matches gated matches
    "no_consensus",  # REQCON ran out of matches before reaching its target error
    "rival_motion",  # a second coherent motion of similar support (moving-car guard)
    "neighbour_outlier",  # disagrees with the neighbours' median (moving-car guard)
)
OK, OUTSIDE, FEW_MATCHES, NO_CONSENSUS, RIVAL_MOTION, NEIGHBOUR_OUTLIER = range(len(STATUS))


@dataclass(frozen=True)
class LocalConfig:
    """Settings of the displacement-field stage (paper section 5). All lengths in base pixels.

    Attributes:
        method: how displacement samples inside a neighbourhood are found. "sift" (paper 5:
            SIFT keypoints in both images, matched within the displacement gate, each match
            voting in the neighbourhood of its reference keypoint) or "flow" (ours: dense DIS
            optical flow sampled every ``flow_step_px``; the REQCON consensus and the moving-car
            guard are the same). Measured on a 2560x1920 aerial image with a known residual
            field of 2.7 px mean (2 busy cores): SIFT 5.2 s, 0.092 px left; flow "medium" 0.7 s,
            0.053 px; flow "fast" 0.25 s, 0.13 px. Full-resolution SIFT dominates the stage.
        cell_px: side of the square neighbourhood whose keypoints vote for one vector; paper 5:
            200 ("significantly larger than the road widths").
        spacing_px: distance between neighbourhood centres; paper 5: 200.
        min_valid_fraction: a neighbourhood is skipped ("outside") when less than this share of
            it lies where both images have data. Larger = fewer, better-supported cells.
        sift_contrast_threshold: SIFT contrast threshold (OpenCV default 0.04, Lowe's 0.03 on a
            [0,1] scale after division by the octave layers); lower = more keypoints.
        sift_edge_threshold: SIFT edge threshold (OpenCV default 10).
        sift_n_octave_layers: SIFT layers per octave (OpenCV and Lowe: 3).
        sift_sigma: SIFT base blur (OpenCV and Lowe: 1.6).
        mask_erode_px: the data mask is eroded by this much before detection so that the edge of
            a frame's footprint (a strong artificial edge) yields no keypoints.
        ratio: Lowe's ratio test (Lowe 2004: 0.8), applied among the candidates that pass the
            displacement gate. Lower = stricter.
        max_displacement_px: matches whose displacement exceeds this are discarded before the
            consensus. The global stage leaves a few px (paper Table 2 post-global: mu 2.6,
            sigma 1.7, so mu + 3 sigma ~ 8 px); a car between two frames usually moves more.
        min_matches: a cell needs at least this many gated matches, and REQCON must keep at least
            this many, for its vector to count.
        reqcon_drop_fraction: REQCON drops this share of the worst matches per iteration (paper
            4.3.2: 5 %).
        reqcon_target_px: REQCON stops when the mean residual of the kept matches is below this.
            The paper's 2 px is for a 17-parameter polyprojective over a whole frame; a single
            translation over 200 px, with SIFT positions good to a few tenths of a pixel, reaches
            1 px easily, and a tighter target leaves fewer car matches in.
        reqcon_max_residual_px: REQCON also continues while any kept match is further than this
            from the fit (our addition; None = the paper's mean-only rule). A mean below 1 px still
            lets ~10 % of matches sit 8 px away (a column of cars), dragging the vector by ~0.8 px;
            no ground match within one 200 px cell disagrees with the cell's consensus by 3 px.
        cell_model: "translation" (the paper: the vector is the REQCON mean of the kept matches)
            or "affine" (REQCON on a displacement that varies linearly over the cell, the vector
            is its value at the cell centre; removes the bias when the keypoints are not centred
            in a cell where the field has a gradient, e.g. a cell cut by the footprint's edge).
            The affine fit falls back to translation with fewer than 6 kept matches or when
            they spread (standard deviation along either principal axis) less than an eighth
            of the cell.
        rival_radius_px: matches closer than this (in displacement) form one coherent motion.
        rival_ratio: the cell is rejected ("rival_motion") when the largest coherent group among
            the matches REQCON rejected has at least this share of the kept set and lies more than
            2 * rival_radius_px from the consensus. 0 disables the check.
        neighbour_tolerance_px: a measured vector further than this from the median of its
            measured 8-neighbours (at least ``neighbour_min_count`` of them) is rejected
            ("neighbour_outlier"). The residual field varies slowly (paper Fig. 5: a few px over
            the whole frame), so neighbours 200 px apart agree to ~1 px. None disables it.
        neighbour_min_count: how many measured neighbours the neighbour check needs.
        flow_preset: DIS optical-flow preset for ``method="flow"``: "ultrafast", "fast" or
            "medium" (OpenCV's; slower = more accurate).
        flow_step_px: flow samples are taken every this many px (8 -> 625 votes per cell).
        flow_margin_px: samples closer than this to missing data are skipped (flow is
            unreliable at the footprint's edge).
        flow_scale: image scale the flow is computed at by :func:`estimate_field_in_frame`
            (both images resampled with area averaging; displacements are mapped back to full
            base px exactly through the global mapping). 0.5 costs ~1/4 of full scale.
        flow_min_width_px: the flow image is never made narrower than this (the scale is raised
            to ``min(1, flow_min_width_px / W)``): on small frames the detail lost by
            downscaling costs accuracy (640x480 frames at 0.5: 0.28-0.31 px motion after local,
            at full scale 0.13-0.22). 0 = no limit.
        fit: how the samples become node vectors. "cells" (the paper: one REQCON consensus per
            ``cell_px`` neighbourhood, the moving-car guard, rejected cells filled from their
            neighbours) or "spline" (ours: every node at once by robust, regularised least
            squares over all samples, :func:`estimate_field_spline`: bilinear interpolation of
            the nodes must reproduce each sample, second differences of the nodes are
            penalised, Tukey weights from the samples' median absolute deviation remove the
            mismatches). The spline follows a field that bends within a cell (a lens beyond
            Harris in the corners, a rolling shutter) and extrapolates its slope to the nodes
            beyond the samples, where a cell's consensus is constant.
        spline_smoothness: weight of the second-difference penalty of ``fit="spline"`` relative
            to the data (per sample and node: the penalty is multiplied by samples / nodes, so
            the balance does not depend on the frame size). Larger = smoother.
    """

    method: str = "sift"
    cell_px: int = 200
    spacing_px: int = 200
    min_valid_fraction: float = 0.25
    sift_contrast_threshold: float = 0.04
    sift_edge_threshold: float = 10.0
    sift_n_octave_layers: int = 3
    sift_sigma: float = 1.6
    mask_erode_px: int = 6
    ratio: float = 0.8
    max_displacement_px: float = 12.0
    min_matches: int = 8
    reqcon_drop_fraction: float = 0.05
    reqcon_target_px: float = 1.0
    reqcon_max_residual_px: float | None = 3.0
    cell_model: str = "translation"
    rival_radius_px: float = 1.5
    rival_ratio: float = 0.5
    neighbour_tolerance_px: float | None = 3.0
    neighbour_min_count: int = 3
    flow_preset: str = "medium"
    flow_step_px: int = 8
    flow_margin_px: int = 8
    flow_scale: float = 1.0
    flow_min_width_px: int = 0
    fit: str = "cells"
    spline_smoothness: float = 0.1

    def __post_init__(self) -> None:
        if self.cell_px <= 0 or self.spacing_px <= 0:
            raise ValueError(
                f"cell_px and spacing_px must be positive, got {self.cell_px}, {self.spacing_px}"
            )
        if not 0 < self.ratio <= 1:
            raise ValueError(f"ratio must be in (0, 1], got {self.ratio}")
        if not 0 < self.reqcon_drop_fraction < 1:
            raise ValueError(
                f"reqcon_drop_fraction must be in (0, 1), got {self.reqcon_drop_fraction}"
            )
        if self.cell_model not in ("translation", "affine"):
            raise ValueError(
                f"cell_model must be 'translation' or 'affine', got {self.cell_model!r}"
            )
        if self.method not in ("sift", "flow"):
            raise ValueError(f"method must be 'sift' or 'flow', got {self.method!r}")
        if self.flow_preset not in ("ultrafast", "fast", "medium"):
            raise ValueError(
                f"flow_preset must be ultrafast, fast or medium, got {self.flow_preset!r}"
            )
        if not 0 < self.flow_scale <= 1:
            raise ValueError(f"flow_scale must be in (0, 1], got {self.flow_scale}")
        if self.flow_step_px < 1:
            raise ValueError(f"flow_step_px must be >= 1, got {self.flow_step_px}")
        if self.min_matches < 1:
            raise ValueError(f"min_matches must be >= 1, got {self.min_matches}")
        if self.fit not in ("cells", "spline"):
            raise ValueError(f"fit must be 'cells' or 'spline', got {self.fit!r}")
        if not self.spline_smoothness > 0:
            raise ValueError(f"spline_smoothness must be positive, got {self.spline_smoothness}")


# Settings for ``method="flow"`` (the project's default preset; the paper preset keeps SIFT).
# Flow samples are dense (625 a cell) and precise (DIS "medium": ~0.07 px median on aerial
# texture), so REQCON can trim to a much tighter fit than with SIFT matches; that also removes the
# flow's smear around moving cars (it is regularised, so a car's motion bleeds into the ground
# next to it at intermediate values no coherence test would catch). Centres 100 px apart with
# the paper's 200 px neighbourhoods (overlapping by half): the paper chose the spacing as a
# trade-off of "fine enough spacing to capture the spatial frequencies of the remaining
# distortion" against computation, and with flow the finer grid costs almost nothing; the
# neighbourhood stays "significantly larger than the road widths". On simulated 640x480
# sequences (frame vs reference, mean error after the local stage): SIFT/200 0.20 px,
# flow/200 0.14 px, flow/100 0.09 px. With 625 samples a cell, the affine cell model (vector at
# the node even when the samples sit to one side of it, as in cells cut by the footprint's edge)
# is well determined: on a known field it halves the node error (0.26 -> 0.10 px max).
FLOW_OVERRIDES: dict[str, Any] = {
    "method": "flow",
    "cell_model": "affine",
    "flow_preset": "medium",
    "spacing_px": 100,
    "reqcon_target_px": 0.3,
    "reqcon_max_residual_px": 1.0,
}


@dataclass(frozen=True)
class KeypointSet:
    """SIFT keypoints in base pixels: ``xy`` (N, 2) float64, ``descriptors`` (N, 128) float32.

    Anything with ``.xy`` and ``.descriptors`` (e.g. ``features.Keypoints``) is accepted where a
    KeypointSet is expected, so the reference's keypoints can be detected once per sequence.
    """

    xy: NDArray[np.float64]
    descriptors: NDArray[np.float32]

    def __len__(self) -> int:
        return int(self.xy.shape[0])


@dataclass(frozen=True)
class DisplacementField:
    """A grid of displacement vectors in base pixels (layout and direction: module docstring).

    Attributes:
        origin: ``(x0, y0)`` base px of grid node ``(0, 0)``.
        spacing: distance between nodes in base px (paper: 200).
        vectors: ``(Gy, Gx, 2)`` float32 ``(dx, dy)`` base px; complete (invalid nodes filled).
        valid: ``(Gy, Gx)`` bool, True where the vector was measured.

    The field covers the nodes' cells: ``[x0 - spacing/2, x0 + (Gx - 1/2) spacing]`` and likewise
    in y; outside it :meth:`sample` returns NaN. Inside, it is bilinear between nodes and constant
    beyond the outermost nodes.
    """

    origin: tuple[float, float]
    spacing: float
    vectors: NDArray[np.float32]
    valid: NDArray[np.bool_]

    def __post_init__(self) -> None:
        v = np.asarray(self.vectors)
        if v.ndim != 3 or v.shape[2] != 2 or v.shape[0] < 1 or v.shape[1] < 1:
            raise ValueError(f"vectors must have shape (Gy, Gx, 2), got {v.shape}")
        if np.asarray(self.valid).shape != v.shape[:2]:
            raise ValueError(
                f"valid must have shape {v.shape[:2]}, got {np.asarray(self.valid).shape}"
            )
        if not self.spacing > 0:
            raise ValueError(f"spacing must be positive, got {self.spacing}")

    @property
    def shape(self) -> tuple[int, int]:
        """``(Gy, Gx)``."""
        return int(self.vectors.shape[0]), int(self.vectors.shape[1])

    @property
    def node_xy(self) -> NDArray[np.float64]:
        """``(Gy, Gx, 2)`` base px of every node."""
        gy, gx = self.shape
        xs = self.origin[0] + self.spacing * np.arange(gx)
        ys = self.origin[1] + self.spacing * np.arange(gy)
        mx, my = np.meshgrid(xs, ys, indexing="xy")
        return np.stack([mx, my], axis=-1)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(x_min, y_min, x_max, y_max)`` base px covered by the field."""
        gy, gx = self.shape
        h = self.spacing / 2.0
        return (
            self.origin[0] - h,
            self.origin[1] - h,
            self.origin[0] + (gx - 1) * self.spacing + h,
            self.origin[1] + (gy - 1) * self.spacing + h,
        )

    def _weights(self, coord: NDArray, o: float, n: int):
        u = (coord - o) / self.spacing
        inside = (u >= -0.5) & (u <= n - 0.5)
        u = np.clip(np.where(np.isfinite(u), u, 0.0), 0.0, n - 1.0)
        i0 = np.minimum(np.floor(u).astype(np.intp), max(n - 2, 0))
        f = u - i0
        i1 = np.minimum(i0 + 1, n - 1)
        return i0, i1, f, inside

    def sample(self, xy: ArrayLike, *, outside: str = "nan") -> NDArray[np.float64]:
        """Displacement at base points: ``(N, 2)`` -> ``(N, 2)`` base px.

        Args:
            outside: what points outside the field get: "nan" or "clamp" (the value at the
                nearest point of the field, i.e. constant extrapolation like the filling of
                cells without a measurement).
        """
        if outside not in ("nan", "clamp"):
            raise ValueError(f"outside must be 'nan' or 'clamp', got {outside!r}")
        p = as_points(xy, "xy")
        gy, gx = self.shape
        v = self.vectors.astype(np.float64)
        with np.errstate(invalid="ignore"):
            j0, j1, fx, in_x = self._weights(p[:, 0], self.origin[0], gx)
            i0, i1, fy, in_y = self._weights(p[:, 1], self.origin[1], gy)
        fx, fy = fx[:, None], fy[:, None]
        out = (
            v[i0, j0] * (1 - fx) * (1 - fy)
            + v[i0, j1] * fx * (1 - fy)
            + v[i1, j0] * (1 - fx) * fy
            + v[i1, j1] * fx * fy
        )
        if outside == "nan":
            out[~(in_x & in_y)] = np.nan
        out[~np.isfinite(p).all(axis=1)] = np.nan
        return out

    def dense(
        self, width: int, height: int, origin: tuple[float, float] = (0.0, 0.0)
    ) -> NDArray[np.float32]:
        """The field at every pixel of a ``width`` x ``height`` crop of the base whose pixel
        ``(0, 0)`` is base ``origin``: ``(height, width, 2)`` float32, NaN outside the field.

        Same values as :meth:`sample` (bilinear, separable so it costs two passes).
        """
        gy, gx = self.shape
        xs = origin[0] + np.arange(width, dtype=np.float64)
        ys = origin[1] + np.arange(height, dtype=np.float64)
        j0, j1, fx, in_x = self._weights(xs, self.origin[0], gx)
        i0, i1, fy, in_y = self._weights(ys, self.origin[1], gy)
        v = self.vectors.astype(np.float32)
        fx32 = fx.astype(np.float32)[None, :, None]
        rows = v[:, j0] * (1 - fx32) + v[:, j1] * fx32  # (Gy, W, 2)
        fy32 = fy.astype(np.float32)[:, None, None]
        out = rows[i0] * (1 - fy32) + rows[i1] * fy32  # (H, W, 2)
        out[~in_y, :, :] = np.nan
        out[:, ~in_x, :] = np.nan
        return out

    def to_arrays(self) -> dict[str, NDArray]:
        """Plain arrays for ``np.savez`` (round trip: :meth:`from_arrays`)."""
        return {
            "origin": np.asarray(self.origin, np.float64),
            "spacing": np.asarray(self.spacing, np.float64),
            "vectors": np.asarray(self.vectors, np.float32),
            "valid": np.asarray(self.valid, bool),
        }

    def to_dict(self) -> dict[str, NDArray]:
        """Alias of :meth:`to_arrays`."""
        return self.to_arrays()

    @classmethod
    def from_arrays(cls, arrays: Any, prefix: str = "") -> DisplacementField:
        """Rebuild from :meth:`to_arrays` output (a dict or an ``np.load`` NpzFile); keys may carry
        ``prefix`` (e.g. ``"field_"``)."""
        origin = np.asarray(arrays[prefix + "origin"], np.float64)
        return cls(
            origin=(float(origin[0]), float(origin[1])),
            spacing=float(np.asarray(arrays[prefix + "spacing"])),
            vectors=np.asarray(arrays[prefix + "vectors"], np.float32),
            valid=np.asarray(arrays[prefix + "valid"], bool),
        )

    @classmethod
    def zeros(
        cls, width: int, height: int, spacing: float, origin: tuple[float, float] = (0.0, 0.0)
    ):
        """An all-zero, all-invalid field on the grid :func:`grid_nodes` lays over the crop."""
        (ox, oy), (gx, gy) = grid_nodes(width, height, spacing, origin)
        return cls(
            (ox, oy), float(spacing), np.zeros((gy, gx, 2), np.float32), np.zeros((gy, gx), bool)
        )


@dataclass
class FieldStats:
    """What :func:`estimate_field` measured (per-cell arrays are ``(Gy, Gx)``).

    Attributes:
        cell_status: int8 code per cell, names in :data:`STATUS`.
        cell_matches: gated matches per cell.
        cell_kept: matches REQCON kept per cell.
        cell_residual_px: mean residual of the kept matches (NaN where no consensus).
        n_keypoints_registered, n_keypoints_reference: SIFT keypoints found in each image's crop.
        time_detect_s, time_match_s, time_total_s: wall time by step.
    """

    cell_status: NDArray[np.int8]
    cell_matches: NDArray[np.int32]
    cell_kept: NDArray[np.int32]
    cell_residual_px: NDArray[np.float32]
    n_keypoints_registered: int = 0
    n_keypoints_reference: int = 0
    time_detect_s: float = 0.0
    time_match_s: float = 0.0
    time_total_s: float = 0.0

    @property
    def n_cells(self) -> int:
        return int(self.cell_status.size)

    @property
    def n_valid(self) -> int:
        return int(np.count_nonzero(self.cell_status == OK))

    def counts(self) -> dict[str, int]:
        """Number of cells per status name."""
        return {name: int(np.count_nonzero(self.cell_status == i)) for i, name in enumerate(STATUS)}

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly summary (no per-cell arrays)."""
        ok = self.cell_status == OK
        return {
            "n_cells": self.n_cells,
            "n_valid": self.n_valid,
            "cells": self.counts(),
            "n_keypoints_registered": self.n_keypoints_registered,
            "n_keypoints_reference": self.n_keypoints_reference,
            "matches_per_valid_cell": float(np.median(self.cell_matches[ok])) if ok.any() else 0.0,
            "kept_per_valid_cell": float(np.median(self.cell_kept[ok])) if ok.any() else 0.0,
            "residual_px": float(np.nanmean(self.cell_residual_px[ok])) if ok.any() else None,
            "time_detect_s": self.time_detect_s,
            "time_match_s": self.time_match_s,
            "time_total_s": self.time_total_s,
        }

    def to_arrays(self) -> dict[str, NDArray]:
        return {
            "cell_status": self.cell_status,
            "cell_matches": self.cell_matches,
            "cell_kept": self.cell_kept,
            "cell_residual_px": self.cell_residual_px,
        }


# --------------------------------------------------------------------------------------------
# Grid


def grid_nodes(
    width: int, height: int, spacing: float, origin: tuple[float, float] = (0.0, 0.0)
) -> tuple[tuple[float, float], tuple[int, int]]:
    """Lay a node grid over a ``width`` x ``height`` crop whose pixel (0,0) is base ``origin``.

    Nodes sit on the base map's lattice of multiples of ``spacing`` (so a crop that moves by a
    pixel, e.g. because the global model changed in its last digits, keeps the same nodes, and
    all frames' fields share one lattice); the first node is at or left of/above the crop's first
    pixel and the last at or beyond its last, so the nodes' cells cover the whole crop. A 1280
    wide crop at x = 0 with spacing 200 gets nodes at 0, 200, ..., 1400 (8).

    Returns:
        ``((x0, y0), (Gx, Gy))``: base px of node (0, 0) and the grid size.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"crop size must be positive, got {width}x{height}")
    if not spacing > 0:
        raise ValueError(f"spacing must be positive, got {spacing}")

    def axis(o: float, n: int) -> tuple[float, int]:
        first = np.floor(o / spacing + 1e-9) * spacing
        last = np.ceil((o + n - 1) / spacing - 1e-9) * spacing
        return float(first), int(round((last - first) / spacing)) + 1

    x0, gx = axis(float(origin[0]), width)
    y0, gy = axis(float(origin[1]), height)
    return (x0, y0), (gx, gy)


# --------------------------------------------------------------------------------------------
# Keypoints and matching


def detect_keypoints(
    grey: NDArray,
    config: LocalConfig = LocalConfig(),
    *,
    mask: NDArray | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
) -> KeypointSet:
    """SIFT keypoints of a grey uint8 crop, positions in base px (crop px + ``origin``).

    Args:
        grey: ``(H, W)`` uint8.
        mask: ``(H, W)`` bool/uint8, where the image has data; eroded by ``mask_erode_px``.
    """
    grey = np.asarray(grey)
    if grey.ndim != 2 or grey.dtype != np.uint8:
        raise ValueError(f"expected a grey uint8 (H, W) image, got {grey.dtype} {grey.shape}")
    cv_mask = None
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != grey.shape:
            raise ValueError(f"mask shape {mask.shape} differs from image shape {grey.shape}")
        cv_mask = (mask > 0).astype(np.uint8) * 255
        if config.mask_erode_px > 0:
            k = 2 * config.mask_erode_px + 1
            cv_mask = cv2.erode(cv_mask, np.ones((k, k), np.uint8))
    sift = cv2.SIFT_create(
        nOctaveLayers=config.sift_n_octave_layers,
        contrastThreshold=config.sift_contrast_threshold,
        edgeThreshold=config.sift_edge_threshold,
        sigma=config.sift_sigma,
    )
    kps, desc = sift.detectAndCompute(grey, cv_mask)
    if not kps:
        return KeypointSet(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    xy = np.array([k.pt for k in kps], np.float64) + np.asarray(origin, np.float64)
    return KeypointSet(xy, np.asarray(desc, np.float32))


def gated_ratio_matches(
    reg_xy: NDArray, reg_desc: NDArray, ref_xy: NDArray, ref_desc: NDArray, config: LocalConfig
) -> tuple[NDArray, NDArray]:
    """Match registered keypoints to reference keypoints within ``max_displacement_px``.

    Both sets are in base px, so a true match lies within the global stage's residual. The
    ratio test is applied among these gated candidates only: repetitive structure farther away
    than any plausible residual cannot veto a distinctive local match. A keypoint with a single
    gated candidate is accepted (REQCON removes the odd mismatch). A reference keypoint claimed
    by several registered ones keeps only the closest descriptor.

    Returns:
        ``(i_reg, i_ref)`` index arrays of the matches.
    """
    from scipy.spatial import cKDTree

    empty = np.zeros(0, np.intp), np.zeros(0, np.intp)
    if len(reg_xy) == 0 or len(ref_xy) == 0:
        return empty
    pairs = cKDTree(reg_xy).sparse_distance_matrix(
        cKDTree(ref_xy), config.max_displacement_px, output_type="ndarray"
    )
    if len(pairs) == 0:
        return empty
    i = pairs["i"].astype(np.intp)
    j = pairs["j"].astype(np.intp)
    a = np.asarray(reg_desc, np.float32)
    b = np.asarray(ref_desc, np.float32)
    d2 = np.einsum("ij,ij->i", a[i] - b[j], a[i] - b[j])
    order = np.lexsort((d2, i))  # by registered keypoint, then descriptor distance
    i, j, d2 = i[order], j[order], d2[order]
    first = np.r_[True, i[1:] != i[:-1]]
    idx_first = np.nonzero(first)[0]
    has_second = np.r_[idx_first[1:], len(i)] - idx_first > 1
    lo = d2[idx_first]
    hi = np.where(has_second, d2[np.minimum(idx_first + 1, len(i) - 1)], np.inf)
    ok = ~has_second | (np.sqrt(lo) < config.ratio * np.sqrt(hi))
    i_reg, i_ref, dist = i[idx_first][ok], j[idx_first][ok], lo[ok]
    if len(i_ref):
        o = np.argsort(dist, kind="stable")
        _, keep = np.unique(i_ref[o], return_index=True)
        keep = np.sort(o[keep])
        i_reg, i_ref = i_reg[keep], i_ref[keep]
    return i_reg, i_ref


# --------------------------------------------------------------------------------------------
# Consensus


@dataclass(frozen=True)
class CellConsensus:
    """Result of :func:`cell_consensus`: ``vector`` (2,) base px at the cell centre (NaN on
    failure), ``kept`` (M,) bool, ``residual_px`` mean residual of the kept matches, ``status``."""

    vector: NDArray[np.float64]
    kept: NDArray[np.bool_]
    residual_px: float
    status: int


def _fit_cells(rel: NDArray, disp: NDArray, kept: NDArray, model: str, cell_px: float):
    """Least-squares displacement model per cell over its kept matches.

    Args:
        rel: ``(C, M, 2)`` match positions relative to the cell centres (padding anywhere).
        disp: ``(C, M, 2)`` displacements.
        kept: ``(C, M)`` bool, the matches to fit.

    Returns:
        ``(vector (C, 2) at the centre, predicted displacement (C, M, 2))``. Cells with fewer
        than 6 kept matches, or whose kept matches spread (standard deviation along either
        principal axis) less than ``cell_px / 8``, get a translation (their mean).
    """
    w = kept.astype(np.float64)[..., None]  # (C, M, 1)
    n = w[..., 0].sum(axis=1)
    safe_n = np.maximum(n, 1.0)[:, None]
    vec = (w * disp).sum(axis=1) / safe_n
    pred = np.broadcast_to(vec[:, None, :], disp.shape)
    if model != "affine":
        return vec, pred
    mu = (w * rel).sum(axis=1) / safe_n
    c = (rel - mu[:, None, :]) * np.sqrt(w)
    cov = np.matmul(c.transpose(0, 2, 1), c) / np.maximum(n - 1, 1.0)[:, None, None]
    a, b, d = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    eig_min = (a + d) / 2 - np.sqrt(((a - d) / 2) ** 2 + b**2)
    affine = (n >= 6) & (np.sqrt(np.maximum(eig_min, 0.0)) >= cell_px / 8.0)
    if not affine.any():
        return vec, pred
    design = np.concatenate([np.ones(rel.shape[:2] + (1,)), rel], axis=2)[affine]  # (A, M, 3)
    weighted_t = (design * w[affine]).transpose(0, 2, 1)  # (A, 3, M)
    coef = np.linalg.solve(weighted_t @ design, weighted_t @ disp[affine])  # (A, 3, 2)
    vec = vec.copy()
    vec[affine] = coef[:, 0, :]
    pred = np.array(pred)
    pred[affine] = design @ coef
    return vec, pred


def consensus_cells(
    pos: NDArray, disp: NDArray, centres: NDArray, members: NDArray, config: LocalConfig
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """REQCON consensus of many neighbourhoods at once (see :func:`cell_consensus`).

    Args:
        pos, disp: ``(N, 2)`` base px of all matches and their displacements.
        centres: ``(C, 2)`` cell centres.
        members: ``(C, M)`` int, each cell's match indices padded with -1.

    Returns:
        ``(vectors (C, 2), kept (C, M) bool, residual_px (C,), status (C,) int8)``; vectors are
        NaN where the status is not OK.
    """
    n_cells, width = members.shape
    slot = members >= 0
    idx = np.where(slot, members, 0)
    rel = pos[idx] - centres[:, None, :]
    d_all = disp[idx]
    kept = slot.copy()
    n = slot.sum(axis=1)
    status = np.full(n_cells, OK, np.int8)
    status[n < config.min_matches] = FEW_MATCHES
    kept[n < config.min_matches] = False
    vectors = np.full((n_cells, 2), np.nan)
    resid = np.full(n_cells, np.nan)
    max_res = config.reqcon_max_residual_px
    active = np.flatnonzero(n >= config.min_matches)
    # The active cells' arrays shrink with them (most cells settle in a few rounds).
    rel_a, d_a, k = rel[active], d_all[active], kept[active]
    while len(active):
        v, pred = _fit_cells(rel_a, d_a, k, config.cell_model, config.cell_px)
        diff = d_a - pred
        r = np.sqrt(diff[..., 0] ** 2 + diff[..., 1] ** 2)
        nk = k.sum(axis=1)
        mean_r = np.where(k, r, 0.0).sum(axis=1) / nk
        done = mean_r < config.reqcon_target_px
        if max_res is not None:
            done &= np.where(k, r, -np.inf).max(axis=1) <= max_res
        resid[active] = mean_r
        vectors[active[done]] = v[done]
        n_drop = np.maximum(1, np.ceil(config.reqcon_drop_fraction * nk).astype(int))
        fail = ~done & (nk - n_drop < config.min_matches)
        status[active[fail]] = NO_CONSENSUS
        kept[active] = k
        go = ~done & ~fail
        if go.any():
            # Drop each cell's n_drop worst kept matches.
            order = np.argsort(np.where(k[go], -r[go], np.inf), axis=1, kind="stable")
            rank = np.empty_like(order)
            np.put_along_axis(rank, order, np.arange(width)[None, :], axis=1)
            k = k[go] & (rank >= n_drop[go, None])
            rel_a, d_a = rel_a[go], d_a[go]
        active = active[go]
    # Rival motion: a second coherent group among the rejected matches, of similar support.
    if config.rival_ratio > 0:
        n_kept = kept.sum(axis=1)
        n_rej = n - n_kept
        suspect = (status == OK) & (
            n_rej >= np.maximum(config.min_matches, config.rival_ratio * n_kept)
        )
        for c in np.flatnonzero(suspect):
            rej = d_all[c][slot[c] & ~kept[c]]
            if _rival_motion(rej, d_all[c][kept[c]].mean(axis=0), int(n_kept[c]), config):
                status[c] = RIVAL_MOTION
    vectors[status != OK] = np.nan
    return vectors, kept, resid, status


def _rival_motion(rejected: NDArray, consensus: NDArray, n_kept: int, config: LocalConfig) -> bool:
    """Whether the rejected displacements hold a coherent group of similar support to the kept
    set, away from the consensus. Group centres are tried at (at most 64, evenly chosen)
    rejected matches: a coherent group is dense, so any of its members finds (nearly) all of it."""
    cand = rejected[:: max(1, len(rejected) // 64)]
    dd = np.sqrt(((cand[:, None, :] - rejected[None, :, :]) ** 2).sum(axis=2))
    counts = (dd <= config.rival_radius_px).sum(axis=1)
    best = int(np.argmax(counts))
    if counts[best] < max(config.min_matches, config.rival_ratio * n_kept):
        return False
    c2 = np.median(rejected[dd[best] <= config.rival_radius_px], axis=0)
    return bool(np.linalg.norm(c2 - consensus) > 2 * config.rival_radius_px)


def cell_consensus(
    pos: ArrayLike, disp: ArrayLike, centre: ArrayLike, config: LocalConfig = LocalConfig()
) -> CellConsensus:
    """One neighbourhood's consensus displacement by REQCON plus the rival-motion guard.

    REQCON (paper 4.3.2, 5): fit the model to all matches, drop the worst ``reqcon_drop_fraction``
    (at least one), refit, until the mean residual of the kept matches is below
    ``reqcon_target_px`` (and, with ``reqcon_max_residual_px``, none is further than that). For
    a translation the least-squares fit is the mean of the kept displacement vectors, so no
    numerical optimiser is needed. :func:`consensus_cells` does the same for many cells at once.

    Args:
        pos: ``(M, 2)`` base px of the matches (reference keypoints).
        disp: ``(M, 2)`` displacement registered - reference, base px.
        centre: ``(2,)`` the cell centre, where the vector is reported.
    """
    pos = as_points(pos, "pos") if len(np.asarray(pos)) else np.zeros((0, 2))
    disp = as_points(disp, "disp") if len(np.asarray(disp)) else np.zeros((0, 2))
    if len(pos) != len(disp):
        raise ValueError(f"pos and disp must have the same length, got {len(pos)} and {len(disp)}")
    centre = np.asarray(centre, np.float64).reshape(1, 2)
    members = np.arange(len(pos))[None, :]
    vectors, kept, resid, status = consensus_cells(pos, disp, centre, members, config)
    return CellConsensus(vectors[0], kept[0], float(resid[0]), int(status[0]))


def neighbour_check(
    vectors: NDArray, valid: NDArray, tolerance_px: float, min_count: int = 3
) -> NDArray[np.bool_]:
    """Cells whose measured vector is further than ``tolerance_px`` from the median of their
    measured 8-neighbours (needs ``min_count`` of them). All cells are judged against the same
    input, so one bad cell cannot condemn a good neighbour unless bad cells are the majority of
    that neighbour's neighbours.

    Returns:
        ``(Gy, Gx)`` bool, True = reject.
    """
    gy, gx = valid.shape
    # The 8 neighbours of every cell side by side: (Gy, Gx, 8, 2), NaN where not measured.
    padded = np.pad(
        np.where(valid[..., None], vectors, np.nan),
        ((1, 1), (1, 1), (0, 0)),
        constant_values=np.nan,
    )
    shifts = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0)]
    nb = np.stack([padded[1 + di : 1 + di + gy, 1 + dj : 1 + dj + gx] for di, dj in shifts], 2)
    count = np.isfinite(nb[..., 0]).sum(axis=2)
    judged = valid & (count >= min_count)
    reject = np.zeros_like(valid, dtype=bool)
    if judged.any():
        med = np.nanmedian(nb[judged], axis=1)
        reject[judged] = np.linalg.norm(vectors[judged] - med, axis=1) > tolerance_px
    return reject


def fill_invalid(vectors: NDArray, valid: NDArray) -> NDArray[np.float32]:
    """Fill the vectors of invalid cells ring by ring with the mean of their already known
    8-neighbours (nearest-valid extrapolation that averages where several are equally near).
    All-invalid grids become zeros."""
    out = np.where(valid[..., None], vectors, 0.0).astype(np.float32)
    known = valid.copy()
    if not known.any():
        return np.zeros_like(out)
    gy, gx = known.shape
    while not known.all():
        kf = known.astype(np.float32)
        pad_k = np.pad(kf, 1)
        pad_v = np.pad(out * kf[..., None], ((1, 1), (1, 1), (0, 0)))
        cnt = sum(
            pad_k[1 + di : 1 + di + gy, 1 + dj : 1 + dj + gx]
            for di in (-1, 0, 1)
            for dj in (-1, 0, 1)
        )
        tot = sum(
            pad_v[1 + di : 1 + di + gy, 1 + dj : 1 + dj + gx]
            for di in (-1, 0, 1)
            for dj in (-1, 0, 1)
        )
        new = (~known) & (cnt > 0)
        out[new] = tot[new] / cnt[new][:, None]
        known = known | new
    return out


# --------------------------------------------------------------------------------------------
# Estimation


def estimate_field_from_keypoints(
    registered_kp: Any,
    reference_kp: Any,
    width: int,
    height: int,
    config: LocalConfig = LocalConfig(),
    *,
    origin: tuple[float, float] = (0.0, 0.0),
    valid_mask: NDArray | None = None,
) -> tuple[DisplacementField, FieldStats]:
    """Displacement field from SIFT keypoints already detected (both in base px).

    Lets a caller detect the mid base image's keypoints once per sequence (or carry the frame's
    keypoints over from the global stage through its transform) instead of once per frame.

    Args:
        registered_kp, reference_kp: objects with ``.xy`` (N, 2) base px and ``.descriptors``.
        width, height, origin: the crop of base coordinates the field covers.
        valid_mask: ``(height, width)`` where both images have data (for the "outside" test).
    """
    t0 = time.perf_counter()
    reg_xy = np.asarray(registered_kp.xy, np.float64).reshape(-1, 2)
    ref_xy = np.asarray(reference_kp.xy, np.float64).reshape(-1, 2)
    reg_desc = np.asarray(registered_kp.descriptors, np.float32)
    ref_desc = np.asarray(reference_kp.descriptors, np.float32)
    # Reference keypoints may cover the whole mid base image: keep those near the crop.
    m = config.max_displacement_px + config.cell_px
    near = (
        (ref_xy[:, 0] >= origin[0] - m)
        & (ref_xy[:, 0] <= origin[0] + width + m)
        & (ref_xy[:, 1] >= origin[1] - m)
        & (ref_xy[:, 1] <= origin[1] + height + m)
    )
    if not near.all():
        ref_xy, ref_desc = ref_xy[near], ref_desc[near]
    # Match once over the whole crop (the gate makes matching local anyway); the matches are
    # then bucketed by the cell their reference keypoint falls in.
    a, b = gated_ratio_matches(reg_xy, reg_desc, ref_xy, ref_desc, config)
    pos = ref_xy[b]
    field_, stats = estimate_field_from_matches(
        pos, reg_xy[a] - pos, width, height, config, origin=origin, valid_mask=valid_mask
    )
    stats.n_keypoints_registered = len(reg_xy)
    stats.n_keypoints_reference = len(ref_xy)
    stats.time_match_s = time.perf_counter() - t0
    return field_, stats


def _box_counts(mask: NDArray, cx: NDArray, cy: NDArray, half: float) -> NDArray[np.int64]:
    """``(Gy, Gx)`` non-zero pixels of ``mask`` in the boxes of side ``2 half`` around the crop
    px ``(cx[j], cy[i])`` (clipped to the crop; box edges rounded to whole pixels). Exact, in
    one pass over the mask: row bands summed at the boxes' row edges, then cumulated over the
    columns (cheaper than a whole integral image of a crop of tens of megapixels)."""
    h, w = mask.shape

    def edges(c: NDArray, n: int) -> tuple[NDArray, NDArray]:
        lo = np.clip(np.floor(c - half + 0.5), 0, n).astype(np.int64)
        hi = np.clip(np.floor(c + half + 0.5), 0, n).astype(np.int64)
        return lo, hi

    r0, r1 = edges(cy, h)
    c0, c1 = edges(cx, w)
    rows = np.unique(np.r_[0, h, r0, r1])
    # The mask's rows summed between consecutive row edges (one pass), then cumulated: the
    # integral image at every row edge and column.
    m = (mask > 0).view(np.uint8)
    bands = np.stack(
        [
            cv2.reduce(m[a:b], 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S)[0]
            for a, b in zip(rows[:-1], rows[1:], strict=True)
        ]
    ).astype(np.int64)
    integral = np.zeros((len(rows), w + 1), np.int64)
    integral[1:, 1:] = np.cumsum(np.cumsum(bands, axis=0), axis=1)
    ri0, ri1 = np.searchsorted(rows, r0), np.searchsorted(rows, r1)
    a = integral[ri1[:, None], c1[None, :]] - integral[ri0[:, None], c1[None, :]]
    b = integral[ri1[:, None], c0[None, :]] - integral[ri0[:, None], c0[None, :]]
    return a - b


def _cell_members(
    pos: NDArray, cxs: NDArray, cys: NDArray, half: float, usable: NDArray[np.bool_]
) -> tuple[NDArray, NDArray, NDArray]:
    """The samples of each usable cell (``c - half < p < c + half`` on both axes), ordered by
    x, then y, then index: ``(rows (C,), columns (C,), members (C, M) padded with -1)``, cells
    in row-major order."""
    n = len(pos)
    gy, gx = usable.shape
    if n == 0 or not usable.any():
        ii, jj = np.nonzero(usable)
        return ii, jj, np.full((len(ii), 0), -1, np.int64)
    sp_x = cxs[1] - cxs[0] if gx > 1 else 1.0
    sp_y = cys[1] - cys[0] if gy > 1 else 1.0

    # Candidate cells of each sample along one axis: the cells whose centre lies within
    # ``half`` of it (at most ceil(2 half / spacing) + 1 of them), checked exactly below.
    def candidates(p: NDArray, c: NDArray, sp: float) -> tuple[NDArray, NDArray]:
        k = int(np.ceil(2 * half / sp)) + 1 if len(c) > 1 else 1
        first = np.floor((p - half - c[0]) / sp).astype(np.int64)
        idx = first[:, None] + np.arange(k + 1)[None, :]
        ok = (idx >= 0) & (idx < len(c))
        cc = c[np.clip(idx, 0, len(c) - 1)]
        ok &= (p[:, None] > cc - half) & (p[:, None] < cc + half)
        return idx, ok

    jx, okx = candidates(pos[:, 0], cxs, sp_x)
    iy, oky = candidates(pos[:, 1], cys, sp_y)
    sample = np.arange(n)
    s_all, i_all, j_all = [], [], []
    for a in range(iy.shape[1]):
        for b in range(jx.shape[1]):
            ok = oky[:, a] & okx[:, b]
            s_all.append(sample[ok])
            i_all.append(iy[ok, a])
            j_all.append(jx[ok, b])
    s_all, i_all, j_all = np.concatenate(s_all), np.concatenate(i_all), np.concatenate(j_all)
    keep = usable[i_all, j_all]
    s_all, i_all, j_all = s_all[keep], i_all[keep], j_all[keep]
    cell = i_all * gx + j_all
    # Order within a cell: x, then y, then index (the order of a stable sort by y, then by x).
    order = np.lexsort((s_all, pos[s_all, 1], pos[s_all, 0], cell))
    s_all, cell = s_all[order], cell[order]
    cells = np.flatnonzero(usable.ravel())
    counts = np.bincount(cell, minlength=gy * gx)[cells]
    members = np.full((len(cells), int(counts.max()) if len(cells) else 0), -1, np.int64)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    slot = np.arange(len(s_all)) - np.repeat(starts, counts)
    members[np.repeat(np.arange(len(cells)), counts), slot] = s_all
    return cells // gx, cells % gx, members


def estimate_field_from_matches(
    pos: ArrayLike,
    disp: ArrayLike,
    width: int,
    height: int,
    config: LocalConfig = LocalConfig(),
    *,
    origin: tuple[float, float] = (0.0, 0.0),
    valid_mask: NDArray | None = None,
) -> tuple[DisplacementField, FieldStats]:
    """Displacement field from point matches: the per-cell consensus, the moving-car guard and
    the filling of rejected cells (``config.fit == "cells"``), or :func:`estimate_field_spline`
    (``"spline"``, no moving-car guard: its Tukey weights drop what disagrees with the fit).

    Args:
        pos: ``(M, 2)`` base px of the matches in the reference (they pick the cell).
        disp: ``(M, 2)`` displacement registered - reference, base px.
        width, height, origin: the crop of base coordinates the field covers.
        valid_mask: ``(height, width)`` where both images have data (for the "outside" test).
    """
    if config.fit == "spline":
        return estimate_field_spline(pos, disp, width, height, config, origin=origin)
    t0 = time.perf_counter()
    all_pos = np.asarray(pos, np.float64).reshape(-1, 2)
    all_disp = np.asarray(disp, np.float64).reshape(-1, 2)
    (x0, y0), (gx, gy) = grid_nodes(width, height, config.spacing_px, origin)
    status = np.full((gy, gx), OUTSIDE, np.int8)
    n_match = np.zeros((gy, gx), np.int32)
    n_kept = np.zeros((gy, gx), np.int32)
    resid = np.full((gy, gx), np.nan, np.float32)
    vec = np.zeros((gy, gx, 2), np.float64)
    half = config.cell_px / 2.0
    cxs = x0 + config.spacing_px * np.arange(gx, dtype=np.float64)
    cys = y0 + config.spacing_px * np.arange(gy, dtype=np.float64)
    usable = np.ones((gy, gx), bool)
    if valid_mask is not None:
        vm = np.asarray(valid_mask)
        if vm.shape != (height, width):
            raise ValueError(
                f"valid_mask shape {vm.shape} differs from the crop ({height}, {width})"
            )
        inside = _box_counts(vm, cxs - origin[0], cys - origin[1], half)
        usable = inside >= config.min_valid_fraction * float(config.cell_px) ** 2
    ii, jj, members = _cell_members(all_pos, cxs, cys, half, usable)
    if len(ii):
        vectors_c, kept_c, resid_c, status_c = consensus_cells(
            all_pos, all_disp, np.c_[cxs[jj], cys[ii]], members, config
        )
        status[ii, jj] = status_c
        n_match[ii, jj] = (members >= 0).sum(axis=1)
        n_kept[ii, jj] = kept_c.sum(axis=1)
        resid[ii, jj] = resid_c
        ok = status_c == OK
        vec[ii[ok], jj[ok]] = vectors_c[ok]
    valid = status == OK
    if config.neighbour_tolerance_px is not None:
        bad = neighbour_check(vec, valid, config.neighbour_tolerance_px, config.neighbour_min_count)
        status[bad] = NEIGHBOUR_OUTLIER
        valid &= ~bad
    vectors = fill_invalid(vec, valid)
    field_ = DisplacementField((x0, y0), float(config.spacing_px), vectors, valid)
    stats = FieldStats(
        cell_status=status,
        cell_matches=n_match,
        cell_kept=n_kept,
        cell_residual_px=resid,
        time_match_s=time.perf_counter() - t0,
    )
    log.debug("local field: %s", stats.counts())
    return field_, stats


# The spline fit (LocalConfig.fit = "spline"): Tukey's biweight constant (95 % efficiency for
# Gaussian residuals), the floor of the robust scale (template and flow samples are never better
# than ~0.1 px; a smaller scale would reject samples for the grid's own approximation error) and
# the reweighting rounds (the weights settle in 3-4; measured on the reference frames of the
# hard profiles).
SPLINE_TUKEY_C = 4.685
SPLINE_MIN_SIGMA_PX = 0.1
SPLINE_ITERATIONS = 6


def _bilinear_design(pos: NDArray, origin: tuple[float, float], spacing: float, gx: int, gy: int):
    """Sparse ``(N, Gy * Gx)`` matrix of the bilinear weights of each position on the node grid
    (node ``(i, j)`` is column ``i * Gx + j``); positions must lie within the nodes' span."""
    from scipy.sparse import csr_matrix

    u = (pos - np.asarray(origin, np.float64)) / spacing
    j0 = np.minimum(np.floor(u[:, 0]).astype(np.intp), max(gx - 2, 0))
    i0 = np.minimum(np.floor(u[:, 1]).astype(np.intp), max(gy - 2, 0))
    fx, fy = u[:, 0] - j0, u[:, 1] - i0
    j1, i1 = np.minimum(j0 + 1, gx - 1), np.minimum(i0 + 1, gy - 1)
    n = len(pos)
    rows = np.tile(np.arange(n), 4)
    cols = np.concatenate([i0 * gx + j0, i0 * gx + j1, i1 * gx + j0, i1 * gx + j1])
    vals = np.concatenate([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    return csr_matrix((vals, (rows, cols)), shape=(n, gx * gy))


def _second_differences(gx: int, gy: int):
    """Sparse matrix of the second differences of a ``(Gy, Gx)`` node grid along x, along y and
    across (its null space is the affine functions of the node position)."""
    from scipy.sparse import csr_matrix

    idx = np.arange(gx * gy).reshape(gy, gx)
    blocks = []  # (node index arrays, coefficients) per kind of difference
    if gx >= 3:
        blocks.append(([idx[:, :-2], idx[:, 1:-1], idx[:, 2:]], (1.0, -2.0, 1.0)))
    if gy >= 3:
        blocks.append(([idx[:-2], idx[1:-1], idx[2:]], (1.0, -2.0, 1.0)))
    if gx >= 2 and gy >= 2:
        corners = [idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]]
        blocks.append((corners, (1.0, -1.0, -1.0, 1.0)))
    rows, cols, vals, r0 = [], [], [], 0
    for nodes, coef in blocks:
        m = nodes[0].size
        for a, c in zip(nodes, coef, strict=True):
            rows.append(r0 + np.arange(m))
            cols.append(a.ravel())
            vals.append(np.full(m, c))
        r0 += m
    if not rows:
        return csr_matrix((0, gx * gy))
    return csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(r0, gx * gy)
    )


def estimate_field_spline(
    pos: ArrayLike,
    disp: ArrayLike,
    width: int,
    height: int,
    config: LocalConfig = LocalConfig(),
    *,
    origin: tuple[float, float] = (0.0, 0.0),
) -> tuple[DisplacementField, FieldStats]:
    """Displacement field from samples by robust, regularised least squares (``fit="spline"``).

    The node vectors ``v`` minimise ``sum_i w_i |B_i v - d_i|^2 + lam |D v|^2``: ``B_i`` the
    bilinear weights of sample ``i`` (so the field :meth:`DisplacementField.sample` returns
    reproduces the samples), ``D`` the second differences of the nodes along x, y and across,
    ``lam = spline_smoothness * samples / nodes``. The weights ``w_i`` are Tukey's biweight of
    the residual over ``SPLINE_TUKEY_C`` robust standard deviations (1.4826 MAD of the samples
    still weighted, at least ``SPLINE_MIN_SIGMA_PX``), ``SPLINE_ITERATIONS`` rounds from equal
    weights. Nodes beyond the samples continue the field's slope (the penalty's null space is
    affine) instead of repeating the nearest cell's vector.

    Args:
        pos: ``(M, 2)`` base px of the samples; disp: ``(M, 2)`` displacements (base px).
        width, height, origin: the crop of base coordinates the field covers (nodes on the
            base lattice of ``spacing_px``, :func:`grid_nodes`); samples outside the nodes'
            span are not used.

    Returns:
        ``(field, stats)``: ``field.valid`` marks nodes with at least one sample's worth of
        (robust- and bilinear-) weight; per node in ``stats``: the samples touching it
        (``cell_matches``), those with a positive weight (``cell_kept``), their weighted mean
        residual; status "ok", "few_matches" (some weight, under one sample's worth) or
        "outside" (none).
    """
    from scipy.sparse import diags, identity
    from scipy.sparse.linalg import spsolve

    t0 = time.perf_counter()
    p = np.asarray(pos, np.float64).reshape(-1, 2)
    d = np.asarray(disp, np.float64).reshape(-1, 2)
    spacing = float(config.spacing_px)
    (x0, y0), (gx, gy) = grid_nodes(width, height, spacing, origin)
    span = np.array([x0 + (gx - 1) * spacing, y0 + (gy - 1) * spacing])
    use = np.isfinite(p).all(axis=1) & np.isfinite(d).all(axis=1)
    use &= (p >= (x0, y0)).all(axis=1) & (p <= span).all(axis=1)
    p, d = p[use], d[use]
    n_nodes = gx * gy
    vectors = np.zeros((gy, gx, 2), np.float32)
    status = np.full((gy, gx), OUTSIDE, np.int8)
    n_match = np.zeros((gy, gx), np.int32)
    n_kept = np.zeros((gy, gx), np.int32)
    resid_node = np.full((gy, gx), np.nan, np.float32)
    if len(p) < max(config.min_matches, 3):
        field_ = DisplacementField((x0, y0), spacing, vectors, np.zeros((gy, gx), bool))
        stats = FieldStats(status, n_match, n_kept, resid_node)
        stats.time_match_s = stats.time_total_s = time.perf_counter() - t0
        return field_, stats
    design = _bilinear_design(p, (x0, y0), spacing, gx, gy)
    penalty = _second_differences(gx, gy)
    regulariser = (config.spline_smoothness * len(p) / n_nodes) * (penalty.T @ penalty)
    w = np.ones(len(p))
    for it in range(SPLINE_ITERATIONS):
        normal = design.T @ diags(w) @ design + regulariser
        ridge = 1e-9 * max(float(normal.diagonal().max()), 1.0)
        v = spsolve((normal + ridge * identity(n_nodes)).tocsc(), design.T @ (w[:, None] * d))
        v = np.asarray(v).reshape(n_nodes, 2)
        r = np.linalg.norm(design @ v - d, axis=1)
        if it == SPLINE_ITERATIONS - 1:
            break
        sigma = max(1.4826 * float(np.median(r[w > 0])), SPLINE_MIN_SIGMA_PX)
        u = r / (SPLINE_TUKEY_C * sigma)
        w = np.where(u < 1, (1 - u**2) ** 2, 0.0)
    touching = (design > 0).astype(np.float64)
    support = np.asarray(design.T @ w).reshape(gy, gx)
    n_match[:] = np.asarray(touching.sum(axis=0)).reshape(gy, gx)
    kept = (w > 0).astype(np.float64)
    n_kept[:] = np.asarray(touching.T @ kept).reshape(gy, gx)
    with np.errstate(invalid="ignore", divide="ignore"):
        resid_node[:] = (np.asarray(design.T @ (w * r)).reshape(gy, gx) / support).astype(
            np.float32
        )
    valid = support >= 1.0
    status[(support > 0) & ~valid] = FEW_MATCHES
    status[valid] = OK
    resid_node[~valid] = np.nan
    field_ = DisplacementField((x0, y0), spacing, v.reshape(gy, gx, 2).astype(np.float32), valid)
    stats = FieldStats(status, n_match, n_kept, resid_node)
    stats.time_match_s = stats.time_total_s = time.perf_counter() - t0
    log.debug("spline field: %s", stats.counts())
    return field_, stats


DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


def flow_matches(
    registered: NDArray,
    reference: NDArray,
    config: LocalConfig = LocalConfig(),
    *,
    valid_mask: NDArray | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Matches for ``method="flow"``: dense DIS optical flow (Kroeger et al. 2016,
    cv2.DISOpticalFlow) from the reference to the registered image, sampled every
    ``flow_step_px`` where both images have data at least ``flow_margin_px`` around.

    The flow at reference pixel ``x`` is where ``x``'s content sits in the registered image,
    i.e. a displacement sample ``d(x)``; each sample votes in its neighbourhood exactly like a
    SIFT match, so REQCON and the moving-car guard apply unchanged.

    Returns:
        ``(pos, disp)``: ``(M, 2)`` base px of the samples and ``(M, 2)`` displacements.
    """
    h, w = reference.shape
    dis = cv2.DISOpticalFlow_create(DIS_PRESETS[config.flow_preset])
    flow = dis.calc(np.ascontiguousarray(reference), np.ascontiguousarray(registered), None)
    step = config.flow_step_px
    ys, xs = np.mgrid[step // 2 : h : step, step // 2 : w : step]
    if valid_mask is not None:
        k = 2 * config.flow_margin_px + 1
        inner = cv2.erode((np.asarray(valid_mask) > 0).astype(np.uint8), np.ones((k, k), np.uint8))
        ok = inner[ys, xs] > 0
        ys, xs = ys[ok], xs[ok]
    else:
        m = config.flow_margin_px
        ok = (xs >= m) & (xs < w - m) & (ys >= m) & (ys < h - m)
        ys, xs = ys[ok], xs[ok]
    pos = np.c_[xs.ravel(), ys.ravel()].astype(np.float64) + np.asarray(origin, np.float64)
    disp = flow[ys.ravel(), xs.ravel()].astype(np.float64)
    # The gate of the SIFT path: a residual beyond max_displacement_px is not the ground.
    keep = np.einsum("ij,ij->i", disp, disp) <= config.max_displacement_px**2
    return pos[keep], disp[keep]


def estimate_field(
    registered: NDArray,
    reference: NDArray,
    config: LocalConfig = LocalConfig(),
    *,
    valid_mask: NDArray | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
    reference_keypoints: Any | None = None,
) -> tuple[DisplacementField, FieldStats]:
    """Displacement field between a globally registered frame and the mid base image (paper 5).

    Args:
        registered: ``(H, W)`` grey uint8, frame k globally registered into base px; pixel
            ``(0, 0)`` is base ``origin``.
        reference: ``(H, W)`` grey uint8, the mid base image over the same crop.
        valid_mask: ``(H, W)`` bool, where both images have data (None = everywhere).
        origin: base px of the crop's pixel (0, 0).
        reference_keypoints: the reference's keypoints in base px if already detected (e.g. once
            per sequence over the whole mid base image); None = detect in ``reference``.

    Returns:
        ``(field, stats)``; ``field`` follows ``registered_local(x) = registered(x + d(x))``.
    """
    registered = np.asarray(registered)
    reference = np.asarray(reference)
    if registered.shape != reference.shape or registered.ndim != 2:
        raise ValueError(
            f"registered and reference must be grey images of one shape, got {registered.shape} "
            f"and {reference.shape}"
        )
    if registered.dtype != np.uint8 or reference.dtype != np.uint8:
        raise ValueError(
            f"registered and reference must be uint8, got {registered.dtype} and {reference.dtype}"
        )
    h, w = registered.shape
    t0 = time.perf_counter()
    if config.method == "flow":
        pos, disp = flow_matches(
            registered, reference, config, valid_mask=valid_mask, origin=origin
        )
        t1 = time.perf_counter()
        field_, stats = estimate_field_from_matches(
            pos, disp, w, h, config, origin=origin, valid_mask=valid_mask
        )
        stats.time_detect_s = t1 - t0
        stats.time_total_s = time.perf_counter() - t0
        return field_, stats
    kp_reg = detect_keypoints(registered, config, mask=valid_mask, origin=origin)
    if reference_keypoints is None:
        kp_ref = detect_keypoints(reference, config, mask=valid_mask, origin=origin)
    else:
        kp_ref = reference_keypoints
    t1 = time.perf_counter()
    field_, stats = estimate_field_from_keypoints(
        kp_reg, kp_ref, w, h, config, origin=origin, valid_mask=valid_mask
    )
    stats.time_detect_s = t1 - t0
    stats.time_total_s = time.perf_counter() - t0
    return field_, stats


@dataclass(frozen=True)
class FlowReference:
    """The mid base image prepared once per sequence for :func:`estimate_field_in_frame`.

    Attributes:
        valid: ``(Hb, Wb)`` bool, where the mid base image has content (base px).
        small: the grey mid base image resampled with area averaging to
            ``(round(Hb * scale), round(Wb * scale))``.
        small_valid: ``small``'s pixels whose every source pixel is valid.
        scale_xy: ``small`` px = ``(base px + 0.5) * scale_xy - 0.5`` (per axis: exact also when
            ``Wb * scale`` is not an integer).
    """

    valid: NDArray[np.bool_]
    small: NDArray[np.uint8]
    small_valid: NDArray[np.bool_]
    scale_xy: NDArray[np.float64]


def prepare_flow_reference(
    grey: NDArray[np.uint8], valid: NDArray[np.bool_], scale: float
) -> FlowReference:
    """See :class:`FlowReference`; ``grey`` and ``valid`` are ``(Hb, Wb)`` in base px."""
    small, scale_xy = _area_resize(grey, scale)
    small_valid, _ = _area_resize(valid.astype(np.uint8) * 255, scale)
    return FlowReference(np.asarray(valid, bool), small, small_valid == 255, scale_xy)


def _area_resize(image: NDArray, scale: float) -> tuple[NDArray, NDArray[np.float64]]:
    """``image`` resampled by about ``scale`` (:func:`features.downscale`) and the exact
    per-axis scale of the result."""
    if scale == 1:
        return image, np.ones(2)
    out = features.downscale(image, scale)
    return out, np.array([out.shape[1] / image.shape[1], out.shape[0] / image.shape[0]])


def flow_scale(width: int, config: LocalConfig) -> float:
    """The scale the flow of a ``width`` px wide frame is computed at (``flow_scale``, raised
    so the flow image is at least ``flow_min_width_px`` wide)."""
    if config.flow_min_width_px <= 0:
        return config.flow_scale
    return max(config.flow_scale, min(1.0, config.flow_min_width_px / width))


def frame_flow_matches(
    frame_grey: NDArray[np.uint8],
    base_from_frame: Callable[[NDArray], NDArray],
    reference: FlowReference,
    config: LocalConfig = LocalConfig(),
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Displacement samples against the mid base image, measured in the frame's own geometry.

    The mid base image is warped into the frame (at :func:`flow_scale`) through the global
    mapping ``base_from_frame``, and DIS optical flow runs from it to the frame: where the warped
    reference shows base point ``B = g(p)`` at frame point ``p``, the frame shows that content at
    ``p + f(p)``. So ``d(B) = g(p + f(p)) - g(p)`` is the field of the module docstring at
    ``B``, exact through ``g`` (no small-displacement approximation). Compared with comparing
    the two in base pixels (:func:`flow_matches`), the frame is never resampled, the costly
    inverse of the global model is never evaluated, and the flow image is the frame's size
    rather than its footprint's bounding box.

    Args:
        frame_grey: ``(H, W)`` uint8 raw frame.
        base_from_frame: the global mapping, ``(N, 2)`` raw frame px -> base px (NaN = none).
        reference: the mid base image (:func:`prepare_flow_reference`).

    Returns:
        ``(pos, disp)``: ``(M, 2)`` base px ``B`` and displacements ``d(B)``, base px.
    """
    h, w = frame_grey.shape
    s = flow_scale(w, config)
    small, s = _area_resize(frame_grey, s)
    hs, ws = small.shape
    rs = reference.scale_xy

    def base_from_small(p: NDArray) -> NDArray:
        return base_from_frame(rescale(p, 1.0 / s))

    smap = warp.source_map_from_function(lambda p: rescale(base_from_small(p), rs), ws, hs, step=8)
    warped = warp.remap(reference.small, smap, interpolation="linear")
    both = warp.remap(reference.small_valid.astype(np.uint8), smap, interpolation="nearest") > 0
    both &= np.isfinite(smap).all(axis=2)
    dis = cv2.DISOpticalFlow_create(DIS_PRESETS[config.flow_preset])
    flow = dis.calc(warped, np.ascontiguousarray(small), None)
    step = max(1, round(config.flow_step_px * s[0]))
    margin = round(config.flow_margin_px * s[0])
    inner = cv2.erode(both.astype(np.uint8), np.ones((2 * margin + 1,) * 2, np.uint8))
    ys, xs = np.mgrid[step // 2 : hs : step, step // 2 : ws : step]
    ok = inner[ys, xs] > 0
    ys, xs = ys[ok], xs[ok]
    p = np.c_[xs, ys].astype(np.float64)
    pos = base_from_small(p)
    disp = base_from_small(p + flow[ys, xs]) - pos
    keep = np.isfinite(pos).all(axis=1) & np.isfinite(disp).all(axis=1)
    keep[keep] = np.einsum("ij,ij->i", disp[keep], disp[keep]) <= config.max_displacement_px**2
    return pos[keep], disp[keep]


def estimate_field_in_frame(
    frame_grey: NDArray[np.uint8],
    base_from_frame: Callable[[NDArray], NDArray],
    reference: FlowReference,
    config: LocalConfig = LocalConfig(),
) -> tuple[DisplacementField, FieldStats] | tuple[None, None]:
    """Displacement field of a frame against the mid base image from :func:`frame_flow_matches`
    (``method="flow"``), over the base-pixel box the frame covers; the per-cell consensus and the
    moving-car guard are those of :func:`estimate_field_from_matches`.

    Args:
        frame_grey: ``(H, W)`` uint8 raw frame.
        base_from_frame: the global mapping, ``(N, 2)`` raw frame px -> base px.
        reference: the mid base image (:func:`prepare_flow_reference`).

    Returns:
        ``(field, stats)``, or ``(None, None)`` when the frame covers no base pixels.
    """
    if config.method != "flow":
        raise ValueError(f"estimate_field_in_frame needs method='flow', got {config.method!r}")
    frame_grey = np.asarray(frame_grey)
    if frame_grey.ndim != 2 or frame_grey.dtype != np.uint8:
        raise ValueError(
            f"frame_grey must be a (H, W) uint8 image, got {frame_grey.shape} {frame_grey.dtype}"
        )
    t0 = time.perf_counter()
    h, w = frame_grey.shape
    hb, wb = reference.valid.shape
    outline = base_from_frame(frame_outline(w, h))
    outline = outline[np.isfinite(outline).all(axis=1)]
    if len(outline) < 3:
        return None, None
    x0, y0, x1, y1 = bbox_of(outline, (wb, hb))
    if x1 - x0 < 2 or y1 - y0 < 2:
        return None, None
    pos, disp = frame_flow_matches(frame_grey, base_from_frame, reference, config)
    t1 = time.perf_counter()
    # Where both have data, for the per-cell "outside" test: the footprint and the mid base.
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillPoly(mask, [np.round(outline - (x0, y0)).astype(np.int32)], 1)
    mask &= reference.valid[y0:y1, x0:x1]
    field_, stats = estimate_field_from_matches(
        pos, disp, x1 - x0, y1 - y0, config, origin=(x0, y0), valid_mask=mask
    )
    stats.time_detect_s = t1 - t0
    stats.time_total_s = time.perf_counter() - t0
    return field_, stats


# --------------------------------------------------------------------------------------------
# Applying the field


def apply_field(
    image: NDArray,
    field_: DisplacementField,
    origin: tuple[float, float] = (0.0, 0.0),
    *,
    interpolation: str = "linear",
    border_value: float | tuple[float, ...] = 0,
) -> NDArray:
    """Locally register a globally registered image: ``out(x) = image(x + d(x))``.

    Args:
        image: ``(H, W[, C])`` globally registered frame over a crop of base px starting at
            ``origin``.
    Returns:
        Same shape and dtype; pixels outside the field get ``border_value``.
    """
    h, w = image.shape[:2]
    source = warp.pixel_grid(w, h) + field_.dense(w, h, origin)
    return warp.remap(image, source, interpolation=interpolation, border_value=border_value)


def local_base_to_frame(
    global_base_to_frame: Callable[[NDArray], NDArray], field_: DisplacementField, xy: ArrayLike
) -> NDArray[np.float64]:
    """``base_to_frame_local(x) = base_to_frame_global(x + d(x))``; ``(N, 2)`` base px -> frame px.

    Beyond the field's extent the field is extended constantly (``sample(outside="clamp")``):
    the global mapping decides what is covered. NaN where it does not cover a point."""
    x = as_points(xy, "xy")
    return np.asarray(global_base_to_frame(x + field_.sample(x, outside="clamp")), np.float64)


def local_frame_to_base(
    global_frame_to_base: Callable[[NDArray], NDArray],
    field_: DisplacementField,
    xy: ArrayLike,
    *,
    tol_px: float = 1e-4,
    max_iterations: int = 100,
) -> NDArray[np.float64]:
    """Frame px -> base px through the global mapping and the field.

    Solves ``x + d(x) = g(q)`` with ``g = global_frame_to_base`` by the fixed-point iteration
    ``x <- g(q) - d(x)``, which converges because the field is smooth (its gradient is far below 1:
    a few px over 200 px). Beyond the field's extent the field is extended constantly, as in
    :func:`local_base_to_frame`. NaN where ``g`` is NaN or the iteration has not converged to
    ``tol_px``.
    """
    q = as_points(xy, "xy")
    y = np.asarray(global_frame_to_base(q), np.float64)
    x = y - np.nan_to_num(field_.sample(y, outside="clamp"))
    done = ~np.isfinite(y).all(axis=1)
    for _ in range(max_iterations):
        todo = ~done
        if not todo.any():
            break
        d = field_.sample(x[todo], outside="clamp")
        x_new = y[todo] - d
        step = np.linalg.norm(x_new - x[todo], axis=1)
        x[todo] = x_new
        conv = step < tol_px
        idx = np.nonzero(todo)[0]
        done[idx[conv | ~np.isfinite(step)]] = True
    final = x + field_.sample(x, outside="clamp") - y
    bad = ~(np.linalg.norm(final, axis=1) < 10 * tol_px)
    x[bad] = np.nan
    return x


def config_dict(config: LocalConfig) -> dict[str, Any]:
    """The config as a plain dict (for result folders / JSON)."""
    return asdict(config)


__all__ = [
    "FLOW_OVERRIDES",
    "STATUS",
    "CellConsensus",
    "DisplacementField",
    "FieldStats",
    "KeypointSet",
    "LocalConfig",
    "apply_field",
    "cell_consensus",
    "config_dict",
    "detect_keypoints",
    "estimate_field",
    "estimate_field_from_keypoints",
    "estimate_field_from_matches",
    "estimate_field_spline",
    "fill_invalid",
    "gated_ratio_matches",
    "grid_nodes",
    "local_base_to_frame",
    "local_frame_to_base",
    "neighbour_check",
    "flow_matches",
]


def reference_field(fine, base_size: tuple[int, int], config: LocalConfig, footprint=None):
    """The reference frame's inter-sensor displacement field (beyond the paper) from its template
    control points: each match says where the base map shows what the global model puts at
    ``model(src)``, i.e. a sample ``d(dst) = model(src) - dst`` of the field of
    :mod:`registration.local`. The per-cell REQCON and the moving-car guard of the local stage
    turn them into a field; mismatches are outvoted by their neighbourhood.

    With ``config.fit == "spline"`` and ``footprint`` (``(N, 2)`` base px, the frame's outline
    under its global model), the field's nodes cover the whole footprint, not only the control
    points' extent: beyond the last control points (the corners, where the frame's radial
    correction stretches the ground most) the spline continues the field's slope.

    Returns ``(field, stats)``, or ``(None, None)`` without control points.
    """
    ok = np.isfinite(fine.src).all(axis=1) & np.isfinite(fine.dst).all(axis=1)
    if not ok.any():
        return None, None
    dst = fine.dst[ok]
    disp = fine.base_from_corrected.apply(fine.src[ok]) - dst
    wb, hb = base_size
    extent = dst
    if footprint is not None and config.fit == "spline":
        outline = np.asarray(footprint, np.float64).reshape(-1, 2)
        extent = np.r_[dst, outline[np.isfinite(outline).all(axis=1)]]
    x0, y0 = np.clip(np.floor(extent.min(axis=0)).astype(int), 0, (wb - 1, hb - 1))
    x1, y1 = np.clip(np.ceil(extent.max(axis=0)).astype(int) + 1, (x0 + 1, y0 + 1), (wb, hb))
    return estimate_field_from_matches(dst, disp, x1 - x0, y1 - y0, config, origin=(x0, y0))


def frame_field(frame, camera: Camera, model, joint, config: LocalConfig):
    """The displacement field of an intra-sensor frame against the mid base image (paper
    section 5): ``frame`` raw (H, W[, 3]) taken by ``camera``, ``model`` its
    ``base_from_corrected``, ``joint`` the :class:`registration.global_registration.JointBase`
    (its flow reference or keypoints are prepared once and kept there). Returns
    ``(field, stats)`` or ``(None, None)``."""
    from registration.render import render_to_base

    hb, wb = joint.mid_grey.shape
    camera.check(frame)
    w = camera.width

    def base_from_raw(q):
        return model.apply(camera.corrected_from_raw(q))

    grey = features.to_grey(frame)
    if config.method == "flow":
        # Measured in the frame's geometry: no rendering of the frame into base pixels.
        if joint.flow_reference is None:
            joint.flow_reference = prepare_flow_reference(
                joint.mid_grey, joint.mid_valid, flow_scale(w, config)
            )
        return estimate_field_in_frame(grey, base_from_raw, joint.flow_reference, config)
    box = bbox_of(model.apply(camera.outline()), (wb, hb), 2)
    x0, y0, x1, y1 = box
    if x1 - x0 < 2 or y1 - y0 < 2:
        return None, None
    registered, valid = render_to_base(grey, camera, model, box)
    reference = joint.mid_grey[y0:y1, x0:x1]
    both = valid & joint.mid_valid[y0:y1, x0:x1]
    # The mid base image is the reference of every frame: detect its keypoints once.
    if joint.local_keypoints is None:
        joint.local_keypoints = detect_keypoints(joint.mid_grey, config, mask=joint.mid_valid)
    return estimate_field(
        registered,
        reference,
        config,
        valid_mask=both,
        origin=(x0, y0),
        reference_keypoints=joint.local_keypoints,
    )

"""The local stage's settings and per-cell results (paper section 5): :class:`LocalConfig`, the
per-cell status codes, :class:`FieldStats` and :class:`KeypointSet`. The field itself is
:class:`registration.geometry.DisplacementField`; the stage is :mod:`registration.local.refine`."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

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
    """Settings of the displacement-field stage (paper section 5). Lengths in base pixels, except
    ``flow_step_px`` and ``flow_margin_px`` (frame pixels: the flow is sampled in the frame).

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
        flow_refinement_iterations: DIS's variational refinement iterations (None: the
            preset's, 5 for "fast" and "medium"; 0 skips the refinement, a third of
            "medium"'s time at 1280x960).
        flow_patch_stride: DIS's patch stride in px (None: the preset's, 3 for "medium", 4 for
            the others); the patch search's cost falls with its square.
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
        base_scale_above: beyond the paper. The lengths above in base px (those in
            ``BASE_PX_LENGTHS``; ``flow_step_px`` and ``flow_margin_px`` are frame px) are for a
            base map at about the frames' ground resolution, as the paper's was. A run whose
            reference frame maps one frame px to ``s`` base px with ``s`` above this value (a
            map finer than the frames) scales them by ``s`` (:meth:`for_base_scale`), so that
            a cell covers the same ground and holds as many flow samples. Measured on
            paper-hard (1280x960, 25 frames) against a map at twice the resolution (``s`` =
            2.38): error after local 0.999 -> 0.750 px of the map at its native resolution
            (0.756 against the native map). A coarser map keeps the lengths (larger cells,
            more samples each); scaled down they were not better: paper-hard at half the
            resolution 0.830 -> 0.782 px, the 120-frame long flight 0.566 -> 0.600. None =
            never (the paper).
        support_folds: beyond the paper; the reference frame's and anchors' field from their
            control points to the map (:func:`registration.local.reference_field`) only. The
            field is fitted again ``support_folds`` times, each time without one fold of the
            points. Where the points left out confirm less than 0.8 of it (the least-squares
            factor between what the field predicts for them and their displacement,
            ``registration.local.refine.SUPPORT_KEEP``) it is kept only at the nodes that the
            left-out points of their own cell confirm, zero vectors elsewhere on its lattice
            (:func:`registration.local.refine.node_support`): against a map of another date the
            points can disagree among themselves by more than a field fitted to all of them
            shows (the real OrthoLoC pair: 1.12 px after the global stage, 2.75 with the field,
            2.02 scaled by the 0.67 confirmed, 1.13 kept at 2 of its 108 nodes). 0 = the field
            as fitted.
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
    flow_refinement_iterations: int | None = None
    flow_patch_stride: int | None = None
    flow_step_px: int = 8
    flow_margin_px: int = 8
    flow_scale: float = 1.0
    flow_min_width_px: int = 0
    fit: str = "cells"
    spline_smoothness: float = 0.1
    base_scale_above: float | None = None
    support_folds: int = 0

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
        if self.flow_refinement_iterations is not None and self.flow_refinement_iterations < 0:
            raise ValueError(
                "flow_refinement_iterations must be None or >= 0, got "
                f"{self.flow_refinement_iterations}"
            )
        if self.flow_patch_stride is not None and self.flow_patch_stride < 1:
            raise ValueError(
                f"flow_patch_stride must be None or >= 1, got {self.flow_patch_stride}"
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
        if self.support_folds == 1 or self.support_folds < 0:
            raise ValueError(f"support_folds must be 0 or at least 2, got {self.support_folds}")
        if self.base_scale_above is not None and not self.base_scale_above >= 1:
            raise ValueError(f"base_scale_above must be None or >= 1, got {self.base_scale_above}")

    def for_base_scale(self, base_px_per_frame_px: float) -> LocalConfig:
        """This configuration for frames that map one frame px to ``base_px_per_frame_px``
        base px: the lengths in ``BASE_PX_LENGTHS`` scaled by it when it exceeds
        ``base_scale_above`` (integers rounded), else ``self``."""
        limit, s = self.base_scale_above, float(base_px_per_frame_px)
        if limit is None or not np.isfinite(s) or s <= limit:
            return self
        scaled = {}
        for name in BASE_PX_LENGTHS:
            v = getattr(self, name)
            if v is not None:
                scaled[name] = round(v * s) if isinstance(v, int) else v * s
        return dataclasses.replace(self, **scaled)


# The LocalConfig lengths in base px: the ground a cell covers and displacement gates and
# residuals measured in base px (LocalConfig.for_base_scale).
BASE_PX_LENGTHS = (
    "cell_px",
    "spacing_px",
    "mask_erode_px",
    "max_displacement_px",
    "reqcon_target_px",
    "reqcon_max_residual_px",
    "rival_radius_px",
    "neighbour_tolerance_px",
)


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
class FieldStats:
    """What :func:`estimate_field` measured (per-cell arrays are ``(Gy, Gx)``).

    Attributes:
        cell_status: int8 code per cell, names in :data:`STATUS`.
        cell_matches: gated matches per cell.
        cell_kept: matches REQCON kept per cell.
        cell_residual_px: mean residual of the kept matches (NaN where no consensus).
        n_keypoints_registered, n_keypoints_reference: SIFT keypoints found in each image's crop.
        time_detect_s, time_match_s, time_total_s: wall time by step.
        support_scale: how much of the field points left out of its fit confirm
            (``LocalConfig.support_folds``; under 0.8 the field is kept only at the nodes
            whose own factor is 0.8 or more), None where it was not measured.
        support_nodes: the share of nodes kept when ``support_scale`` is under 0.8, else None.
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
    support_scale: float | None = None
    support_nodes: float | None = None

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
        } | {
            k: v
            for k, v in (
                ("support_scale", self.support_scale),
                ("support_nodes", self.support_nodes),
            )
            if v is not None
        }

    def to_arrays(self) -> dict[str, NDArray]:
        return {
            "cell_status": self.cell_status,
            "cell_matches": self.cell_matches,
            "cell_kept": self.cell_kept,
            "cell_residual_px": self.cell_residual_px,
        }

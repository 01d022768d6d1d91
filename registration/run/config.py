"""Pipeline configuration: one frozen dataclass collecting each stage's config, and named presets.

Each stage module owns its config dataclass (fields documented there with units and
provenance); this module only collects them. Presets:

* ``paper``: exactly the paper's choices: 1/4-scale SIFT and RANSAC (4 points, 5 px, 1000
  iterations) with Nelder-Mead; 75x75 templates every 50 px with a 20x20 search, correlated
  directly in base pixels; REQCON dropping 5 % until the mean error is below 2 px with
  Nelder-Mead; gridded SIFT (50 px windows every 100 px, decimated by 3) for intra-sensor frames;
  the local field from SIFT in 200x200 neighbourhoods every 200 px with REQCON.
* ``default``: the fastest configuration found that is at least as accurate (see README,
  "Presets"): Levenberg-Marquardt instead of Nelder-Mead (same minimum, ~60x faster), templates
  correlated after warping the reference into frame geometry, template control points for
  intra-sensor frames instead of full-resolution SIFT, the local field from those same kinds of
  matches, and the intra-sensor coarse step's fast path (:mod:`registration.global_registration.predicted_coarse`: the
  frame predicted from the previous one and confirmed by correlation, the SIFT step only when
  that fails).
* ``fast``: the default preset with one dense flow per intra-sensor frame, which gives the
  global model's control points and the local field alike (:data:`INTRA_FLOW_POINT_SPACING_PX`):
  ~20 % less compute per 2560x1920 frame at the same error there, but up to 5 % more error on
  640x480 flights (README, "Presets"). Faster where the stages run one after the other (Dask
  workers, one core); with both cores in one process the default is faster.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field, replace

from registration.adjustment import SequenceAdjustConfig
from registration.global_registration import CoarseConfig, FineConfig, IntraConfig
from registration.lens import LensConfig
from registration.local import FLOW_OVERRIDES, LocalConfig
from registration.matching import TemplateConfig


@dataclass(frozen=True)
class PipelineConfig:
    """Everything a registration run needs besides its inputs.

    Attributes:
        coarse: coarse projective step (paper 4.3.1).
        fine: fine polyprojective step of the reference frame (paper 4.3.2).
        intra: intra-sensor registration of the other frames (paper 4.4).
        local: local displacement field (paper section 5).
        match_in: where control points are found: ``"corrected"`` (the paper: in the radially
            corrected frame on the raw frame's canvas) or ``"raw"`` (in the raw frame, positions
            mapped through the exact Harris model; covers the corners the correction pushes off
            the canvas, and avoids resampling the frame before matching).
        run_local: compute the local field (stage ``"local"``); without it stage ``"local"``
            equals ``"global"``.
        reference_local: beyond the paper: settings of the reference frame's own displacement
            field against the base map, from its template control points
            (:func:`registration.local.refine.reference_field`); the mid base image is rendered
            with it, so every frame's local stage inherits it. None = the paper (the reference
            frame's local stage is its global model).
        reference_local_beyond_harris: beyond the paper: ``reference_local`` for a lens beyond
            Harris (the reference frame's registration adopted a fourth-order term, ``lens``);
            None = ``reference_local`` whatever the lens (:meth:`reference_local_for`).
        lens: beyond the paper: whether the reference frame's registration estimates a
            lens beyond Harris (a fourth-order radial term, :mod:`registration.lens.k2`) and
            registers every frame with it. The default (``LensConfig()``) is the paper: γ only.
        random_seed: seed of every random choice (RANSAC samples); frame ``k`` uses
            ``random_seed + k``.
        chunk_frames: beyond the paper: split the frames after the reference frame, and the
            frames before it, into chunks of at most this many consecutive frames that are
            registered independently of each other (:func:`registration.run.chunks.chunk_plan`),
            so that they can run in parallel (``registration.run.dask_executor``). A chunk's first
            frame has no registered predecessor (unless it follows the reference frame) and
            each chunk sees only its own anchors. 0 = one chunk (the paper's chain). The result
            depends on this value, not on where the chunks run.
        adjust: beyond the paper: once every frame is registered, estimate the global models
            of all frames together, window by window, from their control points and links
            between frames that see the same ground
            (:mod:`registration.adjustment.sequence`); each frame then also gets a predicted
            error and a flag. None = each frame as its own registration left it (the paper).
    """

    coarse: CoarseConfig = field(default_factory=CoarseConfig)
    fine: FineConfig = field(default_factory=FineConfig)
    intra: IntraConfig = field(default_factory=IntraConfig)
    local: LocalConfig = field(default_factory=LocalConfig)
    match_in: str = "corrected"
    run_local: bool = True
    reference_local: LocalConfig | None = None
    reference_local_beyond_harris: LocalConfig | None = None
    lens: LensConfig = field(default_factory=LensConfig)
    random_seed: int = 0
    chunk_frames: int = 0
    adjust: SequenceAdjustConfig | None = None

    def __post_init__(self) -> None:
        if isinstance(self.chunk_frames, bool) or not isinstance(self.chunk_frames, int):
            raise ValueError(f"chunk_frames must be an integer, got {self.chunk_frames!r}")
        if self.chunk_frames < 0:
            raise ValueError(f"chunk_frames must be 0 (one chunk) or more, got {self.chunk_frames}")

    def reference_local_for(self, k2: float) -> LocalConfig | None:
        """The settings of the reference frame's and anchors' own field for a lens whose
        fourth-order term is ``k2`` (0: exactly Harris)."""
        if k2 and self.reference_local_beyond_harris is not None:
            return self.reference_local_beyond_harris
        return self.reference_local


def _paper() -> PipelineConfig:
    # The dataclass defaults are the paper's values except the template matching, whose defaults
    # carry the checks beyond the paper that every other preset uses (TemplateConfig.paper()).
    base = PipelineConfig()
    return replace(
        base,
        fine=replace(base.fine, template=TemplateConfig.paper()),
        intra=replace(base.intra, template=TemplateConfig.paper()),
    )


# Side of the default preset's border templates (templates.TemplateConfig.edge_template_px).
EDGE_TEMPLATE_PX = 31
# The default preset's REQCON stop (mean error of the kept points, px). The paper's 2 px stops
# in the first round on template control points (their mean error is about 0.5 px), keeping
# every mismatch; 0.5 px removes them and roughly halves the corner errors (README, Presets).
REQCON_TARGET_PX = 0.5
# The default preset's REQCON drops only outliers (residuals beyond ~5 robust standard
# deviations) and stops when none is left: a lens beyond Harris or a rolling shutter leaves the
# polyprojective a systematic error that an absolute target never reaches, and the paper's rule
# then drops good points until it fails the frame (robust.ReqconConfig.stop).
REQCON_STOP = "outliers"
# The default preset's RANSAC cap. The paper's 1000 fails at high outlier shares (performance
# notes: 90 % outliers); the adaptive stop (confidence 0.999) makes the higher cap cost nothing
# when the inlier share is high, as it is for a seeded helicopter frame. On the 200 real SRIF
# pairs it doubled the coarse step's success rate (README, Benchmarks).
RANSAC_MAX_ITERATIONS = 10000
# The default local stage measures the flow in the frame's geometry at half scale, but never on
# an image narrower than 1280 px (local.estimate_field_in_frame), with DIS "medium", sampled
# every 16 px (156 samples per 200 px neighbourhood). Measured on simulated 2560x1920 frames against the exact truth (motion
# relative to the reference frame): full scale "fast", every 8 px: 0.09-0.11 px, 0.41-0.43 s;
# half scale "medium", every 16 px: 0.12-0.13 px, 0.22-0.24 s; the global stage leaves
# 0.27-0.58 px and the reference frame's own inter-sensor error is ~1 px, so the difference does
# not show in the absolute error (README, Presets).
# DIS patches every 4 px instead of "medium"'s 3: the patch search costs 25 % less (one
# 1280x960 flow: 123 -> 92 ms), and the error after local does not move (against the truth,
# stride 3 -> 4: 2560x1920 default flight 0.514 -> 0.514 px, paper-hard 3.302 -> 3.298;
# 1280x960 paper-hard 0.765 -> 0.766; 640x480 long flight, 120 frames, 0.682 -> 0.683).
# The local stage's base-px lengths grow with the map's resolution when the reference frame maps
# a frame px to more than 1.5 base px (LocalConfig.base_scale_above; the simulated flights at
# the map's own resolution are at 1.1-1.2 and keep the paper's lengths).
LOCAL_FLOW = {
    "flow_preset": "medium",
    "flow_patch_stride": 4,
    "flow_scale": 0.5,
    "flow_min_width_px": 1280,
    "flow_step_px": 16,
    "base_scale_above": 1.5,
}
# The reference frame's field from its template matches (beyond the paper): one robust, regularised
# least-squares fit of nodes 100 px apart to every match (local.LocalConfig.fit = "spline",
# smoothness 0.1, Tukey weights), over the frame's whole footprint. A polyprojective cannot follow
# the terrain's relief (the best degree-2 fit to a paper-hard 1280x960 frame's truth through the
# exact lens: 1.14 px mean, 1.17 without its rolling shutter, 0.28 without the relief), nor the
# error of a lens estimated beyond Harris: in the corners of a paper-hard reference frame
# (1280x960) its error reaches 50 px within the outermost raw pixels, where a per-cell consensus
# (affine cells of 300 px, 150 px apart, REQCON to 0.5 px: the previous default) is constant and
# the spline continues the field's slope. Reference frame, mean error over a 16 px grid of ground
# points, cells -> spline: paper-hard 1280x960 1.02 -> 0.74, long-flight 640x480 0.71 -> 0.72, the
# tests' 640x480 sequence (exact Harris lens) 0.39 -> 0.43 (its other frames 0.52 -> 0.49, motion
# 0.20 -> 0.18: they align to a mid base image rendered with this field). Both leave the
# inter-sensor matches' shadow bias (~0.4 px in y on the simulated flights: the base map's sun is
# not the frames'), which no field fitted to those matches can remove. Against a map finer than the
# frames the node spacing grows with it as the other frames' cells do
# (LocalConfig.base_scale_above): templates every 25 frame px are ~60 base px apart at 2.4 base px
# per frame px, ~3 per node 100 base px apart, and the field followed their noise, which every
# other frame's smoother field then disagreed with. Paper-hard 1280x960, 25 frames, 2x map, motion
# after local (base px, mean) 0.821 -> 0.427 (seed 6, 217°) and 1.388 -> 0.744 (seed 7, 0°), long
# flight 640x480, 60 frames, 0.953 -> 0.851; error after local, median 0.948 -> 0.884, 1.284 ->
# 1.152, 1.132 -> 1.059, mean 1.499 -> 1.567, 2.631 -> 2.606, 1.447 -> 1.399 (nodes further apart
# extrapolate further into the corners).
# Beyond Harris, the reference frame's and anchors' field bends more freely: smoothness 0.05
# instead of 0.1 (PipelineConfig.reference_local_beyond_harris). A paper-hard frame's error after
# the local stage sits in its outermost raw pixels (1280x960 seed 0: 0.08 base px within 0.8 of the
# half-diagonal, 3.4-4.5 px beyond 0.9), where the fourth-order term's estimate is least sure (k2
# 0.0411 against the truth's 0.040: 3.3 corrected px at the corner) and the terrain's relief grows
# fastest; the stiffer spline carried the slope past it (the reference frame's nodes beyond 0.95:
# 6.9 px off the truth, more than the 5.2 px they should move). Mean error after the local stage,
# 0.1 -> 0.05 for every flight: lens beyond Harris, paper-hard 1280x960 x 12 seeds 0-5
# 0.511/0.409/0.455/0.585/0.449/0.327 -> 0.453/0.399/0.418/0.549/0.388/0.341 (mean 0.456 -> 0.425),
# 2560x1920 x 15 0.352 -> 0.350; exact Harris, default 1280x960 x 12 seeds 0/3 0.312/0.305 ->
# 0.302/0.298, long flight 640x480 x 120 0.375 -> 0.383, the tests' 640x480 sequence (reference
# frame 0) 0.282 -> 0.341 for the reference frame and 0.321 -> 0.375 for the others: with the lens
# exactly Harris a freer field follows the templates' noise. Its held-out points do not tell the
# two apart (5 folds: 0.1308 against 0.1348 px trimmed RMS on that sequence, where 0.05 is worse).
REFERENCE_SMOOTHNESS_BEYOND_HARRIS = 0.05
REFERENCE_LOCAL = LocalConfig(
    fit="spline",
    spacing_px=100,
    spline_smoothness=0.1,
    min_matches=6,
    base_scale_above=LOCAL_FLOW["base_scale_above"],
    support_folds=5,
)
# Template spacing of the reference frame (a one-off): every 25 px instead of the paper's 50, so
# that the field above has matches in the frame's stretched corners (~7200 templates, 3.7 s at
# 2560x1920). Measured on a simulated 2560x1920 reference frame, mean error over a 16 px grid of
# ground points: global 1.78 px; with the field from templates every 50 px 1.15 px (p95 4.7),
# every 25 px 0.54 px (p95 1.2).
REFERENCE_TEMPLATE_SPACING_PX = 25
# The fine step refits through the click where its model misses it by more than 6 px
# (global_registration.FineConfig.click_refit_px): 3 times the 2 px a careful click is off.
# Measured on the 200 SRIF pairs with one click 2 px off: 5 pairs whose first fit followed the
# roofs (14-19 px off the ground at image 1's corners) land at 2-8 px, none gets worse than
# 10 px; at 5 px one pair fewer (pair 26's refit passes 5.1 px from the click).
CLICK_REFIT_PX = 6.0
# Re-anchoring (global_registration.IntraConfig.reanchor_coverage): a frame less than 75 % on the
# mid base image is registered to the base map again and fills the mid base image's holes.
REANCHOR_COVERAGE = 0.75
# An anchor fills the mid base image only from its raw pixels within 0.7 of the half-diagonal
# (IntraConfig.anchor_fill_radius): its outer ring, where the lens compresses the ground and its
# registration is least accurate, is where the mid base image's holes lie ahead of the flight.
# Long flight 640x480, 120 frames, seed 0, error after local (mean; first 10 / last 10 frames;
# anchors; anchor time over the flight, two busy cores): whole frame 0.454 (0.505 / 0.646;
# 10; 20.7 s), 0.8 0.410 (0.505 / 0.569; 13; 24.6 s), 0.7 0.385 (0.505 / 0.551; 27; 51.6 s).
# The same 0.7 measured as an ellipse of the frame's axes: 0.395 (0.505 / 0.532; 22). Tried
# and not kept: anchoring more often instead (reanchor_coverage 0.9: 0.498, last 10 0.731).
ANCHOR_FILL_RADIUS = 0.7
# Coarse SIFT keypoints per intra-sensor frame in the default preset (IntraConfig).
INTRA_COARSE_NFEATURES = 2000
# Intra-sensor templates of the default preset: every 150 px without the dithered
# re-correlation. The global model of a frame is limited by what a polyprojective can represent
# (rolling shutter under lens distortion), not by the control points' precision, and the local
# stage removes the rest: on simulated 2560x1920 frames, motion after global 0.474 px with 1912
# dithered templates every 50 px (0.89 s), 0.472 px with 511 undithered every 100 px (0.30 s);
# after local 0.102 and 0.099 px. Every 150 px (~280 templates with the edge ring) against 100
# (~555), one thread, 2560x1920: fine step 0.217 -> 0.156 s per frame, error after local
# 0.4944 -> 0.4933 px (default flight, 6 frames) and 3.26 -> 3.10 px (paper-hard, 15 frames);
# long flight at 1920x1440 (120 frames): fine 0.216 -> 0.165 s, after local 0.7545 -> 0.7510 px,
# after global 1.420 -> 1.459 px (the global model follows fewer points; the local stage
# removes the difference).
# Smaller frames get a denser grid (at least 200 templates: 640x480 frames would otherwise have
# 24, too few for REQCON on 17 coefficients), so below ~1600 px wide (4:3) the spacing changes
# nothing.
INTRA_TEMPLATE = {"spacing_px": 150, "dither_iterations": 0, "min_templates": 200}
# The fast preset's intra-sensor control points come from the frame's dense flow against the
# mid base image (IntraConfig.control_points = "flow", registration.global_registration.intra_points.flow_points),
# measured through the coarse model: a point every 96 px (never sparser than the template grid
# above), the 31 px templates only along the border (the edge ring) and at grid centres the flow
# does not reach; the local stage reuses the same flow instead of measuring its own. Against the
# truth, default (template grid) -> fast (flow points), error after global / after local:
#   2560x1920, 12 frames: default flight 1.406 / 0.514 -> 1.385 / 0.514 px,
#                         paper-hard 4.81 / 3.30 -> 4.28 / 3.14 px;
#   1280x960, 16 frames: default flight 1.089 / 0.559 -> 1.081 / 0.562 px,
#                        paper-hard 1.402 / 0.765 -> 1.302 / 0.738 px.
# Flow points alone, without the edge ring, left the outermost 8 raw px at 3.18 px after global
# against the template grid's 1.78 (1280x960, default flight): the flow keeps a margin there. A
# point every 128 px instead: 2560x1920 default flight 0.518 px after local, paper-hard 3.14. One DIS flow per frame instead of a template grid and a
# second flow: see the README's speed section. Not the default: on 640x480 flights the flow
# points are worse than the 75 px templates (the tests' sequence: other frames 0.480 -> 0.504 px
# after local; the long flight's last tenth 0.825 -> 0.993 px), where the frame's flow runs at
# full scale and the templates cover an eighth of the frame each.
INTRA_FLOW_POINT_SPACING_PX = 96


# The default preset's test for pixels that changed between a frame and the base map
# (templates.TemplateConfig.change_log_ratio): a natural-log brightness ratio 0.1 (10 %) off the
# template's photometric line. It applies to windows of the base map only (the reference frame,
# re-anchored frames, an intra-sensor frame's templates that only the map can take), not to the mid
# base image or the previous frame: the moved shadows of another date are the map's.
CHANGE_LOG_RATIO = 0.1

# The default preset's coarse step (registration.global_registration.coarse): never smaller than 640 px (1/4 of the
# paper's 2560 px), guided matching and two refinement rounds around the heading estimate, the
# base detected at the frame's ground resolution, and similarity/affine/projective chosen by BIC.
COARSE_BEYOND_PAPER = {
    "min_side_px": 640,
    "guided": True,
    "refine_rounds": 2,
    "match_base_scale": True,
    "models": ("similarity", "affine", "projective"),
}
# Then four rounds of gradient-magnitude correlation (registration.global_registration.gradient_correlation): the frame at
# 256 px (longer side) with +-20 and +-10 px searches, then at 512 px with +-8 and +-5 px. On the
# OrthoLoC UAV photo against the orthophoto of another date, from the seed's similarity alone,
# 52 px -> 2.7 px mean error (intensity correlation: 52 px throughout).
CORRELATION_ROUNDS = ((256, 40), (256, 20), (512, 16), (512, 10))


def _default() -> PipelineConfig:
    paper = PipelineConfig()
    lm_ransac = replace(paper.coarse.ransac, refine="lm", max_iterations=RANSAC_MAX_ITERATIONS)
    lm_reqcon = replace(
        paper.fine.reqcon,
        optimizer="lm",
        target_mean_error_px=REQCON_TARGET_PX,
        stop=REQCON_STOP,
    )
    warped = replace(
        paper.fine.template,
        warp_reference=True,
        edge_template_px=EDGE_TEMPLATE_PX,
        spacing_px=REFERENCE_TEMPLATE_SPACING_PX,
        change_log_ratio=CHANGE_LOG_RATIO,
    )
    return replace(
        paper,
        match_in="raw",
        coarse=replace(
            paper.coarse,
            ransac=lm_ransac,
            correlation=replace(paper.coarse.correlation, rounds=CORRELATION_ROUNDS),
            **COARSE_BEYOND_PAPER,
        ),
        fine=replace(
            paper.fine,
            template=warped,
            reqcon=lm_reqcon,
            check_support=True,
            click_refit_px=CLICK_REFIT_PX,
        ),
        intra=replace(
            paper.intra,
            coarse_nfeatures=INTRA_COARSE_NFEATURES,
            control_points="template",
            template=replace(
                paper.intra.template,
                warp_reference=True,
                edge_template_px=EDGE_TEMPLATE_PX,
                change_log_ratio=CHANGE_LOG_RATIO,
                **INTRA_TEMPLATE,
            ),
            reqcon=lm_reqcon,
            reanchor_coverage=REANCHOR_COVERAGE,
            anchor_fill_radius=ANCHOR_FILL_RADIUS,
            base_fallback=True,
            fast_coarse=True,
            sparse_support=True,
        ),
        local=replace(paper.local, **{**FLOW_OVERRIDES, **LOCAL_FLOW}),
        reference_local=REFERENCE_LOCAL,
        reference_local_beyond_harris=replace(
            REFERENCE_LOCAL, spline_smoothness=REFERENCE_SMOOTHNESS_BEYOND_HARRIS
        ),
        lens=LensConfig(estimate_k2=True),
        adjust=SequenceAdjustConfig(),
    )


def _fast() -> PipelineConfig:
    """The default preset with one DIS flow per intra-sensor frame: control points drawn from
    it (:data:`INTRA_FLOW_POINT_SPACING_PX`) and the local stage reusing it, and no sequence
    adjustment (it would add more to this preset's time than to the default's)."""
    default = _default()
    return replace(
        default,
        adjust=None,
        intra=replace(
            default.intra,
            control_points="flow",
            flow_point_spacing_px=INTRA_FLOW_POINT_SPACING_PX,
        ),
    )


PRESETS: dict[str, typing.Callable[[], PipelineConfig]] = {
    "paper": _paper,
    "default": _default,
    "fast": _fast,
}


def get_preset(name: str) -> PipelineConfig:
    """The named preset; ValueError naming the choices for an unknown name."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    return PRESETS[name]()


def config_to_dict(config: PipelineConfig) -> dict:
    """JSON-able nested dict of a config. Without a sequence adjustment its key is left out, so
    that a result written before the adjustment existed resumes."""
    out = dataclasses.asdict(config)
    if out.get("adjust", 0) is None:
        del out["adjust"]
    return out


_POOLED = (
    "whose sequence adjustment pooled neighbours' local fields; register it afresh to go on "
    "with this release"
)
# Settings earlier releases wrote that no longer exist, and what to do with their results.
RETIRED_KEYS = {
    "config.adjust.field_radius": _POOLED,
    "config.adjust.field_baseline_px": _POOLED,
    "config.adjust.field_support": _POOLED,
}


def config_from_dict(data: dict, cls: type = PipelineConfig, path: str = "config"):
    """Rebuild a (nested) config dataclass; unknown keys are an error, missing keys take defaults."""
    if not isinstance(data, dict):
        raise ValueError(f"{path} must be an object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - known)
    retired = [k for k in unknown if f"{path}.{k}" in RETIRED_KEYS]
    if retired:
        key = f"{path}.{retired[0]}"
        raise ValueError(f"{key}: made by an earlier release, {RETIRED_KEYS[key]}")
    if unknown:
        raise ValueError(f"unknown key {path}.{unknown[0]} (known: {', '.join(sorted(known))})")
    kwargs = {}
    for name, value in data.items():
        tp = hints[name]
        sub = _dataclass_in(tp)
        if sub is not None and isinstance(value, dict):
            kwargs[name] = config_from_dict(value, sub, f"{path}.{name}")
        elif sub is not None and value is not None:
            raise ValueError(f"{path}.{name} must be an object, got {type(value).__name__}")
        else:
            kwargs[name] = _tuples(value)
    return cls(**kwargs)


def _tuples(value):
    """JSON lists back to the tuples the dataclasses hold (nested: correlation rounds)."""
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def _dataclass_in(tp) -> type | None:
    if dataclasses.is_dataclass(tp):
        return tp
    if isinstance(tp, types.UnionType) or typing.get_origin(tp) is typing.Union:
        for arg in typing.get_args(tp):
            if dataclasses.is_dataclass(arg):
                return arg
    return None

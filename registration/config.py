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
  intra-sensor frames instead of full-resolution SIFT, and the local field from those same kinds of
  matches.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field, replace

from registration.global_registration import CoarseConfig, FineConfig, IntraConfig
from registration.local import FLOW_OVERRIDES, LocalConfig


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
        random_seed: seed of every random choice (RANSAC samples); frame ``k`` uses
            ``random_seed + k``.
    """

    coarse: CoarseConfig = field(default_factory=CoarseConfig)
    fine: FineConfig = field(default_factory=FineConfig)
    intra: IntraConfig = field(default_factory=IntraConfig)
    local: LocalConfig = field(default_factory=LocalConfig)
    match_in: str = "corrected"
    run_local: bool = True
    random_seed: int = 0


def _paper() -> PipelineConfig:
    return PipelineConfig()


# Side of the default preset's border templates (features.TemplateConfig.edge_template_px).
EDGE_TEMPLATE_PX = 31
# The default preset's REQCON stop (mean error of the kept points, px). The paper's 2 px stops
# in the first round on template control points (their mean error is about 0.5 px), keeping
# every mismatch; 0.5 px removes them and roughly halves the corner errors (README, Presets).
REQCON_TARGET_PX = 0.5
# The default preset's RANSAC cap. The paper's 1000 fails at high outlier shares (performance
# notes: 90 % outliers); the adaptive stop (confidence 0.999) makes the higher cap cost nothing
# when the inlier share is high, as it is for a seeded helicopter frame. On the 200 real SRIF
# pairs it doubled the coarse step's success rate (README, Benchmarks).
RANSAC_MAX_ITERATIONS = 10000
# DIS optical-flow preset of the default local stage: "fast" costs ~1/4 of "medium" (0.12 vs
# 0.48 s on a 1280x960 frame's footprint) for ~0.13 instead of ~0.05 px field error, far below
# the ~1 px that the reference frame's inter-sensor registration leaves (README, Presets).
LOCAL_FLOW_PRESET = "fast"


def _default() -> PipelineConfig:
    paper = PipelineConfig()
    lm_ransac = replace(paper.coarse.ransac, refine="lm", max_iterations=RANSAC_MAX_ITERATIONS)
    lm_reqcon = replace(paper.fine.reqcon, optimizer="lm", target_mean_error_px=REQCON_TARGET_PX)
    warped = replace(paper.fine.template, warp_reference=True, edge_template_px=EDGE_TEMPLATE_PX)
    return replace(
        paper,
        match_in="raw",
        coarse=replace(paper.coarse, ransac=lm_ransac),
        fine=replace(paper.fine, template=warped, reqcon=lm_reqcon),
        intra=replace(
            paper.intra,
            control_points="template",
            template=replace(
                paper.intra.template, warp_reference=True, edge_template_px=EDGE_TEMPLATE_PX
            ),
            reqcon=lm_reqcon,
        ),
        local=replace(paper.local, **{**FLOW_OVERRIDES, "flow_preset": LOCAL_FLOW_PRESET}),
    )


PRESETS: dict[str, typing.Callable[[], PipelineConfig]] = {"paper": _paper, "default": _default}


def get_preset(name: str) -> PipelineConfig:
    """The named preset; ValueError naming the choices for an unknown name."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    return PRESETS[name]()


def config_to_dict(config: PipelineConfig) -> dict:
    """JSON-able nested dict of a config."""
    return dataclasses.asdict(config)


def config_from_dict(data: dict, cls: type = PipelineConfig, path: str = "config"):
    """Rebuild a (nested) config dataclass; unknown keys are an error, missing keys take defaults."""
    if not isinstance(data, dict):
        raise ValueError(f"{path} must be an object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"unknown key {path}.{unknown[0]} (known: {', '.join(sorted(known))})")
    kwargs = {}
    for name, value in data.items():
        tp = hints[name]
        sub = _dataclass_in(tp)
        if sub is not None and isinstance(value, dict):
            kwargs[name] = config_from_dict(value, sub, f"{path}.{name}")
        elif isinstance(value, list):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
    return cls(**kwargs)


def _dataclass_in(tp) -> type | None:
    if dataclasses.is_dataclass(tp):
        return tp
    if isinstance(tp, types.UnionType) or typing.get_origin(tp) is typing.Union:
        for arg in typing.get_args(tp):
            if dataclasses.is_dataclass(arg):
                return arg
    return None

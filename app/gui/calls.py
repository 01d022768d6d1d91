"""The app's calls into ``registration`` that need a little glue: the run's configuration from the
app's choices, the coarse step with one or two seed pairs, the heading and scale the analyst sees
after seeding (``CoarseResult.heading_deg``, ``.scale``, ``.gate``), a second seed pair made from
a typed heading and scale, and re-running one frame of a result.

Kept apart from the views so that they stay drawing and widgets, and so that what the app
expects of the library is in one place.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from registration import global_registration
from registration.adjustment import SequenceAdjustConfig
from registration.lens import Camera
from registration.run import config as run_config
from registration.run import frame_record_path, pipeline


def pipeline_config(
    preset: str, degree: int, run_local: bool, adjust: bool = False
) -> run_config.PipelineConfig:
    """The preset with the app's transform choice: polyprojective ``degree`` (1 = projective)
    for the reference and every frame, the local displacement field on or off, and the
    sequence adjustment on or off."""
    cfg = run_config.get_preset(preset)
    fine = dataclasses.replace(cfg.fine, degree=int(degree))
    return dataclasses.replace(
        cfg, fine=fine, run_local=bool(run_local),
        adjust=SequenceAdjustConfig() if adjust else None,
    )  # fmt: skip


def seed_argument(seed, seed2):
    """The library's ``seed`` argument from the analyst's pairs: None, one ``(fx, fy, bx, by)``,
    or both (two pairs fix heading and scale)."""
    if seed is None:
        return None
    return seed if seed2 is None else [tuple(seed), tuple(seed2)]


def coarse_register(frame, base, gamma, seed, seed2, config, base_valid=None):
    """The coarse step (paper 4.3.1) with the seed pairs the analyst placed."""
    return global_registration.coarse_register(
        frame, base, gamma, seed_argument(seed, seed2), config.coarse, match_in=config.match_in,
        base_valid=base_valid,
    )  # fmt: skip


def failed_coarse(reason: str) -> global_registration.CoarseResult:
    """A failed coarse result with ``reason`` (for input the library refuses with an error)."""
    empty = np.zeros((0, 2))
    none = np.zeros(0, bool)
    return global_registration.CoarseResult(False, reason, None, empty, empty, none, none, 0, 0)


@dataclasses.dataclass(frozen=True)
class HeadingScale:
    """Rotation frame -> base (degrees in [0, 360), image coordinates: x right, y down, so
    positive = clockwise on screen; the library's ``CoarseResult.heading_deg``) and scale (base
    px per corrected frame px), and where they come from."""

    heading_deg: float
    scale: float
    source: str

    def text(self) -> str:
        return (
            f"heading **{self.heading_deg:.1f}°**, scale **{self.scale:.3f}** map px per frame "
            f"px ({self.source})"
        )


COINCIDENT_PX = 1e-6
"""Seed pairs closer than this (corrected frame px, or map px) fix no heading."""


def _heading(angle_deg: float) -> float:
    """An angle in [0, 360), rounded so that 360 - 1e-12 shows as 0."""
    a = float(angle_deg) % 360.0
    return 0.0 if a >= 360.0 - 1e-9 else a


def heading_from_pairs(seed, seed2, gamma: float, frame_size) -> HeadingScale | None:
    """Heading and scale that two seed pairs fix: the library's
    :func:`registration.global_registration.prior_from_seeds` between corrected frame points and
    map points, as the coarse step builds it; None for coincident or undefined points.

    The library refuses pairs less than 1 px apart (they cannot seed a fit); the panel has always
    shown the heading and scale of any two pairs more than :data:`COINCIDENT_PX` apart. To keep
    that, the pairs' offsets are handed over scaled by a power of two, which leaves heading and
    scale unchanged bit for bit (the coarse step still refuses such pairs, with its reason)."""
    if seed is None or seed2 is None:
        return None
    camera = Camera(gamma, *frame_size)
    f = camera.corrected_from_raw(np.array([seed[:2], seed2[:2]], float))
    b = np.array([seed[2:], seed2[2:]], float)
    df, db = f[1] - f[0], b[1] - b[0]
    nf, nb = math.hypot(*df), math.hypot(*db)
    if not (np.isfinite([nf, nb]).all() and nf > COINCIDENT_PX and nb > COINCIDENT_PX):
        return None
    s = 1.0
    while min(nf, nb) * s < 1.0:  # a power of two: the scaled offsets are exact
        s *= 2.0
    prior = global_registration.prior_from_seeds([(0.0, 0.0), s * df], [(0.0, 0.0), s * db])
    return HeadingScale(_heading(prior.heading_deg), prior.scale, "fixed by the two pairs")


GATE_SOURCES = {
    "seed": "estimated from the click",
    "two seeds": "fixed by the two pairs",
    "no seed": "searched without a seed",
}


def heading_from_coarse(coarse) -> HeadingScale | None:
    """The heading and scale the coarse step used (``CoarseResult.heading_deg``, ``.scale``;
    also on a failed step when it got that far), with how it came by them; None without."""
    if coarse is None:
        return None
    heading, scale = coarse.heading_deg, coarse.scale
    if heading is None or scale is None:
        return None
    source = GATE_SOURCES.get(coarse.gate, coarse.gate or "coarse step")
    if coarse.gate == "seed" and coarse.ambiguity:
        source += f"; ambiguity {coarse.ambiguity:.2f}"
    confirm = coarse.image_agreement
    if confirm is not None:
        # How strongly the images confirm it (CoarseConfig.max_chance_p refuses on this).
        source += f"; {confirm.agreeing} of {confirm.matched} map templates agree"
    return HeadingScale(_heading(heading), float(scale), source)


TYPED_SEED_DISTANCE_PX = 100.0
"""How far (corrected frame px) from the seed the second pair made from a typed heading and
scale lies."""


def second_seed_from_similarity(
    seed, heading_deg: float, scale: float, gamma: float, frame_size
) -> tuple[float, float, float, float]:
    """A second seed pair that fixes ``heading_deg`` and ``scale`` (as
    :func:`heading_from_pairs` reads them): a frame point :data:`TYPED_SEED_DISTANCE_PX`
    corrected px from the seed towards the frame centre (along +x from the centre itself), and
    where the similarity through the seed puts it on the map. Raw frame px, base px.

    Raises:
        ValueError: scale not positive, or a value not finite.
    """
    if not (math.isfinite(heading_deg) and math.isfinite(scale) and scale > 0):
        raise ValueError(
            f"heading must be finite and scale positive, got {heading_deg!r}, {scale!r}"
        )
    w, h = frame_size
    camera = Camera(gamma, w, h)
    c1 = camera.corrected_from_raw(np.array([seed[:2]], float))[0]
    towards = np.array([(w - 1) / 2.0, (h - 1) / 2.0]) - c1
    n = math.hypot(*towards)
    step = towards / n if n > 1.0 else np.array([1.0, 0.0])
    c2 = c1 + TYPED_SEED_DISTANCE_PX * step
    t = math.radians(heading_deg)
    rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    b2 = np.asarray(seed[2:], float) + scale * rot @ (c2 - c1)
    f2 = camera.raw_from_corrected(c2[None])[0]
    return (float(f2[0]), float(f2[1]), float(b2[0]), float(b2[1]))


def forget_frame(out_dir: str | Path, k: int) -> None:
    """Remove frame ``k``'s record from a result folder, so that resuming the run registers it
    again (the folder's contract: a frame without a record is pending)."""
    for suffix in (".json", ".npz"):
        frame_record_path(Path(out_dir), k, suffix).unlink(missing_ok=True)


def rerun_settings(result) -> dict:
    """What ``pipeline.register_sequence`` needs to resume ``result``'s own run: its γ, seed,
    reference frame, preset name and configuration (not the app's current choices)."""
    meta = result.meta
    seed = meta.get("seed")
    if seed is not None:
        arr = np.asarray(seed, float)
        seed = tuple(arr.tolist()) if arr.ndim == 1 else [tuple(row) for row in arr.tolist()]
    return {
        "gamma": float(result.gamma),
        "seed": seed,
        "reference_frame": int(result.reference_frame),
        "preset": result.preset,
        "config": pipeline.load_config(result.out_dir),
    }

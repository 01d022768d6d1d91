"""The app's calls into ``registration`` that need a little glue: the run's configuration from the
app's choices, the coarse step with one or two seed pairs, the heading and scale the analyst sees
after seeding, and re-running one frame of a result.

Kept apart from the views so that they stay drawing and widgets, and so that what the app
expects of the library is in one place (see the report to the lead: ``CoarseResult.heading_deg``,
``.scale``, a second seed pair).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from registration import config as rconfig
from registration import global_registration, pipeline
from registration.distortion import HarrisModel
from registration.result import frame_record_path


def pipeline_config(preset: str, degree: int, run_local: bool) -> rconfig.PipelineConfig:
    """The preset with the app's transform choice: polyprojective ``degree`` (1 = projective)
    for the reference and every frame, and the local displacement field on or off."""
    cfg = rconfig.get_preset(preset)
    fine = dataclasses.replace(cfg.fine, degree=int(degree))
    return dataclasses.replace(cfg, fine=fine, run_local=bool(run_local))


def seed_argument(seed, seed2):
    """The library's ``seed`` argument from the analyst's pairs: None, one ``(fx, fy, bx, by)``,
    or both (two pairs fix heading and scale)."""
    if seed is None:
        return None
    return seed if seed2 is None else [tuple(seed), tuple(seed2)]


def supports_second_seed() -> bool:
    """The coarse step takes a second seed pair (it fixes heading and scale exactly)."""
    return True


def coarse_register(frame, base, gamma, seed, seed2, config, base_valid=None):
    """The coarse step (paper 4.3.1) with the seed pairs the analyst placed."""
    return global_registration.coarse_register(
        frame, base, gamma, seed_argument(seed, seed2), config, base_valid=base_valid
    )


@dataclasses.dataclass(frozen=True)
class HeadingScale:
    """Rotation frame -> base (degrees, image coordinates: x right, y down, positive = clockwise
    on screen) and scale (base px per corrected frame px), and where they come from."""

    heading_deg: float
    scale: float
    source: str

    def text(self) -> str:
        return f"heading {self.heading_deg:+.1f}°, scale {self.scale:.3f} map px per frame px ({self.source})"


def heading_from_pairs(seed, seed2, gamma: float, frame_size) -> HeadingScale | None:
    """Heading and scale that two seed pairs fix (a similarity through both pairs), from the
    corrected frame points; None for coincident points."""
    if seed is None or seed2 is None:
        return None
    harris = HarrisModel(gamma, *frame_size)
    f = harris.corrected_from_raw(np.array([seed[:2], seed2[:2]], float))
    b = np.array([seed[2:], seed2[2:]], float)
    df, db = f[1] - f[0], b[1] - b[0]
    nf, nb = math.hypot(*df), math.hypot(*db)
    if nf < 1e-6 or nb < 1e-6:
        return None
    angle = math.degrees(math.atan2(db[1], db[0]) - math.atan2(df[1], df[0]))
    angle = (angle + 180.0) % 360.0 - 180.0
    return HeadingScale(angle, nb / nf, "from the two seed pairs")


def heading_from_coarse(coarse, seed, gamma: float, frame_size) -> HeadingScale | None:
    """Heading and scale of a coarse result: the library's own (``heading_deg``, ``scale``) when
    it reports them, else the local rotation and scale of its projective model at the seed."""
    if coarse is None or not coarse:
        return None
    heading = getattr(coarse, "heading_deg", None)
    scale = getattr(coarse, "scale", None)
    if heading is not None and scale is not None:
        return HeadingScale(float(heading), float(scale), "coarse step")
    model = coarse.base_from_corrected
    if model is None:
        return None
    w, h = frame_size
    at = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    if seed is not None:
        at = HarrisModel(gamma, w, h).corrected_from_raw(np.array([seed[:2]], float))[0]
    eps = 1.0
    pts = np.array([at, at + (eps, 0.0), at + (0.0, eps)])
    q = model.apply(pts)
    if not np.isfinite(q).all():
        return None
    jx, jy = (q[1] - q[0]) / eps, (q[2] - q[0]) / eps
    scale = math.sqrt(abs(jx[0] * jy[1] - jx[1] * jy[0]))
    heading = math.degrees(math.atan2(jx[1], jx[0]))
    return HeadingScale(heading, scale, "coarse model at the seed")


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

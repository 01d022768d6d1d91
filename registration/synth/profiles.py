"""Named simulator profiles (hard flights the pipeline was not tuned on) and the measurements
that check each profile delivers what it claims.

``PROFILES[name]`` is a :class:`Profile`; calling it gives a :class:`SimConfig`, with any field
overridden: ``PROFILES["paper-hard"](frame_size=(640, 480), seed=3)``. Values given in pixels at
the paper's frame size (2560x1920, table 1) are scaled with the frame width, so a profile is the
same flight at any frame size (angles, times and lens terms in normalised radius need no
scaling).

Measurements (all from the exact truth, no rendering needed):

* :func:`motion_stats`: the paper's table 2 "Unregistered" figure (5 ground points, NW, NE,
  centre, SW, SE of the reference frame, followed in radially corrected coordinates over 10
  frames spread evenly over the flight; μ and σ of their distance from where they were in the
  reference frame), the motion between consecutive frames, the camera's rotation between
  consecutive frames (shake), and how much of the reference frame's ground the last frame sees.
* :func:`camera.best_harris_fit`: how far the best one-parameter Harris model lands from the lens.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from registration.synth.camera import SequenceGeometry
from registration.synth.config import SimConfig
from registration.synth.plan import (
    TABLE2_NAMES,
    TABLE2_POINTS,
    interframe_rotation_deg,
    unregistered_motion,
)

PAPER_FRAME_WIDTH = 2560


@dataclass(frozen=True)
class Profile:
    """A named flight: :class:`SimConfig` overrides, some of them scaled with the frame size.

    Attributes:
        name: the profile's name (``--profile NAME``).
        summary: one line: what the flight is and what it tests.
        values: SimConfig overrides (fixed values).
        paper_px: SimConfig fields given at the paper's frame width (2560 px) and scaled by
            ``frame_width / 2560`` (e.g. drift in metres, which moves the image by
            drift/altitude x focal, both proportional to the frame width at a fixed frame scale).
        targets: what the profile is meant to deliver, in the units of :func:`motion_stats`
            (documentation; the tests check them).
    """

    name: str
    summary: str
    values: dict = field(default_factory=dict)
    paper_px: dict = field(default_factory=dict)
    targets: dict = field(default_factory=dict)

    def __call__(self, **overrides) -> SimConfig:
        """The profile's :class:`SimConfig`; ``overrides`` replace any field (also scaled ones)."""
        unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(SimConfig)})
        if unknown:
            raise ValueError(f"unknown SimConfig field {unknown[0]!r} for profile {self.name!r}")
        base = SimConfig(**{**self.values, **{k: v for k, v in overrides.items()}})
        width = base.frame_size[0]
        scaled = {
            k: v * width / PAPER_FRAME_WIDTH for k, v in self.paper_px.items() if k not in overrides
        }
        return dataclasses.replace(base, **scaled)


PROFILES: dict[str, Profile] = {
    p.name: p
    for p in (
        Profile(
            "default",
            "the project's default flight (the hover the pipeline was tuned on), for comparison",
        ),
        Profile(
            "paper-hard",
            "the paper's camera at its worst: ~93 +- 50 px unregistered motion (table 2) at "
            "2560x1920, 0.6 deg shake between frames, 0.15 s rolling shutter, a lens that is not "
            "exactly Harris (gamma 0.7 nominal), 10 deg heading and 20 % scale to the base",
            values=dict(
                n_frames=50,
                gamma=0.7,
                # Not Harris: ~7 px at 2560x1920 after the best one-parameter fit.
                lens_k2=0.04,
                # A slow CMOS readout: 75 % of the frame interval at 5 fps.
                rolling_shutter_s=0.15,
                # Paper 4.3.1/4.3.2: ~10 deg orientation and ~20 % scale difference to the base.
                heading_deg=10.0,
                frame_scale=1.2,
                # The jitter is scaled so the largest rotation between frames is exactly this.
                shake_deg=0.6,
                jitter_deg=0.3,
                # Slow attitude wander (periods 10-30 s) carries the table-2 motion without
                # breaking the 0.6 deg shake bound.
                wander_deg=1.5,
                wander_hz=(0.035, 0.1),
                yaw_deg=3.0,
            ),
            # Table 2, "Unregistered", average over the 5 locations: 93.3 +- 50.3 px at
            # 2560x1920. The drift and wander (shape as drawn from the seed) are scaled so the
            # mean is exactly 93.3 px (scaled with the frame width); the spread follows.
            paper_px=dict(drift_m=23.0, unregistered_px=93.3),
            targets=dict(
                unregistered_mean_px_at_2560=93.3,
                unregistered_std_px_at_2560=50.3,
                shake_max_deg=0.6,
                harris_fit_corner_px_at_2560=7.0,
            ),
        ),
        Profile(
            "long-flight",
            "a 120-frame straight flyover (24 s at 5 fps): the view leaves the first frame's "
            "footprint entirely (1.5 footprints of travel), moderate shake, slow yaw",
            values=dict(
                n_frames=120,
                flyover_footprints=1.5,
                shake_deg=0.3,
                jitter_deg=0.3,
                wander_deg=0.3,
                wander_hz=(0.05, 0.2),
                yaw_deg=10.0,
            ),
            paper_px=dict(drift_m=10.0),
            targets=dict(last_frame_sees_of_first=0.0, shake_max_deg=0.3),
        ),
    )
}


def profile_config(name: str, **overrides) -> SimConfig:
    """``PROFILES[name](**overrides)`` with a one-line error naming the known profiles."""
    if name not in PROFILES:
        raise ValueError(f"unknown profile {name!r}; choose from {', '.join(PROFILES)}")
    return PROFILES[name](**overrides)


# ------------------------------------------------------------------------------------------
# Measurements


def _geometry_of(truth_or_geometry) -> SequenceGeometry:
    return getattr(truth_or_geometry, "geometry", truth_or_geometry)


def seen_fraction(geom: SequenceGeometry, k: int, ref: int = 0, step: int = 8) -> float:
    """Share of frame ``k``'s ground (raw pixels ``step`` apart, border included) that frame
    ``ref`` also sees."""
    w, h = geom.width, geom.height
    xs = np.unique(np.r_[np.arange(0, w, step), w - 1]).astype(float)
    ys = np.unique(np.r_[np.arange(0, h, step), h - 1]).astype(float)
    gx, gy = np.meshgrid(xs, ys)
    raw = np.column_stack([gx.ravel(), gy.ravel()])
    scene = geom.scene_from_raw(k, raw)
    back = geom.raw_from_scene(ref, scene)
    return float(np.mean(np.isfinite(back).all(axis=1) & geom.in_frame(back)))


def motion_stats(truth_or_geometry, ref: int = 0, n_samples: int = 10) -> dict:
    """Motion figures of a simulated flight (see the module docstring).

    Returns:
        ``unregistered``: per table-2 location ``{name: (μ, σ)}`` px and ``mean``/``std`` (the
        averages over the locations, table 2's "Average" column), in radially corrected pixels
        of the nominal Harris γ (what a registration sees after the paper's correction);
        ``interframe_px``: mean and max over consecutive frames of the distance a ground point
        (the 5 locations) moves in the frame; ``shake_deg``: mean and max rotation of the camera
        between consecutive frames (mid-exposure); ``last_sees_of_ref``: share of the last frame's
        ground that frame ``ref`` sees.
    """
    geom = _geometry_of(truth_or_geometry)
    k_all = geom.n_frames
    w, h = geom.width, geom.height
    pts = TABLE2_POINTS * [w - 1, h - 1]
    d, sample = unregistered_motion(geom, ref, n_samples)
    mu, sd = np.nanmean(d, axis=0), np.nanstd(d, axis=0)
    # Consecutive frames: the same ground points, in raw pixels of both frames.
    ks = np.repeat(np.arange(k_all - 1), len(pts))
    tiled = np.tile(pts, (k_all - 1, 1))
    moved = geom.raw_from_scene(ks + 1, geom.scene_from_raw(ks, tiled))
    steps = np.linalg.norm(moved - tiled, axis=1)
    times = geom.frame_times + 0.5 * geom.readout_s
    shake = interframe_rotation_deg(geom.pose, times) if k_all > 1 else np.zeros(0)
    return {
        "unregistered": {
            "frames": sample,
            **{n: (float(m), float(s)) for n, m, s in zip(TABLE2_NAMES, mu, sd, strict=True)},
            "mean": float(np.mean(mu)),
            "std": float(np.mean(sd)),
        },
        "interframe_px": {"mean": float(np.nanmean(steps)), "max": float(np.nanmax(steps))},
        "shake_deg": {"mean": float(shake.mean()), "max": float(shake.max())},
        "last_sees_of_ref": seen_fraction(geom, k_all - 1, ref),
    }


def describe(profile: Profile | str, frame_size=(640, 480), seeds=(0, 1, 2)) -> dict:
    """Measured properties of a profile at ``frame_size`` over ``seeds`` (planning only, no
    rendering): the :func:`motion_stats` figures (means over the seeds, maxima where the
    profile promises a bound) and the best one-parameter Harris fit to its lens."""
    from registration.synth.camera import SimLens, best_harris_fit
    from registration.synth.plan import plan_procedural

    prof = PROFILES[profile] if isinstance(profile, str) else profile
    rows = [
        motion_stats(plan_procedural(prof(frame_size=tuple(frame_size), seed=seed)))
        for seed in seeds
    ]

    def mean(*keys: str) -> float:
        vals = []
        for r in rows:
            v = r
            for k in keys:
                v = v[k]
            vals.append(v)
        return float(np.mean(vals))

    cfg = prof(frame_size=tuple(frame_size))
    return {
        "profile": prof.name,
        "frame_size": list(frame_size),
        "seeds": list(seeds),
        "unregistered_mean_px": mean("unregistered", "mean"),
        "unregistered_std_px": mean("unregistered", "std"),
        "interframe_mean_px": mean("interframe_px", "mean"),
        "interframe_max_px": max(r["interframe_px"]["max"] for r in rows),
        "shake_mean_deg": mean("shake_deg", "mean"),
        "shake_max_deg": max(r["shake_deg"]["max"] for r in rows),
        "last_sees_of_first_max": max(r["last_sees_of_ref"] for r in rows),
        "harris_fit": best_harris_fit(SimLens(cfg.gamma, cfg.lens_k2, *cfg.frame_size)),
    }

"""Planning a flight: the helicopter's pose track, the terrain, the camera geometry, and the
extent of the scene every frame sees (paper sections 2 and 4.2)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from registration.synth.camera import (
    PoseTrack,
    SequenceGeometry,
    SimLens,
    Terrain,
    apply_homography,
    focal_for_fov,
)
from registration.synth.config import MAX_CITY_PIXELS, SimConfig

# Pixels of the base/scene kept clear around every frame's footprint (interpolation support and
# the optical blur).
FOOTPRINT_MARGIN_PX = 4.0
# A scene's fitted frame scale (scene px per frame px) is refused below this: a 120-frame
# flight at 320x240 over a 1630x1948 px drone photo fitted at 0.6, frames the photo upsampled
# 1.7x in which nothing could be registered (119 of 120 frames failed), a flaw of the
# simulation rather than of the pipeline.
MIN_FITTED_FRAME_SCALE = 0.7
# The paper's table 2 locations as fractions of the frame (NW, NE, centre, SW, SE): near the
# corners, on the ground, inside the frame.
TABLE2_POINTS = np.array([[0.1, 0.1], [0.9, 0.1], [0.5, 0.5], [0.1, 0.9], [0.9, 0.9]])
TABLE2_NAMES = ("NW", "NE", "Center", "SW", "SE")


@dataclass(frozen=True)
class PoseParts:
    """The drawn components of a pose track, kept apart so that the slow motion and the jitter
    can be scaled to targets (``cfg.unregistered_px``, ``cfg.shake_deg``) without redrawing."""

    origin: NDArray
    drift_velocity: NDArray
    flyover_velocity: NDArray
    pos_amp: NDArray
    pos_freq: NDArray
    pos_phase: NDArray
    angles0: NDArray
    angle_rate: NDArray
    wander_amp: NDArray
    jitter_amp: NDArray
    ang_freq: NDArray
    ang_phase: NDArray

    def assemble(self, slow: float = 1.0, jitter: float = 1.0) -> PoseTrack:
        """The pose with the slow motion (drift and attitude wander) scaled by ``slow`` and the
        high-frequency jitter by ``jitter``; the flyover, heading and yaw are kept."""
        return PoseTrack(
            origin=self.origin,
            velocity=self.drift_velocity * slow + self.flyover_velocity,
            pos_amp=self.pos_amp * slow,
            pos_freq=self.pos_freq,
            pos_phase=self.pos_phase,
            angles0=self.angles0,
            angle_rate=self.angle_rate,
            ang_amp=np.concatenate([self.wander_amp * slow, self.jitter_amp * jitter], axis=1),
            ang_freq=self.ang_freq,
            ang_phase=self.ang_phase,
        )


def draw_pose(
    cfg: SimConfig,
    origin_xy: tuple[float, float],
    altitude_m: float,
    focal_px: float | None = None,
) -> PoseParts:
    """Draw the helicopter's motion from ``cfg.seed``: linear drift plus slow sinusoids in
    position (plus a straight flyover, ``cfg.flyover_footprints``, which needs ``focal_px``, the
    corrected focal length); a fixed heading, slow yaw, low-frequency wander and high-frequency
    jitter in angle."""
    rng = np.random.default_rng([cfg.seed, 11])
    duration = cfg.n_frames / cfg.fps
    d = np.radians
    direction = rng.uniform(0, 2 * np.pi)
    # Half the drift is linear, half slow oscillation, so the path is not a straight line.
    speed = 0.6 * cfg.drift_m / max(duration, 1e-6)
    velocity = np.array(
        [speed * np.cos(direction), speed * np.sin(direction), 0.05 * speed * rng.normal()]
    )
    pos_amp = np.abs(rng.normal(0, 0.25 * cfg.drift_m, (3, 2))) * np.array([[1.0], [1.0], [0.2]])
    pos_freq = rng.uniform(0.15, 0.6, (3, 2)) / max(duration, 1.0)  # 0.15-0.6 cycles per sequence
    pos_phase = rng.uniform(0, 2 * np.pi, (3, 2))
    sign = 1.0 if rng.random() < 0.5 else -1.0
    angles0 = np.array([d(rng.normal(0, 0.5)), d(rng.normal(0, 0.5)), d(sign * cfg.heading_deg)])
    angle_rate = np.array(
        [0.0, 0.0, d(cfg.yaw_deg) / max(duration, 1e-6) * (1 if rng.random() < 0.5 else -1)]
    )
    # Columns: 2 slow wander terms, 3 jitter terms; yaw jitters less than roll and pitch.
    amp = np.empty((3, 5))
    amp[:, :2] = d(cfg.wander_deg) / np.sqrt(2) * rng.uniform(0.6, 1.4, (3, 2))
    amp[:, 2:] = d(cfg.jitter_deg) / np.sqrt(3) * rng.uniform(0.6, 1.4, (3, 3))
    amp[2] *= 0.3
    freq = np.concatenate(
        [rng.uniform(*cfg.wander_hz, (3, 2)), rng.uniform(*cfg.jitter_hz, (3, 3))], axis=1
    )
    phase = rng.uniform(0, 2 * np.pi, (3, 5))
    flyover = np.zeros(3)
    if cfg.flyover_footprints > 0 and cfg.n_frames > 1:
        # Own random stream: a hover draws exactly what it drew before flyovers existed.
        heading = np.random.default_rng([cfg.seed, 13]).uniform(0, 2 * np.pi)
        u = np.array([np.cos(heading), np.sin(heading)])
        extent = _footprint_extent_m(cfg, altitude_m, focal_px, float(angles0[2]), u)
        flyover[:2] = u * cfg.flyover_footprints * extent * cfg.fps / (cfg.n_frames - 1)
    return PoseParts(
        origin=np.array([origin_xy[0], origin_xy[1], -altitude_m]),
        drift_velocity=velocity,
        flyover_velocity=flyover,
        pos_amp=pos_amp,
        pos_freq=pos_freq,
        pos_phase=pos_phase,
        angles0=angles0,
        angle_rate=angle_rate,
        wander_amp=amp[:, :2],
        jitter_amp=amp[:, 2:],
        ang_freq=freq,
        ang_phase=phase,
    )


def make_pose(
    cfg: SimConfig,
    origin_xy: tuple[float, float],
    altitude_m: float,
    focal_px: float | None = None,
) -> PoseTrack:
    """The pose track drawn by :func:`draw_pose`, its jitter scaled to ``cfg.shake_deg`` when
    given (the slow-motion target ``cfg.unregistered_px`` needs the whole geometry and is met in
    :func:`plan_procedural` / :func:`plan_scene`)."""
    parts = draw_pose(cfg, origin_xy, altitude_m, focal_px)
    jitter = _jitter_for_shake(parts, cfg, 1.0) if cfg.shake_deg is not None else 1.0
    return parts.assemble(1.0, jitter)


def _footprint_extent_m(
    cfg: SimConfig, altitude_m: float, focal_px: float | None, yaw: float, u: NDArray
) -> float:
    """Length (m) of a nadir frame's ground footprint along the unit direction ``u``."""
    if focal_px is None:
        raise ValueError("a flyover needs the camera's focal length")
    w, h = cfg.frame_size
    lens = SimLens(cfg.gamma, cfg.lens_k2, int(w), int(h))
    s = np.linspace(0.0, 1.0, 33)
    border = np.concatenate(
        [
            np.column_stack([s * (w - 1), np.zeros_like(s)]),
            np.column_stack([s * (w - 1), np.full_like(s, h - 1.0)]),
            np.column_stack([np.zeros_like(s), s * (h - 1)]),
            np.column_stack([np.full_like(s, w - 1.0), s * (h - 1)]),
        ]
    )
    cam = (lens.corrected_from_raw(border) - lens.c) / focal_px * altitude_m
    c, sn = math.cos(yaw), math.sin(yaw)
    ground = cam @ np.array([[c, -sn], [sn, c]]).T
    proj = ground @ u
    return float(proj.max() - proj.min())


def interframe_rotation_deg(pose: PoseTrack, times: NDArray) -> NDArray[np.float64]:
    """``(K-1,)`` rotation angle (degrees) of the camera between consecutive ``times``."""
    r = pose.rotation(times)
    rel = np.einsum("kji,kjl->kil", r[:-1], r[1:])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def _solve_increasing(fn, target: float, what: str) -> float:
    """``x >= 0`` with ``fn(x) = target`` for a function increasing from ``fn(0) <= target``
    (bracket by doubling, then Brent's method to 1e-12)."""
    from scipy.optimize import brentq

    lo, hi = 0.0, 1.0
    while fn(hi) < target:
        lo, hi = hi, hi * 2.0
        if hi > 1e6:
            raise ValueError(f"{what} {target:g} cannot be reached")
    if fn(hi) == target:
        return hi
    return float(brentq(lambda x: fn(x) - target, lo, hi, xtol=1e-13, rtol=1e-12))


def _jitter_for_shake(parts: PoseParts, cfg: SimConfig, slow: float) -> float:
    """Jitter scale that makes the largest rotation between consecutive frames (mid-exposure)
    exactly ``cfg.shake_deg``."""
    times = np.arange(cfg.n_frames) / cfg.fps + 0.5 * cfg.rolling_shutter_s
    target = float(cfg.shake_deg)

    def peak(f: float) -> float:
        return float(interframe_rotation_deg(parts.assemble(slow, f), times).max())

    floor = peak(0.0)
    if floor > target:
        if cfg.unregistered_px is not None:
            raise ValueError(
                f"shake_deg {target:g} cannot be met: moving {cfg.unregistered_px:g} px "
                f"(unregistered_px) within {cfg.n_frames} frames takes slow motion that alone "
                f"turns the camera by {floor:.3f} deg between frames; use more frames (paper-hard "
                "needs ~15) or drop unregistered_px"
            )
        raise ValueError(
            f"shake_deg {target:g} is below what the slow motion alone gives ({floor:.3f} deg "
            "between frames from wander, yaw and drift); lower wander_deg, yaw_deg or wander_hz"
        )
    return _solve_increasing(peak, target, "shake_deg")


def unregistered_motion(
    geom: SequenceGeometry, ref: int = 0, n_samples: int = 10
) -> tuple[NDArray[np.float64], list[int]]:
    """The paper's table-2 "Unregistered" distances: ``(S, 5)`` px for 5 ground points (NW, NE,
    centre, SW, SE of frame ``ref``, :data:`TABLE2_POINTS`) in ``S`` frames spread evenly over
    the flight (``ref`` left out), measured in radially corrected coordinates (nominal Harris γ)
    from where the points were in frame ``ref``; and the sampled frames."""
    w, h = geom.width, geom.height
    harris = geom.lens.harris
    pts = TABLE2_POINTS * [w - 1, h - 1]
    ground = geom.scene_from_raw(ref, pts)
    others = [k for k in range(geom.n_frames) if k != ref]
    if not others:
        raise ValueError("motion statistics need at least two frames")
    idx = np.unique(np.round(np.linspace(0, len(others) - 1, min(n_samples, len(others)))))
    sample = [others[int(i)] for i in idx]
    ref_pos = harris.corrected_from_raw(pts)
    # One batched solve: raw_from_scene takes a frame index per point.
    ks = np.repeat(np.asarray(sample), len(pts))
    raw = geom.raw_from_scene(ks, np.tile(ground, (len(sample), 1)))
    track = harris.corrected_from_raw(raw).reshape(len(sample), len(pts), 2)
    return np.linalg.norm(track - ref_pos, axis=2), sample


def make_terrain(cfg: SimConfig) -> Terrain:
    """A smooth height field of amplitude ``cfg.terrain_m`` with 250-900 m wavelengths."""
    rng = np.random.default_rng([cfg.seed, 12])
    k = 4
    wavelength = rng.uniform(250, 900, k)
    theta = rng.uniform(0, np.pi, k)
    kmag = 2 * np.pi / wavelength
    return Terrain(
        amp=cfg.terrain_m / np.sqrt(k) * rng.uniform(0.7, 1.3, k),
        kx=kmag * np.cos(theta),
        ky=kmag * np.sin(theta),
        phase=rng.uniform(0, 2 * np.pi, k),
    )


def _geometry(
    cfg: SimConfig, scale: float, origin_xy, scene_size, base_size, base_from_scene
) -> SequenceGeometry:
    """The sequence's geometry for a camera at ``scale`` over ``origin_xy``, with the motion
    targets (``cfg.unregistered_px``, ``cfg.shake_deg``) met."""
    w, h = cfg.frame_size
    f = focal_for_fov(w, h, cfg.gamma, cfg.fov_deg, cfg.lens_k2)
    altitude = scale * cfg.gsd_m * f
    parts = draw_pose(cfg, origin_xy, altitude, f)
    geom = SequenceGeometry(
        width=int(w),
        height=int(h),
        gamma=float(cfg.gamma),
        focal_px=f,
        readout_s=float(cfg.rolling_shutter_s),
        frame_times=np.arange(cfg.n_frames) / cfg.fps,
        pose=parts.assemble(),
        terrain=make_terrain(cfg),
        scene_gsd=float(cfg.gsd_m),
        scene_size=tuple(int(v) for v in scene_size),
        base_size=tuple(int(v) for v in base_size),
        base_from_scene=np.asarray(base_from_scene, np.float64),
        lens_k2=float(cfg.lens_k2),
    )
    if cfg.n_frames < 2 or (cfg.shake_deg is None and cfg.unregistered_px is None):
        return geom
    slow, jitter = 1.0, 1.0
    if cfg.unregistered_px is None:
        jitter = _jitter_for_shake(parts, cfg, slow)
    else:
        target = float(cfg.unregistered_px)

        def mean_motion(x: float) -> float:
            g = dataclasses.replace(geom, pose=parts.assemble(x, jitter))
            return float(np.nanmean(unregistered_motion(g)[0]))

        # The two targets are weakly coupled (the jitter adds a little motion, the wander a
        # little shake): alternate until the motion is within 1e-6 of its target, the shake
        # (solved last) exact.
        for _ in range(8):
            floor = mean_motion(0.0)
            if floor > target:
                raise ValueError(
                    f"unregistered_px {target:g} is below what the jitter, yaw and flyover alone "
                    f"give ({floor:.1f} px); lower jitter_deg/shake_deg, yaw_deg or the flyover"
                )
            slow = _solve_increasing(mean_motion, target, "unregistered_px")
            if cfg.shake_deg is not None:
                jitter = _jitter_for_shake(parts, cfg, slow)
            if abs(mean_motion(slow) - target) <= 1e-6 * target:
                break
    return dataclasses.replace(geom, pose=parts.assemble(slow, jitter))


def footprints(geom: SequenceGeometry) -> NDArray[np.float64]:
    """``(K, 4)`` per frame: min x, min y, max x, max y of the footprint in scene pixels."""
    border = geom.border_points()
    out = np.empty((geom.n_frames, 4))
    for k in range(geom.n_frames):
        s = geom.scene_from_raw(k, border)
        if not np.isfinite(s).all():
            out[k] = np.nan
        else:
            out[k] = [*s.min(axis=0), *s.max(axis=0)]
    return out


def check_footprint(geom: SequenceGeometry) -> None:
    """Raise a one-line ValueError if any frame sees outside the scene or the base map."""
    border = geom.border_points()
    m = FOOTPRINT_MARGIN_PX
    sw, sh = geom.scene_size
    bw, bh = geom.base_size
    for k in range(geom.n_frames):
        s = geom.scene_from_raw(k, border)
        if not np.isfinite(s).all():
            raise ValueError(
                f"frame {k} sees the horizon; reduce gamma, the field of view or the tilt"
            )
        lo, hi = s.min(axis=0), s.max(axis=0)
        if lo[0] < m or lo[1] < m or hi[0] > sw - 1 - m or hi[1] > sh - 1 - m:
            raise ValueError(
                f"the camera sees outside the scene in frame {k}: footprint x {lo[0]:.0f}..{hi[0]:.0f}, "
                f"y {lo[1]:.0f}..{hi[1]:.0f} px but the scene is {sw}x{sh} px "
                "(use a smaller frame size or frame scale, less drift, or a larger scene)"
            )
        b = apply_homography(geom.base_from_scene, s)
        lo, hi = np.nanmin(b, axis=0), np.nanmax(b, axis=0)
        if (
            not np.isfinite(b).all()
            or lo[0] < m
            or lo[1] < m
            or hi[0] > bw - 1 - m
            or hi[1] > bh - 1 - m
        ):
            raise ValueError(
                f"the camera sees outside the base map in frame {k}: footprint x {lo[0]:.0f}..{hi[0]:.0f}, "
                f"y {lo[1]:.0f}..{hi[1]:.0f} base px but the base is {bw}x{bh} px "
                "(use a smaller frame size or frame scale, less drift, or a larger base)"
            )


def plan_procedural(cfg: SimConfig) -> SequenceGeometry:
    """Camera and city extent for the procedural city: the city is centred on the footprint of
    the whole sequence (``cfg.city_size`` fixed, or just large enough when None)."""
    scale = cfg.frame_scale if cfg.frame_scale is not None else 1.1
    pad = FOOTPRINT_MARGIN_PX + 8.0
    size = (10**6, 10**6) if cfg.city_size is None else tuple(int(v) for v in cfg.city_size)
    origin = np.zeros(2)
    # Place the camera so the footprint of the whole sequence is centred on the city; the terrain
    # moves the footprint a little when the camera moves, hence a few rounds.
    for _ in range(4):
        geom = _geometry(cfg, scale, (float(origin[0]), float(origin[1])), size, size, np.eye(3))
        fp = footprints(geom)
        if not np.isfinite(fp).all():
            raise ValueError(
                "a frame sees the horizon; reduce gamma, the field of view or the tilt"
            )
        lo, hi = fp[:, :2].min(axis=0), fp[:, 2:].max(axis=0)
        if cfg.city_size is None:
            need = np.ceil((hi - lo + 2 * pad) / 16.0).astype(int) * 16
            if (
                size[0] < 10**6
                and np.all(need <= np.array(size))
                and np.all(lo >= pad - 2)
                and np.all(hi <= np.array(size) - 1 - pad + 2)
            ):
                break
            size = (
                int(max(need[0], size[0] if size[0] < 10**6 else 0)),
                int(max(need[1], size[1] if size[1] < 10**6 else 0)),
            )
        origin = origin + ((np.array(size) - 1) / 2.0 - (lo + hi) / 2.0) * cfg.gsd_m
    if size[0] * size[1] > MAX_CITY_PIXELS:
        raise ValueError(
            f"the flight needs a procedural city of {size[0]}x{size[1]} px "
            f"({size[0] * size[1] / 1e6:.0f} MP), over the limit of {MAX_CITY_PIXELS / 1e6:.0f} MP "
            "(~45 bytes of memory per city pixel); use a smaller frame size or frame scale, a "
            "shorter flyover or less drift"
        )
    geom = _geometry(cfg, scale, (float(origin[0]), float(origin[1])), size, size, np.eye(3))
    check_footprint(geom)
    return geom


def plan_scene(cfg: SimConfig, scene_size, base_size, base_from_scene) -> SequenceGeometry:
    """Camera over a user scene, centred on it; with ``frame_scale=None`` the largest scale
    <= 1.1 whose footprint fits the scene and the base (with margin), refused below
    :data:`MIN_FITTED_FRAME_SCALE`."""
    sw, sh = scene_size
    centre = ((sw - 1) / 2.0 * cfg.gsd_m, (sh - 1) / 2.0 * cfg.gsd_m)
    if cfg.frame_scale is not None:
        scale = cfg.frame_scale
    else:
        scale = 1.1
        for _ in range(4):
            g = _geometry(cfg, scale, centre, scene_size, base_size, base_from_scene)
            fp = footprints(g)
            if not np.isfinite(fp).all():
                break
            lo, hi = fp[:, :2].min(axis=0), fp[:, 2:].max(axis=0)
            half_need = np.maximum(
                (np.array([sw, sh]) - 1) / 2.0 - lo, hi - (np.array([sw, sh]) - 1) / 2.0
            )
            avail = (np.array([sw, sh]) - 1) / 2.0 - FOOTPRINT_MARGIN_PX - 8.0
            ratio = float(np.min(avail / half_need))
            if ratio >= 1.0 and scale >= 1.1:
                break
            scale = min(1.1, scale * ratio * 0.99)
        # The fit above is linear; shrink a little more if the terrain or drift disagree.
        for _ in range(5):
            geom = _geometry(cfg, scale, centre, scene_size, base_size, base_from_scene)
            try:
                check_footprint(geom)
            except ValueError:
                scale *= 0.95
                continue
            if scale < MIN_FITTED_FRAME_SCALE:
                raise ValueError(
                    f"this flight fits the {sw}x{sh} px scene only with frame pixels of "
                    f"{scale:.2f} scene px: its frames would be the scene upsampled "
                    f"{1 / scale:.1f}x, blurrier than any camera; use smaller frames, fewer "
                    "frames or a larger scene, or set the frame scale to force it"
                )
            return geom
    geom = _geometry(cfg, scale, centre, scene_size, base_size, base_from_scene)
    check_footprint(geom)
    return geom

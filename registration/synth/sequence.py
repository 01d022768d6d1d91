"""Render a helicopter sequence with exact ground truth, write it, and load the truth back.

Output layout of :func:`simulate` (``OUT``)::

    OUT/frames/000000.png ...   raw frames (lens-distorted, rolling shutter, noise, JPEG-like
                                compression), RGB PNG
    OUT/base.png                the base map (second sensor), the target of registration
    OUT/truth.json              everything the truth needs: camera, pose track, terrain, mapping
                                between scene and base, the config; :func:`load_truth` recomputes
                                the truth exactly from it
    OUT/sequence.mp4            the frames as H.264 video (cropped to even size), for viewing

Every file is written to a temporary name and moved into place (``os.replace``).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration import warp
from registration.coords import as_points
from registration.result import STAGES
from registration.synth import city as citymod
from registration.synth.camera import (
    PoseTrack,
    SequenceGeometry,
    Terrain,
    apply_homography,
    focal_for_fov,
)

Progress = Callable[[int, int], None]

TRUTH_FORMAT = "aerialreg-synth-truth"
TRUTH_VERSION = 1
# Pixels of the base/scene kept clear around every frame's footprint (interpolation support and
# the optical blur).
FOOTPRINT_MARGIN_PX = 4.0
# Dense source maps are evaluated every this many raw pixels and interpolated; the interpolation
# error is checked by the tests (<< 0.05 px).
MAP_STEP = 8
MAX_PYRAMID_LEVEL = 5


@dataclass(frozen=True)
class SimConfig:
    """Simulator settings (units and provenance per field).

    Attributes:
        frame_size: raw frame ``(width, height)`` px. Paper table 1: 2560x1920; default half.
        n_frames: number of frames.
        fps: frames per second (paper table 1: ~5).
        gamma: Harris γ of the lens (paper section 3: 0.7); must keep the frame corners valid.
        fov_deg: horizontal field of view of the raw frame, degrees (paper table 1: ~70).
        rolling_shutter_s: readout time from the top row to the bottom row, s (0 = global
            shutter). Typical CMOS of the paper's era: 30-50 ms.
        frame_scale: size of a frame pixel at the centre of the reference (first) frame, in
            scene pixels (paper 4.3.2: ~20 % scale difference to the base). None = 1.1 for the
            procedural city, and for a user scene the largest value <= 1.1 whose footprint fits.
        heading_deg: orientation of the first frame relative to the base, degrees (paper 4.3.1:
            ~10°); the sign is drawn from the seed.
        drift_m: helicopter drift over the sequence, metres (paper: a few hundred feet in 5 min).
        wander_deg: low-frequency (0.1-0.4 Hz) roll/pitch amplitude, degrees.
        jitter_deg: high-frequency (0.6-2.2 Hz) roll/pitch amplitude, degrees (paper 4.1: the
            angular jitter dominates).
        yaw_deg: yaw rotation over the sequence, degrees.
        terrain_m: amplitude of the smooth terrain height, metres (paper 4.2: the city is not
            planar).
        base_sun_deg: sun azimuth and elevation (degrees) when the base map was taken; the
            frames' sun is ``city.Look()``'s (35, 55). Different = shifted shadows (paper 4.2:
            another sensor at another time); shadow edges then pull intersensor correlation
            peaks by up to ~1 px. Set (35, 55) for identical shadows.
        gsd_m: metres per scene pixel (procedural city 0.3; nominal for user scenes).
        city_size: procedural city ``(width, height)`` px; None = just large enough for the
            footprint of every frame.
        vehicles: moving vehicles on the lanes (procedural city only).
        traffic_per_km: moving vehicles per km of lane.
        blur_px: optical blur (Gaussian sigma) in raw pixels.
        noise_dn: sensor noise (Gaussian sigma) in 8-bit digital numbers.
        jpeg_quality: JPEG quality of the camera's compression (0 = none).
        seed: random seed; the same seed gives byte-identical output.
        video: also write ``sequence.mp4``.
    """

    frame_size: tuple[int, int] = (1280, 960)
    n_frames: int = 25
    fps: float = 5.0
    gamma: float = 0.7
    fov_deg: float = 70.0
    rolling_shutter_s: float = 0.04
    frame_scale: float | None = None
    heading_deg: float = 6.0
    drift_m: float = 12.0
    wander_deg: float = 1.3
    jitter_deg: float = 1.3
    yaw_deg: float = 2.0
    terrain_m: float = 1.5
    base_sun_deg: tuple[float, float] = (40.0, 53.0)
    gsd_m: float = 0.3
    city_size: tuple[int, int] | None = None
    vehicles: bool = True
    traffic_per_km: float = 25.0
    blur_px: float = 0.6
    noise_dn: float = 2.0
    jpeg_quality: int = 85
    seed: int = 0
    video: bool = True

    def validate(self) -> None:
        """Raise a one-line ValueError naming the first bad value."""
        w, h = self.frame_size
        if int(w) <= 0 or int(h) <= 0:
            raise ValueError(f"frame size must be positive, got {w}x{h}")
        if w < 16 or h < 16 or w > 8192 or h > 8192:
            raise ValueError(f"frame size must be between 16 and 8192 px per side, got {w}x{h}")
        if self.n_frames <= 0:
            raise ValueError(f"number of frames must be positive, got {self.n_frames}")
        if not self.fps > 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        # Harris model valid on the raw frame: 1 - γ ρ² > 0 at the corners (ρ = 1 for a centred
        # model); a margin keeps the corner rays away from the horizon.
        if not (-1.0 <= self.gamma <= 0.9):
            raise ValueError(
                f"gamma must be in the valid Harris range [-1, 0.9] for a {w}x{h} frame, got {self.gamma}"
            )
        if not (10.0 <= self.fov_deg <= 120.0):
            raise ValueError(f"field of view must be in [10, 120] degrees, got {self.fov_deg}")
        if not (0.0 <= self.rolling_shutter_s < 1.0 / self.fps):
            raise ValueError(
                f"rolling shutter readout must be in [0, 1/fps = {1 / self.fps:.3f}) s, got {self.rolling_shutter_s}"
            )
        if self.frame_scale is not None and not (0.05 <= self.frame_scale <= 20):
            raise ValueError(f"frame scale must be in [0.05, 20], got {self.frame_scale}")
        for name in (
            "drift_m",
            "wander_deg",
            "jitter_deg",
            "yaw_deg",
            "terrain_m",
            "blur_px",
            "noise_dn",
            "traffic_per_km",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        if abs(self.heading_deg) > 45:
            raise ValueError(f"heading must be within ±45 degrees, got {self.heading_deg}")
        if not self.gsd_m > 0:
            raise ValueError(f"gsd must be positive, got {self.gsd_m}")
        if self.city_size is not None and (self.city_size[0] <= 0 or self.city_size[1] <= 0):
            raise ValueError(
                f"city size must be positive, got {self.city_size[0]}x{self.city_size[1]}"
            )
        if not (0 <= self.jpeg_quality <= 100):
            raise ValueError(f"JPEG quality must be in [0, 100], got {self.jpeg_quality}")


# ------------------------------------------------------------------------------------------
# Truth


class SimTruth:
    """Exact ground truth of a simulated sequence, with the registration-result interface.

    ``frame_to_base(k, xy, stage)`` and ``base_to_frame(k, xy, stage)`` map ``(N, 2)`` raw
    pixels of frame ``k`` to base pixels and back (``stage`` is validated and ignored); NaN for
    points outside the frame or the base. Truth is defined for the terrain surface (roofs and
    vehicles are painted on the ground in the scene, so they follow the same mapping).
    """

    def __init__(
        self, geometry: SequenceGeometry, root: Path | None = None, config: dict | None = None
    ):
        self.geometry = geometry
        self.root = root
        self.config = config or {}

    @property
    def n_frames(self) -> int:
        return self.geometry.n_frames

    @property
    def gamma(self) -> float:
        return self.geometry.gamma

    @property
    def frame_size(self) -> tuple[int, int]:
        return (self.geometry.width, self.geometry.height)

    @property
    def base_size(self) -> tuple[int, int]:
        return tuple(self.geometry.base_size)

    @property
    def base_path(self) -> Path | None:
        return None if self.root is None else self.root / "base.png"

    @property
    def frames_dir(self) -> Path | None:
        return None if self.root is None else self.root / "frames"

    def frame_paths(self) -> list[Path]:
        return [self.frames_dir / f"{k:06d}.png" for k in range(self.n_frames)]

    def _check(self, k: int, stage: str) -> int:
        if stage not in STAGES:
            raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
        k = int(k)
        if not 0 <= k < self.n_frames:
            raise IndexError(f"frame index {k} out of range 0..{self.n_frames - 1}")
        return k

    def frame_to_base(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]:
        """``(N, 2)`` raw pixels of frame ``k`` -> ``(N, 2)`` base pixels (NaN outside)."""
        k = self._check(k, stage)
        return self.geometry.base_from_raw(k, as_points(xy))

    def base_to_frame(self, k: int, xy: ArrayLike, stage: str = "local") -> NDArray[np.float64]:
        """``(N, 2)`` base pixels -> ``(N, 2)`` raw pixels of frame ``k`` (NaN outside)."""
        k = self._check(k, stage)
        return self.geometry.raw_from_base(k, as_points(xy))

    def camera_altitude_m(self) -> float:
        return float(-self.geometry.pose.origin[2])


def load_truth(directory: str | os.PathLike) -> SimTruth:
    """Load the ground truth of a sequence written by :func:`simulate` (reads ``truth.json``)."""
    root = Path(directory)
    path = root / "truth.json"
    if not path.is_file():
        raise FileNotFoundError(f"no simulator truth in {root}: {path} is missing")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON ({exc.msg} at line {exc.lineno})") from None
    if data.get("format") != TRUTH_FORMAT:
        raise ValueError(f"{path} is not a simulator truth file (format={data.get('format')!r})")
    if data.get("version") != TRUTH_VERSION:
        raise ValueError(
            f"{path} has truth version {data.get('version')}, this code reads {TRUTH_VERSION}"
        )
    return SimTruth(SequenceGeometry.from_dict(data["geometry"]), root, data.get("config"))


# ------------------------------------------------------------------------------------------
# Planning: camera, pose and scene extent


def make_pose(cfg: SimConfig, origin_xy: tuple[float, float], altitude_m: float) -> PoseTrack:
    """Draw the helicopter's pose track from ``cfg.seed``: linear drift plus slow sinusoids in
    position; a fixed heading, slow yaw, low-frequency wander and high-frequency jitter in angle."""
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
    freq = np.concatenate([rng.uniform(0.1, 0.4, (3, 2)), rng.uniform(0.6, 2.2, (3, 3))], axis=1)
    phase = rng.uniform(0, 2 * np.pi, (3, 5))
    return PoseTrack(
        origin=np.array([origin_xy[0], origin_xy[1], -altitude_m]),
        velocity=velocity,
        pos_amp=pos_amp,
        pos_freq=pos_freq,
        pos_phase=pos_phase,
        angles0=angles0,
        angle_rate=angle_rate,
        ang_amp=amp,
        ang_freq=freq,
        ang_phase=phase,
    )


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
    w, h = cfg.frame_size
    f = focal_for_fov(w, h, cfg.gamma, cfg.fov_deg)
    altitude = scale * cfg.gsd_m * f
    return SequenceGeometry(
        width=int(w),
        height=int(h),
        gamma=float(cfg.gamma),
        focal_px=f,
        readout_s=float(cfg.rolling_shutter_s),
        frame_times=np.arange(cfg.n_frames) / cfg.fps,
        pose=make_pose(cfg, origin_xy, altitude),
        terrain=make_terrain(cfg),
        scene_gsd=float(cfg.gsd_m),
        scene_size=tuple(int(v) for v in scene_size),
        base_size=tuple(int(v) for v in base_size),
        base_from_scene=np.asarray(base_from_scene, np.float64),
    )


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
    geom = _geometry(cfg, scale, (float(origin[0]), float(origin[1])), size, size, np.eye(3))
    check_footprint(geom)
    return geom


def plan_scene(cfg: SimConfig, scene_size, base_size, base_from_scene) -> SequenceGeometry:
    """Camera over a user scene, centred on it; with ``frame_scale=None`` the largest scale
    <= 1.1 whose footprint fits the scene and the base (with margin)."""
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
                return geom
            except ValueError:
                scale *= 0.95
    geom = _geometry(cfg, scale, centre, scene_size, base_size, base_from_scene)
    check_footprint(geom)
    return geom


# ------------------------------------------------------------------------------------------
# Rendering


def _pyramid(image: NDArray, levels: int) -> list[NDArray]:
    out = [image]
    for _ in range(levels):
        if min(out[-1].shape[:2]) < 4:
            break
        out.append(cv2.pyrDown(out[-1]))
    return out


def frame_source_map(geom: SequenceGeometry, k: int) -> NDArray[np.float32]:
    """``(H, W, 2)`` scene pixel of every raw pixel of frame ``k`` (the truth, see
    :meth:`SequenceGeometry.scene_map`)."""
    return geom.scene_map(k, step=MAP_STEP)


def _level_of_detail(src_map: NDArray) -> NDArray[np.float32]:
    """Per raw pixel ``log2`` of the largest local stretch (scene px per raw px), >= 0: which
    pyramid level of the scene to sample so the frame does not alias."""
    s = MAP_STEP
    coarse = src_map[::s, ::s].astype(np.float64)
    gy, gx = np.gradient(coarse, s, axis=(0, 1))  # d(scene)/d(raw y), d(scene)/d(raw x)
    a, b, c, d = gx[..., 0], gy[..., 0], gx[..., 1], gy[..., 1]
    # Largest singular value of the 2x2 Jacobian [[a, b], [c, d]].
    t = a * a + b * b + c * c + d * d
    det = a * d - b * c
    smax = np.sqrt(0.5 * (t + np.sqrt(np.maximum(t * t - 4 * det * det, 0))))
    lod = np.log2(np.maximum(smax, 1.0)).astype(np.float32)
    h, w = src_map.shape[:2]
    return cv2.resize(lod, (w, h), interpolation=cv2.INTER_LINEAR)


def sample_antialiased(
    levels: list[NDArray], src_map: NDArray, offset=(0.0, 0.0)
) -> NDArray[np.float32]:
    """Sample an image pyramid at ``src_map`` (level-0 pixels, minus ``offset``) blending the two
    levels around the local level of detail (trilinear mip-mapping). Returns float32 image."""
    lod = np.clip(_level_of_detail(src_map), 0, len(levels) - 1)
    top = float(lod.max())
    m0 = src_map - np.asarray(offset, np.float32)
    out = None
    for lvl, img in enumerate(levels):
        if lvl > top + 1:
            break
        wgt = 1.0 - np.abs(lod - np.float32(lvl))
        np.maximum(wgt, 0.0, out=wgt)
        # cv2.pyrDown keeps every second pixel of the blurred image: level-l pixel i sits on
        # level-0 pixel 2^l i (not on the pixel-area centre of coords.rescale).
        m = m0 if lvl == 0 else m0 * np.float32(0.5**lvl)
        sample = warp.remap(img, m, interpolation="linear").astype(np.float32)
        sample *= wgt[..., None] if sample.ndim == 3 else wgt
        if out is None:
            out = sample
        else:
            out += sample
    return out


@functools.lru_cache(maxsize=4)
def _vignetting(w: int, h: int) -> NDArray[np.float32]:
    """Brightness falloff of a cheap lens: 1 at the centre, 0.82 at the corners."""
    xs = (np.arange(w, dtype=np.float32) - (w - 1) / 2) ** 2
    ys = (np.arange(h, dtype=np.float32) - (h - 1) / 2) ** 2
    out = 1.0 - 0.18 * (ys[:, None] + xs[None, :]) / np.float32((w * w + h * h) / 4)
    out.setflags(write=False)
    return out


def _camera_effects(img: NDArray[np.float32], cfg: SimConfig, k: int) -> NDArray[np.uint8]:
    """Optical blur, vignetting, sensor noise and JPEG compression of one raw frame (RGB)."""
    rng = np.random.default_rng([cfg.seed, 606, k])
    if cfg.blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), cfg.blur_px)
    h, w = img.shape[:2]
    img *= _vignetting(w, h)[..., None]
    if cfg.noise_dn > 0:
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(cfg.noise_dn)
    out = np.clip(img + 0.5, 0, 255).astype(np.uint8)
    if cfg.jpeg_quality > 0:
        ok, buf = cv2.imencode(
            ".jpg", out[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(cfg.jpeg_quality)]
        )
        out = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
    return np.ascontiguousarray(out)


# ------------------------------------------------------------------------------------------
# I/O


def _write_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as fh:
        fh.write(data)
    os.replace(tmp, path)


def write_png(path: Path, rgb: NDArray[np.uint8]) -> None:
    """Write an RGB (or grey) uint8 image as PNG, atomically."""
    img = rgb[..., ::-1] if rgb.ndim == 3 else rgb
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise OSError(f"could not encode {path}")
    _write_bytes(path, buf.tobytes())


def read_rgb(path: str | os.PathLike) -> NDArray[np.uint8]:
    """Read an image file as ``(H, W, 3)`` uint8 RGB."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"image not found: {p}")
    img = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"cannot read image {p}")
    return np.ascontiguousarray(img[..., ::-1])


def _as_rgb(image, name: str) -> NDArray[np.uint8]:
    if isinstance(image, (str, os.PathLike)):
        return read_rgb(image)
    arr = np.asarray(image)
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=2)
    if arr.ndim != 3 or arr.shape[2] not in (3, 4) or arr.dtype != np.uint8:
        raise ValueError(
            f"{name} must be an (H, W, 3) uint8 RGB image or a path, got {arr.shape} {arr.dtype}"
        )
    return np.ascontiguousarray(arr[..., :3])


class _VideoWriter:
    """H.264 video of the frames, cropped to even size, written to a temporary file first."""

    def __init__(self, path: Path, fps: float):
        import imageio.v2 as imageio

        self.path = path
        self.tmp = path.with_name(f".tmp{os.getpid()}.{path.name}")
        self.writer = imageio.get_writer(
            str(self.tmp),
            format="FFMPEG",
            fps=fps,
            codec="libx264",
            quality=7,
            macro_block_size=1,
            output_params=["-preset", "veryfast"],
            pixelformat="yuv420p",
            ffmpeg_log_level="error",
        )

    def append(self, rgb: NDArray[np.uint8]) -> None:
        h, w = rgb.shape[:2]
        self.writer.append_data(np.ascontiguousarray(rgb[: h - h % 2, : w - w % 2]))

    def close(self) -> None:
        self.writer.close()
        os.replace(self.tmp, self.path)


class FrameRenderer:
    """Renders raw frames of one sequence by backward mapping (:meth:`render`).

    For every raw pixel the scene position comes from the truth's own formulas
    (:meth:`SequenceGeometry.scene_map`); the scene is sampled from a Gaussian pyramid at the
    level matching the local stretch (anti-aliasing where the scene is finer than the frame);
    moving vehicles are drawn on a copy of the scene first (ground truth untouched); then the
    camera's blur, vignetting, noise and JPEG compression.
    """

    def __init__(
        self, geom: SequenceGeometry, scene: NDArray[np.uint8], cfg: SimConfig, layout=None
    ):
        self.geom, self.cfg, self.layout = geom, cfg, layout
        # The part of the scene any frame sees (plus the pyramid's support), cropped once.
        fp = footprints(geom)
        pad = 2 ** (MAX_PYRAMID_LEVEL + 1)
        self.x0 = max(0, int(np.floor(fp[:, 0].min())) - pad) // pad * pad
        self.y0 = max(0, int(np.floor(fp[:, 1].min())) - pad) // pad * pad
        x1 = min(scene.shape[1], int(np.ceil(fp[:, 2].max())) + pad)
        y1 = min(scene.shape[0], int(np.ceil(fp[:, 3].max())) + pad)
        self.crop = np.ascontiguousarray(scene[self.y0 : y1, self.x0 : x1])
        self._static_levels: list[NDArray] | None = None

    def render(self, k: int) -> NDArray[np.uint8]:
        """Raw frame ``k`` as ``(H, W, 3)`` uint8 RGB."""
        geom, cfg = self.geom, self.cfg
        src = frame_source_map(geom, k)
        n_levels = min(MAX_PYRAMID_LEVEL, int(np.ceil(float(_level_of_detail(src).max()))))
        if self.layout is not None and cfg.vehicles:
            # Moving vehicles at mid-exposure, on a copy of the scene: the ground (and hence the
            # truth) is untouched.
            img = self.crop.copy()
            t_mid = geom.frame_times[k] + 0.5 * geom.readout_s
            look = citymod.Look()
            az, el = np.radians(look.sun_azimuth_deg), np.radians(look.sun_elevation_deg)
            shadow = np.array([np.cos(az), np.sin(az)]) / np.tan(el) * 1.4 / cfg.gsd_m
            for v in citymod.traffic_snapshot(self.layout, cfg.seed, cfg.traffic_per_km, t_mid):
                cx, cy = v[0] - self.x0, v[1] - self.y0
                if -20 <= cx <= img.shape[1] + 20 and -20 <= cy <= img.shape[0] + 20:
                    citymod.draw_car(img, cx, cy, int(v[2]), v[3], v[4], v[5:8], shadow=shadow)
            levels = _pyramid(img, n_levels)
        else:
            if self._static_levels is None:
                self._static_levels = _pyramid(self.crop, MAX_PYRAMID_LEVEL)
            levels = self._static_levels[: n_levels + 1]
        return _camera_effects(sample_antialiased(levels, src, (self.x0, self.y0)), cfg, k)


# ------------------------------------------------------------------------------------------
# The simulator


def simulate(
    out_dir: str | os.PathLike,
    config: SimConfig | None = None,
    *,
    scene: str | os.PathLike | NDArray | None = None,
    base: str | os.PathLike | NDArray | None = None,
    base_from_scene: ArrayLike | None = None,
    progress: Progress | None = None,
) -> Path:
    """Render a helicopter sequence with exact ground truth into ``out_dir``.

    Args:
        out_dir: output folder (created); layout in the module docstring.
        config: :class:`SimConfig` (defaults: 1280x960, 25 frames, γ 0.7, 40 ms readout).
        scene: image (path or RGB array) to render frames from instead of the procedural city.
        base: base map of the same area (path or RGB array); None with a scene = the scene as
            another sensor would see it. Ignored without ``scene``.
        base_from_scene: ``(3, 3)`` homography scene px -> base px (identity by default, which
            requires scene and base of the same size within 3 %).
        progress: called as ``progress(done, total)``; total = frames + 2 (scene, frames,
            video).

    Returns:
        ``Path(out_dir)``.

    Raises:
        ValueError: one line naming the bad value (sizes, γ, footprint outside the base ...).
    """
    cfg = config or SimConfig()
    cfg.validate()
    total = cfg.n_frames + 2  # scene, frames, video
    if progress:
        progress(0, total)
    layout = None
    if scene is None:
        if base is not None or base_from_scene is not None:
            raise ValueError("base and base_from_scene need a scene image")
        geom = plan_procedural(cfg)
        layout = citymod.make_layout(*geom.scene_size, gsd=cfg.gsd_m, seed=cfg.seed)
        scene_img = citymod.render_city(layout, citymod.Look(parked_seed=cfg.seed * 2 + 1))
        base_img = citymod.second_sensor(
            citymod.render_city(
                layout,
                citymod.Look(
                    sun_azimuth_deg=cfg.base_sun_deg[0],
                    sun_elevation_deg=cfg.base_sun_deg[1],
                    parked_seed=cfg.seed * 2 + 2,
                    parked_fraction=0.55,
                    traffic_seed=cfg.seed + 1000,
                    traffic_per_km=cfg.traffic_per_km * 0.8,
                ),
            ),
            cfg.seed,
        )
        scene_desc = "procedural"
    else:
        scene_desc = str(scene) if isinstance(scene, (str, os.PathLike)) else "array"
        scene_img = _as_rgb(scene, "scene")
        base_img = (
            citymod.second_sensor(scene_img, cfg.seed) if base is None else _as_rgb(base, "base")
        )
        sh, sw = scene_img.shape[:2]
        bh, bw = base_img.shape[:2]
        if base_from_scene is None:
            if abs(sw - bw) > 0.03 * sw or abs(sh - bh) > 0.03 * sh:
                raise ValueError(
                    f"scene is {sw}x{sh} px but base is {bw}x{bh} px; give base_from_scene "
                    "(--base-from-scene, 9 numbers) to relate them"
                )
            H = np.eye(3)
        else:
            H = np.asarray(base_from_scene, np.float64)
            if H.size != 9:
                raise ValueError(f"base_from_scene must have 9 numbers (3x3), got {H.size}")
            H = H.reshape(3, 3)
            if not np.isfinite(H).all() or abs(np.linalg.det(H)) < 1e-12:
                raise ValueError(
                    f"base_from_scene must be a finite invertible 3x3 matrix, got {H.ravel().tolist()}"
                )
            H = H / H[2, 2] if abs(H[2, 2]) > 1e-12 else H
        geom = plan_scene(cfg, (sw, sh), (bw, bh), H)

    out = Path(out_dir)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    # A previous, longer run into the same folder must not leave frames behind (readers take
    # every image of frames/ in name order), nor a video of other frames.
    keep = {f"{k:06d}.png" for k in range(cfg.n_frames)}
    for old in (out / "frames").glob("[0-9][0-9][0-9][0-9][0-9][0-9].png"):
        if old.name not in keep:
            old.unlink()
    if not cfg.video:
        (out / "sequence.mp4").unlink(missing_ok=True)
    write_png(out / "base.png", base_img)
    truth = {
        "format": TRUTH_FORMAT,
        "version": TRUTH_VERSION,
        "scene": scene_desc,
        "base": "base.png",
        "frames": [f"frames/{k:06d}.png" for k in range(cfg.n_frames)],
        "frame_size": list(cfg.frame_size),
        "gamma": cfg.gamma,
        "frame_scale": float(-geom.pose.origin[2] / (cfg.gsd_m * geom.focal_px)),
        "geometry": geom.to_dict(),
        "config": dataclasses.asdict(cfg),
    }
    _write_bytes(out / "truth.json", (json.dumps(truth, indent=1) + "\n").encode())
    if progress:
        progress(1, total)

    renderer = FrameRenderer(geom, scene_img, cfg, layout)
    writer = _VideoWriter(out / "sequence.mp4", cfg.fps) if cfg.video else None
    try:
        for k in range(cfg.n_frames):
            frame = renderer.render(k)
            write_png(out / "frames" / f"{k:06d}.png", frame)
            if writer:
                writer.append(frame)
            if progress:
                progress(k + 2, total)
    except BaseException:
        if writer:
            writer.writer.close()
            Path(writer.tmp).unlink(missing_ok=True)
        raise
    if writer:
        writer.close()
    if progress:
        progress(total, total)
    return out

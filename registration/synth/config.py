"""The simulator's settings (:class:`SimConfig`) and the limits that keep a run within the
machine (one-line errors naming the value and the limit)."""

from __future__ import annotations

import math
from dataclasses import dataclass

# -- Limits ----------------------------------------------------------------------------------
# Per side: OpenCV's remap/warpAffine hold positions as int16 and the 2x-scaled base of a large
# frame's city must stay below that; 8192 px is beyond any aerial video sensor in use (8K).
MAX_FRAME_SIDE = 8192
# One frame is rendered at once: ~60 bytes per frame pixel of maps and float images (measured
# ~45 B/px for the city painting), so 40 MP is ~2.4 GB of working memory per frame.
MAX_FRAME_PIXELS = 40_000_000
MAX_FRAMES = 100_000
# Frames x pixels: ~1.5 bytes of PNG per pixel on disk, so 1e10 px is ~15 GB (the paper's whole
# 5-minute flight, 1500 frames of 2560x1920, is 7.4e9 px).
MAX_SEQUENCE_PIXELS = 10_000_000_000
# The procedural city is painted whole, twice (frames' sensor and the base's): ~45 bytes of
# working memory per city pixel (measured), so 150 MP is ~7 GB and ~2.5 min of painting.
MAX_CITY_PIXELS = 150_000_000


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
            shutter). Typical CMOS of the paper's era: 30-50 ms; slow sensors up to 0.15 s.
        frame_scale: size of a frame pixel at the centre of the reference (first) frame, in
            scene pixels (paper 4.3.2: ~20 % scale difference to the base). None = 1.1 for the
            procedural city, and for a user scene the largest value <= 1.1 whose footprint fits.
        heading_deg: orientation of the first frame relative to the scene, degrees, any angle
            (paper 4.3.1: ~10°; a circling helicopter takes every heading); the sign is drawn
            from the seed.
        drift_m: helicopter drift over the sequence, metres (paper: a few hundred feet in 5 min).
        wander_deg: low-frequency roll/pitch amplitude, degrees.
        jitter_deg: high-frequency roll/pitch amplitude, degrees (paper 4.1: the angular jitter
            dominates).
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
        vehicle_gap_m: None: each vehicle at its own speed, driving through a slower one ahead
            (the flights the registration's tests and figures were measured on); metres: the
            vehicles of a lane share one speed and keep at least this gap bumper to bumper, as
            real traffic does (`aerialreg bench traffic`'s flights: 2.0).
        vehicle_headway_s: with ``vehicle_gap_m``, the gap grows by the distance the lane's
            speed covers in this time, s (car-following models' ``s0 + v T``; drivers keep 1-2
            s behind the vehicle ahead). 0 = the fixed gap alone (`aerialreg bench traffic`'s
            flights: 1.0 since 2026-12-01; 0 before).
        blur_px: optical blur (Gaussian sigma) in raw pixels.
        noise_dn: sensor noise (Gaussian sigma) in 8-bit digital numbers.
        jpeg_quality: JPEG quality of the camera's compression (0 = none).
        seed: random seed; the same seed gives byte-identical output.
        video: also write ``sequence.mp4``.
        lens_k2: fourth-order lens term beyond Harris (:class:`camera.SimLens`: raw to
            corrected ``ρ = ρ' / sqrt(1 - γρ'² - k2 ρ'⁴)``); 0 = exactly the Harris lens.
            0.04 leaves ~7 px at 2560x1920 (0.27 % of the width) at the corners after the best
            one-parameter Harris fit.
        shake_deg: when set, the high-frequency jitter (drawn as for ``jitter_deg``) is scaled
            so that the largest rotation of the camera between consecutive frames (at
            mid-exposure) is exactly this, degrees. None = ``jitter_deg`` as drawn.
        unregistered_px: when set, the slow motion (drift and attitude wander, as drawn) is
            scaled so that the paper's table-2 "Unregistered" mean motion (5 ground points of
            the first frame followed over 10 frames spread over the flight, radially corrected
            px; :func:`plan.unregistered_motion`) is exactly this many pixels at this frame
            size. None = as drawn.
        wander_hz: frequency range of the low-frequency attitude terms, Hz.
        jitter_hz: frequency range of the high-frequency attitude terms, Hz.
        flyover_footprints: straight-line travel from the first to the last frame, in lengths
            of the first frame's ground footprint along the (seeded) direction of flight; > 1
            means the last frame sees none of the first frame's ground. 0 = hover.
        base_heading_deg: the base map turned by this against the scene, degrees, any angle
            (clockwise on screen; :mod:`registration.synth.basemap`).
        base_scale: base pixels per native base pixel (0.5 = half resolution, 2 = double);
            resampled with area averaging when shrinking.
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
    vehicle_gap_m: float | None = None
    vehicle_headway_s: float = 0.0
    blur_px: float = 0.6
    noise_dn: float = 2.0
    jpeg_quality: int = 85
    seed: int = 0
    video: bool = True
    lens_k2: float = 0.0
    shake_deg: float | None = None
    unregistered_px: float | None = None
    wander_hz: tuple[float, float] = (0.1, 0.4)
    jitter_hz: tuple[float, float] = (0.6, 2.2)
    flyover_footprints: float = 0.0
    base_heading_deg: float = 0.0
    base_scale: float = 1.0

    def validate(self) -> None:
        """Raise a one-line ValueError naming the first bad value (and the limit it breaks)."""
        from registration.synth.basemap import check_base_params

        self._check_frames()
        self._check_lens()
        self._check_camera_and_motion()
        self._check_motion_targets()
        self._check_scene_and_output()
        check_base_params(self.base_heading_deg, self.base_scale)

    def _check_frames(self) -> None:
        """Frame size (px per side, MP per frame), number of frames, their total pixels and
        the frame rate."""
        w, h = self.frame_size
        if int(w) <= 0 or int(h) <= 0:
            raise ValueError(f"frame size must be positive, got {w}x{h}")
        if w < 16 or h < 16 or w > MAX_FRAME_SIDE or h > MAX_FRAME_SIDE:
            raise ValueError(
                f"frame size must be between 16 and {MAX_FRAME_SIDE} px per side, got {w}x{h}"
            )
        if w * h > MAX_FRAME_PIXELS:
            raise ValueError(
                f"frame size {w}x{h} is {w * h / 1e6:.1f} MP, over the limit of "
                f"{MAX_FRAME_PIXELS / 1e6:.0f} MP per frame (rendering needs ~60 bytes per pixel)"
            )
        if self.n_frames <= 0:
            raise ValueError(f"number of frames must be positive, got {self.n_frames}")
        if self.n_frames > MAX_FRAMES:
            raise ValueError(f"number of frames must be at most {MAX_FRAMES}, got {self.n_frames}")
        if self.n_frames * w * h > MAX_SEQUENCE_PIXELS:
            raise ValueError(
                f"{self.n_frames} frames of {w}x{h} are {self.n_frames * w * h / 1e9:.1f} "
                f"gigapixels, over the limit of {MAX_SEQUENCE_PIXELS / 1e9:.0f} (~15 GB of PNG); "
                "use fewer frames or a smaller size"
            )
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps must be positive, got {self.fps}")

    def _check_lens(self) -> None:
        """γ and ``lens_k2``, alone and together on this frame size."""
        from registration.synth.camera import SimLens

        w, h = self.frame_size
        # Harris model valid on the raw frame: 1 - γ ρ² > 0 at the corners (ρ = 1 for a centred
        # model); a margin keeps the corner rays away from the horizon.
        if not (-1.0 <= self.gamma <= 0.9):
            raise ValueError(
                f"gamma must be in the valid Harris range [-1, 0.9] for a {w}x{h} frame, got {self.gamma}"
            )
        if not (math.isfinite(self.lens_k2) and -0.5 <= self.lens_k2 <= 0.5):
            raise ValueError(f"lens_k2 must be in [-0.5, 0.5], got {self.lens_k2}")
        if self.gamma + self.lens_k2 > 0.9:
            raise ValueError(
                f"gamma + lens_k2 must be at most 0.9 (the corner rays stay below the horizon), "
                f"got {self.gamma} + {self.lens_k2}"
            )
        problem = SimLens(self.gamma, self.lens_k2, int(w), int(h)).validity_problem()
        if problem:
            raise ValueError(problem)

    def _check_camera_and_motion(self) -> None:
        """Field of view, rolling shutter, frame scale, the non-negative motion and scene
        amplitudes, the flyover length and the heading."""
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
            "flyover_footprints",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        if self.vehicle_gap_m is not None and not (
            math.isfinite(self.vehicle_gap_m) and 0 <= self.vehicle_gap_m <= 100
        ):
            raise ValueError(f"vehicle_gap_m must be in [0, 100] m, got {self.vehicle_gap_m}")
        if not (math.isfinite(self.vehicle_headway_s) and 0 <= self.vehicle_headway_s <= 10):
            raise ValueError(
                f"vehicle_headway_s must be in [0, 10] s, got {self.vehicle_headway_s}"
            )
        if self.vehicle_headway_s > 0 and self.vehicle_gap_m is None:
            raise ValueError(
                f"vehicle_headway_s ({self.vehicle_headway_s}) needs vehicle_gap_m: without a "
                "gap the vehicles drive through each other"
            )
        if self.flyover_footprints > 100:
            raise ValueError(
                f"flyover_footprints must be at most 100, got {self.flyover_footprints}"
            )
        if not math.isfinite(self.heading_deg):
            raise ValueError(f"heading must be a finite angle in degrees, got {self.heading_deg}")

    def _check_motion_targets(self) -> None:
        """``shake_deg`` and ``unregistered_px`` (with what they scale) and the attitude
        frequency ranges."""
        if self.shake_deg is not None:
            if not (math.isfinite(self.shake_deg) and 0 < self.shake_deg <= 20):
                raise ValueError(f"shake_deg must be in (0, 20] degrees, got {self.shake_deg}")
            if self.jitter_deg <= 0:
                raise ValueError("shake_deg scales the jitter: jitter_deg must be > 0, got 0")
        if self.unregistered_px is not None:
            if not (math.isfinite(self.unregistered_px) and 0 < self.unregistered_px <= 1e5):
                raise ValueError(f"unregistered_px must be in (0, 1e5], got {self.unregistered_px}")
            if self.n_frames < 2:
                raise ValueError("unregistered_px needs at least 2 frames")
            if self.drift_m <= 0 and self.wander_deg <= 0:
                raise ValueError(
                    "unregistered_px scales the drift and wander: drift_m or wander_deg must be > 0"
                )
        for name in ("wander_hz", "jitter_hz"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi <= 50):
                raise ValueError(f"{name} must be a range 0 < low <= high <= 50 Hz, got {lo}, {hi}")

    def _check_scene_and_output(self) -> None:
        """Ground sample distance, city size, seed and JPEG quality."""
        if not self.gsd_m > 0:
            raise ValueError(f"gsd must be positive, got {self.gsd_m}")
        if self.city_size is not None:
            cw, ch = self.city_size
            if cw <= 0 or ch <= 0:
                raise ValueError(f"city size must be positive, got {cw}x{ch}")
            if cw * ch > MAX_CITY_PIXELS:
                raise ValueError(
                    f"city size {cw}x{ch} is over the limit of {MAX_CITY_PIXELS / 1e6:.0f} MP"
                )
        if int(self.seed) != self.seed or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed}")
        if not (0 <= self.jpeg_quality <= 100):
            raise ValueError(f"JPEG quality must be in [0, 100], got {self.jpeg_quality}")

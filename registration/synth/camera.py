"""The helicopter camera: pose as a smooth function of time, rolling shutter, Harris distortion,
pinhole projection onto a smooth terrain surface (paper sections 2 and 4.2).

World frame (metres): ``X`` along base-map columns, ``Y`` along base-map rows, ``Z`` pointing
*down* (so a nadir camera has the identity rotation). The ground surface is
``Z = -terrain.height(X, Y)``; the camera flies at ``Z = -altitude``. The scene image (what the
frames are rendered from) has pixel ``(x, y)`` centred on ground ``(x * gsd, y * gsd)``; base
pixels are ``base_from_scene @ (x, y, 1)``.

Camera frame: ``x`` right, ``y`` down (image rows), ``z`` forward (along the optical axis).
``R(t)`` (world from camera) is ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

One frame ``k`` is exposed row by row (rolling shutter): raw row ``y`` is exposed at
``t_k + readout_s * y / H`` and sees the world with the pose at that instant. The *raw* row
decides the time (the sensor reads raw rows), so frame -> ground is direct and ground -> frame is
a small fixed-point iteration on the row time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points
from registration.lens import HarrisModel, TwoTermHarrisModel

# Fixed-point tolerances: far below the 1e-4 px the truth must reach.
_RAW_TOL_PX = 1e-7
_GROUND_TOL_M = 1e-9
_MAX_ITER = 60


def _sines(t: NDArray, amp: NDArray, freq: NDArray, phase: NDArray) -> NDArray:
    """``(N, C)``: per channel ``c`` the sum over ``j`` of ``amp[c,j] sin(2π freq[c,j] t + phase[c,j])``."""
    arg = 2.0 * np.pi * freq[None, :, :] * t[:, None, None] + phase[None, :, :]
    return np.sum(amp[None, :, :] * np.sin(arg), axis=2)


@dataclass(frozen=True)
class PoseTrack:
    """Camera pose as a smooth function of time ``t`` (seconds).

    position(t) = origin + velocity t + Σ sinusoids (metres, world frame),
    angles(t)   = angles0 + angle_rate t + Σ sinusoids (radians: roll, pitch, yaw).

    Attributes:
        origin: ``(3,)`` camera centre at t = 0, metres (``Z`` = -altitude).
        velocity: ``(3,)`` linear drift, m/s.
        pos_amp, pos_freq, pos_phase: ``(3, J)`` position sinusoids (m, Hz, rad).
        angles0: ``(3,)`` roll, pitch, yaw at t = 0, rad.
        angle_rate: ``(3,)`` rad/s.
        ang_amp, ang_freq, ang_phase: ``(3, M)`` angular sinusoids (rad, Hz, rad).
    """

    origin: NDArray
    velocity: NDArray
    pos_amp: NDArray
    pos_freq: NDArray
    pos_phase: NDArray
    angles0: NDArray
    angle_rate: NDArray
    ang_amp: NDArray
    ang_freq: NDArray
    ang_phase: NDArray

    def position(self, t: ArrayLike) -> NDArray[np.float64]:
        """``(N,)`` times -> ``(N, 3)`` camera centres in metres."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        return (
            self.origin[None, :]
            + self.velocity[None, :] * t[:, None]
            + _sines(t, self.pos_amp, self.pos_freq, self.pos_phase)
        )

    def angles(self, t: ArrayLike) -> NDArray[np.float64]:
        """``(N,)`` times -> ``(N, 3)`` roll, pitch, yaw in radians."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        return (
            self.angles0[None, :]
            + self.angle_rate[None, :] * t[:, None]
            + _sines(t, self.ang_amp, self.ang_freq, self.ang_phase)
        )

    def rotation(self, t: ArrayLike) -> NDArray[np.float64]:
        """``(N,)`` times -> ``(N, 3, 3)`` world-from-camera rotations ``Rz(yaw) Ry(pitch) Rx(roll)``."""
        a = self.angles(t)
        cr, sr = np.cos(a[:, 0]), np.sin(a[:, 0])
        cp, sp = np.cos(a[:, 1]), np.sin(a[:, 1])
        cy, sy = np.cos(a[:, 2]), np.sin(a[:, 2])
        r = np.empty((len(a), 3, 3))
        r[:, 0, 0] = cy * cp
        r[:, 0, 1] = cy * sp * sr - sy * cr
        r[:, 0, 2] = cy * sp * cr + sy * sr
        r[:, 1, 0] = sy * cp
        r[:, 1, 1] = sy * sp * sr + cy * cr
        r[:, 1, 2] = sy * sp * cr - cy * sr
        r[:, 2, 0] = -sp
        r[:, 2, 1] = cp * sr
        r[:, 2, 2] = cp * cr
        return r

    def to_dict(self) -> dict:
        return {k: np.asarray(getattr(self, k)).tolist() for k in self.__dataclass_fields__}

    @classmethod
    def from_dict(cls, d: dict) -> PoseTrack:
        return cls(**{k: np.asarray(d[k], np.float64) for k in cls.__dataclass_fields__})


@dataclass(frozen=True)
class Terrain:
    """Smooth ground height ``h(X, Y) = Σ amp sin(kx X + ky Y + phase)`` in metres (the paper's
    fourth error source: the city is not planar). ``amp`` etc. are ``(K,)`` arrays."""

    amp: NDArray
    kx: NDArray
    ky: NDArray
    phase: NDArray

    def height(self, X: NDArray, Y: NDArray) -> NDArray[np.float64]:
        """Height above the datum (metres) at ground points ``X, Y`` (same shapes)."""
        X = np.asarray(X, np.float64)
        Y = np.asarray(Y, np.float64)
        out = np.zeros(np.broadcast(X, Y).shape)
        for a, kx, ky, ph in zip(self.amp, self.kx, self.ky, self.phase, strict=True):
            out += a * np.sin(kx * X + ky * Y + ph)
        return out

    def to_dict(self) -> dict:
        return {k: np.asarray(getattr(self, k)).tolist() for k in self.__dataclass_fields__}

    @classmethod
    def from_dict(cls, d: dict) -> Terrain:
        return cls(**{k: np.asarray(d[k], np.float64) for k in cls.__dataclass_fields__})


# The simulated camera's radial lens: Harris plus an optional fourth-order term that no
# one-parameter Harris model can absorb (exactly Harris at k2 = 0).
SimLens = TwoTermHarrisModel


def best_harris_fit(lens: SimLens, step_px: int = 8) -> dict:
    """How far the best one-parameter Harris model lands from ``lens``, in raw pixels.

    Fits ``γ`` and a free scale ``s`` of the corrected image (a scale is absorbed by any later
    projective transform) so that ``Harris_γ.raw_from_corrected(c + s (x - c))`` reproduces the
    raw position of every corrected point ``x = lens.corrected_from_raw(x')`` on a raw grid
    ``step_px`` apart (plus the four corners), least squares over the grid.

    Returns:
        ``{"gamma", "scale", "rms_px", "max_px", "corner_px"}``: the fitted γ and ``s``, the RMS
        and largest raw-pixel residual over the grid, and the largest at the four corners.
    """
    from scipy.optimize import least_squares

    w, h = lens.width, lens.height
    xs, ys = np.meshgrid(np.arange(0, w, step_px, float), np.arange(0, h, step_px, float))
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    raw = np.concatenate([np.column_stack([xs.ravel(), ys.ravel()]), corners])
    corr = lens.corrected_from_raw(raw)
    c = lens.c

    def residual(p, pts=raw, cor=corr):
        model = HarrisModel(float(p[0]), w, h)
        return (model.raw_from_corrected(c + p[1] * (cor - c)) - pts).ravel()

    def safe(p):
        r = residual(p)
        return np.where(np.isfinite(r), r, 1e3)

    fit = least_squares(safe, x0=[lens.gamma, 1.0], method="lm", xtol=1e-14, ftol=1e-14)
    r = residual(fit.x).reshape(-1, 2)
    d = np.linalg.norm(r, axis=1)
    return {
        "gamma": float(fit.x[0]),
        "scale": float(fit.x[1]),
        "rms_px": float(np.sqrt(np.mean(d * d))),
        "max_px": float(d.max()),
        "corner_px": float(d[-4:].max()),
    }


@dataclass(frozen=True)
class SequenceGeometry:
    """Everything that decides where a raw pixel of frame ``k`` lands on the ground / base map.

    Attributes:
        width, height: raw frame size, px.
        gamma: Harris γ of the lens (raw = lens.raw_from_corrected(ideal pinhole)).
        focal_px: pinhole focal length of the corrected (ideal) image, px.
        readout_s: rolling-shutter readout time from row 0 to row ``height``, s (0 = global shutter).
        frame_times: ``(K,)`` start time of each frame's exposure, s.
        pose: the camera's :class:`PoseTrack`.
        terrain: the ground's :class:`Terrain`.
        scene_gsd: metres per scene pixel.
        scene_size, base_size: ``(width, height)`` of the scene and base images, px.
        base_from_scene: ``(3, 3)`` homography from scene pixels to base pixels.
        lens_k2: the lens's fourth-order term beyond Harris (:class:`SimLens`; 0 = exactly
            Harris).
    """

    width: int
    height: int
    gamma: float
    focal_px: float
    readout_s: float
    frame_times: NDArray
    pose: PoseTrack
    terrain: Terrain
    scene_gsd: float
    scene_size: tuple[int, int]
    base_size: tuple[int, int]
    base_from_scene: NDArray
    lens_k2: float = 0.0

    @property
    def lens(self) -> SimLens:
        """The camera's lens (Harris γ plus ``lens_k2``)."""
        return SimLens(self.gamma, self.lens_k2, self.width, self.height)

    @property
    def n_frames(self) -> int:
        return len(self.frame_times)

    @property
    def principal_point(self) -> NDArray[np.float64]:
        return np.array([(self.width - 1) / 2.0, (self.height - 1) / 2.0])

    def row_time(self, k, raw_y: NDArray) -> NDArray[np.float64]:
        """Exposure time (s) of raw row ``raw_y`` (float) in frame ``k`` (an int, or one per
        row)."""
        return self.frame_times[k] + self.readout_s * np.asarray(raw_y, np.float64) / self.height

    # -- frame -> ground --------------------------------------------------------------------
    def ground_from_raw(self, k, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` raw pixels of frame ``k`` -> ``(N, 2)`` ground ``(X, Y)`` metres (``k`` an
        int, or an ``(N,)`` int array: one frame per point).

        No bounds check (points outside the frame are extrapolated); NaN where the ray misses
        the ground or the distortion is undefined.
        """
        raw = as_points(xy)
        X, Y, _h = self._ground_and_height(k, raw)
        return np.column_stack([X, Y])

    def _rays(self, k: int, raw: NDArray) -> tuple[NDArray, NDArray]:
        """Camera centres ``(N, 3)`` and world ray directions ``(N, 3)`` of raw pixels."""
        corr = self.lens.corrected_from_raw(raw)
        t = self.row_time(k, raw[:, 1])
        c = self.pose.position(t)
        r = self.pose.rotation(t)
        pp = self.principal_point
        d_cam = np.column_stack(
            [
                (corr[:, 0] - pp[0]) / self.focal_px,
                (corr[:, 1] - pp[1]) / self.focal_px,
                np.ones(len(raw)),
            ]
        )
        d = np.einsum("nij,nj->ni", r, d_cam)
        d[~(d[:, 2] > 1e-3)] = np.nan  # ray at or above the horizon
        return c, d

    def _intersect(self, c: NDArray, d: NDArray, h: NDArray, iterations: int | None = None):
        """Ray-surface intersection ``Z = -h(X, Y)`` by fixed-point iteration on the height,
        starting from heights ``h``; contracts by |grad h| * tan(view angle) << 1 for the gentle
        terrain here. ``iterations=None``: until the height changes by < 1e-9 m."""
        with np.errstate(invalid="ignore", divide="ignore"):
            for _ in range(iterations if iterations is not None else _MAX_ITER):
                s = (-h - c[..., 2]) / d[..., 2]
                X = c[..., 0] + s * d[..., 0]
                Y = c[..., 1] + s * d[..., 1]
                h_new = self.terrain.height(X, Y)
                if iterations is None:
                    delta = np.nanmax(np.abs(h_new - h), initial=0.0)
                    h = h_new
                    if delta < _GROUND_TOL_M:
                        break
                else:
                    h = h_new
            s = (-h - c[..., 2]) / d[..., 2]
        return c[..., 0] + s * d[..., 0], c[..., 1] + s * d[..., 1], h

    def _ground_and_height(self, k: int, raw: NDArray):
        c, d = self._rays(k, raw)
        return self._intersect(c, d, np.zeros(len(raw)))

    def scene_map(
        self, k: int, step: int = 8, rows_per_chunk: int = 128, iterations: int = 1
    ) -> NDArray[np.float32]:
        """``(H, W, 2)`` float32 scene pixel of every raw pixel of frame ``k`` (for rendering).

        Same formulas as :meth:`scene_from_raw`, arranged for speed: the pose is evaluated once
        per raw row (the rolling shutter makes it a function of the row only), the distortion and
        the rays per pixel, and the terrain intersection starts from heights interpolated from an
        exact solution every ``step`` px and is then iterated ``iterations`` times per pixel (each
        iteration shrinks the height error ~10x; the tests check the map against the truth).
        """
        from registration.geometry import pixel_grid, source_map_from_function

        w, h = self.width, self.height
        hmap = source_map_from_function(
            lambda xy: np.column_stack([self._ground_and_height(k, xy)[2], np.zeros(len(xy))]),
            w,
            h,
            step=step,
        )[..., 0]
        rows = np.arange(h, dtype=np.float64)
        t = self.row_time(k, rows)
        cs = self.pose.position(t)
        rs = self.pose.rotation(t)
        pp = self.principal_point
        lens = self.lens
        out = np.empty((h, w, 2), np.float32)
        grid = pixel_grid(w, 1).astype(np.float64)[0]  # (W, 2)
        for y0 in range(0, h, rows_per_chunk):
            y1 = min(h, y0 + rows_per_chunk)
            n = y1 - y0
            raw = np.repeat(grid[None], n, axis=0)
            raw[..., 1] = rows[y0:y1, None]
            corr = lens.corrected_from_raw(raw.reshape(-1, 2)).reshape(n, w, 2)
            dc = (corr - pp) / self.focal_px  # (n, W, 2); the third component is 1
            r = rs[y0:y1, None, :, :]  # (n, 1, 3, 3): one rotation per row
            d = r[..., 0] * dc[..., 0:1] + r[..., 1] * dc[..., 1:2] + r[..., 2]
            d[~(d[..., 2] > 1e-3)] = np.nan
            c = np.broadcast_to(cs[y0:y1, None, :], (n, w, 3))
            X, Y, _ = self._intersect(c, d, hmap[y0:y1].astype(np.float64), iterations=iterations)
            out[y0:y1, :, 0] = X / self.scene_gsd
            out[y0:y1, :, 1] = Y / self.scene_gsd
        return out

    # -- ground -> frame --------------------------------------------------------------------
    def raw_from_ground(self, k, XY: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` ground ``(X, Y)`` metres -> ``(N, 2)`` raw pixels of frame ``k`` (an int,
        or an ``(N,)`` int array: one frame per point, solved in one batch).

        Solves for the raw pixel whose row's exposure time projects the ground point onto it
        (rolling shutter). No frame-bounds check; NaN behind the camera or without convergence.
        """
        g = as_points(XY, "ground points")
        P = np.column_stack([g, -self.terrain.height(g[:, 0], g[:, 1])])
        lens = self.lens
        pp = self.principal_point
        t = np.full(len(g), self.frame_times[k] + 0.5 * self.readout_s)
        raw = np.full((len(g), 2), np.nan)
        for it in range(_MAX_ITER):
            c = self.pose.position(t)
            r = self.pose.rotation(t)
            pc = np.einsum("nji,nj->ni", r, P - c)  # R^T (P - C)
            with np.errstate(invalid="ignore", divide="ignore"):
                z = np.where(pc[:, 2] > 1e-6, pc[:, 2], np.nan)
                corr = np.column_stack(
                    [self.focal_px * pc[:, 0] / z + pp[0], self.focal_px * pc[:, 1] / z + pp[1]]
                )
            new = lens.raw_from_corrected(corr)
            if self.readout_s == 0:
                raw = new
                break
            delta = np.abs(new - raw).max(axis=1)
            raw = new
            t = self.row_time(k, raw[:, 1])
            if it > 0 and not np.any(delta > _RAW_TOL_PX):
                break
        else:
            raw[~(delta <= 1e-4)] = np.nan
        return raw

    # -- scene / base pixels ----------------------------------------------------------------
    def scene_from_raw(self, k, xy: ArrayLike) -> NDArray[np.float64]:
        """Raw pixels -> scene pixels (no bounds check; ``k`` as for :meth:`ground_from_raw`)."""
        return self.ground_from_raw(k, xy) / self.scene_gsd

    def raw_from_scene(self, k, xy: ArrayLike) -> NDArray[np.float64]:
        """Scene pixels -> raw pixels (no bounds check; ``k`` as for :meth:`raw_from_ground`)."""
        return self.raw_from_ground(k, as_points(xy) * self.scene_gsd)

    def in_frame(self, xy: NDArray) -> NDArray[np.bool_]:
        """Inside the raw frame: ``-0.5 <= x <= W - 0.5`` and the same for ``y``."""
        return (
            (xy[:, 0] >= -0.5)
            & (xy[:, 0] <= self.width - 0.5)
            & (xy[:, 1] >= -0.5)
            & (xy[:, 1] <= self.height - 0.5)
        )

    def in_base(self, xy: NDArray) -> NDArray[np.bool_]:
        w, h = self.base_size
        return (
            (xy[:, 0] >= -0.5) & (xy[:, 0] <= w - 0.5) & (xy[:, 1] >= -0.5) & (xy[:, 1] <= h - 0.5)
        )

    def base_from_raw(self, k: int, xy: ArrayLike) -> NDArray[np.float64]:
        """Truth: raw pixels of frame ``k`` -> base pixels; NaN outside the frame or the base."""
        raw = as_points(xy)
        out = apply_homography(self.base_from_scene, self.scene_from_raw(k, raw))
        out[~(self.in_frame(raw) & self.in_base(out))] = np.nan
        return out

    def raw_from_base(self, k: int, xy: ArrayLike, clip: bool = True) -> NDArray[np.float64]:
        """Truth: base pixels -> raw pixels of frame ``k``; NaN outside the base or (``clip``)
        the frame."""
        b = as_points(xy)
        scene = apply_homography(np.linalg.inv(self.base_from_scene), b)
        out = self.raw_from_scene(k, scene)
        out[~((self.in_frame(out) | (not clip)) & self.in_base(b))] = np.nan
        return out

    def border_points(self, per_edge: int = 48) -> NDArray[np.float64]:
        """``(4 * per_edge, 2)`` raw points along the frame border (pixel-centre extremes)."""
        s = np.linspace(0.0, 1.0, per_edge)
        w, h = self.width - 1.0, self.height - 1.0
        return np.concatenate(
            [
                np.column_stack([s * w, np.zeros_like(s)]),
                np.column_stack([s * w, np.full_like(s, h)]),
                np.column_stack([np.zeros_like(s), s * h]),
                np.column_stack([np.full_like(s, w), s * h]),
            ]
        )

    def to_dict(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "gamma": self.gamma,
            "focal_px": self.focal_px,
            "readout_s": self.readout_s,
            "frame_times": np.asarray(self.frame_times).tolist(),
            "pose": self.pose.to_dict(),
            "terrain": self.terrain.to_dict(),
            "scene_gsd": self.scene_gsd,
            "scene_size": list(self.scene_size),
            "base_size": list(self.base_size),
            "base_from_scene": np.asarray(self.base_from_scene).tolist(),
            "lens_k2": self.lens_k2,
        }

    @classmethod
    def from_dict(cls, d: dict) -> SequenceGeometry:
        return cls(
            width=int(d["width"]),
            height=int(d["height"]),
            gamma=float(d["gamma"]),
            focal_px=float(d["focal_px"]),
            readout_s=float(d["readout_s"]),
            frame_times=np.asarray(d["frame_times"], np.float64),
            pose=PoseTrack.from_dict(d["pose"]),
            terrain=Terrain.from_dict(d["terrain"]),
            scene_gsd=float(d["scene_gsd"]),
            scene_size=tuple(int(v) for v in d["scene_size"]),
            base_size=tuple(int(v) for v in d["base_size"]),
            base_from_scene=np.asarray(d["base_from_scene"], np.float64),
            lens_k2=float(d.get("lens_k2", 0.0)),
        )


def apply_homography(h: NDArray, xy: NDArray) -> NDArray[np.float64]:
    """``(N, 2)`` points through the ``(3, 3)`` homography ``h`` (NaN where w <= 0)."""
    xy = as_points(xy)
    p = xy @ h[:, :2].T + h[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(p[:, 2] > 1e-12, p[:, 2], np.nan)
        return p[:, :2] / w[:, None]


def focal_for_fov(width: int, height: int, gamma: float, fov_deg: float, k2: float = 0.0) -> float:
    """Pinhole focal length (corrected px) giving the *raw* frame a horizontal field of view of
    ``fov_deg`` through the lens (the paper's ~70°, table 1)."""
    model = SimLens(gamma, k2, width, height)
    c = model.c
    edge = model.corrected_from_raw(np.array([[c[0] + width / 2.0, c[1]]]))[0]
    return float((edge[0] - c[0]) / np.tan(np.radians(fov_deg) / 2.0))

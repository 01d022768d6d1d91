"""Rendering raw frames by backward mapping through the truth's own formulas.

For every raw pixel the scene position comes from :meth:`SequenceGeometry.scene_map`; the scene is
sampled from a Gaussian pyramid at the level matching the local stretch (trilinear mip-mapping:
no aliasing where the scene is finer than the frame); moving vehicles are drawn on a copy of the
part of the scene the frame sees (the ground, hence the truth, is untouched); then the camera's
blur, vignetting, noise and JPEG compression.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.geometry import warp
from registration.synth import city as citymod
from registration.synth.camera import SequenceGeometry
from registration.synth.config import SimConfig
from registration.synth.vehicles import moving_vehicles

# Bump when the same SimConfig renders different frames or base (caches such as the demo's
# compare it and rebuild).
RENDER_VERSION = 2
# Dense source maps are evaluated every this many raw pixels and interpolated; the interpolation
# error is checked by the tests (<< 0.05 px).
MAP_STEP = 8
MAX_PYRAMID_LEVEL = 5
# Crops of the scene start on multiples of this, so every pyramid level's pixels stay aligned
# with level 0 (level-l pixel i sits on level-0 pixel 2^l i), with this much support around.
_ALIGN = 2 ** (MAX_PYRAMID_LEVEL + 1)


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


class FrameRenderer:
    """Renders raw frames of one sequence by backward mapping (:meth:`render`).

    Work per frame is proportional to the frame and its footprint, not to the scene: each frame
    samples (and, with vehicles, paints) only the aligned box of the scene it sees, so a long
    flight over a large city costs per frame what a hover does.
    """

    def __init__(
        self, geom: SequenceGeometry, scene: NDArray[np.uint8], cfg: SimConfig, layout=None
    ):
        self.geom, self.cfg, self.layout = geom, cfg, layout
        self.scene = scene
        self._static_levels: list[NDArray] | None = None

    def _box(self, src: NDArray) -> tuple[int, int, int, int]:
        """Aligned scene box ``(x0, y0, x1, y1)`` holding the footprint of ``src`` plus support."""
        sh, sw = self.scene.shape[:2]
        with np.errstate(invalid="ignore"):
            xs, ys = src[..., 0], src[..., 1]
            lo = np.array([np.nanmin(xs), np.nanmin(ys)])
            hi = np.array([np.nanmax(xs), np.nanmax(ys)])
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            return 0, 0, sw, sh
        x0 = max(0, int(np.floor(lo[0])) - _ALIGN) // _ALIGN * _ALIGN
        y0 = max(0, int(np.floor(lo[1])) - _ALIGN) // _ALIGN * _ALIGN
        x1 = min(sw, int(np.ceil(hi[0])) + _ALIGN)
        y1 = min(sh, int(np.ceil(hi[1])) + _ALIGN)
        return x0, y0, max(x1, x0 + 1), max(y1, y0 + 1)

    def render(self, k: int) -> NDArray[np.uint8]:
        """Raw frame ``k`` as ``(H, W, 3)`` uint8 RGB."""
        geom, cfg = self.geom, self.cfg
        src = frame_source_map(geom, k)
        n_levels = min(MAX_PYRAMID_LEVEL, int(np.ceil(float(_level_of_detail(src).max()))))
        x0, y0, x1, y1 = self._box(src)
        if self.layout is not None and cfg.vehicles:
            # Moving vehicles at mid-exposure, on a copy of the scene: the ground (and hence the
            # truth) is untouched.
            img = self.scene[y0:y1, x0:x1].copy()
            t_mid = geom.frame_times[k] + 0.5 * geom.readout_s
            look = citymod.Look()
            az, el = np.radians(look.sun_azimuth_deg), np.radians(look.sun_elevation_deg)
            shadow = np.array([np.cos(az), np.sin(az)]) / np.tan(el) * 1.4 / cfg.gsd_m
            for v in citymod.car_rows(moving_vehicles(self.layout, cfg, t_mid)):
                cx, cy = v[0] - x0, v[1] - y0
                if -20 <= cx <= img.shape[1] + 20 and -20 <= cy <= img.shape[0] + 20:
                    citymod.draw_car(img, cx, cy, int(v[2]), v[3], v[4], v[5:8], shadow=shadow)
            levels = _pyramid(img, n_levels)
        else:
            if self._static_levels is None:
                self._static_levels = _pyramid(self.scene, MAX_PYRAMID_LEVEL)
            # Views of the whole scene's pyramid: positions stay small (cv2.remap's int16 range)
            # however large the scene.
            levels = [
                lvl[y0 >> i : -(-y1 // 2**i), x0 >> i : -(-x1 // 2**i)]
                for i, lvl in enumerate(self._static_levels[: n_levels + 1])
            ]
        return _camera_effects(sample_antialiased(levels, src, (x0, y0)), cfg, k)

"""2D images in viser's 3D scene: pixel <-> world mapping, ray picking, overlays in pixel units.

An image of ``W x H`` pixels is drawn as a plane of ``W*S x H*S`` world units (``S`` =
:data:`WORLD_PER_PX`) centred on the plane's ``position``; local +x is image right and +y is
image down, the camera looks along +z (see ``notes/viser.md`` section 1). Pixel coordinates follow
the project's convention: pixel centres at integers, ``(0, 0)`` = centre of the top-left pixel,
so pixel ``(x, y)`` lies at continuous ``(x + 0.5, y + 0.5)`` from the image corner.

Everything here except :class:`ImagePlane`'s drawing methods is plain numpy, testable without a
server. A plane can show a downscaled preview: it keeps the full-resolution size for geometry,
so overlays in full-resolution pixels stay registered whatever preview is on screen.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

WORLD_PER_PX = 1e-3
"""World units per image pixel: keeps scenes within viser's default camera range (far = 1000)."""

OVERLAY_DZ = -1e-3
"""Overlays sit this far toward the camera (the camera is at negative z) to avoid z-fighting."""


@dataclass(frozen=True)
class PlaneGeometry:
    """Where a ``width x height`` image lies in the scene.

    Attributes:
        width, height: full-resolution image size in pixels.
        position: world position ``(x, y, z)`` of the image centre.
        scale: world units per pixel.
    """

    width: int
    height: int
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = WORLD_PER_PX

    @property
    def render_size(self) -> tuple[float, float]:
        return self.width * self.scale, self.height * self.scale

    def world_from_pixel(self, xy: ArrayLike, dz: float = 0.0) -> NDArray[np.float64]:
        """``(..., 2)`` pixels (centres at integers) -> ``(..., 3)`` world points on the plane."""
        xy = np.asarray(xy, dtype=np.float64)
        px, py, pz = self.position
        wx = (xy[..., 0] + 0.5 - self.width / 2.0) * self.scale + px
        wy = (xy[..., 1] + 0.5 - self.height / 2.0) * self.scale + py
        wz = np.full(xy.shape[:-1], pz + dz)
        return np.stack([wx, wy, wz], axis=-1)

    def pixel_from_world(self, p: ArrayLike) -> NDArray[np.float64]:
        """``(..., 3)`` world points (on the plane) -> ``(..., 2)`` pixels."""
        p = np.asarray(p, dtype=np.float64)
        px, py, _ = self.position
        x = (p[..., 0] - px) / self.scale + self.width / 2.0 - 0.5
        y = (p[..., 1] - py) / self.scale + self.height / 2.0 - 0.5
        return np.stack([x, y], axis=-1)

    def pixel_from_ray(self, origin: ArrayLike, direction: ArrayLike) -> NDArray[np.float64] | None:
        """Intersect a click ray with the plane; ``(2,)`` pixel or None if the ray misses it.

        The result may lie outside the image; use :meth:`contains` to test.
        """
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(direction, dtype=np.float64)
        if abs(d[2]) < 1e-12:
            return None
        t = (self.position[2] - o[2]) / d[2]
        if t <= 0:
            return None
        return self.pixel_from_world(o + t * d)

    def contains(self, xy: ArrayLike, margin: float = 0.0) -> bool:
        """True when pixel ``xy`` lies on the image (within ``margin`` pixels outside it)."""
        x, y = np.asarray(xy, dtype=np.float64)
        return bool(
            -0.5 - margin <= x < self.width - 0.5 + margin
            and -0.5 - margin <= y < self.height - 0.5 + margin
        )

    def ray_towards_pixel(
        self, xy: ArrayLike, camera: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The click ray from ``camera`` (world point) through pixel ``xy`` (for tests)."""
        target = self.world_from_pixel(np.asarray(xy, dtype=np.float64))
        o = np.asarray(camera, dtype=np.float64)
        d = target - o
        return o, d / np.linalg.norm(d)


def segments_world(
    geom: PlaneGeometry, a: ArrayLike, b: ArrayLike, dz: float = OVERLAY_DZ
) -> NDArray[np.float32]:
    """Line segments from pixel points ``a`` (N,2) to ``b`` (N,2) as viser's (N, 2, 3) float32."""
    wa = geom.world_from_pixel(np.asarray(a, dtype=np.float64).reshape(-1, 2), dz)
    wb = geom.world_from_pixel(np.asarray(b, dtype=np.float64).reshape(-1, 2), dz)
    return np.stack([wa, wb], axis=1).astype(np.float32)


def segments_between(
    geom_a: PlaneGeometry, a: ArrayLike, geom_b: PlaneGeometry, b: ArrayLike, dz: float = OVERLAY_DZ
) -> NDArray[np.float32]:
    """Segments from pixels ``a`` on one plane to pixels ``b`` on another (match lines)."""
    wa = geom_a.world_from_pixel(np.asarray(a, dtype=np.float64).reshape(-1, 2), dz)
    wb = geom_b.world_from_pixel(np.asarray(b, dtype=np.float64).reshape(-1, 2), dz)
    return np.stack([wa, wb], axis=1).astype(np.float32)


def polyline_segments(points: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Consecutive pairs of an ``(N, 2)`` polyline as two ``(N-1, 2)`` arrays (start, end)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    return p[:-1], p[1:]


def circle_segments(center: ArrayLike, radius: float, n: int = 48) -> tuple[NDArray, NDArray]:
    """A circle of ``radius`` pixels around ``center`` as ``n`` segments (start, end arrays)."""
    t = np.linspace(0, 2 * np.pi, n + 1)
    c = np.asarray(center, dtype=np.float64).reshape(2)
    ring = c + radius * np.stack([np.cos(t), np.sin(t)], axis=1)
    return ring[:-1], ring[1:]


def cross_segments(center: ArrayLike, size: float) -> tuple[NDArray, NDArray]:
    """A ``+`` marker of half-size ``size`` pixels (two segments)."""
    x, y = np.asarray(center, dtype=np.float64).reshape(2)
    a = np.array([[x - size, y], [x, y - size]])
    b = np.array([[x + size, y], [x, y + size]])
    return a, b


def preview(image: NDArray, max_side: int) -> NDArray:
    """Downscale ``image`` (INTER_AREA) so its longer side is at most ``max_side`` pixels."""
    h, w = image.shape[:2]
    f = max_side / max(h, w)
    if f >= 1.0:
        return image
    size = (max(1, round(w * f)), max(1, round(h * f)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def to_rgb(image: NDArray) -> NDArray[np.uint8]:
    """BGR/grey uint8 image (OpenCV order, as the library reads it) -> RGB uint8 for viser."""
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


@dataclass
class Overlays:
    """Names of overlay nodes drawn on one plane, so they can be removed together."""

    names: set[str] = field(default_factory=set)


class ImagePlane:
    """One image plane in the scene with its overlays (call only from the worker / under lock)."""

    def __init__(self, scene, name: str, geom: PlaneGeometry, *, jpeg_quality: int = 85) -> None:
        self.scene, self.name, self.geom, self.quality = scene, name, geom, jpeg_quality
        self.handle = None
        self._overlays: dict[str, object] = {}

    def show(self, rgb: NDArray, *, fmt: str = "jpeg") -> None:
        """Show an RGB(A) uint8 image (any resolution; stretched over the full-size plane)."""
        w, h = self.geom.render_size
        if self.handle is None:
            self.handle = self.scene.add_image(
                self.name,
                rgb,
                w,
                h,
                format=fmt,
                jpeg_quality=self.quality if fmt == "jpeg" else None,
                position=self.geom.position,
                cast_shadow=False,
                receive_shadow=False,
            )
        else:
            if self.handle.format != fmt:
                self.handle.format = fmt
            self.handle.image = rgb

    def segments(
        self,
        key: str,
        a: ArrayLike,
        b: ArrayLike,
        color,
        *,
        width: float = 2.0,
        dz: float = OVERLAY_DZ,
        visible: bool = True,
    ) -> None:
        """Draw (or replace) segments ``a -> b`` in this plane's pixels; empty input hides it."""
        a = np.asarray(a, dtype=np.float64).reshape(-1, 2)
        b = np.asarray(b, dtype=np.float64).reshape(-1, 2)
        name = f"{self.name}_ov/{key}"
        if len(a) == 0:
            self.remove(key)
            return
        pts = segments_world(self.geom, a, b, dz)
        col = np.asarray(color, dtype=np.uint8)
        if col.ndim == 2:  # per-segment colours -> per-vertex
            col = np.repeat(col[:, None, :], 2, axis=1)
        self._overlays[key] = self.scene.add_line_segments(
            name, pts, col, thickness=width, thickness_units="screen", visible=visible
        )

    def points(self, key: str, xy: ArrayLike, color, *, size_px: float = 6.0) -> None:
        """Draw (or replace) a float32 point cloud at pixels ``xy``; size in image pixels."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if len(xy) == 0:
            self.remove(key)
            return
        pts = self.geom.world_from_pixel(xy, 2 * OVERLAY_DZ).astype(np.float32)
        col = np.asarray(color, dtype=np.uint8)
        if col.ndim == 1:
            col = np.broadcast_to(col, (len(xy), 3)).copy()
        self._overlays[key] = self.scene.add_point_cloud(
            f"{self.name}_ov/{key}",
            pts,
            col,
            point_size=size_px * self.geom.scale,
            point_shape="circle",
            precision="float32",
        )

    def overlay_image(self, key: str, rgba: NDArray, *, dz: float = OVERLAY_DZ / 2) -> None:
        """An image (RGB -> JPEG, RGBA -> PNG) stretched over this plane, slightly in front."""
        w, h = self.geom.render_size
        px, py, pz = self.geom.position
        fmt = "png" if rgba.shape[-1] == 4 else "jpeg"
        handle = self._overlays.get(key)
        if handle is not None and getattr(handle, "format", None) == fmt:
            handle.image = rgba
            handle.visible = True
            return
        self._overlays[key] = self.scene.add_image(
            f"{self.name}_ov/{key}",
            rgba,
            w,
            h,
            format=fmt,
            jpeg_quality=self.quality if fmt == "jpeg" else None,
            position=(px, py, pz + dz),
            cast_shadow=False,
            receive_shadow=False,
        )

    def remove(self, key: str) -> None:
        handle = self._overlays.pop(key, None)
        if handle is not None:
            handle.remove()

    def clear_overlays(self) -> None:
        for key in list(self._overlays):
            self.remove(key)

    def has(self, key: str) -> bool:
        return key in self._overlays


def fit_camera(
    geoms: list[PlaneGeometry],
    fov_rad: float = np.deg2rad(60),
    margin: float = 1.1,
    aspect: float = 1.0,
) -> dict:
    """Top-down camera pose showing all planes: position, look_at, up, fov (for viser).

    ``fov_rad`` is the vertical field of view and ``aspect`` the viewport's width / height; the
    default 1.0 is safe for any landscape viewport.
    """
    lo = np.array([np.inf, np.inf])
    hi = -lo
    for g in geoms:
        w, h = g.render_size
        c = np.asarray(g.position[:2])
        lo = np.minimum(lo, c - (w / 2, h / 2))
        hi = np.maximum(hi, c + (w / 2, h / 2))
    centre = (lo + hi) / 2
    width, height = (hi - lo) * margin
    # Distance at which both the width (through the horizontal field) and the height fit.
    half_tan = np.tan(fov_rad / 2)
    dist = max(height / (2 * half_tan), width / (2 * half_tan * max(aspect, 1e-3)))
    return {
        "position": (float(centre[0]), float(centre[1]), -float(dist)),
        "look_at": (float(centre[0]), float(centre[1]), 0.0),
        "up": (0.0, -1.0, 0.0),
        "fov": float(fov_rad),
    }

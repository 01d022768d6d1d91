"""2D images in viser's 3D scene: pixel <-> world mapping, ray picking, overlays in pixel units.

An image of ``W x H`` pixels is drawn as a plane of ``W*S x H*S`` world units (``S`` =
:data:`WORLD_PER_PX`) centred on the plane's ``position``; local +x is image right and +y is
image down, the camera looks along +z (see ``notes/viser.md`` section 1). Pixel coordinates follow
the project's convention: pixel centres at integers, ``(0, 0)`` = centre of the top-left pixel,
so pixel ``(x, y)`` lies at continuous ``(x + 0.5, y + 0.5)`` from the image corner.

Everything here except :class:`ImagePlane`'s drawing methods is plain numpy, testable without a
server. A plane can show a downscaled preview: it keeps the full-resolution size for geometry,
so overlays in full-resolution pixels stay registered whatever preview is on screen.

Markers and dots keep a fixed size on screen: the app tells each plane how many image pixels one
screen pixel covers (:meth:`ImagePlane.set_zoom`, from the browser's camera), and the plane
resizes them; lines are drawn with screen-pixel thickness. Overlays are clipped to the image.
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


def x_segments(center: ArrayLike, size: float) -> tuple[NDArray, NDArray]:
    """An ``x`` marker of half-size ``size`` pixels (two segments)."""
    x, y = np.asarray(center, dtype=np.float64).reshape(2)
    a = np.array([[x - size, y - size], [x - size, y + size]])
    b = np.array([[x + size, y + size], [x + size, y - size]])
    return a, b


def square_segments(center: ArrayLike, size: float) -> tuple[NDArray, NDArray]:
    """A square outline of half-size ``size`` pixels (four segments)."""
    x, y = np.asarray(center, dtype=np.float64).reshape(2)
    c = np.array(
        [[x - size, y - size], [x + size, y - size], [x + size, y + size], [x - size, y + size]]
    )
    return c, np.roll(c, -1, axis=0)


MARKER_SHAPES = {
    "cross": cross_segments,
    "x": x_segments,
    "square": square_segments,
    "circle": lambda c, r: circle_segments(c, r, 20),
}
"""Marker shapes (``(center, half_size) -> (starts, ends)``) for :meth:`ImagePlane.markers`."""


def clip_segments(
    a: ArrayLike, b: ArrayLike, width: float, height: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Clip segments ``a -> b`` (``(N, 2)`` pixels) to the image ``[-0.5, W-0.5] x [-0.5, H-0.5]``.

    Liang-Barsky. Returns the clipped starts and ends and the ``(N,)`` mask of segments that keep
    a part inside (non-finite segments are dropped).
    """
    a = np.asarray(a, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 2)
    d = b - a
    t0 = np.zeros(len(a))
    t1 = np.ones(len(a))
    keep = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    lo, hi = -0.5, np.array([width - 0.5, height - 0.5])
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in (0, 1):
            for p, q in ((-d[:, axis], a[:, axis] - lo), (d[:, axis], hi[axis] - a[:, axis])):
                parallel = p == 0
                keep &= ~(parallel & (q < 0))
                r = q / p
                entering = ~parallel & (p < 0)
                leaving = ~parallel & (p > 0)
                t0 = np.where(entering, np.maximum(t0, r), t0)
                t1 = np.where(leaving, np.minimum(t1, r), t1)
    keep &= t0 <= t1
    return a + t0[:, None] * d, a + t1[:, None] * d, keep


def inside(xy: ArrayLike, width: float, height: float) -> NDArray[np.bool_]:
    """``(N,)`` mask of finite pixels ``xy`` on a ``width x height`` image."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    with np.errstate(invalid="ignore"):
        return (
            (p[:, 0] >= -0.5)
            & (p[:, 0] <= width - 0.5)
            & (p[:, 1] >= -0.5)
            & (p[:, 1] <= height - 0.5)
        )


def world_per_screen_px(camera_z: float, fov_rad: float, viewport_height_px: int) -> float:
    """World units one screen pixel covers on the plane z = 0 for a top-down camera at height
    ``|camera_z|`` with vertical field of view ``fov_rad``."""
    return (
        2.0 * abs(float(camera_z)) * float(np.tan(fov_rad / 2.0)) / max(int(viewport_height_px), 1)
    )


def auto_vector_scale(lengths: ArrayLike, plane_width: float, fraction: float = 0.03) -> float:
    """Exaggeration for residual vectors so that the 90th-percentile vector is drawn
    ``fraction`` of the plane's width long (1 when there are none), rounded to 1-2-5 steps."""
    v = np.asarray(lengths, dtype=np.float64)
    v = v[np.isfinite(v) & (v > 0)]
    if not len(v):
        return 1.0
    raw = fraction * plane_width / float(np.percentile(v, 90))
    raw = float(np.clip(raw, 1.0, 10000.0))
    exp = 10 ** np.floor(np.log10(raw))
    for m in (1, 2, 5, 10):
        if raw <= m * exp * 1.5:
            return float(m * exp)
    return float(10 * exp)


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
    """One image plane in the scene with its overlays (call only from the worker / under lock).

    Overlays are keyed; drawing a key again replaces it. ``px_per_screen`` (image pixels per
    screen pixel, :meth:`set_zoom`) sizes markers and dots in screen pixels.
    """

    def __init__(self, scene, name: str, geom: PlaneGeometry, *, jpeg_quality: int = 85) -> None:
        self.scene, self.name, self.geom, self.quality = scene, name, geom, jpeg_quality
        self.handle = None
        self._overlays: dict[str, object] = {}
        self._sized: dict[str, tuple] = {}  # key -> how to redraw at another zoom
        self.px_per_screen = max(geom.width, geom.height) / 800.0

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

    def remove_image(self) -> None:
        self.clear_overlays()
        if self.handle is not None:
            self.handle.remove()
            self.handle = None

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
        clip: bool = True,
    ) -> None:
        """Draw (or replace) segments ``a -> b`` in this plane's pixels, clipped to the image;
        ``width`` in screen pixels; empty input removes the key."""
        a = np.asarray(a, dtype=np.float64).reshape(-1, 2)
        b = np.asarray(b, dtype=np.float64).reshape(-1, 2)
        col = np.asarray(color, dtype=np.uint8)
        if clip and len(a):
            a, b, keep = clip_segments(a, b, self.geom.width, self.geom.height)
            a, b = a[keep], b[keep]
            if col.ndim == 2:
                col = col[keep]
        name = f"{self.name}_ov/{key}"
        if len(a) == 0:
            self.remove(key)
            return
        pts = segments_world(self.geom, a, b, dz)
        if col.ndim == 2:  # per-segment colours -> per-vertex
            col = np.repeat(col[:, None, :], 2, axis=1)
        self._overlays[key] = self.scene.add_line_segments(
            name, pts, col, thickness=width, thickness_units="screen", visible=visible
        )

    def points(self, key: str, xy: ArrayLike, color, *, size_px: float = 6.0) -> None:
        """Draw (or replace) dots at pixels ``xy`` (those on the image), ``size_px`` screen
        pixels across whatever the zoom."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        col = np.asarray(color, dtype=np.uint8)
        on = inside(xy, self.geom.width, self.geom.height)
        xy = xy[on]
        if col.ndim == 2:
            col = col[on]
        if len(xy) == 0:
            self.remove(key)
            return
        pts = self.geom.world_from_pixel(xy, 2 * OVERLAY_DZ).astype(np.float32)
        if col.ndim == 1:
            col = np.broadcast_to(col, (len(xy), 3)).copy()
        self._overlays[key] = self.scene.add_point_cloud(
            f"{self.name}_ov/{key}",
            pts,
            col,
            point_size=self._world_size(size_px),
            point_shape="circle",
            precision="float32",
        )
        self._sized[key] = ("points", size_px)

    def markers(
        self,
        key: str,
        xy: ArrayLike,
        color,
        *,
        shape: str = "cross",
        size_px: float = 10.0,
        width: float = 2.0,
        dz: float = 3 * OVERLAY_DZ,
    ) -> None:
        """Draw (or replace) ``shape`` markers (:data:`MARKER_SHAPES`) at pixels ``xy``,
        ``size_px`` screen pixels from centre to edge whatever the zoom."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        col = np.asarray(color, dtype=np.uint8)
        self._sized[key] = ("markers", xy, col, shape, size_px, width, dz)
        self._draw_markers(key)

    def _draw_markers(self, key: str) -> None:
        _, xy, col, shape, size_px, width, dz = self._sized[key]
        on = inside(xy, self.geom.width, self.geom.height)
        half = size_px * self.px_per_screen
        starts, ends, cols = [], [], []
        for i in np.flatnonzero(on):
            s, e = MARKER_SHAPES[shape](xy[i], half)
            starts.append(s)
            ends.append(e)
            c = col[i] if col.ndim == 2 else col
            cols.append(np.broadcast_to(c, (len(s), 3)))
        if not starts:
            spec = self._sized[key]
            self.remove(key)
            self._sized[key] = spec  # kept: the markers come back if drawn again
            return
        self.segments(
            key,
            np.concatenate(starts),
            np.concatenate(ends),
            np.concatenate(cols).astype(np.uint8),
            width=width,
            dz=dz,
            clip=False,
        )

    def set_zoom(self, px_per_screen: float) -> None:
        """The browser now shows ``px_per_screen`` image pixels per screen pixel: resize the
        dots and markers."""
        if not np.isfinite(px_per_screen) or px_per_screen <= 0:
            return
        self.px_per_screen = float(px_per_screen)
        for key, spec in list(self._sized.items()):
            if key not in self._overlays:
                continue
            if spec[0] == "points":
                self._overlays[key].point_size = self._world_size(spec[1])
            elif spec[0] == "markers":
                self._draw_markers(key)

    def _world_size(self, size_px: float) -> float:
        # viser's point shader draws a point of size P as P * height / (z tan(fov/2)) pixels:
        # twice its world size on screen (client ThreeAssets.tsx), hence the half.
        return float(size_px * self.px_per_screen * self.geom.scale / 2.0)

    def overlay_image(
        self,
        key: str,
        rgba: NDArray,
        *,
        box: tuple[float, float, float, float] | None = None,
        dz: float = OVERLAY_DZ / 2,
    ) -> None:
        """An image (RGB -> JPEG, RGBA -> PNG) in front of this plane: over the whole plane, or
        over the box ``(x0, y0, x1, y1)`` whose edges are in corner coordinates (pixel ``i``
        spans ``[i, i + 1)``; a pixel box with ``x1``, ``y1`` exclusive)."""
        x0, y0, x1, y1 = box if box is not None else (0, 0, self.geom.width, self.geom.height)
        s = self.geom.scale
        centre = self.geom.world_from_pixel(
            np.array([(x0 + x1) / 2.0 - 0.5, (y0 + y1) / 2.0 - 0.5]), dz
        )
        w, h = (x1 - x0) * s, (y1 - y0) * s
        fmt = "png" if rgba.shape[-1] == 4 else "jpeg"
        handle = self._overlays.get(key)
        same_place = self._sized.get(key) == ("box", (x0, y0, x1, y1))
        if handle is not None and getattr(handle, "format", None) == fmt and same_place:
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
            position=tuple(centre),
            cast_shadow=False,
            receive_shadow=False,
        )
        self._sized[key] = ("box", (x0, y0, x1, y1))

    def set_visible(self, key: str, visible: bool) -> None:
        handle = self._overlays.get(key)
        if handle is not None:
            handle.visible = bool(visible)

    def remove(self, key: str) -> None:
        handle = self._overlays.pop(key, None)
        self._sized.pop(key, None)
        if handle is not None:
            handle.remove()

    def clear_overlays(self) -> None:
        for key in list(self._overlays):
            self.remove(key)

    def has(self, key: str) -> bool:
        return key in self._overlays

    def overlay(self, key: str):
        """The viser handle drawn under ``key`` (tests and benchmarks), or None."""
        return self._overlays.get(key)


def ring_mesh(square: bool = False, inner: float = 0.6, n: int = 32) -> tuple[NDArray, NDArray]:
    """A flat ring of outer radius 1 (``square``: a square frame of half-size 1) in the z = 0
    plane: ``(vertices (V, 3), faces (F, 3))`` for ``scene.add_mesh_simple``."""
    if square:
        outer = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64)
    else:
        t = np.linspace(0, 2 * np.pi, n, endpoint=False)
        outer = np.stack([np.cos(t), np.sin(t)], axis=1)
    m = len(outer)
    ring = np.concatenate([outer, inner * outer])
    verts = np.concatenate([ring, np.zeros((2 * m, 1))], axis=1).astype(np.float32)
    faces = []
    for i in range(m):
        j = (i + 1) % m
        # Wound to face the camera (which looks along +z with image rows going down).
        faces.append([i, m + i, j])
        faces.append([j, m + i, m + j])
    return verts, np.asarray(faces, np.uint32)


class DragMarker:
    """A grab handle at a pixel of a plane that the analyst can drag: an invisible ring (or
    square) mesh a fixed size on screen, under the visible marker the caller draws with lines
    (scene lighting would darken a coloured mesh). The drag itself is handled by the caller
    (``handle.on_drag``)."""

    def __init__(
        self, scene, name: str, plane: ImagePlane, xy, color, *, square: bool, size_px: float = 13.0
    ) -> None:
        self.plane, self.size_px = plane, size_px
        verts, faces = ring_mesh(square)
        self.xy = np.asarray(xy, np.float64).reshape(2)
        self.handle = scene.add_mesh_simple(
            name,
            verts,
            faces,
            color=tuple(int(c) for c in color),
            side="double",
            opacity=0.0,
            cast_shadow=False,
            receive_shadow=False,
            position=tuple(plane.geom.world_from_pixel(self.xy, 4 * OVERLAY_DZ)),
            scale=self._radius(),
        )

    def _radius(self) -> float:
        return float(self.size_px * self.plane.px_per_screen * self.plane.geom.scale)

    @property
    def radius(self) -> float:
        """The ring's outer radius in world units (its inner one is 0.6 of that)."""
        return self._radius()

    def move_to(self, xy) -> None:
        self.xy = np.asarray(xy, np.float64).reshape(2)
        self.handle.position = tuple(self.plane.geom.world_from_pixel(self.xy, 4 * OVERLAY_DZ))

    def resize(self) -> None:
        self.handle.scale = self._radius()

    def remove(self) -> None:
        self.handle.remove()


def pixel_under_pointer(geom: PlaneGeometry, camera_position: ArrayLike, point: ArrayLike):
    """The plane pixel under the pointer: the ray from the camera through ``point`` (a world
    point the pointer is over, e.g. a drag event's position on its drag plane) meets the image
    plane there. None when the ray misses the plane."""
    o = np.asarray(camera_position, np.float64)
    d = np.asarray(point, np.float64) - o
    n = np.linalg.norm(d)
    if not np.isfinite(n) or n == 0:
        return None
    return geom.pixel_from_ray(o, d / n)


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

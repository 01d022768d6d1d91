"""A procedural city seen from straight above (the base map), and its rendering by two sensors.

:func:`make_layout` draws the geometry once from a seed: a grid of straight streets (2 or 4 lanes,
dashed lane lines, a double centre line, crosswalks and stop lines at intersections), blocks of
buildings (heights, textured roofs with parapets and roof units), parking lots (stalls), parks
with trees. :func:`render_city` paints that layout as one sensor at one time of day sees it (sun
direction for the shadows, which stalls hold parked cars, a snapshot of traffic); the first sensor
(the helicopter camera's world) and a second one (the paper's Google Maps base: other colours,
contrast, blur, noise, shadows and cars, :func:`second_sensor`) share the pixel geometry exactly.

Roofs are painted where the building stands (an orthophoto), i.e. as if on the ground; the
simulator's truth is defined for the terrain surface, so roof pixels are the only place where a
registration may legitimately disagree with the truth by the building's lean.

Units: pixels of the base map; ``gsd`` metres per pixel (default 0.3).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

# Fixed-point shift for sub-pixel cv2 drawing.
_SHIFT = 4
_ONE = 1 << _SHIFT

CAR_COLOURS = np.array(
    [
        [235, 235, 235],
        [240, 240, 240],
        [25, 25, 28],
        [40, 40, 45],
        [120, 120, 125],
        [170, 170, 175],
        [160, 30, 30],
        [30, 50, 140],
        [40, 90, 50],
        [200, 180, 140],
        [210, 200, 60],
        [90, 20, 20],
    ],
    dtype=np.float32,
)  # RGB
# Share of each colour (mostly white, black, grey and silver, as on real roads).
CAR_COLOUR_P = np.array([0.17, 0.1, 0.14, 0.08, 0.12, 0.14, 0.06, 0.06, 0.03, 0.04, 0.02, 0.04])
CAR_COLOUR_P = CAR_COLOUR_P / CAR_COLOUR_P.sum()


@dataclass
class Street:
    """A straight street across the whole map. ``axis`` 0: runs along x (horizontal), 1: along y."""

    axis: int
    centre: float  # px, the coordinate across the street
    lanes: int  # total lanes, half in each direction
    lane_w: float  # px
    sidewalk: float  # px

    @property
    def half(self) -> float:
        return self.lanes * self.lane_w / 2.0


@dataclass
class Building:
    rect: tuple[float, float, float, float]  # x0, y0, x1, y1 px
    height_m: float
    colour: tuple[float, float, float]
    style: int  # 0 flat gravel, 1 ridged, 2 panels


@dataclass
class Layout:
    """The geometry of the city, shared by every rendering."""

    width: int
    height: int
    gsd: float
    seed: int
    streets: list[Street] = field(default_factory=list)
    buildings: list[Building] = field(default_factory=list)
    trees: list[tuple[float, float, float, float]] = field(default_factory=list)  # x, y, r px, h m
    lots: list[tuple[float, float, float, float]] = field(default_factory=list)  # parking lots
    stalls: list[tuple[float, float, int]] = field(default_factory=list)  # centre x, y, axis of car
    greens: list[tuple[float, float, float, float]] = field(default_factory=list)
    plazas: list[tuple[float, float, float, float]] = field(default_factory=list)

    def lanes(self) -> list[tuple[int, float, int]]:
        """Every traffic lane as ``(axis, centre coordinate px, direction ±1)``."""
        out = []
        for s in self.streets:
            n = s.lanes // 2
            for i in range(n):
                off = (i + 0.5) * s.lane_w
                out.append((s.axis, s.centre + off, +1))
                out.append((s.axis, s.centre - off, -1))
        return out


def _streets_along(length: int, gsd: float, rng: np.random.Generator, axis: int) -> list[Street]:
    m = 1.0 / gsd
    out = []
    pos = rng.uniform(20, 60) * m
    while pos < length - 10 * m:
        lanes = int(rng.choice([2, 2, 4, 4, 6], p=[0.35, 0.15, 0.25, 0.15, 0.1]))
        lane_w = rng.uniform(3.2, 3.7) * m
        out.append(Street(axis, pos, lanes, lane_w, rng.uniform(2.0, 3.5) * m))
        pos += rng.uniform(70, 140) * m + lanes * lane_w
    return out


def make_layout(width: int, height: int, *, gsd: float = 0.3, seed: int = 0) -> Layout:
    """Generate the city's geometry for a ``width`` x ``height`` px map at ``gsd`` m/px."""
    if width <= 0 or height <= 0:
        raise ValueError(f"city size must be positive, got {width}x{height}")
    if not gsd > 0:
        raise ValueError(f"gsd must be positive, got {gsd}")
    rng = np.random.default_rng([seed, 101])
    m = 1.0 / gsd
    lay = Layout(width, height, gsd, seed)
    vs = _streets_along(width, gsd, rng, axis=1)
    hs = _streets_along(height, gsd, rng, axis=0)
    lay.streets = hs + vs
    # Block edges: between consecutive streets, inside the sidewalks.
    xe = [(-1e9, 0.0)] + [
        (s.centre - s.half - s.sidewalk, s.centre + s.half + s.sidewalk) for s in vs
    ]
    xe += [(float(width), 1e9)]
    ye = [(-1e9, 0.0)] + [
        (s.centre - s.half - s.sidewalk, s.centre + s.half + s.sidewalk) for s in hs
    ]
    ye += [(float(height), 1e9)]
    for i in range(len(xe) - 1):
        x0, x1 = max(xe[i][1], 0.0), min(xe[i + 1][0], float(width))
        for j in range(len(ye) - 1):
            y0, y1 = max(ye[j][1], 0.0), min(ye[j + 1][0], float(height))
            if x1 - x0 < 8 * m or y1 - y0 < 8 * m:
                continue
            kind = rng.choice(["build", "parking", "park", "mixed"], p=[0.55, 0.12, 0.13, 0.2])
            if kind == "park":
                lay.greens.append((x0, y0, x1, y1))
                _scatter_trees(lay, (x0, y0, x1, y1), rng, density=0.006, gsd=gsd)
            elif kind == "parking":
                _parking(lay, (x0, y0, x1, y1), rng, gsd)
            elif kind == "mixed":
                if x1 - x0 > y1 - y0:
                    xm = x0 + (x1 - x0) * rng.uniform(0.4, 0.6)
                    _buildings(lay, (x0, y0, xm, y1), rng, gsd)
                    _parking(lay, (xm, y0, x1, y1), rng, gsd)
                else:
                    ym = y0 + (y1 - y0) * rng.uniform(0.4, 0.6)
                    _buildings(lay, (x0, y0, x1, ym), rng, gsd)
                    _parking(lay, (x0, ym, x1, y1), rng, gsd)
            else:
                _buildings(lay, (x0, y0, x1, y1), rng, gsd)
    # Street trees along some sidewalks.
    for s in lay.streets:
        if rng.random() < 0.5:
            continue
        spacing = rng.uniform(9, 15) * m
        length = width if s.axis == 0 else height
        for side in (-1, 1):
            across = s.centre + side * (s.half + s.sidewalk * 0.6)
            for a in np.arange(rng.uniform(0, spacing), length, spacing):
                if rng.random() < 0.25:
                    continue
                r = rng.uniform(2.0, 3.5) * m
                x, y = (a, across) if s.axis == 0 else (across, a)
                if not _on_street_crossing(lay, x, y, s.axis):
                    lay.trees.append((x, y, r, rng.uniform(5, 10)))
    return lay


def _on_street_crossing(lay: Layout, x: float, y: float, axis: int) -> bool:
    for s in lay.streets:
        if s.axis == axis:
            continue
        c = y if s.axis == 0 else x
        if abs(c - s.centre) < s.half + s.sidewalk + 4:
            return True
    return False


def _scatter_trees(lay, rect, rng, density, gsd):
    x0, y0, x1, y1 = rect
    m = 1.0 / gsd
    area_m2 = (x1 - x0) * (y1 - y0) * gsd * gsd
    n = rng.poisson(area_m2 * density)
    for _ in range(n):
        r = min(rng.uniform(2.0, 5.5) * m, 0.45 * (x1 - x0), 0.45 * (y1 - y0))
        lay.trees.append(
            (rng.uniform(x0 + r, x1 - r), rng.uniform(y0 + r, y1 - r), r, rng.uniform(5, 14))
        )


def _parking(lay, rect, rng, gsd):
    m = 1.0 / gsd
    x0, y0, x1, y1 = rect
    pad = 2 * m
    x0, y0, x1, y1 = x0 + pad, y0 + pad, x1 - pad, y1 - pad
    if x1 - x0 < 15 * m or y1 - y0 < 15 * m:
        lay.greens.append(rect)
        return
    lay.lots.append((x0, y0, x1, y1))
    stall_w, stall_d, aisle = 2.7 * m, 5.3 * m, 7.0 * m
    horizontal_rows = rng.random() < 0.5  # rows of stalls running along x
    if horizontal_rows:
        y = y0 + 1 * m
        while y + 2 * stall_d + aisle <= y1:
            for row_y in (y, y + stall_d + aisle):
                for x in np.arange(x0 + 1 * m, x1 - stall_w, stall_w):
                    lay.stalls.append((x + stall_w / 2, row_y + stall_d / 2, 1))
            y += 2 * stall_d + aisle + 0.5 * m
    else:
        x = x0 + 1 * m
        while x + 2 * stall_d + aisle <= x1:
            for row_x in (x, x + stall_d + aisle):
                for y in np.arange(y0 + 1 * m, y1 - stall_w, stall_w):
                    lay.stalls.append((row_x + stall_d / 2, y + stall_w / 2, 0))
            x += 2 * stall_d + aisle + 0.5 * m
    # A few trees on the lot's edges.
    for _ in range(rng.integers(0, 4)):
        r = rng.uniform(2, 4) * m
        lay.trees.append((rng.choice([x0 + r, x1 - r]), rng.uniform(y0 + r, y1 - r), r, 8.0))


ROOF_COLOURS = np.array(
    [
        [150, 150, 148],
        [175, 172, 165],
        [120, 118, 115],
        [95, 95, 98],
        [200, 198, 190],
        [165, 120, 95],
        [140, 100, 80],
        [185, 170, 140],
        [110, 115, 120],
        [215, 215, 210],
        [80, 85, 80],
        [150, 140, 120],
    ],
    dtype=np.float32,
)


def _buildings(lay, rect, rng, gsd, depth=0):
    m = 1.0 / gsd
    x0, y0, x1, y1 = rect
    w, h = x1 - x0, y1 - y0
    # Split big lots (binary space partition) into building lots of ~15-60 m.
    if (max(w, h) > 60 * m or (max(w, h) > 28 * m and rng.random() < 0.6)) and depth < 6:
        if w > h:
            xm = x0 + w * rng.uniform(0.35, 0.65)
            _buildings(lay, (x0, y0, xm, y1), rng, gsd, depth + 1)
            _buildings(lay, (xm, y0, x1, y1), rng, gsd, depth + 1)
        else:
            ym = y0 + h * rng.uniform(0.35, 0.65)
            _buildings(lay, (x0, y0, x1, ym), rng, gsd, depth + 1)
            _buildings(lay, (x0, ym, x1, y1), rng, gsd, depth + 1)
        return
    set_back = rng.uniform(0.8, 4.0) * m
    bx0, by0, bx1, by1 = x0 + set_back, y0 + set_back, x1 - set_back, y1 - set_back
    if bx1 - bx0 < 5 * m or by1 - by0 < 5 * m:
        lay.greens.append(rect)
        return
    if rng.random() < 0.12:  # an open plaza or yard instead of a building
        lay.plazas.append(rect)
        _scatter_trees(lay, rect, rng, density=0.004, gsd=gsd)
        return
    height_m = float(
        rng.choice(
            [rng.uniform(4, 12), rng.uniform(12, 30), rng.uniform(30, 70)], p=[0.6, 0.3, 0.1]
        )
    )
    colour = ROOF_COLOURS[rng.integers(len(ROOF_COLOURS))] * rng.uniform(0.88, 1.12)
    lay.plazas.append(rect)  # paved ground around the building
    lay.buildings.append(
        Building(
            (bx0, by0, bx1, by1), height_m, tuple(float(c) for c in colour), int(rng.integers(3))
        )
    )
    if rng.random() < 0.4:
        _scatter_trees(lay, rect, rng, density=0.002, gsd=gsd)


# ------------------------------------------------------------------------------------------
# Rendering


def fractal_noise(
    height: int, width: int, rng: np.random.Generator, *, cell: float, octaves: int = 4
) -> NDArray[np.float32]:
    """Zero-mean, unit-ish ``(height, width)`` fractal noise whose coarsest feature is ``cell`` px."""
    out = np.zeros((height, width), np.float32)
    amp, total = 1.0, 0.0
    for _ in range(octaves):
        gh, gw = max(2, int(height / cell) + 2), max(2, int(width / cell) + 2)
        small = rng.standard_normal((gh, gw)).astype(np.float32)
        out += amp * cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
        total += amp * amp
        amp *= 0.55
        cell /= 2.0
        if cell < 1.0:
            break
    return out / np.float32(np.sqrt(total))


def _rect(img, x0, y0, x1, y1, colour):
    """Filled axis-aligned rectangle with sub-pixel (anti-aliased) edges; coordinates are pixel
    edges (the rectangle covers [x0, x1] x [y0, y1] in continuous coordinates)."""
    pts = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], np.float64) - 0.5
    cv2.fillConvexPoly(img, np.round(pts * _ONE).astype(np.int32), colour, cv2.LINE_AA, _SHIFT)


def _poly(img, pts, colour):
    pts = np.asarray(pts, np.float64) - 0.5
    cv2.fillConvexPoly(img, np.round(pts * _ONE).astype(np.int32), colour, cv2.LINE_AA, _SHIFT)


def _circle(img, x, y, r, colour):
    cv2.circle(
        img,
        (int(round(x * _ONE)), int(round(y * _ONE))),
        int(round(r * _ONE)),
        colour,
        -1,
        cv2.LINE_AA,
        _SHIFT,
    )


@dataclass(frozen=True)
class Look:
    """How one sensor at one time sees the city.

    Attributes:
        sun_azimuth_deg: direction the shadows point, degrees from +x towards +y.
        sun_elevation_deg: shadow length = height / tan(elevation).
        parked_seed: which stalls hold cars (and their colours).
        parked_fraction: share of occupied stalls.
        traffic_seed: seed of a frozen snapshot of moving traffic painted into the image, or None.
        traffic_per_km: vehicles per km of lane for that snapshot.
    """

    sun_azimuth_deg: float = 35.0
    sun_elevation_deg: float = 55.0
    parked_seed: int = 1
    parked_fraction: float = 0.65
    traffic_seed: int | None = None
    traffic_per_km: float = 20.0


def draw_car(img, x, y, axis, length, width, colour, shadow=None):
    """A car (body, darker windscreen/rear window, roof) centred at ``(x, y)``; ``axis`` 0: long
    side along x. ``colour`` RGB float. ``shadow`` = (dx, dy) offset of a soft dark shadow."""
    hl, hw = length / 2.0, width / 2.0
    if axis == 0:
        box = (x - hl, y - hw, x + hl, y + hw)
    else:
        box = (x - hw, y - hl, x + hw, y + hl)
    if shadow is not None:
        dx, dy = shadow
        _rect(img, box[0] + dx, box[1] + dy, box[2] + dx, box[3] + dy, (28, 28, 32))
    c = tuple(float(v) for v in colour)
    _rect(img, *box, c)
    dark = tuple(float(v) * 0.35 + 15 for v in colour)
    roof = tuple(min(255.0, float(v) * 0.92 + 8) for v in colour)
    # Windscreen at the front third, roof in the middle.
    f = 0.22 * length
    if axis == 0:
        _rect(
            img,
            x + hl * 0.15,
            box[1] + 0.15 * width,
            x + hl * 0.15 + f,
            box[3] - 0.15 * width,
            dark,
        )
        _rect(
            img,
            x - hl * 0.55,
            box[1] + 0.18 * width,
            x - hl * 0.55 + f * 0.6,
            box[3] - 0.18 * width,
            dark,
        )
        _rect(img, x - hl * 0.35, box[1] + 0.2 * width, x + hl * 0.15, box[3] - 0.2 * width, roof)
    else:
        _rect(
            img,
            box[0] + 0.15 * width,
            y + hl * 0.15,
            box[2] - 0.15 * width,
            y + hl * 0.15 + f,
            dark,
        )
        _rect(
            img,
            box[0] + 0.18 * width,
            y - hl * 0.55,
            box[2] - 0.18 * width,
            y - hl * 0.55 + f * 0.6,
            dark,
        )
        _rect(img, box[0] + 0.2 * width, y - hl * 0.35, box[2] - 0.2 * width, y + hl * 0.15, roof)


def render_city(lay: Layout, look: Look = Look()) -> NDArray[np.uint8]:
    """Paint ``lay`` as seen with ``look``: ``(H, W, 3)`` uint8 RGB."""
    m = 1.0 / lay.gsd
    rng = np.random.default_rng([lay.seed, 202])  # texture shared by all looks (same ground)
    img, n2 = _paint_ground(lay, rng, m)
    _paint_paving(img, lay)
    # Asphalt patches and stains (texture for correlation on the roads).
    _road_patches(img, lay, rng)
    _paint_stall_lines(img, lay, m)
    _markings(img, lay)
    sun = _sun_offset(look)
    _paint_cars(img, lay, look, sun, m)
    # Cast shadows of buildings and trees (darken), then roofs and canopies on top.
    _cast_shadows(img, lay, sun, m)
    for b in lay.buildings:
        _roof(img, b, m, rng)
    _paint_trees(img, lay, sun, rng)
    # Texture everywhere: multiplicative dirt (large) and grain (small), plus colour speckle.
    n3 = fractal_noise(lay.height, lay.width, rng, cell=30.0, octaves=4)
    img *= (1.0 + 0.07 * n3 + 0.06 * n2)[..., None]
    img += rng.normal(0, 3.0, (lay.height, lay.width, 1)).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)


def _paint_ground(lay: Layout, rng: np.random.Generator, m: float):
    """``(img, grain)``: the ``(H, W, 3)`` float32 ground, dry grass / dirt with large-scale
    variation, and the ``(H, W)`` fine noise the final texture reuses (``m``: px per metre)."""
    W, H = lay.width, lay.height
    n1 = fractal_noise(H, W, rng, cell=120 * m / 3.33, octaves=5)
    n2 = fractal_noise(H, W, rng, cell=8.0, octaves=3)
    base = np.empty((H, W, 3), np.float32)
    base[..., 0] = 128 + 18 * n1
    base[..., 1] = 122 + 14 * n1
    base[..., 2] = 92 + 10 * n1
    return base, n2


def _paint_paving(img: NDArray[np.float32], lay: Layout) -> None:
    """Greens, plazas, the streets' sidewalks and asphalt and the parking lots, in that order."""
    W, H = lay.width, lay.height
    # Greens (parks, leftover yards): grass.
    for x0, y0, x1, y1 in lay.greens:
        _rect(img, x0, y0, x1, y1, (88, 118, 62))
    # Paved plazas and lots around buildings.
    for x0, y0, x1, y1 in lay.plazas:
        _rect(img, x0, y0, x1, y1, (165, 160, 150))
    # Sidewalks, then asphalt.
    for s in lay.streets:
        a0, a1 = s.centre - s.half - s.sidewalk, s.centre + s.half + s.sidewalk
        if s.axis == 0:
            _rect(img, 0, a0, W, a1, (178, 175, 168))
        else:
            _rect(img, a0, 0, a1, H, (178, 175, 168))
    for s in lay.streets:
        a0, a1 = s.centre - s.half, s.centre + s.half
        shade = 78 + 6 * ((s.lanes // 2) % 2)
        if s.axis == 0:
            _rect(img, 0, a0, W, a1, (shade, shade, shade + 3))
        else:
            _rect(img, a0, 0, a1, H, (shade, shade, shade + 3))
    # Parking lots: asphalt with stall lines.
    for x0, y0, x1, y1 in lay.lots:
        _rect(img, x0, y0, x1, y1, (92, 92, 95))


def _paint_stall_lines(img: NDArray[np.float32], lay: Layout, m: float) -> None:
    """The two side lines of every parking stall (``m``: px per metre)."""
    for x, y, axis in lay.stalls:
        hw, hd = 1.35 * m, 2.65 * m
        lw = 0.12 * m + 0.5
        col = (215, 215, 210)
        if axis == 1:
            _rect(img, x - hw - lw / 2, y - hd, x - hw + lw / 2, y + hd, col)
            _rect(img, x + hw - lw / 2, y - hd, x + hw + lw / 2, y + hd, col)
        else:
            _rect(img, x - hd, y - hw - lw / 2, x + hd, y - hw + lw / 2, col)
            _rect(img, x - hd, y + hw - lw / 2, x + hd, y + hw + lw / 2, col)


def _sun_offset(look: Look) -> NDArray[np.float64]:
    """``(2,)`` shadow offset per unit of height (px per px), pointing along the sun's azimuth."""
    az = np.radians(look.sun_azimuth_deg)
    return np.array([np.cos(az), np.sin(az)]) / np.tan(np.radians(look.sun_elevation_deg))


def _paint_cars(img: NDArray[np.float32], lay: Layout, look: Look, sun: NDArray, m: float) -> None:
    """This look's parked cars (drawn from its own seed) and moving traffic, with shadows."""
    prng = np.random.default_rng([lay.seed, 303, look.parked_seed])
    for x, y, axis in lay.stalls:
        if prng.random() < look.parked_fraction:
            col = CAR_COLOURS[prng.choice(len(CAR_COLOURS), p=CAR_COLOUR_P)]
            draw_car(
                img,
                x + prng.normal(0, 0.1 * m),
                y + prng.normal(0, 0.1 * m),
                axis,
                prng.uniform(4.2, 5.0) * m,
                prng.uniform(1.7, 1.9) * m,
                col,
                shadow=sun * 1.4 * m,
            )
    if look.traffic_seed is not None:
        for v in traffic_snapshot(lay, look.traffic_seed, look.traffic_per_km):
            draw_car(img, v[0], v[1], int(v[2]), v[3], v[4], v[5:8], shadow=sun * 1.4 * m)


def _cast_shadows(img: NDArray[np.float32], lay: Layout, sun: NDArray, m: float) -> None:
    """Darken ``img`` where buildings and trees cast their shadows."""
    shadow = np.zeros((lay.height, lay.width), np.uint8)
    for b in lay.buildings:
        x0, y0, x1, y1 = b.rect
        d = sun * b.height_m * m
        pts = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], np.float64)
        hull = cv2.convexHull(np.concatenate([pts, pts + d]).astype(np.float32))[:, 0, :]
        _poly(shadow, hull, 255)
    for x, y, r, hm in lay.trees:
        d = sun * hm * m * 0.8
        _circle(shadow, x + d[0], y + d[1], r * 0.95, 255)
    sh = shadow.astype(np.float32)[..., None] / 255.0
    img *= 1.0 - sh * np.array([0.58, 0.55, 0.48], np.float32)


def _paint_trees(img: NDArray[np.float32], lay: Layout, sun: NDArray, rng: np.random.Generator):
    """The tree canopies: a shade of green, the side lit towards the sun and a few lumps."""
    for x, y, r, _hm in lay.trees:
        g = rng.uniform(0.8, 1.15)
        _circle(img, x, y, r, (52 * g, 78 * g, 40 * g))
        # Lit side of the canopy (towards the sun) and a few lumps.
        _circle(
            img, x - sun[0] * r * 0.25, y - sun[1] * r * 0.25, r * 0.7, (66 * g, 96 * g, 48 * g)
        )
        for _ in range(3):
            ox, oy = rng.uniform(-0.5, 0.5, 2) * r
            _circle(img, x + ox, y + oy, r * rng.uniform(0.2, 0.4), (58 * g, 90 * g, 45 * g))


def _road_patches(img, lay: Layout, rng):
    m = 1.0 / lay.gsd
    for s in lay.streets:
        length = lay.width if s.axis == 0 else lay.height
        n = int(length / m / 25)
        for _ in range(n):
            a = rng.uniform(0, length)
            across = s.centre + rng.uniform(-s.half, s.half) * 0.9
            la, lb = rng.uniform(1, 8) * m, rng.uniform(0.6, 3) * m
            v = rng.uniform(60, 100)
            if s.axis == 0:
                _rect(img, a, across - lb / 2, a + la, across + lb / 2, (v, v, v + 2))
            else:
                _rect(img, across - lb / 2, a, across + lb / 2, a + la, (v, v, v + 2))
        # Oil stains along lane centres.
        for axis, c, _d in [
            (s.axis, s.centre + (i + 0.5) * s.lane_w * sg, 0)
            for i in range(s.lanes // 2)
            for sg in (-1, 1)
        ]:
            for a in rng.uniform(0, length, int(length / m / 12)):
                r = rng.uniform(0.3, 0.8) * m
                if axis == 0:
                    _circle(img, a, c + rng.normal(0, 0.3 * m), r, (55, 55, 58))
                else:
                    _circle(img, c + rng.normal(0, 0.3 * m), a, r, (55, 55, 58))


def _intersections(lay: Layout, s: Street) -> list[tuple[float, float]]:
    """Spans ``(a0, a1)`` along ``s`` covered by crossing streets (incl. sidewalks)."""
    out = []
    for o in lay.streets:
        if o.axis != s.axis:
            out.append((o.centre - o.half - o.sidewalk, o.centre + o.half + o.sidewalk))
    return sorted(out)


def _markings(img, lay: Layout):
    m = 1.0 / lay.gsd
    white, yellow = (225, 225, 220), (215, 185, 60)
    lw = max(0.15 * m, 1.1)  # painted line width, px
    for s in lay.streets:
        length = lay.width if s.axis == 0 else lay.height
        spans = _intersections(lay, s)
        # Segments between intersections.
        edges = [-1e9] + [v for sp in spans for v in sp] + [1e9]
        segs = [
            (max(edges[i], 0.0), min(edges[i + 1], float(length))) for i in range(0, len(edges), 2)
        ]

        def span_rect(a0, a1, c0, c1, col, axis=s.axis):
            if axis == 0:
                _rect(img, a0, c0, a1, c1, col)
            else:
                _rect(img, c0, a0, c1, a1, col)

        for a0, a1 in segs:
            if a1 - a0 < 2 * m:
                continue
            # Double yellow centre line.
            for off in (-0.25 * m, 0.25 * m):
                span_rect(a0, a1, s.centre + off - lw / 2, s.centre + off + lw / 2, yellow)
            # Dashed lane lines: 3 m dash, 9 m gap.
            for i in range(1, s.lanes // 2):
                for sg in (-1, 1):
                    c = s.centre + sg * i * s.lane_w
                    for d in np.arange(a0 + 2 * m, a1 - 3 * m, 12 * m):
                        span_rect(d, d + 3 * m, c - lw / 2, c + lw / 2, white)
            # Edge lines.
            for sg in (-1, 1):
                c = s.centre + sg * (s.half - 0.4 * m)
                span_rect(a0, a1, c - lw / 2, c + lw / 2, white)
            # Crosswalks and stop lines at both ends (not at the map border).
            for end, sgn in ((a0, 1), (a1, -1)):
                if end <= 0 or end >= length:
                    continue
                cw0 = end + sgn * 1.0 * m
                cw1 = end + sgn * 4.0 * m
                lo, hi = min(cw0, cw1), max(cw0, cw1)
                stripe = 0.6 * m
                for c in np.arange(
                    s.centre - s.half + 0.3 * m, s.centre + s.half - stripe, 2 * stripe
                ):
                    span_rect(lo, hi, c, c + stripe, white)
                stop = end + sgn * 5.5 * m
                # The stop line spans the lanes arriving at this end.
                if sgn > 0:  # lanes with direction -1 (centre - off) arrive at a0
                    span_rect(
                        min(stop, stop + sgn * 0.5 * m),
                        max(stop, stop + sgn * 0.5 * m),
                        s.centre - s.half,
                        s.centre,
                        white,
                    )
                else:
                    span_rect(
                        min(stop, stop + sgn * 0.5 * m),
                        max(stop, stop + sgn * 0.5 * m),
                        s.centre,
                        s.centre + s.half,
                        white,
                    )


def _roof(img, b: Building, m: float, rng):
    x0, y0, x1, y1 = b.rect
    col = np.array(b.colour, np.float32)
    _rect(img, x0, y0, x1, y1, tuple(float(v) * 0.7 for v in col))  # parapet / edge
    inset = max(0.5 * m, 1.2)
    _rect(img, x0 + inset, y0 + inset, x1 - inset, y1 - inset, tuple(float(v) for v in col))
    w, h = x1 - x0, y1 - y0
    if b.style == 1:  # ridged / corrugated: stripes across the short side
        step = rng.uniform(0.9, 1.6) * m
        if w > h:
            for x in np.arange(x0 + inset, x1 - inset - step / 2, step):
                _rect(
                    img,
                    x,
                    y0 + inset,
                    x + step / 2,
                    y1 - inset,
                    tuple(float(v) * 0.88 for v in col),
                )
        else:
            for y in np.arange(y0 + inset, y1 - inset - step / 2, step):
                _rect(
                    img,
                    x0 + inset,
                    y,
                    x1 - inset,
                    y + step / 2,
                    tuple(float(v) * 0.88 for v in col),
                )
    elif b.style == 2:  # panels
        nx, ny = max(1, int(w / (6 * m))), max(1, int(h / (6 * m)))
        for i in range(nx):
            for j in range(ny):
                f = rng.uniform(0.9, 1.08)
                px0 = x0 + inset + i * (w - 2 * inset) / nx
                py0 = y0 + inset + j * (h - 2 * inset) / ny
                _rect(
                    img,
                    px0 + 1,
                    py0 + 1,
                    px0 + (w - 2 * inset) / nx - 1,
                    py0 + (h - 2 * inset) / ny - 1,
                    tuple(float(v) * f for v in col),
                )
    # Roof units (air conditioners, vents, stair houses) with little shadows.
    n_units = int(rng.integers(0, 3 + int(w * h / (m * m * 150))))
    for _ in range(min(n_units, 12)):
        uw, uh = rng.uniform(1.2, 4.5, 2) * m
        if uw > w - 3 * inset or uh > h - 3 * inset:
            continue
        ux = rng.uniform(x0 + 1.5 * inset, x1 - 1.5 * inset - uw)
        uy = rng.uniform(y0 + 1.5 * inset, y1 - 1.5 * inset - uh)
        _rect(
            img,
            ux + 0.5 * m,
            uy + 0.5 * m,
            ux + uw + 0.5 * m,
            uy + uh + 0.5 * m,
            tuple(float(v) * 0.55 for v in col),
        )
        v = rng.uniform(150, 230)
        _rect(img, ux, uy, ux + uw, uy + uh, (v, v, v * 0.98))


def traffic_states(
    lay: Layout,
    seed: int,
    per_km: float,
    t: float = 0.0,
    min_gap_m: float | None = None,
    headway_s: float = 0.0,
) -> dict[str, NDArray]:
    """Every vehicle on the lanes at time ``t`` (s), as arrays of one row per vehicle.

    Each vehicle drives along its lane at a constant speed (8-16 m/s) and wraps around at the
    map's edge; the same ``seed`` gives the same traffic at every ``t``. With ``min_gap_m`` None a
    vehicle drives through a slower one ahead (the flights every registration test was measured
    on); with a gap (metres) the vehicles of a lane share its speed (its first vehicle's) and
    stay at least that far apart bumper to bumper, with the same sizes and colours (vehicles of
    crossing lanes still meet at intersections, which have no signals); ``headway_s`` adds the
    distance the lane's speed covers in that time (the desired gap of car-following models,
    ``s0 + v T``: drivers keep about 1-2 s behind the vehicle ahead, not 2 m at 16 m/s; a lane
    too full for it shares out the room it has). Keys: ``vehicle`` (its
    index, stable over time), ``lap`` (how often it wrapped since ``t`` = 0: a wrap teleports
    it, so ``(vehicle, lap)`` is one trajectory), ``x``, ``y`` (centre, px), ``axis`` (0: along
    x), ``direction`` (±1 along the axis), ``speed`` (px/s), ``length``, ``width`` (px),
    ``rgb`` ``(V, 3)``.
    """
    rng = np.random.default_rng([lay.seed, 404, seed])
    m = 1.0 / lay.gsd
    parts: dict[str, list] = {k: [] for k in ("lap", "x", "y", "axis", "direction", "speed")}
    parts.update(length=[], width=[], rgb=[])
    for axis, c, direction in lay.lanes():
        length = lay.width if axis == 0 else lay.height
        n = rng.poisson(per_km * length * lay.gsd / 1000.0)
        s0 = rng.uniform(0, length, n)
        speed = rng.uniform(8, 16, n) * m
        kind = rng.random(n)
        vlen = np.where(kind < 0.9, rng.uniform(4.2, 5.2, n), rng.uniform(8, 12, n)) * m
        vwid = np.where(kind < 0.9, rng.uniform(1.7, 1.95, n), rng.uniform(2.4, 2.6, n)) * m
        cols = CAR_COLOURS[rng.choice(len(CAR_COLOURS), size=n, p=CAR_COLOUR_P)]
        if min_gap_m is not None and n:
            # One speed for the lane (its first vehicle's: the same draws, so sizes and colours
            # stay) and room between its vehicles: one behind another keeps its distance.
            speed = np.full(n, speed[0])
            gap = min_gap_m * m + headway_s * speed[0]
            # A lane too full for the headway keeps what room it has (at least the gap).
            room = (length - float(vlen.sum())) / n
            s0 = _spaced(s0, vlen, max(min_gap_m * m, min(gap, 0.999 * room)), length)
        travelled = s0 + direction * speed * t
        pos = np.mod(travelled, length)
        across = c + rng.normal(0, 0.15 * m, n)
        parts["lap"].append(np.floor_divide(travelled, length).astype(np.int64))
        parts["x"].append(pos if axis == 0 else across)
        parts["y"].append(across if axis == 0 else pos)
        parts["axis"].append(np.full(n, axis, np.int64))
        parts["direction"].append(np.full(n, direction, np.int64))
        parts["speed"].append(speed)
        parts["length"].append(vlen)
        parts["width"].append(vwid)
        parts["rgb"].append(cols.reshape(-1, 3))
    out = {
        k: (np.concatenate(v) if v else np.zeros((0, 3) if k == "rgb" else 0))
        for k, v in parts.items()
    }
    out["vehicle"] = np.arange(len(out["x"]), dtype=np.int64)
    return out


def _spaced(s0: NDArray, vlen: NDArray, gap: float, length: float) -> NDArray:
    """Positions ``s0`` along a ring lane of ``length`` px moved forward, in their order, so that
    consecutive vehicles (lengths ``vlen`` px) are at least ``gap`` px apart bumper to bumper;
    unchanged where they already are. A lane too full for that keeps ``s0``."""
    n = len(s0)
    if n < 2 or float(vlen.sum()) + n * gap > length:
        return s0
    order = np.argsort(s0, kind="stable")
    pos = s0[order].copy()
    half = vlen[order] / 2.0
    # Around the ring until no vehicle moves (the last one's room is before the first one's
    # next lap); it ends because the lane has room for all of them.
    for _ in range(n + 1):
        moved = False
        for i in range(n):
            ahead = pos[i - 1] - (length if i == 0 else 0.0)
            need = ahead + half[i - 1] + half[i] + gap
            if pos[i] < need - 1e-9:
                pos[i], moved = need, True
        if not moved:
            break
    out = np.empty_like(s0)
    out[order] = np.mod(pos, length)
    return out


def traffic_snapshot(lay: Layout, seed: int, per_km: float, t: float = 0.0) -> NDArray[np.float64]:
    """Vehicles on the lanes at time ``t`` (s) (:func:`traffic_states`, each at its own speed)
    as :func:`car_rows`."""
    return car_rows(traffic_states(lay, seed, per_km, t))


def car_rows(v: dict[str, NDArray]) -> NDArray[np.float64]:
    """:func:`traffic_states`' vehicles ``v`` as ``(V, 8)`` rows ``x, y, axis, length px, width
    px, r, g, b``, the form :func:`draw_car` paints."""
    return (
        np.column_stack([v["x"], v["y"], v["axis"], v["length"], v["width"], v["rgb"]])
        .astype(np.float64)
        .reshape(-1, 8)
    )


def second_sensor(image: NDArray[np.uint8], seed: int) -> NDArray[np.uint8]:
    """Make ``image`` look like another sensor's: colour balance, contrast/gamma, blur, noise and
    JPEG-like compression (the paper's Google Maps base vs the helicopter camera)."""
    rng = np.random.default_rng([seed, 505])
    img = image.astype(np.float32) / 255.0
    img = cv2.GaussianBlur(img, (0, 0), 1.1)
    gains = np.array([1.06, 0.98, 0.88], np.float32) * rng.uniform(0.95, 1.05, 3).astype(np.float32)
    img = img * gains
    grey = img.mean(axis=2, keepdims=True)
    img = grey + 0.75 * (img - grey)  # lower saturation
    img = np.clip(img, 0, 1) ** 0.85  # different tone curve
    img = 0.08 + 0.88 * img  # haze: lifted blacks, lower contrast
    img = img + rng.normal(0, 0.012, img.shape[:2] + (1,)).astype(np.float32)
    out = np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, 80])
    return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)

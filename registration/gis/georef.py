"""Georeference of a base map: base pixels <-> map coordinates in the base's CRS, world files,
other CRSs through pyproj.

The affine transform follows GDAL (``conventions.md``, "Map coordinates"): ``A`` maps the
**corner** of pixel (0, 0), so the pixel whose centre sits at integer base coordinates
``(x, y)`` has map coordinates ``A * (x + 0.5, y + 0.5)``, and a map point ``(X, Y)`` lies at
base pixel ``~A * (X, Y) - (0.5, 0.5)``. A world file (``.pgw``, ``.jgw``, ``.tfw``, ``.wld``)
stores the *centre* of pixel (0, 0) instead, i.e. ``A * (0.5, 0.5)``; :func:`read_world_file` and
:func:`world_file_text` convert.

Transform coefficients are ``(a, b, c, d, e, f)`` in the order of the ``affine`` package and
rasterio: ``X = a * col + b * row + c``, ``Y = d * col + e * row + f`` with ``(col, row)`` in
pixel-corner coordinates. pyproj is imported only when a CRS is interpreted.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points

Affine6 = tuple[float, float, float, float, float, float]


def parse_crs(crs: Any) -> Any:
    """A ``pyproj.CRS`` from an EPSG code (``32643``, ``"EPSG:32643"``), a WKT or PROJ string,
    a ``pyproj.CRS`` or a rasterio CRS.

    Raises:
        ValueError: naming the value when pyproj cannot interpret it.
    """
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    if isinstance(crs, CRS):
        return crs
    if hasattr(crs, "to_wkt") and not isinstance(crs, str):  # rasterio.crs.CRS
        crs = crs.to_wkt()
    try:
        return CRS.from_user_input(crs)
    except CRSError as exc:
        text = str(crs)
        shown = text if len(text) <= 60 else text[:57] + "..."
        raise ValueError(f"not a coordinate reference system: {shown!r} ({exc})") from None


def check_map_crs(crs: Any, what: str = "the base map's CRS") -> None:
    """ValueError (one line) unless ``crs`` is a horizontal 2-D CRS, projected or geographic:
    base-map pixels are positions on the ground, which a vertical, geocentric, 3-D or compound
    CRS cannot give."""
    c = parse_crs(crs)
    kind = c.type_name
    if (c.is_projected or c.is_geographic) and len(c.axis_info) == 2 and not c.is_compound:
        return
    name = c.name if len(c.name) <= 60 else c.name[:57] + "..."
    epsg = c.to_epsg()
    shown = f"EPSG:{epsg} ({name})" if epsg else repr(name)
    raise ValueError(
        f"{what} {shown} is a {kind}: a base map needs a horizontal projected or geographic "
        "2-D CRS (for example its UTM zone, or EPSG:4326)"
    )


# A geographic map's pixels larger than this (degrees) is not an orthophoto: most likely a map in
# local metres tagged with a geographic CRS.
MAX_GEOGRAPHIC_PIXEL_DEG = 1.0


def check_plausible(georef: GeoReference, size: tuple[int, int], name: str) -> None:
    """ValueError (one line) for a georeference that cannot be true of a ``size`` (width,
    height) map called ``name``: a CRS that is not horizontal 2-D (:func:`check_map_crs`), or a
    geographic CRS whose pixels are larger than ``MAX_GEOGRAPHIC_PIXEL_DEG`` or whose corners
    leave latitude ±90° or longitude -180..360°."""
    if georef.crs is None:
        return
    check_map_crs(georef.crs, f"{name}'s CRS")
    if not georef.crs.is_geographic:
        return
    w, h = size
    corners = georef.map_from_base(
        np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    )
    px = max(georef.pixel_size)
    lon, lat = corners[:, 0], corners[:, 1]
    if (
        px > MAX_GEOGRAPHIC_PIXEL_DEG
        or np.abs(lat).max() > 90.0
        or lon.min() < -180.0
        or lon.max() > 360.0
    ):
        raise ValueError(
            f"{name} is tagged with the geographic CRS {georef.crs.name!r} but its pixels are "
            f"{px:.4g} degrees and it spans latitude {lat.min():.4g}..{lat.max():.4g}, "
            f"longitude {lon.min():.4g}..{lon.max():.4g}: its coordinates are not degrees "
            "(give its real CRS with --base-crs, or --base-crs none to use it without one)"
        )


@dataclass(frozen=True)
class GeoReference:
    """Where a base map lies on the Earth: its affine transform and coordinate reference system.

    Attributes:
        transform: ``(a, b, c, d, e, f)``, GDAL's pixel-corner convention (module docstring).
        crs_wkt: the CRS as WKT, or None when unknown (a world file without a ``.prj``); map
            coordinates then still work, other CRSs do not. Any form :func:`parse_crs` takes
            (``"EPSG:32643"``, a ``pyproj.CRS``) is accepted and stored as WKT.
    """

    transform: Affine6
    crs_wkt: str | None = None

    def __post_init__(self) -> None:
        t = tuple(float(v) for v in self.transform)
        if len(t) != 6 or not all(math.isfinite(v) for v in t):
            raise ValueError(f"a georeference needs 6 finite affine coefficients, got {t}")
        a, b, _, d, e, _ = t
        if abs(a * e - b * d) < 1e-300:
            raise ValueError(f"the affine transform {t} is singular (zero pixel area)")
        object.__setattr__(self, "transform", t)
        crs = self.crs_wkt
        if crs is not None and not (isinstance(crs, str) and "[" in crs):
            object.__setattr__(self, "crs_wkt", parse_crs(crs).to_wkt())

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_affine(cls, affine, crs: Any = None) -> GeoReference:
        """From an ``affine.Affine`` (rasterio's ``dataset.transform``) and any CRS form."""
        t = (affine.a, affine.b, affine.c, affine.d, affine.e, affine.f)
        return cls(t, None if crs is None else parse_crs(crs).to_wkt())

    @classmethod
    def from_dict(cls, d: dict | None) -> GeoReference | None:
        """Inverse of :meth:`to_dict` (None stays None)."""
        if not d:
            return None
        return cls(tuple(d["transform"]), d.get("crs_wkt"))

    def to_dict(self) -> dict:
        """JSON-ready: ``transform``, ``crs_wkt``, plus ``epsg``, ``units`` and ``pixel_size``
        for people reading ``result.json`` (ignored when reading back)."""
        return {
            "transform": list(self.transform),
            "convention": "GDAL: transform maps the corner of pixel (0,0); base pixel (x,y) "
            "is at transform*(x+0.5, y+0.5)",
            "crs_wkt": self.crs_wkt,
            "epsg": self.epsg,
            "units": self.units,
            "pixel_size": list(self.pixel_size),
        }

    # -- properties --------------------------------------------------------------------------
    @property
    def affine(self):
        """The transform as ``affine.Affine`` (what rasterio writes)."""
        from affine import Affine

        return Affine(*self.transform)

    @cached_property
    def crs(self):
        """The CRS as ``pyproj.CRS``, or None."""
        return None if self.crs_wkt is None else parse_crs(self.crs_wkt)

    @property
    def epsg(self) -> int | None:
        """The EPSG code when the CRS matches one exactly, else None."""
        return None if self.crs is None else self.crs.to_epsg()

    @property
    def units(self) -> str | None:
        """Unit of the map coordinates (e.g. ``"metre"``, ``"degree"``), or None."""
        if self.crs is None or not self.crs.axis_info:
            return None
        return self.crs.axis_info[0].unit_name

    @property
    def pixel_size(self) -> tuple[float, float]:
        """Ground size of one base pixel along its columns and rows, in map units."""
        a, b, _, d, e, _ = self.transform
        return math.hypot(a, d), math.hypot(b, e)

    # -- mapping -----------------------------------------------------------------------------
    def map_from_base(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` base pixels (centres at integers) -> ``(N, 2)`` map coordinates."""
        p = as_points(xy, "xy") + 0.5
        a, b, c, d, e, f = self.transform
        return np.c_[a * p[:, 0] + b * p[:, 1] + c, d * p[:, 0] + e * p[:, 1] + f]

    def base_from_map(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` map coordinates -> ``(N, 2)`` base pixels (centres at integers)."""
        a, b, c, d, e, f = self.transform
        # Offsets first: map coordinates are large (UTM northings ~1e6), their differences not.
        p = as_points(xy, "xy") - (c, f)
        inv = np.linalg.inv(np.array([[a, b], [d, e]]))
        return p @ inv.T - 0.5

    def to_crs(self, xy_map: ArrayLike, crs: Any) -> NDArray[np.float64]:
        """Map coordinates of this georeference -> coordinates in ``crs`` (``"EPSG:4326"``, ...).

        Axis order is always (x, y) = (easting, northing) or (longitude, latitude), whatever
        the CRS's official axis order (pyproj ``always_xy``). NaN rows stay NaN.
        """
        return _transform(self._require_crs(), parse_crs(crs), xy_map)

    def from_crs(self, xy: ArrayLike, crs: Any) -> NDArray[np.float64]:
        """Coordinates in ``crs`` (x, y order as in :meth:`to_crs`) -> this georeference's map."""
        return _transform(parse_crs(crs), self._require_crs(), xy)

    def _require_crs(self):
        if self.crs is None:
            raise ValueError(
                "the base map's CRS is unknown (a world file without .prj?): give it explicitly"
            )
        return self.crs

    # -- derived grids -----------------------------------------------------------------------
    def cropped(self, x0: float, y0: float) -> GeoReference:
        """The georeference of a crop whose pixel (0, 0) is base pixel ``(x0, y0)``."""
        a, b, c, d, e, f = self.transform
        return GeoReference((a, b, c + a * x0 + b * y0, d, e, f + d * x0 + e * y0), self.crs_wkt)

    def scaled(self, sx: float, sy: float | None = None) -> GeoReference:
        """The georeference of the image resized by ``sx`` along its columns and ``sy`` (default
        ``sx``) along its rows (0.5 = half as many pixels); the outer corner stays put."""
        a, b, c, d, e, f = self.transform
        ix, iy = 1.0 / float(sx), 1.0 / float(sx if sy is None else sy)
        return GeoReference((a * ix, b * iy, c, d * ix, e * iy, f), self.crs_wkt)

    def bounds(self, width: int, height: int) -> tuple[float, float, float, float]:
        """``(left, bottom, right, top)`` of a ``width`` x ``height`` image's outer edges."""
        corners = np.array([[0, 0], [width, 0], [0, height], [width, height]], float) - 0.5
        m = self.map_from_base(corners)
        return (
            float(m[:, 0].min()),
            float(m[:, 1].min()),
            float(m[:, 0].max()),
            float(m[:, 1].max()),
        )


def _transform(src, dst, xy: ArrayLike) -> NDArray[np.float64]:
    from pyproj import Transformer

    p = as_points(xy, "xy")
    out = np.full_like(p, np.nan)
    ok = np.isfinite(p).all(axis=1)  # NaN stays NaN (pyproj would give inf)
    if ok.any():
        tr = Transformer.from_crs(src, dst, always_xy=True)
        x, y = tr.transform(p[ok, 0], p[ok, 1])
        out[ok] = np.c_[np.asarray(x, float), np.asarray(y, float)]
    return out


# --------------------------------------------------------------------------------------------
# World files


def world_file_candidates(image_path: str | os.PathLike) -> list[Path]:
    """Sidecar world-file names GDAL looks for beside ``image_path``, in its order:
    ``.pgw``/``.jgw``/``.tfw`` (first and last letter of the suffix + ``w``), ``.pngw``/``.jpgw``
    (suffix + ``w``), ``.wld``."""
    p = Path(image_path)
    suf = p.suffix.lower()
    names = []
    if len(suf) >= 3:
        names.append(suf[:2] + suf[-1] + "w")
    names += [suf + "w", ".wld"]
    out = []
    for n in names:
        out += [p.with_suffix(n), p.with_suffix(n.upper())]
    return out


def find_world_file(image_path: str | os.PathLike) -> Path | None:
    """The world file beside ``image_path``, or None."""
    for c in world_file_candidates(image_path):
        if c.is_file():
            return c
    return None


def read_world_file(path: str | os.PathLike) -> Affine6:
    """A world file's six lines ``A D B E C F`` -> the pixel-corner transform ``(a..f)``.

    The file gives the map coordinates ``(C, F)`` of the *centre* of pixel (0, 0), so the
    corner is half a pixel up and left of it.

    Raises:
        ValueError: naming the file when it does not hold six numbers.
    """
    p = Path(path)
    try:
        values = [float(v) for v in p.read_text(encoding="utf-8-sig").split()]
    except (ValueError, UnicodeDecodeError):
        raise ValueError(f"world file {p.name} must hold six numbers, one a line") from None
    if len(values) != 6 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"world file {p.name} must hold six numbers, got {len(values)}")
    a, d, b, e, cx, cy = values
    return (a, b, cx - 0.5 * a - 0.5 * b, d, e, cy - 0.5 * d - 0.5 * e)


PIXEL_GRID = GeoReference((1.0, 0.0, 0.0, 0.0, -1.0, 0.0), None)
"""A plain base map's own pixels as GIS software shows an image without a georeference (QGIS,
its Georeferencer's ``.points``): the corner of pixel (0, 0) at (0, 0), columns along x, rows
along -y. World files and ``.points`` of a plain base are written in it, so that registered
frames and control points land on the base image opened beside them."""


def world_file_text(transform: Affine6) -> str:
    """The six lines of a world file for a pixel-corner transform (inverse of
    :func:`read_world_file`)."""
    a, b, c, d, e, f = (float(v) for v in transform)
    values = (a, d, b, e, c + 0.5 * a + 0.5 * b, f + 0.5 * d + 0.5 * e)
    return "".join(f"{v!r}\n" for v in values)


def world_file_suffix(image_suffix: str) -> str:
    """``.png`` -> ``.pgw``, ``.jpg`` -> ``.jgw``, ``.tif`` -> ``.tfw``."""
    s = image_suffix.lower()
    return s[:2] + s[-1] + "w" if len(s) >= 3 else ".wld"


def read_sidecar_crs(image_path: str | os.PathLike) -> str | None:
    """The CRS stored beside an image as WKT: ``<stem>.prj`` (ESRI) or ``<name>.aux.xml``
    (GDAL's ``<SRS>`` element); None when there is neither."""
    p = Path(image_path)
    for prj in (p.with_suffix(".prj"), p.with_suffix(".PRJ"), Path(str(p) + ".prj")):
        if prj.is_file():
            return parse_crs(prj.read_text(encoding="utf-8-sig").strip()).to_wkt()
    aux = Path(str(p) + ".aux.xml")
    if aux.is_file():
        import xml.etree.ElementTree as ET

        try:
            srs = ET.parse(aux).getroot().find("SRS")
        except ET.ParseError:
            raise ValueError(f"{aux.name} is not valid XML") from None
        if srs is not None and srs.text and srs.text.strip():
            return parse_crs(srs.text.strip()).to_wkt()
    return None


def esri_wkt(crs_wkt: str) -> str:
    """The CRS in the ESRI WKT flavour that ``.prj`` files use."""
    from pyproj.enums import WktVersion

    return parse_crs(crs_wkt).to_wkt(WktVersion.WKT1_ESRI)


def aux_xml_text(crs_wkt: str) -> str:
    """A minimal GDAL PAM sidecar (``<name>.aux.xml``) carrying the CRS, which GDAL and QGIS
    read for PNG/JPEG images (a world file holds no CRS)."""
    from xml.sax.saxutils import escape

    return f"<PAMDataset>\n  <SRS>{escape(crs_wkt)}</SRS>\n</PAMDataset>\n"

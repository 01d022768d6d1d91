"""Reading the base map: GeoTIFFs through rasterio and plain images with a world file, their
georeference, bands to BGR (palette, 16-bit and float data stretched to 8 bits) and no-data as a
mask that matching respects.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.io.images import (
    GDAL_READ_BYTES_PER_PIXEL,
    MAX_BASE_PIXELS,
    check_image_size,
    check_memory,
    decode_image_file,
)

# --------------------------------------------------------------------------------------------
# Base maps (georeferenced or plain)

# Read with rasterio (GDAL): the georeference sits inside the file.
GDAL_SUFFIXES = {".tif", ".tiff", ".gtif", ".gtiff", ".jp2", ".img", ".vrt"}
# Read with OpenCV; a world file (+ .prj or .aux.xml) beside it gives the georeference.
PLAIN_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".webp"}
# Percentiles of the robust stretch of 16-bit / float base maps to 8 bits.
STRETCH_PERCENTILES = (0.5, 99.5)
# "Black" of a no-data collar: exactly 0 in lossless files, up to this level in JPEG-compressed
# ones (compression rings around the collar's edge).
LOSSY_BLACK_LEVEL = 8


@dataclass
class BaseMap:
    """A base map ready for matching.

    Attributes:
        image: ``(H, W, 3)`` BGR uint8.
        valid: ``(H, W)`` bool, False where the map has no data (no-data value, alpha, mask,
            transparent palette entries, the black collar of a rotated orthophoto).
        georef: the map's :class:`registration.gis.georef.GeoReference`, or None for a plain image.
        path: the file read.
        notes: what was converted, for logs (e.g. ``"palette -> RGB (256 colours)"``).
    """

    image: NDArray[np.uint8]
    valid: NDArray[np.bool_]
    georef: Any = None
    path: str = ""
    notes: list[str] = field(default_factory=list)

    @property
    def size(self) -> tuple[int, int]:
        return int(self.image.shape[1]), int(self.image.shape[0])

    @property
    def valid_or_none(self) -> NDArray[np.bool_] | None:
        """``valid``, or None when every pixel is valid (matching can skip the mask)."""
        return None if self.valid.all() else self.valid


def read_base_map(
    path: str | os.PathLike, *, crs: Any = None, nodata: str | float = "auto"
) -> BaseMap:
    """Read a base map: pixels converted for matching, no-data mask and georeference.

    * **GeoTIFF** (and other GDAL rasters: ``.jp2``, ``.img``, ``.vrt``) through rasterio: affine
      transform and CRS from the file (or its ``.tfw``/``.aux.xml`` sidecars, which GDAL reads).
    * **PNG/JPEG/BMP/WebP** through OpenCV; georeferenced by a world file beside it (``.pgw``,
      ``.jgw``, ``.pngw``, ``.wld``; see :mod:`registration.gis.georef` for its half-pixel offset)
      with the CRS from ``crs``, ``<stem>.prj`` or ``<name>.aux.xml``. Without a world file
      the map is a plain image (``georef`` None) and everything stays in base pixels.

    Pixel conversions:

    * palette (colour-mapped) images: each index through the file's colour table to RGB;
      entries with alpha 0 and the no-data index are invalid;
    * 1 band grey -> grey in all three channels; 3+ bands: the bands the file labels red, green
      and blue (else the first three); an alpha band (or a band-less GDAL mask) -> ``valid``;
    * 16-bit, 32-bit and float data: a **robust percentile stretch** to 8 bits, the same linear
      map for all bands: value at the 0.5th percentile of the valid pixels -> 0, at the 99.5th
      -> 255, clipped (keeps colour balance; a few hot pixels cannot darken the whole map).

    Args:
        path: the file.
        crs: CRS of the map (EPSG code, ``"EPSG:32643"``, WKT): for a world file without
            ``.prj``, or to override the file's; ``"none"`` ignores the file's georeference (a
            map in local units whose tag cannot be true).
        nodata: ``"auto"`` (default): the file's own no-data (tag, alpha, mask) plus a black
            collar: pixels black in every band (after the palette) *connected to the image
            border*, how rotated orthophotos are filled even without a no-data tag; dark
            shadows inside the map stay valid. ``"file"``: only the file's own declarations.
            A number: additionally every pixel equal to it in all bands (source values; for a
            palette image, the index), GDAL's meaning of a no-data value.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: unreadable file, a bad world file or CRS, a map without valid pixels.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"image not found: {p}")
    if p.is_dir():
        raise ValueError(f"{p} is a directory, not an image file")
    if p.stat().st_size == 0:
        raise ValueError(f"image file {p} is empty")
    if not (nodata in ("auto", "file") or isinstance(nodata, (int, float))):
        raise ValueError(f"nodata must be 'auto', 'file' or a number, got {nodata!r}")
    ignore_georef = _is_none(crs)
    crs = None if ignore_georef else crs
    if p.suffix.lower() in PLAIN_SUFFIXES:
        base = _read_plain_base(p, crs, nodata)
    else:
        base = _read_gdal_base(p, crs, nodata)
    if ignore_georef and base.georef is not None:
        base = dataclasses.replace(
            base, georef=None, notes=[*base.notes, "georeference ignored (CRS none)"]
        )
    if not base.valid.any():
        raise ValueError(f"base map {p.name} has no valid pixels (all no-data)")
    if base.georef is not None:
        from registration.gis.georef import check_plausible

        check_plausible(base.georef, base.size, f"base map {p.name}")
    return base


def read_georeference(path: str | os.PathLike, *, crs: Any = None):
    """Only the georeference of a base map file and its ``(width, height)``, without decoding
    the pixels of a GeoTIFF (what :func:`read_base_map` would give as ``georef``).

    Returns:
        ``(georef or None, (width, height))``.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"georeference file not found: {p}")
    if _is_none(crs):
        return None, _read_georeference(p, None)[1]
    georef, size = _read_georeference(p, crs)
    if georef is not None:
        from registration.gis.georef import check_plausible

        check_plausible(georef, size, f"georeference {p.name}")
    return georef, size


def _is_none(crs: Any) -> bool:
    """``crs`` "none": the map is used without its file's georeference (a map in local units)."""
    return isinstance(crs, str) and crs.strip().lower() == "none"


def _read_georeference(p: Path, crs: Any):
    if p.suffix.lower() in PLAIN_SUFFIXES:
        base = _read_plain_base(p, crs, "file")
        return base.georef, base.size
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

    from registration.gis import georef as gis_georef

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(p) as ds:
                size = (ds.width, ds.height)
                if ds.transform.is_identity and ds.crs is None:
                    return None, size
                file_crs = crs if crs is not None else ds.crs or gis_georef.read_sidecar_crs(p)
                return gis_georef.GeoReference.from_affine(ds.transform, file_crs), size
    except RasterioIOError as exc:
        raise ValueError(f"not a readable raster: {p} ({str(exc).splitlines()[0]})") from None


def _read_plain_base(p: Path, crs: Any, nodata) -> BaseMap:
    from registration.gis import georef as gis_georef

    # Size limits from the header before decoding, truncated files refused (decode_image_file).
    img = decode_image_file(p, max_pixels=MAX_BASE_PIXELS)
    notes: list[str] = []
    if img.ndim == 2:
        img = img[:, :, None]
    valid = np.ones(img.shape[:2], bool)
    if img.shape[2] in (2, 4):
        valid = img[:, :, -1] > 0
        img = img[:, :, :-1]
        notes.append("alpha channel -> no-data mask")
    bands = np.moveaxis(img, 2, 0)  # OpenCV's channel order is already BGR
    lossy = p.suffix.lower() in (".jpg", ".jpeg")
    image, valid = _bands_to_bgr(bands, valid, nodata, lossy, notes)
    world = gis_georef.find_world_file(p)
    georef = None
    if world is not None:
        wkt = (
            gis_georef.parse_crs(crs).to_wkt()
            if crs is not None
            else gis_georef.read_sidecar_crs(p)
        )
        georef = gis_georef.GeoReference(gis_georef.read_world_file(world), wkt)
        notes.append(f"georeferenced by world file {world.name}" + ("" if wkt else " (no CRS)"))
    elif crs is not None:
        raise ValueError(
            f"a CRS was given but {p.name} has no world file ({', '.join(c.name for c in gis_georef.world_file_candidates(p)[::2])})"
        )
    return BaseMap(image, valid, georef, str(p), notes)


def _read_gdal_base(p: Path, crs: Any, nodata) -> BaseMap:
    import warnings

    import rasterio
    from rasterio.enums import ColorInterp, MaskFlags
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

    from registration.gis import georef as gis_georef

    notes: list[str] = []
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            ds = rasterio.open(p)
    except RasterioIOError as exc:
        raise ValueError(f"not a readable raster: {p} ({str(exc).splitlines()[0]})") from None
    with ds:
        # The raster's size from its header, before any pixel is read.
        check_image_size((ds.width, ds.height), p, max_pixels=MAX_BASE_PIXELS)
        item = max(np.dtype(t).itemsize for t in ds.dtypes)
        check_memory(
            (ds.width, ds.height), p, bytes_per_pixel=GDAL_READ_BYTES_PER_PIXEL + 6 * (item - 1)
        )
        interp = list(ds.colorinterp)
        lossy = str(getattr(ds.compression, "value", ds.compression)).upper() in ("JPEG", "WEBP")
        has_mask = any(flags != [MaskFlags.all_valid] for flags in ds.mask_flag_enums)
        palette = ds.count == 1 and interp[0] == ColorInterp.palette
        if not palette and _blank(ds, _colour_bands(ds, interp), nodata):
            raise ValueError(f"base map {p.name} has no valid pixels (all no-data)")
        valid = ds.dataset_mask() > 0 if has_mask else np.ones((ds.height, ds.width), bool)
        if has_mask:
            notes.append("file's no-data/alpha/mask -> no-data mask")
        if palette:
            index = ds.read(1)
            bands, valid = _expand_palette(index, ds.colormap(1), valid, nodata, notes)
            nodata = "file" if not isinstance(nodata, str) else nodata  # applied to the index
        else:
            idx = _colour_bands(ds, interp)
            if ds.count > len(idx) and ColorInterp.alpha not in interp:
                notes.append(f"bands {idx} of {ds.count} used as colour")
            bands = ds.read(idx)[::-1] if len(idx) == 3 else ds.read(idx)
        georef = None
        if not (ds.transform.is_identity and ds.crs is None):
            if crs is not None:
                georef = gis_georef.GeoReference.from_affine(ds.transform, crs)
                notes.append("CRS given explicitly")
            else:
                file_crs = ds.crs if ds.crs is not None else gis_georef.read_sidecar_crs(p)
                georef = gis_georef.GeoReference.from_affine(ds.transform, file_crs)
        elif crs is not None:
            raise ValueError(f"a CRS was given but {p.name} has no affine transform")
        elif ds.gcps[0]:
            notes.append("ground control points in the file are not used (no affine transform)")
    image, valid = _bands_to_bgr(bands, valid, nodata, lossy, notes)
    return BaseMap(image, valid, georef, str(p), notes)


def _colour_bands(ds, interp) -> list[int]:
    """The raster's bands read as colour: red, green, blue by their colour interpretation, else
    the first three, else the first."""
    from rasterio.enums import ColorInterp

    named = {ci: i + 1 for i, ci in reversed(list(enumerate(interp)))}
    rgb = [named.get(c) for c in (ColorInterp.red, ColorInterp.green, ColorInterp.blue)]
    if all(rgb):
        return rgb
    return [1, 2, 3] if ds.count >= 3 else [1]


BLANK_CHECK_PIXELS = 16_000_000
"""Rasters larger than this are first scanned window by window, stopping at the first window
that holds data, to refuse a blank one (all black with ``nodata="auto"``, or all the given
no-data value) before it is read whole: a blank 15000x15000 GeoTIFF compresses to 770 KB, and
reading it whole took 14.6 s and 5.84 GB before it was refused."""
BLANK_CHECK_WINDOW = 1024


def _blank(ds, idx: list[int], nodata) -> bool:
    """Whether bands ``idx`` of the open raster ``ds`` hold only no-data (a map's first window
    with data ends the scan; memory: one window)."""
    import rasterio
    from rasterio.windows import Window

    w, h = ds.width, ds.height
    if w * h <= BLANK_CHECK_PIXELS or nodata == "file":
        return False
    blank_value = 0 if nodata == "auto" else nodata
    step = BLANK_CHECK_WINDOW
    # GDAL would keep every block read in its cache (5 % of the memory): a small one here.
    with rasterio.Env(GDAL_CACHEMAX=64):
        for y in range(0, h, step):
            for x in range(0, w, step):
                block = ds.read(idx, window=Window(x, y, min(step, w - x), min(step, h - y)))
                if (block != blank_value).any():
                    return False
    return True


def _expand_palette(index: NDArray, colormap: dict, valid, nodata, notes):
    """Palette indices -> ``(3, H, W)`` BGR bands through the colour table, and the mask of
    transparent entries and a no-data index."""
    n = max(int(index.max()) + 1, max(colormap) + 1 if colormap else 1)
    lut = np.zeros((n, 4), np.uint8)
    for i, rgba in colormap.items():
        lut[i] = rgba
    rgba = lut[index]
    valid = valid & (rgba[..., 3] > 0)
    if not isinstance(nodata, str):
        valid &= index != nodata
    notes.append(f"palette -> RGB ({len(colormap)} colours)")
    return np.moveaxis(rgba[..., 2::-1], 2, 0), valid


def _bands_to_bgr(bands: NDArray, valid, nodata, lossy: bool, notes: list[str]):
    """``(C, H, W)`` bands (C = 1 grey or 3 BGR, any dtype) -> BGR uint8 image and ``valid``."""
    if not isinstance(nodata, str):
        valid = valid & ~(bands == nodata).all(axis=0)
    black = (bands == 0).all(axis=0)
    if bands.dtype != np.uint8:
        dtype = bands.dtype.name
        bands, (lo, hi) = stretch_to_uint8(bands, valid)
        notes.append(
            f"{dtype} data stretched to 8 bits: {lo:g} -> 0, {hi:g} -> 255 "
            f"(percentiles {STRETCH_PERCENTILES[0]:g} and {STRETCH_PERCENTILES[1]:g})"
        )
    if lossy:
        black = (bands <= LOSSY_BLACK_LEVEL).all(axis=0)
    if nodata == "auto" and black.any():
        collar = border_connected(black)
        if collar.any():
            valid = valid & ~collar
            notes.append(f"black collar -> no-data ({100 * collar.mean():.1f} % of the map)")
    image = np.ascontiguousarray(np.moveaxis(bands, 0, 2))
    if image.shape[2] == 1:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return image, valid


def border_connected(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """The parts of ``mask`` (4-)connected to the image border."""
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=4)
    if n <= 1:
        return np.zeros_like(mask, bool)
    edge = np.unique(np.r_[labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    edge = edge[edge > 0]
    return np.isin(labels, edge)


def stretch_to_uint8(
    bands: NDArray, valid: NDArray[np.bool_] | None = None, percentiles=STRETCH_PERCENTILES
) -> tuple[NDArray[np.uint8], tuple[float, float]]:
    """Linear stretch of ``(C, H, W)`` data to uint8, one map for all bands: the ``percentiles``
    of the valid pixels' values (all bands pooled, NaN ignored) go to 0 and 255.

    Returns:
        The uint8 bands and the ``(low, high)`` source values used.
    """
    data = np.asarray(bands)
    pool = data[:, valid] if valid is not None and valid.shape == data.shape[1:] else data
    pool = pool.reshape(-1)
    # A deterministic subsample keeps percentiles cheap on large maps.
    step = max(1, pool.size // 2_000_000)
    pool = pool[::step].astype(np.float64)
    pool = pool[np.isfinite(pool)]
    if not pool.size:
        return np.zeros(data.shape, np.uint8), (0.0, 0.0)
    lo, hi = (float(v) for v in np.percentile(pool, percentiles))
    if hi <= lo:
        hi = lo + 1.0
    out = (np.nan_to_num(data.astype(np.float32), nan=lo) - lo) * (255.0 / (hi - lo))
    return np.clip(out + 0.5, 0, 255).astype(np.uint8), (lo, hi)

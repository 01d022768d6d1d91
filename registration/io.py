"""Reading frames and images, and writing files atomically. The only disk access of the pipeline.

A frame source is a video file (read with imageio/ffmpeg frame by frame, never the whole video
in memory), a directory of images (sorted by name), or a glob pattern. Frames are BGR uint8.
"""

from __future__ import annotations

import copy
import glob as globlib
import hashlib
import json
import os
import struct
import tempfile
import threading
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}
VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".webm"}

# Limits on what is read (README "Reliability"). The paper's frames are 2560x1920 = 4.9 MP; an
# 8K video frame is 33 MP. A base map covers more ground than a frame and may be larger.
MIN_IMAGE_SIDE = 16
MAX_FRAME_PIXELS = 100_000_000
MAX_BASE_PIXELS = 250_000_000
MAX_IMAGE_FILE_BYTES = 2 << 30
MAX_TEXT_FILE_BYTES = 64 << 20  # JSON and CSV inputs (LINES.json, POINTS.csv, result records)


class FrameReadError(ValueError):
    """A frame of a sequence cannot be read (missing, truncated, corrupt, too large or small)."""


def read_image(
    path: str | os.PathLike,
    *,
    grey: bool = False,
    max_pixels: int = MAX_BASE_PIXELS,
) -> NDArray[np.uint8]:
    """Read an image as BGR uint8 ``(H, W, 3)`` (or grey ``(H, W)``).

    Checks before decoding where the format allows (PNG, JPEG, TIFF, BMP, WebP headers): at
    least ``MIN_IMAGE_SIDE`` pixels a side and at most ``max_pixels`` pixels, and a complete
    file (a truncated PNG or JPEG is refused instead of decoded into a partly grey image).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: one line naming the file and the problem (a directory, empty, too large or
            small, truncated, corrupt or not an image).
    """
    img = to_uint8(decode_image_file(path, max_pixels=max_pixels))
    if img.ndim == 2:
        return img if grey else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if grey else img


def decode_image_file(path: str | os.PathLike, *, max_pixels: int = MAX_BASE_PIXELS) -> NDArray:
    """An image file decoded as stored (grey, BGR or BGRA; 8 or 16 bit), after the checks of
    :func:`read_image`. Raises as :func:`read_image`."""
    p = Path(path)
    data = _read_image_bytes(p)
    size = image_header_size(data)
    if size is not None:
        check_image_size(size, p, max_pixels=max_pixels)
    problem = incomplete_image(data)
    if problem:
        raise ValueError(f"{p}: {problem}")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise ValueError(
            f"cannot read {p} as an image (not an image file, corrupt, or a format OpenCV "
            "cannot decode)"
        )
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)):
        raise ValueError(
            f"{p}: unsupported image layout {img.shape} (need grey, colour or colour+alpha)"
        )
    if size is None:
        check_image_size((img.shape[1], img.shape[0]), p, max_pixels=max_pixels)
    return img


def _read_image_bytes(p: Path) -> bytes:
    if not p.exists():
        raise FileNotFoundError(f"image not found: {p}")
    if p.is_dir():
        raise ValueError(f"{p} is a directory, not an image file")
    n = p.stat().st_size
    if n == 0:
        raise ValueError(f"image file {p} is empty")
    if n > MAX_IMAGE_FILE_BYTES:
        raise ValueError(
            f"{p}: file of {n / 2**20:.0f} MiB is over the {MAX_IMAGE_FILE_BYTES >> 20} MiB limit "
            "for images"
        )
    with open(p, "rb") as f:
        return f.read()


def check_image_size(size: tuple[int, int], path: object, *, max_pixels: int) -> None:
    """ValueError naming ``path`` and its ``(width, height)`` when outside the limits."""
    w, h = int(size[0]), int(size[1])
    if min(w, h) < MIN_IMAGE_SIDE:
        raise ValueError(
            f"{path}: image of {w}x{h} pixels is too small (at least {MIN_IMAGE_SIDE} a side)"
        )
    if w * h > max_pixels:
        raise ValueError(
            f"{path}: image of {w}x{h} pixels ({w * h / 1e6:.0f} MP) is over the limit of "
            f"{max_pixels / 1e6:.0f} MP"
        )


def image_header_size(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` from the header of a PNG, JPEG, TIFF, BMP or WebP file's bytes, without
    decoding; None for other formats or an unreadable header."""
    try:
        if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR":
            return struct.unpack(">II", data[16:24])
        if data[:2] == b"\xff\xd8":
            return _jpeg_size(data)
        if data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
            return _tiff_size(data)
        if data[:2] == b"BM":
            if struct.unpack("<I", data[14:18])[0] == 12:  # OS/2 BITMAPCOREHEADER
                return struct.unpack("<HH", data[18:22])
            w, h = struct.unpack("<ii", data[18:26])
            return abs(w), abs(h)
        if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
            return _webp_size(data)
    except (struct.error, IndexError, ValueError):
        return None
    return None


_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_STANDALONE = {0x01, *range(0xD0, 0xD9)}


def _jpeg_segments(data: bytes) -> Iterator[tuple[int, int]]:
    """``(marker, offset of the marker)`` of a JPEG's header segments, up to and including SOS."""
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            raise ValueError("JPEG marker expected")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        yield marker, i
        if marker == 0xDA:
            return
        if marker in _JPEG_STANDALONE:
            i += 2
        else:
            i += 2 + struct.unpack(">H", data[i + 2 : i + 4])[0]


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    for marker, i in _jpeg_segments(data):
        if marker in _JPEG_SOF:
            h, w = struct.unpack(">HH", data[i + 5 : i + 9])
            return w, h
    return None


def _tiff_size(data: bytes) -> tuple[int, int] | None:
    e = "<" if data[:2] == b"II" else ">"
    big = data[2:4] in (b"+\x00", b"\x00+")
    if big:
        off = struct.unpack(e + "Q", data[8:16])[0]
        n = struct.unpack(e + "Q", data[off : off + 8])[0]
        first, step, head = off + 8, 20, e + "HHQ"
    else:
        off = struct.unpack(e + "I", data[4:8])[0]
        n = struct.unpack(e + "H", data[off : off + 2])[0]
        first, step, head = off + 2, 12, e + "HHI"
    hsize = struct.calcsize(head)
    found = {}
    for j in range(min(n, 4096)):
        at = first + j * step
        tag, typ, _count = struct.unpack(head, data[at : at + hsize])
        if tag in (256, 257):
            fmt = e + ("H" if typ == 3 else "Q" if typ == 16 else "I")
            found[tag] = struct.unpack(fmt, data[at + hsize : at + hsize + struct.calcsize(fmt)])[0]
    if 256 in found and 257 in found:
        return found[256], found[257]
    return None


def _webp_size(data: bytes) -> tuple[int, int] | None:
    kind = data[12:16]
    if kind == b"VP8X":
        w = int.from_bytes(data[24:27], "little") + 1
        h = int.from_bytes(data[27:30], "little") + 1
        return w, h
    if kind == b"VP8L" and data[20] == 0x2F:
        bits = int.from_bytes(data[21:25], "little")
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if kind == b"VP8 " and data[23:26] == b"\x9d\x01\x2a":
        w, h = struct.unpack("<HH", data[26:30])
        return w & 0x3FFF, h & 0x3FFF
    return None


def incomplete_image(data: bytes) -> str:
    """Why the bytes of a PNG, JPEG or WebP file are not a complete image ("" when they are, or
    for other formats): a truncated file, a PNG chunk failing its CRC. OpenCV decodes some
    truncated files into partly grey images without an error; this catches them first."""
    try:
        if data[:8] == b"\x89PNG\r\n\x1a\n":
            return _png_problem(data)
        if data[:2] == b"\xff\xd8":
            sos = [i for m, i in _jpeg_segments(data) if m == 0xDA]
            if not sos:
                return "truncated JPEG (no image data)"
            if data.rfind(b"\xff\xd9") < sos[0]:
                return "truncated JPEG (no end-of-image marker)"
            return ""
        if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
            declared = struct.unpack("<I", data[4:8])[0] + 8
            if len(data) < declared:
                return f"truncated WebP ({len(data)} of {declared} bytes)"
    except (struct.error, IndexError, ValueError) as exc:
        return f"corrupt header ({exc})"
    return ""


def _png_problem(data: bytes) -> str:
    i, n = 8, len(data)
    view = memoryview(data)
    while i + 12 <= n:
        length = struct.unpack(">I", data[i : i + 4])[0]
        kind = data[i + 4 : i + 8]
        end = i + 8 + length
        if end + 4 > n:
            break
        crc = struct.unpack(">I", data[end : end + 4])[0]
        if zlib.crc32(view[i + 4 : end]) != crc:
            name = kind.decode("latin-1")
            return f"corrupt PNG (chunk {name!r} at byte {i} fails its CRC check)"
        if kind == b"IEND":
            return ""
        i = end + 4
    return f"truncated PNG (no IEND chunk; {n} bytes)"


def to_uint8(img: NDArray) -> NDArray[np.uint8]:
    """Scale 16-bit or float images to uint8 (float assumed in [0, 1])."""
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        return (img >> 8).astype(np.uint8)
    if np.issubdtype(img.dtype, np.floating):
        return np.clip(np.nan_to_num(img) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.clip(img, 0, 255).astype(np.uint8)


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
        georef: the map's :class:`registration.georef.GeoReference`, or None for a plain image.
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
      ``.jgw``, ``.pngw``, ``.wld``; see :mod:`registration.georef` for its half-pixel offset)
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
            ``.prj``, or to override the file's.
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
    if p.suffix.lower() in PLAIN_SUFFIXES:
        base = _read_plain_base(p, crs, nodata)
    else:
        base = _read_gdal_base(p, crs, nodata)
    if not base.valid.any():
        raise ValueError(f"base map {p.name} has no valid pixels (all no-data)")
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
    if p.suffix.lower() in PLAIN_SUFFIXES:
        base = _read_plain_base(p, crs, "file")
        return base.georef, base.size
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

    from registration import georef as gr

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(p) as ds:
                size = (ds.width, ds.height)
                if ds.transform.is_identity and ds.crs is None:
                    return None, size
                file_crs = crs if crs is not None else ds.crs or gr.read_sidecar_crs(p)
                return gr.GeoReference.from_affine(ds.transform, file_crs), size
    except RasterioIOError as exc:
        raise ValueError(f"not a readable raster: {p} ({str(exc).splitlines()[0]})") from None


def _read_plain_base(p: Path, crs: Any, nodata) -> BaseMap:
    from registration import georef as gr

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
    world = gr.find_world_file(p)
    georef = None
    if world is not None:
        wkt = gr.parse_crs(crs).to_wkt() if crs is not None else gr.read_sidecar_crs(p)
        georef = gr.GeoReference(gr.read_world_file(world), wkt)
        notes.append(f"georeferenced by world file {world.name}" + ("" if wkt else " (no CRS)"))
    elif crs is not None:
        raise ValueError(
            f"a CRS was given but {p.name} has no world file ({', '.join(c.name for c in gr.world_file_candidates(p)[::2])})"
        )
    return BaseMap(image, valid, georef, str(p), notes)


def _read_gdal_base(p: Path, crs: Any, nodata) -> BaseMap:
    import warnings

    import rasterio
    from rasterio.enums import ColorInterp, MaskFlags
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

    from registration import georef as gr

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
        interp = list(ds.colorinterp)
        lossy = str(getattr(ds.compression, "value", ds.compression)).upper() in ("JPEG", "WEBP")
        has_mask = any(flags != [MaskFlags.all_valid] for flags in ds.mask_flag_enums)
        valid = ds.dataset_mask() > 0 if has_mask else np.ones((ds.height, ds.width), bool)
        if has_mask:
            notes.append("file's no-data/alpha/mask -> no-data mask")
        if ds.count == 1 and interp[0] == ColorInterp.palette:
            index = ds.read(1)
            bands, valid = _expand_palette(index, ds.colormap(1), valid, nodata, notes)
            nodata = "file" if not isinstance(nodata, str) else nodata  # applied to the index
        else:
            named = {ci: i + 1 for i, ci in reversed(list(enumerate(interp)))}
            rgb = [named.get(c) for c in (ColorInterp.red, ColorInterp.green, ColorInterp.blue)]
            if all(rgb):
                idx = rgb
            elif ds.count >= 3:
                idx = [1, 2, 3]
            else:
                idx = [1]
            if ds.count > len(idx) and ColorInterp.alpha not in interp:
                notes.append(f"bands {idx} of {ds.count} used as colour")
            bands = ds.read(idx)[::-1] if len(idx) == 3 else ds.read(idx)
        georef = None
        if not (ds.transform.is_identity and ds.crs is None):
            if crs is not None:
                georef = gr.GeoReference.from_affine(ds.transform, crs)
                notes.append("CRS given explicitly")
            else:
                file_crs = ds.crs if ds.crs is not None else gr.read_sidecar_crs(p)
                georef = gr.GeoReference.from_affine(ds.transform, file_crs)
        elif crs is not None:
            raise ValueError(f"a CRS was given but {p.name} has no affine transform")
        elif ds.gcps[0]:
            notes.append("ground control points in the file are not used (no affine transform)")
    image, valid = _bands_to_bgr(bands, valid, nodata, lossy, notes)
    return BaseMap(image, valid, georef, str(p), notes)


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


def temp_path_beside(path: str | os.PathLike) -> Path:
    """A new empty temporary file in ``path``'s folder with its suffix (for writers that need a
    file name, e.g. GDAL): write it, then ``os.replace`` it onto ``path``."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=p.parent, prefix=f".{p.stem}.", suffix=p.suffix)
    os.close(fd)
    return Path(tmp)


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the new one, never a part."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=p.parent, prefix=f".{p.name}.", suffix=".tmp")
    try:
        if hasattr(os, "fchmod"):
            os.fchmod(fd, 0o644)  # mkstemp's 0600 would hide results from other users
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_json_atomic(path: str | os.PathLike, obj: object) -> None:
    write_bytes_atomic(path, (json.dumps(obj, indent=1, default=_json_default) + "\n").encode())


def write_image_atomic(path: str | os.PathLike, image: NDArray, *, jpeg_quality: int = 92) -> None:
    """Encode by the suffix of ``path`` (png/jpg/...) and write atomically."""
    suffix = Path(path).suffix.lower() or ".png"
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if suffix in (".jpg", ".jpeg") else []
    ok, buf = cv2.imencode(suffix, image, params)
    if not ok:
        raise ValueError(f"could not encode image for {path}")
    write_bytes_atomic(path, buf.tobytes())


def encode_npz(**arrays: NDArray) -> bytes:
    """``arrays`` as the bytes of a compressed ``.npz`` file."""
    import io as _io

    buf = _io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def write_npz_atomic(path: str | os.PathLike, **arrays: NDArray) -> None:
    write_bytes_atomic(path, encode_npz(**arrays))


def read_text_file(
    path: str | os.PathLike, what: str, *, max_bytes: int = MAX_TEXT_FILE_BYTES
) -> str:
    """A UTF-8 text file (JSON, CSV) of at most ``max_bytes``.

    Raises:
        FileNotFoundError: ``{what} not found: {path}``.
        ValueError: one line naming the file: a directory, too large, or not UTF-8.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{what} not found: {p}")
    if p.is_dir():
        raise ValueError(f"{what} {p} is a directory, not a file")
    n = p.stat().st_size
    if n > max_bytes:
        raise ValueError(
            f"{what} {p} has {n / 2**20:.1f} MiB, over the {max_bytes >> 20} MiB limit"
        )
    data = p.read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(
            f"{what} {p} is not UTF-8 text ({exc.reason} at byte {exc.start})"
        ) from None


SAMPLE_BYTES = 64 << 10


def file_fingerprint(path: str | os.PathLike) -> dict:
    """A cheap identity of a file: ``size``, ``mtime_ns`` and ``sample_sha256``, the SHA-256 of
    its first and last ``SAMPLE_BYTES`` (the whole file when it is at most twice that)."""
    p = Path(path)
    st = p.stat()
    h = hashlib.sha256()
    with open(p, "rb") as f:
        if st.st_size <= 2 * SAMPLE_BYTES:
            h.update(f.read())
        else:
            h.update(f.read(SAMPLE_BYTES))
            f.seek(-SAMPLE_BYTES, os.SEEK_END)
            h.update(f.read(SAMPLE_BYTES))
    return {
        "size": int(st.st_size),
        "mtime_ns": int(st.st_mtime_ns),
        "sample_sha256": h.hexdigest(),
    }


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a whole file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# Frames a backward seek in a video decodes at once (the request and the 7 before it): 8 frames
# of 2560x1920 hold 118 MB; a backward frame then costs ~(0.7 + 8 x 0.03) / 8 s, not 0.7 s.
VIDEO_BACKWARD_BLOCK = 8


class FrameSource:
    """Frames in reading order: ``len(src)``, ``src.get(k)``, ``for k, frame in src.iter(start)``.

    Attributes:
        description: what was opened (for messages and the result's metadata).
        size: ``(width, height)`` of the frames: the first readable frame's (from its header for
            images; frames of another size are refused by the pipeline, frame by frame).
    """

    max_pixels = MAX_FRAME_PIXELS

    def __init__(self, spec: str | os.PathLike) -> None:
        self.description = str(spec)
        p = Path(spec)
        self._video: str | None = None
        self._paths: list[Path] = []
        if p.is_dir():
            self._paths = sorted(
                q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES and not q.is_dir()
            )
            if not self._paths:
                raise ValueError(
                    f"no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in directory {p}"
                )
        elif p.is_file():
            if p.suffix.lower() in IMAGE_SUFFIXES:
                self._paths = [p]
            else:
                self._video = str(p)
        elif any(ch in str(spec) for ch in "*?["):
            self._paths = sorted(
                Path(q)
                for q in globlib.glob(str(spec))
                if Path(q).suffix.lower() in IMAGE_SUFFIXES and not Path(q).is_dir()
            )
            if not self._paths:
                raise ValueError(f"glob pattern matched no images: {spec}")
        else:
            raise FileNotFoundError(f"frames not found: {spec}")
        # A video's reader stays open between frames: the next frame then costs a decode
        # (~0.02 s at 2560x1920), where reopening and seeking cost ~0.7 s. Read backwards (the
        # frames before a reference frame), one seek decodes a block ahead of the request.
        self._open_video = None
        self._video_next: int | None = None  # the frame the open reader decodes next
        self._video_last = -1  # the frame asked for last
        self._video_block: dict[int, NDArray[np.uint8]] = {}  # decoded by a backward seek
        self._video_lock = threading.Lock()
        if self._video is not None:
            self._n = self._count_video_frames()
        else:
            self._n = len(self._paths)
        self.size = self._first_size()

    def __len__(self) -> int:
        return self._n

    def __getstate__(self) -> dict:
        # Copies and pickles (Dask workers) open their own reader.
        state = self.__dict__.copy()
        state.update(_open_video=None, _video_next=None, _video_last=-1, _video_block={})
        del state["_video_lock"]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._video_lock = threading.Lock()

    def close(self) -> None:
        """Close the video reader kept open between frames (reopened when needed)."""
        with self._video_lock:
            self._close_video()

    def _close_video(self) -> None:
        reader, self._open_video = self._open_video, None
        self._video_next, self._video_block = None, {}
        if reader is not None:
            try:
                reader.close()
            except Exception:  # a broken ffmpeg pipe: nothing left to keep
                pass

    def __del__(self) -> None:
        if getattr(self, "_open_video", None) is not None:
            self._close_video()

    def path(self, k: int) -> Path | None:
        """The image file of frame ``k`` (None for a video)."""
        return self._paths[k] if self._video is None else None

    @property
    def video_path(self) -> Path | None:
        """The video file (None for images)."""
        return None if self._video is None else Path(self._video)

    def resolved(self) -> FrameSource:
        """A copy that names its files by absolute paths (for a process whose working folder
        differs, e.g. a Dask worker); the same frames."""
        other = copy.copy(self)
        other._paths = [q.resolve() for q in self._paths]
        if self._video is not None:
            other._video = str(Path(self._video).resolve())
        return other

    def name(self, k: int) -> str:
        """Frame ``k`` for messages: its file (images) or ``video.mp4 frame k``."""
        if self._video is None:
            return str(self._paths[k])
        return f"{self._video} frame {k}"

    def _first_size(self) -> tuple[int, int]:
        if self._video is not None:
            frame = self.get(0)
            return int(frame.shape[1]), int(frame.shape[0])
        first_problem = ""
        for k in range(self._n):
            try:
                return self.frame_size(k)
            except (ValueError, OSError) as exc:
                first_problem = first_problem or str(exc)
        raise ValueError(f"no readable frame in {self.description} ({first_problem})")

    def frame_size(self, k: int) -> tuple[int, int]:
        """``(width, height)`` of frame ``k`` from its file's header when the format allows
        (decoding it otherwise), checked against the size limits.

        Raises:
            FrameReadError: naming the frame and the problem.
        """
        if self._video is not None:
            return self.size
        path = self._paths[k]
        try:
            with open(path, "rb") as f:
                head = f.read(SAMPLE_BYTES)
            size = image_header_size(head)
            if size is None:
                img = self.get(k)
                return int(img.shape[1]), int(img.shape[0])
            check_image_size(size, path, max_pixels=self.max_pixels)
        except FrameReadError:
            raise
        except (ValueError, OSError) as exc:
            raise FrameReadError(_one_line(exc)) from None
        return int(size[0]), int(size[1])

    def _reader(self):
        import imageio.v2 as iio

        try:
            return iio.get_reader(self._video, format="FFMPEG")
        except Exception as exc:  # imageio raises several types for non-videos
            raise ValueError(
                f"not a readable video: {self._video} ({type(exc).__name__})"
            ) from None

    def _count_video_frames(self) -> int:
        reader = self._reader()
        try:
            meta = reader.get_meta_data()
            w, h = (int(v) for v in meta.get("size", (0, 0)))
            if w and h:
                check_image_size((w, h), self._video, max_pixels=self.max_pixels)
            n = reader.count_frames()
        except ValueError:
            raise
        except Exception as exc:  # imageio/ffmpeg: RuntimeError, OSError, ...
            raise ValueError(f"not a readable video: {self._video} ({_one_line(exc)})") from None
        finally:
            reader.close()
        if n <= 0:
            raise ValueError(f"video has no frames: {self._video}")
        return int(n)

    def get(self, k: int) -> NDArray[np.uint8]:
        """Frame ``k`` as BGR uint8.

        Raises:
            IndexError: ``k`` outside the sequence.
            FrameReadError: the frame cannot be read (one line naming the frame and why).
        """
        if not 0 <= k < self._n:
            raise IndexError(f"frame {k} out of range: the source has {self._n} frames")
        if self._video is None:
            try:
                return read_image(self._paths[k], max_pixels=self.max_pixels)
            except (ValueError, OSError) as exc:
                raise FrameReadError(_one_line(exc)) from None
        with self._video_lock:
            backwards = k == self._video_last - 1
            self._video_last = k
            frame = self._video_block.pop(k, None)
            if frame is not None:
                return frame
            first = k
            if backwards and self._video_next is not None and k < self._video_next:
                first = max(0, k - VIDEO_BACKWARD_BLOCK + 1)
            block = {j: self._decode_video(j) for j in range(first, k + 1)}
            frame = block.pop(k)
            self._video_block = block
        return frame

    def _decode_video(self, k: int) -> NDArray[np.uint8]:
        """Frame ``k`` from the open reader (opened when needed); the caller holds the lock."""
        if self._open_video is None:
            self._open_video = self._reader()
        try:
            # Sequential calls read on; any other index makes imageio seek.
            rgb = self._open_video.get_data(k)
        except Exception as exc:  # imageio/ffmpeg: IndexError, RuntimeError, OSError, ...
            self._close_video()
            raise FrameReadError(f"{self.name(k)}: {_one_line(exc)}") from None
        self._video_next = k + 1
        return cv2.cvtColor(np.asarray(rgb), cv2.COLOR_RGB2BGR)

    def iter(self, start: int = 0) -> Iterator[tuple[int, NDArray[np.uint8]]]:
        """Yield ``(k, frame)`` from ``start`` on, decoding a video sequentially."""
        if self._video is None:
            for k in range(start, self._n):
                yield k, self.get(k)
            return
        reader = self._reader()
        try:
            for k, rgb in enumerate(reader):
                if k >= start:
                    yield k, cv2.cvtColor(np.asarray(rgb), cv2.COLOR_RGB2BGR)
        finally:
            reader.close()

    def identity(self) -> dict:
        """What the frames are, cheaply (README "Reliability"): per image file its name and
        :func:`file_fingerprint`; for a video the file's fingerprint, frame count and size."""
        if self._video is not None:
            return {
                "kind": "video",
                "name": Path(self._video).name,
                "n_frames": self._n,
                "frame_size": list(self.size),
                **file_fingerprint(self._video),
            }
        files = []
        for q in self._paths:
            try:
                files.append({"name": q.name, **file_fingerprint(q)})
            except OSError as exc:  # unreadable now: the frame will fail, say so
                files.append({"name": q.name, "error": _one_line(exc)})
        return {"kind": "images", "n_frames": self._n, "files": files}


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    if isinstance(exc, OSError) and exc.strerror:
        text = f"{exc.strerror}: {exc.filename}" if exc.filename else exc.strerror
    return text.splitlines()[0] if text else type(exc).__name__


def open_frames(spec: str | os.PathLike) -> FrameSource:
    """Open a video file, a directory of images or a glob pattern (see :class:`FrameSource`)."""
    return FrameSource(spec)

"""Reading images: frames and maps as BGR uint8, with their size checked from the file's header
before decoding (limits below) and truncated files recognised (OpenCV decodes some into grey
images without an error).

A frame source is a video file (read with imageio/ffmpeg frame by frame, never the whole video
in memory), a directory of images (sorted by name), or a glob pattern. Frames are BGR uint8.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}

# Limits on what is read (README "Reliability"). The paper's frames are 2560x1920 = 4.9 MP; an
# 8K video frame is 33 MP. A base map covers more ground than a frame and may be larger.
MIN_IMAGE_SIDE = 16
MAX_FRAME_PIXELS = 100_000_000
MAX_BASE_PIXELS = 250_000_000
MAX_IMAGE_FILE_BYTES = 2 << 30
# Peak memory of reading an image, bytes per pixel, checked against the memory available before
# a pixel is read. A base map read through GDAL (bands, no-data masks, the collar search, the
# BGR image) peaked at 5.84 GB for a 15000x15000 RGB GeoTIFF: 26 B/px for 8-bit bands, more
# for wider samples. OpenCV's decoder needs the file and the image, about 8 B/px.
GDAL_READ_BYTES_PER_PIXEL = 26
DECODE_BYTES_PER_PIXEL = 8


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
    if size is not None:
        check_memory(size, p, bytes_per_pixel=DECODE_BYTES_PER_PIXEL)
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


def available_memory_bytes() -> int | None:
    """Memory the system can give without swapping (Linux ``MemAvailable``; elsewhere the free
    physical pages), bytes; None when unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def check_memory(size: tuple[int, int], path: object, *, bytes_per_pixel: float) -> None:
    """ValueError naming ``path``, its size and the memory, when reading its ``(width,
    height)`` pixels at ``bytes_per_pixel`` would need more memory than is available (checked
    from the header, before a pixel is read)."""
    w, h = int(size[0]), int(size[1])
    need = w * h * bytes_per_pixel
    available = available_memory_bytes()
    if available is not None and need > available:
        raise ValueError(
            f"{path}: reading its {w}x{h} pixels needs about {need / 2**30:.1f} GiB of memory and "
            f"{available / 2**30:.1f} GiB is available: crop or downsample it first"
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

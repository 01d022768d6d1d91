"""Writing files atomically: to a temporary name beside the target, then renamed into place, so a
reader never sees a partial file.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray


def _file_mode() -> int:
    """The permissions a new file gets from the process's umask (``0o666 & ~umask``), as any
    ``open(..., "w")`` would; ``mkstemp`` alone gives 0600."""
    status = Path("/proc/self/status")
    if status.is_file():  # Linux: read without changing it (os.umask is process-wide)
        for line in status.read_text().splitlines():
            if line.startswith("Umask:"):
                return 0o666 & ~int(line.split()[1], 8)
    with _UMASK_LOCK:
        mask = os.umask(0)
        os.umask(mask)
    return 0o666 & ~mask


_UMASK_LOCK = threading.Lock()

# The temporary names atomic_path makes: .NAME.XXXXXXXX.tmp (mkstemp's 8 characters), plus
# NAME's suffix with keep_suffix.
_TEMP_NAME = re.compile(r"^\.(?P<name>.+)\.[a-z0-9_]{8}\.tmp(\.[A-Za-z0-9]+)?$")


def temp_target(name: str) -> str | None:
    """The file name an :func:`atomic_path` temporary file ``name`` was writing (a writer killed
    before the rename leaves it), or None when ``name`` is not such a temporary file."""
    m = _TEMP_NAME.match(name)
    return m["name"] if m else None


@contextmanager
def atomic_path(path: str | os.PathLike, *, keep_suffix: bool = False) -> Iterator[Path]:
    """The one way this project writes a file: a temporary file beside ``path`` for the caller to
    write (by name, so GDAL, ffmpeg, SQLite and ``cv2.imwrite`` can use it too), which on leaving
    the block is flushed to disk (fsync), given the permissions the umask gives and renamed onto
    ``path`` (readers see the old file or the new one, never a part); on an exception it is
    removed and ``path`` is left as it was.

    The temporary name is ``.NAME.XXXXXXXX.tmp``, which no ``*.json`` or ``*.png`` glob matches
    and result folders recognise as their own; with ``keep_suffix`` ``path``'s suffix follows
    (``.NAME.XXXXXXXX.tmp.mp4``) for writers that pick their format by the name (ffmpeg).
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    suffix = ".tmp" + (p.suffix if keep_suffix else "")
    fd, name = tempfile.mkstemp(dir=p.parent, prefix=f".{p.name}.", suffix=suffix)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, _file_mode())
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, p)
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the new one, never a part
    (:func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


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


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")

"""Writing files atomically: to a temporary name beside the target, then renamed into place, so a
reader never sees a partial file.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray


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


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")

"""Reading frames and images, and writing files atomically. The only disk access of the pipeline.

A frame source is a video file (read with imageio/ffmpeg frame by frame, never the whole video
in memory), a directory of images (sorted by name), or a glob pattern. Frames are BGR uint8.
"""

from __future__ import annotations

import glob as globlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}
VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".webm"}


def read_image(path: str | os.PathLike, *, grey: bool = False) -> NDArray[np.uint8]:
    """Read an image as BGR uint8 ``(H, W, 3)`` (or grey ``(H, W)``).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is empty or not a readable image.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"image not found: {p}")
    if p.is_dir():
        raise ValueError(f"expected an image file, got a directory: {p}")
    if p.stat().st_size == 0:
        raise ValueError(f"image file is empty: {p}")
    data = np.fromfile(str(p), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"not a readable image: {p}")
    img = to_uint8(img)
    if img.ndim == 2:
        return img if grey else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if grey else img


def to_uint8(img: NDArray) -> NDArray[np.uint8]:
    """Scale 16-bit or float images to uint8 (float assumed in [0, 1])."""
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        return (img >> 8).astype(np.uint8)
    if np.issubdtype(img.dtype, np.floating):
        return np.clip(np.nan_to_num(img) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.clip(img, 0, 255).astype(np.uint8)


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the new one, never a part."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=p.parent, prefix=f".{p.name}.", suffix=".tmp")
    try:
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


def write_npz_atomic(path: str | os.PathLike, **arrays: NDArray) -> None:
    import io as _io

    buf = _io.BytesIO()
    np.savez_compressed(buf, **arrays)
    write_bytes_atomic(path, buf.getvalue())


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


class FrameSource:
    """Frames in reading order: ``len(src)``, ``src.get(k)``, ``for k, frame in src.iter(start)``.

    Attributes:
        description: what was opened (for messages and the result's metadata).
        size: ``(width, height)`` of the frames.
    """

    def __init__(self, spec: str | os.PathLike) -> None:
        self.description = str(spec)
        p = Path(spec)
        self._video: str | None = None
        self._paths: list[Path] = []
        if p.is_dir():
            self._paths = sorted(q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES)
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
                Path(q) for q in globlib.glob(str(spec)) if Path(q).suffix.lower() in IMAGE_SUFFIXES
            )
            if not self._paths:
                raise ValueError(f"glob pattern matched no images: {spec}")
        else:
            raise FileNotFoundError(f"frames not found: {spec}")
        if self._video is not None:
            self._n = self._count_video_frames()
            first = self.get(0)
        else:
            self._n = len(self._paths)
            first = self.get(0)
        self.size = (int(first.shape[1]), int(first.shape[0]))

    def __len__(self) -> int:
        return self._n

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
            n = reader.count_frames()
        finally:
            reader.close()
        if n <= 0:
            raise ValueError(f"video has no frames: {self._video}")
        return int(n)

    def get(self, k: int) -> NDArray[np.uint8]:
        """Frame ``k`` as BGR uint8."""
        if not 0 <= k < self._n:
            raise IndexError(f"frame {k} out of range: the source has {self._n} frames")
        if self._video is None:
            return read_image(self._paths[k])
        reader = self._reader()
        try:
            rgb = reader.get_data(k)
        finally:
            reader.close()
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


def open_frames(spec: str | os.PathLike) -> FrameSource:
    """Open a video file, a directory of images or a glob pattern (see :class:`FrameSource`)."""
    return FrameSource(spec)

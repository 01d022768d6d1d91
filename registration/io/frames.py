"""Frame sources: a video, a directory of images (sorted by name) or a glob pattern, read frame by
frame with limits checked before decoding.
"""

from __future__ import annotations

import copy
import glob as globlib
import os
import threading
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from registration.io.files import SAMPLE_BYTES, file_fingerprint, file_sha256
from registration.io.images import (
    IMAGE_SUFFIXES,
    MAX_FRAME_PIXELS,
    check_image_size,
    image_header_size,
    read_image,
)

VIDEO_SUFFIXES = {".mp4", ".avi", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".webm"}


class FrameReadError(ValueError):
    """A frame of a sequence cannot be read (missing, truncated, corrupt, too large or small)."""


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
        """What the frames are (README "Reliability"): per image file its name and
        :func:`file_fingerprint`; for a video the file's fingerprint and whole-file SHA-256,
        frame count and size."""
        if self._video is not None:
            # A video is hashed whole: one changed packet in its middle changes the frames
            # decoded after it, which the first and last 64 KB do not see (a 4.9 MB flight
            # hashes in 0.02 s; a 2 GB one in a few seconds, once per run or export).
            return {
                "kind": "video",
                "name": Path(self._video).name,
                "n_frames": self._n,
                "frame_size": list(self.size),
                **file_fingerprint(self._video),
                "sha256": file_sha256(self._video),
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


def input_differs(label: str, what: str) -> str:
    """The message for an input that is not the one a run recorded."""
    return f"{label} differs from the run's input ({what})"


def frames_difference(
    old: dict | None, new: dict | None, whole_sha256: list[str | None], frames
) -> str:
    """What differs between the recorded and the current frames ("" when nothing does).

    Sizes and the SHA-256 of each file's first and last 64 KB must agree. When only a file's
    mtime differs (copied, touched) and it is larger than the sampled bytes, a frame already
    registered is hashed whole and compared with ``whole_sha256[k]`` (the hash its record
    holds; None where none is).

    Args:
        old, new: :meth:`FrameSource.identity` as recorded and as it is now.
        frames: the :class:`FrameSource` of ``new``.
    """
    if old is None or new is None:
        return "" if old == new else "the frames' identity is not recorded for both runs"
    if old.get("kind") != new.get("kind"):
        return f"the frames were {old.get('kind')}, now {new.get('kind')}"
    if old.get("n_frames") != new.get("n_frames"):
        return f"the frames were {old.get('n_frames')}, now {new.get('n_frames')}"
    if new["kind"] == "video":
        label = f"the video {new.get('name')}"
        if old.get("size") != new.get("size"):
            return input_differs(label, f"size {new.get('size')} vs {old.get('size')} bytes")
        if old.get("sample_sha256") != new.get("sample_sha256"):
            return input_differs(label, "content of its first or last 64 KB")
        if old.get("sha256") and new.get("sha256") and old["sha256"] != new["sha256"]:
            return input_differs(label, "content changed since it was registered")
        return ""
    for k, (o, n) in enumerate(zip(old.get("files", []), new.get("files", []), strict=False)):
        path = frames.path(k) if hasattr(frames, "path") else n.get("name")
        label = f"frame {k} ({path})"
        if "error" in n:
            return f"{label} cannot be read now ({n['error']})"
        if o.get("size") != n.get("size"):
            return input_differs(label, f"size {n.get('size')} vs {o.get('size')} bytes")
        if o.get("sample_sha256") != n.get("sample_sha256"):
            return input_differs(label, "content of its first or last 64 KB")
        if o.get("mtime_ns") != n.get("mtime_ns") and n["size"] > 2 * SAMPLE_BYTES:
            want = whole_sha256[k] if k < len(whole_sha256) else None
            if want and path is not None and file_sha256(path) != want:
                return input_differs(label, "content changed since it was registered")
    return ""


def check_frames_match(frames, n_frames: int, frame_size: tuple[int, int]) -> None:
    """Raise a one-line ValueError unless ``frames`` holds ``n_frames`` frames of
    ``frame_size`` ``(W, H)`` (the frames a result was registered from)."""
    if len(frames) != n_frames or tuple(frames.size) != tuple(frame_size):
        raise ValueError(
            f"the frames ({len(frames)} of {frames.size[0]}x{frames.size[1]}) are not the "
            f"result's ({n_frames} of {frame_size[0]}x{frame_size[1]})"
        )


def check_recorded_frames(frames, recorded: dict | None, whole_sha256: list[str | None]) -> None:
    """Raise a one-line ValueError unless ``frames`` are the frames a result recorded
    (``recorded``: its ``inputs.frames`` identity; ``whole_sha256``: its records' whole-file
    hashes): reading another sequence at the same path would render another flight's pixels."""
    if recorded is None:
        return  # an older result: count and size are all it recorded
    difference = frames_difference(recorded, frames.identity(), whole_sha256, frames)
    if difference:
        raise ValueError(
            f"the frames {frames.description} are not the ones this result was registered "
            f"from: {difference}"
        )


def check_result_frames(frames, result) -> None:
    """:func:`check_frames_match` and :func:`check_recorded_frames` of ``frames`` against a
    registration result (``n_frames``, ``frame_size``, ``meta``, ``records``)."""
    check_frames_match(frames, result.n_frames, result.frame_size)
    check_recorded_frames(
        frames,
        (result.meta.get("inputs") or {}).get("frames"),
        [getattr(r, "input_sha256", None) for r in result.records],
    )


def open_frames(spec: str | os.PathLike) -> FrameSource:
    """Open a video file, a directory of images or a glob pattern (see :class:`FrameSource`)."""
    return FrameSource(spec)

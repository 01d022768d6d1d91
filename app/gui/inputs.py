"""The opened frame source and base map, with small caches and read-ahead for scrubbing.

Decoding a 2560x1920 frame takes tens of milliseconds (a video frame more), which dominated the
Sequence view's scrubbing; :meth:`Inputs.prefetch` decodes the neighbours of the frame on screen
on a background thread, so the next step of the scrubber finds its frame decoded.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict

import numpy as np

from app.gui import scene2d

log = logging.getLogger(__name__)

FRAME_CACHE = 10
PREVIEW_CACHE = 24


class Inputs:
    """The opened inputs (read-only once built); thread-safe caches of frames and previews."""

    def __init__(self, frames_path: str, base_path: str) -> None:
        from registration import io
        from registration.gis import basemap

        self.frames_path, self.base_path = str(frames_path), str(base_path)
        self.frames = io.open_frames(frames_path)
        # GeoTIFFs (CRS, palette, 16-bit, no-data) and PNG/JPEG with a world file alike.
        base_map = basemap.read_base_map(base_path)
        self.base = base_map.image
        self.base_valid = base_map.valid_or_none
        self.base_georef = base_map.georef
        self.n_frames = len(self.frames)
        self.frame_size = tuple(int(v) for v in self.frames.size)
        self.base_size = (int(self.base.shape[1]), int(self.base.shape[0]))
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._previews: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._base_previews: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()
        self._decoding: dict[int, threading.Event] = {}
        self._wanted: list[int] = []
        self._sides: tuple[int, ...] = ()
        self._wake = threading.Condition(self._lock)
        self._stop = False
        self.read_ahead = True
        self._thread = threading.Thread(
            target=self._read_ahead, name="inputs-prefetch", daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        with self._wake:
            self._stop = True
            self._wake.notify_all()

    def frame(self, k: int) -> np.ndarray:
        """Raw frame ``k`` (BGR uint8), decoded once and cached (LRU)."""
        if not 0 <= k < self.n_frames:
            raise ValueError(f"frame {k} out of range 0..{self.n_frames - 1}")
        while True:
            with self._lock:
                if k in self._cache:
                    self._cache.move_to_end(k)
                    return self._cache[k]
                busy = self._decoding.get(k)
                if busy is None:
                    done = self._decoding[k] = threading.Event()
                    break
            busy.wait()  # the read-ahead thread is decoding it: wait rather than decode twice
        try:
            img = self.frames.get(k)
            with self._lock:
                self._cache[k] = img
                while len(self._cache) > FRAME_CACHE:
                    self._cache.popitem(last=False)
        finally:
            with self._lock:
                self._decoding.pop(k, None)
            done.set()
        return img

    def preview(self, k: int, max_side: int) -> np.ndarray:
        """Raw frame ``k`` downscaled to at most ``max_side`` pixels (BGR), cached."""
        key = (k, max_side)
        with self._lock:
            if key in self._previews:
                self._previews.move_to_end(key)
                return self._previews[key]
        img = scene2d.preview(self.frame(k), max_side)
        with self._lock:
            self._previews[key] = img
            while len(self._previews) > PREVIEW_CACHE:
                self._previews.popitem(last=False)
        return img

    def base_preview(self, max_side: int) -> np.ndarray:
        """The base map downscaled to at most ``max_side`` pixels, RGB, cached."""
        with self._lock:
            img = self._base_previews.get(max_side)
        if img is None:
            img = scene2d.to_rgb(scene2d.preview(self.base, max_side))
            with self._lock:
                self._base_previews[max_side] = img
        return img

    def clear(self) -> None:
        """Forget every decoded frame and preview (benchmarks measure cold decoding)."""
        with self._lock:
            self._cache.clear()
            self._previews.clear()

    def cached(self, k: int) -> bool:
        with self._lock:
            return k in self._cache

    def prefetch(self, frames: list[int], preview_sides: tuple[int, ...] = ()) -> None:
        """Decode ``frames`` (in order) in the background, with their previews of
        ``preview_sides``, unless cached; replaces earlier wishes."""
        if not self.read_ahead:
            return
        with self._wake:
            self._wanted = [k for k in frames if 0 <= k < self.n_frames]
            self._sides = tuple(preview_sides)
            self._wake.notify_all()

    def _read_ahead(self) -> None:
        while True:
            with self._wake:
                self._wake.wait_for(lambda: self._stop or self._wanted)
                if self._stop:
                    return
                k = self._wanted.pop(0)
                sides = self._sides
                if k in self._decoding:
                    continue
            try:
                self.frame(k)
                for side in sides:
                    self.preview(k, side)
            except Exception:  # a broken frame is reported when it is shown, not here
                log.debug("read-ahead of frame %d failed", k, exc_info=True)

"""When each frame was taken and how big a map pixel is: the two things a speed needs.

* :func:`video_frame_times`: presentation timestamps from the video container (ffmpeg reads
  the packets without decoding them), so a variable frame rate or a dropped frame is seen.
* :func:`frame_times`: those, or ``k / fps`` for images when the user gives ``fps``; never a
  guessed rate (a one-line error says what to give).
* :class:`MetricFrame`: base pixels <-> metres, from the map's projected CRS or a ground sampling
  distance the user gives.
"""

from __future__ import annotations

import math
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.coords import as_points


def video_frame_times(path: str | Path) -> NDArray[np.float64] | None:
    """``(K,)`` presentation times (s, first frame at 0) of the first video stream of
    ``path``, from its packets' timestamps; None when the container has none."""
    import imageio_ffmpeg

    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(path)]
    cmd += ["-map", "0:v:0", "-c", "copy", "-f", "framemd5", "-"]
    try:
        text = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    tb = None
    pts = []
    for line in text.splitlines():
        if line.startswith("#tb 0:"):
            num, _, den = line.split(":", 1)[1].strip().partition("/")
            tb = float(num) / float(den or 1)
        elif line and not line.startswith("#"):
            cols = [c.strip() for c in line.split(",")]
            if len(cols) >= 3 and cols[2].lstrip("-").isdigit():
                pts.append(int(cols[2]))
    if tb is None or not pts:
        return None
    t = np.sort(np.asarray(pts, np.float64)) * tb
    return t - t[0]


def frame_times(
    n_frames: int, *, video: str | Path | None = None, fps: float | None = None
) -> tuple[NDArray[np.float64], str]:
    """``(times s, source)`` of ``n_frames`` frames: ``k / fps`` when ``fps`` is given (it
    overrides the container), else the video's timestamps.

    Raises:
        ValueError: one line: ``fps`` not a positive finite number, no ``fps`` for images, or
            a container whose timestamps do not fit the frames.
    """
    if fps is not None:
        if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
            raise ValueError(
                f"frame rate must be a positive number of frames per second, got {fps}"
            )
        return np.arange(n_frames, dtype=np.float64) / float(fps), f"--fps {fps:g}"
    if video is None:
        raise ValueError(
            "frame times unknown: the frames are images, not a video; give the frame rate (--fps)"
        )
    t = video_frame_times(video)
    if t is None or len(t) != n_frames:
        got = "none" if t is None else f"{len(t)}"
        raise ValueError(
            f"frame times unknown: {Path(video).name} has {got} timestamps for {n_frames} "
            "frames; give the frame rate (--fps)"
        )
    if np.any(np.diff(t) <= 0):
        raise ValueError(
            f"frame times unusable: {Path(video).name} repeats a timestamp; give --fps"
        )
    return t, "video timestamps"


@dataclass(frozen=True)
class MetricFrame:
    """Base pixels <-> metres on the ground, x east (right), y north (up).

    With a base in a projected CRS in metres these are the CRS's coordinates (``georef``); else
    ``x = bx * gsd``, ``y = -by * gsd`` from the user's ground sampling distance ``gsd_m``
    (metres per base pixel).
    """

    georef: object | None = None
    gsd_m: float | None = None

    @classmethod
    def for_result(cls, georef, gsd_m: float | None) -> MetricFrame:
        """The frame of a result whose base has ``georef`` (or None); ``gsd_m`` overrides it.

        Raises:
            ValueError: one line: no metric georeference and no ``gsd_m``, or a bad ``gsd_m``.
        """
        if gsd_m is not None:
            if not (isinstance(gsd_m, (int, float)) and math.isfinite(gsd_m) and gsd_m > 0):
                raise ValueError(f"ground sampling distance must be positive metres, got {gsd_m}")
            return cls(None, float(gsd_m))
        units = getattr(georef, "units", None) if georef is not None else None
        if units not in ("metre", "meter", "m"):
            what = "no georeference" if georef is None else f"a map in {units or 'unknown units'}"
            raise ValueError(
                f"metres unknown: the base has {what}; give the ground sampling distance in "
                "metres per base pixel (--gsd)"
            )
        return cls(georef, None)

    @property
    def description(self) -> str:
        if self.georef is not None:
            epsg = getattr(self.georef, "epsg", None)
            return f"map CRS (EPSG:{epsg})" if epsg else "map CRS"
        return f"base px x {self.gsd_m:g} m (y up)"

    def metres_from_base(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` base px -> ``(N, 2)`` metres."""
        b = as_points(xy)
        if self.georef is not None:
            return self.georef.map_from_base(b)
        return np.column_stack([b[:, 0] * self.gsd_m, -b[:, 1] * self.gsd_m])

    def base_from_metres(self, xy: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` metres -> ``(N, 2)`` base px."""
        m = as_points(xy)
        if self.georef is not None:
            return self.georef.base_from_map(m)
        return np.column_stack([m[:, 0] / self.gsd_m, -m[:, 1] / self.gsd_m])

    def metres_per_base_px(self) -> float:
        """Mean ground size of a base pixel, metres."""
        if self.georef is not None:
            sx, sy = self.georef.pixel_size
            return float(math.sqrt(sx * sy))
        return float(self.gsd_m)

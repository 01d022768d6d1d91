"""Polylines traced along straight world features, and the LINES.json file that holds them.

LINES.json (what the GUI saves; :func:`load_lines` / :func:`save_lines`)::

    {"version": 1,
     "image_size": [W, H],
     "lines": [[[x, y], [x, y], [x, y], ...], ...]}

* ``version``: the integer 1.
* ``image_size``: the raw image's width and height in pixels (positive integers); it must match
  the image the lines are used with.
* ``lines``: one or more polylines, each a list of at least 3 ``[x, y]`` points in *raw* pixel
  coordinates (pixel centres at integers, ``(0, 0)`` = centre of the top-left pixel), tracing
  something straight in the world; every point within the image (``-0.5 <= x <= W - 0.5``, same
  for y). No other keys are allowed.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from registration.coords import as_points

LINES_FORMAT_VERSION = 1
MIN_POINTS_PER_LINE = 3
# LINES.json limits: hand-drawn files hold tens of lines of tens of points; refuse anything
# vastly beyond that before parsing it (a file of this size parses in well under a second).
MAX_LINES_FILE_BYTES = 8_000_000
MAX_LINES = 10_000
MAX_LINES_POINTS = 200_000
# A line whose points all lie within this many pixels of each other has no direction.
MIN_LINE_EXTENT_PX = 1.0


def as_polylines(polylines, name: str = "line") -> list[NDArray[np.float64]]:
    """Validate a list of polylines: each an ``(N_i, 2)`` float array with ``N_i >= 3``.

    Raises:
        ValueError: naming the first offending line (0-based index) and what is wrong with it.
    """
    if isinstance(polylines, np.ndarray) and polylines.ndim == 2:
        polylines = [polylines]
    lines = list(polylines)
    if not lines:
        raise ValueError("no lines given; at least one line of 3 or more points is needed")
    out = []
    for i, line in enumerate(lines):
        try:
            pts = as_points(line, f"{name} {i}")
        except ValueError as exc:
            raise ValueError(str(exc)) from None
        if len(pts) < MIN_POINTS_PER_LINE:
            raise ValueError(
                f"{name} {i} has {len(pts)} point{'s' if len(pts) != 1 else ''}; "
                f"each line needs at least {MIN_POINTS_PER_LINE}"
            )
        if not np.all(np.isfinite(pts)):
            raise ValueError(f"{name} {i} has non-finite coordinates")
        out.append(pts)
    return out


@dataclass(frozen=True)
class LinesFile:
    """Contents of a LINES.json file (see the module docstring)."""

    image_size: tuple[int, int]
    lines: list[NDArray[np.float64]]


def parse_lines(obj: object, source: str = "LINES.json") -> LinesFile:
    """Validate a decoded LINES.json object; ValueError (one line, naming ``source``) if invalid."""

    def bad(msg: str) -> ValueError:
        return ValueError(f"{source}: {msg}")

    if not isinstance(obj, dict):
        raise bad(f"must be a JSON object, got {type(obj).__name__}")
    unknown = sorted(set(obj) - {"version", "image_size", "lines"})
    if unknown:
        raise bad(f"unknown key {unknown[0]!r} (allowed: version, image_size, lines)")
    for key in ("version", "image_size", "lines"):
        if key not in obj:
            raise bad(f"missing key {key!r}")
    if obj["version"] != LINES_FORMAT_VERSION or isinstance(obj["version"], bool):
        raise bad(f"version must be {LINES_FORMAT_VERSION}, got {obj['version']!r}")
    size = obj["image_size"]
    if (
        not isinstance(size, list)
        or len(size) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)
    ):
        raise bad(f"image_size must be [width, height] as positive integers, got {size!r}")
    w, h = size
    lines = obj["lines"]
    if not isinstance(lines, list) or not lines:
        raise bad("lines must be a non-empty list of polylines")
    if len(lines) > MAX_LINES:
        raise bad(f"{len(lines)} lines; at most {MAX_LINES} are accepted")
    n_points = sum(len(line) if isinstance(line, list) else 0 for line in lines)
    if n_points > MAX_LINES_POINTS:
        raise bad(f"{n_points} points in all; at most {MAX_LINES_POINTS} are accepted")
    out = []
    for i, line in enumerate(lines):
        if not isinstance(line, list):
            raise bad(f"lines[{i}] must be a list of [x, y] points, got {type(line).__name__}")
        for j, p in enumerate(line):
            if (
                not isinstance(p, list)
                or len(p) != 2
                or not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                    for v in p
                )
            ):
                raise bad(f"lines[{i}][{j}] must be an [x, y] pair of finite numbers, got {p!r}")
            x, y = p
            if not (-0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5):
                raise bad(f"lines[{i}][{j}] = {p!r} lies outside the {w}x{h} image")
        if len(line) < MIN_POINTS_PER_LINE:
            raise bad(
                f"lines[{i}] has {len(line)} point{'s' if len(line) != 1 else ''}; "
                f"each line needs at least {MIN_POINTS_PER_LINE}"
            )
        pts = np.asarray(line, dtype=np.float64).reshape(-1, 2)
        problem = degenerate_reason(pts)
        if problem:
            raise bad(f"lines[{i}] {problem}")
        out.append(pts)
    return LinesFile((w, h), out)


def degenerate_reason(pts: NDArray) -> str | None:
    """Why a polyline cannot trace a straight line (all its points within a pixel), or None."""
    if float(np.max(np.ptp(pts, axis=0))) >= MIN_LINE_EXTENT_PX:
        return None
    return (
        f"is degenerate: its {len(pts)} points all lie within {MIN_LINE_EXTENT_PX:g} px of "
        f"({pts[0, 0]:g}, {pts[0, 1]:g}), so it has no direction to be straight along"
    )


def load_lines(path: str | Path) -> LinesFile:
    """Read and validate a LINES.json file.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: not JSON, not a valid LINES.json, a degenerate line, or beyond the size
            limits (``MAX_LINES_FILE_BYTES``, ``MAX_LINES``, ``MAX_LINES_POINTS``); one line
            naming the file and the problem.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"lines file not found: {path}")
    if path.is_dir():
        raise ValueError(f"lines file {path} is a directory")
    size = path.stat().st_size
    if size > MAX_LINES_FILE_BYTES:
        raise ValueError(
            f"{path}: file is {size / 1e6:.1f} MB; LINES.json files may be at most "
            f"{MAX_LINES_FILE_BYTES / 1e6:g} MB"
        )
    text = path.read_bytes()
    if not text.strip():
        raise ValueError(f"{path}: file is empty")
    try:
        obj = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        msg = str(exc).splitlines()[0]
        raise ValueError(f"{path}: not valid JSON ({msg})") from None
    return parse_lines(obj, str(path))


def lines_to_json(lines, image_size: tuple[int, int]) -> dict:
    """The LINES.json object for ``lines`` (validated) on an image of ``image_size`` (W, H)."""
    obj = {
        "version": LINES_FORMAT_VERSION,
        "image_size": [int(image_size[0]), int(image_size[1])],
        "lines": [[[float(x), float(y)] for x, y in pts] for pts in as_polylines(lines)],
    }
    parse_lines(obj)
    return obj


def save_lines(path: str | Path, lines, image_size: tuple[int, int]) -> None:
    """Write ``lines`` (raw pixels) as LINES.json."""
    Path(path).write_text(json.dumps(lines_to_json(lines, image_size)) + "\n")

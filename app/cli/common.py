"""What every ``aerialreg`` subcommand shares: the usage error, argument checks, JSON output.

Kept apart from :mod:`app.cli.main` (which imports the commands) so that the commands import
only this module and the command line has no import cycle.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path


class UsageError(ValueError):
    """Unusable input: reported as one line and exit status 2."""


def parse_size(text: str, *, max_pixels: int | None = None) -> tuple[int, int]:
    """``"1280x960"`` -> ``(1280, 960)``; UsageError for anything else, sizes under
    ``registration.io.images.MIN_IMAGE_SIDE`` a side or over ``max_pixels`` (default: the frame limit,
    ``registration.io.images.MAX_FRAME_PIXELS``)."""
    from registration.io import MAX_FRAME_PIXELS, MIN_IMAGE_SIDE

    max_pixels = MAX_FRAME_PIXELS if max_pixels is None else max_pixels
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size must look like 1280x960, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise UsageError(f"--size must be positive, got {text!r}")
    if min(w, h) < MIN_IMAGE_SIDE or w * h > max_pixels:
        raise UsageError(
            f"--size {text!r} is outside the limits: at least {MIN_IMAGE_SIDE} pixels a side and "
            f"at most {max_pixels / 1e6:.0f} MP"
        )
    return w, h


def check_output_file(
    path: str | os.PathLike, flag: str, *, force: bool = False, inputs: Sequence = ()
) -> Path:
    """An output file a command may write: UsageError (one line) when it is a folder, its folder
    does not exist, it is one of the command's ``inputs``, or it exists and ``force`` is off."""
    p = Path(path)
    if p.is_dir():
        raise UsageError(f"{flag} {p} is a folder; give a file name")
    if not p.parent.is_dir():
        raise UsageError(f"{flag} {p}: folder {p.parent} does not exist")
    for q in inputs:
        if q is not None and p.exists() and Path(q).exists() and p.samefile(q):
            raise UsageError(f"{flag} {p} is an input of this command; give another file name")
    if p.exists() and not force:
        raise UsageError(f"{flag} {p} exists; pass --force to overwrite it")
    return p


def emit_json(obj: object) -> None:
    """Print exactly one JSON object on standard output."""
    sys.stdout.write(json.dumps(obj, default=_json_default) + "\n")
    sys.stdout.flush()


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# What the user can do about a library error (registration.errors.REMEDIES), in the command
# line's words.
CLI_REMEDIES = {
    "another_folder": "give a new or empty folder for --out",
    "continue_or_restart": (
        "pass --resume to continue it, --force to start over, or choose another folder"
    ),
    "restart": "use another --out or --force to start over",
    "wait": "wait for it or use another --out",
    "another_reference_frame": "choose another --reference-frame",
    "georeference": "give its georeference (a GeoTIFF or world file) with --georef",
    "overwrite": "pass --force to overwrite",
    "resume": "`aerialreg register --resume` redoes them",
    "click": "give one with --seed FX,FY,BX,BY",
}


def error_line(exc: BaseException) -> str:
    """One line describing ``exc`` (an OSError as ``strerror: filename``; a library error with
    what to do about it in the command line's words)."""
    text = str(exc).strip()
    if isinstance(exc, OSError) and exc.strerror and exc.filename:
        text = f"{exc.strerror}: {exc.filename}"
    elif isinstance(exc, OSError) and exc.strerror:
        text = exc.strerror
    line = text.splitlines()[0] if text else type(exc).__name__
    remedy = CLI_REMEDIES.get(getattr(exc, "remedy", ""))
    return f"{line}; {remedy}" if remedy else line

"""``aerialreg``: one console command, one subcommand per stage.

Errors on unusable input are one line on standard error (``aerialreg <cmd>: error: ...``) and exit
status 2, never a traceback; an unexpected error (a bug) is one line and exit status 1 (with
``--verbose``, its traceback). With ``--json`` a command prints exactly one JSON object on standard
output; progress and logs go to standard error.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path

# Subcommand modules in app/commands/, in the order --help lists them.
COMMANDS = (
    "app",
    "simulate",
    "undistort",
    "calibrate",
    "register",
    "evaluate",
    "export",
    "bench",
)


class UsageError(ValueError):
    """Unusable input: reported as one line and exit status 2."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``aerialreg register: error: ...``), like the commands'."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="aerialreg",
        description="Register shaky aerial traffic video to an orthorectified base map.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages to stderr")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"app.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"app.commands.{name}":
                raise
            continue
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run, _command=name)
    return parser


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


def error_line(exc: BaseException) -> str:
    """One line describing ``exc`` (an OSError as ``strerror: filename``)."""
    text = str(exc).strip()
    if isinstance(exc, OSError) and exc.strerror and exc.filename:
        text = f"{exc.strerror}: {exc.filename}"
    elif isinstance(exc, OSError) and exc.strerror:
        text = exc.strerror
    return text.splitlines()[0] if text else type(exc).__name__


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    if not getattr(args, "_run", None):
        parser.print_help(sys.stderr)
        return 2
    if not args.verbose:
        _quiet_opencv()
    try:
        return int(args._run(args) or 0)
    except (UsageError, ValueError, OSError, IndexError) as exc:
        # ValueError and OSError: unusable input (their messages name file and value);
        # IndexError: a frame index outside a sequence.
        if args.verbose:
            logging.getLogger("aerialreg").debug("traceback", exc_info=True)
        sys.stderr.write(f"aerialreg {args._command}: error: {error_line(exc)}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write(f"aerialreg {args._command}: interrupted\n")
        return 130
    except Exception as exc:  # a bug: still one line, the traceback with --verbose
        if args.verbose:
            raise
        sys.stderr.write(
            f"aerialreg {args._command}: internal error: {type(exc).__name__}: "
            f"{error_line(exc)} (run with --verbose for the traceback)\n"
        )
        return 1


def _quiet_opencv() -> None:
    """OpenCV logs decoder errors on stderr ("[ERROR:0@0.04] ... TIFF_Error"); the reader turns
    them into one-line errors itself."""
    try:
        import cv2

        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    except (ImportError, AttributeError):
        pass


if __name__ == "__main__":
    # Through the package, so that the commands' ``app.cli.UsageError`` is the one caught here.
    from app.cli import main as package_main

    sys.exit(package_main())

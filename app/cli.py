"""``aerialreg``: one console command, one subcommand per stage.

Errors on unusable input are one line on standard error (``aerialreg <cmd>: error: ...``) and exit
status 2, never a traceback. With ``--json`` a command prints exactly one JSON object on standard
output; progress and logs go to standard error.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import sys
from collections.abc import Sequence

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


class UsageError(Exception):
    """Unusable input: reported as one line and exit status 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
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


def parse_size(text: str) -> tuple[int, int]:
    """``"1280x960"`` -> ``(1280, 960)``; UsageError for anything else or non-positive sizes."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size must look like 1280x960, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise UsageError(f"--size must be positive, got {text!r}")
    return w, h


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
    try:
        return int(args._run(args) or 0)
    except (UsageError, ValueError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        sys.stderr.write(f"aerialreg {args._command}: error: {msg}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write(f"aerialreg {args._command}: interrupted\n")
        return 130


if __name__ == "__main__":
    sys.exit(main())

"""The ``aerialreg`` console command: one subcommand per module of :mod:`app.cli.commands`.

Errors on unusable input are one line on standard error (``aerialreg <cmd>: error: ...``) and exit
status 2, never a traceback; an unexpected error (a bug) is one line and exit status 1 (with
``--verbose``, its traceback). With ``--json`` a command prints exactly one JSON object on standard
output; progress and logs go to standard error.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from app.cli.common import UsageError, error_line

# Subcommand modules in app/cli/commands/, in the order --help lists them.
COMMANDS = (
    "app",
    "simulate",
    "undistort",
    "calibrate",
    "register",
    "adjust",
    "evaluate",
    "export",
    "traffic",
    "bench",
)


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
            module = importlib.import_module(f"app.cli.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"app.cli.commands.{name}":
                raise
            continue
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run, _command=name)
    return parser


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

"""``aerialreg``: the command line, one console command with one subcommand per stage
(:mod:`app.cli.main`; the subcommands in :mod:`app.cli.commands`, what they share in
:mod:`app.cli.common`). The ``app`` subcommand starts the browser app (:mod:`app.gui`); the
browser app never imports the command line.
"""

from app.cli.common import UsageError, check_output_file, emit_json, error_line, parse_size
from app.cli.main import COMMANDS, build_parser, main

__all__ = [
    "COMMANDS",
    "UsageError",
    "build_parser",
    "check_output_file",
    "emit_json",
    "error_line",
    "main",
    "parse_size",
]

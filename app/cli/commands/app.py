"""``aerialreg app``: the analyst's browser app (viser)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

NAME = "app"
HELP = (
    "Serve the analyst's browser app: calibrate γ, seed by clicking, review matches, residuals "
    "and the registered sequence, mark points for Table 2. Without --frames/--base it opens the "
    "built-in demo (built on first use)."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--base", metavar="IMG", help="base map image (orthorectified)")
    p.add_argument(
        "--frames",
        metavar="VIDEO|DIR|GLOB",
        help="the aerial frames: a video, a folder of images or a glob",
    )
    p.add_argument(
        "--project",
        metavar="DIR",
        help="project folder keeping the session and results (default: one per input under the "
        "user's data folder)",
    )
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to bind (default 127.0.0.1: this machine only; 0.0.0.0: all interfaces, "
        "pages are still accepted only from the address they were served at)",
    )
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; 0 = any free port)")
    p.add_argument(
        "--allow-dir",
        action="append",
        default=[],
        metavar="DIR",
        help="a folder the browser's path field may open files from (repeatable; the project and "
        "the inputs' folders are allowed too, the current folder only when named here)",
    )
    p.add_argument(
        "--max-upload-mb",
        type=float,
        default=500.0,
        metavar="N",
        help="largest upload accepted, in MB (default 500)",
    )


def run(args: argparse.Namespace) -> int:
    from app.cli.common import UsageError
    from app.gui import serve

    if (args.frames is None) != (args.base is None):
        raise UsageError("--frames and --base go together (or give neither for the built-in demo)")
    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port must be 0..65535, got {args.port}")
    if not 0 < args.max_upload_mb < math.inf:
        raise UsageError(f"--max-upload-mb must be a positive number, got {args.max_upload_mb}")
    if args.project and Path(args.project).exists() and not Path(args.project).is_dir():
        raise UsageError(f"--project {args.project} is a file, not a folder")
    serve(
        frames=args.frames,
        base=args.base,
        project_dir=args.project,
        host=args.host,
        port=args.port,
        allow_dirs=args.allow_dir,
        max_upload_mb=args.max_upload_mb,
    )
    return 0

"""``aerialreg bench``: speed and accuracy figures, each against a baseline measured in the same run."""

from __future__ import annotations

import argparse
import importlib
import sys

from app.cli import UsageError, emit_json, parse_size

NAME = "bench"
HELP = "Measure speed and accuracy against in-run baselines and print the figures (markdown or --json)."
SUITES = ("distortion", "simulate", "register", "srif", "export", "app")
MAX_FRAMES = 1000


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "suites",
        nargs="*",
        metavar="SUITE",
        help=f"which suites to run, from {', '.join(SUITES)}, or 'all' (default: register)",
    )
    p.add_argument(
        "--size",
        default="1280x960",
        help="frame size WxH for simulated sequences (default 1280x960)",
    )
    p.add_argument(
        "--frames", type=int, default=6, help="frames per simulated sequence (default 6)"
    )
    p.add_argument("--scene", help="scene image to simulate from instead of the procedural city")
    p.add_argument("--base", help="base map of the same area as --scene")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of markdown")


def run(args: argparse.Namespace) -> int:
    suites = list(args.suites) or ["register"]
    if "all" in suites:
        suites = list(SUITES)
    unknown = [s for s in suites if s not in SUITES]
    if unknown:
        raise UsageError(f"unknown bench suite {unknown[0]!r}; choose from {', '.join(SUITES)}")
    if (args.scene is None) != (args.base is None):
        raise UsageError("--scene and --base go together")
    if not 1 <= args.frames <= MAX_FRAMES:
        raise UsageError(f"--frames must be 1..{MAX_FRAMES}, got {args.frames}")
    args.size_wh = parse_size(args.size)
    if args.scene is not None:
        from registration.io import read_image

        for path in (args.scene, args.base):  # one-line errors before any suite starts
            read_image(path)
    results = {}
    for name in suites:
        module = importlib.import_module(f"app.bench.{name}")
        sys.stderr.write(f"bench: running {name} ...\n")
        results[name] = module.run(args)
    if args.json:
        emit_json(results)
    else:
        for name in suites:
            sys.stdout.write(f"## {importlib.import_module(f'app.bench.{name}').TITLE}\n\n")
            sys.stdout.write(results[name].get("markdown", "") + "\n\n")
    return 0

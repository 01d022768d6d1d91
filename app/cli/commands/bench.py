"""``aerialreg bench``: speed and accuracy figures, each against a baseline measured in the same run."""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from app.cli.common import UsageError, emit_json, parse_size

NAME = "bench"
HELP = "Measure speed and accuracy against in-run baselines and print the figures (markdown or --json)."
# benchmarks.SUITES, repeated so that --help works without the checkout (a test checks they agree).
SUITES = (
    "distortion",
    "simulate",
    "register",
    "heading",
    "scaleout",
    "srif",
    "export",
    "app",
    "flyover",
    "traffic",
)
# Frames a suite takes when neither --frames nor --profile is given, where it is not
# DEFAULT_FRAMES: the real flyover video is scored whole; traffic needs tracks (5 s at 5 frames/s).
SUITE_FRAMES = {"flyover": 600, "traffic": 25}
MAX_FRAMES = 1000
DEFAULT_SIZE, DEFAULT_FRAMES = "1280x960", 6
# Size and frames of a --profile run unless --size/--frames say otherwise: a few minutes of
# `bench register` on 2 cores.
PROFILE_RUNS = {
    "default": ("1280x960", 25),
    "paper-hard": ("1280x960", 25),
    "long-flight": ("640x480", 120),
}
PROFILE_SUITES = ("register", "scaleout", "traffic")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "suites",
        nargs="*",
        metavar="SUITE",
        help=f"which suites to run, from {', '.join(SUITES)}, or 'all' (default: register)",
    )
    p.add_argument(
        "--size",
        help=f"frame size WxH for simulated sequences (default {DEFAULT_SIZE}; with --profile: "
        "the profile's, see there)",
    )
    p.add_argument(
        "--frames",
        type=int,
        help=f"frames per simulated sequence (default {DEFAULT_FRAMES}; with --profile: the "
        "profile's, see there)",
    )
    runs = ", ".join(f"{k} {v[0]} x {v[1]}" for k, v in PROFILE_RUNS.items())
    p.add_argument(
        "--profile",
        choices=tuple(PROFILE_RUNS),
        help=f"{', '.join(PROFILE_SUITES)}: simulate this `aerialreg simulate --profile` flight "
        f"(default size and frames: {runs})",
    )
    p.add_argument(
        "--speed-options",
        action="store_true",
        help="register: also run the default preset on one thread (overlap=False) and, on one "
        "thread, with the SIFT coarse step for every frame (fast_coarse=False), a row each",
    )
    p.add_argument("--scene", help="scene image to simulate from instead of the procedural city")
    p.add_argument("--base", help="base map of the same area as --scene")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--chunk-frames",
        type=int,
        default=0,
        metavar="M",
        help="scaleout: frames per chunk (default: half the frames after the reference frame)",
    )
    p.add_argument(
        "--workers",
        default="1,2",
        metavar="N,N,...",
        help="scaleout: local Dask cluster sizes to measure (default 1,2)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object instead of markdown")


def run(args: argparse.Namespace) -> int:
    suites = list(args.suites) or ["register"]
    if "all" in suites:
        suites = list(SUITES)
    unknown = [s for s in suites if s not in SUITES]
    if unknown:
        raise UsageError(f"unknown bench suite {unknown[0]!r}; choose from {', '.join(SUITES)}")
    if args.profile and any(s not in PROFILE_SUITES for s in suites):
        raise UsageError(f"--profile goes with the suites {', '.join(PROFILE_SUITES)} only")
    if args.speed_options and suites != ["register"]:
        raise UsageError("--speed-options goes with the register suite only")
    size, frames = PROFILE_RUNS.get(args.profile, (DEFAULT_SIZE, DEFAULT_FRAMES))
    if len(suites) == 1 and suites[0] in SUITE_FRAMES and not args.profile:
        frames = SUITE_FRAMES[suites[0]]
    args.size_given = args.size is not None
    args.size = size if args.size is None else args.size
    args.frames = frames if args.frames is None else args.frames
    if (args.scene is None) != (args.base is None):
        raise UsageError("--scene and --base go together")
    if not 1 <= args.frames <= MAX_FRAMES:
        raise UsageError(f"--frames must be 1..{MAX_FRAMES}, got {args.frames}")
    args.size_wh = parse_size(args.size)
    if args.chunk_frames < 0:
        raise UsageError(f"--chunk-frames must be 0 (automatic) or more, got {args.chunk_frames}")
    try:
        args.workers_list = [int(v) for v in args.workers.split(",")]
    except ValueError:
        raise UsageError(f"--workers must be numbers like 1,2, got {args.workers!r}") from None
    if not args.workers_list or not all(1 <= v <= 64 for v in args.workers_list):
        raise UsageError(f"--workers must be numbers 1..64, got {args.workers!r}")
    if args.scene is not None:
        from registration.io import read_image

        for path in (args.scene, args.base):  # one-line errors before any suite starts
            read_image(path)
    modules = {name: suite_module(name) for name in suites}
    results = {}
    for name in suites:
        sys.stderr.write(f"bench: running {name} ...\n")
        results[name] = modules[name].run(args)
    if args.json:
        emit_json(results)
    else:
        for name in suites:
            sys.stdout.write(f"## {modules[name].TITLE}\n\n")
            sys.stdout.write(results[name].get("markdown", "") + "\n\n")
    return 0


def suite_module(name: str):
    """The module of benchmark suite ``name`` from the ``benchmarks`` package of the source
    checkout this ``app`` package belongs to (the benchmarks are not installed with aerialreg);
    UsageError (one line) when there is none."""
    checkout = Path(__file__).resolve().parents[2]
    if (checkout / "benchmarks" / "__init__.py").is_file() and str(checkout) not in sys.path:
        sys.path.insert(0, str(checkout))
    try:
        package = importlib.import_module("benchmarks")
    except ModuleNotFoundError as exc:
        if exc.name != "benchmarks":
            raise
        package = None
    if package is None or not hasattr(package, "SUITES"):
        raise UsageError(
            "aerialreg bench runs from a source checkout of aerialreg: the benchmarks/ folder is "
            "not installed with the package (clone the repository, pip install -e it and run "
            "the command there)"
        )
    return importlib.import_module(f"benchmarks.{name}")

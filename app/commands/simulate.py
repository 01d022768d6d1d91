"""``aerialreg simulate``: render a helicopter sequence with exact ground truth."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from app.cli import UsageError, emit_json, parse_size
from app.progress import ProgressBar

NAME = "simulate"
HELP = (
    "Simulate a shaky helicopter video over a procedural city (or a given scene image) with exact "
    "ground truth: writes OUT/frames/000000.png..., OUT/base.png, OUT/truth.json, OUT/sequence.mp4."
)

EPILOG = """\
The camera looks down with ~70 deg field of view, drifts slowly and jitters in angle (5 frames/s),
has a rolling shutter and Harris radial distortion; frames get blur, noise and JPEG compression.
The base map is the same place as another sensor saw it. Load the truth in Python with
registration.synth.load_truth(OUT): frame_to_base(k, xy) / base_to_frame(k, xy).

examples:
  aerialreg simulate out/sim --frames 20 --size 1280x960
  aerialreg simulate out/songdo --scene ../shared/data/songdo-vision-drone/images/00003.jpg
  aerialreg simulate --demo          # build (once) and print the cached demo sequence
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = EPILOG
    p.add_argument("out", nargs="?", metavar="OUT", help="output folder (omit with --demo)")
    p.add_argument(
        "--scene", metavar="IMG", help="render from this nadir image instead of the procedural city"
    )
    p.add_argument(
        "--base",
        metavar="IMG",
        help="base map of the same area as --scene (default: the scene as another sensor sees it)",
    )
    p.add_argument(
        "--base-from-scene",
        nargs=9,
        type=float,
        metavar="H",
        help="3x3 homography, row-major, from scene pixels to base pixels (default identity)",
    )
    p.add_argument("--frames", type=int, default=25, help="number of frames (default 25)")
    p.add_argument(
        "--size", default="1280x960", help="raw frame size WxH (default 1280x960; paper 2560x1920)"
    )
    p.add_argument(
        "--gamma", type=float, default=0.7, help="Harris distortion gamma of the lens (default 0.7)"
    )
    p.add_argument(
        "--rolling-shutter",
        type=float,
        default=0.04,
        metavar="SECONDS",
        help="readout time top to bottom row, s (default 0.04; 0 = global shutter)",
    )
    p.add_argument(
        "--scale",
        type=float,
        default=None,
        help="frame pixel size in base pixels at the first frame's centre (default: 1.1, or the "
        "largest that fits a --scene)",
    )
    p.add_argument("--fps", type=float, default=5.0, help="frames per second (default 5)")
    p.add_argument(
        "--seed", type=int, default=0, help="random seed (default 0); same seed, same files"
    )
    p.add_argument(
        "--no-vehicles", action="store_true", help="no moving vehicles (procedural city)"
    )
    p.add_argument("--no-video", action="store_true", help="do not write sequence.mp4")
    p.add_argument(
        "--demo",
        action="store_true",
        help="build (first use) or reuse the cached demo sequence and print its folder",
    )
    p.add_argument("--rebuild", action="store_true", help="with --demo: build the demo again")
    p.add_argument(
        "--json", action="store_true", help="print one JSON object describing the output"
    )


def run(args: argparse.Namespace) -> int:
    from registration.synth import SimConfig, demo_sequence, load_truth, simulate

    start = time.monotonic()
    if args.demo:
        if args.out or args.scene or args.base:
            raise UsageError("--demo takes no OUT, --scene or --base (it lives in the user cache)")
        bar = None

        def progress(done: int, total: int) -> None:
            nonlocal bar
            if bar is None:
                bar = ProgressBar(total, "demo").__enter__()
            bar.update(done - bar.done)

        try:
            out = demo_sequence(progress, rebuild=args.rebuild)
        finally:
            if bar is not None:
                bar.__exit__(None, None, None)
    else:
        if not args.out:
            raise UsageError("OUT is required (or use --demo)")
        if args.base and not args.scene:
            raise UsageError("--base needs --scene")
        if args.base_from_scene and not args.scene:
            raise UsageError("--base-from-scene needs --scene")
        if args.rebuild:
            raise UsageError("--rebuild goes with --demo")
        for flag, path in (("--scene", args.scene), ("--base", args.base)):
            if path and not Path(path).is_file():
                raise FileNotFoundError(f"{flag} image not found: {path}")
        if Path(args.out).exists() and not Path(args.out).is_dir():
            raise UsageError(f"OUT exists and is not a folder: {args.out}")
        cfg = SimConfig(
            frame_size=parse_size(args.size),
            n_frames=args.frames,
            fps=args.fps,
            gamma=args.gamma,
            rolling_shutter_s=args.rolling_shutter,
            frame_scale=args.scale,
            seed=args.seed,
            vehicles=not args.no_vehicles,
            video=not args.no_video,
        )
        cfg.validate()
        with ProgressBar(cfg.n_frames + 2, "simulate", stream=sys.stderr) as bar:
            out = simulate(
                args.out,
                cfg,
                scene=args.scene,
                base=args.base,
                base_from_scene=args.base_from_scene,
                progress=lambda done, total: bar.update(done - bar.done),
            )
    truth = load_truth(out)
    info = {
        "out": str(Path(out).resolve()),
        "n_frames": truth.n_frames,
        "frame_size": list(truth.frame_size),
        "base_size": list(truth.base_size),
        "gamma": truth.gamma,
        "base": str(truth.base_path),
        "frames": str(truth.frames_dir),
        "truth": str(Path(out) / "truth.json"),
        "video": str(Path(out) / "sequence.mp4") if (Path(out) / "sequence.mp4").exists() else None,
        "altitude_m": truth.camera_altitude_m(),
        "config": truth.config,
        "seconds": round(time.monotonic() - start, 2),
    }
    if args.json:
        emit_json(info)
    else:
        sys.stdout.write(
            f"{info['n_frames']} frames {info['frame_size'][0]}x{info['frame_size'][1]} "
            f"(gamma {info['gamma']}) over a {info['base_size'][0]}x{info['base_size'][1]} px base "
            f"in {info['out']} ({info['seconds']} s)\n"
        )
    return 0

"""``aerialreg simulate``: render a helicopter sequence with exact ground truth."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from app.cli.common import UsageError, emit_json, parse_size
from app.progress import LazyProgressBar

NAME = "simulate"
HELP = (
    "Simulate a shaky helicopter video over a procedural city (or a given scene image) with exact "
    "ground truth: writes OUT/frames/000000.png..., OUT/base.png, OUT/truth.json, OUT/sequence.mp4."
)

EPILOG = """\
The camera looks down with ~70 deg field of view, drifts and jitters in angle (5 frames/s), has a
rolling shutter and Harris radial distortion; frames get blur, noise and JPEG compression. The base
map is the same place as another sensor saw it, at any heading (--base-heading) and resolution
(--base-scale). Load the truth in Python with registration.synth.load_truth(OUT):
frame_to_base(k, xy) / base_to_frame(k, xy).

OUT must be new or empty: nothing is overwritten without --force, which replaces OUT's frames/,
base.png, truth.json and sequence.mp4 (other files are left alone). The run renders into a hidden
folder inside OUT and swaps the results in at the end, truth.json last.

profiles (--profile NAME; options given on the command line override the profile's values):
{profiles}

examples:
  aerialreg simulate out/sim --frames 20 --size 1280x960
  aerialreg simulate out/hard --profile paper-hard --size 1280x960
  aerialreg simulate out/long --profile long-flight --size 640x480
  aerialreg simulate out/rot30 --rebase out/sim --base-heading 30 --base-scale 0.5
  aerialreg simulate out/songdo --scene ../shared/data/songdo-vision-drone/images/00003.jpg
  aerialreg simulate --demo          # build (once) and print the cached demo sequence
"""

# Command-line option -> SimConfig field, for options that override a profile.
_FIELDS = {
    "frames": "n_frames",
    "size": "frame_size",
    "gamma": "gamma",
    "lens_k2": "lens_k2",
    "rolling_shutter": "rolling_shutter_s",
    "scale": "frame_scale",
    "heading": "heading_deg",
    "shake": "shake_deg",
    "fps": "fps",
    "seed": "seed",
    "base_heading": "base_heading_deg",
    "base_scale": "base_scale",
    "vehicle_gap": "vehicle_gap_m",
    "vehicle_headway": "vehicle_headway_s",
}


def _profiles_text() -> str:
    from registration.synth import PROFILES

    return "\n".join(f"  {name:12s} {p.summary}" for name, p in PROFILES.items())


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = EPILOG.format(profiles=_profiles_text())

    def one_line_error(message: str) -> None:
        # argparse prints the usage first; every bad input here is one line (exit status 2).
        sys.stderr.write(f"aerialreg simulate: error: {message}\n")
        sys.exit(2)

    p.error = one_line_error
    _scene_arguments(p)
    _flight_arguments(p)
    _output_arguments(p)


def _scene_arguments(p: argparse.ArgumentParser) -> None:
    """The output, the profile, the scene and the base map."""
    p.add_argument("out", nargs="?", metavar="OUT", help="output folder (omit with --demo)")
    p.add_argument(
        "--profile",
        metavar="NAME",
        help="start from a named flight (see below); other options override its values",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace OUT's frames/, base.png, truth.json and sequence.mp4 if OUT is not empty",
    )
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
        nargs="+",
        metavar="H",
        help="3x3 homography, row-major, from scene pixels to base pixels (default identity): "
        "9 numbers, space- or comma-separated; write --base-from-scene=h11,h12,... when one "
        "is negative in exponent notation (-8.5e-07), which the shell's argument parser would "
        "take for an option",
    )
    p.add_argument(
        "--rebase",
        metavar="SRC",
        help="copy the simulated sequence SRC to OUT with a new base (--base-heading, "
        "--base-scale); frames are hard-linked, the truth stays exact",
    )


def _flight_arguments(p: argparse.ArgumentParser) -> None:
    """The frames, the lens and the flight."""
    p.add_argument("--frames", type=int, help="number of frames (default 25)")
    p.add_argument("--size", help="raw frame size WxH (default 1280x960; paper 2560x1920)")
    p.add_argument("--gamma", type=float, help="Harris distortion gamma of the lens (default 0.7)")
    p.add_argument(
        "--lens-k2",
        type=float,
        metavar="K2",
        help="extra 4th-order lens term beyond Harris (default 0 = exactly Harris)",
    )
    p.add_argument(
        "--rolling-shutter",
        type=float,
        metavar="SECONDS",
        help="readout time top to bottom row, s (default 0.04; 0 = global shutter)",
    )
    p.add_argument(
        "--scale",
        type=float,
        help="frame pixel size in scene pixels at the first frame's centre (default: 1.1, or "
        "the largest that fits a --scene)",
    )
    p.add_argument(
        "--heading",
        type=float,
        metavar="DEG",
        help="heading of the first frame against the scene, any angle (default 6)",
    )
    p.add_argument(
        "--shake",
        type=float,
        metavar="DEG",
        help="largest camera rotation between consecutive frames, degrees (jitter scaled to it)",
    )
    p.add_argument(
        "--base-heading",
        type=float,
        metavar="DEG",
        help="turn the base map by DEG against the scene (clockwise on screen; default 0)",
    )
    p.add_argument(
        "--base-scale",
        type=float,
        metavar="S",
        help="base pixels per scene pixel, e.g. 0.5 or 2 (default 1; area-averaged when < 1)",
    )


def _output_arguments(p: argparse.ArgumentParser) -> None:
    """Timing, randomness, what is written, the demo."""
    p.add_argument("--fps", type=float, help="frames per second (default 5)")
    p.add_argument("--seed", type=int, help="random seed (default 0); same seed, same files")
    p.add_argument(
        "--no-vehicles", action="store_true", help="no moving vehicles (procedural city)"
    )
    p.add_argument(
        "--vehicle-gap",
        type=float,
        metavar="M",
        help="the vehicles of a lane share one speed and keep at least M metres apart, as real "
        "traffic does (default: each at its own speed, driving through slower ones)",
    )
    p.add_argument(
        "--vehicle-headway",
        type=float,
        metavar="S",
        help="with --vehicle-gap, the gap grows by what the lane's speed covers in S seconds "
        "(drivers keep 1-2 s behind the vehicle ahead; default 0)",
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


def _overrides(args: argparse.Namespace) -> dict:
    out = {}
    for opt, field in _FIELDS.items():
        value = getattr(args, opt)
        if value is not None:
            out[field] = parse_size(value) if opt == "size" else value
    if args.no_vehicles:
        out["vehicles"] = False
    if args.no_video:
        out["video"] = False
    return out


def _config(args: argparse.Namespace):
    from registration.synth import SimConfig
    from registration.synth.profiles import profile_config

    overrides = _overrides(args)
    cfg = profile_config(args.profile, **overrides) if args.profile else SimConfig(**overrides)
    cfg.validate()
    return cfg


def _demo(args: argparse.Namespace) -> Path:
    from registration.synth import demo_sequence

    given = [
        flag
        for flag, v in (
            ("OUT", args.out),
            ("--scene", args.scene),
            ("--base", args.base),
            ("--profile", args.profile),
            ("--rebase", args.rebase),
            ("--force", args.force or None),
        )
        if v
    ]
    if given or _overrides(args):
        raise UsageError(
            f"--demo takes no OUT, --scene, --base, --profile, --rebase, --force or flight "
            f"options (it lives in the user cache), got {(given or list(_overrides(args)))[0]}"
        )
    bar = LazyProgressBar("demo")
    try:
        return demo_sequence(bar, rebuild=args.rebuild)
    finally:
        bar.close()


def _rebase(args: argparse.Namespace) -> Path:
    from registration.synth import rebase

    extra = {
        k: v for k, v in _overrides(args).items() if k not in ("base_heading_deg", "base_scale")
    }
    if args.scene or args.base or args.base_from_scene or args.profile or extra:
        raise UsageError(
            "--rebase reuses SRC's frames: it takes only OUT, --base-heading, --base-scale and "
            "--force"
        )
    if args.base_heading is None and args.base_scale is None:
        raise UsageError("--rebase needs --base-heading and/or --base-scale")
    if not Path(args.rebase).is_dir():
        raise FileNotFoundError(f"--rebase source folder not found: {args.rebase}")
    return rebase(
        args.rebase,
        args.out,
        0.0 if args.base_heading is None else args.base_heading,
        1.0 if args.base_scale is None else args.base_scale,
        force=args.force,
    )


def _homography_arg(tokens: list[str] | None) -> list[float] | None:
    """``--base-from-scene``'s 9 numbers from space- and/or comma-separated tokens."""
    if not tokens:
        return None
    parts = [t for token in tokens for t in token.replace(",", " ").split()]
    try:
        values = [float(t) for t in parts]
    except ValueError:
        raise UsageError(f"--base-from-scene needs 9 numbers, got {' '.join(tokens)!r}") from None
    if len(values) != 9 or not all(math.isfinite(v) for v in values):
        raise UsageError(
            f"--base-from-scene needs 9 finite numbers (a 3x3 homography, row-major), got "
            f"{len(values)}: {' '.join(tokens)!r}"
        )
    return values


def _simulate(args: argparse.Namespace) -> Path:
    from registration.synth import simulate

    if args.base and not args.scene:
        raise UsageError("--base needs --scene")
    if args.base_from_scene and not args.scene:
        raise UsageError("--base-from-scene needs --scene")
    base_from_scene = _homography_arg(args.base_from_scene)
    for flag, path in (("--scene", args.scene), ("--base", args.base)):
        if path and not Path(path).is_file():
            raise FileNotFoundError(f"{flag} image not found: {path}")
    cfg = _config(args)
    return simulate(
        args.out,
        cfg,
        scene=args.scene,
        base=args.base,
        base_from_scene=base_from_scene,
        progress=LazyProgressBar("simulate"),
        force=args.force,
    )


def run(args: argparse.Namespace) -> int:
    from registration.synth import load_truth

    start = time.monotonic()
    if args.demo:
        out = _demo(args)
    else:
        if not args.out:
            raise UsageError("OUT is required (or use --demo)")
        if args.rebuild:
            raise UsageError("--rebuild goes with --demo")
        if Path(args.out).exists() and not Path(args.out).is_dir():
            raise UsageError(f"OUT exists and is not a folder: {args.out}")
        try:
            out = _rebase(args) if args.rebase else _simulate(args)
        except (FileExistsError, NotADirectoryError) as exc:
            raise UsageError(str(exc)) from None
    truth = load_truth(out)
    info = {
        "out": str(Path(out).resolve()),
        "profile": args.profile,
        "n_frames": truth.n_frames,
        "frame_size": list(truth.frame_size),
        "base_size": list(truth.base_size),
        "gamma": truth.gamma,
        "lens_k2": truth.geometry.lens_k2,
        "base_heading_deg": truth.base_map["heading_deg"],
        "base_scale": truth.base_map["scale"],
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
        extra = f", profile {args.profile}" if args.profile else ""
        sys.stdout.write(
            f"{info['n_frames']} frames {info['frame_size'][0]}x{info['frame_size'][1]} "
            f"(gamma {info['gamma']}{extra}) over a {info['base_size'][0]}x{info['base_size'][1]} "
            f"px base in {info['out']} ({info['seconds']} s)\n"
        )
    return 0

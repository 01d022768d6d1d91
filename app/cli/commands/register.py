"""``aerialreg register``: register a whole sequence to a base map (paper section 4 and 5)."""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import time
from pathlib import Path

from app.cli.common import UsageError, emit_json
from app.progress import ProgressBar

# Frames per chunk with --workers/--scheduler (registration.run.dask_executor.DEFAULT_CHUNK_FRAMES,
# repeated here so that --help does not import dask; a test checks they agree).
DEFAULT_CHUNK_FRAMES = 100
# More local worker processes than this is a typo (each holds the base map and a chunk's frames).
MAX_LOCAL_WORKERS = 256

NAME = "register"
HELP = "Register every frame of a video, image folder or glob to an orthorectified base map."


def add_arguments(p: argparse.ArgumentParser) -> None:
    _input_arguments(p)
    _registration_arguments(p)
    _run_arguments(p)


def _input_arguments(p: argparse.ArgumentParser) -> None:
    """The base map, the frames and where the result goes."""
    p.add_argument(
        "--base",
        required=True,
        help="base map (orthorectified): a GeoTIFF (georeference, no-data and palette read from "
        "it), or a PNG/JPEG, optionally with a world file (.pgw/.jgw/.wld) and .prj",
    )
    p.add_argument(
        "--base-crs",
        metavar="CRS",
        help="CRS of the base map (e.g. EPSG:32643) when its files do not say it (a world file "
        "without .prj), or to override the file's: a horizontal projected or geographic 2-D "
        "CRS; 'none' uses the map without its georeference (a map in local units tagged with "
        "a CRS it is not in)",
    )
    p.add_argument(
        "--base-nodata",
        default="auto",
        metavar="auto|file|VALUE",
        help="base map no-data: 'auto' (default: the file's no-data/alpha/mask plus a black "
        "collar touching the border), 'file' (only the file's), or a pixel value",
    )
    p.add_argument(
        "--frames",
        required=True,
        help="video file, directory of images (sorted by name) or glob pattern",
    )
    p.add_argument("--out", required=True, help="result folder (created; written frame by frame)")


def _registration_arguments(p: argparse.ArgumentParser) -> None:
    """γ, the seed, the reference frame and the preset."""
    p.add_argument(
        "--gamma",
        default="auto",
        metavar="G|auto",
        help="Harris radial distortion γ of the frames (0 = none; the paper's camera 0.7). "
        "Default 'auto': estimated from the frames' motion first (as calibrate --frames) and "
        "reported on standard error; an estimate uncertain by more than ±0.03 or at the end of "
        "the searched range (too little motion) is refused in one line saying how to give γ",
    )
    p.add_argument(
        "--seed",
        action="append",
        metavar="FX,FY,BX,BY",
        help="one corresponding point: raw pixel of the reference frame and base pixel of the "
        "same ground spot; heading and scale between frame and map are estimated from it. Give "
        "it twice (two points at least 20 px apart) to fix heading and scale exactly. Without "
        "it the coarse step searches all headings and scales",
    )
    p.add_argument(
        "--reference-frame",
        type=int,
        default=0,
        help="frame registered to the base map inter-sensor (default 0)",
    )
    p.add_argument(
        "--preset",
        default="default",
        help=(
            "parameter preset: 'paper' (exactly the paper's choices), 'default' (faster, at "
            "least as accurate) or 'fast' (one flow per frame: ~20%% less compute at "
            "2560x1920, faster where frames run one stage after the other, e.g. Dask workers, "
            "but not with both cores in one process; up to 5%% more error on small frames)"
        ),
    )
    p.add_argument(
        "--no-local",
        action="store_true",
        help="skip the local displacement field (stage 'local' then equals 'global')",
    )
    p.add_argument(
        "--adjust",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="beyond the paper: once every frame is registered, estimate the frames' global "
        "models together, window by window, from their control points and links between frames "
        "that see the same ground, so that consecutive frames agree; each frame gets a predicted "
        "error, and one likely to be off by more than 2 base px is flagged (default: on with "
        "--preset default, off with paper and fast)",
    )


def _run_arguments(p: argparse.ArgumentParser) -> None:
    """Resuming, chunks and scale-out, what is written."""
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue an interrupted run in --out without redoing finished frames (refused when "
        "the frames, base map or settings differ from the run's; damaged frames are redone)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="delete the registration result already in --out and start over (only a folder "
        "written by 'aerialreg register' is ever deleted)",
    )
    p.add_argument(
        "--chunk-frames",
        type=int,
        metavar="M",
        help="split the frames after the reference frame, and those before it, into chunks of at "
        "most M consecutive frames registered independently (each chunk's first frame without "
        "a predecessor); 0 = one chunk, the default for a run in this process; with --workers or "
        f"--scheduler the default is {DEFAULT_CHUNK_FRAMES}. The result depends on M, not on "
        "where chunks run. --resume takes the folder's",
    )
    scale = p.add_mutually_exclusive_group()
    scale.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="run the chunks on a local Dask cluster of N worker processes (needs "
        "'pip install aerialreg[dask]'); the result is the serial run's with the same "
        "--chunk-frames",
    )
    scale.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run the chunks on an existing Dask cluster, e.g. tcp://10.0.0.5:8786 (its workers "
        "need aerialreg installed and the frames at the same path: README, 'Scale-out with Dask')",
    )
    p.add_argument(
        "--write-frames",
        action="store_true",
        help="also write registered frames (PNG) and an mp4 in base coordinates, cropped to the sequence's footprint",
    )
    p.add_argument(
        "--json", action="store_true", help="print one JSON object with the run's summary"
    )


def parse_seed(text: str | list[str] | None):
    """``--seed`` values -> None, one ``(fx, fy, bx, by)`` or a list of two."""
    if text is None:
        return None
    texts = [text] if isinstance(text, str) else list(text)
    if len(texts) > 2:
        raise UsageError(f"--seed may be given at most twice, got {len(texts)} times")
    seeds = []
    for t in texts:
        parts = t.replace(" ", "").split(",")
        try:
            values = tuple(float(v) for v in parts)
        except ValueError:
            raise UsageError(f"--seed must be four numbers FX,FY,BX,BY, got {t!r}") from None
        if len(values) != 4:
            raise UsageError(f"--seed must be four numbers FX,FY,BX,BY, got {len(values)} in {t!r}")
        if not all(math.isfinite(v) for v in values):
            raise UsageError(f"--seed must be four finite numbers, got {t!r}")
        seeds.append(values)
    return seeds[0] if len(seeds) == 1 else seeds


def parse_gamma(text: str) -> float | None:
    """``--gamma``: a finite number, or None for 'auto'."""
    if text.strip().lower() == "auto":
        return None
    try:
        value = float(text)
    except ValueError:
        raise UsageError(f"--gamma must be a number or 'auto', got {text!r}") from None
    if not math.isfinite(value):
        raise UsageError(f"--gamma must be a finite number, got {text}")
    return value


def gamma_from_motion(frames) -> float:
    """``--gamma auto``: γ from frame pairs of the flight, reported on standard error."""
    from app.cli.commands.calibrate import motion_summary
    from registration.lens import DEFAULT_PAIRS, estimate_gamma_from_flight

    if len(frames) < 2:
        raise UsageError(f"--gamma auto needs 2 frames or more, got {len(frames)}")
    with ProgressBar(DEFAULT_PAIRS, "register (gamma from motion)") as bar:
        est = estimate_gamma_from_flight(
            frames.get, len(frames), progress=lambda done, total: bar.update(1)
        )
    problem = est.unusable_as_default()
    if problem:
        raise UsageError(
            f"gamma could not be estimated from the frames' motion ({problem}); give it with "
            "--gamma G (0 for a lens without distortion; `aerialreg calibrate` measures it from "
            "straight streets)"
        )
    sys.stderr.write(f"gamma {est.gamma:.4f} ± {est.uncertainty:.4f} from the frames' motion\n")
    sys.stderr.write(motion_summary(est) + "\n")
    return float(est.gamma)


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from registration.gis import read_base_map
    from registration.io import open_frames
    from registration.run import check_out_dir, get_preset, register_sequence, validate_inputs

    seed = parse_seed(args.seed)
    gamma = parse_gamma(args.gamma)
    config = get_preset(args.preset)
    if args.no_local:
        config = replace(config, run_local=False)
    if args.adjust is not None:
        from registration.adjustment import SequenceAdjustConfig

        config = replace(config, adjust=SequenceAdjustConfig() if args.adjust else None)
    # A file, another tool's folder or a result without --resume/--force: refused before any work.
    if args.resume and args.force:
        raise UsageError("--resume and --force exclude each other")
    state = check_out_dir(Path(args.out), resume=args.resume, force=args.force)
    config = replace(config, chunk_frames=chunk_frames(args, state))
    base_map = read_base_map(args.base, crs=args.base_crs, nodata=parse_nodata(args.base_nodata))
    base = base_map.image
    frames = open_frames(args.frames)
    if gamma is None:
        gamma = gamma_from_motion(frames)
    validate_inputs(frames, base, gamma, seed, args.reference_frame)
    t0 = time.perf_counter()
    # The bar starts with the first frame, so a refused folder gives just the error line.
    bar = None

    def progress(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = ProgressBar(total, "register").__enter__()
        bar.update(done - bar.done)

    def adjust_progress(done: int, total: int) -> None:
        nonlocal bar
        if bar is None or bar.label != "adjust":
            if bar is not None:
                bar.__exit__(None, None, None)
            bar = ProgressBar(total, "adjust").__enter__()
        bar.update(done - bar.done)

    try:
        with executor(args) as run_on:
            result = register_sequence(
                frames,
                base,
                gamma,
                Path(args.out),
                config=config,
                preset=args.preset,
                base_path=Path(args.base).resolve(),
                seed=seed,
                reference_frame=args.reference_frame,
                resume=args.resume,
                force=args.force,
                progress=progress,
                adjust_progress=adjust_progress,
                base_georef=base_map.georef,
                base_valid=base_map.valid_or_none,
                executor=run_on,
            )
    finally:
        if bar is not None:
            bar.__exit__(None, None, None)
    elapsed = time.perf_counter() - t0
    written = None
    if args.write_frames:
        from registration.render import write_registered_sequence

        with ProgressBar(result.n_frames, "write frames") as bar:
            written = write_registered_sequence(
                result, frames, progress=lambda d, t: bar.update(d - bar.done)
            )
    report(args, result, base_map, config, elapsed, written)
    return 0


def parse_nodata(text: str) -> str | float:
    """``--base-nodata``: ``"auto"``, ``"file"`` or a number; UsageError for anything else."""
    if text in ("auto", "file"):
        return text
    try:
        return float(text)
    except ValueError:
        raise UsageError(
            f"--base-nodata must be 'auto', 'file' or a number, got {text!r}"
        ) from None


def report(args: argparse.Namespace, result, base_map, config, elapsed: float, written) -> None:
    """The run's summary: one JSON object (``--json``) or a few lines, on standard output."""
    failed = [
        {"frame": k, "reason": r.reason} for k, r in enumerate(result.records) if r.status != "ok"
    ]
    flagged = [
        {"frame": k, "predicted_error_px": r.stats["adjustment"]["predicted_error_px"]}
        for k, r in enumerate(result.records)
        if r.ok and r.stats.get("adjustment", {}).get("flagged")
    ]
    summary = {
        "out": str(Path(args.out).resolve()),
        "n_frames": result.n_frames,
        "n_ok": result.n_frames - len(failed),
        "n_failed": len(failed),
        "failed": failed,
        "n_adjusted": sum(result.is_adjusted(k) for k in range(result.n_frames)),
        "flagged": flagged,
        "preset": args.preset,
        "gamma": result.gamma,
        "lens_k2": result.camera.k2,
        "lens": result.records[result.reference_frame].stats.get("lens"),
        "click": result.records[result.reference_frame].stats.get("click"),
        "time_s": round(elapsed, 3),
        "written": written,
        "base_georeferenced": base_map.georef is not None,
        "chunk_frames": config.chunk_frames,
        "workers": args.workers,
        "scheduler": args.scheduler,
        "base_notes": base_map.notes,
    }
    if args.json:
        emit_json(summary)
    else:
        sys.stdout.write(
            f"registered {summary['n_ok']}/{summary['n_frames']} frames into {summary['out']} "
            f"in {elapsed:.1f} s\n"
        )
        if summary["lens"]:
            sys.stdout.write(f"  lens: {summary['lens']['reason']}\n")
        if summary["click"]:
            sys.stdout.write(f"  click: {summary['click']}\n")
        for f in failed:
            sys.stdout.write(f"  frame {f['frame']} failed: {f['reason']}\n")
        if summary["n_adjusted"]:
            sys.stdout.write(
                f"  adjusted {summary['n_adjusted']} frames together; "
                f"{len(flagged)} flagged as likely off by more than "
                f"{config.adjust.flag_px:g} base px\n"
            )
        for f in flagged:
            sys.stdout.write(
                f"  frame {f['frame']} flagged: predicted error "
                f"{f['predicted_error_px']:.2f} base px\n"
            )


def chunk_frames(args: argparse.Namespace, state: str) -> int:
    """The run's chunk size: ``--chunk-frames``; when resuming without it, the folder's (a
    resumed run must be the same run); otherwise 0, or :data:`DEFAULT_CHUNK_FRAMES` with
    ``--workers``/``--scheduler``. UsageError for bad values."""
    distributed = args.workers is not None or args.scheduler is not None
    if args.workers is not None and not 1 <= args.workers <= MAX_LOCAL_WORKERS:
        raise UsageError(f"--workers must be 1..{MAX_LOCAL_WORKERS}, got {args.workers}")
    cores = os.cpu_count() or 1
    if args.workers is not None and args.workers > cores:
        # Each local worker is a process with one thread: more than the cores only contend
        # (24 on 2 cores printed dask tracebacks; 100 did not finish in 130 s).
        raise UsageError(
            f"--workers {args.workers} is more than this machine's {cores} CPU cores; use at "
            f"most {cores}, or --scheduler for a cluster of several machines"
        )
    if args.scheduler is not None and not args.scheduler.strip():
        raise UsageError("--scheduler needs an address, e.g. tcp://10.0.0.5:8786")
    recorded = None
    if args.resume and state == "result":
        from registration.run import load_config

        try:
            recorded = load_config(args.out).chunk_frames
        except (OSError, ValueError, KeyError):
            recorded = None  # ResultWriter.create says what is wrong with the folder
    m = args.chunk_frames
    if m is None:
        m = recorded if recorded is not None else (DEFAULT_CHUNK_FRAMES if distributed else 0)
    if m < 0:
        raise UsageError(f"--chunk-frames must be 0 (one chunk) or more, got {m}")
    if recorded is not None and m != recorded:
        raise UsageError(
            f"cannot resume {args.out}: it was made with --chunk-frames {recorded}, not {m}; "
            "drop --chunk-frames, or use --force to start over"
        )
    if distributed and m == 0:
        made = f" ({args.out} was made so)" if recorded == 0 else ""
        raise UsageError(
            "--workers and --scheduler need chunks: --chunk-frames 0 (one chunk) leaves nothing "
            f"to run in parallel{made}"
        )
    return m


@contextlib.contextmanager
def executor(args: argparse.Namespace):
    """Where the chunks run: None (this process), or a Dask executor on a local cluster
    (``--workers``) or an existing one (``--scheduler``), closed afterwards."""
    if args.workers is None and args.scheduler is None:
        yield None
        return
    import logging

    from registration.run import DaskUnavailable, open_executor, require_distributed

    try:
        require_distributed()  # importing it sets its loggers' levels
        if not logging.getLogger().isEnabledFor(logging.DEBUG):  # without --verbose
            logging.getLogger("distributed").setLevel(logging.WARNING)
        with open_executor(workers=args.workers, scheduler=args.scheduler) as dask_executor:
            yield dask_executor
    except DaskUnavailable as exc:
        raise UsageError(str(exc)) from None

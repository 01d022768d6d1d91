"""Where the CPU goes: CPU seconds per frame by stage, for the default preset (intra-sensor
frames and the sequence adjustment) and Stabilo's recipe, on one simulated flight.

Not part of CI. Everything runs on one thread (``cv2.setNumThreads(1)``, ``overlap=False``) under
``cProfile`` with the process's CPU clock, so each stage's cumulative time is its CPU; the
profiler's own overhead (~10 % here) falls mostly on the Python-heavy stages, so read the
shares, not the absolute figures (``aerialreg bench register`` measures those without a
profiler).

Usage::

    python tools/cpu_by_stage.py --size 1280x960 --frames 10 [--stats ours.prof]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import tempfile
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# (stage, the profiled function whose cumulative time it is[, only its calls from this
# function]), in pipeline order; a function is named by its file's path and its name (the
# file "~": a built-in, as pstats names it).
OURS = (
    ("decode the frame", "registration/run/intra_frames.py", "read_frame", "_chunk_frames"),
    ("coarse step (fast path)", "registration/global_registration/intra.py", "_intra_coarse"),
    ("control points (templates)", "registration/global_registration/intra.py",
     "_intra_control_points"),
    ("fine fit (REQCON, LM)", "registration/global_registration/fine.py", "fit_fine",
     "register_intra"),
    ("local stage (DIS flow + field)", "registration/run/intra_frames.py", "_local_stage"),
    ("... of which DIS flow", "registration/matching/dense_flow.py", "frame_flow",
     "frame_flow_matches"),
    ("write the frame's record", "registration/run/writer.py", "write_frame", "_write_outputs"),
    ("links to the frames before (for the adjustment)", "registration/run/chunk_links.py",
     "add"),
    ("adjustment: links between frames", "registration/adjustment/sequence.py", "links"),
    ("... of which decoding frames again", "registration/run/adjust.py", "grey"),
    ("adjustment: window solves", "registration/adjustment/solve.py", "adjust_models"),
    ("adjustment: local fields made consistent", "registration/run/adjust.py", "_solve"),
    ("adjustment: writing adjusted frames", "registration/run/adjust.py", "_write_adjusted"),
)  # fmt: skip
STABILO = (
    ("decode the frame", "registration/io/frames.py", "get"),
    ("grey + lens correction + ORB", "registration/evaluation/baselines.py", "_orb_features"),
    ("... of which ORB", "~", "<method 'detectAndCompute' of 'cv2.Feature2D' objects>"),
    ("match + MAGSAC++", "registration/evaluation/baselines.py", "stabilo_homography"),
)  # fmt: skip


def _cumulative(stats: pstats.Stats, file_suffix: str, name: str, caller: str = "") -> float:
    """Cumulative CPU seconds of a function (of its calls from ``caller`` when given)."""
    total = 0.0
    for (file, _, func), (_, _, _, cum, callers) in stats.stats.items():
        if func != name or not (file_suffix == "~" or file.endswith(file_suffix)):
            continue
        if not caller:
            total += cum
        else:
            total += sum(c[3] for (_, _, f), c in callers.items() if f == caller)
    return total


def _table(title: str, stats: pstats.Stats, rows, n: int, whole: float) -> list[str]:
    out = [f"| {title} | CPU s per frame | share |", "|---|---:|---:|"]
    for label, *function in rows:
        s = _cumulative(stats, *function) / n
        out.append(f"| {label} | {s:.4f} | {s / whole:.0%} |")
    out.append(f"| **all (profiled run, per frame)** | **{whole:.4f}** | 100% |")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="1280x960")
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--stats", help="also write our run's profile here (pstats format)")
    args = parser.parse_args()
    w, h = (int(v) for v in args.size.split("x"))

    from registration.evaluation import register_baseline, register_stabilo
    from registration.io import open_frames, read_image
    from registration.run import get_preset, register_sequence
    from registration.synth import SimConfig, load_truth, simulate

    cv2.setNumThreads(1)
    tmp = Path(tempfile.mkdtemp(prefix="aerialreg-cpu-"))
    seq = simulate(tmp / "sim", SimConfig(frame_size=(w, h), n_frames=args.frames, video=False,
                                          seed=args.seed))  # fmt: skip
    truth = load_truth(seq)
    frames, base = open_frames(seq / "frames"), read_image(seq / "base.png")
    bx, by = truth.frame_to_base(0, [[w / 2, h / 2]])[0]
    n_intra = args.frames - 1

    prof = cProfile.Profile(time.process_time)
    prof.enable()
    register_sequence(
        frames, base, truth.gamma, tmp / "ours", config=get_preset("default"), preset="default",
        seed=(w / 2, h / 2, float(bx), float(by)), overlap=False,
    )  # fmt: skip
    prof.disable()
    ours = pstats.Stats(prof)
    if args.stats:
        ours.dump_stats(args.stats)
    # The intra-sensor frames: registered and written (the reference frame is its own step).
    intra = _cumulative(ours, "registration/run/pipeline.py", "_write_outputs")
    adjust = _cumulative(ours, "registration/run/adjust.py", "adjust_result")
    whole = (intra + adjust) / n_intra

    link = register_baseline(frames, base, truth.gamma).homographies[0]
    prof = cProfile.Profile(time.process_time)
    t0 = time.process_time()
    prof.enable()
    register_stabilo(frames, link, truth.gamma)
    prof.disable()
    stabilo = pstats.Stats(prof)
    stabilo_whole = (time.process_time() - t0) / args.frames

    lines = [
        f"{args.frames} simulated frames {w}x{h}, seed {args.seed}; one thread, cProfile with "
        "the process CPU clock. Ours: the intra-sensor frames (the reference frame's one-off "
        "inter-sensor registration left out) and the sequence adjustment, per intra-sensor "
        "frame. Stabilo's recipe: per frame, its reference frame's features included.",
        "",
        *_table("default preset", ours, OURS, n_intra, whole),
        "",
        *_table("Stabilo's recipe", stabilo, STABILO, args.frames, stabilo_whole),
    ]
    print("\n".join(lines))


if __name__ == "__main__":
    main()

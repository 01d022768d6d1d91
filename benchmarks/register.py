"""Registration accuracy and speed: our presets, the plain OpenCV pipeline and Stabilo's recipe
(ORB + brute-force Hamming + MAGSAC++ to the reference frame), on one simulated sequence (or a
given scene), scored against the exact truth, all in the same run.

Ours: the ``default``, ``fast`` and ``paper`` presets; with ``--profile NAME`` (a hard simulated
flight, issue 11) the default and fast presets only (the paper preset costs ~4 s per 1280x960
frame and is not what the hard flights measure). The presets run as ``aerialreg register`` runs
them: the fast intra-sensor coarse step (``IntraConfig.fast_coarse``) and both cores
(``register_sequence``'s ``overlap``); ``--speed-options`` adds the default preset on one thread
(``overlap=False``) and, on one thread, with the paper's SIFT coarse step for every frame
(``fast_coarse=False``), each as its own row, and the default and fast runs reading the frames
from the simulator's H.264 video instead of its PNGs (as a flight arrives; the decoding differs,
and the compression changes the pixels a little).

Error per frame: mean over a dense grid of ground points against the truth; reported over the
whole flight (pooled), and per frame averaged over the first, middle and last tenth of the
frames (drift shows as a last tenth worse than the first). Failed frames: ours, frames whose
record is not ``ok``; the baselines, frames without a homography. Off: registered frames whose
mean error exceeds ``GROSS_PX`` (a baseline chaining a frame to a reference frame it no longer
sees returns a wrong homography rather than none). REQCON kept share: control
points kept over those found, mean and lowest over our registered frames.

Times per intra-sensor frame: the stages as each frame's record gives them (``read`` = waiting
for the decoded frame), and the marginal wall time per frame (the time between the progress
reports of the first and the last intra-sensor frame, over their number: decoding, writing and
anything the stages do not count included, threads overlapping included).

CPU per frame (issue 37's measure), for every row: the process's CPU seconds over all its threads
(``time.process_time``) per frame after the first, decoding and lens correction included for
ours and for the baselines (theirs stamped before each frame is decoded), and a video's ffmpeg
decoder process's CPU too; ours split into the registration (between the progress reports of the
first and the last intra-sensor frame) and the sequence adjustment with the result's last writes
(after the last report, spread over all frames). Where that CPU goes by stage:
``tools/cpu_by_stage.py``."""

from __future__ import annotations

import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

TITLE = "Registration: our presets vs plain OpenCV vs Stabilo's recipe"
STAGES = ("read", "coarse", "fine", "local", "total")
# A registered frame whose mean error against the truth exceeds this (base px) is counted as off.
GROSS_PX = 10.0


def _stat_times(result) -> dict[str, float]:
    """Mean seconds per stage over the intra-sensor frames (the reference frame is a one-off)."""
    out = {}
    for stage in STAGES:
        values = [
            r.stats["time_s"].get(stage)
            for k, r in enumerate(result.records)
            if r.status == "ok" and k != result.reference_frame
        ]
        values = [v for v in values if v is not None]
        out[stage] = float(np.mean(values)) if values else float("nan")
    return out


def tenth(n_frames: int) -> int:
    """Frames in a tenth of a flight of ``n_frames`` (at least one)."""
    return max(1, round(n_frames / 10))


def tenths(values) -> dict[str, float]:
    """Mean of the finite ``values`` (one per frame, in frame order) over the first, the middle
    and the last tenth of the frames (:func:`tenth`)."""
    v = np.asarray(values, float)
    t = tenth(len(v))
    mid = (len(v) - t) // 2
    parts = {"first": v[:t], "middle": v[mid : mid + t], "last": v[len(v) - t :]}
    return {
        k: float(np.nanmean(p)) if np.isfinite(p).any() else float("nan") for k, p in parts.items()
    }


def _evaluate(result, truth) -> dict:
    from registration.evaluation import evaluate_truth

    report = evaluate_truth(result, truth)

    def stage(name: str) -> dict:
        per_frame = [
            np.nan if f[name]["mean"] is None else f[name]["mean"] for f in report.per_frame
        ]
        return {k: report.summary[name][k] for k in ("mean", "p95")} | {
            "tenths": tenths(per_frame),
            "per_frame": [round(e, 4) for e in per_frame],
            # A frame a baseline chains to a reference frame it no longer overlaps gets a
            # homography, not a failure: count the frames that are grossly off.
            "frames_off": int(np.sum(np.asarray(per_frame) > GROSS_PX)),
        }

    return {
        "global": stage("global"),
        "local": stage("local"),
        "motion_local_mean": report.summary_motion["local"]["mean"],
        "unregistered_mean": report.summary["unregistered"]["mean"],
        "table2": report.table.to_markdown() if hasattr(report.table, "to_markdown") else "",
    }


def _kept_share(result) -> dict[str, float]:
    """Share of its control points REQCON kept, mean and lowest over the registered frames."""
    shares = [
        r.stats["n_inliers"] / r.stats["n_control_points"]
        for r in result.records
        if r.status == "ok" and r.stats.get("n_control_points")
    ]
    if not shares:
        return {"mean": float("nan"), "min": float("nan")}
    return {"mean": float(np.mean(shares)), "min": float(min(shares))}


def _marginal(stamps: list[float], result) -> float:
    """Wall seconds per intra-sensor frame between the progress reports (``stamps[j]``: when
    ``j + 1`` frames were done) of the first and the last one."""
    n_intra = sum(1 for k in range(result.n_frames) if k != result.reference_frame)
    if n_intra < 2 or len(stamps) < n_intra + 1:
        return float("nan")
    # stamps[0]: the reference frame written; stamps[1]: the first intra-sensor frame.
    return (stamps[n_intra] - stamps[1]) / (n_intra - 1)


def _children_cpu() -> float:
    """CPU seconds of the process's finished child processes (the ffmpeg that decodes a video
    runs as one: its time is added to ours, since ``time.process_time`` does not see it)."""
    t = os.times()
    return t.children_user + t.children_system


def _cpu_per_frame(cpu_stamps: list[float], cpu_end: float, result) -> dict[str, float]:
    """CPU seconds (all the process's threads: decoding, lens correction, OpenCV's own threads
    included) per intra-sensor frame between the progress reports of the first and the last
    one (``registration``), and per frame from the last report to the end (``adjustment``: the
    sequence adjustment and the result's last writes), and their sum (``total``)."""
    n_intra = sum(1 for k in range(result.n_frames) if k != result.reference_frame)
    nan = float("nan")
    if n_intra < 2 or len(cpu_stamps) < n_intra + 1:
        return {"registration": nan, "adjustment": nan, "total": nan}
    reg = (cpu_stamps[n_intra] - cpu_stamps[1]) / (n_intra - 1)
    adj = (cpu_end - cpu_stamps[n_intra]) / result.n_frames
    return {"registration": reg, "adjustment": adj, "total": reg + adj}


def links_cpu_per_frame(result) -> float:
    """CPU seconds per frame of measuring the links between frames for the sequence adjustment
    as the frames were registered (``time_s["links_cpu"]`` of each record; 0 without)."""
    total = sum(r.stats.get("time_s", {}).get("links_cpu", 0.0) for r in result.records)
    return total / max(result.n_frames, 1)


def _run_ours(key, config, overlap, seq, out) -> dict:
    """Register ``seq`` with ``config`` (and ``overlap``) and measure the result."""
    from registration.run import register_sequence

    stamps: list[float] = []
    cpu_stamps: list[float] = []
    last = [-1]

    def progress(done: int, n: int) -> None:
        if done != last[0]:
            last[0] = done
            if done >= 1:
                stamps.append(time.perf_counter())
                cpu_stamps.append(time.process_time())

    children = _children_cpu()
    t1 = time.perf_counter()
    result = register_sequence(
        seq.frames, seq.base, seq.truth.gamma, out, config=config,
        preset=key if key in ("default", "paper", "fast") else None, seed=seq.seed,
        progress=progress,
        overlap=overlap,
    )  # fmt: skip
    elapsed = time.perf_counter() - t1
    cpu = _cpu_per_frame(cpu_stamps, time.process_time(), result)
    # A video's decoder process: its CPU over the run, spread over the frames (counted once it
    # has ended: the reader kept open between frames is closed here, and reopened when needed).
    seq.frames.close()
    cpu["registration"] += (_children_cpu() - children) / result.n_frames
    # The links between frames are measured as frames are registered, for the adjustment: their
    # CPU is the adjustment's.
    links = links_cpu_per_frame(result)
    cpu["registration"] -= links
    cpu["adjustment"] += links
    cpu["total"] = cpu["registration"] + cpu["adjustment"]
    sys.stderr.write(f"bench register: {key} {elapsed:.1f} s\n")
    paths = [r.stats.get("coarse_path") for r in result.records]
    return {
        "times": _stat_times(result) | {"marginal": _marginal(stamps, result)},
        "cpu": cpu,
        **_evaluate(result, seq.truth),
        "wall_s": elapsed,
        "fast_coarse_frames": sum(p == "fast" for p in paths),
        "failed_frames": sum(1 for r in result.records if r.status != "ok"),
        "reqcon_kept": _kept_share(result),
    }


class _CpuStampedFrames:
    """A frame source that notes the process's CPU time before each frame is decoded, so a
    baseline's CPU per frame counts decoding too (the sources here decode on demand)."""

    def __init__(self, frames) -> None:
        self.frames, self.stamps = frames, []

    def __len__(self) -> int:
        return len(self.frames)

    def __getattr__(self, name):
        return getattr(self.frames, name)

    def iter(self, start: int = 0):
        frames = self.frames.iter(start)
        while True:
            self.stamps.append(time.process_time())
            item = next(frames, None)
            if item is None:
                return
            yield item


def _baseline_cpu(stamped: _CpuStampedFrames, cpu_end: float, n_frames: int) -> dict:
    """A baseline's CPU seconds per frame after frame 0 (its reference frame in these runs):
    from before frame 1 is decoded to the end, over ``n_frames - 1`` frames, decoding and lens
    correction included."""
    nan = float("nan")
    if n_frames < 3 or len(stamped.stamps) < 2:
        return {"registration": nan, "adjustment": nan, "total": nan}
    per = (cpu_end - stamped.stamps[1]) / (n_frames - 1)
    return {"registration": per, "adjustment": 0.0, "total": per}


def _baseline_row(res, truth, elapsed, cpu=None) -> dict:
    per_frame = [t for k, t in enumerate(res.times_s) if k != res.reference_frame]
    nan = float("nan")
    total = float(np.mean(per_frame)) if per_frame else nan
    return {
        "times": {s: nan for s in STAGES} | {"total": total, "marginal": nan},
        "cpu": cpu or {"registration": nan, "adjustment": nan, "total": nan},
        **_evaluate(res, truth),
        "wall_s": elapsed,
        "failed_frames": sum(h is None for h in res.homographies),
    }


def our_runs(args) -> list[tuple[str, object, bool]]:
    """``(row key, configuration, overlap)`` of each of our runs that ``args`` asks for."""
    from registration.run import get_preset

    default = get_preset("default")
    runs = [("default", default, True), ("fast", get_preset("fast"), True)]
    if not args.profile:
        runs.append(("paper", get_preset("paper"), False))
    if args.speed_options:
        sift = dataclasses.replace(
            default, intra=dataclasses.replace(default.intra, fast_coarse=False)
        )
        runs += [("serial", default, False), ("sift", sift, False)]
    return runs


def run(args) -> dict:
    from benchmarks.sequence import simulated_sequence
    from registration.evaluation import register_baseline, register_stabilo

    w, h = args.size_wh
    tmp = Path(tempfile.mkdtemp(prefix="aerialreg-bench-"))
    seq = simulated_sequence(args, tmp / "sim", "bench register", video=args.speed_options)
    rows = {
        key: _run_ours(key, config, overlap, seq, tmp / key)
        for key, config, overlap in our_runs(args)
    }
    if args.speed_options:
        # As a flight arrives: H.264 video, decoded by ffmpeg frame after frame.
        from registration.io import open_frames
        from registration.run import get_preset

        video = dataclasses.replace(seq, frames=open_frames(seq.folder / "sequence.mp4"))
        rows["video"] = _run_ours("video", get_preset("default"), True, video, tmp / "video")
        rows["fast_video"] = _run_ours(
            "fast_video", get_preset("fast"), True, video, tmp / "fast_video"
        )

    t1 = time.perf_counter()
    stamped = _CpuStampedFrames(seq.frames)
    opencv = register_baseline(stamped, seq.base, seq.truth.gamma)
    cpu = _baseline_cpu(stamped, time.process_time(), len(seq.frames))
    rows["opencv"] = _baseline_row(opencv, seq.truth, time.perf_counter() - t1, cpu)
    # Stabilo has no base map: it reaches the base through the plain pipeline's reference link.
    t1 = time.perf_counter()
    link = opencv.homographies[opencv.reference_frame]
    stamped = _CpuStampedFrames(seq.frames)
    stabilo = register_stabilo(stamped, link, seq.truth.gamma)
    cpu = _baseline_cpu(stamped, time.process_time(), len(seq.frames))
    rows["stabilo"] = _baseline_row(stabilo, seq.truth, time.perf_counter() - t1, cpu)
    sys.stderr.write("bench register: baselines done\n")
    return {
        "size": [w, h],
        "frames": args.frames,
        "profile": args.profile or "default",
        "rows": rows,
        "markdown": _markdown(rows, args, w, h),
    }


NAMES = {
    "paper": "paper preset",
    "default": "default preset",
    "serial": "default preset on one thread (`overlap=False`)",
    "sift": "same with the SIFT coarse step for every frame (`fast_coarse=False`)",
    "video": "default preset reading the H.264 video (`sequence.mp4`), both cores",
    "fast": "fast preset (one flow per frame for both stages), both cores",
    "fast_video": "fast preset reading the H.264 video, both cores",
    "opencv": "plain OpenCV (SIFT+FLANN+MAGSAC)",
    "stabilo": "Stabilo's recipe (ORB 2000+BF+MAGSAC++ to ref.)",
}
ORDER = (
    "paper", "default", "serial", "sift", "video", "fast", "fast_video", "opencv", "stabilo",
)  # fmt: skip


def _cpu_text(cpu: dict) -> str:
    if not cpu["adjustment"]:
        return _f(cpu["total"])
    return f"{_f(cpu['total'])} ({_f(cpu['registration'])} + {_f(cpu['adjustment'])})"


def _f(v: float | None, digits: int = 3) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"


def _markdown(rows: dict, args, w: int, h: int) -> str:
    d = rows["default"]["times"]["total"]
    flight = f"profile {args.profile}" if args.profile else "default flight"
    lines = [
        f"Sequence: {args.frames} simulated frames {w}x{h} ({flight}), seed {args.seed}; error in "
        "base px against the exact truth (dense grid of ground points); times = mean seconds per "
        "intra-sensor frame on this machine (read = waiting for the decoded frame; total = "
        "read excluded; marginal = wall time per frame between progress reports, decoding and "
        "writing included).",
        "",
        "| pipeline | global mean | global p95 | local mean | local p95 | failed | read s | "
        "coarse s | fine s | local s | total s | marginal s | total vs default | CPU s/frame | "
        "CPU vs Stabilo's |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    stabilo_cpu = rows.get("stabilo", {}).get("cpu", {}).get("total", float("nan"))
    for key in (k for k in ORDER if k in rows):
        r, t = rows[key], rows[key]["times"]
        lines.append(
            f"| {NAMES[key]} | {_f(r['global']['mean'], 2)} | {_f(r['global']['p95'], 2)} | "
            f"{_f(r['local']['mean'], 2)} | {_f(r['local']['p95'], 2)} | {r['failed_frames']} | "
            f"{_f(t['read'])} | {_f(t['coarse'])} | {_f(t['fine'])} | {_f(t['local'])} | "
            f"{_f(t['total'])} | {_f(t['marginal'])} | {_f(t['total'] / d, 2)}x | "
            f"{_cpu_text(r['cpu'])} | {_f(r['cpu']['total'] / stabilo_cpu, 2)}x |"
        )
    lines += ["", *_tenths_table(rows, args.frames), ""]
    for key in (k for k in ORDER if rows.get(k, {}).get("fast_coarse_frames")):
        lines.append(
            f"{NAMES[key]}: {rows[key]['fast_coarse_frames']} of {args.frames - 1} intra-sensor "
            "frames took the fast coarse path."
        )
    lines += [
        "Baselines: decoding excluded from their times (as from ours' total). CPU s/frame: the "
        "process's CPU seconds (all threads) per frame after the first, decoding and lens "
        "correction included for every row (a video's ffmpeg decoder process too); ours: between "
        "the progress reports of the first and the last intra-sensor frame, plus (after +) the "
        "sequence adjustment and last writes spread over all frames.",
        "",
        f"Unregistered motion (corrected frame px): {rows['default']['unregistered_mean']:.1f}",
        "",
        "Table 2 layout, default preset:",
        "",
        rows["default"]["table2"],
    ]
    return "\n".join(lines)


def _tenths_table(rows: dict, n_frames: int) -> list[str]:
    """Error per frame over the flight: each stage of ours, each baseline once (one homography
    per frame: its global and local stages are the same)."""
    t = tenth(n_frames)
    lines = [
        f"Error per frame (base px, mean over frames) over the first, middle and last tenth "
        f"({t} frames each) and the whole flight (pooled over ground points); off: registered "
        f"frames more than {GROSS_PX:g} px off; REQCON kept: mean share of control points kept "
        "(lowest frame).",
        "",
        "| pipeline | stage | first tenth | middle tenth | last tenth | whole flight | failed | "
        f"off > {GROSS_PX:g} px | REQCON kept | total s/frame |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for key in (k for k in ORDER if k in rows):
        r = rows[key]
        kept = r.get("reqcon_kept")
        kept_text = f"{kept['mean']:.1%} ({kept['min']:.1%})" if kept else "–"
        stages = ("global", "local") if kept else ("global",)
        for stage in stages:
            e = r[stage]["tenths"]
            lines.append(
                f"| {NAMES[key]} | {stage if kept else 'homography'} | {_f(e['first'])} | "
                f"{_f(e['middle'])} | {_f(e['last'])} | {_f(r[stage]['mean'])} | "
                f"{r['failed_frames']} | {r[stage]['frames_off']} | {kept_text} | "
                f"{_f(r['times']['total'])} |"
            )
    return lines

"""Traffic (issue 35) on a simulated flight against the simulator's true trajectories: the
traffic stage on aerialreg's registration (default preset) and, in the same run, on plain OpenCV
stabilisation (SIFT + FLANN + MAGSAC, every frame chained to the reference frame and that one
to the map: :func:`registration.evaluation.register_baseline`): what the registration buys.

Scores (:func:`registration.evaluation.traffic.score_traffic`, motmetrics CLEAR-MOT): MOTA,
precision, recall, identity switches, position RMSE (m) and speed RMSE (m/s) of the matched
track points, over every frame of the flight (the vehicles of a frame a registration lost count
as missed). CPU: user + system seconds of this process per frame (all threads), for the
registration and for the traffic stage, and their ratio (the issue's budget: 30 %)."""

from __future__ import annotations

import resource
import sys
import tempfile
from pathlib import Path

import numpy as np

# The flights' vehicles keep their distance in their lanes, as real traffic does (the
# simulator's default lets a vehicle drive through a slower one: 27 % of the vehicle instances of
# a 640x480 default flight touched another, 3 % with this gap, at intersections), and keep
# 1 s behind the vehicle ahead beyond that (car-following models' s0 + v T; with 2 m alone a lane
# at 16 m/s ran 0.13 s apart, and at 5 frames/s a queue moving half its spacing per frame
# looks as if it stood still or ran backwards).
VEHICLE_GAP_M = 2.0
VEHICLE_HEADWAY_S = 1.0

TITLE = "Traffic: vehicles tracked on aerialreg's registration vs plain OpenCV stabilisation"


def _cpu() -> float:
    use = resource.getrusage(resource.RUSAGE_SELF)
    return use.ru_utime + use.ru_stime


class _Homographies:
    """Plain OpenCV's homographies with what the traffic stage asks of a result."""

    def __init__(self, baseline, base_size, reference_frame: int):
        self.baseline = baseline
        self.base_size = tuple(base_size)
        self.frame_size = baseline.frame_size
        self.reference_frame = reference_frame
        self.n_frames = baseline.n_frames

    def frame_to_base(self, k, xy, stage="local"):
        return self.baseline.frame_to_base(k, xy, stage)

    def base_to_frame(self, k, xy, stage="local", *, clip=True):
        return self.baseline.base_to_frame(k, xy, stage, clip=clip)


def _score(result, seq, folder: Path, use: list[int]) -> dict:
    from registration.evaluation.traffic import score_traffic, truth_metric_frame
    from registration.traffic import TrafficConfig
    from registration.traffic.runner import find_traffic

    metric = truth_metric_frame(seq.truth)
    times = np.arange(seq.truth.n_frames) / float(seq.truth.config["fps"])
    cpu = _cpu()
    tracks, _, _, _ = find_traffic(result, seq.frames, folder, metric, times, use, TrafficConfig())
    cpu = _cpu() - cpu
    # Scored over every frame of the flight: a frame the registration lost has no tracks, and
    # its vehicles count as missed.
    every = list(range(seq.truth.n_frames))
    separable = score_traffic(tracks, seq.truth, every, separable_only=True).to_dict()
    return score_traffic(tracks, seq.truth, every).to_dict() | {
        "cpu_s_per_frame": cpu / len(use),
        "separable": separable,
    }


def run(args) -> dict:
    from benchmarks.sequence import simulated_sequence
    from registration.evaluation import register_baseline
    from registration.run import get_preset, register_sequence
    from registration.traffic.sequence import usable_frames

    tmp = Path(tempfile.mkdtemp(prefix="aerialreg-bench-traffic-"))
    seq = simulated_sequence(
        args, tmp / "sim", "bench traffic",
        vehicle_gap_m=VEHICLE_GAP_M, vehicle_headway_s=VEHICLE_HEADWAY_S,
    )  # fmt: skip
    cpu = _cpu()
    result = register_sequence(
        seq.frames, seq.base, seq.truth.gamma, tmp / "reg", config=get_preset("default"),
        preset="default", seed=seq.seed,
    )  # fmt: skip
    reg_cpu = (_cpu() - cpu) / result.n_frames
    sys.stderr.write(f"bench traffic: registered, {reg_cpu:.2f} s CPU per frame\n")
    use, _ = usable_frames(result)
    rows = {"aerialreg": _score(result, seq, tmp / "ours", use)}
    sys.stderr.write("bench traffic: traffic on aerialreg's registration done\n")
    cpu = _cpu()
    baseline = register_baseline(seq.frames, seq.base, seq.truth.gamma)
    base_cpu = (_cpu() - cpu) / baseline.n_frames
    plain = _Homographies(baseline, result.base_size, baseline.reference_frame)
    plain_use = [k for k, h in enumerate(baseline.homographies) if h is not None]
    rows["opencv"] = _score(plain, seq, tmp / "opencv", plain_use)
    sys.stderr.write("bench traffic: traffic on plain OpenCV done\n")
    rows["aerialreg"]["registration_cpu_s_per_frame"] = reg_cpu
    rows["opencv"]["registration_cpu_s_per_frame"] = base_cpu
    return {
        "size": list(args.size_wh),
        "frames": args.frames,
        "profile": args.profile or "default",
        "rows": rows,
        "markdown": _markdown(rows, args),
    }


def _markdown(rows: dict, args) -> str:
    w, h = args.size_wh
    flight = f"profile {args.profile}" if args.profile else "default flight"
    lines = [
        f"{args.frames} simulated frames {w}x{h} ({flight}, vehicles at least {VEHICLE_GAP_M:g} m "
        f"+ {VEHICLE_HEADWAY_S:g} s of their speed apart in their lanes), seed {args.seed}; "
        "scored against "
        "the simulator's vehicle truth (motmetrics, pairs within 2 m); CPU = user + system "
        "seconds per frame of this process.",
        "",
        "| registration | MOTA | precision | recall | ID switches | position RMSE m | "
        "speed RMSE m/s | registration CPU s | traffic CPU s | traffic / registration |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    names = {"aerialreg": "aerialreg (default preset)", "opencv": "plain OpenCV stabilisation"}
    for key, r in rows.items():
        ratio = r["cpu_s_per_frame"] / r["registration_cpu_s_per_frame"]
        for label, s in ((names[key], r), (f"{names[key]}, separable vehicles", r["separable"])):
            lines.append(
                f"| {label} | {s['mota']:.3f} | {s['precision']:.3f} | {s['recall']:.3f} | "
                f"{s['id_switches']} | {s['position_rmse_m']:.3f} | {s['speed_rmse_mps']:.3f} | "
                f"{r['registration_cpu_s_per_frame']:.3f} | {r['cpu_s_per_frame']:.3f} | "
                f"{100 * ratio:.0f} % |"
            )
    lines += [
        "",
        "Separable vehicles: scored without the true vehicles that touch or overlap another "
        "(within 0.5 m: vehicles of crossing lanes meet at intersections, which have no "
        "signals) and the track points that pair with them.",
    ]
    return "\n".join(lines)

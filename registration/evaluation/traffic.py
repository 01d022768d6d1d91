"""Traffic against the simulator's true trajectories: CLEAR-MOT tracking quality (motmetrics'
MOTA, identity switches, precision, recall), position RMSE in metres and speed RMSE in m/s.

Truth and tracks are compared in the same metric frame (the base's pixels at the truth's ground
resolution, :class:`~registration.traffic.timing.MetricFrame`), frame by frame over the frames
the traffic stage used; a track point and a true vehicle pair up when they are within
``max_distance_m`` (motmetrics' Hungarian matching with its identity memory).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from registration.traffic.timing import MetricFrame

# A pairing further apart than this is a miss and a false track, not an error (a car is ~4.5 m).
MAX_DISTANCE_M = 2.0


@dataclass(frozen=True)
class TrafficScore:
    """Tracking quality and kinematic errors (units in the names)."""

    mota: float
    motp_m: float
    precision: float
    recall: float
    id_switches: int
    false_positives: int
    misses: int
    truth_objects: int
    truth_tracks: int
    tracks: int
    position_rmse_m: float
    speed_rmse_mps: float
    velocity_rmse_mps: float
    frames: int

    def to_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def score_traffic(tracks, truth, frames: list[int], max_distance_m: float = MAX_DISTANCE_M):
    """Score ``tracks`` (:class:`~registration.traffic.track.SmoothTrack`, metres in the
    frame :meth:`truth_metric_frame` gives) against ``truth``'s vehicles over ``frames``.

    Raises:
        ValueError: the truth has no vehicles file.
        ImportError: motmetrics is missing (``pip install aerialreg[eval]``).
    """
    try:
        import motmetrics as mm
    except ImportError as exc:  # pragma: no cover - the test extras install it
        raise ImportError(
            "scoring traffic needs motmetrics: pip install 'aerialreg[eval]'"
        ) from exc
    v = _vehicles(truth)
    metric = MetricFrame(None, 1.0 / float(v["base_px_per_m"]))
    true_xy = metric.metres_from_base(np.column_stack([v["x_base"], v["y_base"]]))
    ux, uy = v["ux"], -v["uy"]  # base y runs down, metres' y up
    true_vel = np.column_stack([ux, uy]) * v["speed_mps"][:, None]
    by_frame: dict[int, list[tuple[int, np.ndarray, np.ndarray]]] = {}
    for tr in tracks:
        for i, k in enumerate(tr.frames.tolist()):
            by_frame.setdefault(k, []).append((tr.track_id, tr.xy[i], tr.velocity[i]))
    acc = mm.MOTAccumulator(auto_id=True)
    pos_err, speed_err, vel_err = [], [], []
    for k in frames:
        sel = np.nonzero(v["frame"] == k)[0]
        hyp = by_frame.get(k, [])
        gt_xy = true_xy[sel]
        hyp_xy = np.array([h[1] for h in hyp]).reshape(-1, 2)
        dist = mm.distances.norm2squared_matrix(gt_xy, hyp_xy, max_d2=max_distance_m**2)
        frame_id = acc.update(v["track_id"][sel].tolist(), [h[0] for h in hyp], dist)
        events = acc.mot_events.loc[frame_id]
        for _, ev in events[events.Type.isin(["MATCH", "SWITCH"])].iterrows():
            gi = sel[list(v["track_id"][sel]).index(ev.OId)]
            hv = next(h for h in hyp if h[0] == ev.HId)
            pos_err.append(np.linalg.norm(hv[1] - true_xy[gi]))
            speed_err.append(np.linalg.norm(hv[2]) - v["speed_mps"][gi])
            vel_err.append(np.linalg.norm(hv[2] - true_vel[gi]))
    mh = mm.metrics.create()
    names = ["mota", "motp", "precision", "recall", "num_switches", "num_false_positives"]
    names += ["num_misses", "num_objects", "num_unique_objects"]
    s = mh.compute(acc, metrics=names, name="traffic").iloc[0]

    def rms(a):
        return float(np.sqrt(np.mean(np.square(a)))) if a else float("nan")

    return TrafficScore(
        mota=float(s["mota"]),
        motp_m=float(np.sqrt(s["motp"])) if np.isfinite(s["motp"]) else float("nan"),
        precision=float(s["precision"]),
        recall=float(s["recall"]),
        id_switches=int(s["num_switches"]),
        false_positives=int(s["num_false_positives"]),
        misses=int(s["num_misses"]),
        truth_objects=int(s["num_objects"]),
        truth_tracks=int(s["num_unique_objects"]),
        tracks=len(tracks),
        position_rmse_m=rms(pos_err),
        speed_rmse_mps=rms(speed_err),
        velocity_rmse_mps=rms(vel_err),
        frames=len(frames),
    )


def truth_metric_frame(truth) -> MetricFrame:
    """The metric frame of a simulated base: its pixels at the truth's metres per base pixel."""
    return MetricFrame(None, 1.0 / float(_vehicles(truth)["base_px_per_m"]))


def _vehicles(truth) -> dict:
    """``truth.vehicles()``; a one-line ValueError when the sequence has none."""
    v = truth.vehicles()
    if v is None:
        raise ValueError(
            f"{truth.root}: the simulated sequence has no vehicle truth (vehicles.csv)"
        )
    return v

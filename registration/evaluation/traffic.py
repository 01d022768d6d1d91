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


def score_traffic(
    tracks,
    truth,
    frames: list[int],
    max_distance_m: float = MAX_DISTANCE_M,
    *,
    separable_only: bool = False,
):
    """Score ``tracks`` (:class:`~registration.traffic.track.SmoothTrack`, metres in the
    frame :meth:`truth_metric_frame` gives) against ``truth``'s vehicles over ``frames``.

    ``separable_only``: leave out, frame by frame, the true vehicles that touch or overlap
    another (:func:`touching`; the simulator's vehicles meet at intersections and, unless its
    ``vehicle_gap_m`` is set, drive through each other; no image tells two touching cars apart),
    and the track points that pair with them (MOT benchmarks' "ignore" regions): what the
    tracker does on the vehicles an image can show.

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
    seen: dict[int, tuple[dict, list]] = {}
    for k in frames:
        sel = np.nonzero(v["frame"] == k)[0]
        hyp = by_frame.get(k, [])
        if separable_only and len(sel):
            sel, hyp = _without_touching(v, sel, true_xy, hyp, max_distance_m)
        gt_xy = true_xy[sel]
        hyp_xy = np.array([h[1] for h in hyp]).reshape(-1, 2)
        dist = mm.distances.norm2squared_matrix(gt_xy, hyp_xy, max_d2=max_distance_m**2)
        frame_id = acc.update(v["track_id"][sel].tolist(), [h[0] for h in hyp], dist)
        seen[frame_id] = (dict(zip(v["track_id"][sel].tolist(), sel.tolist(), strict=True)), hyp)
    # The pairs, read once from the events table (building it per frame is quadratic).
    events = acc.mot_events
    paired = events[events.Type.isin(["MATCH", "SWITCH"])]
    for frame_id, oid, hid in zip(
        paired.index.get_level_values(0), paired.OId, paired.HId, strict=True
    ):
        truth_index, hyp = seen[frame_id]
        gi = truth_index[oid]
        hv = next(h for h in hyp if h[0] == hid)
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


# Vehicles closer than this (metres, box to box) count as touching.
TOUCH_GAP_M = 0.5


def touching(v: dict, sel: np.ndarray, gap_m: float = TOUCH_GAP_M) -> np.ndarray:
    """``(len(sel),)`` bool: which of the true vehicles ``sel`` (indices into ``v``, one frame)
    come within ``gap_m`` of another's box (each a ``length_m`` x ``width_m`` box along its
    direction of travel; a crossing pair is compared with the other's width along the axis)."""
    m = float(v["base_px_per_m"])
    xy = np.column_stack([v["x_base"][sel], v["y_base"][sel]]) / m
    u = np.column_stack([v["ux"][sel], v["uy"][sel]])
    length, width = v["length_m"][sel], v["width_m"][sel]
    rel = xy[:, None] - xy[None]
    along = np.abs((rel * u[:, None]).sum(axis=2))
    across = np.abs(rel[..., 0] * u[:, None, 1] - rel[..., 1] * u[:, None, 0])
    parallel = np.abs((u[:, None] * u[None]).sum(axis=2)) > 0.5
    reach_along = np.where(parallel, length[None], width[None]) / 2 + length[:, None] / 2 + gap_m
    reach_across = np.where(parallel, width[None], length[None]) / 2 + width[:, None] / 2 + gap_m
    close = (along < reach_along) & (across < reach_across)
    np.fill_diagonal(close, False)
    return close.any(axis=1)


def _without_touching(v, sel, true_xy, hyp, max_distance_m):
    """``(sel, hyp)`` without the touching true vehicles and the track points that pair with
    them (Hungarian pairing with all true vehicles within ``max_distance_m``)."""
    from scipy.optimize import linear_sum_assignment

    crowd = touching(v, sel)
    if not crowd.any():
        return sel, hyp
    if hyp:
        hyp_xy = np.array([h[1] for h in hyp])
        dist = np.linalg.norm(true_xy[sel][:, None] - hyp_xy[None], axis=2)
        rows, cols = linear_sum_assignment(np.where(dist <= max_distance_m, dist, 1e6))
        drop = {
            c for r, c in zip(rows, cols, strict=True) if crowd[r] and dist[r, c] <= max_distance_m
        }
        hyp = [h for i, h in enumerate(hyp) if i not in drop]
    return sel[~crowd], hyp


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

"""Detections into trajectories: a constant-velocity Kalman filter per vehicle, Hungarian
assignment between predictions and detections, then a forward-backward (Rauch-Tung-Striebel)
constant-velocity smoother over each trajectory.

The filter and smoother are filterpy's (``filterpy.kalman``), the assignment scipy's
``linear_sum_assignment``: the tracker the issue names rather than a home-made one. Norfair pins
numpy < 2 and Roboflow's ``trackers`` pulls ``opencv-python`` (a second cv2 beside
``opencv-contrib-python-headless``) and ``supervision``; filterpy is pure Python on numpy and
scipy (docs/traffic.md).

Everything here is in metres and seconds (:class:`~registration.traffic.timing.MetricFrame`):
``x`` east, ``y`` north, times from the video's timestamps or the user's frame rate.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from filterpy.kalman import KalmanFilter
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from registration.traffic.config import TrafficConfig

# A track begun on a detection whose pixels were matched in a frame before starts at that
# velocity with this uncertainty (m/s): the match's own error (0.1 m median over 0.2 s) and the
# few that caught another vehicle's pixels.
INITIAL_VELOCITY_SIGMA = 2.0
# A cost that no gated pair reaches (scipy needs finite costs).
_FAR = 1e6
# A detection pairs with a track only within the 99 % ellipse of its predicted position
# (chi-square, 2 degrees of freedom).
GATE_CHI2 = 9.21


@dataclass
class _Live:
    """A track being followed: its filter and what it was given."""

    track_id: int
    kf: KalmanFilter
    t_last: float
    velocity_known: bool = False
    frames: list[int] = field(default_factory=list)
    times: list[float] = field(default_factory=list)
    xy: list[NDArray] = field(default_factory=list)
    det_index: list[int] = field(default_factory=list)


@dataclass
class RawTrack:
    """A vehicle's detections in time order: ``frames`` ``(M,)``, ``times`` ``(M,)`` s,
    ``xy`` ``(M, 2)`` metres, ``det_index`` ``(M,)`` (index of each detection in its frame's
    list)."""

    track_id: int
    frames: NDArray[np.int64]
    times: NDArray[np.float64]
    xy: NDArray[np.float64]
    det_index: NDArray[np.int64]


@functools.lru_cache(maxsize=256)
def _cv_matrices(dt: float, q: float) -> tuple[NDArray, NDArray]:
    """Constant-velocity transition and process noise (white acceleration of spectral density
    ``q`` m²/s³) for state ``[x, y, vx, vy]``. Cached (a flight has few distinct frame
    intervals; built afresh they were a tenth of the tracker's time), hence read-only."""
    f = np.eye(4)
    f[0, 2] = f[1, 3] = dt
    q1 = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    qm = np.zeros((4, 4))
    qm[np.ix_([0, 2], [0, 2])] = q1
    qm[np.ix_([1, 3], [1, 3])] = q1
    f.flags.writeable = False
    qm.flags.writeable = False
    return f, qm


def _new_filter(xy: NDArray, sigma_m: float) -> KalmanFilter:
    """A constant-velocity filter at ``xy`` (m) with position noise ``sigma_m``."""
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x = np.array([xy[0], xy[1], 0.0, 0.0])
    # Unknown velocity: anything up to ~30 m/s (1 sigma 15 m/s).
    kf.P = np.diag([sigma_m**2] * 2 + [15.0**2] * 2)
    kf.H = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
    kf.R = np.eye(2) * sigma_m**2
    return kf


def track_detections(
    frames: list[int],
    times: NDArray[np.float64],
    detections: dict[int, NDArray[np.float64]],
    config: TrafficConfig,
    velocities: dict[int, NDArray[np.float64]] | None = None,
) -> list[RawTrack]:
    """Follow vehicles through ``frames`` (ascending; frames left out, e.g. failed ones, are
    simply gaps) at ``times[k]`` (s) given each frame's detections ``(N_k, 2)`` metres and,
    optionally, their measured velocities ``(N_k, 2)`` m/s (NaN where none): a track begun
    on a detection with one starts at that velocity (1-sigma ``INITIAL_VELOCITY_SIGMA``), and
    a detection whose velocity disagrees with a track's (:func:`_velocities_agree`,
    ``config.velocity_gate_mps``) does not join it.

    Returns the tracks with at least ``config.min_hits`` detections, in order of their first
    detection (ids count from 1 in that order; ties broken by position: reproducible).
    """
    q = config.accel_sigma_mps2**2
    gate = config.gate_m
    r_meas = np.eye(2) * config.measurement_sigma_m**2
    live: list[_Live] = []
    done: list[_Live] = []
    next_id = 0
    t_prev = -np.inf
    for k in frames:
        t = float(times[k])
        dets = np.asarray(detections.get(k, np.zeros((0, 2))), np.float64).reshape(-1, 2)
        measured = None if velocities is None else velocities.get(k)
        if measured is not None:
            measured = np.asarray(measured, np.float64).reshape(-1, 2)
            if len(measured) != len(dets):
                raise ValueError(
                    f"frame {k}: {len(measured)} measured velocities for {len(dets)} detections"
                )
        # End the tracks not seen for too long.
        still = []
        for tr in live:
            (done if t - tr.t_last > config.max_gap_s else still).append(tr)
        live = still
        preds = []
        for tr in live:
            f, qm = _cv_matrices(t - tr.t_last, q)
            x = f @ tr.kf.x
            p = f @ tr.kf.P @ f.T + qm
            preds.append((x, p, f, qm))
        cost = np.full((len(live), len(dets)), _FAR)
        if live and len(dets):
            pxy = np.array([p[0][:2] for p in preds])
            resid = dets[None, :, :] - pxy[:, None, :]
            dist = np.linalg.norm(resid, axis=2)
            # Within the prediction's own uncertainty too: at 30 frames/s a new track's reach
            # is ~1.9 m, not the 3 m (90 m/s) of the fixed gate.
            s_inv = np.linalg.inv(np.array([p[1][:2, :2] for p in preds]) + r_meas)
            d2 = np.einsum("tdi,tij,tdj->td", resid, s_inv, resid)
            # A new track's velocity is unknown: in the next frame it may be as far on as a
            # vehicle at gate_speed goes in one frame interval (at the paper's 5 frames/s, 4 m
            # at 72 km/h). Not further after a missed frame: over a gap that reach would chain
            # noise. A track with a velocity keeps the fixed gate.
            fresh = np.array(
                [
                    len(tr.frames) == 1 and tr.t_last == t_prev and not tr.velocity_known
                    for tr in live
                ]
            )
            reach = np.where(fresh, max(gate, config.gate_speed_mps * (t - t_prev)), gate)
            ok = (dist <= reach[:, None]) & (d2 <= GATE_CHI2)
            if measured is not None:
                ok &= _velocities_agree(preds, measured, config.velocity_gate_mps)
            cost = np.where(ok, dist, _FAR)
        rows, cols = linear_sum_assignment(cost) if cost.size else ([], [])
        used = set()
        for r, c in zip(rows, cols, strict=True):
            if cost[r, c] >= _FAR:
                continue
            tr = live[r]
            x, p, f, qm = preds[r]
            tr.kf.x, tr.kf.P = x, p
            tr.kf.update(dets[c])
            tr.t_last = t
            tr.frames.append(k)
            tr.times.append(t)
            tr.xy.append(dets[c].copy())
            tr.det_index.append(int(c))
            used.add(int(c))
        for c in range(len(dets)):
            if c in used:
                continue
            next_id += 1
            tr = _Live(next_id, _new_filter(dets[c], config.measurement_sigma_m), t)
            if measured is not None and np.isfinite(measured[c]).all():
                tr.kf.x[2:4] = measured[c]
                tr.kf.P[2:4, 2:4] = np.eye(2) * INITIAL_VELOCITY_SIGMA**2
                tr.velocity_known = True
            tr.frames.append(k)
            tr.times.append(t)
            tr.xy.append(dets[c].copy())
            tr.det_index.append(c)
            live.append(tr)
        t_prev = t
    done.extend(live)
    kept = [tr for tr in merge_parallel(done) if len(tr.frames) >= config.min_hits]
    return [
        RawTrack(
            i + 1,
            np.asarray(tr.frames, np.int64),
            np.asarray(tr.times, np.float64),
            np.asarray(tr.xy, np.float64),
            np.asarray(tr.det_index, np.int64),
        )
        for i, tr in enumerate(kept)
    ]


def _velocities_agree(preds: list, measured: NDArray, slack_mps: float) -> NDArray[np.bool_]:
    """``(tracks, detections)`` bool: whether each detection's measured velocity ``(N, 2)`` m/s
    lies within the 99 % ellipse of each track's predicted velocity, its uncertainty widened by
    ``slack_mps`` (1 sigma: the match's own error, a vehicle braking or turning). A detection
    with no measured velocity (NaN) agrees with every track."""
    pv = np.array([p[0][2:4] for p in preds])
    s_inv = np.linalg.inv(np.array([p[1][2:4, 2:4] for p in preds]) + np.eye(2) * slack_mps**2)
    resid = measured[None, :, :] - pv[:, None, :]
    d2 = np.einsum("tdi,tij,tdj->td", resid, s_inv, resid)
    return ~(d2 > GATE_CHI2)  # NaN compares False: agrees


# Two tracks that share frames and stay this close (m) in every one of them follow one vehicle.
PARALLEL_M = 3.5


def merge_parallel(tracks: list[_Live]) -> list[_Live]:
    """``tracks`` in order of their first detection (ties by position), each merged with the
    later ones that share at least two frames with it and stay within :data:`PARALLEL_M` of it
    in all of them (their positions averaged where both were seen).

    A vehicle split into two blobs (its body and a piece that blur, a windscreen or its shadow
    cut off) starts a second track beside its own; the two then take its detections in turn
    and both may end too short. Merging them on the simulated flights: MOTA +0.017 to +0.036,
    precision +0.02 to +0.07, recall unchanged (docs/traffic.md)."""
    tracks = sorted(tracks, key=lambda tr: (tr.frames[0], tr.xy[0][1], tr.xy[0][0]))
    first = np.array([tr.frames[0] for tr in tracks])
    # Each track's bounding box: a pair whose boxes lie more than PARALLEL_M apart has no
    # position within it and is passed over at once (most pairs: other vehicles).
    lo = np.array([np.min(tr.xy, axis=0) for tr in tracks]).reshape(-1, 2)
    hi = np.array([np.max(tr.xy, axis=0) for tr in tracks]).reshape(-1, 2)
    merged = np.zeros(len(tracks), np.bool_)
    out = []
    for i, a in enumerate(tracks):
        if merged[i]:
            continue
        at = {k: xy for k, xy in zip(a.frames, a.xy, strict=True)}
        j = i + 1
        while True:
            end = int(np.searchsorted(first, a.frames[-1], side="right"))
            a_lo, a_hi = np.min(a.xy, axis=0), np.max(a.xy, axis=0)
            near = (lo[j:end] <= a_hi + PARALLEL_M).all(axis=1)
            near &= (hi[j:end] >= a_lo - PARALLEL_M).all(axis=1) & ~merged[j:end]
            cand = (j + int(c) for c in np.flatnonzero(near))
            hit = next((c for c in cand if _parallel(at, tracks[c])), None)
            if hit is None:
                break
            # The merged one changes the track: the later ones are looked at again after it.
            j = hit
            _absorb(a, tracks[j])
            at = {k: xy for k, xy in zip(a.frames, a.xy, strict=True)}
            merged[j] = True
            j += 1
        out.append(a)
    return out


def _parallel(at: dict[int, NDArray], b: _Live) -> bool:
    """Whether ``b`` shares at least two frames with the track whose positions by frame are
    ``at`` and stays within :data:`PARALLEL_M` of it in every one (the first far pair ends the
    look: most pairs are other vehicles)."""
    shared = 0
    for k, xy in zip(b.frames, b.xy, strict=True):
        other = at.get(k)
        if other is None:
            continue
        d = other - xy
        if d[0] * d[0] + d[1] * d[1] > PARALLEL_M * PARALLEL_M:
            return False
        shared += 1
    return shared >= 2


def _absorb(a: _Live, b: _Live) -> None:
    """Merge ``b``'s detections into ``a`` (in frame order; shared frames averaged)."""
    rows = {k: (t, xy, d) for k, t, xy, d in zip(a.frames, a.times, a.xy, a.det_index, strict=True)}
    for k, t, xy, d in zip(b.frames, b.times, b.xy, b.det_index, strict=True):
        rows[k] = (t, (rows[k][1] + xy) / 2, rows[k][2]) if k in rows else (t, xy, d)
    order = sorted(rows)
    a.frames = order
    a.times = [rows[k][0] for k in order]
    a.xy = [rows[k][1] for k in order]
    a.det_index = [rows[k][2] for k in order]
    a.t_last = a.times[-1]


_H_VELOCITY = np.array([[0.0, 0, 1, 0], [0, 0, 0, 1]])


def _velocity_update(kf: KalmanFilter, v: NDArray, r: NDArray) -> None:
    """Update ``kf`` with a measured velocity ``v`` (noise ``r``) unless it lies outside the
    prediction's 99 % ellipse (a match on another vehicle or the road)."""
    innovation = v - kf.x[2:4]
    s = kf.P[2:4, 2:4] + r
    if innovation @ np.linalg.solve(s, innovation) > GATE_CHI2:
        return
    kf.update(v, R=r, H=_H_VELOCITY)


@dataclass
class SmoothTrack:
    """A trajectory after the forward-backward smoother, one row per frame from its first to
    its last detection (frames between detections included, ``observed`` False there).

    ``frames`` ``(M,)``, ``times`` ``(M,)`` s, ``xy`` ``(M, 2)`` m, ``velocity`` ``(M, 2)``
    m/s, ``acceleration`` ``(M, 2)`` m/s², ``position_sigma_m`` ``(M,)`` (the smoother's
    1-sigma position uncertainty), ``observed`` ``(M,)`` bool.
    """

    track_id: int
    frames: NDArray[np.int64]
    times: NDArray[np.float64]
    xy: NDArray[np.float64]
    velocity: NDArray[np.float64]
    acceleration: NDArray[np.float64]
    position_sigma_m: NDArray[np.float64]
    observed: NDArray[np.bool_]

    @property
    def speed(self) -> NDArray[np.float64]:
        return np.linalg.norm(self.velocity, axis=1)

    @property
    def travel_m(self) -> float:
        """Distance from the first to the last smoothed position."""
        return float(np.linalg.norm(self.xy[-1] - self.xy[0]))


def blob_noise(
    lengths: NDArray[np.float64], axes: NDArray[np.float64], config: TrafficConfig
) -> NDArray[np.float64]:
    """``(M, 2, 2)`` each detection's position noise (m²): ``config.smooth_sigma_m`` all
    round, plus, along its blob's axis (``axes`` ``(M, 2)`` unit vectors in metres), half the
    length by which its blob is shorter than the track's median blob (``lengths`` ``(M,)`` m):
    a blob that lost one end of its vehicle (a dark windscreen or roof taken for background)
    has its centre that far off along the axis, ahead or behind. Measured on the default
    flight: blobs 3.5-4.5 m long are 0.96 m off along their axis and 0.62 m across (RMS),
    those of 5.5-6.5 m 0.40 and 0.46 m. Longer blobs than the median are not trusted less:
    that gained 0.01 m on the simulated flights and let a roof's relief on the real flyover
    travel far enough to pass for a vehicle."""
    off = 0.5 * np.maximum(np.median(lengths) - lengths, 0.0)
    along = np.einsum("mi,mj->mij", axes, axes) * (off**2)[:, None, None]
    return np.eye(2)[None] * config.smooth_sigma_m**2 + along


def lost_end_noise(
    noise: NDArray[np.float64], frames: NDArray[np.int64], use: list[int], config: TrafficConfig
) -> NDArray[np.float64]:
    """``noise`` ``(M, 2, 2)`` (:func:`blob_noise`) of a track seen in ``frames`` ``(M,)``, with
    the first and the last ``config.end_detections`` detections trusted ``end_noise_factor``
    times less (their noise scaled by its square), unless the track begins at the first or ends
    at the last of the usable frames ``use``, or is too short to keep the ends' speed from its
    middle (at most ``2 * end_detections + 2`` detections).

    A track that begins or ends inside the flight does so where the detector lost its vehicle
    (it left the view, a neighbour's blob took it, it faded into the road), and the blobs just
    before were failing already: on the default simulated flight the smoothed speed was off by
    2.09 m/s RMS (0.80 m/s too slow on average) within 2 frames of an end where the vehicle was
    still in view, 1.75 m/s at a start where it was already in view, against 0.67 m/s where it
    left the view and 0.70 m/s 3 or more frames from an end."""
    n_end = int(config.end_detections)
    if len(frames) <= 2 * n_end + 2 or config.end_noise_factor == 1.0:
        return noise
    out = np.array(noise, np.float64)
    scale = config.end_noise_factor**2
    if int(frames[0]) != use[0]:
        out[:n_end] *= scale
    if int(frames[-1]) != use[-1]:
        out[-n_end:] *= scale
    return out


def smooth_track(
    raw: RawTrack,
    frames: list[int],
    times: NDArray[np.float64],
    config: TrafficConfig,
    noise: NDArray[np.float64] | None = None,
    velocity: dict[int, tuple[NDArray, NDArray]] | None = None,
) -> SmoothTrack:
    """Forward Kalman filter and Rauch-Tung-Striebel smoother (filterpy) over ``raw``'s span of
    ``frames`` (the usable frames, ascending) with a constant-velocity model whose velocity
    wanders by ``config.smooth_accel_sigma_mps2``; the acceleration is the smoothed velocity's
    derivative over time (central differences). ``noise``: ``(M, 2, 2)`` each detection's
    position noise (:func:`blob_noise`); None = ``config.smooth_sigma_m`` for all.
    ``velocity``: by frame, a measured velocity ``(2,)`` m/s and its noise ``(2, 2)`` (m/s)²
    (the vehicle's own pixels matched in the frame before, :func:`vehicle_velocities`), used
    with the position where it agrees with the filter's prediction (99 % ellipse)."""
    first, last = int(raw.frames[0]), int(raw.frames[-1])
    span = [k for k in frames if first <= k <= last]
    seen = dict(zip(raw.frames.tolist(), raw.xy, strict=True))
    if noise is None:
        noise = np.broadcast_to(np.eye(2) * config.smooth_sigma_m**2, (len(raw.frames), 2, 2))
    noise_at = dict(zip(raw.frames.tolist(), noise, strict=True))
    q = config.smooth_accel_sigma_mps2**2
    kf = _new_filter(raw.xy[0], config.smooth_sigma_m)
    kf.P[:2, :2] = noise_at[first]
    xs, ps, fs, qs = [], [], [], []
    t_prev = float(times[span[0]])
    for k in span:
        f, qm = _cv_matrices(float(times[k]) - t_prev, q)
        if k != span[0]:
            kf.predict(F=f, Q=qm)
        if k in seen:
            kf.update(seen[k], R=noise_at[k])
            if velocity is not None and k in velocity:
                _velocity_update(kf, *velocity[k])
        xs.append(kf.x.copy())
        ps.append(kf.P.copy())
        fs.append(f)
        qs.append(qm)
        t_prev = float(times[k])
    # filterpy's smoother steps from k to k + 1 with Fs[k + 1], Qs[k + 1]: the transition into
    # k + 1, as built here.
    sx, sp, _, _ = kf.rts_smoother(np.array(xs), np.array(ps), fs, qs)
    t_span = np.asarray([times[k] for k in span], np.float64)
    if len(span) > 1:
        accel = np.gradient(sx[:, 2:4], t_span, axis=0)
    else:
        accel = np.zeros((1, 2))
    return SmoothTrack(
        raw.track_id,
        np.asarray(span, np.int64),
        t_span,
        sx[:, 0:2].copy(),
        sx[:, 2:4].copy(),
        accel,
        np.sqrt(0.5 * (sp[:, 0, 0] + sp[:, 1, 1])),
        np.array([k in seen for k in span]),
    )

"""The local stage made consistent in time (beyond the paper, whose local stage measures each
frame's displacement field alone, section 5).

A frame's field corrects its global model where relief and the lens bend the view away from it.
Measured per frame against the mid base image, it carries that frame's own matching noise, so
consecutive frames disagree by it (on the real flyover the local stage made frame-to-frame
consistency worse than the global stage). After the sequence adjustment, the correction a frame
needs at a ground point is nearly what its neighbours need there: relief moves slowly across
the frame as the camera moves. So each frame's field is re-expressed on its adjusted model and
averaged, node by node, with its neighbours' fields re-expressed on theirs: the frames within
``field_radius`` frames that saw the ground from nearly the same place (their views less than
``field_baseline_px`` apart: relief looks the same from there), and kept only where the frames
agree on it: the mean is shrunk by how little its spread supports it, ``m (1 - s²/(n |m|²))⁺``
(``s`` the spread of the ``n`` frames' corrections at that node). What is stored is the
difference between the pooled and the frame's own correction, ``δ``, a field on top of the
frame's own local stage (``x' + δ(x') = own_local(q)``), extended from the pooled nodes to the
rest; a frame without neighbours has none (its local stage is the paper's, exactly). (Storing the pooled
field itself on the adjusted model instead needs the model change interpolated between nodes,
which beyond the frame's edge is an extrapolation of two polynomials: the tests' flight lost
0.1 px at the local stage to it.)

Pooling assumes that what differs between the neighbours' corrections is noise. A warp of each
frame's own that the global model does not follow (a strong rolling shutter with shake) differs
between frames for real, and pooling averages it away: on the simulator's paper-hard flight
(7-26 base px between frames) pooling frames 8 px apart made consecutive frames disagree more
at the local stage (0.095 -> 0.14 px), which is why neighbours further apart than
``field_baseline_px`` (5) are left out. Taking a smooth warp off each neighbour before pooling
kept that flight's frames apart but undid the pooling on the real flyover (1.0x -> 2.5x the
floor), whose frames' fields differ mostly in exactly such smooth, noisy warps.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from registration.geometry import DisplacementField, PolyProjective
from registration.local import fill_invalid


@dataclass(frozen=True)
class FrameField:
    """What one frame contributes to its neighbours' fields: its own field, the model it was
    measured on, and its adjusted model."""

    field: DisplacementField
    own: PolyProjective
    adjusted: PolyProjective


def correction_at(
    frame: FrameField, nodes: NDArray, clip: Callable[[NDArray], NDArray]
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The correction ``frame`` makes at base px ``nodes`` (``(N, 2)``), re-expressed on its
    adjusted model, and where its field was measured (the nearest node valid and the node in
    the frame).

    For the frame point ``q`` its own local stage puts at ``x`` (``x + d(x) = g(q)``):
    ``d'(x) = d(x) + g'(q) - g(q)``, exactly where the frame's own local stage was. Beyond the
    frame, the change of model is taken at the nearest point of the frame (``clip``: corrected
    px -> the nearest corrected px inside the raw frame): there both models extrapolate, and
    their difference can grow without bound where neither is held by evidence."""
    f = frame.field
    d = f.sample(nodes, outside="nan")
    gy, gx = f.shape
    ij = np.round((nodes - np.asarray(f.origin)) / f.spacing).astype(int)
    on_grid = (ij[:, 0] >= 0) & (ij[:, 0] < gx) & (ij[:, 1] >= 0) & (ij[:, 1] < gy)
    measured = np.zeros(len(nodes), bool)
    measured[on_grid] = f.valid[ij[on_grid, 1], ij[on_grid, 0]]
    q = frame.own.inverse(nodes + d)
    known = np.isfinite(q).all(axis=1) & np.isfinite(d).all(axis=1)
    out = np.full((len(nodes), 2), np.nan)
    inside = np.zeros(len(nodes), bool)
    if known.any():
        qc = clip(q[known])
        inside[known] = np.hypot(*(qc - q[known]).T) < 1e-6
        out[known] = d[known] + frame.adjusted.apply(qc) - frame.own.apply(qc)
    return out, measured & inside


def consistent_field(
    own: FrameField, neighbours: Sequence[FrameField], clip: Callable[[NDArray], NDArray]
) -> DisplacementField | None:
    """What makes frame ``own``'s local stage consistent with its ``neighbours``' (module
    docstring): a field ``δ`` on its own field's grid, refined (:func:`refined_grid`), that its
    own local stage is corrected by (``x' + δ(x') = own_local(q)``); None without neighbours
    (its local stage stays its own)."""
    if not neighbours:
        return None
    grid = refined_grid(own.field)
    nodes = grid.node_xy.reshape(-1, 2)
    return pool_corrections(grid, [correction_at(f, nodes, clip) for f in (own, *neighbours)])


# The consistency field has twice the nodes per side of the frame's own field: the pooled
# corrections vary between the own field's nodes.
REFINE = 2


def refined_grid(field_: DisplacementField, factor: int = REFINE) -> DisplacementField:
    """An empty field (zeros, nothing valid) on ``field_``'s grid with ``factor`` times the
    nodes per side, over the same extent."""
    gy, gx = field_.shape
    shape = ((gy - 1) * factor + 1, (gx - 1) * factor + 1)
    return DisplacementField(
        field_.origin, field_.spacing / factor, np.zeros((*shape, 2), np.float32),
        np.zeros(shape, bool),
    )  # fmt: skip


def pool_corrections(
    grid: DisplacementField,
    corrections: Sequence[tuple[NDArray, NDArray]],
    support: float = 1.0,
) -> DisplacementField:
    """:func:`consistent_field` from the corrections and their measured masks
    (:func:`correction_at`) at the nodes of ``grid`` (:func:`refined_grid`), the frame's own
    first: where two or more frames measured a node, the pooled correction (shrunk by
    ``support`` times how little its spread supports it) less the frame's own; elsewhere that of
    the nearest such nodes."""
    own = corrections[0][0]
    stack = np.stack([np.where(m[:, None], c, np.nan) for c, m in corrections])  # (F, N, 2)
    n = np.isfinite(stack).all(axis=2).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # nodes no frame measured: NaN
        mean = np.nanmean(stack, axis=0)
        spread2 = np.nansum((stack - mean) ** 2, axis=(0, 2)) / np.maximum(n - 1, 1)
        shrink = np.clip(1.0 - support * spread2 / (n * (mean**2).sum(axis=1)), 0.0, 1.0)
    pooled = (n >= 2) & np.isfinite(own).all(axis=1)
    delta = np.zeros_like(own)
    delta[pooled] = mean[pooled] * np.nan_to_num(shrink[pooled])[:, None] - own[pooled]
    shape = grid.vectors.shape
    # Nodes no neighbour measured (the frame's edges) take the correction of the pooled nodes
    # nearest them, so that it does not stop short at the edge.
    filled = fill_invalid(delta.reshape(shape), pooled.reshape(shape[:2]))
    return DisplacementField(grid.origin, grid.spacing, filled, pooled.reshape(shape[:2]))

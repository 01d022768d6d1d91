"""The local field as a robust regularised spline (``LocalConfig.fit = "spline"``; beyond the
paper): nodes on a grid fitted to every displacement sample with Tukey weights and a
second-difference penalty.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.geometry import DisplacementField, grid_nodes
from registration.local.config import (
    FEW_MATCHES,
    OK,
    OUTSIDE,
    FieldStats,
    LocalConfig,
)

log = logging.getLogger(__name__)


# The spline fit (LocalConfig.fit = "spline"): Tukey's biweight constant (95 % efficiency for
# Gaussian residuals), the floor of the robust scale (template and flow samples are never better
# than ~0.1 px; a smaller scale would reject samples for the grid's own approximation error) and
# the reweighting rounds (the weights settle in 3-4; measured on the reference frames of the
# hard profiles).
SPLINE_TUKEY_C = 4.685
SPLINE_MIN_SIGMA_PX = 0.1
SPLINE_ITERATIONS = 6


def _bilinear_design(pos: NDArray, origin: tuple[float, float], spacing: float, gx: int, gy: int):
    """Sparse ``(N, Gy * Gx)`` matrix of the bilinear weights of each position on the node grid
    (node ``(i, j)`` is column ``i * Gx + j``); positions must lie within the nodes' span."""
    from scipy.sparse import csr_matrix

    u = (pos - np.asarray(origin, np.float64)) / spacing
    j0 = np.minimum(np.floor(u[:, 0]).astype(np.intp), max(gx - 2, 0))
    i0 = np.minimum(np.floor(u[:, 1]).astype(np.intp), max(gy - 2, 0))
    fx, fy = u[:, 0] - j0, u[:, 1] - i0
    j1, i1 = np.minimum(j0 + 1, gx - 1), np.minimum(i0 + 1, gy - 1)
    n = len(pos)
    rows = np.tile(np.arange(n), 4)
    cols = np.concatenate([i0 * gx + j0, i0 * gx + j1, i1 * gx + j0, i1 * gx + j1])
    vals = np.concatenate([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    return csr_matrix((vals, (rows, cols)), shape=(n, gx * gy))


def _second_differences(gx: int, gy: int):
    """Sparse matrix of the second differences of a ``(Gy, Gx)`` node grid along x, along y and
    across (its null space is the affine functions of the node position)."""
    from scipy.sparse import csr_matrix

    idx = np.arange(gx * gy).reshape(gy, gx)
    blocks = []  # (node index arrays, coefficients) per kind of difference
    if gx >= 3:
        blocks.append(([idx[:, :-2], idx[:, 1:-1], idx[:, 2:]], (1.0, -2.0, 1.0)))
    if gy >= 3:
        blocks.append(([idx[:-2], idx[1:-1], idx[2:]], (1.0, -2.0, 1.0)))
    if gx >= 2 and gy >= 2:
        corners = [idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]]
        blocks.append((corners, (1.0, -1.0, -1.0, 1.0)))
    rows, cols, vals, r0 = [], [], [], 0
    for nodes, coef in blocks:
        m = nodes[0].size
        for a, c in zip(nodes, coef, strict=True):
            rows.append(r0 + np.arange(m))
            cols.append(a.ravel())
            vals.append(np.full(m, c))
        r0 += m
    if not rows:
        return csr_matrix((0, gx * gy))
    return csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(r0, gx * gy)
    )


def estimate_field_spline(
    pos: ArrayLike,
    disp: ArrayLike,
    width: int,
    height: int,
    config: LocalConfig = LocalConfig(),
    *,
    origin: tuple[float, float] = (0.0, 0.0),
) -> tuple[DisplacementField, FieldStats]:
    """Displacement field from samples by robust, regularised least squares (``fit="spline"``).

    The node vectors ``v`` minimise ``sum_i w_i |B_i v - d_i|^2 + lam |D v|^2``: ``B_i`` the
    bilinear weights of sample ``i`` (so the field :meth:`DisplacementField.sample` returns
    reproduces the samples), ``D`` the second differences of the nodes along x, y and across,
    ``lam = spline_smoothness * samples / nodes``. The weights ``w_i`` are Tukey's biweight of
    the residual over ``SPLINE_TUKEY_C`` robust standard deviations (1.4826 MAD of the samples
    still weighted, at least ``SPLINE_MIN_SIGMA_PX``), ``SPLINE_ITERATIONS`` rounds from equal
    weights. Nodes beyond the samples continue the field's slope (the penalty's null space is
    affine) instead of repeating the nearest cell's vector.

    Args:
        pos: ``(M, 2)`` base px of the samples; disp: ``(M, 2)`` displacements (base px).
        width, height, origin: the crop of base coordinates the field covers (nodes on the
            base lattice of ``spacing_px``, :func:`grid_nodes`); samples outside the nodes'
            span are not used.

    Returns:
        ``(field, stats)``: ``field.valid`` marks nodes with at least one sample's worth of
        (robust- and bilinear-) weight; per node in ``stats``: the samples touching it
        (``cell_matches``), those with a positive weight (``cell_kept``), their weighted mean
        residual; status "ok", "few_matches" (some weight, under one sample's worth) or
        "outside" (none).
    """
    t0 = time.perf_counter()
    p = np.asarray(pos, np.float64).reshape(-1, 2)
    d = np.asarray(disp, np.float64).reshape(-1, 2)
    spacing = float(config.spacing_px)
    (x0, y0), (gx, gy) = grid_nodes(width, height, spacing, origin)
    span = np.array([x0 + (gx - 1) * spacing, y0 + (gy - 1) * spacing])
    use = np.isfinite(p).all(axis=1) & np.isfinite(d).all(axis=1)
    use &= (p >= (x0, y0)).all(axis=1) & (p <= span).all(axis=1)
    p, d = p[use], d[use]
    if len(p) < max(config.min_matches, 3):
        field_ = DisplacementField(
            (x0, y0), spacing, np.zeros((gy, gx, 2), np.float32), np.zeros((gy, gx), bool)
        )
        stats = FieldStats(
            np.full((gy, gx), OUTSIDE, np.int8),
            np.zeros((gy, gx), np.int32),
            np.zeros((gy, gx), np.int32),
            np.full((gy, gx), np.nan, np.float32),
        )
        t = time.perf_counter() - t0
        return field_, replace(stats, time_match_s=t, time_total_s=t)
    design = _bilinear_design(p, (x0, y0), spacing, gx, gy)
    v, w, r = _robust_node_fit(design, d, gx, gy, config)
    valid, stats = _node_stats(design, w, r, gx, gy)
    field_ = DisplacementField((x0, y0), spacing, v.reshape(gy, gx, 2).astype(np.float32), valid)
    t = time.perf_counter() - t0
    stats = replace(stats, time_match_s=t, time_total_s=t)
    log.debug("spline field: %s", stats.counts())
    return field_, stats


def _robust_node_fit(design, d: NDArray, gx: int, gy: int, config: LocalConfig):
    """The node vectors by iteratively reweighted, regularised least squares (see
    :func:`estimate_field_spline`).

    Args:
        design: sparse ``(M, Gy * Gx)`` bilinear weights of the samples (:func:`_bilinear_design`).
        d: ``(M, 2)`` the samples' displacements, base px.

    Returns:
        ``(v, w, r)``: ``(Gy * Gx, 2)`` node vectors (base px), ``(M,)`` the Tukey weights they
        were fitted with and ``(M,)`` the samples' residuals (base px).
    """
    from scipy.sparse import diags, identity
    from scipy.sparse.linalg import spsolve

    n_nodes = gx * gy
    penalty = _second_differences(gx, gy)
    regulariser = (config.spline_smoothness * len(d) / n_nodes) * (penalty.T @ penalty)
    w = np.ones(len(d))
    for it in range(SPLINE_ITERATIONS):
        normal = design.T @ diags(w) @ design + regulariser
        ridge = 1e-9 * max(float(normal.diagonal().max()), 1.0)
        v = spsolve((normal + ridge * identity(n_nodes)).tocsc(), design.T @ (w[:, None] * d))
        v = np.asarray(v).reshape(n_nodes, 2)
        r = np.linalg.norm(design @ v - d, axis=1)
        if it == SPLINE_ITERATIONS - 1:
            break
        sigma = max(1.4826 * float(np.median(r[w > 0])), SPLINE_MIN_SIGMA_PX)
        u = r / (SPLINE_TUKEY_C * sigma)
        w = np.where(u < 1, (1 - u**2) ** 2, 0.0)
    return v, w, r


def _node_stats(design, w: NDArray, r: NDArray, gx: int, gy: int) -> tuple[NDArray, FieldStats]:
    """``(valid, stats)`` per node of the ``(Gy, Gx)`` grid from the samples' bilinear
    ``design`` ``(M, Gy * Gx)``, weights ``w`` and residuals ``r`` (``(M,)``, base px): valid
    where the weight reaching the node is at least one sample's worth; in ``stats`` the
    samples touching each node, those with a positive weight, their weighted mean residual
    (NaN where not valid) and the status ("ok", "few_matches" or "outside")."""
    status = np.full((gy, gx), OUTSIDE, np.int8)
    n_match = np.zeros((gy, gx), np.int32)
    n_kept = np.zeros((gy, gx), np.int32)
    resid_node = np.full((gy, gx), np.nan, np.float32)
    touching = (design > 0).astype(np.float64)
    support = np.asarray(design.T @ w).reshape(gy, gx)
    n_match[:] = np.asarray(touching.sum(axis=0)).reshape(gy, gx)
    kept = (w > 0).astype(np.float64)
    n_kept[:] = np.asarray(touching.T @ kept).reshape(gy, gx)
    with np.errstate(invalid="ignore", divide="ignore"):
        resid_node[:] = (np.asarray(design.T @ (w * r)).reshape(gy, gx) / support).astype(
            np.float32
        )
    valid = support >= 1.0
    status[(support > 0) & ~valid] = FEW_MATCHES
    status[valid] = OK
    resid_node[~valid] = np.nan
    return valid, FieldStats(status, n_match, n_kept, resid_node)

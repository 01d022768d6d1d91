"""The sequence adjustment (beyond the paper): the global models of many frames estimated
together, so that consecutive frames agree with each other as well as each agrees with the map.

Each frame's model is the paper's polyprojective (eq. 5), ``base_from_corrected``. Two kinds of
evidence, each weighted by its measured noise:

* **frame -> map**: a frame's control points (corrected px -> base px: the mid base image, the
  base map itself, the analyst's clicks), as each frame's own fine step used them;
* **frame <-> frame**: the same ground points seen in two frames (:class:`FrameLinks`):
  ``model_k(p_k)`` and ``model_l(p_l)`` must land on the same base px.

Per frame the paper fits its model to the first kind alone; the errors of one frame's fit are
then independent of its neighbours', and consecutive frames disagree by both (0.40 px at the
90th percentile on the real flyover's first 40 frames, where a homography fitted to the
measured points leaves 0.23). The links tie neighbours together at the precision of
same-sensor matching, and the map evidence of a stretch of frames is pooled.

Solved as bundle adjusters solve it: Gauss-Newton steps on the normal equations, which are
sparse (each residual touches one or two frames' parameters; a frame's block couples only with
the frames it is linked to), each step solved by scipy's sparse direct solver (SuperLU), with
Levenberg-Marquardt damping and iteratively reweighted least squares for a soft-L1 loss, so
that a moving car or a wrong control point does not pull. The Jacobian is analytic
(:meth:`registration.geometry.PolyProjective.param_jacobian`). scipy's ``least_squares``
(trust-region reflective, LSMR on the sparse Jacobian, the same loss) reached the same solution
but needed 30-50 steps of 1.5 s each on the real flyover's first 40 frames (its iterative inner
solver struggles with the polyprojective's correlated coefficients), where the direct solve of
the normal equations converges in a handful of steps of milliseconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from registration.geometry import PolyProjective, quantized


@dataclass(frozen=True)
class AdjustmentConfig:
    """Settings of :func:`adjust_models`.

    Attributes:
        link_sigma_px: expected noise of a frame-to-frame link, base px (same-sensor patches
            of consecutive frames: ~0.1 frame px on real video).
        min_control_sigma_px: floor of a frame's control-point noise (its fine step's
            ``sigma_px``), base px.
        f_scale: residuals beyond this many expected noises are down-weighted (soft-L1).
        cost_tolerance: the solver stops when a step changes the robust cost by less than this
            share of it.
        max_evaluations: iteration cap of the solver (Gauss-Newton steps tried).
    """

    link_sigma_px: float = 0.1
    min_control_sigma_px: float = 0.05
    f_scale: float = 3.0
    cost_tolerance: float = 1e-5
    max_evaluations: int = 50

    def __post_init__(self) -> None:
        for name in ("link_sigma_px", "min_control_sigma_px", "f_scale"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"AdjustmentConfig.{name} must be > 0, got {v!r}")
        if self.max_evaluations < 1:
            raise ValueError(f"max_evaluations must be at least 1, got {self.max_evaluations}")


@dataclass(frozen=True)
class FrameLinks:
    """The same ground points seen in frames ``k`` and ``l``: ``src_k[i]`` (corrected px of
    ``k``) shows what ``src_l[i]`` (corrected px of ``l``) shows; both ``(M, 2)``."""

    k: int
    l: int  # noqa: E741 (the second frame, as in the paper's notation of frame pairs)
    src_k: NDArray[np.float64]
    src_l: NDArray[np.float64]


@dataclass(frozen=True)
class ControlPointSet:
    """Frame ``k``'s control points: ``src`` corrected px -> ``dst`` base px (``(N, 2)``), with
    their noise ``sigma_px`` (base px)."""

    k: int
    src: NDArray[np.float64]
    dst: NDArray[np.float64]
    sigma_px: float


@dataclass(frozen=True)
class AdjustmentResult:
    """Outcome of :func:`adjust_models`.

    Attributes:
        models: the adjusted model of each frame (None where the input had none).
        link_rms_px, control_rms_px: per frame, the RMS residual (base px) of its links and of
            its control points after the adjustment (NaN where it has none).
        success: the solver converged (else it stopped at ``max_evaluations``).
        message: the solver's own words.
        n_evaluations: residual evaluations.
    """

    models: tuple[PolyProjective | None, ...]
    link_rms_px: NDArray[np.float64]
    control_rms_px: NDArray[np.float64]
    success: bool
    message: str
    n_evaluations: int


class _Problem:
    """Residuals and their sparse Jacobian over the stacked parameters of the frames that have
    a model (``index[k]``: their block)."""

    def __init__(self, models, links, controls, cfg: AdjustmentConfig) -> None:
        self.models = models
        has = {k for k, m in enumerate(models) if m is not None}
        # Only frames with evidence are unknowns: a model nothing constrains stays as it is.
        seen = {c.k for c in controls if c.k in has and len(c.src)} | {
            k for lk in links if lk.k in has and lk.l in has and len(lk.src_k) for k in (lk.k, lk.l)
        }
        self.n_params = {k: len(models[k].params) for k in sorted(seen)}
        self.offset, start = {}, 0
        for k, size in self.n_params.items():
            self.offset[k] = start
            start += size
        self.size = start
        self.links = [
            lk for lk in links if lk.k in self.offset and lk.l in self.offset and len(lk.src_k)
        ]
        self.controls = [c for c in controls if c.k in self.offset and len(c.src)]
        self.link_w = 1.0 / cfg.link_sigma_px
        self.control_w = [1.0 / max(c.sigma_px, cfg.min_control_sigma_px) for c in self.controls]
        rows, cols, self.blocks, r = [], [], [], 0
        for lk in self.links:
            m = 2 * len(lk.src_k)
            self.blocks.append(("link", r, m))
            for k in (lk.k, lk.l):
                rr, cc = np.meshgrid(
                    np.arange(r, r + m),
                    np.arange(self.offset[k], self.offset[k] + self.n_params[k]),
                )
                rows.append(rr.T.ravel())
                cols.append(cc.T.ravel())
            r += m
        for c in self.controls:
            m = 2 * len(c.src)
            self.blocks.append(("control", r, m))
            rr, cc = np.meshgrid(
                np.arange(r, r + m),
                np.arange(self.offset[c.k], self.offset[c.k] + self.n_params[c.k]),
            )
            rows.append(rr.T.ravel())
            cols.append(cc.T.ravel())
            r += m
        self.n_rows = r
        self.rows = np.concatenate(rows) if rows else np.zeros(0, int)
        self.cols = np.concatenate(cols) if cols else np.zeros(0, int)

    def model(self, x: NDArray, k: int) -> PolyProjective:
        m = self.models[k]
        o = self.offset[k]
        return PolyProjective(m.degree, x[o : o + self.n_params[k]], m.src_norm, m.dst_norm)

    def _evaluate(self, x: NDArray, with_jacobian: bool):
        res, jac = [], []
        models = {k: self.model(x, k) for k in self.offset}
        for lk in self.links:
            vk, jk = models[lk.k].param_jacobian(lk.src_k)
            vl, jl = models[lk.l].param_jacobian(lk.src_l)
            res.append(((vk - vl) * self.link_w).ravel())
            if with_jacobian:
                jac.append((jk * self.link_w).reshape(-1, jk.shape[2]).ravel())
                jac.append((-jl * self.link_w).reshape(-1, jl.shape[2]).ravel())
        for c, w in zip(self.controls, self.control_w, strict=True):
            v, j = models[c.k].param_jacobian(c.src)
            res.append(((v - c.dst) * w).ravel())
            if with_jacobian:
                jac.append((j * w).reshape(-1, j.shape[2]).ravel())
        r = np.concatenate(res) if res else np.zeros(0)
        if not with_jacobian:
            return r
        data = np.concatenate(jac) if jac else np.zeros(0)
        return sp.csr_matrix((data, (self.rows, self.cols)), shape=(self.n_rows, self.size))

    def residuals(self, x: NDArray) -> NDArray:
        r = self._evaluate(x, False)
        # A model that folds (denominator through 0) gives inf: a large finite residual instead,
        # so the trust region shrinks rather than the solver stopping.
        return np.where(np.isfinite(r), r, 1e6)

    def jacobian(self, x: NDArray):
        return self._evaluate(x, True)

    def per_frame_rms(self, x: NDArray, n: int) -> tuple[NDArray, NDArray]:
        r = self._evaluate(x, False)
        sq = {"link": np.zeros(n), "control": np.zeros(n)}
        cnt = {"link": np.zeros(n), "control": np.zeros(n)}
        li = ci = 0
        for kind, start, m in self.blocks:
            e = r[start : start + m].reshape(-1, 2)
            if kind == "link":
                lk = self.links[li]
                li += 1
                d2 = (e**2).sum(1) / self.link_w**2
                for k in (lk.k, lk.l):
                    sq["link"][k] += d2.sum()
                    cnt["link"][k] += len(d2)
            else:
                c = self.controls[ci]
                d2 = (e**2).sum(1) / self.control_w[ci] ** 2
                ci += 1
                sq["control"][c.k] += d2.sum()
                cnt["control"][c.k] += len(d2)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.sqrt(sq["link"] / cnt["link"]), np.sqrt(sq["control"] / cnt["control"])


def _robust_weights(r: NDArray, f_scale: float) -> NDArray:
    """IRLS weights of the soft-L1 loss ``2 (sqrt(1 + z) - 1)``, ``z = |e|² / f²``, per point
    (the two components of a residual pair share their point's weight)."""
    z = (r.reshape(-1, 2) ** 2).sum(1) / f_scale**2
    return np.repeat(1.0 / np.sqrt(1.0 + z), 2)


def _robust_cost(r: NDArray, f_scale: float) -> float:
    z = (r.reshape(-1, 2) ** 2).sum(1) / f_scale**2
    return float(np.sum(2.0 * (np.sqrt(1.0 + z) - 1.0)) * f_scale**2)


def _solve(problem: _Problem, x0: NDArray, cfg: AdjustmentConfig) -> tuple[NDArray, bool, int]:
    """Damped Gauss-Newton with IRLS weights on the sparse normal equations (module docstring):
    ``(x, converged, steps tried)``."""
    x = x0
    r = problem.residuals(x)
    cost = _robust_cost(r, cfg.f_scale)
    damping = 1e-6
    for step in range(1, cfg.max_evaluations + 1):
        jac = problem.jacobian(x)
        w = _robust_weights(r, cfg.f_scale)
        jw = jac.multiply(w[:, None]).tocsr()
        normal = (jac.T @ jw).tocsc()
        grad = jw.T @ r
        diag = normal.diagonal()
        while True:
            lhs = normal + sp.diags(damping * np.maximum(diag, 1e-12), format="csc")
            dx = spla.spsolve(lhs, -grad)
            x_new = x + dx
            r_new = problem.residuals(x_new)
            cost_new = _robust_cost(r_new, cfg.f_scale)
            if cost_new <= cost:
                break
            damping *= 10.0
            if damping > 1e6:
                return x, False, step
        done = cost - cost_new <= cfg.cost_tolerance * cost
        x, r, cost = x_new, r_new, cost_new
        damping = max(damping / 10.0, 1e-9)
        if done:
            return x, True, step
    return x, False, cfg.max_evaluations


def adjust_models(
    models: Sequence[PolyProjective | None],
    links: Sequence[FrameLinks],
    controls: Sequence[ControlPointSet],
    config: AdjustmentConfig | None = None,
) -> AdjustmentResult:
    """Estimate the frames' global models together (module docstring).

    Args:
        models: each frame's model from its own fine step (the start), None for a failed
            frame (left out, with the links that touch it).
        links: frame-to-frame correspondences (:class:`FrameLinks`), corrected px.
        controls: each frame's control points to the map (:class:`ControlPointSet`).

    Returns:
        The adjusted models (recorded to the project's quantum, as every stage's models are) and
        per-frame residuals.
    """
    cfg = config or AdjustmentConfig()
    models = list(models)
    problem = _Problem(models, links, controls, cfg)
    n = len(models)
    if problem.size == 0 or problem.n_rows == 0:
        nan = np.full(n, np.nan)
        return AdjustmentResult(tuple(models), nan, nan, True, "nothing to adjust", 0)
    x0 = np.concatenate([models[k].params for k in problem.offset])
    x, converged, steps = _solve(problem, x0, cfg)
    out = [quantized(problem.model(x, k)) if k in problem.offset else models[k] for k in range(n)]
    link_rms, control_rms = problem.per_frame_rms(x, n)
    message = f"converged in {steps} steps" if converged else f"stopped after {steps} steps"
    return AdjustmentResult(tuple(out), link_rms, control_rms, converged, message, steps)

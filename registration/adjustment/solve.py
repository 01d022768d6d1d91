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

from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray
from scipy.linalg import lapack

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
            share of it. (1e-5 took 45 steps instead of 12 on a 2560x1920 flight whose links
            reach 2 px, crawling through the soft-L1 weights of links beyond ``f_scale``, and
            moved its frames by 0.002 px more.)
        max_evaluations: iteration cap of the solver (Gauss-Newton steps tried).
        noise_rounds: rounds of re-estimating each frame's control-point noise from its own
            residuals after a solution (variance components): a frame whose control points
            disagree with everything else as a whole (its own registration went wrong, so they
            agree with each other and a robust loss keeps them) then weighs as little as it
            deserves, and does not pull its neighbours. 0 = the noise as given.
    """

    link_sigma_px: float = 0.1
    min_control_sigma_px: float = 0.05
    f_scale: float = 3.0
    cost_tolerance: float = 1e-4
    max_evaluations: int = 50
    noise_rounds: int = 2

    def __post_init__(self) -> None:
        for name in ("link_sigma_px", "min_control_sigma_px", "f_scale"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"AdjustmentConfig.{name} must be > 0, got {v!r}")
        if self.noise_rounds < 0:
            raise ValueError(f"noise_rounds must be 0 or more, got {self.noise_rounds}")
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
    their noise ``sigma_px`` (base px); ``fixed_noise``: the noise is known (an analyst's map
    points) and not re-estimated from the residuals."""

    k: int
    src: NDArray[np.float64]
    dst: NDArray[np.float64]
    sigma_px: float
    fixed_noise: bool = False


@dataclass(frozen=True)
class AdjustmentResult:
    """Outcome of :func:`adjust_models`.

    Attributes:
        models: the adjusted model of each frame (None where the input had none).
        link_rms_px, control_rms_px: per frame, the RMS residual (base px) of its links and of
            its control points after the adjustment (NaN where it has none).
        position_sigma_px: per frame, the standard deviation (base px) of where the adjusted
            model puts its points (RMS over its control and link points), from the solution's
            covariance scaled by the residuals' own variance factor (NaN where the frame was no
            unknown): what the evidence leaves unknown, not a model error the evidence shares.
        variance_factor: the a-posteriori variance factor (weighted squared residuals per degree
            of freedom; 1 when the residuals are as noisy as their expected noise).
        success: the solver converged (else it stopped at ``max_evaluations``).
        message: the solver's own words.
        n_evaluations: residual evaluations.
    """

    models: tuple[PolyProjective | None, ...]
    link_rms_px: NDArray[np.float64]
    control_rms_px: NDArray[np.float64]
    position_sigma_px: NDArray[np.float64]
    variance_factor: float
    success: bool
    message: str
    n_evaluations: int


class _Problem:
    """Residuals and their sparse Jacobian over the stacked parameters of the frames that have
    a model (``index[k]``: their block)."""

    def __init__(self, models, links, controls, cfg: AdjustmentConfig, fixed=(), priors=()) -> None:
        self.models = models
        has = {k for k, m in enumerate(models) if m is not None}
        fixed = {k for k in fixed if k in has}
        # Only frames with evidence are unknowns: a model nothing constrains stays as it is. A
        # fixed frame (final already, or the reference frame the mid base image is made of)
        # enters its links as a constant.
        seen = {c.k for c in controls if c.k in has and len(c.src)} | {
            k for lk in links if lk.k in has and lk.l in has and len(lk.src_k) for k in (lk.k, lk.l)
        }
        self.n_params = {k: len(models[k].params) for k in sorted(seen - fixed)}
        self.offset, start = {}, 0
        for k, size in self.n_params.items():
            self.offset[k] = start
            start += size
        self.size = start
        self.fixed = fixed
        self.links = [
            lk
            for lk in links
            if {lk.k, lk.l} <= (set(self.offset) | fixed)
            and (lk.k in self.offset or lk.l in self.offset)
            and len(lk.src_k)
        ]
        self.controls = [c for c in controls if c.k in self.offset and len(c.src)]
        self.n_controls = len(self.controls)
        # Priors are control points of another kind: the same residual, not counted as evidence.
        self.controls += [c for c in priors if c.k in self.offset and len(c.src)]
        self.link_w = 1.0 / cfg.link_sigma_px
        self.control_w = [1.0 / max(c.sigma_px, cfg.min_control_sigma_px) for c in self.controls]
        self.blocks, r = [], 0
        for lk in self.links:
            self.blocks.append(("link", r, 2 * len(lk.src_k)))
            r += 2 * len(lk.src_k)
        for i, c in enumerate(self.controls):
            self.blocks.append(("control" if i < self.n_controls else "prior", r, 2 * len(c.src)))
            r += 2 * len(c.src)
        self.n_rows = r
        # The points never move: their monomials are computed once (each frame's source
        # normalisation is fixed in the solve).
        self.link_design = [
            (models[lk.k].design(lk.src_k), models[lk.l].design(lk.src_l)) for lk in self.links
        ]
        self.control_design = [models[c.k].design(c.src) for c in self.controls]
        self._stack_points()
        self._normal_index = None

    def _stack_points(self) -> None:
        """Each unknown frame's points of every block, stacked (``stack[k]``: their monomials),
        and per block where its points lie there (``sides``: ``(k, lo, hi)`` per frame of the
        block, or a held frame's values, which never change): the normal equations then take
        one Jacobian per frame, not one per block and frame."""
        parts: dict[int, list] = {k: [] for k in self.offset}
        count = dict.fromkeys(self.offset, 0)

        def place(k, design):
            if k not in self.offset:
                return self.models[k].apply_design(design)
            lo = count[k]
            count[k] += len(design)
            parts[k].append(design)
            return k, lo, count[k]

        self.sides = [
            (place(lk.k, dk), place(lk.l, dl))
            for lk, (dk, dl) in zip(self.links, self.link_design, strict=True)
        ]
        self.sides += [
            (place(c.k, d),) for c, d in zip(self.controls, self.control_design, strict=True)
        ]
        self.stack = {k: np.concatenate(p) for k, p in parts.items() if p}

    def model(self, x: NDArray, k: int) -> PolyProjective:
        m = self.models[k]
        if k not in self.offset:
            return m
        o = self.offset[k]
        return PolyProjective(m.degree, x[o : o + self.n_params[k]], m.src_norm, m.dst_norm)

    def _block_residuals(self, vals: dict[int, NDArray]):
        """Per block, in order: ``(sides, block weight, residuals (m, 2))``, the residuals
        weighted by the block's expected noise, from ``vals[k]`` (each unknown frame's model at
        its stacked points, base px)."""
        ci = 0
        for (kind, _, _), sides in zip(self.blocks, self.sides, strict=True):
            v = [vals[s[0]][s[1] : s[2]] if isinstance(s, tuple) else s for s in sides]
            if kind == "link":
                yield sides, self.link_w, (v[0] - v[1]) * self.link_w
            else:
                w = self.control_w[ci]
                yield sides, w, (v[0] - self.controls[ci].dst) * w
                ci += 1

    def _evaluate(self, x: NDArray) -> NDArray:
        """The weighted residuals at ``x``, flat."""
        vals = {k: self.model(x, k).apply_design(d) for k, d in self.stack.items()}
        res = [r.ravel() for _, _, r in self._block_residuals(vals)]
        return np.concatenate(res or [np.zeros(0)])

    def normal_equations(self, x: NDArray, f_scale: float):
        """``(JᵀWJ, JᵀWr, r)`` of the weighted residuals ``r`` with the soft-L1 IRLS weights
        ``W`` at ``x``. ``JᵀWJ`` is a sparse matrix of dense ``P x P`` blocks: a frame's own
        block sums all its points (one product over its stacked Jacobian), a pair of linked
        frames' block their links' points."""
        vals, jacs = {}, {}
        for k, design in self.stack.items():
            vals[k], *row = self.model(x, k).param_jacobian_by_row(design)
            jacs[k] = tuple(row)
        # Per stacked point: its weight in JᵀWJ (block weight² x robust weight) and its
        # weighted residual in JᵀWr (block weight x sign x robust weight x residual).
        row_w = {k: np.zeros(len(v)) for k, v in vals.items()}
        row_r = {k: np.zeros((len(v), 2)) for k, v in vals.items()}
        pairs = []
        res = []
        for sides, bw, r in self._block_residuals(vals):
            r = np.where(np.isfinite(r), r, 1e6)
            res.append(r.ravel())
            w = _robust_weights(r, f_scale)[::2]  # per point (its two coordinates alike)
            # A link's residual is frame k's minus frame l's; a control point has one side.
            for sign, side in zip((1.0, -1.0), sides, strict=False):
                if isinstance(side, tuple):
                    k, lo, hi = side
                    row_w[k][lo:hi] = bw * bw * w
                    row_r[k][lo:hi] = (sign * bw) * r * w[:, None]
            if len(sides) == 2 and all(isinstance(s, tuple) for s in sides):
                pairs.append((*sides[0], *sides[1], -bw * bw * w))
        grad = np.zeros(self.size)
        blocks: dict[tuple[int, int], NDArray] = {}
        for k, (ix, iy, vx, vy) in jacs.items():
            o = self.offset[k]
            grad[o + ix] += vx.T @ row_r[k][:, 0]
            grad[o + iy] += vy.T @ row_r[k][:, 1]
            blocks[(k, k)] = _row_product(jacs[k], row_w[k], jacs[k], slice(None), slice(None))
        for a, alo, ahi, b, blo, bhi, w in pairs:
            block = _row_product(jacs[a], w, jacs[b], slice(alo, ahi), slice(blo, bhi))
            for key, part in (((a, b), block), ((b, a), block.T)):
                blocks[key] = blocks[key] + part if key in blocks else part
        keys = tuple(blocks)
        if self._normal_index is None or self._normal_index[0] != keys:
            # Where each block's entries go: the same blocks every call (the links do not change).
            rows = [
                np.repeat(
                    np.arange(self.offset[a], self.offset[a] + self.n_params[a]), self.n_params[b]
                )
                for a, b in keys
            ]
            cols = [
                np.tile(
                    np.arange(self.offset[b], self.offset[b] + self.n_params[b]), self.n_params[a]
                )
                for a, b in keys
            ]
            self._normal_index = (keys, np.concatenate(rows), np.concatenate(cols))
        _, rows, cols = self._normal_index
        data = np.concatenate([block.ravel() for block in blocks.values()])
        normal = sp.csc_matrix((data, (rows, cols)), shape=(self.size, self.size))
        return normal, grad, np.concatenate(res)

    def residuals(self, x: NDArray) -> NDArray:
        r = self._evaluate(x)
        # A model that folds (denominator through 0) gives inf: a large finite residual instead,
        # so the trust region shrinks rather than the solver stopping.
        return np.where(np.isfinite(r), r, 1e6)

    def reestimate_noise(self, x: NDArray) -> bool:
        """Raise each frame's control-point noise, and the links' noise, to what their
        residuals show (robustly: the median point residual / 1.177, the median of a 2D
        normal's radius); whether any weight changed by more than 20 %. The links' noise is one
        figure for all: where the ground is not flat (relief seen from two places) links
        disagree with any two frames' models, and at the expected noise of same-sensor matching
        they would outweigh the control points that hold the frames' edges."""
        r = self._evaluate(x)
        changed, ci = False, 0
        link_errors = []
        for kind, start, m in self.blocks:
            if kind == "link":
                e = r[start : start + m].reshape(-1, 2) / self.link_w
                link_errors.append(np.hypot(e[:, 0], e[:, 1]))
            if kind != "control":
                continue
            e = r[start : start + m].reshape(-1, 2) / self.control_w[ci]
            seen = float(np.median(np.hypot(e[:, 0], e[:, 1]))) / 1.177
            if not self.controls[ci].fixed_noise and seen * self.control_w[ci] > 1.2:
                self.control_w[ci] = 1.0 / seen
                changed = True
            ci += 1
        if link_errors:
            seen = float(np.median(np.concatenate(link_errors))) / 1.177
            if seen * self.link_w > 1.2:
                self.link_w = 1.0 / seen
                changed = True
        return changed

    def per_frame_rms(self, x: NDArray, n: int) -> tuple[NDArray, NDArray]:
        r = self._evaluate(x)
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
            elif kind == "control":
                c = self.controls[ci]
                d2 = (e**2).sum(1) / self.control_w[ci] ** 2
                ci += 1
                sq["control"][c.k] += d2.sum()
                cnt["control"][c.k] += len(d2)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.sqrt(sq["link"] / cnt["link"]), np.sqrt(sq["control"] / cnt["control"])


def _row_product(a, w: NDArray, b, rows_a: slice, rows_b: slice) -> NDArray:
    """``Jaᵀ diag(w) Jb`` over the points ``rows_a`` of ``a`` and ``rows_b`` of ``b`` (row
    Jacobians ``(ix, iy, jx, jy)``, :meth:`PolyProjective.param_jacobian_by_row`; ``w`` per
    point, for both its rows): products over a row's 2J - 1 parameters take 2.3x fewer
    operations than over all P."""
    ixa, iya, jxa, jya = a
    ixb, iyb, jxb, jyb = b
    # 2J - 1 parameters per row of P = 3J - 1.
    out = np.zeros((3 * (len(ixa) + 1) // 2 - 1, 3 * (len(ixb) + 1) // 2 - 1))
    out[np.ix_(ixa, ixb)] = (jxa[rows_a] * w[:, None]).T @ jxb[rows_b]
    out[np.ix_(iya, iyb)] += (jya[rows_a] * w[:, None]).T @ jyb[rows_b]
    return out


# Up to this many unknowns the covariance is inverted densely (a window of 40 frames is 1160).
DENSE_COVARIANCE = 3000


def _block_inverse(normal) -> Callable[[int, int], NDArray] | None:
    """``cov(o, size)``: the diagonal block ``[o : o + size, o : o + size]`` of ``normal``'s
    inverse (symmetric positive definite), or None when it is singular. Up to
    :data:`DENSE_COVARIANCE` unknowns by LAPACK's Cholesky inverse (``potrf``/``potri``: a
    window's whole inverse costs about what one frame's block cost by sparse solves), beyond
    by SuperLU, block by block."""
    n = normal.shape[0]
    if n <= DENSE_COVARIANCE:
        factor, info = lapack.dpotrf(normal.toarray(), lower=0)
        if info != 0:
            return None
        inverse, info = lapack.dpotri(factor, lower=0)
        if info != 0:
            return None

        def dense(o: int, size: int) -> NDArray:
            block = inverse[o : o + size, o : o + size]  # upper triangle holds the inverse
            return np.triu(block) + np.triu(block, 1).T

        return dense
    try:
        lu = spla.splu(normal)
    except RuntimeError:
        return None

    def sparse(o: int, size: int) -> NDArray:
        unit = np.zeros((n, size))
        unit[o : o + size] = np.eye(size)
        return lu.solve(unit)[o : o + size]

    return sparse


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
        normal, grad, _ = problem.normal_equations(x, cfg.f_scale)
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
    fixed: Collection[int] = (),
    priors: Sequence[ControlPointSet] = (),
    report: Collection[int] | None = None,
) -> AdjustmentResult:
    """Estimate the frames' global models together (module docstring).

    Args:
        models: each frame's model from its own fine step (the start), None for a failed
            frame (left out, with the links that touch it).
        links: frame-to-frame correspondences (:class:`FrameLinks`), corrected px.
        controls: each frame's control points to the map (:class:`ControlPointSet`).
        fixed: frames whose models are held as they are (their links still count): frames
            already final in a sliding window, the reference frame.
        priors: weak control points that hold a frame where its evidence does not reach (as
            control points, but no part of its ``control_rms_px`` nor of where its
            ``position_sigma_px`` is taken).
        report: frames whose ``position_sigma_px`` is wanted (None: all; the others NaN): a
            sliding window needs it only for the frames it makes final.

    Returns:
        The adjusted models (recorded to the project's quantum, as every stage's models are) and
        per-frame residuals.
    """
    cfg = config or AdjustmentConfig()
    models = list(models)
    problem = _Problem(models, links, controls, cfg, fixed, priors)
    n = len(models)
    if problem.size == 0 or problem.n_rows == 0:
        nan = np.full(n, np.nan)
        return AdjustmentResult(tuple(models), nan, nan, nan, np.nan, True, "nothing to adjust", 0)
    x = np.concatenate([models[k].params for k in problem.offset])
    steps = 0
    for _ in range(cfg.noise_rounds + 1):
        x, converged, taken = _solve(problem, x, cfg)
        steps += taken
        if not problem.reestimate_noise(x):
            break
    out = [quantized(problem.model(x, k)) if k in problem.offset else models[k] for k in range(n)]
    link_rms, control_rms = problem.per_frame_rms(x, n)
    sigma, factor = _position_sigma(problem, x, cfg, n, report)
    message = f"converged in {steps} steps" if converged else f"stopped after {steps} steps"
    return AdjustmentResult(
        tuple(out), link_rms, control_rms, sigma, factor, converged, message, steps
    )


def _position_sigma(
    problem: _Problem, x: NDArray, cfg: AdjustmentConfig, n: int, report: Collection[int] | None
):
    """Per frame (of ``report``; None: all), the RMS positional standard deviation (base px) of
    its points under the solution's covariance, ``s0² (Jᵀ W J)⁻¹`` with the robust weights
    ``W`` at the solution; and ``s0²``, the weighted squared residuals per degree of freedom."""
    normal, _, r = problem.normal_equations(x, cfg.f_scale)
    w = _robust_weights(r, cfg.f_scale)
    dof = max(problem.n_rows - problem.size, 1)
    factor = float(np.sum(w * r**2) / dof)
    # A whisker of damping keeps a frame the evidence barely fixes from a singular factor.
    normal = normal + sp.diags(1e-12 * np.maximum(normal.diagonal(), 1e-12), format="csc")
    sigma = np.full(n, np.nan)
    covariance = _block_inverse(normal)
    if covariance is None:  # singular: nothing to say
        return sigma, factor
    points: dict[int, list] = {k: [] for k in problem.offset}
    for c in problem.controls[: problem.n_controls]:
        points[c.k].append(c.src)
    with_controls = {c.k for c in problem.controls[: problem.n_controls]}
    for lk in problem.links:  # a frame without control points: where its links are
        for k, src in ((lk.k, lk.src_k), (lk.l, lk.src_l)):
            if k in points and k not in with_controls:
                points[k].append(src)
    for k, o in problem.offset.items():
        if report is not None and k not in report:
            continue
        size = problem.n_params[k]
        cov = covariance(o, size) * factor
        if not points[k]:  # held by its prior alone
            continue
        _, j = problem.model(x, k).param_jacobian(np.concatenate(points[k]))
        var = np.einsum("nip,pq,niq->n", j, cov, j)
        sigma[k] = float(np.sqrt(np.mean(np.maximum(var, 0.0))))
    return sigma, factor

"""The optimisers every model's refinement runs: our own Levenberg-Marquardt (numpy and LAPACK
calls whose results do not depend on memory alignment, so every process gets the same bits) and
Nelder-Mead (the paper's choice).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.optimize

from registration.geometry.estimation import Array

OPTIMIZERS = ("lstsq", "lm", "nelder-mead")


def _check_optimizer(optimizer: str) -> None:
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {optimizer!r}")


def _refine(
    p0: Array,
    fun: Callable[[Array], Array],
    jac: Callable[[Array], Array] | None,
    optimizer: str,
) -> Array:
    """Minimise the sum of squared geometric residuals from ``p0`` with the chosen optimiser."""
    if optimizer == "lm":
        if jac is not None and len(fun(p0)) >= len(p0):
            return levenberg_marquardt(p0, fun, jac)
        res = scipy.optimize.least_squares(
            fun, p0, jac=jac if jac is not None else "2-point", method="trf",
            ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=200 * (len(p0) + 1),
        )  # fmt: skip
        return res.x
    if optimizer == "nelder-mead":
        return _nelder_mead(p0, fun)
    return p0


def levenberg_marquardt(
    p0: Array,
    fun: Callable[[Array], Array],
    jac: Callable[[Array], Array],
    *,
    tol: float = 1e-12,
    max_nfev: int | None = None,
) -> Array:
    """Levenberg-Marquardt minimisation of ``|fun(p)|^2`` from ``p0``, in numpy.

    Marquardt's damping scaled by the Jacobian's column norms (kept at their largest, as
    MINPACK does), solved through the normal equations of the column-scaled problem (17-29
    parameters of normalised coordinates: well enough conditioned). Stops when a step lowers the
    cost by less than ``tol`` relative, or is shorter than ``tol`` relative to the scaled
    parameters, or after ``max_nfev`` evaluations (``200 (n + 1)`` by default).

    Why not MINPACK (``scipy.optimize.least_squares(method="lm")``): its vectorised loops peel
    differently with the memory alignment of its work arrays, so the same residuals and
    Jacobians gave trial steps differing in their last bits from one process to the next, and
    the fit ended ~1e-9 apart; REQCON and the next frames amplified that to pixels. Here every
    operation is a BLAS/LAPACK call or an element-wise numpy operation whose result does not
    depend on where its arrays lie, so the same inputs give the same bits in every process.
    """
    p = np.array(p0, dtype=np.float64)
    n = len(p)
    max_nfev = 200 * (n + 1) if max_nfev is None else int(max_nfev)
    r = fun(p)
    cost = float(r @ r)
    if not math.isfinite(cost):
        return p
    st = _LMState(p, r, cost)
    J = jac(p)
    scale = np.sqrt((J * J).sum(axis=0))
    while st.nfev < max_nfev:
        scale = np.where(scale > 0, scale, 1.0)
        # The problem in scaled parameters u = scale * p: unit-diagonal normal equations.
        js = J / scale
        a = js.T @ js
        g = js.T @ st.r
        if not (np.isfinite(a).all() and np.isfinite(g).all()):
            return st.p  # no usable Jacobian here (the model undefined at a point)
        if st.lam is None:
            st.lam = max(1e-3 * float(np.max(np.diag(a))), 1e-12)
        if float(np.max(np.abs(g))) <= tol * math.sqrt(st.cost):
            return st.p  # gradient zero to working precision
        # The most the quadratic model can still gain (the undamped step's reduction): the
        # convergence test, which a heavily damped step's small reduction cannot fake.
        u_gn = np.linalg.lstsq(a, -g, rcond=None)[0]
        gain = float(-g @ u_gn)
        if gain <= tol * st.cost:
            return st.p
        if _step_until_accepted(st, fun, a, g, u_gn, scale, max_nfev, tol):
            return st.p
        J = jac(st.p)
        scale = np.maximum(scale, np.sqrt((J * J).sum(axis=0)))
    return st.p


@dataclass
class _LMState:
    """Where a :func:`levenberg_marquardt` run is: parameters ``p`` ``(n,)``, the residuals
    ``r`` ``(m,)`` and cost ``r @ r`` there, Marquardt's damping ``lam`` (None until the first
    Jacobian) and its growth factor ``nu``, and the evaluations of ``fun`` so far."""

    p: Array
    r: Array
    cost: float
    lam: float | None = None
    nu: float = 2.0
    nfev: int = 1


def _step_until_accepted(
    st: _LMState,
    fun: Callable[[Array], Array],
    a: Array,
    g: Array,
    u_gn: Array,
    scale: Array,
    max_nfev: int,
    tol: float,
) -> bool:
    """Trial steps from ``st.p`` with one Jacobian, until one lowers the cost.

    ``a`` ``(n, n)`` and ``g`` ``(n,)`` are the normal equations of the problem in the scaled
    parameters ``u = scale * p`` and ``u_gn`` their undamped solution. The undamped step goes
    first, then ever more damped ones; an accepted step moves ``st`` and eases the damping by
    Nielsen's rule. Stops early when ``max_nfev`` evaluations are spent.

    Returns:
        True when the minimisation is over: a step shorter than ``tol`` relative to the scaled
        parameters, or the damping beyond 1e16 (NaN too).
    """
    n = len(st.p)
    # The undamped step first: damping turns the step towards the gradient, which can point
    # into the denominator barrier (a fit ending on it) where the full step clears it.
    undamped = True
    while st.nfev < max_nfev:
        if undamped:
            u = u_gn
        else:
            try:
                u = np.linalg.solve(a + st.lam * np.eye(n), -g)
            except np.linalg.LinAlgError:
                u = np.full(n, np.nan)
        if not np.isfinite(u).all():
            st.lam, st.nu, undamped = st.lam * st.nu, st.nu * 2.0, False
            st.nfev += 1  # counted as a trial: this loop must end
            if not st.lam <= 1e16:  # NaN too
                return True
            continue
        if float(np.linalg.norm(u)) <= tol * (float(np.linalg.norm(scale * st.p)) + tol):
            return True
        trial = st.p + u / scale
        r_trial = fun(trial)
        st.nfev += 1
        c_trial = float(r_trial @ r_trial)
        predicted = -float(2.0 * (g @ u) + u @ a @ u)
        actual = st.cost - c_trial if math.isfinite(c_trial) else -math.inf
        if predicted > 0 and actual > 0:
            # Nielsen's update: less damping the better the quadratic model predicted.
            rho = actual / predicted
            st.lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            st.nu = 2.0
            st.p, st.r, st.cost = trial, r_trial, c_trial
            # Accepted steps the quadratic model keeps mispredicting (rho ~ 0, gains at
            # rounding level: a fit pressed against the denominator barrier) double the
            # damping each time: nothing more to gain.
            return not st.lam <= 1e16
        if undamped:
            undamped = False  # no say on the damping
            continue
        st.lam, st.nu = st.lam * st.nu, min(st.nu * 2.0, 1e6)
        if not st.lam <= 1e16:  # NaN too
            return True
    return False


def _nelder_mead(p0: Array, fun: Callable[[Array], Array]) -> Array:
    """Nelder-Mead (paper 4.3) on the sum of squared residuals, restarted until it stalls.

    ``adaptive=True`` (Gao & Han parameters) is needed beyond ~10 dimensions. The initial simplex
    steps each normalised coefficient by 1e-3 (about half a pixel at 1000 px extents). A fresh
    simplex around the result is started while that still lowers the cost by more than 1e-9
    relative: a single NM run often collapses its simplex before reaching the minimum.
    """

    def cost(p: Array) -> float:
        r = fun(p)
        v = float(r @ r)
        return v if math.isfinite(v) else math.inf

    n = len(p0)
    p = np.asarray(p0, dtype=np.float64).copy()
    f = cost(p)
    step = 1e-3
    for _ in range(8):
        simplex = np.vstack([p, p + step * np.eye(n)])
        res = scipy.optimize.minimize(
            cost,
            p,
            method="Nelder-Mead",
            options={
                "adaptive": True,
                "initial_simplex": simplex,
                "xatol": 1e-10,
                "fatol": 1e-12 * max(f, 1e-12),
                "maxfev": 2000 * n,
            },
        )
        improved = f - res.fun
        if res.fun < f:
            p, f = res.x, float(res.fun)
        if improved <= 1e-9 * max(f, 1e-300):
            break
        step = max(step * 0.1, 1e-7)
    return p

"""The lens refit's analytic Jacobian equals finite differences (it replaced them: the robust fit
takes hundreds of iterations and each cost 13 evaluations)."""

from __future__ import annotations

import numpy as np
import scipy.optimize as so
from scipy.optimize._numdiff import approx_derivative

import registration.lens.k2 as k2_module
from registration.lens import Camera


def test_analytic_jacobian_matches_finite_differences(monkeypatch):
    rng = np.random.default_rng(4)
    w, h = 1024, 768
    raw = rng.uniform([20, 20], [w - 20, h - 20], (300, 2))
    camera = Camera(0.3, w, h)
    truth = camera.with_k2(0.03)
    corrected = truth.corrected_from_raw(raw)
    hmat = np.array([[0.9, 0.2, 300.0], [-0.15, 1.1, 120.0], [2e-5, -1e-5, 1.0]])
    q = np.c_[corrected, np.ones(len(raw))] @ hmat.T
    base = q[:, :2] / q[:, 2:] + rng.normal(0, 0.3, (len(raw), 2))
    calls = []
    real = so.least_squares

    def spy(fun, x0, jac=None, **kw):
        calls.append((fun, x0, jac, kw.get("args", ())))
        return real(fun, x0, jac=jac, **kw)

    monkeypatch.setattr(k2_module, "least_squares", spy)
    est = k2_module.estimate_k2(raw, base, camera, k2_module.LensConfig(estimate_k2=True))
    assert abs(est.k2 - 0.03) < 0.005, est.summary
    assert len(calls) == 2 and all(callable(c[2]) for c in calls)
    for fun, x0, jac, args in calls:
        x = x0 + rng.normal(0, 0.01, len(x0))
        analytic = jac(x, *args)
        numeric = approx_derivative(fun, x, args=args, method="3-point")
        scale = np.abs(numeric).max()
        assert np.abs(analytic - numeric).max() < 1e-6 * scale

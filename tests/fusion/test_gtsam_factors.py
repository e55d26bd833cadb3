"""fusion/graph/factors.py against GTSAM's own robust model, the closed-form white-acceleration
noise and scipy's least squares."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from gt3dkit.fusion.graph.factors import cv_whitening, gauss_newton, huber_loss, huber_sqrt_weight


def test_huber_loss_and_weight_are_gtsams() -> None:
    import gtsam

    k = 1.345
    h = gtsam.noiseModel.mEstimator.Huber.Create(k)
    r = np.array([0.0, 0.3, 1.0, 1.345, 1.5, 4.0, 40.0])
    np.testing.assert_allclose(huber_loss(r, k), [h.loss(float(v)) for v in r], rtol=1e-12)
    np.testing.assert_allclose(huber_sqrt_weight(r, k) ** 2, [h.weight(float(v)) for v in r], rtol=1e-12)


@pytest.mark.parametrize("position_sd", [0.0, 0.2])
def test_cv_whitening_whitens_the_closed_form_noise(position_sd: float) -> None:
    """``W Q W^T = I`` with ``Q`` the exact discrete noise of white acceleration (density
    ``q^2``) plus a random walk of the position, written out here (isotropic: no up axis)."""
    q = 0.7
    dts = np.array([0.04, 0.1, 0.04, 1.0])
    W = cv_whitening(dts, q, None, 0.1, position_sd)
    for dt, w in zip(dts, W, strict=True):
        blk = q * q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        blk[0, 0] += position_sd**2 * dt
        Q = np.kron(blk, np.eye(3))
        np.testing.assert_allclose(w @ Q @ w.T, np.eye(6), atol=1e-9)


def test_gauss_newton_reaches_scipys_least_squares() -> None:
    """An exponential fit: the line-searched Gauss-Newton on arrays ends where scipy's
    trust-region least squares does."""
    rng = np.random.default_rng(0)
    t = np.linspace(0, 2, 30)
    y = 1.7 * np.exp(-0.8 * t) + rng.normal(scale=0.01, size=t.size)

    def resid(p: np.ndarray) -> np.ndarray:
        return p[0] * np.exp(-p[1] * t) - y

    def step(p: np.ndarray) -> np.ndarray:
        J = np.stack([np.exp(-p[1] * t), -p[0] * t * np.exp(-p[1] * t)], 1)
        return np.linalg.lstsq(J, -resid(p), rcond=None)[0]

    p, iters, err = gauss_newton(lambda p: 0.5 * float(resid(p) @ resid(p)), step,
                                 lambda p, d, s: p + s * d, np.array([1.0, 0.1]), 100, 1e-14)
    ref = least_squares(resid, [1.0, 0.1], xtol=1e-14, ftol=1e-14, gtol=1e-14)
    np.testing.assert_allclose(p, ref.x, rtol=1e-7)
    assert err == pytest.approx(0.5 * float(ref.fun @ ref.fun), rel=1e-9) and 1 < iters < 100

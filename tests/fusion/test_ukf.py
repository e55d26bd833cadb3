"""The UKF/RTS steps against filterpy and against exact linear-Gaussian results: the
covariance-form oracle (tests/oracles.py) against filterpy, the package's information-form update
against the oracle."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

from gt3dkit.fusion.motion import StateLayout
from gt3dkit.fusion.ukf.sigma import SigmaWeights
from gt3dkit.fusion.ukf.update import Measured
from tests.oracles import sigma_points, ukf_update, unscented_transform
from tests.oracles_frames import predict_linear, rts_step, ukf_update_information

finite = st.floats(-3, 3, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, (4,), elements=finite), arrays(np.float64, (4, 4), elements=finite),
       st.sampled_from([(1.0, 0.0, 0.0), (1.0, 2.0, 2.0), (0.5, 2.0, 0.0)]))
def test_unscented_transform_recovers_mean_and_covariance(x, A, abk) -> None:
    """Any SPD P: the UT of the identity (and of a linear map) is exact."""
    P = A @ A.T + 0.5 * np.eye(4)
    w = SigmaWeights(4, *abk)
    X, rep = sigma_points(x[None], P[None], w)
    assert rep == 0
    m, C = unscented_transform(X, w)
    np.testing.assert_allclose(m[0], x, atol=1e-9)
    np.testing.assert_allclose(C[0], P, atol=1e-9)
    M = np.arange(8.0).reshape(2, 4) / 7
    m2, C2 = unscented_transform(X @ M.T, w)
    np.testing.assert_allclose(m2[0], M @ x, atol=1e-9)
    np.testing.assert_allclose(C2[0], M @ P @ M.T, atol=1e-9)


def _linear_model(dt=0.5):
    lay = StateLayout(0)
    F, Q = lay.transition(np.array([dt]), 0.7, 0.01)
    H = np.zeros((4, 9))
    H[0, 0] = H[1, 1] = H[2, 2] = 1.0
    H[3, 8] = 2.0
    return F[0], Q[0], H


def test_ukf_matches_filterpy_ukf_and_kf_on_linear_model() -> None:
    F, Q, H = _linear_model()
    R = np.diag([0.01, 0.02, 0.03, 0.05])
    rng = np.random.default_rng(0)
    x0 = rng.normal(size=9)
    P0 = np.diag(rng.uniform(0.1, 1.0, 9))
    zs = rng.normal(size=(8, 4))

    pts = MerweScaledSigmaPoints(9, alpha=1.0, beta=0.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(9, 4, dt=0.5, hx=lambda x: H @ x, fx=lambda x, dt: F @ x,
                                points=pts)
    ukf.x, ukf.P, ukf.Q, ukf.R = x0.copy(), P0.copy(), Q, R
    kf = KalmanFilter(9, 4)
    kf.x, kf.P, kf.F, kf.Q, kf.H, kf.R = x0.copy(), P0.copy(), F, Q, H, R

    w = SigmaWeights(9)
    x, P = x0[None], P0[None]
    for z in zs:
        # filterpy's UKF update uses the sigma points of its predict(): predict every step
        x, P = predict_linear(x, P, F, Q)
        ukf.predict()
        kf.predict()
        np.testing.assert_allclose(P[0], ukf.P, atol=1e-9)
        x, P, _ = ukf_update(x, P, z[None], np.ones((1, 4), bool), np.diag(R),
                             lambda X: X @ H.T, w)
        ukf.update(z)
        kf.update(z)
        np.testing.assert_allclose(x[0], ukf.x, atol=1e-9)
        np.testing.assert_allclose(P[0], ukf.P, atol=1e-9)
        np.testing.assert_allclose(x[0], kf.x, atol=1e-9)


def test_iterated_update_is_exact_for_linear_measurements() -> None:
    F, Q, H = _linear_model()
    rng = np.random.default_rng(1)
    x0, P0 = rng.normal(size=(1, 9)), np.eye(9)[None] * 0.3
    z = rng.normal(size=(1, 4))
    args = (x0, P0, z, np.ones((1, 4), bool), 0.02, lambda X: X @ H.T, SigmaWeights(9))
    x1, P1, _ = ukf_update(*args, iterations=1)
    x3, P3, _ = ukf_update(*args, iterations=3)
    np.testing.assert_allclose(x3, x1, atol=1e-10)
    np.testing.assert_allclose(P3, P1, atol=1e-10)


def test_masked_update_equals_update_without_those_entries() -> None:
    _, _, H = _linear_model()
    rng = np.random.default_rng(2)
    x0 = rng.normal(size=(2, 9))
    P0 = np.stack([np.eye(9) * 0.5, np.eye(9) * 0.2])
    z = rng.normal(size=(2, 4))
    mask = np.array([[True, False, True, True], [False, False, True, False]])
    xm, Pm, _ = ukf_update(x0, P0, z, mask, 0.04, lambda X: X @ H.T, SigmaWeights(9))
    for b in range(2):
        keep = mask[b]
        xr, Pr, _ = ukf_update(x0[b:b + 1], P0[b:b + 1], z[b:b + 1, keep],
                               np.ones((1, keep.sum()), bool), 0.04,
                               lambda X, k=keep: (X @ H.T)[..., k], SigmaWeights(9))
        np.testing.assert_allclose(xm[b], xr[0], atol=1e-10)
        np.testing.assert_allclose(Pm[b], Pr[0], atol=1e-10)


def test_rts_matches_filterpy_rts_smoother() -> None:
    F, Q, H = _linear_model()
    R = np.eye(4) * 0.05
    rng = np.random.default_rng(3)
    zs = rng.normal(size=(10, 4))
    kf = KalmanFilter(9, 4)
    kf.x, kf.P, kf.F, kf.Q, kf.H, kf.R = np.zeros(9), np.eye(9), F, Q, H, R
    xs, Ps, _, _ = kf.batch_filter(zs)
    ms, Pss, _, _ = kf.rts_smoother(xs, Ps)
    # ours, forward with the same convention (filterpy's batch_filter predicts first)
    x, P = np.zeros((1, 9)), np.eye(9)[None]
    xf, Pf, xp, Pp = [], [], [], []
    for z in zs:
        x, P = predict_linear(x, P, F, Q)
        xp.append(x)
        Pp.append(P)
        x, P, _ = ukf_update(x, P, z[None], np.ones((1, 4), bool), 0.05, lambda X: X @ H.T,
                             SigmaWeights(9))
        xf.append(x)
        Pf.append(P)
    np.testing.assert_allclose(np.concatenate(xf), xs, atol=1e-9)
    x_s, P_s = xf[-1], Pf[-1]
    out = [x_s]
    for k in range(len(zs) - 2, -1, -1):
        x_s, P_s = rts_step(xf[k], Pf[k], xp[k + 1], Pp[k + 1], x_s, P_s, F)
        out.append(x_s)
    np.testing.assert_allclose(np.concatenate(out[::-1]), ms, atol=1e-9)


def test_information_form_equals_covariance_form_on_linear_model() -> None:
    _, _, H = _linear_model()
    rng = np.random.default_rng(4)
    A = rng.normal(size=(9, 9))
    P0 = (A @ A.T / 9 + 0.1 * np.eye(9))[None].repeat(2, 0)
    x0 = rng.normal(size=(2, 9))
    z = rng.normal(size=(2, 4))
    mask = np.array([[True, True, False, True], [True, True, True, True]])
    R = np.array([0.01, 0.02, 0.03, 0.04])
    xc, Pc, ic = ukf_update(x0, P0, z, mask, R, lambda X: X @ H.T, SigmaWeights(9))
    xi, Pi, ii = ukf_update_information(x0, P0, Measured(z, mask, R), lambda X: X @ H.T, SigmaWeights(9),
                                        iterations=2)
    np.testing.assert_allclose(xi, xc, atol=1e-9)
    np.testing.assert_allclose(Pi, Pc, atol=1e-9)
    assert ii["loglik"] == pytest.approx(ic["loglik"], rel=1e-9)
    assert ii["nis"] == pytest.approx(ic["nis"], rel=1e-9)

"""fusion/ukf/kalman.py: the prediction and RTS step against numpy's dense algebra (bit for bit where
the sparse products skip only zeros), the fading factor against ``e^T S^-1 e`` written out.
(The filter and smoother as a whole are held to filterpy in test_ukf.py and test_filterloop.py.)"""

from __future__ import annotations

import numpy as np

from gt3dkit.fusion.motion import StateLayout
from gt3dkit.geom.smallmat import matmul
from tests.oracles_frames import predict_linear, rts_step


def test_prediction_and_rts_skip_the_transitions_zeros_bit_for_bit() -> None:
    """The prediction and RTS step multiply by the sparse ``F`` skipping its zeros: the same bits
    as the dense products (compiled ``matmul``), on a 19-joint state with random covariances."""
    lay = StateLayout(n_joints=19)
    n = lay.n
    F, Q = lay.transition(np.array([0.1, 0.35]), accel_sd=1.3, shape_sd=0.05, joint_accel_sd=4.0)
    rng = np.random.default_rng(2)
    A = rng.normal(size=(2, n, n))
    P = A @ np.swapaxes(A, 1, 2) / n + 1e-3 * np.eye(n)
    x = rng.normal(size=(2, n))

    def dense(b: int) -> tuple[np.ndarray, np.ndarray]:
        FP, Pp = np.empty((n, n)), np.empty((n, n))
        matmul(F[b], P[b], FP)
        matmul(FP, np.ascontiguousarray(F[b].T), Pp)
        return F[b] @ x[b], 0.5 * ((Pp + Q[b]) + (Pp.T + Q[b].T))

    x_p, P_p = predict_linear(x, P, F, Q)
    for b in range(2):
        xd, Pd = dense(b)
        np.testing.assert_allclose(x_p[b], xd, rtol=1e-14, atol=1e-15)
        np.testing.assert_array_equal(P_p[b], Pd)
    # the RTS step against numpy's dense algebra
    x_s, P_s = x_p + 0.01 * rng.normal(size=(2, n)), 0.9 * P_p
    x_o, P_o = rts_step(x, P, x_p, P_p, x_s, P_s, F)
    for b in range(2):
        G = P[b] @ F[b].T @ np.linalg.inv(P_p[b])
        np.testing.assert_allclose(x_o[b], x[b] + G @ (x_s[b] - x_p[b]), rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(P_o[b], P[b] + G @ (P_s[b] - P_p[b]) @ G.T, rtol=1e-7, atol=1e-10)


def test_fading_is_continuous_in_the_prediction_s_distance() -> None:
    """The fading factor is 1 up to the chi-square limit and grows continuously beyond it (the
    excess per degree of freedom), approaching ``sqrt(d^2 / 3)`` far beyond; written out against
    ``e^T S^-1 e`` by numpy."""
    from gt3dkit.fusion.ukf.kalman import fade_factors_of

    rng = np.random.default_rng(4)
    A = rng.normal(size=(3, 3))
    S = A @ A.T + 0.5 * np.eye(3)
    u = rng.normal(size=3)
    u /= np.sqrt(u @ np.linalg.solve(S, u))  # d^2 = 1 along u
    limit = 16.27
    d2 = np.array([0.0, 4.0, limit - 1e-9, limit + 1e-9, limit + 3.0, 300.0, 3e4])
    e = np.sqrt(d2)[:, None] * u
    f = fade_factors_of(e, np.broadcast_to(S, (len(d2), 3, 3)).copy(), limit)
    want = np.sqrt(1.0 + np.maximum(d2 - limit, 0.0) / 3.0)
    np.testing.assert_allclose(f, want, rtol=1e-9)
    assert abs(f[3] - f[2]) < 1e-6  # no jump at the limit
    assert f[-1] / np.sqrt(d2[-1] / 3.0) > 0.999

"""The one filter loop (gt3dkit.fusion.ukf.filterloop) held to filterpy: a kind whose steps are a
plain linear Kalman filter (constant velocity in 1D, position measured, rows without a
measurement) gives filterpy's filtered and RTS-smoothed states; a faded row whose gap is spread
re-predicts the gap's rows with the scaled noise, as written out here."""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np
import pytest

from gt3dkit.fusion.ukf.filterloop import Chains, backward_chain, forward_chain, register


class Toy(NamedTuple):
    chains: Chains
    z: np.ndarray  # (R,) position measured (NaN: none)
    r: float  # measurement variance
    q: float  # white-acceleration spectral density
    x0: np.ndarray  # (2,)
    P0: np.ndarray  # (2, 2)
    fade_at: int  # the row whose prediction is faded (-1: none)
    f: float
    x: np.ndarray  # (R, 2) filtered, then smoothed
    P: np.ndarray
    xp: np.ndarray  # (R, 2) predicted
    Pp: np.ndarray
    faded_rows: np.ndarray


@numba.njit(cache=False)
def _fq(dt: float, q: float, f: float) -> tuple[np.ndarray, np.ndarray]:
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = f * f * q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    return F, Q


@numba.njit(cache=False)
def _start(ctx, e, row):  # noqa: ANN001, ANN202
    ctx.xp[row] = ctx.x0
    ctx.Pp[row] = ctx.P0


@numba.njit(cache=False)
def _predict(ctx, e, row, prev, f):  # noqa: ANN001, ANN202
    F, Q = _fq(ctx.chains.t_s[row] - ctx.chains.t_s[prev], ctx.q, f)
    ctx.xp[row] = F @ ctx.x[prev]
    ctx.Pp[row] = F @ ctx.P[prev] @ F.T + Q


@numba.njit(cache=False)
def _fades(ctx, e, row):  # noqa: ANN001, ANN202
    return row == ctx.fade_at


@numba.njit(cache=False)
def _fade(ctx, e, row):  # noqa: ANN001, ANN202
    return ctx.f if ctx.faded_rows[row] == 0 else 1.0


@numba.njit(cache=False)
def _faded(ctx, e, row, f):  # noqa: ANN001, ANN202
    ctx.faded_rows[row] = 1


@numba.njit(cache=False)
def _measured(ctx, e, row):  # noqa: ANN001, ANN202
    return not np.isnan(ctx.z[row])


@numba.njit(cache=False)
def _keep(ctx, e, row):  # noqa: ANN001, ANN202
    ctx.x[row] = ctx.xp[row]
    ctx.P[row] = ctx.Pp[row]


@numba.njit(cache=False)
def _update(ctx, e, row):  # noqa: ANN001, ANN202
    x, P = ctx.xp[row].copy(), ctx.Pp[row].copy()
    if not np.isnan(ctx.z[row]):
        S = P[0, 0] + ctx.r
        K = P[:, 0] / S
        x = x + K * (ctx.z[row] - x[0])
        P = P - np.outer(K, P[0, :])
    ctx.x[row] = x
    ctx.P[row] = P


@numba.njit(cache=False)
def _smooth(ctx, e, row, nxt):  # noqa: ANN001, ANN202
    F, _ = _fq(ctx.chains.t_s[nxt] - ctx.chains.t_s[row], ctx.q, 1.0)
    C = ctx.P[row] @ F.T @ np.linalg.inv(ctx.Pp[nxt])
    ctx.x[row] = ctx.x[row] + C @ (ctx.x[nxt] - ctx.xp[nxt])
    ctx.P[row] = ctx.P[row] + C @ (ctx.P[nxt] - ctx.Pp[nxt]) @ C.T


register(Toy, start=_start, predict=_predict, fades=_fades, fade=_fade, faded=_faded,
         measured=_measured, keep=_keep, update=_update, smooth=_smooth)


def _toy(z: np.ndarray, t: np.ndarray, fade_at: int = -1, f: float = 1.0) -> Toy:
    R = len(z)
    nxt = np.r_[np.arange(1, R), -1].astype(np.int64)
    prv = np.r_[-1, np.arange(R - 1)].astype(np.int64)
    return Toy(Chains(nxt, prv, np.ones(R, bool), t.astype(float)), z, 0.04, 0.5, np.zeros(2),
               np.diag([4.0, 1.0]), fade_at, f, np.zeros((R, 2)), np.zeros((R, 2, 2)), np.zeros((R, 2)),
               np.zeros((R, 2, 2)), np.zeros(R, np.int64))


def test_the_loop_is_a_kalman_filter_and_rts_smoother() -> None:
    from filterpy.kalman import KalmanFilter, rts_smoother

    rng = np.random.default_rng(3)
    R, dt = 40, 0.1
    t = np.arange(R) * dt
    z = np.sin(t) + rng.normal(scale=0.2, size=R)
    z[[5, 6, 7, 20]] = np.nan  # rows without a measurement: prediction only
    ctx = _toy(z, t)
    forward_chain(ctx, 0, 0)
    filtered = ctx.x.copy(), ctx.P.copy()
    backward_chain(ctx, 0, R - 1)

    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P = np.zeros(2), np.diag([4.0, 1.0])
    F, Q = np.array([[1.0, dt], [0.0, 1.0]]), 0.5 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    kf.F, kf.Q, kf.H, kf.R = F, Q, np.array([[1.0, 0.0]]), np.array([[0.04]])
    # filterpy predicts before its first update; the loop starts at the initial state: start it
    # one step back so that its first prediction is the same initial state
    kf.x, kf.P = np.linalg.solve(F, kf.x), np.linalg.inv(F) @ (kf.P - Q) @ np.linalg.inv(F).T
    xs, Ps, _, _ = kf.batch_filter([None if np.isnan(v) else np.array([v]) for v in z])
    np.testing.assert_allclose(filtered[0], xs, atol=1e-10)
    np.testing.assert_allclose(filtered[1], Ps, atol=1e-10)
    xs_s, Ps_s, _, _ = rts_smoother(xs, Ps, np.repeat(F[None], R, 0), np.repeat(Q[None], R, 0))
    np.testing.assert_allclose(ctx.x, xs_s, atol=1e-9)
    np.testing.assert_allclose(ctx.P, Ps_s, atol=1e-9)


@pytest.mark.parametrize("gap", [False, True])
def test_a_faded_row_spreads_its_gap(gap: bool) -> None:
    """The row after a gap (rows without a measurement) is faded: the gap's rows are predicted
    again with the noise scaled by the fading factor, their filtered values those predictions;
    without a gap nothing before the row changes."""
    R, dt, at, f = 12, 0.1, 8, 3.0
    t = np.arange(R) * dt
    z = np.linspace(0, 1, R)
    if gap:
        z[5:at] = np.nan
    ctx = _toy(z, t, fade_at=at, f=f)
    forward_chain(ctx, 0, 0)
    assert ctx.faded_rows[at] == 1 and ctx.faded_rows.sum() == 1
    plain = _toy(z, t)
    forward_chain(plain, 0, 0)
    last = 4 if gap else at - 1
    np.testing.assert_allclose(ctx.x[:last + 1], plain.x[:last + 1], atol=0)
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = f * f * 0.5 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    x, P = plain.x[last], plain.P[last]
    for row in range(last + 1, at + 1):  # the gap predicted again at the scaled noise
        x, P = F @ x, F @ P @ F.T + (Q if gap else Q / f / f)
        if row < at:
            np.testing.assert_allclose(ctx.x[row], x, rtol=1e-12)
            np.testing.assert_allclose(ctx.P[row], P, rtol=1e-12)
    np.testing.assert_allclose(ctx.xp[at], x, rtol=1e-12)
    np.testing.assert_allclose(ctx.Pp[at], P, rtol=1e-12)


def test_a_kind_registers_every_step() -> None:
    with pytest.raises(ValueError, match="steps must be exactly"):
        register(Toy, start=_start)


def test_the_steps_called_from_python_are_the_kinds() -> None:
    """Outside compiled code a step calls the kind's own (the same state written); a bundle of no
    registered kind is refused by name."""
    from gt3dkit.fusion.ukf import filterloop

    ctx = _toy(np.array([0.5, np.nan]), np.array([0.0, 0.1]))
    filterloop.start(ctx, 0, 0)
    filterloop.update(ctx, 0, 0)
    assert filterloop.measured(ctx, 0, 0) and not filterloop.measured(ctx, 0, 1)
    ref = _toy(np.array([0.5, np.nan]), np.array([0.0, 0.1]))
    _start(ref, 0, 0)
    _update(ref, 0, 0)
    np.testing.assert_array_equal(ctx.x, ref.x)
    with pytest.raises(TypeError, match="no kind registered for Chains"):
        filterloop.keep(ctx.chains, 0, 0)

"""gt3dkit.fusion.motion, the one motion model, against an independent discretisation: Van Loan's
matrix exponential of the continuous-time model (scipy.linalg.expm), and the moments the noise
estimate uses derived from that ``Q`` by hand."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from gt3dkit.fusion.motion import (
    MotionModel,
    StateLayout,
    joint_step,
    lag_two_excess_var,
    position_step,
    second_difference_var,
    walk_sd,
    walk_var,
)


def van_loan(Ac: np.ndarray, Qc: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``F, Q`` of ``dx = Ac x dt + dw``, ``E[dw dw^T] = Qc dt`` over ``dt`` (Van Loan 1978)."""
    n = len(Ac)
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -Ac
    M[:n, n:] = Qc
    M[n:, n:] = Ac.T
    E = expm(M * dt)
    F = E[n:, n:].T
    return F, F @ E[:n, n:]


def continuous(n_joints: int, accel: float, shape: float, joint: float, pos: float, A3: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    lay = StateLayout(n_joints)
    n = lay.n
    Ac, Qc = np.zeros((n, n)), np.zeros((n, n))
    c, v, la = lay.center, lay.velocity, lay.log_axes
    Ac[c, v] = np.eye(3)
    Qc[v, v] = accel**2 * A3
    Qc[c, c] = pos**2 * A3
    Qc[la, la] = shape**2 * np.eye(3)
    p, w = lay.joints, lay.joint_velocity
    Ac[p, w] = np.eye(3 * n_joints)
    Qc[w, w] = joint**2 * np.eye(3 * n_joints)
    return Ac, Qc


@pytest.mark.parametrize("dt", [0.04, 0.5, 2.0])
@pytest.mark.parametrize("joints", [0, 2])
def test_transition_is_the_exact_discretisation(dt: float, joints: int) -> None:
    up = np.array([0.0, 0.6, -0.8])
    model = MotionModel(1.3, 0.02, joint_accel_sd=4.0, position_sd=0.07, up=up, vertical_ratio=0.1)
    F, Q = model.transition(StateLayout(joints), np.array([dt]))
    Ac, Qc = continuous(joints, 1.3, 0.02, 4.0, 0.07, model.accel_shape)
    F0, Q0 = van_loan(Ac, Qc, dt)
    np.testing.assert_allclose(F[0], F0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(Q[0], Q0, rtol=1e-9, atol=1e-14)


def test_layout_transition_is_the_model_transition() -> None:
    lay = StateLayout(1)
    dts = np.array([0.1, 0.3])
    a = lay.transition(dts, 0.7, 0.01, joint_accel_sd=2.0, up=np.array([0, 0, 1.0]), vertical_ratio=0.2,
                       position_sd=0.05)
    b = MotionModel(0.7, 0.01, 2.0, 0.05, np.array([0, 0, 1.0]), 0.2).transition(lay, dts)
    for u, v in zip(a, b, strict=True):
        np.testing.assert_array_equal(u, v)


def test_joint_and_position_steps_are_blocks_of_the_whole() -> None:
    lay = StateLayout(1)
    _, Q = MotionModel(0.3, 0.01, joint_accel_sd=1.7).transition(lay, np.array([0.04]))
    F0, Q0 = van_loan(*continuous(1, 0.3, 0.01, 1.7, 0.0, np.eye(3)), 0.04)
    Fj, Qj = np.empty((6, 6)), np.empty((6, 6))
    joint_step(0.04, 1.7, Fj, Qj)
    e = np.r_[lay.joints.start:lay.n]
    np.testing.assert_array_equal(Qj, Q[0][np.ix_(e, e)])
    np.testing.assert_allclose(Fj, F0[np.ix_(e, e)], atol=1e-12)
    F2, Q2 = position_step(0.04, 1.7)
    i = [lay.joints.start, lay.joint_velocity.start]
    np.testing.assert_allclose(F2, F0[np.ix_(i, i)], atol=1e-12)
    np.testing.assert_allclose(Q2, Q0[np.ix_(i, i)], rtol=1e-9)


@pytest.mark.parametrize("dt", [0.1, 1.0, 3.0])
def test_moments_follow_from_q(dt: float) -> None:
    """The second difference ``x2 - 2 x1 + x0`` is ``[-1, dt] w1 + [1, 0] w2`` (two independent
    steps' noise): its variance from Van Loan's ``Q``; at lag 2 the same over ``2 dt``."""
    def second(step: float) -> float:
        F, Q = van_loan(np.array([[0.0, 1.0], [0.0, 0.0]]), np.diag([0.0, 1.0]), step)
        a = np.array([-1.0, step])
        return float(a @ Q @ a + Q[0, 0])

    np.testing.assert_allclose(second_difference_var(np.array([dt])), second(dt), rtol=1e-9)
    np.testing.assert_allclose(lag_two_excess_var() * dt**3, second(2 * dt) - second(dt), rtol=1e-9)
    F, Q = van_loan(np.zeros((1, 1)), np.ones((1, 1)), dt)
    np.testing.assert_allclose(walk_var(np.array([dt])), Q[0, 0], rtol=1e-12)
    np.testing.assert_allclose(walk_sd(0.3, dt) ** 2, 0.09 * Q[0, 0], rtol=1e-12)


def test_noise_defaults_joints_to_the_centre() -> None:
    assert MotionModel(0.8, 0.01).noise.joint_accel_sd == 0.8
    assert MotionModel(0.8, 0.01, joint_accel_sd=2.5).noise.joint_accel_sd == 2.5


@pytest.mark.parametrize("ratio", [1.0, 0.1])
def test_transition_noise_is_symmetric_psd_and_anisotropic(ratio: float) -> None:
    lay = StateLayout(2)
    up = np.array([0.0, -1.0, 0.0])
    F, Q = lay.transition(np.array([0.1, 0.5]), 1.0, 0.01, up=up, vertical_ratio=ratio)
    assert F.shape == Q.shape == (2, lay.n, lay.n)
    np.testing.assert_allclose(Q, np.swapaxes(Q, 1, 2))
    assert np.linalg.eigvalsh(Q).min() > -1e-15
    np.testing.assert_allclose(Q[1, 1, 1] / Q[1, 0, 0], ratio**2)

r"""State layout and the linear motion model: the only place that knows where an entry of the
state sits, and the one implementation of ``F`` and ``Q``.

State of one object (``n = 9 + 6 J``)::

    [ centre (3) | velocity (3) | log semi-axes (3) | joints (3J) | joint velocities (3J) ]

Centre and joints move with constant velocity under white acceleration noise, the
log semi-axes follow a random walk (the paper's model):

.. math::
    F = \begin{bmatrix} I & \Delta t I & \\ & I & \\ & & I \end{bmatrix},\quad
    Q_{pv} = q_a^2 \begin{bmatrix} \Delta t^3/3 & \Delta t^2/2 \\ \Delta t^2/2 & \Delta t
    \end{bmatrix} \otimes A,\quad Q_\sigma = q_\sigma^2 \Delta t\, I_3

with ``A = I + (r^2 - 1) u u^T`` shaping the centre's acceleration noise (``r`` the vertical
ratio, ``u`` the up direction; joints are isotropic). The centre's position may also take a
random walk of its own, ``Q_{cc} \mathrel{+}= q_p^2 \Delta t\, A``: where the labels place an
object frame by frame (an annotator's click on a ground grid at 2 fps), its position departs
from any smooth path by more than a walker's acceleration explains, and velocity should not
follow those departures.

This module is the one place the motion model is written. :class:`MotionModel` is its typed
value (the noise levels and the acceleration's shape); :func:`cv_block` the constant-velocity
noise of one coordinate, which the centre, every joint (:func:`joint_step`, one joint's block
alone), the windows' steady-state context (:func:`position_step`), the moment estimate of the
noise (:func:`second_difference_var`, :func:`walk_var`) and GTSAM's factors (:func:`walk_sd`,
:meth:`MotionModel.transition`) all read. :func:`transition` is compiled: the compiled filters
call it per step, :meth:`MotionModel.transition` per batch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, overload

import numba
import numpy as np

from gt3dkit.geom.kernel_cache import drop_stale
from gt3dkit.types import F64, I64

drop_stale()  # before any compiled function below is called (and its cache read)

#: Coordinates of a point in space (a centre, a velocity, a joint).
SPACE = 3


class StateIndex(NamedTuple):
    """Where the blocks of a state start (what a compiled kernel needs of a :class:`StateLayout`):
    ``n`` entries, ``n_joints`` joints."""

    n: int
    centre: int
    velocity: int
    log_axes: int
    joints: int
    joint_velocity: int
    n_joints: int


class Noise(NamedTuple):
    """Process noise of one step: the centre's white acceleration (m/s^2/sqrt(Hz)), the log
    semi-axes' random walk (1/sqrt(s)), the joints' white acceleration and the centre position's
    own random walk (m/sqrt(s); 0: none)."""

    accel_sd: float
    shape_sd: float
    joint_accel_sd: float
    position_sd: float


@dataclass(frozen=True)
class MotionModel:
    """The motion model's noise levels, one typed value (units as in :class:`Noise`):
    ``accel_sd`` the centre's white acceleration, ``shape_sd`` the log semi-axes' random walk,
    ``joint_accel_sd`` the joints' white acceleration (None: ``accel_sd``), ``position_sd`` the
    centre position's own random walk; the centre's acceleration noise along the unit vector
    ``up (3,)`` is ``vertical_ratio`` times ``accel_sd`` (None: isotropic)."""

    accel_sd: float
    shape_sd: float
    joint_accel_sd: float | None = None
    position_sd: float = 0.0
    up: F64 | None = None
    vertical_ratio: float = 1.0

    @property
    def noise(self) -> Noise:
        """The levels as the compiled kernels take them."""
        return Noise(float(self.accel_sd), float(self.shape_sd),
                     float(self.accel_sd if self.joint_accel_sd is None else self.joint_accel_sd),
                     float(self.position_sd))

    @property
    def accel_shape(self) -> F64:
        """``A (3, 3)``: the shape of the centre's acceleration noise (:func:`accel_shape`)."""
        return accel_shape(self.up, self.vertical_ratio)

    def transition(self, layout: StateLayout, dt_s: F64) -> tuple[F64, F64]:
        """``F, Q (B, n, n)`` of the state ``layout`` for time steps ``dt_s (B,)`` in seconds."""
        dt = np.ascontiguousarray(dt_s, dtype=np.float64).reshape(-1)
        B, n = len(dt), layout.n
        F, Q = np.empty((B, n, n)), np.empty((B, n, n))
        transitions(dt, self.noise, self.accel_shape, layout.index, F, Q)
        return F, Q


@dataclass(frozen=True)
class StateLayout:
    n_joints: int = 0

    @property
    def n(self) -> int:
        return 3 * SPACE + 2 * SPACE * self.n_joints

    @property
    def center(self) -> slice:
        return slice(0, SPACE)

    @property
    def velocity(self) -> slice:
        return slice(SPACE, 2 * SPACE)

    @property
    def log_axes(self) -> slice:
        return slice(2 * SPACE, 3 * SPACE)

    @property
    def joints(self) -> slice:
        return slice(3 * SPACE, 3 * SPACE + SPACE * self.n_joints)

    @property
    def joint_velocity(self) -> slice:
        return slice(3 * SPACE + SPACE * self.n_joints, self.n)

    @property
    def index(self) -> StateIndex:
        return StateIndex(self.n, self.center.start, self.velocity.start, self.log_axes.start,
                          self.joints.start, self.joint_velocity.start, self.n_joints)

    @property
    def ellipsoid_dims(self) -> I64:
        """(6,) the entries the ellipsoid's shape depends on: centre, then log semi-axes."""
        return np.r_[np.arange(self.center.start, self.center.stop),
                     np.arange(self.log_axes.start, self.log_axes.stop)].astype(np.int64)

    @property
    def timed_ellipsoid_dims(self) -> I64:
        """(9,) the entries the boxes of views taken off their row's time depend on: centre,
        velocity (the centre moved to the view's time), log semi-axes."""
        return np.arange(self.center.start, self.log_axes.stop, dtype=np.int64)

    def joint_dims(self, joints: I64) -> I64:
        """(..., 3) the entries of joints ``joints (...)``."""
        return self.joints.start + SPACE * np.asarray(joints)[..., None] + np.arange(SPACE)

    def transition(self, dt_s: F64, accel_sd: float, shape_sd: float,
                   joint_accel_sd: float | None = None, up: F64 | None = None,
                   vertical_ratio: float = 1.0, position_sd: float = 0.0) -> tuple[F64, F64]:
        """``F, Q`` of shape ``(B, n, n)`` for time steps ``dt_s (B,)`` in seconds.

        The centre's acceleration noise along ``up`` is ``vertical_ratio * accel_sd``
        (objects on the ground rarely accelerate vertically); joints are isotropic.
        """
        return MotionModel(accel_sd, shape_sd, joint_accel_sd, position_sd, up,
                           vertical_ratio).transition(self, dt_s)


def accel_shape(up: F64 | None, vertical_ratio: float) -> F64:
    """``A (3, 3) = I + (r^2 - 1) u u^T``: the shape of the centre's acceleration noise."""
    A = np.eye(SPACE)
    if up is not None and vertical_ratio != 1.0:
        u = np.asarray(up, dtype=np.float64)
        A = A + (vertical_ratio**2 - 1.0) * np.outer(u, u)
    return A


@numba.njit(cache=True, nogil=True)
def cv_block(q2: float, dt: float) -> tuple[float, float, float]:
    r"""The process noise of one coordinate's (position, velocity) under white acceleration of
    spectral density ``q2`` over a step ``dt`` (s): ``Q = q^2 [[dt^3/3, dt^2/2], [dt^2/2,
    dt]]``, as ``(Q_pp, Q_pv, Q_vv)`` (Bar-Shalom, Li & Kirubarajan, "Estimation with
    Applications to Tracking and Navigation", 2001, 6.2.2)."""
    return q2 * dt**3 / 3.0, q2 * dt**2 / 2.0, q2 * dt


@numba.njit(cache=True, nogil=True)
def transition(dt: float, noise: Noise, A: F64, ix: StateIndex, F: F64, Q: F64) -> None:
    """``F, Q (n, n)`` of one step ``dt`` (s) into ``F, Q`` (see the module doc)."""
    F[:, :] = 0.0
    Q[:, :] = 0.0
    for i in range(ix.n):
        F[i, i] = 1.0
    b00, b01, b11 = cv_block(noise.accel_sd * noise.accel_sd, dt)
    b00 += noise.position_sd * noise.position_sd * dt
    c, v, la = ix.centre, ix.velocity, ix.log_axes
    for i in range(SPACE):
        F[c + i, v + i] = dt
        for j in range(SPACE):
            Q[c + i, c + j] = b00 * A[i, j]
            Q[c + i, v + j] = b01 * A[i, j]
            Q[v + i, c + j] = b01 * A[i, j]
            Q[v + i, v + j] = b11 * A[i, j]
        Q[la + i, la + i] = noise.shape_sd * noise.shape_sd * dt
    j00, j01, j11 = cv_block(noise.joint_accel_sd * noise.joint_accel_sd, dt)
    p, w = ix.joints, ix.joint_velocity
    for k in range(SPACE * ix.n_joints):
        F[p + k, w + k] = dt
        Q[p + k, p + k] = j00
        Q[p + k, w + k] = j01
        Q[w + k, p + k] = j01
        Q[w + k, w + k] = j11


@numba.njit(cache=True, nogil=True)
def joint_step(dt: float, q: float, F: F64, Q: F64) -> None:
    """``F, Q (6, 6)`` of one joint alone (position, velocity) over a step ``dt`` (s) with white
    acceleration noise ``q`` (m/s^2/sqrt(Hz)): the joint block of :func:`transition`."""
    F[:, :] = 0.0
    Q[:, :] = 0.0
    b00, b01, b11 = cv_block(q * q, dt)
    for k in range(SPACE):
        F[k, k] = 1.0
        F[SPACE + k, SPACE + k] = 1.0
        F[k, SPACE + k] = dt
        Q[k, k] = b00
        Q[k, SPACE + k] = b01
        Q[SPACE + k, k] = b01
        Q[SPACE + k, SPACE + k] = b11


def position_step(dt_s: float, accel_sd: float) -> tuple[F64, F64]:
    """``F, Q (2, 2)`` of one coordinate's (position, velocity) over a step ``dt_s`` under white
    acceleration ``accel_sd`` (:func:`cv_block`): the model the windows' steady state is
    computed for."""
    b00, b01, b11 = cv_block(float(accel_sd) ** 2, float(dt_s))
    return np.array([[1.0, dt_s], [0.0, 1.0]]), np.array([[b00, b01], [b01, b11]])


def second_difference_var(dt_s: F64) -> F64:
    r"""Variance of a position's second difference ``x_{k+1} - 2 x_k + x_{k-1}`` over frames
    ``dt_s`` apart under unit white acceleration: ``\int`` of the triangular kernel squared,
    ``(2/3) dt^3`` (the moment estimate of ``q^2``)."""
    return 2.0 / 3.0 * np.asarray(dt_s) ** 3


def lag_two_excess_var() -> float:
    r"""``(V(2 dt) - V(dt)) / dt^3`` of :func:`second_difference_var`: the second difference at
    lag 2 spans twice the time, ``(2/3) (8 - 1)`` (a white per-frame noise adds the same to both
    and cancels)."""
    return 7 * 2.0 / 3.0


def walk_var(dt_s: F64) -> F64:
    """Variance of a random walk's step over ``dt_s`` per unit spectral density (the log
    semi-axes' and the centre position's walk): ``dt``."""
    return np.asarray(dt_s, dtype=np.float64)


@overload
def walk_sd(sd: float, dt_s: float) -> float: ...


@overload
def walk_sd(sd: float, dt_s: F64) -> F64: ...


def walk_sd(sd: float, dt_s: F64 | float) -> F64 | float:
    """The sd of a random walk's step over ``dt_s`` with noise ``sd`` per sqrt(s)."""
    return sd * np.sqrt(dt_s)


@numba.njit(cache=True, nogil=True)
def transitions(dt: F64, noise: Noise, A: F64, ix: StateIndex, F: F64, Q: F64) -> None:
    """:func:`transition` of each step ``dt (B,)`` into ``F, Q (B, n, n)``."""
    for b in range(dt.shape[0]):
        transition(dt[b], noise, A, ix, F[b], Q[b])

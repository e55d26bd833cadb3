r"""State layout and the linear motion model.

State of one object (``n = 9 + 6 J``)::

    [ centre (3) | velocity (3) | log semi-axes (3) | joints (3J) | joint velocities (3J) ]

Centre and joints move with constant velocity under white acceleration noise, the
log semi-axes follow a random walk (the paper's model):

.. math::
    F = \begin{bmatrix} I & \Delta t I & \\ & I & \\ & & I \end{bmatrix},\quad
    Q_{pv} = q_a^2 \begin{bmatrix} \Delta t^3/3 & \Delta t^2/2 \\ \Delta t^2/2 & \Delta t
    \end{bmatrix} \otimes I_3,\quad Q_\sigma = q_\sigma^2 \Delta t\, I_3
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gt3dkit.types import F64


@dataclass(frozen=True)
class StateLayout:
    n_joints: int = 0

    @property
    def n(self) -> int:
        return 9 + 6 * self.n_joints

    @property
    def center(self) -> slice:
        return slice(0, 3)

    @property
    def velocity(self) -> slice:
        return slice(3, 6)

    @property
    def log_axes(self) -> slice:
        return slice(6, 9)

    @property
    def joints(self) -> slice:
        return slice(9, 9 + 3 * self.n_joints)

    @property
    def joint_velocity(self) -> slice:
        return slice(9 + 3 * self.n_joints, 9 + 6 * self.n_joints)

    def transition(self, dt_s: F64, accel_sd: float, shape_sd: float,
                   joint_accel_sd: float | None = None, up: F64 | None = None,
                   vertical_ratio: float = 1.0) -> tuple[F64, F64]:
        """``F, Q`` of shape ``(B, n, n)`` for time steps ``dt_s (B,)`` in seconds.

        The centre's acceleration noise along ``up`` is ``vertical_ratio * accel_sd``
        (objects on the ground rarely accelerate vertically); joints are isotropic.
        """
        dt = np.asarray(dt_s, dtype=np.float64).reshape(-1)
        B, n, J3 = len(dt), self.n, 3 * self.n_joints
        F = np.broadcast_to(np.eye(n), (B, n, n)).copy()
        Q = np.zeros((B, n, n))
        qa2 = accel_sd**2
        qj2 = (accel_sd if joint_accel_sd is None else joint_accel_sd) ** 2
        blocks = [(self.center, self.velocity, 3, qa2)]
        if J3:
            blocks.append((self.joints, self.joint_velocity, J3, qj2))
        for pos, vel, k, q in blocks:
            i = np.arange(k)
            p_idx, v_idx = pos.start + i, vel.start + i
            F[:, p_idx, v_idx] = dt[:, None]
            Q[:, p_idx, p_idx] = (q * dt**3 / 3)[:, None]
            Q[:, p_idx, v_idx] = Q[:, v_idx, p_idx] = (q * dt**2 / 2)[:, None]
            Q[:, v_idx, v_idx] = (q * dt)[:, None]
        if up is not None and vertical_ratio != 1.0:
            u = np.asarray(up, dtype=np.float64)
            A = np.eye(3) + (vertical_ratio**2 - 1.0) * np.outer(u, u)
            base = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]) * qa2  # (2, 2, B)
            blk = np.einsum("ijb,kl->bikjl", base, A).reshape(-1, 6, 6)
            order = np.r_[np.arange(self.center.start, self.center.stop),
                          np.arange(self.velocity.start, self.velocity.stop)]
            Q[np.ix_(np.arange(B), order, order)] = blk
        s = np.arange(self.log_axes.start, self.log_axes.stop)
        Q[:, s, s] = (shape_sd**2 * dt)[:, None]
        return F, Q

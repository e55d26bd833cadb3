r"""The unscented measurement update of a batch of rows: sigma-point weights, the statistical
linear regression of each measurement block, and the driver of the iterated, robust,
information-form update (:mod:`gt3dkit.fusion.ukf.update` holds the update itself, one row at a
time, compiled).

Arrays carry a leading batch axis ``B`` (one row per object): means ``(B, n)``, covariances
``(B, n, n)``, measurements ``(B, m)`` with a mask of the present entries (a missing entry has
no weight: the same as leaving it out, so objects with different visible box edges or joints
share one batch).

References
----------
* Wan & van der Merwe, "The unscented Kalman filter for nonlinear estimation", 2000
  (scaled sigma points, weights).
* García-Fernández, Svensson, Morelande & Särkkä, "Posterior linearization filter: principles
  and implementation using sigma points", IEEE TSP 63, 2015 (the iterated regression).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from gt3dkit.fusion.preparation.robust import RobustConfig
from gt3dkit.fusion.ukf.update import Columns
from gt3dkit.types import F64

MeasureFn = Callable[[F64], F64]


@dataclass(frozen=True)
class SigmaWeights:
    """Scaled unscented weights for an ``n``-dimensional state (2n+1 points).

    Defaults ``alpha=1, beta=0, kappa=0`` give the cubature rule: ``W_0 = 0`` and
    all other weights ``1/(2n)`` (all non-negative, so predicted covariances are
    positive semi-definite by construction).
    """

    n: int
    alpha: float = 1.0
    beta: float = 0.0
    kappa: float = 0.0

    @property
    def lam(self) -> float:
        return self.alpha**2 * (self.n + self.kappa) - self.n

    @property
    def Wm(self) -> F64:
        w = np.full(2 * self.n + 1, 1.0 / (2 * (self.n + self.lam)))
        w[0] = self.lam / (self.n + self.lam)
        return w

    @property
    def Wc(self) -> F64:
        w = self.Wm.copy()
        w[0] += 1.0 - self.alpha**2 + self.beta
        return w


def safe_cholesky(P: F64) -> tuple[F64, int]:
    """Lower Cholesky factors of ``(B, n, n)``; eigenvalue-clipped where not PD.

    Returns the factors and how many matrices needed repair.
    """
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    try:
        return np.asarray(np.linalg.cholesky(P), dtype=np.float64), 0
    except np.linalg.LinAlgError:
        pass
    w, V = np.linalg.eigh(P)
    bad = w.min(axis=-1) <= 1e-15 * np.maximum(w.max(axis=-1), 1e-300)
    floor = 1e-12 * np.maximum(w.max(axis=-1, keepdims=True), 1e-300)
    w = np.maximum(w, floor)
    P2 = (V * w[:, None, :]) @ np.swapaxes(V, -1, -2)
    return np.linalg.cholesky(0.5 * (P2 + np.swapaxes(P2, -1, -2))), int(bad.sum())


@dataclass(frozen=True)
class Block:
    """Measurements that each depend on a few state entries only.

    ``G`` groups of ``k`` measurement columns ``cols (G, k)``; group ``g`` is a function of the
    ``d`` state entries ``dims[g]`` (``dims (G, d)``) through ``h: (B, G, S, d) -> (B, G, S, k)``.
    A joint's projections into every camera depend on that joint's three coordinates only, a
    box on the centre and the semi-axes, a bone on its two joints: the statistical linear
    regression of such a group needs the sigma points of its ``d``-dimensional marginal only
    (``2d`` points, not ``2n``), and its information is a ``d x d`` block.
    ``masked``: ``h`` also takes the usable columns ``(B, G, k)``
    and may leave the others out (NaN). ``regress``: the block's own regression (the box block's
    is compiled, :func:`gt3dkit.fusion.ukf.boxupdate.box_regressions`), called as
    ``regress(rows, xj, Pj, meas, w, lin, repaired)`` ; None: the
    sigma points of ``h`` (the reference ``block_regression`` of ``tests/oracles_frames.py``).
    """

    dims: np.ndarray
    cols: np.ndarray
    h: MeasureFn | None
    masked: bool = False
    regress: Callable[..., None] | None = None


@dataclass(frozen=True)
class Robust:
    """Which measurement points an update may down-weight: ``blocks`` of ``(slice of the
    measurement vector, entries per point)``, judged by ``config``."""

    config: RobustConfig
    blocks: tuple[tuple[slice, int], ...]


def block_columns(blocks: Sequence[Block], m: int, robust: Robust | None) -> Columns:
    """The :class:`gt3dkit.fusion.ukf.update.Columns` of ``m`` measurement columns made of ``blocks``:
    the state entries of each column's group and, with ``robust``, the points of its blocks with
    their thresholds (infinite when its config is disabled)."""
    d = max(b.dims.shape[1] for b in blocks)
    dims = np.concatenate([np.pad(b.dims, ((0, 0), (0, d - b.dims.shape[1])), constant_values=-1)
                           for b in blocks]).astype(np.int64)  # (G, d): each group's entries
    order = np.concatenate([b.cols.reshape(-1) for b in blocks]).astype(np.int64)
    sizes = np.concatenate([np.full(b.cols.shape[0], b.cols.shape[1]) for b in blocks])
    start = np.r_[0, np.cumsum(sizes)].astype(np.int64)
    width = np.concatenate([np.full(b.cols.shape[0], b.dims.shape[1]) for b in blocks]).astype(np.int64)
    first = np.arange(m, dtype=np.int64)
    size = np.zeros(m, np.int64)
    c_thr, g_thr = np.full(m, np.inf), np.full(m, np.inf)
    for sl, e in robust.blocks if robust is not None else ():
        k = np.arange(*sl.indices(m))
        first[k] = k[0] + (k - k[0]) // e * e
        size[k] = e
        if robust is not None and robust.config.enabled:
            c_thr[k], g_thr[k] = robust.config.thresholds(e)
    return Columns(dims, first, size, c_thr, g_thr, order, start, width)

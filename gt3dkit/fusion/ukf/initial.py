"""Initial covariances made where they are read: a filter reads a row's initial covariance only
where its object starts, and all of them held at once would be one more ``(R, n, n)`` array
(121 kB a row with 19 joints)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from gt3dkit.types import F64, RowIndex


class InitialCov:
    """The per-frame fits' covariances ``(R, n, n)`` as initial covariances, made when indexed
    (a row's is read only where its object starts; all of them held at once would be 121 kB a
    row with 19 joints): ``diag(var (R, n))`` with the fit's ``cov6 (R, 6, 6)`` on the entries
    ``dims (6,)`` where ``ok (R,)``. Indexed by rows (``P0[rows]``: ``(k, n, n)``) or, as an
    array, by broadcast integer arrays ``P0[rows, i, j]`` (at least one dimension). ``pos (R, n)``
    maps a row's state entry to its place in ``dims`` (-1: none)."""

    #: Entries made at once when indexed as an array (bounds the index arrays' memory).
    CHUNK_ENTRIES = 1 << 20

    def __init__(self, var: F64, cov6: F64, ok: np.ndarray, dims: np.ndarray) -> None:
        self.var, self.cov6, self.ok = var, cov6, ok
        pos = np.full(var.shape[1], -1, np.int64)  # state entry -> its place in dims
        pos[dims] = np.arange(len(dims))
        self.pos = np.broadcast_to(pos, var.shape)  # per row (a view: the same for all)

    @property
    def shape(self) -> tuple[int, int, int]:
        R, n = self.var.shape
        return R, n, n

    def rows(self, idx: RowIndex) -> InitialCov:
        """The rows ``idx`` as another lazy set."""
        return self._of(self.var[idx], self.cov6[idx], self.ok[idx], self.pos[idx])

    def entries(self, src: np.ndarray, dims: np.ndarray) -> InitialCov:
        """``P0[src[:, None, None], dims[:, :, None], dims[:, None, :]]`` as another lazy set:
        row ``k`` the entries ``dims[k] (m,)`` (distinct) of row ``src[k]`` (the joint split's
        parts)."""
        return self._of(self.var[src[:, None], dims], self.cov6[src], self.ok[src],
                        self.pos[src[:, None], dims])

    @staticmethod
    def _of(var: F64, cov6: F64, ok: np.ndarray, pos: np.ndarray) -> InitialCov:
        out = InitialCov.__new__(InitialCov)
        out.var, out.cov6, out.ok, out.pos = var, cov6, ok, pos
        return out

    def __getitem__(self, idx: RowIndex | tuple[np.ndarray, np.ndarray, np.ndarray]) -> F64:
        if not isinstance(idx, tuple):
            n = self.var.shape[1]
            r = np.arange(len(self.var))[idx]
            i, j = np.arange(n)[:, None], np.arange(n)[None, :]
            return self[r.reshape(r.shape + (1, 1)), i, j]
        parts = tuple(np.asarray(a) for a in idx)
        shape = np.broadcast_shapes(*(a.shape for a in parts))
        out = np.empty(shape)
        step = max(1, self.CHUNK_ENTRIES // max(int(np.prod(shape[1:])), 1))
        for a in range(0, shape[0], step):  # bounded index temporaries
            part = tuple(x[a:a + step] if x.ndim == len(shape) and x.shape[0] > 1 else x for x in parts)
            r, i, j = np.broadcast_arrays(*part)
            o = np.where(i == j, self.var[r, i], 0.0)
            pi, pj = self.pos[r, i], self.pos[r, j]
            blk = (pi >= 0) & (pj >= 0) & self.ok[r]
            o[blk] = self.cov6[r[blk], pi[blk], pj[blk]]
            out[a:a + step] = o
        return out

    def __array__(self, dtype: npt.DTypeLike | None = None, copy: bool | None = None) -> F64:
        out = self[np.arange(len(self.var))]
        return out if dtype is None else out.astype(dtype)



def rows_of(P0: F64 | InitialCov, idx: np.ndarray) -> F64 | InitialCov:
    """The rows ``idx`` of initial covariances, lazy where they are."""
    return P0.rows(idx) if isinstance(P0, InitialCov) else P0[idx]


@dataclass(frozen=True)
class Init:
    """Initial state ``x0 (R, n)`` and covariance ``P0 (R, n, n)`` of every row (used where
    an object starts): the row's own per-frame fit with its covariance. ``P0`` an array or
    one made when indexed (:class:`InitialCov`)."""

    x0: F64
    P0: F64 | InitialCov

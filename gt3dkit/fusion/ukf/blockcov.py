"""Block-diagonal covariances of many rows held as their blocks.

A run of the per-joint filters (:mod:`gt3dkit.fusion.ukf.jointupdate`) estimates a person's state as
independent parts: the ellipsoid (9 entries) and each joint's position and velocity (6). Their
covariance is block-diagonal; written out as the whole ``(R, n, n)`` it is 121 kB a row with 19
joints, of which 6 kB are not zero. :class:`BlockCov` keeps the blocks and answers what the
estimator asks of the whole: entries by (rows, entries, entries) indices, rows, scaling, and
the dense array where one is wanted (``np.asarray``).
"""

from __future__ import annotations

from typing import overload

import numpy as np
import numpy.typing as npt

from gt3dkit.types import F64, I64, RowIndex


class BlockCov:
    """Covariances ``(R, n, n)`` that are zero but for ``groups``: each ``(dims (k, d), values
    (R, k, d, d))``, ``k`` blocks of ``d`` state entries ``dims[i]`` (every entry in one block
    at most)."""

    def __init__(self, n: int, groups: list[tuple[I64, F64]]) -> None:
        self.n = n
        self.groups = groups
        self.group = np.full(n, -1, np.int64)  # each entry's group, block and place in it
        self.block = np.zeros(n, np.int64)
        self.place = np.zeros(n, np.int64)
        for g, (dims, _) in enumerate(groups):
            self.group[dims] = g
            self.block[dims] = np.arange(dims.shape[0])[:, None]
            self.place[dims] = np.arange(dims.shape[1])[None, :]

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.groups[0][1].shape[0], self.n, self.n)

    @property
    def ndim(self) -> int:
        return 3

    def __len__(self) -> int:
        return self.shape[0]

    def rows_that_ran(self, ran: np.ndarray, into: F64 | BlockCov | None = None) -> F64 | BlockCov:
        """A run's covariances from these, of which only the rows ``ran (R,)`` were run: written
        into ``into`` (the other rows left as they are; ``into`` is returned), or these with the
        other rows zero."""
        if into is not None:
            into[ran] = self[ran]
            return into
        for _, v in self.groups:
            v[~ran] = 0.0
        return self

    def __array__(self, dtype: npt.DTypeLike | None = None, copy: bool | None = None) -> F64:
        out = np.zeros(self.shape)
        for dims, v in self.groups:
            out[:, dims[:, :, None], dims[:, None, :]] = v
        return out if dtype is None else out.astype(dtype)

    @overload
    def __getitem__(self, key: RowIndex) -> BlockCov: ...

    @overload
    def __getitem__(self, key: tuple[RowIndex, np.ndarray | slice, np.ndarray | slice]) -> F64: ...

    def __getitem__(self, key: RowIndex | tuple[RowIndex, np.ndarray | slice, np.ndarray | slice]
                    ) -> BlockCov | F64:
        """``P[rows]`` (a :class:`BlockCov` of those rows) or ``P[rows, I, J]`` (the entries,
        as numpy indexes the dense array: two slices make a block, two integer arrays
        broadcast)."""
        if not isinstance(key, tuple):
            return BlockCov(self.n, [(d, v[key]) for d, v in self.groups])
        rows, i, j = key
        if isinstance(i, slice) and isinstance(j, slice):
            i, j = np.arange(self.n)[i][:, None], np.arange(self.n)[j][None, :]
        i, j = np.broadcast_arrays(np.asarray(i), np.asarray(j))
        gi, gj = self.group[i], self.group[j]
        same = (gi == gj) & (gi >= 0) & (self.block[i] == self.block[j])
        out = None
        for g, (_, v) in enumerate(self.groups):
            on = same & (gi == g)
            if not on.any():
                continue
            b, pi, pj = (np.where(on, a, 0) for a in (self.block[i], self.place[i], self.place[j]))
            val = np.where(on, v[rows][:, b, pi, pj], 0.0)
            out = val if out is None else out + val
        if out is None:
            nr = len(np.arange(len(self))[rows])
            out = np.zeros((nr,) + i.shape)
        return out

    def __setitem__(self, rows: RowIndex, other: BlockCov) -> None:
        """``P[rows] = Q[rows]`` of two runs' covariances alike."""
        for (_, v), (_, w) in zip(self.groups, other.groups, strict=True):
            v[rows] = w

    def __imul__(self, s: float) -> BlockCov:
        for _, v in self.groups:
            v *= s
        return self

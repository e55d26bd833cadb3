"""Small array helpers shared by the loaders, checks and estimators."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt


def frame_grid(frames: np.ndarray, step: int | None = None) -> tuple[np.ndarray, int]:
    """All frame numbers from the first to the last of ``frames`` at ``step`` (None: the
    input's own frame step, the greatest common divisor of the gaps between its frames):
    ``(N,)`` int64 frame numbers and the step."""
    u = np.unique(np.asarray(frames, dtype=np.int64))
    if step is None:
        step = int(np.gcd.reduce(np.diff(u))) if len(u) > 1 else 1
    step = max(int(step), 1)
    return np.arange(u[0], u[-1] + 1, step, dtype=np.int64), step


def unique_rows(a: np.ndarray, return_index: bool = False, return_inverse: bool = False,
                return_counts: bool = False) -> Any:
    """``np.unique(a, axis=0, ...)`` of an integer array ``a (N, K)``: the same results (rows
    sorted lexicographically, first column first; the inverse as a flat ``(N,)`` array).

    numpy sorts rows as a structured type, ~50x slower than sorting integers (0.3 s of every
    400-frame x 40-person load went there); here the rows are packed into one int64 key in
    mixed radix (column ranges), which sorts in the same order. Falls back to numpy when the
    ranges do not fit in 62 bits or the array is not integer."""
    a = np.asarray(a)
    packed = _pack(a) if a.ndim == 2 and len(a) and a.shape[1] else None
    if packed is None:
        return _numpy_rows(a, return_index, return_inverse, return_counts)
    (key,) = packed
    # which arrays np.unique returns depends on the flags' runtime values: its overloads need literals
    unique: Any = np.unique
    res = unique(key, return_index=True, return_inverse=return_inverse, return_counts=return_counts)
    first = res[1]
    out: list[Any] = [a[first]]
    if return_index:
        out.append(first)
    if return_inverse:
        out.append(np.asarray(res[2]).reshape(-1))
    if return_counts:
        out.append(res[-1])
    return out[0] if len(out) == 1 else tuple(out)


def _numpy_rows(a: np.ndarray, return_index: bool, return_inverse: bool, return_counts: bool) -> Any:
    unique: Any = np.unique
    out = unique(a, axis=0, return_index=return_index, return_inverse=return_inverse,
                    return_counts=return_counts)
    if return_inverse and isinstance(out, tuple):
        k = 1 + int(return_index)
        out = out[:k] + (np.asarray(out[k]).reshape(-1),) + out[k + 1:]
    return out


def lookup_rows(keys: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """``(M,)`` the index in ``keys (N, K)`` (integer rows, unique) of each row of ``queries
    (M, K)``, -1 where it has none: a dict lookup per query as one sort and a binary search."""
    keys, queries = np.asarray(keys), np.asarray(queries)
    out = np.full(len(queries), -1, dtype=np.int64)
    if not len(keys) or not len(queries):
        return out
    packed = _pack(keys, queries)
    if packed is None:
        index = {tuple(k): i for i, k in enumerate(keys.tolist())}
        return np.array([index.get(tuple(q), -1) for q in queries.tolist()], dtype=np.int64)
    kp, qp = packed
    order = np.argsort(kp, kind="stable")
    pos = np.minimum(np.searchsorted(kp[order], qp), len(kp) - 1)
    hit = kp[order][pos] == qp
    out[hit] = order[pos[hit]]
    return out


def _pack(*arrays: np.ndarray) -> tuple[np.ndarray, ...] | None:
    """Integer rows ``(N_i, K)`` of each array as one int64 key each, in mixed radix over their
    common column ranges (first column most significant: keys sort as the rows do); None when
    they are not integers or the ranges do not fit in 62 bits."""
    if not all(np.issubdtype(a.dtype, np.integer) for a in arrays):
        return None
    both = np.concatenate(arrays)
    lo = both.min(axis=0).astype(np.int64)
    span = both.max(axis=0).astype(np.int64) - lo + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0**62:
        return None
    out = []
    for a in arrays:
        key = np.zeros(len(a), np.int64)
        for k in range(a.shape[1]):
            key = key * span[k] + (a[:, k].astype(np.int64) - lo[k])
        out.append(key)
    return tuple(out)


def compiled_arg(a: npt.ArrayLike, dtype: npt.DTypeLike = np.float64) -> np.ndarray:
    """``a`` for a compiled call (one signature: C order, writable): as it is in the common case,
    without :func:`contiguous`'s ~4 us (GTSAM's factors call this 40 000 times)."""
    if type(a) is np.ndarray and a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable:
        return a
    return np.require(a, dtype=dtype, requirements=["C", "W"])


def contiguous(a: npt.ArrayLike, dtype: npt.DTypeLike = np.float64) -> np.ndarray:
    """``a`` as a C-contiguous, writable array of ``dtype``: numba compiles a function once per
    argument type, and a read-only array (a broadcast view) is another type."""
    return np.require(a, dtype=dtype, requirements=["C", "W"])

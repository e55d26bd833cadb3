"""fusion/ukf/blockcov.py against the dense arrays it stands for (brute force): every way the
estimator reads or writes it gives what numpy gives on the whole ``(R, n, n)``."""

from __future__ import annotations

import numpy as np
import pytest

from gt3dkit.fusion.ukf.blockcov import BlockCov


def _random(rng: np.random.Generator, R: int = 5) -> tuple[BlockCov, np.ndarray]:
    """An ellipsoid block of 9 entries and three joints of 6 (entries 9..26), as the joint run
    makes them, and the dense array."""
    n = 9 + 3 * 6
    ell = np.arange(9)[None]
    joints = (9 + np.arange(18)).reshape(3, 6)
    groups = [(ell, rng.normal(size=(R, 1, 9, 9))), (joints, rng.normal(size=(R, 3, 6, 6)))]
    dense = np.zeros((R, n, n))
    for dims, v in groups:
        for k in range(dims.shape[0]):
            dense[:, dims[k][:, None], dims[k][None, :]] = v[:, k]
    return BlockCov(n, groups), dense


def test_dense_entries_and_rows_are_numpys() -> None:
    rng = np.random.default_rng(0)
    P, D = _random(rng)
    assert P.shape == D.shape and len(P) == 5 and P.ndim == 3
    np.testing.assert_array_equal(np.asarray(P), D)
    rows = np.array([4, 0, 2])
    np.testing.assert_array_equal(np.asarray(P[rows]), D[rows])
    np.testing.assert_array_equal(np.asarray(P[1:3]), D[1:3])
    # blocks by slices, entries by broadcast integer arrays, across groups (zeros between them)
    np.testing.assert_array_equal(P[rows, slice(5, 20), slice(0, 12)], D[rows][:, 5:20, 0:12])
    i = rng.integers(0, 27, (4, 1))
    j = rng.integers(0, 27, (1, 6))
    np.testing.assert_array_equal(P[rows, i, j], D[rows][:, i, j])
    np.testing.assert_array_equal(P[rows, np.arange(27), np.arange(27)],
                                  D[rows][:, np.arange(27), np.arange(27)])


def test_writes_scaling_and_rows_that_ran_are_numpys() -> None:
    rng = np.random.default_rng(1)
    P, D = _random(rng)
    Q, E = _random(rng)
    ran = np.array([True, False, True, False, False])
    P[ran] = Q[ran]
    D[ran] = E[ran]
    np.testing.assert_array_equal(np.asarray(P), D)
    P *= 2.5
    np.testing.assert_array_equal(np.asarray(P), 2.5 * D)
    into = np.full(D.shape, 7.0)
    out = Q.rows_that_ran(ran, into)
    assert out is into
    np.testing.assert_array_equal(into, np.where(ran[:, None, None], E, 7.0))
    zeroed = Q.rows_that_ran(ran)
    np.testing.assert_array_equal(np.asarray(zeroed), np.where(ran[:, None, None], E, 0.0))


@pytest.mark.parametrize("dtype", [np.float32, None])
def test_as_array_takes_a_dtype(dtype) -> None:  # noqa: ANN001
    P, D = _random(np.random.default_rng(2), R=2)
    a = np.asarray(P, dtype=dtype)
    assert a.dtype == (dtype or np.float64)
    np.testing.assert_allclose(a, D, rtol=1e-6)

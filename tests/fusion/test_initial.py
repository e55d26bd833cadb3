"""fusion/ukf/initial.py's lazy initial covariances against the dense ones they stand for (brute
force): ``diag(var)`` with each fit's 6x6 covariance on its entries where the fit is good."""

from __future__ import annotations

import numpy as np

from gt3dkit.fusion.ukf.initial import InitialCov, rows_of


def _random(rng: np.random.Generator, R: int = 6, n: int = 21) -> tuple[InitialCov, np.ndarray]:
    var = rng.uniform(0.1, 2.0, (R, n))
    A = rng.normal(size=(R, 6, 6))
    cov6 = A @ A.transpose(0, 2, 1)
    ok = rng.uniform(size=R) < 0.6
    dims = np.array([0, 1, 2, 6, 7, 8])
    dense = np.zeros((R, n, n))
    dense[:, np.arange(n), np.arange(n)] = var
    for r in np.flatnonzero(ok):
        dense[r][np.ix_(dims, dims)] = cov6[r]
    return InitialCov(var, cov6, ok, dims), dense


def test_rows_entries_and_arrays_are_the_dense_ones() -> None:
    rng = np.random.default_rng(0)
    P0, D = _random(rng)
    assert P0.shape == D.shape
    np.testing.assert_array_equal(np.asarray(P0), D)
    rows = np.array([5, 1, 1, 3])
    np.testing.assert_array_equal(P0[rows], D[rows])
    np.testing.assert_array_equal(np.asarray(P0.rows(rows)), D[rows])
    np.testing.assert_array_equal(np.asarray(rows_of(P0, rows)), D[rows])
    np.testing.assert_array_equal(rows_of(D, rows), D[rows])
    r, i, j = rows[:, None, None], rng.integers(0, 21, (1, 3, 1)), rng.integers(0, 21, (1, 1, 4))
    np.testing.assert_array_equal(P0[r, i, j], D[r, i, j])
    # a part's entries (the joint split): row k the entries dims[k] of row src[k]
    src = np.array([0, 2, 4])
    dims = np.array([[0, 1, 2, 9, 10, 11], [6, 7, 8, 3, 4, 5], [12, 13, 14, 15, 16, 17]])
    part = P0.entries(src, dims)
    want = np.stack([D[s][np.ix_(d, d)] for s, d in zip(src, dims, strict=True)])
    np.testing.assert_array_equal(np.asarray(part), want)


def test_chunked_indexing_matches_one_chunk(monkeypatch) -> None:  # noqa: ANN001
    P0, D = _random(np.random.default_rng(1), R=40)
    monkeypatch.setattr(InitialCov, "CHUNK_ENTRIES", 50)  # many chunks
    np.testing.assert_array_equal(np.asarray(P0), D)

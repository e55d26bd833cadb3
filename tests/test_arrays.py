"""gt3dkit.arrays against numpy's own row uniques."""

from __future__ import annotations

import itertools

import numpy as np

from gt3dkit.arrays import unique_rows


def test_unique_rows_equals_numpy() -> None:
    rng = np.random.default_rng(0)
    for case in range(60):
        K, N = int(rng.integers(1, 4)), int(rng.integers(1, 50))
        hi = 2**40 if case % 5 == 0 else 6  # ranges too wide to pack: numpy's own path
        a = rng.integers(-hi, hi, (N, K))
        for flags in itertools.product([False, True], repeat=3):
            ours = unique_rows(a, *flags)
            ref = np.unique(a, axis=0, return_index=flags[0], return_inverse=flags[1],
                            return_counts=flags[2])
            ours, ref = (ours, ref) if isinstance(ours, tuple) else ((ours,), (ref,))
            assert len(ours) == len(ref)
            for x, y in zip(ours, ref, strict=True):
                np.testing.assert_array_equal(x, np.asarray(y).reshape(x.shape))
    assert unique_rows(np.zeros((0, 2), np.int64)).shape == (0, 2)


def test_lookup_rows_equals_a_dict() -> None:
    from gt3dkit.arrays import lookup_rows

    rng = np.random.default_rng(1)
    for case in range(40):
        hi = 2**40 if case % 4 == 0 else 20
        keys = np.unique(rng.integers(-hi, hi, (int(rng.integers(0, 60)), 2)), axis=0)
        keys = keys[rng.permutation(len(keys))]
        queries = np.concatenate([keys[: len(keys) // 2], rng.integers(-hi, hi, (30, 2))])
        index = {tuple(k): i for i, k in enumerate(keys.tolist())}
        want = [index.get(tuple(q), -1) for q in queries.tolist()]
        np.testing.assert_array_equal(lookup_rows(keys.reshape(-1, 2), queries), want)

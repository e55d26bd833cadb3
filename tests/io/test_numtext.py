"""The output rows' compiled formatter (gt3dkit.io.numtext) writes what Python's ``%d`` and
``%.6f`` write, to the byte: on random values of every size, exact ties (multiples of 1/128),
values a hair from a tie, signed zeros, NaN, infinities and the limits."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings, strategies as st

from gt3dkit.io.numtext import LIMIT, format_rows


def _python(values: np.ndarray, fixed: np.ndarray) -> str:
    template = ",".join("%.6f" if f else "%d" for f in fixed.tolist()) + "\r\n"
    return "".join(template % tuple(v if f else int(v) for v, f in zip(row, fixed.tolist(), strict=True))
                   for row in values.tolist())


def test_rows_as_python_writes_them() -> None:
    rng = np.random.default_rng(1)
    n = 50_000
    ties = (rng.integers(-10**9, 10**9, n) + 0.5) / 1e6
    cols = [rng.integers(0, 2**31, n), rng.integers(-2**53, 2**53, n, dtype=np.int64),
            rng.normal(0, 10, n), rng.uniform(-1, 1, n) * 10.0 ** rng.integers(-12, 10, n),
            rng.integers(-10**6, 10**6, n) / 128.0, ties, np.nextafter(ties, np.inf),
            np.nextafter(ties, -np.inf),
            rng.choice([0.0, -0.0, np.nan, np.inf, -np.inf, LIMIT, -LIMIT, np.nextafter(LIMIT, 0), 1e-300,
                        -1e-300, 5e-324, 0.5e-6, -0.5e-6, 1.5e-6, 0.0078125, 2.0**53], n)]
    values = np.column_stack(cols).astype(np.float64)
    fixed = np.r_[False, False, np.ones(len(cols) - 2, bool)]
    assert format_rows(values, fixed) == _python(values, fixed)
    typical = values[:, :4]  # no row left to Python
    assert format_rows(typical, fixed[:4]) == _python(typical, fixed[:4])
    assert format_rows(np.zeros((0, 3)), np.ones(3, bool)) == ""


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(-2**53, 2**53), st.floats(allow_nan=True, allow_infinity=True),
                          st.floats(-1e4, 1e4)), min_size=1, max_size=20))
def test_random_rows(rows: list[tuple[int, float, float]]) -> None:
    values = np.array(rows, dtype=np.float64)
    fixed = np.array([False, True, True])
    assert format_rows(values, fixed) == _python(values, fixed)

"""Rows of numbers as text, exactly as Python's ``%d`` and ``%.6f`` write them, by a compiled loop
(the output files' rows: :mod:`gt3dkit.io.writers`).

``"%.6f" % x`` rounds the binary value of ``x`` to 6 decimals, half to even. The loop rounds
``|x| * 1e6`` instead, which is the product rounded to a double: its error is at most
``|x| * 1e6 * 2**-53``, so wherever the product's fraction is further than that (twice, here)
from one half, both round to the same integer. A value closer to a tie (``1/128``, whose product
is exactly 7812.5, is one), one beyond ``4e9``, NaN or infinite sends its row to Python's own
formatting. On 104 269 rows of 11 numbers: 0.03 s against 0.36 s by ``%`` row by row."""

from __future__ import annotations

import math

import numba
import numpy as np

from gt3dkit.geom.kernel_cache import drop_stale

drop_stale()  # before any compiled function below is called (and its cache read)

#: Rows formatted at once (their text held in one buffer).
ROWS_AT_ONCE = 65536
#: ``|x|`` beyond which a ``%.6f`` field goes to Python (``x * 1e6`` then nears 2**52).
LIMIT = 4e9


@numba.njit(cache=True, nogil=True)
def _write_int(v: int | np.int64, buf: np.ndarray, p: int) -> int:
    """The decimal digits of ``v`` >= 0 into ``buf`` from ``p``; the position after them."""
    n = 1
    t = v
    while t >= 10:
        t //= 10
        n += 1
    for e in range(n - 1, -1, -1):
        buf[p + e] = 48 + v % 10
        v //= 10
    return p + n


@numba.njit(cache=True, nogil=True)
def rows_text(values: np.ndarray, fixed: np.ndarray, buf: np.ndarray, ends: np.ndarray,
              python: np.ndarray) -> int:
    """Each row of ``values (N, C)`` as ``%d`` (the columns ``fixed`` is False for: integers held
    exactly in float64) or ``%.6f`` fields joined by commas and ended by CRLF, into ``buf``
    (uint8, at least 24 bytes a field and 2 a row); ``ends[i]`` where row ``i``'s text ends (or
    would: a row left to Python takes none), ``python[i]`` whether it was. The bytes written."""
    n, c = values.shape
    p = 0
    for i in range(n):
        start = p
        python[i] = False
        for k in range(c):
            if k > 0:
                buf[p] = 44  # ,
                p += 1
            x = values[i, k]
            if math.copysign(1.0, x) < 0.0 and (fixed[k] or x != 0.0):
                buf[p] = 45  # -
                p += 1
            if not fixed[k]:
                p = _write_int(abs(np.int64(x)), buf, p)
                continue
            y = abs(x) * 1e6
            if not y < LIMIT * 1e6:  # NaN too
                python[i] = True
                break
            whole = math.floor(y)
            frac = y - whole
            if abs(frac - 0.5) <= y * 2.0**-52:
                python[i] = True
                break
            r = np.int64(whole) + (1 if frac > 0.5 else 0)
            p = _write_int(r // 1000000, buf, p)
            buf[p] = 46  # .
            f = r % 1000000
            for e in range(5, -1, -1):
                buf[p + 1 + e] = 48 + f % 10
                f //= 10
            p += 7
        if python[i]:
            p = start
        else:
            buf[p] = 13
            buf[p + 1] = 10
            p += 2
        ends[i] = p
    return p


def format_rows(values: np.ndarray, fixed: np.ndarray) -> str:
    """The text of ``"%d,...,%.6f\\r\\n" % row`` for every row of ``values (N, C)`` (float64;
    ``fixed (C,)``: True for a ``%.6f`` column, False for a ``%d`` one, whose values must be
    integers of magnitude up to 2**53), as ``csv.writer`` would write them."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    fixed = np.ascontiguousarray(fixed, dtype=np.bool_)
    flags = fixed.tolist()
    template = ",".join("%.6f" if f else "%d" for f in flags) + "\r\n"
    out: list[str] = []
    for a in range(0, len(values), ROWS_AT_ONCE):
        part = values[a:a + ROWS_AT_ONCE]
        buf = np.empty(len(part) * (24 * part.shape[1] + 2), np.uint8)
        ends = np.empty(len(part), np.int64)
        python = np.empty(len(part), np.bool_)
        size = rows_text(part, fixed, buf, ends, python)
        text = buf[:size].tobytes().decode("ascii")
        if not python.any():
            out.append(text)
            continue
        last = 0
        for i in np.flatnonzero(python).tolist():
            row = tuple(v if f else int(v) for v, f in zip(part[i].tolist(), flags, strict=True))
            out += [text[last:ends[i]], template % row]
            last = int(ends[i])
        out.append(text[last:])
    return "".join(out)

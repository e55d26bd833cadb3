"""The process-noise search's maximiser (gt3dkit.fusion.ukf.smoother.maximise_log)."""

from __future__ import annotations

import numpy as np
import pytest

from gt3dkit.fusion.ukf.noise import maximise_log


def test_the_search_finds_the_top_of_a_curve() -> None:
    calls: list[int] = []

    def f(values: list[float]) -> list[float]:
        calls.append(len(values))
        return [-(np.log(v) - np.log(0.37)) ** 2 for v in values]

    best, seen = maximise_log(f, 0.01, 100.0, 5)
    assert best == pytest.approx(0.37, rel=1e-6)  # a parabola in log q: the vertex is exact
    assert max(seen, key=lambda v: seen[v]) == best
    assert len(calls) == 3  # the scan and two rounds, each one batch

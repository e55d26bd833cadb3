"""The seeded hostile-input suite (tests/hostile.py), seed 0, run in this process: every
case ends in one clean error line (exit 2, nothing written or changed) or in a complete
result with one warning line per odd kind."""

from __future__ import annotations

from pathlib import Path

import pytest

from .hostile import cases, make_bases, run_case

CASES = cases(seed=0)


@pytest.fixture(scope="module")
def bases(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_bases(Path(tmp_path_factory.mktemp("bases")))


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_hostile(case, bases, tmp_path) -> None:
    o = run_case(case, bases, tmp_path / "w")
    assert not o.problems, f"{o.problems}\nexit {o.code}\nstderr: {o.stderr[-2000:]}"

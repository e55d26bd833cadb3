"""gt3dkit runs its small-matrix work with one BLAS thread unless the user says otherwise."""

from __future__ import annotations

import pytest
from threadpoolctl import threadpool_info

from gt3dkit.threads import blas_threads, small_matrix_blas


def _blas_threads_now() -> list[int]:
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


@pytest.mark.parametrize(("env", "load", "want"), [({}, 3.0, 1), ({}, 0.1, "cores"),
                                                    ({"GT3D_BLAS_THREADS": "2"}, 3.0, 2),
                                                    ({"OPENBLAS_NUM_THREADS": "2"}, 0.1, None),
                                                    ({"GT3D_BLAS_THREADS": "x"}, 0.1, 1)])
def test_blas_threads_choice(monkeypatch, env, load, want) -> None:
    import os

    for k in ("GT3D_BLAS_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
              "BLIS_NUM_THREADS"):
        monkeypatch.delenv(k, raising=False)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setattr(os, "getloadavg", lambda: (load, load, load))
    assert blas_threads() == (os.cpu_count() if want == "cores" else want)


def test_the_pool_is_limited_inside_and_restored(monkeypatch) -> None:
    for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("GT3D_BLAS_THREADS", "1")
    from threadpoolctl import threadpool_limits

    if not _blas_threads_now():
        pytest.skip("no BLAS pool threadpoolctl can see")
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads_now()
        with small_matrix_blas():
            assert set(_blas_threads_now()) == {1}
        assert _blas_threads_now() == before

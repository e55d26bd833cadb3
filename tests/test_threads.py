"""gt3dkit runs its small-matrix work with one BLAS thread unless the user says otherwise."""

from __future__ import annotations

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from gt3dkit.threads import blas_threads, compiled_threads, every_core, small_matrix_blas


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


def _boxes_in_child(q) -> None:  # runs in a forked child
    from gt3dkit.geom.conics import ellipsoid_boxes

    q.put(ellipsoid_boxes(*_box_args())[0])


def _box_args():
    C, N = 4, 2000  # large enough to be split over threads
    K = np.tile(np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]]), (C, 1, 1))
    dist = np.zeros((C, 5))
    dist[:, 0] = 0.01
    c = np.random.default_rng(0).normal(size=(N, 3))
    return (c, np.full((N, 3), 0.3), np.eye(3), K, dist, np.tile(np.eye(3), (C, 1, 1)),
            np.tile([0, 0, 8.0], (C, 1)), np.ones(C))


def test_split_work_survives_a_fork(monkeypatch) -> None:
    """A process forked after the thread pool was made (a user's multiprocessing on Linux)
    inherits the pool without its threads: it must make its own, not wait forever."""
    import multiprocessing as mp

    from gt3dkit.geom.conics import ellipsoid_boxes

    monkeypatch.setenv("GT3D_THREADS", "2")
    here, _ = ellipsoid_boxes(*_box_args())  # the pool exists now
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_boxes_in_child, args=(q,))
    p.start()
    try:  # a deadlock, not a speed limit: the child needs well under a second
        got = q.get(timeout=120)
    finally:
        p.join(10)
        if p.is_alive():
            p.kill()
    assert p.exitcode == 0
    np.testing.assert_array_equal(got, here)


def test_compiled_threads_choice(monkeypatch) -> None:
    """Every core in the main thread; one in reconstruct-many workers and in other threads (they
    are the parallelism there), but inside ``every_core`` (and only there); GT3D_THREADS
    overrides."""
    import os
    import threading

    for k in ("GT3D_THREADS", "GT3D_BLAS_THREADS"):
        monkeypatch.delenv(k, raising=False)
    assert compiled_threads() == (os.cpu_count() or 1)
    seen: list[int] = []
    t = threading.Thread(target=lambda: seen.append(compiled_threads()))
    t.start()
    t.join()
    assert seen == [1]

    def in_every_core() -> None:  # a step the idle siblings wait for (a Dask worker's thread)
        with every_core():
            seen.append(compiled_threads())
        seen.append(compiled_threads())

    t = threading.Thread(target=in_every_core)
    t.start()
    t.join()
    assert seen == [1, os.cpu_count() or 1, 1]
    monkeypatch.setenv("GT3D_BLAS_THREADS", "1")  # what a reconstruct-many worker sets
    assert compiled_threads() == 1
    monkeypatch.setenv("GT3D_THREADS", "3")
    assert compiled_threads() == 3
    with every_core():
        assert compiled_threads() == 3


def test_roomy_malloc_on_a_dask_like_worker() -> None:
    """Under a trim threshold (as a Dask nanny sets it) the block's large temporaries come from the
    heap, not one mmap each: fewer page faults for the same work; after it, the trim threshold
    is the environment's again and the memory handed back."""
    import os
    import subprocess
    import sys

    code = """
import resource, numpy as np
from gt3dkit.threads import roomy_malloc, _glibc
def work():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(200):
        a = np.ones(400_000)  # 3.2 MB: above the fixed 128 kB mmap threshold
        a.sum()
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
plain = work()
with roomy_malloc():
    roomy = work()
print(_glibc() is not None, plain, roomy)
"""
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    glibc, plain, roomy = r.stdout.split()
    if glibc != "True":
        pytest.skip("not glibc")
    assert int(roomy) < int(plain) / 4, (plain, roomy)


def test_roomy_malloc_keeps_a_runs_memory_between_its_windows() -> None:
    """Without a trim threshold in the environment (a run in one process), ``roomy_malloc(run=True)``
    keeps memory freed at a window's end for the next one: windows of many 3.2 MB temporaries,
    freed together, fault their memory in once, not once a window as glibc's own thresholds let
    it (it handed the heap's top back after each)."""
    import os
    import subprocess
    import sys

    code = """
import resource, numpy as np
from gt3dkit.threads import roomy_malloc, _glibc
def windows():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
        held = [np.ones(400_000) for _ in range(20)]  # a window's temporaries, 64 MB
        del held
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
plain = windows()
with roomy_malloc(run=True):
    roomy = windows()
print(_glibc() is not None, plain, roomy)
"""
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    glibc, plain, roomy = r.stdout.split()
    if glibc != "True":
        pytest.skip("not glibc")
    assert int(roomy) < int(plain) / 4, (plain, roomy)

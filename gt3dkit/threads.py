"""How many BLAS threads gt3dkit's small-matrix work uses.

Our linear algebra is many small matrices (a 123-state UKF, per-object 9-state updates): with
OpenBLAS's default of one thread per core, its threads spin and oversubscribe; on this 2-core
machine a keypoint run was 3-12x slower than with one thread, and a loaded machine went past
15 minutes for a 77 s run (notes/profile-2026-11.md). Measured here on an idle machine, two
threads ran the Panoptic keypoint scene in 34.8 s wall / 60.1 s CPU against 38.1 s / 32.2 s with
one. So gt3dkit uses every core's BLAS thread only when the machine is idle (1-minute load
average below :data:`IDLE_LOAD`) and one thread otherwise; ``reconstruct-many`` workers always
use one (they are the parallelism). ``GT3D_BLAS_THREADS=N`` sets N; a user who set
``OPENBLAS_NUM_THREADS``/``OMP_NUM_THREADS``/``MKL_NUM_THREADS`` themselves is obeyed (we leave the
pool alone). threadpoolctl changes the pool at run time (numpy's BLAS is already loaded).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import os
from collections.abc import Callable, Iterator
from typing import Any

_USER_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")
#: below this 1-minute load average the machine counts as idle
IDLE_LOAD = 0.5


def _env_threads(name: str) -> int | None:
    """A thread count set in the environment variable ``name`` (at least 1; 1 if not a number),
    or None when unset."""
    v = os.environ.get(name)
    if not v:
        return None
    try:
        return max(int(v), 1)
    except ValueError:
        return 1


def blas_threads() -> int | None:
    """The BLAS thread count to impose, or None to leave the user's setting alone."""
    v = _env_threads("GT3D_BLAS_THREADS")
    if v is not None:
        return v
    if any(os.environ.get(k) for k in _USER_VARS):
        return None
    cores = os.cpu_count() or 1
    try:
        idle = os.getloadavg()[0] < IDLE_LOAD
    except OSError:  # no load average on this system
        idle = False
    # an idle machine: its cores (measured +9 % faster wall time at twice the CPU); anything else
    # running (tests, other sequences, a desktop): one thread, as threads then spin and fight
    return cores if idle else 1


@contextlib.contextmanager
def small_matrix_blas() -> Iterator[None]:
    """Run the block with :func:`blas_threads` BLAS threads (and restore the pool after)."""
    n = blas_threads()
    if n is None:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=n, user_api="blas"):
        yield


def compiled_threads() -> int:
    """Threads for gt3dkit's own compiled loops (the tangent box, the box filter: numba
    functions that release the GIL, split over threads by :func:`run_split`).

    ``GT3D_THREADS=N`` sets N. Otherwise one thread in ``reconstruct-many`` workers (the
    workers are the parallelism: they set ``GT3D_BLAS_THREADS=1``) and in any thread but the
    main one (a Dask or user thread pool is the parallelism there), else every core. Unlike
    BLAS's spinning threads these work in bursts of a few milliseconds; measured on this 2-core
    machine the tangent box ran 1.8x faster on two threads. (numba's own ``parallel=True`` was
    measured too: the same speed, but 90 s more compilation on first use.)
    """
    import threading

    v = _env_threads("GT3D_THREADS")
    if v is not None:
        return v
    if _EVERY_CORE.get():
        return _cores()
    worker = os.environ.get("GT3D_BLAS_THREADS") == "1"
    if worker or threading.current_thread() is not threading.main_thread():
        return 1
    return _cores()


#: Set by :func:`every_core` for the block it runs (in this thread and context).
_EVERY_CORE: contextvars.ContextVar[bool] = contextvars.ContextVar("gt3dkit_every_core", default=False)


@contextlib.contextmanager
def every_core() -> Iterator[None]:
    """:func:`compiled_threads` gives every core in the block, in any thread (``GT3D_THREADS``
    still decides where set): for a step the rest of the run waits for, on a worker whose
    siblings are idle meanwhile (:func:`gt3dkit.windows.noise.sample_noise` on a Dask worker)."""
    token = _EVERY_CORE.set(True)
    try:
        yield
    finally:
        _EVERY_CORE.reset(token)


@functools.cache
def _cores() -> int:
    return os.cpu_count() or 1


_POOL: list[Any] = []


def run_split(fn: Callable[[int, int], None], n: int, min_per_thread: int = 1) -> None:
    """``fn(a, b)`` over ``[0, n)`` split into :func:`compiled_threads` contiguous parts run
    on a thread pool (``fn`` must release the GIL and write disjoint outputs); one part (this
    thread) when ``n < 2 * min_per_thread`` or one thread is to be used."""
    k = min(compiled_threads(), n // max(min_per_thread, 1))
    if k <= 1:
        fn(0, n)
        return
    if not _POOL or _POOL[0][0] != os.getpid():  # none yet, or inherited by a fork (no threads)
        from concurrent.futures import ThreadPoolExecutor

        _POOL[:] = [(os.getpid(), ThreadPoolExecutor(max_workers=_cores(), thread_name_prefix="gt3dkit"))]
    cuts = [n * i // k for i in range(k + 1)]
    futures = [_POOL[0][1].submit(fn, a, b) for a, b in zip(cuts[1:-1], cuts[2:], strict=True)]
    fn(cuts[0], cuts[1])
    for f in futures:
        f.result()


#: glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: glibc's default mmap threshold, where a fixed trim threshold leaves it (bytes)
_GLIBC_MMAP_THRESHOLD = 128 * 1024


@contextlib.contextmanager
def roomy_malloc(run: bool = False) -> Iterator[None]:
    """glibc's allocator with room for a window's numpy temporaries while the block runs, in a
    process started with ``MALLOC_TRIM_THRESHOLD_`` set (a Dask nanny starts its workers with
    64 kB, to hand freed memory back to the system: ``distributed.nanny.pre-spawn-environ``).
    Setting it also fixes glibc's mmap threshold at 128 kB (no longer raised as large blocks are
    freed): every larger temporary is then a fresh ``mmap``, page-faulted in and unmapped again.
    A box window (374 frames of the 4 000-frame, 40-person benchmark scene) on such a worker ran
    11 % slower, 14 % with two workers side by side; 200 arrays of 3.2 MB page-fault 100 times
    as often (``tests/test_threads.py``). For the block: mmap threshold
    32 MiB, trim threshold 256 MiB; after it the environment's values and ``malloc_trim(0)``, so
    that the worker hands the memory back as its nanny expects. Nothing elsewhere (no such
    variable, or not glibc), but with ``run``: the block is a long sequence's windows one after
    another in this process (:func:`gt3dkit.windows.reconstruct_windowed`), where glibc's own
    thresholds (raised as large blocks are freed) still handed each window's memory back and
    faulted it in again for the next: the 4 000-frame box scene's run had 480 000-710 000 minor
    page faults, 370 000 with these settings, and ran 0.9 s faster. After it glibc's thresholds
    stay fixed at their defaults (glibc cannot make them dynamic again)."""
    env = os.environ.get("MALLOC_TRIM_THRESHOLD_")
    libc = _glibc() if env or run else None
    if libc is None:
        yield
        return
    libc.mallopt(_M_MMAP_THRESHOLD, 32 << 20)
    libc.mallopt(_M_TRIM_THRESHOLD, 256 << 20)
    try:
        yield
    finally:
        libc.mallopt(_M_MMAP_THRESHOLD, _env_bytes("MALLOC_MMAP_THRESHOLD_", _GLIBC_MMAP_THRESHOLD))
        libc.mallopt(_M_TRIM_THRESHOLD, _env_bytes("MALLOC_TRIM_THRESHOLD_", _GLIBC_MMAP_THRESHOLD))
        libc.malloc_trim(0)


def _env_bytes(name: str, default: int) -> int:
    """A byte count set in the environment variable ``name``, or ``default``."""
    try:
        return max(int(os.environ.get(name, "")), 0)
    except ValueError:
        return default


@functools.cache
def _glibc() -> Any:
    """The C library when it is glibc (has ``mallopt`` and ``malloc_trim``), else None."""
    import ctypes
    import platform

    if platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
        return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None
    except OSError:
        return None

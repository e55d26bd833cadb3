"""``gt3d``'s entry point. It imports nothing heavy itself: where ``gt3d reconstruct`` names a Dask
scheduler (``--scheduler``), it connects first and sends the scheduler's first worker to load
gt3dkit's imports and compiled kernels (:func:`gt3dkit.early.connect_early`), and only then loads
the commands (:mod:`gt3dkit.commands.main`, by name, to keep this module light: with the
package's lazy names, one of the two places gt3dkit imports a module of its own late). On the
4 000-frame box scene with 2 workers on 2 cores, the worker's warm-up had waited for the 1.2 s of
this process's imports.

As a program (:func:`entry`), ``gt3d`` ends its process once its work and Python's own exit steps
are done, without the interpreter's teardown (:func:`finish`)."""

from __future__ import annotations

import atexit
import contextlib
import importlib
import os
import sys
import threading
from typing import Any, NoReturn

from gt3dkit.early import DEFAULT_ESTIMATOR, Early, connect_early

#: After a signal, the longest :func:`finish` waits for the ``atexit`` handlers (s).
SIGNALLED_EXIT_S = 5.0


def entry() -> NoReturn:
    """The ``gt3d`` program (the console script, ``python -m gt3dkit.cli``): :func:`main` on the
    process's command line, then :func:`finish` with its exit status."""
    finish(main())


def finish(code: int) -> NoReturn:
    """End this process with exit status ``code`` after what a Python process does as it exits,
    except the interpreter's teardown: the non-daemon threads are joined (and the thread pools'
    exit hooks run, ``threading._shutdown``, as the interpreter calls it first), the ``atexit``
    handlers run (Dask's clients closed, temporary folders removed, logging flushed), stdout and
    stderr are flushed, then ``os._exit``. The teardown frees every module and object one by one:
    0.30-0.41 s after a 4 000-frame box run (its outputs already written and closed), 0.02 s
    with this. Only for the program: :func:`main` called from Python returns as usual.

    After a signal (``code`` 129-143: the run has unwound, its one line is printed and nothing
    half-written is left), the threads are not joined and the ``atexit`` handlers get
    :data:`SIGNALLED_EXIT_S`: the signal may have struck while this thread held a lock another
    thread waits for (llvmlite's, numba compiling a kernel for a pool thread), and a ``gt3d
    compare`` stopped by SIGTERM then waited for that thread for ever."""
    if code > 128:
        steps = threading.Thread(target=atexit._run_exitfuncs, daemon=True)
        steps.start()
        steps.join(SIGNALLED_EXIT_S)
    else:
        shutdown = getattr(threading, "_shutdown", None)
        if shutdown is not None:
            shutdown()
        atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a closed pipe: nothing left to tell
            stream.flush()
    os._exit(code)


def main(argv: list[str] | None = None) -> int:
    """The ``gt3d`` command (:func:`gt3dkit.commands.main.main`, which gives the exit statuses)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        early = early_start(argv)
    except KeyboardInterrupt:
        print("error: interrupted (Ctrl-C): no output written or changed", file=sys.stderr)
        return 130
    try:
        return int(importlib.import_module("gt3dkit.commands.main").main(argv, early))
    finally:
        if early is not None:  # taken and closed by the run, or never used
            early.close()


def early_start(argv: list[str]) -> Early | None:
    """The early connection of ``gt3d reconstruct ... --scheduler ADDRESS`` (:mod:`gt3dkit.early`),
    with the warm-up of its ``--estimator`` (:func:`gt3dkit.windows.cluster.warm_first`, sent by
    name: :class:`Named`) sent to the first worker; None for any other
    command line. The options are read as given (``--opt value`` or ``--opt=value``); the command
    line is parsed whole, and checked, afterwards."""
    if not argv or argv[0] != "reconstruct" or "-h" in argv or "--help" in argv:
        return None
    address = (_value(argv, "--scheduler") or "").strip()
    if not address:
        return None
    return connect_early(address, Named("gt3dkit.windows.cluster", "warm_first"),
                         _value(argv, "--estimator") or DEFAULT_ESTIMATOR, {})


def _value(argv: list[str], option: str) -> str | None:
    """The value ``argv`` gives ``option`` (its last), or None."""
    found = None
    for k, a in enumerate(argv):
        if a == "--":
            break
        if a == option and k + 1 < len(argv):
            found = argv[k + 1]
        elif a.startswith(option + "="):
            found = a[len(option) + 1:]
    return found


def by_name(module: str, name: str) -> Any:
    """``module``'s ``name``, ``module`` imported here if it is not yet (:class:`Named`)."""
    return getattr(importlib.import_module(module), name)


class Named:
    """The function ``module.name``, sent to a Dask worker without this process importing
    ``module``: it pickles as the call that imports it (:func:`by_name`). Sent sealed
    (:func:`gt3dkit.sealed.submit`, as every task of a run is), it is unpickled, and ``module``
    imported, where the task runs, under the lock a worker opens every sealed value with: no
    other thread of the worker imports gt3dkit meanwhile (two threads importing one package at
    once can deadlock in Python's import locks, and a worker died of it: ``KeyError:
    'gt3dkit.windows'`` reading the next task, once in the test suite)."""

    def __init__(self, module: str, name: str) -> None:
        self.module, self.__name__ = module, name  # Dask names the task after the function

    def __call__(self, *args: object, **kwargs: object) -> Any:
        return by_name(self.module, self.__name__)(*args, **kwargs)

    def __reduce__(self) -> tuple[Any, tuple[str, str]]:
        return by_name, (self.module, self.__name__)


if __name__ == "__main__":
    entry()

"""``gt3d``'s entry point. It imports nothing heavy itself: where ``gt3d reconstruct`` names a Dask
scheduler (``--scheduler``), it connects first and sends the scheduler's first worker to load
gt3dkit's imports and compiled kernels (:func:`gt3dkit.early.connect_early`), and only then loads
the commands (:mod:`gt3dkit.commands.main`, by name: the one place gt3dkit imports a module of its
own late, to keep this one light). On the 4 000-frame box scene with 2 workers on 2 cores, the
worker's warm-up had waited for the 1.2 s of this process's imports."""

from __future__ import annotations

import importlib
import sys

from gt3dkit.early import DEFAULT_ESTIMATOR, Early, connect_early


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
    with :func:`warm_named` of its ``--estimator`` sent to the first worker; None for any other
    command line. The options are read as given (``--opt value`` or ``--opt=value``); the command
    line is parsed whole, and checked, afterwards."""
    if not argv or argv[0] != "reconstruct" or "-h" in argv or "--help" in argv:
        return None
    address = (_value(argv, "--scheduler") or "").strip()
    if not address:
        return None
    return connect_early(address, warm_named, _value(argv, "--estimator") or DEFAULT_ESTIMATOR)


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


def warm_named(estimator: str) -> None:
    """On a Dask worker: gt3dkit's imports and ``estimator``'s compiled kernels loaded
    (:func:`gt3dkit.windows.cluster.warm_first`), the module imported by name so that the client
    sending this need not import it first."""
    importlib.import_module("gt3dkit.windows.cluster").warm_first(estimator, {})


if __name__ == "__main__":
    sys.exit(main())

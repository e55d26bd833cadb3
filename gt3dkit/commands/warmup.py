"""Compile every kernel a first run uses, once (``make setup``; the test session's first fixture):
``python -m gt3dkit.commands.warmup``. A first real run then loads machine code from numba's
cache instead of compiling it (:mod:`gt3dkit.geom.kernel_cache` drops stale caches).

The kernels fall in two sets that share little: the boxes' (per-frame box fits, the noise
search, the box filter) and the joints' (triangulation, the joint filter). numba compiles on one
core, so the two sets compile side by side, the joints' in a second process
(:func:`compile_joints`), each saying when it is done. Each process makes only its own kind's
tiny scene (:func:`gt3dkit.api.tiny_scene`): the joints' process also simulated the boxes, and
so compiled the box models' kernels (13 s) the boxes' process compiles too; without, the kernels
were ready in 90 and 98 s against 105 and 106 s (the same 103 compiled functions, two runs each
with an empty cache, this 2-core machine)."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from gt3dkit.api import tiny_scene
from gt3dkit.fusion.base import ESTIMATORS, make_estimator
from gt3dkit.fusion.ukf import smoother as us
from gt3dkit.fusion.ukf.filtering import initial_states, run_filter
from gt3dkit.fusion.ukf.measurement import Model
from gt3dkit.io.numtext import format_rows


def compile_boxes() -> float:
    """Estimate a 4-frame, 2-person simulated box scene by every estimator (the UKF's per-frame
    fits, noise search, forward and backward; the GTSAM smoother's factors), run the UKF's
    filter with the noise set, and format a row of numbers as the output files' rows are
    (:func:`gt3dkit.io.numtext.format_rows`); returns the seconds it took."""
    t0 = time.perf_counter()
    scene = tiny_scene("boxes")
    for name in ESTIMATORS:
        make_estimator(name).estimate(scene)
    format_rows(np.zeros((1, 2)), np.array([False, True]))
    est = us.UKFSmoother()
    model = Model.of(est.prepare(scene))
    cfg = replace(est.config, accel_sd=0.5, shape_sd=0.01)
    run_filter(model, initial_states(model, cfg), cfg, scene.fps)
    return time.perf_counter() - t0


def compile_joints() -> float:
    """Estimate a 3-frame simulated skeleton scene and run its joints' chains with the noise set
    (the filter's collecting pass); returns the seconds it took."""
    t0 = time.perf_counter()
    scene = tiny_scene("joints")
    est = us.UKFSmoother()
    est.estimate(scene)
    model = Model.of(est.prepare(scene))
    cfg = replace(est.config, accel_sd=0.5, shape_sd=0.01, joint_accel_sd=0.5)
    run_filter(model, initial_states(model, cfg), cfg, scene.fps, collect=True)
    return time.perf_counter() - t0


def warm_up(say: bool = False) -> float:
    """Compile (or load from numba's disk cache) every compiled function a run uses: the box
    kernels here, the joint kernels meanwhile in a second process. ``say``: print a line as each
    set is ready. Returns the seconds it took."""
    t0 = time.perf_counter()
    side = subprocess.Popen([sys.executable, "-m", "gt3dkit.commands.warmup", "--joints",  # noqa: S603
                             *(["--say"] if say else [])])
    s = compile_boxes()
    if say:
        print(f"  box kernels ready ({s:.0f} s)", flush=True)
    if side.wait() != 0:
        raise RuntimeError("compiling the joint kernels failed (see above)")
    return time.perf_counter() - t0


#: The installed packages gt3dkit's commands, reports, clusters and tests import, besides every
#: module of gt3dkit itself (:func:`import_all`). ``import open3d`` alone imports dash, plotly,
#: IPython and werkzeug (open3d's web visualiser). msgspec: imported where a WILDTRACK frame file is
#: first read (:mod:`gt3dkit.io.datasets.wildtrack`), by no module's import.
IMPORTED = ("open3d", "matplotlib.pyplot", "distributed", "pytest", "hypothesis", "pandas", "motmetrics",
            "trackeval", "pycocotools.coco", "c3d", "importlinter", "msgspec.json", "msgspec.structs")

#: Writes the bytecode of what gt3dkit imports (``make setup`` installs with ``pip --no-compile``):
#: a process at the lowest priority that imports it with bytecode writing on
#: (:func:`import_all`). Beside the kernels' compilation it takes the core the joints' process
#: leaves idle. Only what is imported: every file of every installed package (``compileall``,
#: 25 s of CPU for 2.4 GB) was still being written 11 s after the kernels were ready, and
#: ``make demo`` waited for it; 1 700 of those files are imported.
BYTECODE = ("import os, sys; os.nice(19); sys.dont_write_bytecode = False; "
            "from gt3dkit.commands.warmup import import_all; import_all()")


def import_all() -> None:
    """Import every module of gt3dkit and the packages of :data:`IMPORTED` (one not installed, or
    that fails to import, left out), and the modules numba imports only when a process first
    calls a compiled function (:func:`numba_registries`): where bytecode writing is on, each
    one's is written."""
    import importlib
    import pkgutil

    package = str(Path(__file__).resolve().parents[1])  # gt3dkit's folder
    names = [m.name for m in pkgutil.walk_packages([package], "gt3dkit.")] + list(IMPORTED)
    for name in names:
        with contextlib.suppress(Exception):
            importlib.import_module(name)
    with contextlib.suppress(Exception):
        numba_registries()


def numba_registries() -> None:
    """Load numba's typing and lowering registries, as the first call of a compiled function in a
    process does (``BaseContext.refresh``: 94 modules, ``numba.np.arraymath``, ``arrayobj``,
    ``linalg``, ...), which ``import numba`` does not. Without their bytecode every process
    compiled them from source at its first kernel call: 0.27 s of each ``gt3d reconstruct``
    where ``PYTHONDONTWRITEBYTECODE`` is set (Python's compile calls, timed)."""
    from numba.core.registry import cpu_target

    cpu_target.typing_context.refresh()
    cpu_target.target_context.refresh()


def main(argv: list[str]) -> None:
    """``python -m gt3dkit.commands.warmup [--joints] [--say] [--bytecode]``: every kernel
    (``make setup``), or the joints' alone (:func:`warm_up`'s second process). ``--bytecode``:
    meanwhile the bytecode of what gt3dkit imports is written (:data:`BYTECODE`): pip wrote
    every package's one file after another, 16-20 s before the kernels started; where
    ``PYTHONDONTWRITEBYTECODE`` is set (as on CI), nothing else writes it, and every process
    compiles numpy, scipy, ... from source again (the test suite: 254 s -> 366 s)."""
    if "--joints" in argv:
        s = compile_joints()
        if "--say" in argv:
            print(f"  joint kernels ready ({s:.0f} s)", flush=True)
        return
    t0 = time.perf_counter()
    side = (subprocess.Popen([sys.executable, "-c", BYTECODE], stdout=subprocess.DEVNULL)  # noqa: S603
            if "--bytecode" in argv else None)
    also = "; the packages' bytecode meanwhile" if side is not None else ""
    print("gt3dkit: compiling the box and the joint kernels side by side (once: numba keeps them next "
          f"to the package){also}", flush=True)
    print(f"gt3dkit: compiled kernels ready ({warm_up(say=True):.0f} s)", flush=True)
    if side is not None:
        side.wait()  # bytecode only speeds imports up: nothing to stop for
        print(f"gt3dkit: the imported packages' bytecode written ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main(sys.argv[1:])

"""The warm-up (``make setup``, the test session's first fixture) compiles every kernel the demo's
runs use, so that a first run loads machine code instead of compiling it."""

from __future__ import annotations

import json
import subprocess
import sys

#: Prints, as JSON, every signature of every compiled function of the kernel files that this
#: process compiled or loaded after running ``{body}``.
SIGNATURES = """
import json
from importlib import import_module
from numba.core.dispatcher import Dispatcher
from gt3dkit.geom.kernel_cache import KERNEL_FILES
{body}
mods = [import_module("gt3dkit." + rel[:-3].replace("/", ".")) for rel in KERNEL_FILES]
print(json.dumps(sorted(f"{{d.py_func.__module__}}.{{d.py_func.__qualname__}}{{k}}" for m in mods
                        for d in vars(m).values() if isinstance(d, Dispatcher) for k in d.overloads)))
"""

WARM_UP = """
from gt3dkit.commands.warmup import compile_boxes, compile_joints
compile_boxes()
compile_joints()
"""

DEMO_RUNS = """
from gt3dkit.api import ESTIMATORS, load_scene, reconstruct
from gt3dkit.commands.common import bundled
scene = load_scene(bundled("multiviewx"))
for name in ESTIMATORS:
    reconstruct(scene, name)
for noise in (0.0, 2.0):
    tracks = reconstruct(load_scene(bundled("panoptic_160906_band1"), noise_px=noise, seed=0), "ukf")
import io
from gt3dkit.io import writers
writers._tracks_rows(io.StringIO(), tracks)
writers._keypoint_rows(io.StringIO(), tracks)
"""


def signatures(body: str) -> set[str]:
    """The kernel signatures a fresh process uses to run ``body`` (loaded from numba's cache): each
    entry point's, those called from within are compiled into it."""
    r = subprocess.run([sys.executable, "-c", SIGNATURES.format(body=body)], capture_output=True, text=True,
                       check=True)
    return set(json.loads(r.stdout.strip().splitlines()[-1]))


def test_the_warm_up_compiles_what_the_demo_runs_use() -> None:
    warmed, used = signatures(WARM_UP), signatures(DEMO_RUNS)
    # the entry points (what they call is compiled into them): the box and the joint kernels ran
    modules = {m for s in used for m in s.split("(")[0].split(".")}
    assert modules >= {"boxlm", "boxupdate", "jointupdate", "trikernel", "boxkernel", "numtext"}, modules
    assert used <= warmed, f"compiled on first use, not by the warm-up: {sorted(used - warmed)}"


#: Run with bytecode written under the folder ``sys.argv[1]`` (Python's ``pycache_prefix``): what
#: ``make setup``'s warm-up writes where ``PYTHONDONTWRITEBYTECODE`` is set.
WRITES_BYTECODE = """
import sys
sys.pycache_prefix, sys.dont_write_bytecode = sys.argv[1], False
from gt3dkit.commands.warmup import numba_registries
numba_registries()
"""

#: Prints, as JSON, the source files of the modules a fresh process imports at its first call of a
#: compiled function (``format_rows``, loaded from numba's cache) whose bytecode is not under
#: ``sys.argv[1]``: those it compiles from source, where nothing writes bytecode.
FIRST_CALL_COMPILES = """
import json, sys
from importlib.util import cache_from_source
from pathlib import Path
sys.pycache_prefix, sys.dont_write_bytecode = sys.argv[1], True
import numpy as np
from gt3dkit.io.numtext import format_rows
before = set(sys.modules)
format_rows(np.zeros((1, 2)), np.array([False, True]))
new = [sys.modules[m] for m in set(sys.modules) - before]
files = [m.__file__ for m in new if str(getattr(m, "__file__", None) or "").endswith(".py")]
compiled = [f for f in files if not Path(cache_from_source(f)).exists()]
print(json.dumps({"imported": len(files), "from_source": compiled}))
"""


def test_the_warm_up_writes_the_bytecode_of_what_a_first_kernel_call_imports(tmp_path) -> None:
    subprocess.run([sys.executable, "-c", WRITES_BYTECODE, str(tmp_path)], check=True)
    r = subprocess.run([sys.executable, "-c", FIRST_CALL_COMPILES, str(tmp_path)], capture_output=True,
                       text=True, check=True)
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["imported"] > 50  # numba's registries: numba.np.arraymath, arrayobj, linalg, ...
    assert got["from_source"] == []

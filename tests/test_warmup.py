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
    assert {s.split(".")[2] for s in used} >= {"boxlm", "boxupdate", "jointupdate", "trikernel", "boxkernel",
                                               "numtext"}
    assert used <= warmed, f"compiled on first use, not by the warm-up: {sorted(used - warmed)}"

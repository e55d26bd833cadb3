from __future__ import annotations

from pathlib import Path

import pytest

from gt3dkit.api import load_scene
from gt3dkit.commands.common import bundled
from gt3dkit.types import Scene

from .scenes import SMALL, written_scene


@pytest.fixture(scope="session", autouse=True)
def _one_blas_thread():
    """One BLAS thread for the tests and the gt3d processes they start (gt3dkit.threads: the
    suite runs two things at once; an idle-looking start must not give every process 2)."""
    import os

    os.environ.setdefault("GT3D_BLAS_THREADS", "1")
    from gt3dkit.threads import small_matrix_blas

    with small_matrix_blas():
        yield


@pytest.fixture(scope="session", autouse=True)
def _compiled_kernels(_one_blas_thread):
    """Every compiled kernel compiled (or loaded from numba's cache) once, before the first test,
    not inside whichever test happens to call one first (gt3dkit.commands.warmup; stale caches
    are dropped by gt3dkit.geom.kernel_cache)."""
    from gt3dkit.commands.warmup import warm_up

    warm_up()


@pytest.fixture(scope="session")
def multiviewx() -> Scene:
    return load_scene(bundled("multiviewx"))


@pytest.fixture(scope="session")
def small_native(tmp_path_factory: pytest.TempPathFactory):
    root = Path(tmp_path_factory.mktemp("small_native"))
    return written_scene(root, "native", **SMALL)

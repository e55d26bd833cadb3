"""Each annotation file is opened once a run: a WILDTRACK-layout folder indexed (the run may go in
windows) and then read whole reads its frame files and cameras from what the index kept
(``FrameIndex.ahead``), and the scene is the same as one read from nothing."""

from __future__ import annotations

import dataclasses
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.api import load_head, load_scene
from gt3dkit.calib.formats.grid import WILDTRACK
from gt3dkit.io.datasets import wildtrack
from gt3dkit.sim import Errors, simulate, write_scene


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("wt") / "in"
    sim = simulate("wildtrack", seed=3, frames=12, people=4, errors=Errors(dropped=0.1))
    write_scene(sim, root, "wildtrack")
    return root


def _counted(monkeypatch: pytest.MonkeyPatch) -> Counter[str]:
    """Every ``Path.read_bytes`` from now on, by path (the readers' only way to a frame file)."""
    count: Counter[str] = Counter()
    read = Path.read_bytes

    def counted(self: Path) -> bytes:
        count[str(self)] += 1
        return read(self)

    monkeypatch.setattr(Path, "read_bytes", counted)
    return count


def test_a_folder_indexed_then_read_whole_opens_each_frame_file_once(folder: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    count = _counted(monkeypatch)
    head = load_head(folder)
    assert head is not None and head.index is not None and head.index.ahead is not None
    scene = load_scene(head)
    frames = sorted((folder / "annotations_positions").glob("*.json"))
    assert frames and all(count[str(p)] == 1 for p in frames), count
    monkeypatch.undo()
    fresh = load_scene(folder)
    assert scene.files == fresh.files  # the same digests, in the same order
    for f in dataclasses.fields(fresh.obs):
        a, b = getattr(scene.obs, f.name), getattr(fresh.obs, f.name)
        if isinstance(b, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=f.name)
    assert scene.rig.names == fresh.rig.names
    np.testing.assert_array_equal(scene.rig.R, fresh.rig.R)


def test_what_the_index_keeps_is_bounded(folder: Path) -> None:
    """Past its bound (``READ_AHEAD_BYTES``) the index keeps nothing: such a run goes in windows,
    each reading its own frames."""
    g = WILDTRACK
    size = sum(p.stat().st_size for p in (folder / "annotations_positions").glob("*.json"))
    assert wildtrack.index(folder, g, keep_bytes=size).index.ahead is not None  # type: ignore[union-attr]
    assert wildtrack.index(folder, g, keep_bytes=size - 1).index.ahead is None  # type: ignore[union-attr]
    assert size < wildtrack.READ_AHEAD_BYTES

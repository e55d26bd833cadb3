"""Windows that read their own frames: a sequence indexed without its rows
(:func:`gt3dkit.api.load_head`) has each window's frames read where the window runs, on the
worker, not in the process that plans the run and sends the windows out. That process reads
only the cameras, the frame files' names and each frame's objects (for the plan), and the frames
the process noise and the box model are chosen on (:func:`gt3dkit.windows.noise.noise_sample`);
each window sends back, beside its rows, what the run's output says about the input it read
(:class:`FramesRead`), and :func:`completed` puts the sequence's together."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from gt3dkit.api import read_frames, with_box_model
from gt3dkit.io.datasets import checks
from gt3dkit.threads import roomy_malloc
from gt3dkit.types import FrameIndex, GroundTruth, Scene
from gt3dkit.windows.plan import Window

#: A window's job, whatever the function run on the window takes (:func:`read_then`).
Job = TypeVar("Job")


@dataclass(frozen=True)
class WindowRead:
    """Window ``window``'s scene, read from the input when called (picklable: a task's argument,
    a few kB): the frames ``lo..hi`` of the sequence ``head`` (without its index)."""

    head: Scene
    window: Window

    @classmethod
    def of(cls, head: Scene, window: Window) -> WindowRead:
        return cls(dataclasses.replace(head, index=None, truth=None), window)

    def __call__(self) -> tuple[Scene, tuple[str, ...]]:
        """The window's scene, checked, and the warnings of the checks of its own frames alone
        (a context's are its neighbour's own)."""
        w = self.window
        raw = read_frames(self.head, w.lo, w.hi, check=False)
        own = (raw.obs.frame >= w.first) & (raw.obs.frame <= w.last)
        said = checks.check_scene(dataclasses.replace(raw, obs=raw.obs.select(own)), whole=False).warnings
        return checks.check_scene(raw, whole=False), said


@dataclass(frozen=True)
class SampleRead:
    """The frames ``lo..hi`` of the sequence ``head`` (without its index), read when called where
    they are used (picklable): the process noise's sample, with the box model the head was given
    or the one its boxes choose (:func:`gt3dkit.api.with_box_model`), and a worker's warm-up
    frames."""

    head: Scene
    lo: int
    hi: int

    @classmethod
    def of(cls, head: Scene, lo: int, hi: int) -> SampleRead:
        return cls(dataclasses.replace(head, index=None, truth=None), lo, hi)

    def __call__(self) -> Scene:
        return with_box_model(read_frames(self.head, self.lo, self.hi),
                              str(self.head.load_options.get("box_model", "auto")))


def with_chosen_box_model(head: Scene, box_model: str, box_model_px: dict[str, float]) -> Scene:
    """``head`` with the box model its sample chose (:class:`SampleRead`), where it was not given."""
    if head.load_options.get("box_model", "auto") != "auto":
        return head
    return dataclasses.replace(head, box_model=box_model, box_model_px=box_model_px,
                               load_options={**head.load_options, "box_model": box_model})


@dataclass(frozen=True)
class FramesRead:
    """What a window read of the input, for the run's output: the digests of the files it read
    (``files``), and of its own frames (``first..last``): the annotation rows, whether one has a
    box, the truth the frames give (None: the sequence's truth file gives it, or none) and the
    warnings of its checks, each prefixed with its frames."""

    files: dict[str, str]
    rows: int
    boxes: bool
    truth: GroundTruth | None
    warnings: tuple[str, ...]


@dataclass(frozen=True)
class ReadPart:
    """A window's part (its function's result) with what it read (:func:`read_then`)."""

    part: Any
    read: FramesRead


def read_then(fn: Callable[[Job, Scene], object], job: Job, read: WindowRead) -> ReadPart:
    """``fn(job, scene)`` on the window's scene read by ``read`` (its truth and warnings left out,
    as :func:`gt3dkit.windows.plan.window_scene` leaves them), with what it read."""
    with roomy_malloc():  # as the window's run (a Dask worker's allocator hands memory back)
        scene, warnings = read()
    w = read.window
    own = (scene.obs.frame >= w.first) & (scene.obs.frame <= w.last)
    truth = scene.truth
    if truth is not None:
        truth = truth.select((truth.frame >= w.first) & (truth.frame <= w.last))
    said = FramesRead(scene.files, int(own.sum()), bool(scene.obs.has_box[own].any()), truth,
                      tuple(f"frames {w.first}-{w.last}: {x}" for x in warnings))
    return ReadPart(fn(job, dataclasses.replace(scene, truth=None, warnings=())), said)


def completed(head: Scene, reads: list[FramesRead], truth: Scene | None = None) -> Scene:
    """``head`` as the run found the sequence its windows read (``reads``, in frame order): every
    file's digest, the annotation rows, the warnings, and the truth: ``truth``'s (the sequence's
    truth file, :func:`gt3dkit.io.datasets.with_sequence_truth`) or the windows' own frames'."""
    files = dict(head.files)
    for r in reads:
        files.update(r.files)
    got = [r.truth for r in reads if r.truth is not None]
    if truth is not None and truth.truth is not None:
        files.update(truth.files)
        seq_truth: GroundTruth | None = truth.truth
    elif got:
        seq_truth = GroundTruth.concat(got)
    else:
        seq_truth = None
    index = head.index or FrameIndex(np.zeros(0, np.int64), np.zeros(0, np.int64))
    return dataclasses.replace(head, files=files, truth=seq_truth,
                               warnings=(*head.warnings, *(x for r in reads for x in r.warnings)),
                               index=dataclasses.replace(index, rows=sum(r.rows for r in reads),
                                                         boxes=any(r.boxes for r in reads)))

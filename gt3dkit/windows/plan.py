"""How a long sequence is cut into windows: the plan (``--window``, or sized by itself from the
memory a window needs), the windows' frames and their context, and the rows a window holds across
an object's long gaps (:class:`Bridge`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import numpy as np

from gt3dkit.arrays import unique_rows
from gt3dkit.fusion.ukf.jointupdate import covariance_entries
from gt3dkit.types import I64, Scene

#: Default context on each side of a window, seconds (at least :data:`MIN_OVERLAP_FRAMES`).
OVERLAP_S = 2.0


MIN_OVERLAP_FRAMES = 20


#: Bytes of a run's per-object-frame state beyond which ``gt3d reconstruct`` runs a sequence in
#: windows by itself (:func:`auto_plan`), and that a window holds at most: with the process's own
#: code and data (about 0.3 GB: the compiled kernels, the libraries, the loaded sequence) a run
#: stays under about 0.5 GB, what a laptop has to spare.
MEMORY_BUDGET_BYTES = 0.2e9


@dataclass(frozen=True)
class Plan:
    """How to run a long sequence: windows of ``size`` frames with ``overlap`` frames of context
    on each side (None: :func:`overlap_frames`), in ``jobs`` local processes or on the Dask
    scheduler at ``scheduler``."""

    size: int  # 0: one window per worker
    overlap: int | None = None
    jobs: int = 1
    scheduler: str | None = None
    why: str = ""  # why windows, when the user did not ask for them
    span: int = 0  # frames a window holds with its context (the tool's windows; 0: not fixed)


@dataclass(frozen=True)
class Window:
    """One window, as frame numbers: run on ``lo..hi``, keep ``first..last`` (inclusive)."""

    lo: int
    first: int
    last: int
    hi: int


def plan_windows(frames: I64, size: int, overlap: int, work: np.ndarray | None = None) -> list[Window]:
    """Windows of ``size`` frames of the grid ``frames`` (sorted), each with ``overlap`` frames of
    context on each side (fewer at the ends). With ``work (F,)``, each frame's objects: as many
    windows, cut where each holds an equal share of the object-frames instead of equal frames
    (a window's time and memory go with its object-frames, not its frames)."""
    n = len(frames)
    starts = list(range(0, n, max(size, 1)))
    if work is not None and len(starts) > 1 and float(np.sum(work)) > 0:
        before = np.cumsum(work) - work  # object-frames before each frame
        share = float(np.sum(work)) * np.arange(1, len(starts)) / len(starts)
        starts = [0, *np.unique(np.clip(np.searchsorted(before, share), 1, n - 1)).tolist()]
    out = []
    for a, nxt in zip(starts, [*starts[1:], n], strict=True):
        b = nxt - 1
        out.append(Window(int(frames[max(a - overlap, 0)]), int(frames[a]), int(frames[b]),
                          int(frames[min(b + overlap, n - 1)])))
    return out


def frame_work(scene: Scene, frames: I64) -> np.ndarray:
    """``(F,)`` the objects annotated in each frame of the grid ``frames``."""
    f, count = objects_per_frame(scene)
    work = np.zeros(len(frames))
    at = np.searchsorted(frames, f)
    ok = (at < len(frames)) & (frames[np.minimum(at, len(frames) - 1)] == f)
    work[at[ok]] = count[ok]
    return work


def balanced_size(n_frames: int, size: int, workers: int) -> int:
    """A window length near ``size`` (0: the whole) that cuts ``n_frames`` into a multiple of
    ``workers`` windows of equal length."""
    n_win = -(-n_frames // max(size or n_frames, 1))
    n_win = -(-n_win // max(workers, 1)) * max(workers, 1)
    return max(-(-n_frames // n_win), 1)


def overlap_frames(scene: Scene) -> int:
    """The default context: :data:`OVERLAP_S` seconds of the scene's frame grid."""
    f = np.asarray(scene.frames)
    step = float(np.median(np.diff(f))) if len(f) > 1 else 1.0
    return max(MIN_OVERLAP_FRAMES, int(np.ceil(OVERLAP_S * scene.fps / max(step, 1.0))))


def state_bytes(n_joints: int) -> float:
    """Bytes a window is budgeted per object-frame. With joints: measured 77 kB with 19 joints and
    8 cameras (peak RSS of runs of 1 000 frames of 3 people in windows of 50 to 1 000 frames:
    about 2.2 times the per-joint filters' covariance entries,
    :func:`gt3dkit.fusion.ukf.jointupdate.covariance_entries`;
    the joints' chains' states and the measurements' arrays, the bones' pass a fixed batch); the
    measurements' arrays grow with the cameras (~3.5 kB a camera with 19 joints by their
    shapes: 31 cameras add ~80 kB), so twice the 8-camera figure is budgeted. A box's 9-entry
    state, its covariance about 20 times over and ~11 kB of the rest, 13 kB (measured)."""
    if n_joints:
        return 2 * 2.2 * 8 * covariance_entries(n_joints)
    return 20.0 * 9 * 9 + 11e3


def objects_per_frame(scene: Scene) -> tuple[I64, I64]:
    """``(F,)`` the annotated frames and ``(F,)`` how many objects each holds (object-frames): the
    scene's rows', or its index's (:class:`gt3dkit.types.FrameIndex`)."""
    if scene.index is not None:
        return scene.index.frames, scene.index.objects
    keys = unique_rows(np.c_[scene.obs.frame, scene.obs.track_id])
    frames, count = np.unique(keys[:, 0], return_counts=True)
    return frames.astype(np.int64), count.astype(np.int64)


def auto_plan(scene: Scene) -> Plan | None:
    """Windows for a sequence whose state would exceed :data:`MEMORY_BUDGET_BYTES` whole (None:
    it fits): as many frames as hold that much state for the busiest frames (95th percentile of
    objects per frame), less the context."""
    _, count = objects_per_frame(scene)
    if not len(count):
        return None
    per_row = state_bytes(scene.obs.n_joints)
    if count.sum() * per_row <= MEMORY_BUDGET_BYTES:
        return None
    per_frame = float(np.percentile(count, 95))
    ov = overlap_frames(scene)
    fit = int(MEMORY_BUDGET_BYTES // (per_row * max(per_frame, 1.0)))
    return Plan(max(fit - 2 * ov, ov), why="the whole sequence would not fit in memory",
                span=max(fit, 3 * ov))


def occupied(windows: list[Window], scene: Scene, bridge: Bridge | None = None) -> list[Window]:
    """The ``windows`` that hold an annotation, with their context, or a ``bridge`` row
    (:meth:`Bridge.rows`): a gap in the annotations longer than a window and its context holds
    nothing to estimate; all when none does."""
    f = scene.index.frames if scene.index is not None else np.unique(scene.obs.frame)
    keep = [w for w in windows if np.searchsorted(f, w.hi, side="right") > np.searchsorted(f, w.lo)
            or (bridge is not None and bridge.rows(w).any())]
    return keep or windows


def window_scene(scene: Scene, lo: int, hi: int, extra: np.ndarray | None = None) -> Scene:
    """``scene`` cut to the frame numbers ``lo..hi`` (no truth: scored on the stitched tracks),
    and the rows ``extra (N,)`` (:meth:`Bridge.rows`), its frames reaching theirs."""
    keep = (scene.obs.frame >= lo) & (scene.obs.frame <= hi)
    if extra is not None:
        keep |= extra
        held = scene.obs.frame[keep]
        lo, hi = min(lo, int(held.min(initial=lo))), max(hi, int(held.max(initial=hi)))
    frames = np.asarray(scene.frames)
    return dataclasses.replace(scene, obs=scene.obs.select(keep),
                               frames=frames[(frames >= lo) & (frames <= hi)], truth=None, warnings=())


@dataclass(frozen=True)
class Bridge:
    """Each object's annotated frames of a scene, once for all its windows: ``key (K,)`` one
    sorted int64 per object and frame (``span`` apart per object), ``start, end (O,)`` each
    object's entries, ``entry (N,)`` each scene row's; :meth:`rows` of a window, ``count`` a
    side."""

    key: I64
    start: I64
    end: I64
    span: int
    entry: I64
    count: int

    @classmethod
    def of(cls, scene: Scene, count: int) -> Bridge:
        keys, entry = unique_rows(np.c_[scene.obs.track_id, scene.obs.frame], return_inverse=True)
        _, obj = np.unique(keys[:, 0], return_inverse=True)
        obj = obj.ravel().astype(np.int64)
        span = int(keys[:, 1].max(initial=0)) + 2
        start = np.searchsorted(obj, np.arange(int(obj.max(initial=-1)) + 1))
        return cls(obj * span + keys[:, 1], start, np.r_[start[1:], len(keys)], span, entry, count)

    def rows(self, w: Window) -> np.ndarray:
        """``(N,)`` the rows of each object whose annotations span some of the window ``w``'s own
        frames: its ``count`` annotated frames nearest before ``w.first`` and nearest after
        ``w.last``, wherever they are. Each such object then has its own context on both sides
        of the window's frames, as a window's context gives an object seen in every frame,
        however long it goes unannotated: its rows between annotations (``--every-frame``) are
        the whole run's (they were missing, or estimated from one side, where it went
        unannotated for longer than the context)."""
        base = np.arange(len(self.start)) * self.span

        def at(frame: int, side: Literal["left", "right"]) -> np.ndarray:  # past all its own entries
            return np.searchsorted(self.key, base + min(max(frame, 0), self.span - 1), side=side)

        first, last = at(w.first, "left"), at(w.last, "right")  # its entries from w.first, after w.last
        spans = ((first > self.start) & (last < self.end)) | (last > first)
        begin = np.r_[np.maximum(self.start, first - self.count)[spans], last[spans]]
        stop = np.r_[first[spans], np.minimum(self.end, last + self.count)[spans]]
        n = len(self.key) + 1
        inside = np.cumsum(np.bincount(begin, minlength=n) - np.bincount(stop, minlength=n))[:-1] > 0
        return inside[self.entry]


def sized_plan(plan: Plan, overlap: int, n_frames: int, workers: int) -> Plan:
    """``plan`` with the window length it runs: a window the tool sized holds ``span`` frames with
    its ``overlap``, and the tool's windows are a multiple of the workers, of equal lengths
    (:func:`balanced_size`); the user's ``--window`` stays as given."""
    if not plan.why:
        return plan
    size = max(plan.span - 2 * overlap, overlap) if plan.span else plan.size
    return dataclasses.replace(plan, size=balanced_size(n_frames, size, workers))

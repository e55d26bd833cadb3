"""Long sequences in overlapping time windows (``gt3d reconstruct --window FRAMES``): memory bounded
by the window, not the sequence, and one sequence over several workers (``--jobs N`` local
processes, or ``--scheduler ADDRESS``: the Dask cluster ``reconstruct-many`` uses).

* The process noise (``accel_sd``, ``position_sd``, ``shape_sd``, ``joint_accel_sd``) is chosen
  once, by the estimator's own maximum likelihood on the window with the most annotations, cut to
  at most :data:`NOISE_SAMPLE_OBJECT_FRAMES` object-frames around its middle
  (:func:`noise_sample`, :func:`chosen_noise`), of which the search's own draw of whole objects
  (:func:`searched_objects`); every window then runs with it fixed, so that the windows agree.
  Where the windows run on workers, so does the search; on a Dask cluster on every core of its
  worker, as the others wait for it (:func:`searched_on_worker`). ``gt3d reconstruct
  --scheduler`` connects before it loads the sequence, and the search's worker loads gt3dkit's
  imports and compiled kernels while it loads (:class:`Cluster`, :func:`warm_first`): the
  search starts warm. The other workers do that during the search (:func:`_warm_workers`), and
  the windows are cut and sent to the workers meanwhile (:func:`_cut_windows`).
* On a Dask cluster, a window (or the search) whose worker is lost runs again on the others: the
  window scenes scattered to that worker went with it, and are scattered again
  (:class:`Scattered`, :func:`_on_dask`); a local process that dies (``--jobs``) is an error
  naming its window (:func:`_in_pool`). :func:`connect_scheduler` refuses a scheduler without
  workers and workers without this gt3dkit.
* Each window's rows are written as soon as they are final (every window before it done:
  :class:`gt3dkit.io.writers.StreamedRows`), into the folder that replaces ``OUT`` at the end.
* The windows the tool chose (not a ``--window`` the user gave) are cut where each holds an
  equal share of the object-frames (:func:`plan_windows` with each frame's objects): a window's
  time and memory go with its object-frames, not its frames. Spread over workers they are made
  as many as a multiple of the workers (:func:`balanced_size`): no worker runs a last window
  alone while the others wait. On a Dask worker a window gives glibc's allocator room while it
  runs (:func:`gt3dkit.threads.roomy_malloc`).
* Each window runs the whole pipeline (:func:`gt3dkit.api.estimate_checked`: per-frame fits,
  identity, the estimator, the annotation QA) on its frames plus ``overlap`` frames of context
  on each side, and keeps its own frames' rows and findings (:func:`run_window`). A smoother's
  estimate at a frame depends on frames farther away through the motion model only, with a
  weight that decays geometrically with the distance; the context makes that weight negligible
  (``tests/test_windows.py`` holds the stitched result to the whole-sequence one). How fast it
  decays follows from the chosen process noise and the per-frame fits' noise (the steady-state
  filter's and smoother's gains, :func:`context_steps`): keypoint sequences take the context
  that brings it under :data:`CONTEXT_WEIGHT` (at least :data:`MIN_OVERLAP_FRAMES`, at most
  :data:`OVERLAP_S`), not :data:`OVERLAP_S` whole; a window the tool sized keeps its frames
  (its own frames grow as the context shrinks).
* A person's bone lengths (keypoints with bones) are found once for the whole sequence, as the
  whole run finds them: a first round over the windows runs each one's first pass and returns
  its own frames' bone samples (:func:`window_bones`: 17 bytes a bone and person-frame), pooled
  by person (:func:`pooled_bones`, :class:`gt3dkit.fusion.bones.PersonBones`); the second round
  runs the windows with them. On 1 000 frames of 3 people the windows' joints sat up to 0.46 of
  their sd from the whole run's with each window's own lengths, 0.18 with them pooled.
* The measurement noise levels (robust residual levels of the per-frame fits) are each window's
  own: measured on thousands of residuals they agree across windows to a few percent.

What a window cannot know: an identity split is found from the frames the window holds (a split
in a window's context is found again by its neighbour); segment numbers restart per window.

With ``--every-frame``, an object's rows between two of its annotations need both in the window:
each window also holds, of each object whose annotations span some of its own frames, the
object's ``overlap`` annotated frames nearest before and after them, wherever they are
(:meth:`Bridge.rows`). So an object unannotated for longer than a window and its context still
gets the whole run's rows across the stretch (they were missing, or estimated from one annotated
frame of one side and 6.7 sd off). A window that holds nothing, context and those included, is
left out (:func:`occupied`; it was an internal error).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gt3dkit.api import (
    bone_samples_checked,
    dense_frames,
    estimate_checked,
    process_noise_prepared,
    take_rows,
    tiny_scenes,
)
from gt3dkit.arrays import unique_rows
from gt3dkit.errors import EstimationError, InputError
from gt3dkit.fusion.base import make_estimator, over_time
from gt3dkit.fusion.bones import BoneSamples, PersonBones
from gt3dkit.fusion.jointupdate import covariance_entries
from gt3dkit.fusion.motion import position_step
from gt3dkit.fusion.noise import SEARCH_OBJECT_FRAMES, drawn_objects
from gt3dkit.fusion.ukf_config import UKFConfig
from gt3dkit.io.atomic import write_dir_atomically
from gt3dkit.io.writers import StreamedRows, write_result_files
from gt3dkit.qa.anomalies import Anomalies
from gt3dkit.threads import every_core, roomy_malloc, small_matrix_blas
from gt3dkit.types import I64, Downweighted, Scene, TrackSet
from gt3dkit.version import __version__

#: What a window's rows and findings go to as it finishes (:func:`reconstruct_windowed`): its index,
#: its tracks and its QA rows.
OnPart = Callable[[int, TrackSet, list[tuple[Any, ...]]], None]
#: Frames each Dask worker but the first estimates first, to load its imports and kernels
#: (:func:`_warm_workers`).
WARM_FRAMES = 3
#: Times a window is submitted to a Dask cluster whose workers holding its scene are lost, at most
#: (:func:`_on_dask`).
WINDOW_TRIES = 3
#: The process-noise settings chosen once for all windows.
PROCESS_NOISE = ("accel_sd", "position_sd", "shape_sd", "joint_accel_sd")
#: Default context on each side of a window, seconds (at least :data:`MIN_OVERLAP_FRAMES`).
OVERLAP_S = 2.0
MIN_OVERLAP_FRAMES = 20
#: The weight a frame beyond a window's context keeps in the window's estimates, at most (the
#: context of keypoint sequences, :func:`context_steps`; 1e-3: a start state off by 20 of its
#: sds, as an unknown velocity is, moves the first kept frame by 0.02 sd).
CONTEXT_WEIGHT = 1e-3
#: The per-frame joint fits' sd (percentile over joints and frames) the context is sized for.
CONTEXT_SD_PERCENTILE = 90.0
#: Object-frames the process-noise search's sample holds at most (of which the search draws its
#: whole objects, :func:`searched_objects`): thousands of object-frames fix a maximum-likelihood
#: noise level to a few percent, and the search is the one step the other workers wait for.
NOISE_SAMPLE_OBJECT_FRAMES = 20_000
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
    :func:`gt3dkit.fusion.jointupdate.covariance_entries`;
    the joints' chains' states and the measurements' arrays, the bones' pass a fixed batch); the
    measurements' arrays grow with the cameras (~3.5 kB a camera with 19 joints by their
    shapes: 31 cameras add ~80 kB), so twice the 8-camera figure is budgeted. A box's 9-entry
    state, its covariance about 20 times over and ~11 kB of the rest, 13 kB (measured)."""
    if n_joints:
        return 2 * 2.2 * 8 * covariance_entries(n_joints)
    return 20.0 * 9 * 9 + 11e3


def objects_per_frame(scene: Scene) -> tuple[I64, I64]:
    """``(F,)`` the annotated frames and ``(F,)`` how many objects each holds (object-frames)."""
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
    f = np.unique(scene.obs.frame)
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

        def at(frame: int, side: str) -> np.ndarray:  # within each object's entries: past all its own
            return np.searchsorted(self.key, base + min(max(frame, 0), self.span - 1),
                                   side=side)  # type: ignore[call-overload]

        first, last = at(w.first, "left"), at(w.last, "right")  # its entries from w.first, after w.last
        spans = ((first > self.start) & (last < self.end)) | (last > first)
        begin = np.r_[np.maximum(self.start, first - self.count)[spans], last[spans]]
        stop = np.r_[first[spans], np.minimum(self.end, last + self.count)[spans]]
        n = len(self.key) + 1
        inside = np.cumsum(np.bincount(begin, minlength=n) - np.bincount(stop, minlength=n))[:-1] > 0
        return inside[self.entry]


def noise_sample(scene: Scene, windows: list[Window], limit: int = NOISE_SAMPLE_OBJECT_FRAMES
                 ) -> tuple[int, int]:
    """The frames ``lo, hi`` the process noise is chosen on: the window (with its context) holding
    the most object-frames, cut around its middle to at most ``limit`` of them."""
    frames, count = objects_per_frame(scene)
    inside = [(frames >= w.lo) & (frames <= w.hi) for w in windows]
    k = int(np.argmax([count[m].sum() for m in inside]))
    f, c = frames[inside[k]], count[inside[k]]
    if c.sum() <= limit:
        return windows[k].lo, windows[k].hi
    cum = np.cumsum(c)
    a = int(np.searchsorted(cum, (cum[-1] - limit) / 2.0, side="right"))
    b = int(np.searchsorted(cum, cum[a] - c[a] + limit, side="right")) - 1
    return int(f[a]), int(f[max(b, a)])


def chosen_noise(scene: Scene, windows: list[Window], estimator: str, config: dict[str, Any],
                 runner: Any = None) -> Callable[[], tuple[dict[str, float], int | None]]:
    """The process noise every window runs with (the settings ``config`` gives, the others the
    estimator's own choice on :func:`noise_sample`'s frames, :func:`sample_noise`) and the
    context in frames that noise needs (:func:`joint_context`; None: the default's), when the
    returned function is called: found in this process, or where the windows run (``runner``:
    the Dask client or the process pool, whose workers need the estimator's compiled kernels
    anyway), this process free to go on meanwhile."""
    lo, hi = noise_sample(scene, windows)
    sample = searched_objects(window_scene(scene, lo, hi))
    f = np.asarray(scene.frames)
    step_s = (float(np.median(np.diff(f))) if len(f) > 1 else 1.0) / scene.fps
    if runner is None:
        found = sample_noise(sample, estimator, config, step_s)
        return lambda: found
    if hasattr(runner, "scatter"):  # a Dask client
        return _search_on_dask(runner, sample, estimator, config, step_s)
    return runner.submit(sample_noise, sample, estimator, config, step_s).result


def _search_on_dask(client: Any, sample: Scene, estimator: str, config: dict[str, Any], step_s: float
                    ) -> Callable[[], tuple[dict[str, float], int | None]]:
    """:func:`searched_on_worker` of ``sample`` (scattered as data, not inside the task graph) on
    the Dask ``client``'s first worker, warmed as the sequence loaded (:class:`Cluster`); the
    result when the returned function is called. If that worker is lost, the search runs again on
    any other (:func:`_on_dask`)."""
    first = _workers(client)[:1] or None
    future = client.submit(searched_on_worker, client.scatter(sample, hash=False, workers=first),
                           estimator, config, step_s, workers=first, pure=False)

    def again(_: int) -> tuple[Any, ...]:  # on any worker
        return searched_on_worker, client.scatter(sample, hash=False), estimator, config, step_s

    return lambda: next(_on_dask(client, again, 1, lambda _: "the process-noise search", {future: 0}))[1]


def searched_objects(sample: Scene, budget: int = SEARCH_OBJECT_FRAMES) -> Scene:
    """``sample`` cut to the objects the noise search runs on, drawn before their per-frame fits
    (:func:`gt3dkit.fusion.noise.drawn_objects`, whole objects up to ``budget``
    object-frames): the other objects' fits would only feed the search's provisional values.
    On 4 000 frames of 40 people that halved the search (2.4 s to 1.2 s), the same noise chosen."""
    keys = unique_rows(np.c_[sample.obs.frame, sample.obs.track_id])
    ids, count = np.unique(keys[:, 1], return_counts=True)
    if count.sum() <= budget:
        return sample
    keep = np.isin(sample.obs.track_id, ids[drawn_objects(count, budget)])
    return dataclasses.replace(sample, obs=sample.obs.select(keep))


def sample_noise(sample: Scene, estimator: str, config: dict[str, Any], step_s: float
                 ) -> tuple[dict[str, float], int | None]:
    """:func:`chosen_noise` on its ``sample`` of the sequence (frames ``step_s`` seconds apart)."""
    given = {k: config[k] for k in PROCESS_NOISE if config.get(k) is not None}
    with small_matrix_blas(), roomy_malloc():
        est = make_estimator(estimator, **config)
        found, pre = process_noise_prepared(sample, est)  # the search alone, where the estimator has one
        if found is None:
            tracks, _ = estimate_checked(sample, est, qa=False)
            found = {k: v for k, v in tracks.info.get("params", {}).items() if v is not None}
    fields = {f.name for f in dataclasses.fields(est.config)} if hasattr(est, "config") else set()
    chosen = {k: float(found[k]) for k in PROCESS_NOISE if k in fields and found.get(k) is not None}
    noise = {**chosen, **given}
    return noise, joint_context(pre, noise, step_s)


def searched_on_worker(sample: Scene, estimator: str, config: dict[str, Any], step_s: float
                       ) -> tuple[dict[str, float], int | None]:
    """:func:`sample_noise` on a Dask worker, on every core of its machine (the compiled loops'
    threads, :func:`gt3dkit.threads.every_core`; a worker's task thread gets one): every worker
    waits for it. On the 4 000-frame box scene's sample, on a warm worker of a 2-core machine:
    1.34-1.96 s on one thread, 1.25-1.37 s on both cores (4 runs each), the same noise."""
    with every_core():
        return sample_noise(sample, estimator, config, step_s)


def context_steps(accel_sd: float, meas_sd_m: float, dt_s: float, weight: float = CONTEXT_WEIGHT) -> int:
    """Steps after which a measurement's weight falls under ``weight`` in a constant-velocity
    filter and RTS smoother (white acceleration ``accel_sd`` m/s^2/sqrt(Hz), the motion model of
    :mod:`gt3dkit.fusion.motion`; position measured with sd ``meas_sd_m`` every ``dt_s``), at
    their steady state: with ``P`` the predicted covariance (the Riccati equation's fixed point)
    and ``K`` the gain, the filter forgets its start by ``(I - K H) F`` a step and the smoother
    weighs the future by ``G = P_f F^T P^-1`` a step; ``rho`` the larger spectral radius of the
    two, ``ceil(log weight / log rho)``."""
    from scipy.linalg import solve_discrete_are

    F, Q = position_step(dt_s, accel_sd)
    H = np.array([[1.0, 0.0]])
    Rm = np.array([[max(meas_sd_m, 1e-9) ** 2]])
    P = solve_discrete_are(F.T, H.T, Q, Rm)
    K = P @ H.T / (H @ P @ H.T + Rm)
    Pf = (np.eye(2) - K @ H) @ P
    rho = max(float(np.abs(np.linalg.eigvals((np.eye(2) - K @ H) @ F)).max()),
              float(np.abs(np.linalg.eigvals(Pf @ F.T @ np.linalg.inv(P))).max()))
    if not 0.0 < rho < 1.0:
        return 10**9
    return int(np.ceil(np.log(weight) / np.log(rho)))


def joint_context(pre: Any, noise: dict[str, float], step_s: float) -> int | None:
    """The context in frames a keypoint sequence (no boxes) needs: :func:`context_steps` with
    the chosen ``joint_accel_sd`` and the per-frame joint fits' sd (the largest axis, the
    :data:`CONTEXT_SD_PERCENTILE` percentile over joints and frames of the preparation ``pre``),
    divided by the share of joint-frames with a fit (a joint unseen for a while forgets nothing
    meanwhile); frames ``step_s`` seconds apart. None (the default context) for boxes, or when
    the preparation tells nothing."""
    q = noise.get("joint_accel_sd")
    if pre is None or q is None or getattr(pre, "use_box", True) or getattr(pre, "kpt0_cov", None) is None:
        return None
    var = np.diagonal(pre.kpt0_cov, axis1=-2, axis2=-1).max(axis=-1)  # (R, J) m^2
    seen = np.isfinite(pre.kpt0).all(axis=-1) & np.isfinite(var)
    if not seen.any():
        return None
    sd = float(np.sqrt(np.percentile(var[seen], CONTEXT_SD_PERCENTILE)))
    steps = context_steps(float(q), sd, step_s)
    return int(np.ceil(steps / float(seen.mean())))


@dataclass(frozen=True)
class WindowJob:
    """What a worker needs for one window besides its scene (picklable)."""

    window: Window
    estimator: str
    config: dict[str, Any]
    every_frame: int | None
    bones: PersonBones | None = None  # every person's bones, pooled over the windows


def run_window(job: WindowJob, scene: Scene) -> tuple[TrackSet, list[tuple[Any, ...]]]:
    """One window's rows and QA findings in its own frames, from its ``scene`` (the persons' bones
    ``job.bones`` where given: the window's own ids only, its split pieces' ids are its own)."""
    w = job.window
    with small_matrix_blas(), roomy_malloc():
        est = make_estimator(job.estimator, **job.config)
        if job.bones is not None:
            est.bones = job.bones.of(np.unique(scene.obs.track_id))
        tracks, qa = estimate_checked(scene, est, job.every_frame)
    keep = (tracks.frame >= w.first) & (tracks.frame <= w.last)
    d = tracks.downweighted
    if d is not None:
        d = _downweighted_rows(d, (d.frame >= w.first) & (d.frame <= w.last))
    out = take_rows(dataclasses.replace(tracks, downweighted=d), keep)
    return out, sorted((r for r in qa.rows if w.first <= r[0] <= w.last), key=finding_order)


def finding_order(row: tuple[Any, ...]) -> tuple[Any, ...]:
    """A QA finding's place in ``anomalies.csv``: by frame, camera, id (a window's, and so the
    windows' in order: :class:`gt3dkit.io.writers.StreamedRows`)."""
    return row[0], str(row[1]), row[2]


def window_bones(job: WindowJob, scene: Scene) -> tuple[BoneSamples | None, I64, float]:
    """One window's first-pass bones in its own frames, the ids it splits, from its ``scene``
    (:func:`gt3dkit.api.bone_samples_checked`; None: its estimator ties no bones), and the
    seconds it took."""
    t0 = time.perf_counter()
    w = job.window
    if job.every_frame is not None:
        scene = dense_frames(scene, job.every_frame or None)
    with small_matrix_blas(), roomy_malloc():
        s, split = bone_samples_checked(scene, make_estimator(job.estimator, **job.config))
    s = None if s is None else s.take((s.frame >= w.first) & (s.frame <= w.last))
    return s, split, time.perf_counter() - t0


def pooled_bones(parts: list[tuple[BoneSamples | None, I64, float]], config: dict[str, Any]
                 ) -> PersonBones | None:
    """Every person's bones from the windows' first-pass bones and split ids ``parts``
    (:func:`window_bones`), as the whole sequence's run finds them (its config's
    ``bone_sd_floor_m``, ``bone_sd_m``): of the ids no window splits (a split id's pieces may
    be different people: each window keeps its own pieces' bones). None: no window ties any."""
    got = [p[0] for p in parts if p[0] is not None]
    if not got:
        return None
    split = np.concatenate([p[1] for p in parts])
    s = BoneSamples.joined(got)
    s = s.take(~np.isin(s.obj, split))
    cfg = UKFConfig(**{k: config[k] for k in ("bone_sd_floor_m", "bone_sd_m") if k in config})
    return PersonBones.pooled(s, cfg.bone_sd_floor_m, cfg.bone_sd_m)


def _downweighted_rows(d: Downweighted, keep: np.ndarray) -> Downweighted:
    return Downweighted(**{f.name: getattr(d, f.name)[keep] for f in dataclasses.fields(d)})


def stitch(parts: list[tuple[TrackSet, list[tuple[Any, ...]]]], windows: list[Window], plan: Plan,
           overlap: int, noise: dict[str, float]) -> tuple[TrackSet, Anomalies]:
    """The windows' rows and findings as one run's (rows by frame, then id)."""
    ts = [p[0] for p in parts]
    cat = {k: np.concatenate([getattr(t, k) for t in ts]) for k in
           ("frame", "track_id", "center_world", "semi_axes", "center_sd", "n_views", "kpt_world", "kpt_sd")}
    order = np.lexsort((cat["track_id"], cat["frame"]))
    ds = [t.downweighted for t in ts if t.downweighted is not None]
    down = Downweighted(**{f.name: np.concatenate([getattr(d, f.name) for d in ds])
                           for f in dataclasses.fields(Downweighted)}) if ds else None
    info = dict(ts[0].info)
    info["windows"] = {
        "count": len(windows), "frames": plan.size, "overlap_frames": overlap, "why": plan.why,
        "cut": "equal object-frames" if plan.why else "equal frames",
        "windows": [dataclasses.asdict(w) for w in windows], "process_noise": noise,
        "note": "each window run on its frames plus context, its own frames kept; the process noise "
                "chosen once (gt3dkit.windows)"}
    info["seconds"] = float(sum(t.info.get("seconds", 0.0) for t in ts))
    info["object_frames"] = int(len(order))
    for key in ("robust",):
        if key in info and isinstance(info[key], dict) and down is not None:
            info[key] = {**info[key], "downweighted": int(np.sum(down.weight > 0)),
                         "rejected": int(np.sum(down.weight == 0))}
    segs = [s for t in ts for s in t.info.get("segments", [])]
    if segs:
        info["segments"] = segs
    rows = [r for p in parts for r in p[1]]  # each window's sorted, the windows in frame order
    qa = Anomalies(rows)
    info["qa"] = {"anomalies": qa.counts(), "file": "anomalies.csv"}
    tracks = TrackSet(**{k: v[order] for k, v in cat.items()}, info=info, downweighted=down)
    return tracks, qa


def connect_scheduler(address: str) -> Any:
    """A Dask client of the scheduler at ``address`` (``--scheduler``, here and in
    ``reconstruct-many``) with at least one worker, or InputError naming ``--scheduler``. It waits
    for the connection, and then for a first worker, as long as Dask's own
    ``distributed.comm.timeouts.connect`` says (30 s unless the user's Dask configuration or
    ``DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT`` says otherwise): a scheduler no worker joins
    made ``reconstruct-many`` wait for ever and ``reconstruct`` fail inside Dask. Every worker
    there must have this gt3dkit (its version; a worker without it, or with another, failed
    inside the first task or wrote another output)."""
    import dask
    from dask.utils import parse_timedelta
    from distributed import Client

    wait = parse_timedelta(dask.config.get("distributed.comm.timeouts.connect"), default="s")
    check_scheduler_address(address)
    try:
        client = Client(address)
    except (OSError, TimeoutError) as e:
        raise InputError("--scheduler", f"cannot reach the Dask scheduler at {address} ({e})") from None
    try:
        client.wait_for_workers(1, timeout=wait)
        # a worker's error: no gt3dkit there to load the function with
        others = {w: v if isinstance(v, str) else "none" for w, v in
                  sorted(client.run(_gt3dkit_here, on_error="return").items()) if v != __version__}
    except TimeoutError:
        client.close()
        raise InputError("--scheduler", f"the Dask scheduler at {address} has no worker (none joined "
                                        f"in {wait:g} s)") from None
    if others:  # the windows must run the code this process runs (the same output)
        client.close()
        w, v = next(iter(others.items()))
        raise InputError("--scheduler", f"the Dask worker {w} has gt3dkit {v}, this process {__version__} "
                                        f"({len(others)} worker(s) differ): install this gt3dkit on every "
                                        "worker")
    return client


def check_scheduler_address(address: str) -> None:
    """InputError naming ``--scheduler`` unless ``address`` is one Dask can connect to: a known
    scheme (``tcp://`` when none is given) and, for the network schemes, a host and a port
    (Dask's own parsers; they raised inside the client as an internal error)."""
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import backends

    try:
        scheme, loc = parse_address(address)
        if scheme not in backends:
            raise ValueError(f"unknown address scheme {scheme!r} (known: {', '.join(sorted(backends))})")
        if scheme in ("tcp", "tls", "ws", "wss"):
            host, _ = parse_host_port(loc)
            if not host:
                raise ValueError("no host")
    except ValueError as e:
        raise InputError("--scheduler", f"{address!r} is not a Dask scheduler address ({e}): give "
                                        "tcp://HOST:PORT") from None


def _gt3dkit_here() -> str:
    """The version of gt3dkit the process running this has (on each Dask worker, by
    :func:`connect_scheduler`; a worker without gt3dkit fails to load this function)."""
    return __version__


class Cluster:
    """The Dask scheduler at ``address`` (``--scheduler``): a client, connected at once (an
    unreachable scheduler is an :class:`InputError` naming ``--scheduler``). With ``loading``
    (``gt3d reconstruct`` makes it before it loads the sequence) its first worker, the one the
    noise search runs on (:func:`chosen_noise`), loads gt3dkit's imports and compiled kernels
    while the sequence loads (:func:`warm_first`); without, it would only do that before the
    search. The others do it during the search, on the sequence's own first frames
    (:func:`_warm_workers`): on 2 cores, warming them all during the loading slowed it (4.3 s
    against 3.4 s, means of 4 runs), and so did connecting in a thread beside it with the second
    worker warming (4.5 s against 3.9 s; connecting first took 0.3-0.45 s). A context manager."""

    def __init__(self, address: str, estimator: str, config: dict[str, Any], loading: bool = True) -> None:
        self.client = connect_scheduler(address)
        try:
            first = _workers(self.client)[:1] if loading else []
            # held until closed: a future let go is a task cancelled
            self._warming = [self.client.submit(warm_first, estimator, config, workers=first,
                                                allow_other_workers=False, pure=False)] if first else []
        except BaseException:
            self.client.close()
            raise

    def close(self) -> None:
        self._warming = []
        self.client.close()

    def __enter__(self) -> Cluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def reconstruct_windows(scene: Scene, estimator: str, plan: Plan, out: str | None = None,
                        extra_meta: dict[str, Any] | None = None, every_frame: int | None = None,
                        on_window: Callable[[int, int], None] | None = None, cluster: Cluster | None = None,
                        **config: Any) -> TrackSet:
    """:func:`gt3dkit.api.reconstruct` of a long sequence by ``plan``; writes ``out`` if given,
    atomically as one run: each window's rows as soon as they are final (the windows before it
    done, :class:`gt3dkit.io.writers.StreamedRows`; on the 4 000-frame box scene, what is left
    for after the last window went from 0.6-1.0 s of writing to its rows and 0.02 s of
    ``meta.json``), into a folder that replaces ``out`` at the end. ``cluster``:
    ``plan.scheduler``'s, connected early by the caller (who closes it)."""
    if out is None:
        return reconstruct_windowed(scene, estimator, plan, every_frame, on_window, cluster, **config)[0]
    made: list[TrackSet] = []

    def run(tmp: Path) -> None:
        with StreamedRows(tmp) as rows:
            tracks, qa = reconstruct_windowed(scene, estimator, plan, every_frame, on_window, cluster,
                                              rows.add, **config)
        write_result_files(tmp, scene, tracks, extra_meta, qa, streamed=True)
        made.append(tracks)

    write_dir_atomically(Path(out), run)
    return made[0]


def reconstruct_windowed(scene: Scene, estimator: str, plan: Plan, every_frame: int | None = None,
                         on_window: Callable[[int, int], None] | None = None, cluster: Cluster | None = None,
                         on_part: OnPart | None = None, **config: Any) -> tuple[TrackSet, Anomalies]:
    """``scene`` in windows (:mod:`gt3dkit.windows`, ``plan``): the stitched tracks and QA
    findings; ``on_window(done, total)`` as the windows start (0) and after each one; ``cluster``
    as :func:`reconstruct_windows`; ``on_part(k, tracks, anomaly_rows)`` with each window's final
    rows and findings as it finishes (:func:`run_window`)."""
    if not over_time(estimator):
        raise InputError("--window", f"the {estimator} fits each frame on its own: it needs no window")
    ov = overlap_frames(scene) if plan.overlap is None else plan.overlap
    own = cluster is None and bool(plan.scheduler)
    if own:
        cluster = Cluster(str(plan.scheduler), estimator, config, loading=False)
    try:
        client = cluster.client if cluster is not None else None
        workers = len(client.scheduler_info()["workers"]) if client is not None else plan.jobs
        frames = np.asarray(scene.frames, dtype=np.int64)
        windows = plan_windows(frames, _sized(plan, ov, len(frames), workers).size, ov)
        with contextlib.ExitStack() as stack:
            runner = client
            if client is None and plan.jobs > 1 and len(windows) > 1:
                runner = stack.enter_context(_process_pool(min(plan.jobs, len(windows))))
            warming = _warm_workers(client, scene, estimator, config) if client is not None else []
            noise_when_done = chosen_noise(scene, windows, estimator, config, runner)
            # meanwhile the windows, cut (and sent to the cluster) for the context the noise leaves
            # as it is (always, for boxes), again if it needs less; each frame's objects and each
            # object's annotated frames (--every-frame) found once for both
            work = frame_work(scene, frames) if plan.why else None
            index = Bridge.of(scene, ov) if every_frame is not None else None
            windows, bridge, scenes = _cut_windows(scene, _sized(plan, ov, len(frames), workers), ov,
                                                   client, index, work)
            noise, needed = noise_when_done()
            if plan.overlap is None and needed is not None and needed < ov:  # the noise's own context
                ov = max(needed, MIN_OVERLAP_FRAMES)
                windows, bridge, scenes = _cut_windows(scene, _sized(plan, ov, len(frames), workers), ov,
                                                       client, index, work)
            plan = _sized(plan, ov, len(frames), workers)
            like = WindowJob(windows[0], estimator, {**config, **noise}, every_frame)
            done = on_window or (lambda k, n: None)
            n = len(windows)
            if client is None and n == 1:
                runner = None
            if ties_bones(scene, estimator, config) and n > 1:  # two rounds: the bones, then the rest
                samples = _run_windows(scenes, windows, like, runner, lambda k, _: done(k, 2 * n),
                                       window_bones)
                like = dataclasses.replace(like, bones=pooled_bones(samples, config))
                parts = _run_windows(scenes, windows, like, runner, lambda k, _: done(n + k, 2 * n),
                                     on_part=on_part)
            else:
                samples = []
                parts = _run_windows(scenes, windows, like, runner, done, on_part=on_part)
            del warming
    finally:
        if own and cluster is not None:
            cluster.close()
    tracks, qa = stitch(parts, windows, plan, ov, noise)
    if like.bones is not None:  # every person's, not the first window's
        tracks.info["bones"] = {**like.bones.lengths.info(like.bones.ids),
                                "pooled": "over every window's own frames (gt3dkit.windows)"}
    if samples:  # the bones' round is the estimator's time too
        first = float(sum(p[2] for p in samples))
        tracks.info["seconds"] += first
        tracks.info["windows"]["bones_round_seconds"] = first
    return tracks, qa


def _sized(plan: Plan, overlap: int, n_frames: int, workers: int) -> Plan:
    """``plan`` with the window length it runs: a window the tool sized holds ``span`` frames with
    its ``overlap``, and the tool's windows are a multiple of the workers, of equal lengths
    (:func:`balanced_size`); the user's ``--window`` stays as given."""
    if not plan.why:
        return plan
    size = max(plan.span - 2 * overlap, overlap) if plan.span else plan.size
    return dataclasses.replace(plan, size=balanced_size(n_frames, size, workers))


def ties_bones(scene: Scene, estimator: str, config: dict[str, Any]) -> bool:
    """Whether ``estimator`` ties the joints of ``scene`` by its persons' bones (then the windows
    pool theirs first: :func:`window_bones`, :func:`pooled_bones`)."""
    est = make_estimator(estimator, **config)
    return (callable(getattr(est, "bone_samples", None)) and scene.obs.n_joints > 0
            and bool(getattr(est.config, "bones", False)))


def _process_pool(workers: int) -> Any:
    """``workers`` local processes (spawned: no fork of a process that holds threads)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    return ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"))


def warm_first(estimator: str, config: dict[str, Any]) -> None:
    """:func:`warm_worker` on two tiny simulated scenes, boxes and joints
    (:func:`gt3dkit.api.tiny_scenes`): the first Dask worker's, while the sequence loads
    (:class:`Cluster`)."""
    for scene in tiny_scenes():
        warm_worker(scene, estimator, config)


def warm_worker(scene: Scene, estimator: str, config: dict[str, Any]) -> None:
    """Estimate ``scene`` (a few frames) and drop the result: this process's imports and compiled
    kernels loaded (:func:`_warm_workers`, :func:`warm_first`); an error is left to the windows
    to find."""
    with contextlib.suppress(Exception), small_matrix_blas():
        estimate_checked(scene, make_estimator(estimator, **config))


def _warm_workers(client: Any, scene: Scene, estimator: str, config: dict[str, Any]) -> list[Any]:
    """The sequence's first annotated frames estimated and dropped on the Dask ``client``'s
    workers but the first (:func:`warm_worker`): while the first searches the noise
    (:func:`chosen_noise`), the others load their imports and compiled kernels (a second or two
    a process) instead of on their first window. Their futures, to hold until the windows run
    (a future let go is a task cancelled)."""
    f = np.unique(scene.obs.frame)[:WARM_FRAMES]  # the first annotated frames
    if not len(f):
        return []
    tiny = window_scene(scene, int(f[0]), int(f[-1]))  # small: inside the task
    return [client.submit(warm_worker, tiny, estimator, config, workers=[w], allow_other_workers=False,
                          pure=False) for w in _workers(client)[1:]]


def _workers(client: Any) -> list[str]:
    """The Dask ``client``'s workers' addresses, sorted."""
    return sorted(client.scheduler_info()["workers"])


def _cut_windows(scene: Scene, plan: Plan, overlap: int, client: Any, index: Bridge | None,
                 work: np.ndarray | None) -> tuple[list[Window], Bridge | None, Callable[[int], Any]]:
    """The windows of ``plan`` with ``overlap`` frames of context, the rows between annotations
    they bring (``--every-frame``: ``index``, :class:`Bridge`, with ``overlap`` a side) and their
    scenes (:func:`_window_scenes`). The tool's windows hold equal object-frames (``work``, each
    frame's objects: the workers finish together); a ``--window`` is cut as given (None)."""
    frames = np.asarray(scene.frames, dtype=np.int64)
    bridge = dataclasses.replace(index, count=overlap) if index is not None else None
    windows = occupied(plan_windows(frames, plan.size, overlap, work), scene, bridge)
    return windows, bridge, _window_scenes(scene, windows, client, bridge)


def _window_scenes(scene: Scene, windows: list[Window], client: Any, bridge: Bridge | None = None
                   ) -> Callable[[int], Any]:
    """Window ``k``'s scene: made when asked (one window's at a time in this process), or on a
    Dask ``client`` scattered once to the cluster as data (not inside the task graph) and its
    future given to every round (:class:`Scattered`); with the ``bridge`` rows (the rows between
    annotations, ``--every-frame``)."""
    def cut(w: Window) -> Scene:
        return window_scene(scene, w.lo, w.hi, bridge.rows(w) if bridge is not None else None)

    if client is None:
        return lambda k: cut(windows[k])
    return Scattered(client, [functools.partial(cut, w) for w in windows])


class Scattered:
    """Scenes scattered to a Dask cluster as data, each one's future when called with its index;
    a scene whose worker was lost (scattered data cannot be recomputed) is cut and scattered
    again (:func:`_run_windows` then runs its window again)."""

    def __init__(self, client: Any, cuts: list[Callable[[], Scene]]) -> None:
        self.client, self.cuts = client, cuts
        self.futures = [self._sent(k) for k in range(len(cuts))]

    def __call__(self, k: int) -> Any:
        if self.futures[k].status != "finished":
            self.futures[k] = self._sent(k)
        return self.futures[k]

    def _sent(self, k: int) -> Any:
        """Scene ``k`` scattered; again a second later if the worker it went to was just lost
        (the scheduler drops it meanwhile), up to :data:`WINDOW_TRIES` times."""
        for attempt in range(1, WINDOW_TRIES + 1):
            try:
                return self.client.scatter(self.cuts[k](), hash=False)
            except OSError as e:  # distributed's CommClosedError
                if attempt == WINDOW_TRIES:
                    raise EstimationError("--scheduler", f"could not send a window's frames to the Dask "
                                                         f"workers ({e})") from None
                time.sleep(1.0)


def _run_windows(scenes: Callable[[int], Any], windows: list[Window], like: WindowJob, runner: Any,
                 done: Callable[[int, int], None], fn: Callable[[WindowJob, Scene], Any] = run_window,
                 on_part: OnPart | None = None) -> list[Any]:
    """Every window's ``fn`` (:func:`run_window`; ``like`` with each window's frames, ``scenes(k)``
    its scene): on the Dask client or the process pool ``runner``, or one after the other in this
    process (None); ``done(k, n)`` as they start (0) and finish, ``on_part(k, *part)`` with window
    ``k``'s part as it comes. On Dask, a window whose worker was lost runs again on the others
    (:func:`_on_dask`)."""
    done(0, len(windows))
    parts: list[Any] = [None] * len(windows)
    got = on_part or (lambda k, *part: None)
    if runner is None:
        for k, w in enumerate(windows):
            parts[k] = fn(dataclasses.replace(like, window=w), scenes(k))
            got(k, *parts[k])
            done(k + 1, len(windows))
        return parts
    if hasattr(runner, "scatter"):  # a Dask client
        finished = _on_dask(runner, lambda k: (fn, dataclasses.replace(like, window=windows[k]), scenes(k)),
                            len(windows), lambda k: f"window {k + 1} (frames {windows[k].first}-"
                                                    f"{windows[k].last})")
    else:
        futures = {runner.submit(fn, dataclasses.replace(like, window=w), scenes(k)): k
                   for k, w in enumerate(windows)}
        finished = _in_pool(futures, windows)
    for n, (k, part) in enumerate(finished, 1):
        parts[k] = part
        got(k, *part)
        done(n, len(windows))
    return parts


def _in_pool(futures: dict[Any, int], windows: list[Window]) -> Iterator[tuple[int, Any]]:
    """``(k, result)`` of the local process pool's ``futures`` (window ``k`` each) as they finish;
    a process of the pool that died (the out-of-memory killer, a signal) is an
    :class:`EstimationError` naming the window it was running, not an internal error."""
    from concurrent.futures import as_completed
    from concurrent.futures.process import BrokenProcessPool

    for f in as_completed(futures):
        k = futures[f]
        try:
            yield k, f.result()
        except BrokenProcessPool:
            w = windows[k]
            raise EstimationError("--jobs", f"a worker process died (out of memory? a shorter --window or "
                                            f"fewer --jobs need less) with window {k + 1} (frames "
                                            f"{w.first}-{w.last}) not done") from None


def _on_dask(client: Any, task: Callable[[int], tuple[Any, ...]], n: int, what: Callable[[int], str],
             submitted: dict[Any, int] | None = None) -> Iterator[tuple[int, Any]]:
    """Tasks ``task(k) = (fn, *args)``, ``k < n``, on the Dask ``client``: ``(k, result)`` as they
    finish (``submitted``: their futures, already submitted by the caller). A task cancelled
    because the worker holding its input was lost (a worker killed or gone: a scattered scene
    cannot be recomputed) is submitted again, its input scattered again (:class:`Scattered`), up
    to :data:`WINDOW_TRIES` times; one that kills its worker (Dask's ``KilledWorker``, after Dask's
    own retries) is an :class:`EstimationError` naming it (``what(k)``)."""
    from distributed import as_completed
    from distributed.client import FutureCancelledError
    from distributed.scheduler import KilledWorker

    def submit(k: int) -> Any:
        fn, *args = task(k)
        return client.submit(fn, *args, pure=False)

    futures = submitted if submitted is not None else {submit(k): k for k in range(n)}
    tries = [1] * n
    pending = as_completed(futures)
    for f in pending:
        k = futures.pop(f)
        try:
            result = f.result()
        except FutureCancelledError:
            if tries[k] >= WINDOW_TRIES:
                raise EstimationError("--scheduler", f"{what(k)} lost its Dask worker {tries[k]} times: is "
                                                     "the cluster stable?") from None
            tries[k] += 1
            again = submit(k)
            futures[again] = k
            pending.add(again)
            continue
        except KilledWorker:
            raise EstimationError("--scheduler", f"{what(k)} killed the Dask workers that ran it (out of "
                                                 "memory? a smaller --window needs less)") from None
        yield k, result

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
  search starts warm. The other workers do that during the search (:func:`warm_workers`), and
  the windows are cut and sent to the workers meanwhile (:func:`_cut_windows`).
* Where the input's layout reads a span of frames on its own (one file a frame: WILDTRACK and
  MultiviewX, ``Layout.index``) and nothing about the whole sequence is needed to read one (no
  cross-camera association, no ``--every-frame`` rows across windows), ``gt3d reconstruct``
  reads only the cameras, the frame files' names and each frame's objects
  (:func:`gt3dkit.api.load_head`); each window reads and checks its own frames where it runs,
  and so does the search its sample, on which the box model is chosen too
  (:mod:`gt3dkit.windows.frames`). The truth file is read meanwhile. Each window sends back its
  files' digests, its own frames' rows, truth and warnings (:func:`completed`). On the 4 000-frame
  box scene that took 2.3 s of reading off the client, which now waits for its workers from
  about 2 s into the run. Other inputs are read whole and their windows cut from them, as
  before; the output is the same either way (a test).
* On a Dask cluster, a window (or the search) whose worker is lost runs again on the others: the
  window scenes scattered to that worker went with it, and are scattered again
  (:class:`Scattered`, :func:`on_dask`); a local process that dies (``--jobs``) is an error
  naming its window (:func:`in_pool`). :func:`connect_scheduler` refuses a scheduler without
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
  by person (:func:`pooled_bones`, :class:`gt3dkit.fusion.ukf.bones.PersonBones`); the second round
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
import uuid
from collections.abc import Callable, Iterable
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gt3dkit.api import scene_kind
from gt3dkit.errors import InputError
from gt3dkit.fusion.base import make_estimator, over_time
from gt3dkit.io.atomic import write_dir_atomically
from gt3dkit.io.datasets import with_sequence_truth
from gt3dkit.io.writers import StreamedRows, write_result_files
from gt3dkit.qa.anomalies import Anomalies
from gt3dkit.sealed import Sealed, opened_call
from gt3dkit.threads import roomy_malloc
from gt3dkit.types import JsonDict, Options, OptionValue, Scene, TrackSet
from gt3dkit.windows.cluster import (
    Cluster,
    Runner,
    Scattered,
    connect_scheduler,
    in_pool,
    on_dask,
    process_pool,
    warm_workers,
)
from gt3dkit.windows.frames import (
    FramesRead,
    ReadPart,
    SampleRead,
    WindowRead,
    completed,
    read_then,
    with_chosen_box_model,
)
from gt3dkit.windows.noise import chosen_noise, noise_sample
from gt3dkit.windows.plan import (
    MIN_OVERLAP_FRAMES,
    Bridge,
    Plan,
    Window,
    auto_plan,
    frame_work,
    occupied,
    overlap_frames,
    plan_windows,
    sized_plan,
    window_scene,
)
from gt3dkit.windows.stitch import (
    Keep,
    OnPart,
    RowsTally,
    WindowJob,
    WindowPart,
    drop_kept,
    pooled_bones,
    run_window,
    stitch,
    window_bones,
)

if TYPE_CHECKING:
    from distributed import Client

#: What the commands use; the rest is in the submodules (plan, noise, cluster, stitch).
__all__ = ["Cluster", "Plan", "Window", "auto_plan", "connect_scheduler", "reconstruct_windowed",
           "reconstruct_windows"]

def reconstruct_windows(scene: Scene, estimator: str, plan: Plan, out: str | None = None,
                        extra_meta: JsonDict | None = None, every_frame: int | None = None,
                        on_window: Callable[[int, int], None] | None = None, cluster: Cluster | None = None,
                        tally: RowsTally | None = None, **config: OptionValue) -> tuple[TrackSet, Scene]:
    """:func:`gt3dkit.api.reconstruct` of a long sequence by ``plan``; writes ``out`` if given,
    atomically as one run: each window's rows as soon as they are final (the windows before it
    done, :class:`gt3dkit.io.writers.StreamedRows`; on the 4 000-frame box scene, what is left
    for after the last window went from 0.6-1.0 s of writing to its rows and 0.02 s of
    ``meta.json``), into a folder that replaces ``out`` at the end. ``cluster``:
    ``plan.scheduler``'s, connected early by the caller (who closes it). ``tally``: told the
    rows as they are written, window by window, and where the truth comes from (the truth
    report's counts, made while the windows run: on the 8 000-frame, 60-person box scene,
    0.85 s of the 1.3 s it took after them; :class:`gt3dkit.eval.tracking.TrackingTally`);
    only with ``out``. The tracks, and the scene as the windows read it
    (:func:`reconstruct_windowed`)."""
    if out is None:
        tracks, _, read = reconstruct_windowed(scene, estimator, plan, every_frame, on_window, cluster,
                                               on_part=None, tally=None, **config)
        return tracks, read
    made: list[tuple[TrackSet, Scene]] = []

    def run(tmp: Path) -> None:
        with StreamedRows(tmp, tally.add if tally is not None else None) as rows:
            tracks, qa, read = reconstruct_windowed(scene, estimator, plan, every_frame, on_window, cluster,
                                                    rows.add, tally, **config)
        write_result_files(tmp, read, tracks, extra_meta, qa, streamed=True)
        made.append((tracks, read))

    write_dir_atomically(Path(out), run)
    return made[0]


def reconstruct_windowed(scene: Scene, estimator: str, plan: Plan, every_frame: int | None = None,
                         on_window: Callable[[int, int], None] | None = None, cluster: Cluster | None = None,
                         on_part: OnPart | None = None, tally: RowsTally | None = None, **config: OptionValue
                         ) -> tuple[TrackSet, Anomalies, Scene]:
    """``scene`` in windows (:mod:`gt3dkit.windows`, ``plan``): the stitched tracks, the QA findings,
    and the scene as the windows read it: ``scene`` itself, or where it is an index whose windows
    read their own frames (:func:`gt3dkit.api.load_head`), the index with what they read
    (:func:`gt3dkit.windows.frames.completed`); ``on_window(done, total)`` as the windows start (0)
    and after each one; ``cluster`` as :func:`reconstruct_windows`; ``on_part(k, tracks,
    anomaly_rows, text)`` with each window's final rows, findings and their text (made on the
    worker, :class:`gt3dkit.io.writers.PartText`) as it finishes (:func:`run_window`);
    ``tally``: told where the truth comes from (:class:`RowsTally`; its rows come through
    ``on_part``)."""
    _refuse_unwindowed(scene, estimator, every_frame)
    ov = overlap_frames(scene) if plan.overlap is None else plan.overlap
    own = cluster is None and bool(plan.scheduler)
    if own:
        cluster = Cluster(str(plan.scheduler), estimator, config, loading=False)
    if cluster is not None:  # before the search: it would wait for the other kind's warm-up
        cluster.warm_only(scene_kind(scene))
    reads: list[FramesRead] | None = [] if scene.index is not None else None
    try:
        client = cluster.client if cluster is not None else None
        workers = len(client.scheduler_info()["workers"]) if client is not None else plan.jobs
        frames = np.asarray(scene.frames, dtype=np.int64)
        windows = plan_windows(frames, sized_plan(plan, ov, len(frames), workers).size, ov)
        with contextlib.ExitStack() as stack:
            runner = client
            if client is None and plan.jobs > 1 and len(windows) > 1:
                runner = stack.enter_context(process_pool(min(plan.jobs, len(windows))))
            if runner is None:  # the windows one after another here: their memory kept between them
                stack.enter_context(roomy_malloc(run=True))
            # an index's frames are read where they are used: the noise's sample (and the box
            # model chosen on it) where the search runs, the truth file here meanwhile
            cut = _cutter(scene)
            warming = (warm_workers(client, scene, estimator, config, cut, cluster.warmed)
                       if client is not None and cluster is not None else [])
            sample = cut(*noise_sample(scene, windows))
            noise_when_done = chosen_noise(scene, sample, estimator, config, runner)
            truth = _truth_meanwhile(scene, stack, tally)
            # meanwhile the windows, cut (and sent to the cluster) for the context the noise leaves
            # as it is (always, for boxes), again if it needs less; each frame's objects and each
            # object's annotated frames (--every-frame) found once for both
            work = frame_work(scene, frames) if plan.why else None
            index = Bridge.of(scene, ov) if every_frame is not None else None
            windows, bridge, scenes = _cut_windows(scene, sized_plan(plan, ov, len(frames), workers), ov,
                                                   client, index, work)
            chosen = noise_when_done()
            noise, needed = chosen.noise, chosen.context
            if scene.index is not None:
                scene = with_chosen_box_model(scene, chosen.box_model, chosen.box_model_px)
            recut = plan.overlap is None and needed is not None and needed < ov
            if recut and needed is not None:  # the noise's own context
                ov = max(needed, MIN_OVERLAP_FRAMES)
            if recut or scene.index is not None:  # (an index's windows carry its box model)
                windows, bridge, scenes = _cut_windows(scene, sized_plan(plan, ov, len(frames), workers), ov,
                                                       client, index, work)
            plan = sized_plan(plan, ov, len(frames), workers)
            like = WindowJob(windows[0], estimator, {**config, **noise}, every_frame,
                             text=on_part is not None)
            done, n = on_window or (lambda k, n: None), len(windows)
            runner = None if client is None and n == 1 else runner
            parts, samples, like = _run_rounds(
                scenes, windows, like, runner, client, done, on_part, reads,
                config if ties_bones(scene, estimator, config) and n > 1 else None)
            if reads is not None:
                scene = completed(scene, reads, truth.result() if truth is not None else None)
            del warming
    finally:
        if own and cluster is not None:
            cluster.close()
    tracks, qa = stitch(parts, windows, plan, ov, noise)
    return _with_pooled_bones(tracks, like, samples), qa, scene


def _refuse_unwindowed(scene: Scene, estimator: str, every_frame: int | None) -> None:
    """:class:`InputError` where ``scene`` cannot be run in windows by ``estimator``: one that fits
    each frame on its own, or a dense grid over an index (its objects' annotations are not read
    whole)."""
    if not over_time(estimator):
        raise InputError("--window", f"the {estimator} fits each frame on its own: it needs no window")
    if scene.index is not None and every_frame is not None:
        raise InputError("--every-frame", "needs each object's annotations over the whole sequence: "
                                          "read it whole (gt3dkit.api.load_scene), not by its windows")


def _with_pooled_bones(tracks: TrackSet, like: WindowJob, samples: list[Any]) -> TrackSet:
    """The stitched ``tracks`` with every person's pooled bones (not the first window's) and the
    bones' round's time (the estimator's time too) in their :class:`RunInfo`."""
    if like.bones is not None:
        pooled = "over every window's own frames (gt3dkit.windows)"
        tracks = tracks.with_info(dataclasses.replace(tracks.info, bones={
            **like.bones.lengths.info(like.bones.ids), "pooled": pooled}))
    if samples:
        first = float(sum(p[2] for p in samples))
        win = tracks.info.windows
        win = None if win is None else dataclasses.replace(win, bones_round_seconds=first)
        tracks = tracks.with_info(dataclasses.replace(tracks.info, seconds=tracks.info.seconds + first,
                                                      windows=win))
    return tracks


def _run_rounds(scenes: Callable[[int], Any], windows: list[Window], like: WindowJob, runner: Runner,
                client: Client | None, done: Callable[[int, int], None], on_part: OnPart | None,
                reads: list[FramesRead] | None, pooled: Options | None
                ) -> tuple[list[Any], list[Any], WindowJob]:
    """The windows run (:func:`_run_windows`) in one round, or in two where ``pooled`` gives the
    bones' settings: each window's bone samples first (:func:`window_bones`), pooled by person
    (:func:`pooled_bones`), then the windows with them. The second round takes each window's
    preparation from the first, in this process or on the Dask worker holding its scene (a
    process pool's are any process's), dropped after it. The parts, the first round's samples
    (none in one round) and the job the windows ran (with the pooled bones)."""
    n = len(windows)
    if pooled is None:
        return _run_windows(scenes, windows, like, runner, done, on_part=on_part, reads=reads), [], like
    kept = Keep(uuid.uuid4().hex) if runner is None or client is not None else None
    try:
        samples = _run_windows(scenes, windows, like, runner, lambda k, _: done(k, 2 * n),
                               functools.partial(window_bones, kept=kept), reads=reads)
        like = dataclasses.replace(like, bones=pooled_bones(samples, pooled))
        parts = _run_windows(scenes, windows, like, runner, lambda k, _: done(n + k, 2 * n),
                             functools.partial(run_window, kept=kept), on_part=on_part, reads=reads)
    finally:
        if kept is not None:
            _drop_kept(kept.token, client)
    return parts, samples, like


def _truth_meanwhile(scene: Scene, stack: contextlib.ExitStack, tally: RowsTally | None
                     ) -> Future[Scene] | None:
    """Where ``scene`` is an index whose windows read their own frames, its sequence's truth file
    read in a thread of ``stack`` meanwhile (:func:`gt3dkit.io.datasets.with_sequence_truth`: the
    future of the scene with it); ``tally`` told where the truth comes from (that future's, or
    ``scene``'s own)."""
    truth = (stack.enter_context(ThreadPoolExecutor(1)).submit(with_sequence_truth, scene)
             if scene.index is not None else None)
    if tally is not None:
        given = scene.truth
        tally.truth_from(lambda: truth.result().truth if truth is not None else given)
    return truth


def _cutter(scene: Scene) -> Callable[[int, int], Scene | SampleRead]:
    """The scene of the frames ``lo..hi`` of ``scene``, cut from its rows; where it is an index,
    the function that reads it where it is used (:class:`SampleRead`)."""
    if scene.index is not None:
        return functools.partial(SampleRead.of, scene)
    return functools.partial(window_scene, scene)


def _drop_kept(token: str, client: Client | None) -> None:
    """The run ``token``'s kept preparations removed here and on every Dask worker
    (:class:`gt3dkit.windows.stitch.Keep`); a worker gone meanwhile took its own with it. Sent
    sealed (:mod:`gt3dkit.sealed`): opened where ``client.run`` runs it, in the worker's thread
    that reads its messages, under the lock its task threads open theirs with."""
    drop_kept(token)
    if client is not None:
        with contextlib.suppress(Exception):
            client.run(opened_call, Sealed.of(drop_kept), token)


def ties_bones(scene: Scene, estimator: str, config: Options) -> bool:
    """Whether ``estimator`` ties the joints of ``scene`` by its persons' bones (then the windows
    pool theirs first: :func:`window_bones`, :func:`pooled_bones`)."""
    return make_estimator(estimator, **config).capabilities.bone_samples and scene.obs.n_joints > 0


def _cut_windows(scene: Scene, plan: Plan, overlap: int, client: Client | None, index: Bridge | None,
                 work: np.ndarray | None) -> tuple[list[Window], Bridge | None, Callable[[int], Any]]:
    """The windows of ``plan`` with ``overlap`` frames of context, the rows between annotations
    they bring (``--every-frame``: ``index``, :class:`Bridge`, with ``overlap`` a side) and their
    scenes (:func:`_window_scenes`). The tool's windows hold equal object-frames (``work``, each
    frame's objects: the workers finish together); a ``--window`` is cut as given (None)."""
    frames = np.asarray(scene.frames, dtype=np.int64)
    bridge = dataclasses.replace(index, count=overlap) if index is not None else None
    windows = occupied(plan_windows(frames, plan.size, overlap, work), scene, bridge)
    return windows, bridge, _window_scenes(scene, windows, client, bridge)


def _window_scenes(scene: Scene, windows: list[Window], client: Client | None, bridge: Bridge | None = None
                   ) -> Callable[[int], Any]:
    """Window ``k``'s scene: made when asked (one window's at a time in this process), or on a
    Dask ``client`` scattered once to the cluster as data (not inside the task graph) and its
    future given to every round (:class:`Scattered`); with the ``bridge`` rows (the rows between
    annotations, ``--every-frame``)."""
    def cut(w: Window) -> Scene:
        return window_scene(scene, w.lo, w.hi, bridge.rows(w) if bridge is not None else None)

    if scene.index is not None:  # each read where its window runs
        return lambda k: WindowRead.of(scene, windows[k])
    if client is None:
        return lambda k: cut(windows[k])
    return Scattered(client, [functools.partial(cut, w) for w in windows])


def _run_windows(scenes: Callable[[int], Any], windows: list[Window], like: WindowJob, runner: Runner,
                 done: Callable[[int, int], None], fn: Callable[[WindowJob, Scene], Any] = run_window,
                 on_part: OnPart | None = None, reads: list[FramesRead] | None = None) -> list[Any]:
    """Every window's ``fn`` (:func:`run_window`; ``like`` with each window's frames, ``scenes(k)``
    its scene): on the Dask client or the process pool ``runner``, or one after the other in this
    process (None); ``done(k, n)`` as they start (0) and finish, ``on_part(k, *part)`` with window
    ``k``'s part as it comes. On Dask, a window whose worker was lost runs again on the others
    (:func:`on_dask`). ``reads``: where ``scenes(k)`` is a :class:`WindowRead`, filled with what
    each window read (:func:`read_then`), in window order."""
    done(0, len(windows))
    parts: list[Any] = [None] * len(windows)
    said: list[Any] = [None] * len(windows)
    got = on_part or (lambda k, *part: None)
    if reads is not None:
        fn = functools.partial(read_then, fn)
    finished: Iterable[tuple[int, Any]]
    if runner is None:  # in window order, each as the loop asks for it
        finished = ((k, fn(dataclasses.replace(like, window=w), scenes(k))) for k, w in enumerate(windows))
    elif not isinstance(runner, Executor):  # a Dask client
        finished = on_dask(runner, lambda k: (fn, dataclasses.replace(like, window=windows[k]), scenes(k)),
                            len(windows), lambda k: f"window {k + 1} (frames {windows[k].first}-"
                                                    f"{windows[k].last})")
    else:
        futures = {runner.submit(fn, dataclasses.replace(like, window=w), scenes(k)): k
                   for k, w in enumerate(windows)}
        finished = in_pool(futures, windows)
    for n, (k, part) in enumerate(finished, 1):
        if isinstance(part, ReadPart):
            part, said[k] = part.part, part.read
        got(k, *part)
        parts[k] = part._replace(text=None) if isinstance(part, WindowPart) else part  # written, not kept
        done(n, len(windows))
    if reads is not None:
        reads[:] = said
    return parts

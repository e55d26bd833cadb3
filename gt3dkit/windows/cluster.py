"""Where the windows run: local processes (``--jobs``) or a Dask cluster (``--scheduler``): the
connection and its checks, the workers warmed, scenes scattered and sent again when a worker is
lost, and each failure as one error naming its window."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Collection, Iterator
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np

from gt3dkit.api import (
    estimate_checked,
    tiny_scene,
)
from gt3dkit.early import WARM_KINDS, Early, check_scheduler_address
from gt3dkit.errors import EstimationError, InputError
from gt3dkit.fusion.base import make_estimator
from gt3dkit.sealed import scatter, submit
from gt3dkit.threads import small_matrix_blas
from gt3dkit.types import Options, Scene
from gt3dkit.version import __version__, installed
from gt3dkit.windows.plan import Window

if TYPE_CHECKING:
    from concurrent.futures import Executor

    from distributed import Client, Future

#: Where windows run: a Dask cluster's client, a local process pool, or this process (None).
Runner: TypeAlias = "Client | Executor | None"

#: Frames each Dask worker but the first estimates first, to load its imports and kernels
#: (:func:`warm_workers`).
WARM_FRAMES = 3


#: Times a window is submitted to a Dask cluster whose workers holding its scene are lost, at most
#: (:func:`on_dask`).
WINDOW_TRIES = 3


def connect_scheduler(address: str, early: Early | None = None) -> Any:
    """A Dask client of the scheduler at ``address`` (``--scheduler``, here and in
    ``reconstruct-many``) with at least one worker, or InputError naming ``--scheduler``. It waits
    for the connection, and then for a first worker, as long as Dask's own
    ``distributed.comm.timeouts.connect`` says (30 s unless the user's Dask configuration or
    ``DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT`` says otherwise): a scheduler no worker joins
    made ``reconstruct-many`` wait for ever and ``reconstruct`` fail inside Dask. Every worker
    there must have this gt3dkit (its version; a worker without it, or with another, failed
    inside the first task or wrote another output). ``early``: the connection ``gt3d`` made to
    ``address`` before its imports (:func:`gt3dkit.early.connect_early`), taken as this one: its
    client, or its error said here."""
    import dask
    from dask.utils import parse_timedelta
    from distributed import Client

    wait = parse_timedelta(dask.config.get("distributed.comm.timeouts.connect"), default="s")
    check_scheduler_address(address)
    try:
        mine = early if early is not None and early.address == address else None
        if mine is not None and mine.error is not None:
            raise mine.error
        client = mine.client if mine is not None and mine.client is not None else Client(address)
    except (OSError, TimeoutError) as e:
        raise InputError("--scheduler", f"cannot reach the Dask scheduler at {address} ({e})") from None
    try:
        client.wait_for_workers(1, timeout=wait)
        # a worker's error: no gt3dkit there to load the function with
        others = {w: v if isinstance(v, str) else "none" for w, v in
                  sorted(client.run(installed, on_error="return").items()) if v != __version__}
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


class Cluster:
    """The Dask scheduler at ``address`` (``--scheduler``): a client, connected at once (an
    unreachable scheduler is an :class:`InputError` naming ``--scheduler``). With ``loading``
    (``gt3d reconstruct`` makes it before it loads the sequence) its first worker, the one the
    noise search runs on (:func:`chosen_noise`), loads gt3dkit's imports and compiled kernels
    while the sequence loads (:func:`warm_first`, a task for each kind of tiny scene,
    :data:`gt3dkit.early.WARM_KINDS`); without, it would only do that before the search. The
    others do it during the search, on the sequence's own first frames (:func:`warm_workers`):
    on 2 cores, warming them all during the loading slowed it (4.3 s against 3.4 s, means of 4
    runs), and so did connecting in a thread beside it with the second worker warming (4.5 s
    against 3.9 s; connecting first took 0.3-0.45 s). ``early``: the connection ``gt3d`` made
    before its own imports, with the first worker's warm-ups already sent
    (:func:`gt3dkit.early.connect_early`), taken over; the other workers are then sent theirs at
    once: on the 4 000-frame box scene with 2 workers, warming the second during the search
    (where :func:`warm_workers` does) slowed the search from 0.9 s to 1.2-1.6 s, and the
    whole run took 19.1-20.1 s against 19.8-20.7 s (3 runs each). The run lets go of the
    warm-ups of the kind its input does not use (:meth:`warm_only`). A context manager."""

    def __init__(self, address: str, estimator: str, config: Options, loading: bool = True,
                 early: Early | None = None) -> None:
        self.client = connect_scheduler(address, early)
        try:
            # held until closed or let go (warm_only): a future let go is a task cancelled
            self._warming: dict[tuple[str, str], Future[object]] = {}
            if early is not None and early.client is self.client:
                self._warming, early.warming = early.warming, {}
            # the first worker at once; where it was sent its warm-ups before this process's
            # imports, the others now too, while this process loads the input, not during the search
            now = worker_addresses(self.client)[:1 if not self._warming else None] if loading else []
            self._warming.update({(w, kind): submit(self.client, warm_first, estimator, config, kind,
                                                    workers=[w], allow_other_workers=False)
                                  for w in now if w not in self.warmed for kind in WARM_KINDS})
        except BaseException:
            self.client.close()
            raise

    @property
    def warmed(self) -> set[str]:
        """The workers sent a warm-up from the start (:func:`warm_workers` leaves them out)."""
        return {w for w, _ in self._warming}

    def warm_only(self, kind: str) -> None:
        """Let go of the warm-ups of the kinds other than ``kind`` (:data:`WARM_KINDS`; that of the
        loaded input, :func:`gt3dkit.api.scene_kind`): Dask cancels those that have not
        started, which the noise search, sent next to the first worker, would wait for."""
        self._warming = {k: f for k, f in self._warming.items() if k[1] == kind}

    def close(self) -> None:
        self._warming = {}
        self.client.close()

    def __enter__(self) -> Cluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def process_pool(workers: int) -> Any:
    """``workers`` local processes (spawned: no fork of a process that holds threads)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    return ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"))


def warm_first(estimator: str, config: Options, kind: str) -> None:
    """:func:`warm_worker` on the tiny simulated scene of ``kind``, boxes or joints
    (:func:`gt3dkit.api.tiny_scene`): the first Dask worker's, while the sequence loads
    (:class:`Cluster`)."""
    warm_worker(tiny_scene(kind), estimator, config)


def warm_worker(scene: Scene | Callable[[], Scene], estimator: str, config: Options) -> None:
    """Estimate ``scene`` (a few frames; read here where it is a reader) and drop the result: this
    process's imports and compiled kernels loaded (:func:`warm_workers`, :func:`warm_first`); an
    error is left to the windows to find."""
    with contextlib.suppress(Exception), small_matrix_blas():
        estimate_checked(scene if isinstance(scene, Scene) else scene(), make_estimator(estimator, **config))


def warm_workers(client: Client, scene: Scene, estimator: str, config: Options,
                 cut: Callable[[int, int], Scene | Callable[[], Scene]], warmed: Collection[str] = ()
                 ) -> list[Any]:
    """The sequence's first annotated frames (``cut(lo, hi)``: the scene of frames ``lo..hi``, or
    its reader)
    estimated and dropped on the Dask ``client``'s workers but the first (:func:`warm_worker`):
    while the first searches the noise (:func:`chosen_noise`), the others load their imports and
    compiled kernels (a second or two a process) instead of on their first window; not those
    ``warmed`` already (:class:`Cluster`). Their futures, to hold until the windows run (a future
    let go is a task cancelled)."""
    f = (scene.index.frames if scene.index is not None else np.unique(scene.obs.frame))[:WARM_FRAMES]
    others = [w for w in worker_addresses(client)[1:] if w not in warmed]
    if not len(f) or not others:
        return []
    tiny = cut(int(f[0]), int(f[-1]))  # small: inside the task
    return [submit(client, warm_worker, tiny, estimator, config, workers=[w], allow_other_workers=False)
            for w in others]


def worker_addresses(client: Client) -> list[str]:
    """The Dask ``client``'s workers' addresses, sorted."""
    return sorted(client.scheduler_info()["workers"])


class Scattered:
    """Scenes scattered to a Dask cluster as data, each one's future when called with its index;
    a scene whose worker was lost (scattered data cannot be recomputed) is cut and scattered
    again (:func:`_run_windows` then runs its window again)."""

    def __init__(self, client: Client, cuts: list[Callable[[], Scene]]) -> None:
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
                return scatter(self.client, self.cuts[k]())
            except OSError as e:  # distributed's CommClosedError
                if attempt == WINDOW_TRIES:
                    raise EstimationError("--scheduler", f"could not send a window's frames to the Dask "
                                                         f"workers ({e})") from None
                time.sleep(1.0)


def in_pool(futures: dict[Any, int], windows: list[Window]) -> Iterator[tuple[int, Any]]:
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


def on_dask(client: Client, task: Callable[[int], tuple[Any, ...]], n: int, what: Callable[[int], str],
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

    def send(k: int) -> Any:
        fn, *args = task(k)
        return submit(client, fn, *args)

    futures = submitted if submitted is not None else {send(k): k for k in range(n)}
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
            again = send(k)
            futures[again] = k
            pending.add(again)
            continue
        except KilledWorker:
            raise EstimationError("--scheduler", f"{what(k)} killed the Dask workers that ran it (out of "
                                                 "memory? a smaller --window needs less)") from None
        yield k, result

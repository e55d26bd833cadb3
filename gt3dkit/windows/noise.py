"""The process noise of a long sequence, chosen once for all its windows (on a sample of it, on a
worker where the windows run on workers), and the context a window needs from it (the
steady-state filter's and smoother's gains)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from gt3dkit.api import (
    estimate_checked,
    process_noise_prepared,
)
from gt3dkit.arrays import unique_rows
from gt3dkit.fusion.base import make_estimator
from gt3dkit.fusion.motion import position_step
from gt3dkit.fusion.preparation.prepare import Prepared
from gt3dkit.fusion.ukf.noise import SEARCH_OBJECT_FRAMES, drawn_objects
from gt3dkit.jsondoc import json_num
from gt3dkit.sealed import scatter, submit
from gt3dkit.threads import every_core, roomy_malloc, small_matrix_blas
from gt3dkit.types import Options, Scene
from gt3dkit.windows.cluster import Runner, on_dask, worker_addresses
from gt3dkit.windows.plan import Window, objects_per_frame

if TYPE_CHECKING:
    from distributed import Client

#: The process-noise settings chosen once for all windows.
PROCESS_NOISE = ("accel_sd", "position_sd", "shape_sd", "joint_accel_sd")


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


#: The scene the process noise is chosen on, or a picklable function that reads it where the
#: search runs (:class:`gt3dkit.windows.frames.SampleRead`).
Sample = Scene | Callable[[], Scene]


@dataclass(frozen=True)
class Chosen:
    """What the search chose on its sample (:func:`sample_noise`): the process ``noise``, the
    ``context`` in frames it needs (:func:`joint_context`; None: the default's), and the
    sample's box model and its evidence (``Scene.box_model``, ``box_model_px``)."""

    noise: dict[str, float]
    context: int | None
    box_model: str
    box_model_px: dict[str, float]


def chosen_noise(scene: Scene, sample: Sample, estimator: str, config: Options,
                 runner: Runner = None) -> Callable[[], Chosen]:
    """The process noise every window of ``scene`` runs with (the settings ``config`` gives, the
    others the estimator's own choice on ``sample``, the scene of :func:`noise_sample`'s
    frames, :func:`sample_noise`) and what else the search chose (:class:`Chosen`), when the
    returned function is called: found in this process, or where the windows run (``runner``:
    the Dask client or the process pool, whose workers need the estimator's compiled kernels
    anyway), this process free to go on meanwhile."""
    f = np.asarray(scene.frames)
    step_s = (float(np.median(np.diff(f))) if len(f) > 1 else 1.0) / scene.fps
    if runner is None:
        found = sample_noise(sample, estimator, config, step_s)
        return lambda: found
    if not isinstance(runner, Executor):  # a Dask client
        return _search_on_dask(runner, sample, estimator, config, step_s)
    return runner.submit(sample_noise, sample, estimator, config, step_s).result


def _search_on_dask(client: Client, sample: Sample, estimator: str, config: Options, step_s: float
                    ) -> Callable[[], Chosen]:
    """:func:`searched_on_worker` of ``sample`` (a scene scattered as data, not inside the task
    graph; a reader as it is) on the Dask ``client``'s first worker, warmed as the sequence
    loaded (:class:`Cluster`), or another where that one is gone; the result when the returned
    function is called. If the worker running it is lost, the search runs again on any other
    (:func:`on_dask`)."""
    first = worker_addresses(client)[:1] or None

    def sent(workers: list[str] | None) -> Any:
        if not isinstance(sample, Scene):
            return sample
        try:
            return scatter(client, sample, workers=workers)
        except KeyError:  # that worker gone meanwhile: the scheduler no longer knows it
            return scatter(client, sample)

    # the first worker preferred, not required: one lost before the search starts left it
    # waiting for a worker that would never come back (the test suite hung there once)
    future = submit(client, searched_on_worker, sent(first), estimator, config, step_s, workers=first,
                    allow_other_workers=True)

    def again(_: int) -> tuple[Any, ...]:  # on any worker
        return searched_on_worker, sent(None), estimator, config, step_s

    return lambda: next(on_dask(client, again, 1, lambda _: "the process-noise search", {future: 0}))[1]


def searched_objects(sample: Scene, budget: int = SEARCH_OBJECT_FRAMES) -> Scene:
    """``sample`` cut to the objects the noise search runs on, drawn before their per-frame fits
    (:func:`gt3dkit.fusion.ukf.noise.drawn_objects`, whole objects up to ``budget``
    object-frames): the other objects' fits would only feed the search's provisional values.
    On 4 000 frames of 40 people that halved the search (2.4 s to 1.2 s), the same noise chosen."""
    keys = unique_rows(np.c_[sample.obs.frame, sample.obs.track_id])
    ids, count = np.unique(keys[:, 1], return_counts=True)
    if count.sum() <= budget:
        return sample
    keep = np.isin(sample.obs.track_id, ids[drawn_objects(count, budget)])
    return dataclasses.replace(sample, obs=sample.obs.select(keep))


def sample_noise(sample: Sample, estimator: str, config: Options, step_s: float) -> Chosen:
    """:func:`chosen_noise` on its ``sample`` of the sequence (frames ``step_s`` seconds apart;
    read here where it is a reader), of which the objects the search draws
    (:func:`searched_objects`)."""
    given = {k: float(v) for k in PROCESS_NOISE if isinstance(v := config.get(k), int | float)}
    with small_matrix_blas(), roomy_malloc():
        whole = sample if isinstance(sample, Scene) else sample()
        sample = searched_objects(whole)
        est = make_estimator(estimator, **config)
        found, pre = process_noise_prepared(sample, est)  # the search alone, where the estimator has one
        if found is None:
            tracks, _ = estimate_checked(sample, est, qa=False)
            found = {k: v for k in PROCESS_NOISE if (v := json_num(tracks.info.params, k)) is not None}
    fields = {f.name for f in dataclasses.fields(est.config)} if hasattr(est, "config") else set()
    chosen = {k: float(found[k]) for k in PROCESS_NOISE if k in fields and found.get(k) is not None}
    noise = {**chosen, **given}
    return Chosen(noise, joint_context(pre, noise, step_s), whole.box_model, whole.box_model_px)


def searched_on_worker(sample: Sample, estimator: str, config: Options, step_s: float) -> Chosen:
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


def joint_context(pre: Prepared | None, noise: dict[str, float], step_s: float) -> int | None:
    """The context in frames a keypoint sequence (no boxes) needs: :func:`context_steps` with
    the chosen ``joint_accel_sd`` and the per-frame joint fits' sd (the largest axis, the
    :data:`CONTEXT_SD_PERCENTILE` percentile over joints and frames of the preparation ``pre``),
    divided by the share of joint-frames with a fit (a joint unseen for a while forgets nothing
    meanwhile); frames ``step_s`` seconds apart. None (the default context) for boxes, or when
    the preparation tells nothing."""
    q = noise.get("joint_accel_sd")
    if pre is None or q is None or pre.use_box or pre.kpt0_cov is None or pre.kpt0 is None:
        return None
    var = np.diagonal(pre.kpt0_cov, axis1=-2, axis2=-1).max(axis=-1)  # (R, J) m^2
    seen = np.isfinite(pre.kpt0).all(axis=-1) & np.isfinite(var)
    if not seen.any():
        return None
    sd = float(np.sqrt(np.percentile(var[seen], CONTEXT_SD_PERCENTILE)))
    steps = context_steps(float(q), sd, step_s)
    return int(np.ceil(steps / float(seen.mean())))

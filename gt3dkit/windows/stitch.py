"""One window's run (its own frames' rows and findings from its scene with context), the bones
pooled over the windows, and the windows' rows stitched into the sequence's."""

from __future__ import annotations

import dataclasses
import pickle
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np

from gt3dkit.api import (
    bone_samples_checked,
    dense_frames,
    estimate_checked,
    take_rows,
)
from gt3dkit.fusion.base import make_estimator
from gt3dkit.fusion.preparation.prepare import Prepared
from gt3dkit.fusion.ukf.bones import BoneSamples, PersonBones
from gt3dkit.fusion.ukf.config import UKFConfig
from gt3dkit.io.writers import PartText
from gt3dkit.qa.anomalies import Anomalies
from gt3dkit.threads import roomy_malloc, small_matrix_blas
from gt3dkit.types import I64, Downweighted, GroundTruth, Options, QASummary, Scene, TrackSet, WindowsSummary
from gt3dkit.windows.plan import Plan, Window

#: What a window's rows and findings go to as it finishes (:func:`reconstruct_windowed`): its index,
#: its tracks, its QA rows and their text (:class:`WindowPart`).
OnPart = Callable[[int, TrackSet, list[tuple[Any, ...]], PartText | None], None]


class WindowPart(NamedTuple):
    """A window's result (:func:`run_window`): its own frames' ``tracks`` and QA ``findings``, and
    where the run writes them (``WindowJob.text``) their ``text`` as the output files hold it,
    made where the window ran (:class:`gt3dkit.io.writers.PartText`)."""

    tracks: TrackSet
    findings: list[tuple[Any, ...]]
    text: PartText | None = None


class RowsTally(Protocol):
    """What counts a run's rows as they become final, window by window in frame order (the
    truth report's counts, :class:`gt3dkit.commands.common.TruthTally`): told first where the
    sequence's truth comes from (read meanwhile, where the windows read their own frames)."""

    def truth_from(self, get: Callable[[], GroundTruth | None]) -> None: ...

    def add(self, tracks: TrackSet) -> None: ...


@dataclass(frozen=True)
class WindowJob:
    """What a worker needs for one window besides its scene (picklable)."""

    window: Window
    estimator: str
    config: Options
    every_frame: int | None
    bones: PersonBones | None = None  # every person's bones, pooled over the windows
    text: bool = False  # the rows' text made too (the run writes them: WindowPart.text)


class KeptPreparations:
    """Each window's preparation (the estimator's per-frame fits, ``prepare``) as the bones' round
    made it (:func:`window_bones`), kept for the second round in the same process
    (:func:`run_window`), which made it again: on the 1 000-frame, 3-person, 8-camera skeleton
    scene 0.42-0.54 s of a window's run, 1.3 s of a 9.9 s run. Kept on disk, in a temporary
    folder of its own (6.4 MB a window of 391 frames there), so that memory stays bounded by the
    window. A preparation that cannot be written (a full disk) or read back is made again, as
    before. The folder goes when it closes (:func:`drop_kept`). Reached from the windows' tasks
    through a :class:`Keep` handle."""

    def __init__(self) -> None:
        self._dir = tempfile.TemporaryDirectory(prefix="gt3dkit-windows-")
        self._paths: dict[Window, Path] = {}

    def put(self, window: Window, pre: Prepared) -> None:
        """Keep ``pre``, ``window``'s preparation (a copy, as it is now)."""
        path = Path(self._dir.name) / f"{window.lo}-{window.hi}.pickle"
        try:
            with open(path, "wb") as f:
                pickle.dump(pre, f, protocol=pickle.HIGHEST_PROTOCOL)
        except OSError:
            path.unlink(missing_ok=True)
            return
        self._paths[window] = path

    def take(self, window: Window) -> Prepared | None:
        """``window``'s kept preparation, given once (None: none kept, or unreadable)."""
        path = self._paths.pop(window, None)
        if path is None:
            return None
        try:
            with open(path, "rb") as f:
                return pickle.load(f)  # noqa: S301 (this run's own file, in its own folder)
        except (OSError, EOFError, pickle.UnpicklingError):
            return None
        finally:
            path.unlink(missing_ok=True)

    def close(self) -> None:
        """Remove the folder and whatever it still holds."""
        self._paths.clear()
        self._dir.cleanup()


#: This process's kept preparations, by run (:class:`Keep`).
_KEPT: dict[str, KeptPreparations] = {}


@dataclass(frozen=True)
class Keep:
    """A run's handle to the preparations its windows keep between the two rounds, in whichever
    process runs them: this one, or each Dask worker (a window's scene is scattered to one
    worker once and both rounds' tasks go to where it is, so the second round finds the first's
    preparation there; one that runs elsewhere makes it again). Picklable: the store itself stays
    in its process (:data:`_KEPT`); :func:`drop_kept` removes it at the end of the run."""

    token: str

    def put(self, window: Window, pre: Prepared) -> None:
        store = _KEPT.get(self.token)
        if store is None:
            store = _KEPT[self.token] = KeptPreparations()
        store.put(window, pre)

    def take(self, window: Window) -> Prepared | None:
        store = _KEPT.get(self.token)
        return store.take(window) if store is not None else None


def drop_kept(token: str) -> None:
    """Remove the run ``token``'s kept preparations in this process (:class:`Keep`)."""
    store = _KEPT.pop(token, None)
    if store is not None:
        store.close()


def run_window(job: WindowJob, scene: Scene, kept: Keep | None = None) -> WindowPart:
    """One window's rows and QA findings in its own frames, from its ``scene`` (the persons' bones
    ``job.bones`` where given: the window's own ids only, its split pieces' ids are its own),
    with their text where ``job.text`` (:class:`WindowPart`); ``kept``: the preparations the
    bones' round kept (:class:`Keep`)."""
    w = job.window
    with small_matrix_blas(), roomy_malloc():
        est = make_estimator(job.estimator, **job.config)
        if job.bones is not None:
            est.bones = job.bones.of(np.unique(scene.obs.track_id))
        pre = kept.take(w) if kept is not None else None
        tracks, qa = estimate_checked(scene, est, job.every_frame, pre=pre)
    keep = (tracks.frame >= w.first) & (tracks.frame <= w.last)
    d = tracks.downweighted
    if d is not None:
        d = _downweighted_rows(d, (d.frame >= w.first) & (d.frame <= w.last))
    out = take_rows(dataclasses.replace(tracks, downweighted=d), keep)
    rows = qa.rows if qa is not None else []
    findings = sorted((r for r in rows if w.first <= r[0] <= w.last), key=finding_order)
    return WindowPart(out, findings, PartText.of(out, findings) if job.text else None)


def finding_order(row: tuple[Any, ...]) -> tuple[Any, ...]:
    """A QA finding's place in ``anomalies.csv``: by frame, camera, id (a window's, and so the
    windows' in order: :class:`gt3dkit.io.writers.StreamedRows`)."""
    return row[0], str(row[1]), row[2]


def window_bones(job: WindowJob, scene: Scene, kept: Keep | None = None
                 ) -> tuple[BoneSamples | None, I64, float]:
    """One window's first-pass bones in its own frames, the ids it splits, from its ``scene``
    (:func:`gt3dkit.api.bone_samples_checked`; None: its estimator ties no bones), and the
    seconds it took; its preparation kept in ``kept`` where given, for :func:`run_window`."""
    t0 = time.perf_counter()
    w = job.window
    if job.every_frame is not None:
        scene = dense_frames(scene, job.every_frame or None)
    with small_matrix_blas(), roomy_malloc():
        est = make_estimator(job.estimator, **job.config)
        pre = None
        if kept is not None:
            pre = est.prepare(scene)
            kept.put(w, pre)  # before the first pass adds to it
        s, split = bone_samples_checked(scene, est, pre)
    s = None if s is None else s.take((s.frame >= w.first) & (s.frame <= w.last))
    return s, split, time.perf_counter() - t0


def pooled_bones(parts: list[tuple[BoneSamples | None, I64, float]], config: Options
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
    # the run's own bone settings (checked by UKFConfig, as the run's estimator checked them)
    bone_options: dict[str, Any] = {k: config[k] for k in ("bone_sd_floor_m", "bone_sd_m") if k in config}
    cfg = UKFConfig(**bone_options)
    return PersonBones.pooled(s, cfg.bone_sd_floor_m, cfg.bone_sd_m)


def _downweighted_rows(d: Downweighted, keep: np.ndarray) -> Downweighted:
    return Downweighted(**{f.name: getattr(d, f.name)[keep] for f in dataclasses.fields(d)})


def stitch(parts: list[WindowPart], windows: list[Window], plan: Plan,
           overlap: int, noise: dict[str, float]) -> tuple[TrackSet, Anomalies]:
    """The windows' rows and findings as one run's (rows by frame, then id)."""
    ts = [p[0] for p in parts]
    cat = {k: np.concatenate([getattr(t, k) for t in ts]) for k in
           ("frame", "track_id", "center_world", "semi_axes", "center_sd", "n_views", "kpt_world", "kpt_sd")}
    order = np.lexsort((cat["track_id"], cat["frame"]))
    ds = [t.downweighted for t in ts if t.downweighted is not None]
    down = Downweighted(**{f.name: np.concatenate([getattr(d, f.name) for d in ds])
                           for f in dataclasses.fields(Downweighted)}) if ds else None
    first = ts[0].info
    robust = first.robust
    if robust is not None and down is not None:
        robust = dataclasses.replace(robust, downweighted=int(np.sum(down.weight > 0)),
                                     rejected=int(np.sum(down.weight == 0)))
    rows = [r for p in parts for r in p[1]]  # each window's sorted, the windows in frame order
    qa = Anomalies(rows)
    info = dataclasses.replace(
        first, seconds=float(sum(t.info.seconds for t in ts)), object_frames=int(len(order)),
        robust=robust, segments=[s for t in ts for s in t.info.segments],
        qa=QASummary(qa.counts()),
        windows=WindowsSummary(len(windows), plan.size, overlap, plan.why,
                               "equal object-frames" if plan.why else "equal frames",
                               [dataclasses.asdict(w) for w in windows], noise,
                               "each window run on its frames plus context, its own frames kept; the process "
                               "noise chosen once (gt3dkit.windows)"))
    tracks = TrackSet(**{k: v[order] for k, v in cat.items()}, info=info, downweighted=down)
    return tracks, qa

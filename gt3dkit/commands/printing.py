"""What the commands print of a run: its warnings, the table of errors against the input's truth
(boxes and keypoints; tracking scores), the line ``gt3d reconstruct`` ends with, and the way from
a rig found from the people into the input's own calibration's frame, where its truth is."""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from gt3dkit.api import take_rows
from gt3dkit.eval.metrics import box_errors, relabel_to_truth
from gt3dkit.eval.pose import mpjpe_by_id, score_tracks
from gt3dkit.eval.tracking import TrackingTally, tracking_scores
from gt3dkit.refine.common import centre_similarity
from gt3dkit.rig import Rig
from gt3dkit.types import (
    BOX_MODEL_REGISTRY,
    GroundTruth,
    Scene,
    TrackSet,
)


@dataclass(frozen=True)
class IntoGiven:
    """The similarity ``X_given = scale R X + t`` from the people's world into the input's own
    calibration's (the one that best maps the found cameras' centres onto its own), and that rig:
    where the input's truth is."""

    scale: float
    R: np.ndarray
    t: np.ndarray
    rig: Rig

    def tracks(self, tracks: TrackSet) -> TrackSet:
        """``tracks`` moved by the similarity (positions, sizes and sds)."""
        s, R, t = self.scale, self.R, self.t
        return dataclasses.replace(tracks, center_world=s * tracks.center_world @ R.T + t,
                                   semi_axes=s * tracks.semi_axes, center_sd=s * tracks.center_sd,
                                   kpt_world=s * tracks.kpt_world @ R.T + t, kpt_sd=s * tracks.kpt_sd)


def into_given(found: Rig, given: Rig) -> IntoGiven | None:
    """:class:`IntoGiven` of ``found`` onto ``given`` (:func:`gt3dkit.refine.common.centre_similarity`;
    None where it has none)."""
    sim = centre_similarity(found, given)
    return None if sim is None else IntoGiven(float(sim[0]), sim[1], sim[2], given)


def box_model_note(scene: Scene) -> str:
    """How the boxes are drawn, with the evidence when it was chosen: e.g. ``occupancy-map rectangles
    (edges 0.27 px off; ellipsoid 0.83, cylinder 0.86)``."""
    px = scene.box_model_px
    if not px:
        return BOX_MODEL_REGISTRY[scene.box_model].summary
    others = ", ".join(f"{m} {v:.2f}" for m, v in px.items() if m != scene.box_model)
    return f"{BOX_MODEL_REGISTRY[scene.box_model].summary} (edges {px[scene.box_model]:.2f} px off; {others})"


def print_warnings(scene: Scene) -> None:
    """The input's ``warning:`` lines, printed once the run succeeded (a failed run prints its
    one ``error:`` line only)."""
    for w in scene.all_warnings:
        print(f"warning: {w}", file=sys.stderr)


def error_table(rows: list[tuple[str, Any]]) -> str:
    """Fixed-width table of (estimator, BoxErrors)."""
    head = (f"{'estimator':<14}{'rows':>6}{'cover%':>8}{'ground mm':>11}{'median mm':>11}"
            f"{'centre mm':>11}{'height mm':>11}{'radius mm':>11}{'MOTA%':>8}{'IDF1%':>8}")
    lines = [head, "-" * len(head)]
    def mm(v: float) -> str:
        return f"{1000 * v:>11.2f}" if np.isfinite(v) else f"{'-':>11}"

    for name, e in rows:
        lines.append(f"{name:<14}{e.rows_matched:>6}{100 * e.coverage:>8.1f}"
                     f"{mm(e.ground_mean_m)}{mm(e.ground_median_m)}{mm(e.centre_mean_m)}"
                     f"{mm(e.height_mean_m)}{mm(e.radius_mean_m)}{100 * e.mota:>8.1f}"
                     f"{100 * e.idf1:>8.1f}")
    return "\n".join(lines)


def fmt_num(v: float | None, width: int, digits: int) -> str:
    """``v`` right-aligned in ``width``, or ``-`` where there is no value (None, NaN)."""
    return f"{v:>{width}.{digits}f}" if v is not None and np.isfinite(v) else f"{'-':>{width}}"


def pose_table(rows: list[tuple[str, Any, float]]) -> str:
    """Fixed-width table of (name, PoseScores, MPJPE by id in mm)."""
    head = (f"{'estimator':<26}{'AP@25':>7}{'AP@50':>7}{'AP@100':>8}{'AP@150':>8}"
            f"{'Rec@500':>9}{'MPJPE mm':>11}{'by id mm':>10}")
    lines = [head, "-" * len(head)]
    for name, p, by_id in rows:
        lines.append(f"{name:<26}{100 * p.ap[25]:>7.1f}{100 * p.ap[50]:>7.1f}"
                     f"{100 * p.ap[100]:>8.1f}{100 * p.ap[150]:>8.1f}{100 * p.recall_500:>9.1f}"
                     f"{fmt_num(p.mpjpe_mm, 11, 4)}{fmt_num(by_id, 10, 4)}")
    return "\n".join(lines)


class TruthTally:
    """The truth report's tracking scores and box errors (:func:`report_truth`) counted as a
    windowed run's rows become final, window by window
    (:class:`gt3dkit.eval.tracking.TrackingTally`; :class:`gt3dkit.windows.stitch.RowsTally`):
    of the rows in frames the truth has a row in, against the truth where it gives positions and
    the ids are the input's (gt3dkit's own ids are matched to the truth's over the whole run
    first: then nothing is counted here). ``up``: the rig's."""

    def __init__(self, up: np.ndarray, max_dist_m: float = 1.0) -> None:
        self.up, self.max_dist_m = up, max_dist_m
        self._get: Callable[[], GroundTruth | None] | None = None
        self.tally: TrackingTally | None = None
        self.truth: GroundTruth | None = None
        self.unscored = 0
        self._frames = np.zeros(0, np.int64)
        self._off = False

    def truth_from(self, get: Callable[[], GroundTruth | None]) -> None:
        """The truth is ``get()``, called when the first rows come (None: no truth to count)."""
        self._get = get

    def add(self, tracks: TrackSet) -> None:
        """The next window's final rows (frames after every earlier window's)."""
        if self._off or self._get is None:
            self._off = True
            return
        if self.tally is None:
            self.truth = self._get()
            if self.truth is None or not np.isfinite(self.truth.center_world).any():
                self._off = True
                return
            self.tally = TrackingTally(self.truth, self.up, self.max_dist_m)
            self._frames = np.unique(self.truth.frame)
        on = np.isin(tracks.frame, self._frames)
        self.unscored += int((~on).sum())
        self.tally.add(tracks if on.all() else take_rows(tracks, on))

    def counted(self, scene: Scene, tracks: TrackSet) -> TrackingTally | None:
        """The tally, where it counted every row of ``tracks`` (those in frames ``scene``'s truth
        has) against that truth, with the input's ids; None: :func:`report_truth` computes it."""
        t = self.tally
        ok = (t is not None and not self._off and scene.association is None and self.truth is scene.truth
              and t.rows + self.unscored == len(tracks))
        return t if ok else None


def print_run(scene: Scene, tracks: TrackSet, estimator: str, out: str, into: IntoGiven | None = None,
              tally: TruthTally | None = None) -> None:
    """What ``gt3d reconstruct`` prints after its run: the scene's warnings, a line of what was read,
    estimated and written (to ``out``), and the errors against the input's truth where it has one
    (``into``: a rig found from the people, scored in the input calibration's frame; ``tally``:
    the truth's counts made while the windows ran)."""
    print_warnings(scene)
    info = tracks.info
    kinds = " + ".join(k for k, v in ((f"boxes: {box_model_note(scene)}", scene.has_boxes),
                                      (f"{scene.skeleton} keypoints", scene.obs.n_joints > 0)) if v)
    fps = f"{scene.fps:g} fps" + (" (assumed)" if scene.fps_assumed else "")
    rob = info.robust
    flagged = (f", {rob.rejected} measurements rejected and {rob.downweighted} "
               f"down-weighted (downweighted.csv)" if rob is not None and rob.enabled else "")
    qa = info.qa.anomalies if info.qa is not None else {}
    flagged += (", anomalies: " + ", ".join(f"{v} {k}" for k, v in qa.items()) + " (anomalies.csv)"
                if qa else ", no anomalies")
    win = info.windows
    if win is not None:
        about = "about " if win.cut == "equal object-frames" else ""
        flagged += (f", in {win.count} windows of {about}{win.frames} frames with {win.overlap_frames} of "
                    "context" + (f" ({win.why}; --window FRAMES to choose)" if win.why else ""))
    print(f"{scene.layout}: {scene.n_annotations} annotation rows ({kinds}), {len(scene.rig.cameras)} "
          f"cameras, {fps} -> {len(tracks)} object-frames of {len(set(tracks.track_id.tolist()))} "
          f"objects ({estimator}, {info.seconds:.2f} s{flagged}) written to "
          f"{out}")
    if into is not None and scene.truth is not None:
        print("(scored in the input calibration's frame: the tracks moved by the similarity that best maps "
              f"the found cameras' centres onto its own, scale {into.scale:.4f}; the written files stay in "
              "the people's world)")
        report_truth(dataclasses.replace(scene, rig=into.rig), into.tracks(tracks), estimator)
    else:
        report_truth(scene, tracks, estimator, tally=tally)


def report_truth(scene: Scene, tracks: TrackSet, name: str, max_dist_m: float = 1.0,
                 tally: TruthTally | None = None) -> None:
    """Print errors against the input's truth: boxes/positions and/or keypoints; tracking scores
    count an estimate within ``max_dist_m`` (ground plane) of a true object as a match. ``tally``:
    the same scores counted as the run's windows finished (:class:`TruthTally`), used where it
    counted these rows."""
    if scene.truth is None:
        return
    print(f"against {scene.truth.source}:")
    counted = tally.counted(scene, tracks) if tally is not None and tally.max_dist_m == max_dist_m else None
    on = np.isin(tracks.frame, scene.truth.frame)
    if not on.all():  # a dense run's rows between the frames the truth has: nothing to score them by
        print(f"({int((~on).sum())} rows in frames the truth has no row in are not scored)")
        tracks = take_rows(tracks, on)
    if scene.association is not None:
        tracks = relabel_to_truth(tracks, scene.truth, scene.rig.up, max_dist_m)
        print("(ids are gt3dkit's cross-view association: each matched to its truth id for the errors)")
    if np.isfinite(scene.truth.center_world).any():
        if counted is not None:
            t, errors = counted.scores(), counted.errors()
        else:
            t = tracking_scores(tracks, scene.truth, scene.rig.up, max_dist_m)
            errors = box_errors(tracks, scene.truth, scene.rig.up, max_dist_m, mot=t)
        print(error_table([(name, errors)]))
        print(f"ground plane, {max_dist_m:g} m: MOTA {100 * t['mota']:.1f}  IDF1 {100 * t['idf1']:.1f}  "
              f"FP {t['fp']}  FN {t['fn']}  IDs {t['ids']}  HOTA {100 * t['hota']:.1f}  "
              f"OSPA(2) {t['ospa2_m']:.4f} m")
    if scene.truth.kpt_world.shape[1] and tracks.kpt_world.shape[1]:
        sets: list[tuple[str, np.ndarray | None]] = [("all joints", None)]
        if scene.skeleton == "coco19":
            sets.append(("15 body joints", np.arange(15)))
        print(pose_table([(f"{name}, {label}", score_tracks(tracks, scene.truth, j),
                           mpjpe_by_id(tracks, scene.truth, j)[0]) for label, j in sets]))

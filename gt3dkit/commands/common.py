"""What the commands share: bundled data, output checks, loading with the CLI's options, tables
of errors, the progress display, the option types."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import signal
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from types import FrameType
from typing import Any, NamedTuple, NoReturn

import numpy as np

from gt3dkit.api import load_detections, load_head, load_scene, take_rows
from gt3dkit.calib.formats.native import cameras_doc, write as write_native
from gt3dkit.errors import InputError
from gt3dkit.eval.metrics import box_errors, relabel_to_truth
from gt3dkit.eval.pose import mpjpe_by_id, score_tracks
from gt3dkit.eval.tracking import TrackingTally, tracking_scores
from gt3dkit.fusion.base import REGISTRY
from gt3dkit.io.atomic import check_out
from gt3dkit.io.clocks import CameraClocks, read_time_offsets
from gt3dkit.io.datasets import ASSOCIATED, detect_layout
from gt3dkit.refine.boxpeople import BoxPeopleConfig, calibrate_boxes
from gt3dkit.refine.clocks import Clocks
from gt3dkit.refine.common import centre_similarity
from gt3dkit.refine.people import PeopleCalibration, PeopleConfig, calibrate_people
from gt3dkit.rig import Rig
from gt3dkit.synchronise import find_clocks
from gt3dkit.types import (
    BOX_MODEL_REGISTRY,
    GroundTruth,
    JsonDict,
    Options,
    Scene,
    TrackSet,
    json_list,
    json_num,
)

#: Published numbers of Ma et al. for the datasets we can compare on.
PAPER: dict[str, dict[str, float]] = {"multiviewx": {"MOTA": 96.5, "OSPA2_m": 0.17},
                                      "wildtrack": {"MOTA": 98.7, "OSPA2_m": 0.10}}
PAPER_PANOPTIC_MPJPE_MM = (6.1, 14.7)


def bundled(name: str) -> Path:
    """Path of a dataset bundled with the package (``gt3dkit/data/<name>``)."""
    return Path(str(resources.files("gt3dkit") / "data" / name))


#: CLI option -> estimator config field (and the value it sets).
_CONFIG_OPTIONS = {"sigma_px": ("--sigma-px", "sigma_px"), "accel_sd": ("--accel-sd", "accel_sd"),
                   "no_smooth": ("--no-smooth", "smooth"), "no_bones": ("--no-bones", "bones")}


def estimator_config(args: argparse.Namespace) -> Options:
    """The estimator's config from the options given; an option the estimator has no use for
    is an error, never silently ignored."""
    from importlib import import_module


    e = REGISTRY[args.estimator]
    fields = {f.name for f in dataclasses.fields(getattr(import_module(e.module), e.config))}
    cfg: Options = {}
    for attr, (option, name) in _CONFIG_OPTIONS.items():
        v = getattr(args, attr, None)
        if v is None or v is False:
            continue
        if name not in fields:
            raise InputError(option, f"does not apply to the {args.estimator} estimator")
        cfg[name] = (not v) if isinstance(v, bool) else v
    return cfg


def check_out_apart(out: str | Path, inp: str | Path, option: str = "--out", inside_ok: bool = False) -> None:
    """Refuse an output folder that is, contains or lies inside the input folder: results
    must never overwrite (or be mistaken for) annotations. ``inside_ok``: a subfolder of the
    input is fine (a report or an export inside a gt3d output)."""
    o, i = Path(out).resolve(), Path(inp).resolve()
    if o == i or o in i.parents or (i in o.parents and not inside_ok):
        raise InputError(option, f"{out} is, contains or lies inside the input folder {inp}: "
                                 "choose an output folder apart from the input")


def check_output(out: str | Path, inputs: tuple[str | Path, ...] = (), option: str = "--out") -> None:
    """Every check of an output folder (the user's ``option``) that can be made before the work
    starts."""
    for inp in inputs:
        check_out_apart(out, inp, option)
    check_out(out, option)


def panoptic_options(args: argparse.Namespace, layout: str) -> JsonDict:
    """The CMU Panoptic reader's options of ``args`` (``--cameras``, ``--noise-px``, ``--seed``),
    refused for any other layout."""
    opts: JsonDict = {}
    if layout == "panoptic":
        if args.cameras is not None:
            opts["cameras"] = [c.strip() for c in args.cameras.split(",") if c.strip()]
            if not opts["cameras"]:
                raise InputError("--cameras", f"no camera names in {args.cameras!r}")
        opts["noise_px"], opts["seed"] = args.noise_px, args.seed or 0
    else:
        for option, v in (("--cameras", args.cameras), ("--noise-px", args.noise_px or None),
                          ("--seed", args.seed)):
            if v is not None:
                raise InputError(option, f"applies to CMU Panoptic inputs only, not {layout}")
    return opts


def load_input(args: argparse.Namespace, by_windows: bool = False, calib: str | None = None,
               clocks: CameraClocks | None = None, head: Scene | None = None) -> Any:
    """The input of a command's ``args``, read and checked (:func:`gt3dkit.api.load_scene`);
    ``by_windows``: without its rows where its windows can read their own frames
    (:func:`gt3dkit.api.load_head`), as a long sequence run in windows does; ``calib``: this
    calibration in place of ``args.calib``; ``clocks``: these in place of ``--time-offsets``';
    ``head``: the input as read ``by_windows`` (what that read is not read again)."""

    if getattr(args, "out", None) is not None:
        check_output(args.out, (args.input,))
    calib = calib or getattr(args, "calib", None)
    if calib == "people":
        raise InputError("--calib", "people applies to gt3d reconstruct; gt3d calib people writes the rig "
                                    "for the other commands")
    layout = args.layout or detect_layout(Path(args.input))
    opts = panoptic_options(args, layout)
    association: str | None = getattr(args, "association", None)
    segments: str | None = getattr(args, "segments", None)
    box_model = str(getattr(args, "box_model", "auto"))

    def read(on: CameraClocks | None) -> Scene:
        source = Path(args.input) if head is None else head
        return load_scene(source, layout, args.skeleton, getattr(args, "fps", None), calib=calib,
                          association=association, segments=segments, box_model=box_model, clocks=on,
                          **opts)

    clocks = clocks or time_offsets(args, calib, read)
    if by_windows and clocks is None and association is None and segments is None:
        head = load_head(Path(args.input), layout, getattr(args, "fps", None), calib, box_model)
        if head is not None:
            return head
    scene = read(clocks)
    if box_model != "auto" and not scene.obs.has_box.any():
        # one rule for an option the input has nothing for (as --skeleton on boxes, --association
        # on a native input): refused, not ignored
        raise InputError("--box-model", f"applies to inputs with boxes: {args.input} has keypoints only")
    return scene


def time_offsets(args: argparse.Namespace, calib: str | None, read: Callable[[CameraClocks], Scene],
                 start: Clocks | None = None) -> CameraClocks | None:
    """``--time-offsets``: the file's clocks, or with ``auto`` each camera's clock found from the
    people in the input through its calibration (``calib`` in place of ``args.calib``; ``read``
    loads the input onto given clocks; ``start``: pairwise clocks already found;
    :func:`gt3dkit.synchronise.find_clocks`); None without the option."""
    given = getattr(args, "time_offsets", None)
    if given is None:
        return None
    if given != "auto":
        return read_time_offsets(Path(given))
    det = detections_input(args, calib)
    if det.obs.n_joints == 0:
        raise InputError("--time-offsets", "auto finds the clocks from the people's keypoints; this input "
                                           "has boxes only: give each camera's clock as a file")
    found, rep = find_clocks(det, read, start)
    print_clocks(found.names, found.late_frames, found.sd_frames,
                 f"{len(json_list(rep, 'rounds'))} rounds against the reconstruction, "
                 f"{json_num(rep, 'seconds') or 0.0:.1f} s; "
                 "meta.json input")
    return found


def print_clocks(names: tuple[str, ...], late: np.ndarray, sd: np.ndarray, where: str = "meta.json input"
                 ) -> None:
    """One line: each camera's clock found from the people."""
    print(f"clocks from the people (frames late against camera {names[0]}, sd; {where}): "
          + ", ".join(f"{n} {round(d, 2) + 0.0:+.2f} ({s:.2f})"
                      for n, d, s in zip(names, late, sd, strict=True)))


def detections_input(args: argparse.Namespace, calib: str | None = None) -> Scene:
    """The input of ``args`` as each camera's detections, with no identities across cameras
    (:func:`gt3dkit.api.load_detections`); ``calib``: this calibration's intrinsics in place of the
    input's."""
    layout = args.layout or detect_layout(Path(args.input))
    return load_detections(Path(args.input), layout, args.skeleton, getattr(args, "fps", None), calib,
                           **panoptic_options(args, layout))


def people_rig(scene: Scene, cfg: PeopleConfig) -> PeopleCalibration:
    """The rig from the people of ``scene``'s detections: from their keypoints
    (:func:`gt3dkit.refine.people.calibrate_people`), or where it has boxes only, from their boxes
    (:func:`gt3dkit.refine.boxpeople.calibrate_boxes`: the ids must name a person in every camera)."""
    if scene.obs.n_joints > 0:
        return calibrate_people(scene, cfg)
    where = scene.root or "input"
    if scene.layout in ASSOCIATED:
        raise InputError(where, "a rig from boxes needs each person's id the same in every camera; "
                                f"{scene.layout}'s ids are each camera's own")
    for on, option in ((cfg.clocks, "--clocks / --time-offsets auto"),
                       (not cfg.focal_known, "--focal-unknown")):
        if on:
            raise InputError(option, "applies to keypoints (a rig from boxes takes the intrinsics given and "
                                     "one clock)")
    config = BoxPeopleConfig() if cfg.height_m is None else BoxPeopleConfig(height_m=cfg.height_m)
    return calibrate_boxes(scene, config)


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


class PeopleScene(NamedTuple):
    """``--calib people``'s input (:func:`scene_from_people`): the scene on the found rig, what
    meta.json records of it, and the way into the input's own calibration's frame (None: none)."""

    scene: Scene
    meta: JsonDict
    into_given: IntoGiven | None


def scene_from_people(args: argparse.Namespace) -> PeopleScene:
    """``--calib people``: the input with the rig :func:`gt3dkit.refine.people.calibrate_people`
    finds from its people (its own calibration's intrinsics), and what to record of it in
    meta.json (the rig and the report)."""
    det = detections_input(args)
    auto = getattr(args, "time_offsets", None) == "auto"
    res = people_rig(det, PeopleConfig(clocks=auto))
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)
    with tempfile.TemporaryDirectory() as tmp:
        write_native(res.rig, Path(tmp) / "cameras.json", fps=None if det.fps_assumed else det.fps)
        cal = str(Path(tmp) / "cameras.json")
        clocks = None
        if res.clocks is not None:  # the clocks the rig was adjusted on, held to the reconstruction
            clocks = time_offsets(args, cal, lambda on: load_input(args, calib=cal, clocks=on), res.clocks)
        scene = load_input(args, calib=cal, clocks=clocks)
    scene = dataclasses.replace(scene, load_options={**scene.load_options, "calib": None})
    print(f"cameras placed from the people: {len(res.rig.cameras)} ({res.report['seconds']:.1f} s, median "
          f"{res.report['reprojection_median_px']:.2f} px; meta.json: calibration_from_people)")
    return PeopleScene(scene, {"calibration_from_people": {**res.report, "rig": cameras_doc(res.rig, None)}},
                       into_given(res.rig, det.rig))


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


def clock(seconds: float) -> str:
    """``mm:ss`` (``h:mm:ss`` from an hour) of a duration."""
    s = int(round(max(seconds, 0.0)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60:02d}:{s % 60:02d}"


class Stages:
    """A one-line progress display of a run's stages on stderr (``stage [elapsed] k/n``): only on
    a terminal, only once the run has taken a second, never with ``--quiet``; erased at the end
    so that the summary and ``warning:`` lines stay as they are. :meth:`part` shows a stage's
    progress with the time it has left (``windows 3/10 done [01:12, about 02:48 left]``)."""

    def __init__(self, total: int, quiet: bool) -> None:
        self.total, self.k, self.name = total, 0, ""
        self.t0 = self._stage_t0 = time.monotonic()
        self.shown = False
        self._stop = threading.Event()
        self.on = not quiet and sys.stderr.isatty()
        if self.on:
            threading.Thread(target=self._tick, daemon=True).start()

    def _line(self) -> str:
        return f"\r{self.name} [{clock(time.monotonic() - self.t0)}] {self.k}/{self.total}\x1b[K"

    def _tick(self) -> None:
        while not self._stop.wait(0.5):
            if time.monotonic() - self.t0 >= 1.0:
                with contextlib.suppress(Exception):
                    sys.stderr.write(self._line())
                    sys.stderr.flush()
                    self.shown = True

    def __call__(self, name: str) -> None:
        self.k, self.name = min(self.k + 1, self.total), name
        self._stage_t0 = time.monotonic()

    def part(self, what: str, done: int, total: int) -> None:
        """``done`` of the current stage's ``total`` parts are finished (0: they start now): the
        line says so, with the time left at the pace so far."""
        if done == 0:  # the parts start now (after the stage's own preliminaries)
            self._stage_t0 = time.monotonic()
        spent = time.monotonic() - self._stage_t0
        self.name = f"{what} {done}/{total} done" + (
            f", about {clock(spent / done * (total - done))} left" if 0 < done < total else "")

    def close(self) -> None:
        self._stop.set()
        if self.on and self.shown:
            with contextlib.suppress(Exception):
                sys.stderr.write("\r\x1b[K")
                sys.stderr.flush()


class Parser(argparse.ArgumentParser):
    """argparse with the one-line ``error: <entry>: <problem>`` (exit 2) of every other error."""

    def error(self, message: str) -> NoReturn:
        print(f"error: {self.prog}: {message} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(2)


def number_type(kind: type, lo: float, hi: float, *, lo_open: bool = False,
            hi_open: bool = False) -> Callable[[str], Any]:
    """argparse type: a finite ``kind`` in [lo, hi] (open ends where asked)."""
    def parse(text: str) -> Any:
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}"
                                             f", got {text!r}") from None
        ok = (np.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi))
        if not ok:
            raise argparse.ArgumentTypeError(
                f"must be in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}, got {text}")
        return v
    return parse


def scheduler_address(text: str) -> str:
    """argparse type of ``--scheduler``: a non-empty address (an unset shell variable gives an
    empty one, which would otherwise run locally without a word); Dask's own check of it runs
    when the client connects (:func:`gt3dkit.early.check_scheduler_address`)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty address (an unset variable?): give tcp://HOST:PORT, "
                                         "or leave --scheduler out to run here")
    return text.strip()


FRACTION = number_type(float, 0, 1)
PIXELS = number_type(float, 0, 1000)              # image noise, px
SIGMA_PX = number_type(float, 1e-3, 1000)
ACCEL = number_type(float, 1e-6, 1000)             # m/s^2/sqrt(Hz)
FPS = number_type(float, 1e-3, 1e6)                # one frame per 17 minutes .. 1 MHz
SEED = number_type(int, 0, 2**32 - 1)


class Terminated(BaseException):
    """SIGTERM or SIGHUP, raised where the program is so that clean-ups run."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


#: signals received during this run: an exception raised by a signal handler inside a C
#: extension's initialisation (numba loading its thread pool) reaches us as an ImportError
RECEIVED_SIGNALS: list[int] = []


def _after_a_signal(unraisable: sys.UnraisableHookArgs) -> None:
    """Objects the signal left half-built (numba's compiler, interrupted mid-function) may fail in
    their finalisers as the process ends; the user has their one ``error:`` line already."""


def on_terminate(signum: int, frame: FrameType | None) -> None:
    RECEIVED_SIGNALS.append(signum)
    sys.unraisablehook = _after_a_signal
    raise Terminated(signum)


def on_interrupt(signum: int, frame: FrameType | None) -> None:
    RECEIVED_SIGNALS.append(signum)
    sys.unraisablehook = _after_a_signal
    raise KeyboardInterrupt


@contextlib.contextmanager
def signals_handled() -> Any:
    """While a command runs: SIGTERM and SIGHUP raise :class:`Terminated`, SIGINT (unless the
    shell ignores it, as for a background job) ``KeyboardInterrupt``, each noted in
    :data:`RECEIVED_SIGNALS`; the previous handlers are put back after (not in a thread other
    than the main one, where handlers cannot be set)."""
    previous = {}
    handlers = [(signal.SIGTERM, on_terminate), (signal.SIGHUP, on_terminate)]
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        handlers.append((signal.SIGINT, on_interrupt))
    RECEIVED_SIGNALS.clear()
    for sig, handler in handlers:
        try:
            previous[sig] = signal.signal(sig, handler)
        except ValueError:  # not the main thread
            pass
    try:
        yield
    finally:
        for sig, h in previous.items():
            signal.signal(sig, h)


def unexpected_error(e: Exception, debug: bool) -> int:
    """The one line (and exit status) of an exception nothing else handled: a signal's, wrapped by
    the code it interrupted (130 / 143), else a bug (1; ``debug`` prints the traceback)."""
    if RECEIVED_SIGNALS:
        how = ("interrupted (Ctrl-C)" if RECEIVED_SIGNALS[0] == signal.SIGINT
               else f"stopped by {signal.Signals(RECEIVED_SIGNALS[0]).name}")
        print(f"error: {how}: no output written or changed", file=sys.stderr)
        return 128 + RECEIVED_SIGNALS[0]
    if debug:
        traceback.print_exc()
    where = traceback.extract_tb(e.__traceback__)[-1]
    print(f"error: internal error, {type(e).__name__}: {e} (at {Path(where.filename).name}:"
          f"{where.lineno}; please report it, --debug shows the traceback)", file=sys.stderr)
    return 1


def quiet_stdout() -> None:
    """After a broken pipe: send what Python still flushes at exit nowhere."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass

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
from importlib import resources
from pathlib import Path
from types import FrameType
from typing import Any, NamedTuple, NoReturn

import numpy as np

from gt3dkit.api import disagreeing_cameras, load_detections, load_head, load_scene, reconstruct
from gt3dkit.calib.formats.native import cameras_doc, write as write_native
from gt3dkit.commands.printing import IntoGiven, into_given
from gt3dkit.errors import InputError
from gt3dkit.fusion.base import REGISTRY
from gt3dkit.fusion.preparation.associate import Association
from gt3dkit.io.atomic import check_out
from gt3dkit.io.clocks import CameraClocks, read_time_offsets
from gt3dkit.io.datasets import ASSOCIATED, Calibration, detect_layout
from gt3dkit.jsondoc import json_list, json_num
from gt3dkit.refine.boxpeople import BoxPeopleConfig, calibrate_boxes
from gt3dkit.refine.clocks import Clocks
from gt3dkit.refine.people import PeopleCalibration, PeopleConfig, calibrate_people
from gt3dkit.refine.repose import correspondences, reposed
from gt3dkit.synchronise import find_clocks
from gt3dkit.types import (
    JsonDict,
    Options,
    Scene,
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


def calibration_of(args: argparse.Namespace, calib: str | Calibration | None) -> str | Calibration | None:
    """``calib`` (a path; None: beside the input) with ``--calib-units`` where given; a
    :class:`Calibration` as it is."""
    units = getattr(args, "calib_units", None)
    if isinstance(calib, Calibration) or units is None:
        return calib
    return Calibration(calib, units)


def load_input(args: argparse.Namespace, by_windows: bool = False, calib: str | Calibration | None = None,
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

    calib_spec = calibration_of(args, calib)

    def read(on: CameraClocks | None) -> Scene:
        source = Path(args.input) if head is None else head
        return load_scene(source, layout, args.skeleton, getattr(args, "fps", None), calib=calib_spec,
                          association=association, segments=segments, box_model=box_model, clocks=on,
                          **opts)

    clocks = clocks or time_offsets(args, calib, read)
    if by_windows and clocks is None and association is None and segments is None:
        head = load_head(Path(args.input), layout, getattr(args, "fps", None), calib_spec, box_model)
        if head is not None:
            return head
    scene = read(clocks)
    if box_model != "auto" and not scene.obs.has_box.any():
        # one rule for an option the input has nothing for (as --skeleton on boxes, --association
        # on a native input): refused, not ignored
        raise InputError("--box-model", f"applies to inputs with boxes: {args.input} has keypoints only")
    return scene


def time_offsets(args: argparse.Namespace, calib: str | Calibration | None,
                 read: Callable[[CameraClocks], Scene], start: Clocks | None = None) -> CameraClocks | None:
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


def detections_input(args: argparse.Namespace, calib: str | Calibration | None = None) -> Scene:
    """The input of ``args`` as each camera's detections, with no identities across cameras
    (:func:`gt3dkit.api.load_detections`); ``calib``: this calibration's intrinsics in place of the
    input's."""
    layout = args.layout or detect_layout(Path(args.input))
    return load_detections(Path(args.input), layout, args.skeleton, getattr(args, "fps", None),
                           calibration_of(args, calib), **panoptic_options(args, layout))


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


def with_reposed_cameras(args: argparse.Namespace, scene: Scene) -> tuple[Scene, JsonDict]:
    """``--refine-calib``'s first step: each camera whose calibration fits no other camera's
    (:func:`gt3dkit.api.disagreeing_cameras`: the association left all its detections out) posed
    again on the people the others place (:mod:`gt3dkit.refine.repose`), and the input read again
    on that rig (its views kept now); what was done, for ``meta.json``. The scene as it is where
    no camera disagrees."""
    assoc = scene.association
    bad = [cam for cam, _ in disagreeing_cameras(assoc)] if isinstance(assoc, Association) else []
    calib = getattr(args, "calib", None)
    if not bad or calib == "people":  # (a rig found from the people was fitted to them all)
        return scene, {}
    first = reconstruct(scene, "ukf")
    det = detections_input(args, calib)
    rig = scene.rig
    report: JsonDict = {}
    for name in bad:
        X, uv = correspondences(det.obs, det.rig.index(name), first)
        rig, found = reposed(rig, name, X, uv)
        report[name] = found
        was, now = json_num(found, "median_px_before") or 0.0, json_num(found, "median_px_after") or 0.0
        print(f"camera {name} posed again on the people the others place: median {was:.1f} -> {now:.1f} px, "
              f"focal {json_num(found, 'focal_px') or 0.0:.1f} px (meta.json: calibration_refinement)")
    with tempfile.TemporaryDirectory() as tmp:
        write_native(rig, Path(tmp) / "cameras.json", fps=None if scene.fps_assumed else scene.fps)
        again = load_input(args, calib=Calibration(str(Path(tmp) / "cameras.json"), "m"))
    # the input's own calibration recorded (the rig the run used goes to meta.json)
    return (dataclasses.replace(again, load_options=scene.load_options, fps_assumed=scene.fps_assumed),
            {"reposed_cameras": report})


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

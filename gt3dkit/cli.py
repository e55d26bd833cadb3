"""``gt3d``: parse, call the library, print. No maths here."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import signal
import sys
import threading
import traceback
import warnings
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from gt3dkit.api import ESTIMATORS, load_scene, reconstruct
from gt3dkit.calib.formats import WRITABLE, detect_format, read_calibration
from gt3dkit.calib.formats.native import cameras_doc
from gt3dkit.calib.show import camera_table, rig_warnings
from gt3dkit.compare import compare
from gt3dkit.errors import EstimationError, InputError
from gt3dkit.eval.metrics import box_errors, relabel_to_truth
from gt3dkit.eval.pose import mpjpe_by_id, score_tracks
from gt3dkit.eval.tracking import tracking_scores
from gt3dkit.export import export
from gt3dkit.fusion.base import REGISTRY
from gt3dkit.io.atomic import check_out, write_dir_atomically
from gt3dkit.io.datasets import LAYOUTS, detect_layout
from gt3dkit.io.results import read_result
from gt3dkit.io.writers import read_keypoints_csv, read_tracks_csv, write_refined_calibration
from gt3dkit.many import read_manifest, run_many
from gt3dkit.refine import RefineConfig, refine, rig_digest, scene_warnings
from gt3dkit.sim import (
    SIM_LAYOUTS,
    Errors,
    simulate,
    simulate_skeletons,
    to_z_up,
    write_coco,
    write_openpose,
    write_scene,
    write_skeleton_scene,
)
from gt3dkit.skeletons import DETECTOR_SKELETONS, SKELETONS
from gt3dkit.threads import small_matrix_blas
from gt3dkit.viz.report import write_report

#: Published numbers of Ma et al. for the datasets we can compare on.
PAPER = {"multiviewx": {"MOTA": 96.5, "OSPA2_m": 0.17}, "wildtrack": {"MOTA": 98.7, "OSPA2_m": 0.10},
         "panoptic": {"MPJPE_mm": (6.1, 14.7)}}


def bundled(name: str) -> Path:
    """Path of a dataset bundled with the package (``gt3dkit/data/<name>``)."""
    return Path(str(resources.files("gt3dkit") / "data" / name))


#: CLI option -> estimator config field (and the value it sets).
_CONFIG_OPTIONS = {"sigma_px": ("--sigma-px", "sigma_px"), "accel_sd": ("--accel-sd", "accel_sd"),
                   "no_smooth": ("--no-smooth", "smooth"), "no_bones": ("--no-bones", "bones")}


def _estimator_config(args: argparse.Namespace) -> dict[str, Any]:
    """The estimator's config from the options given; an option the estimator has no use for
    is an error, never silently ignored."""
    from importlib import import_module


    e = REGISTRY[args.estimator]
    fields = {f.name for f in dataclasses.fields(getattr(import_module(e.module), e.config))}
    cfg: dict[str, Any] = {}
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


def check_output(out: str | Path, inputs: tuple[str | Path, ...] = ()) -> None:
    """Every check of an output folder that can be made before the work starts."""

    for inp in inputs:
        check_out_apart(out, inp)
    check_out(out)


def _load(args: argparse.Namespace) -> Any:

    if getattr(args, "out", None) is not None:
        check_output(args.out, (args.input,))
    layout = args.layout or detect_layout(Path(args.input))
    opts: dict[str, Any] = {}
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
    if getattr(args, "association", None) is not None:
        opts["association"] = args.association
    scene = load_scene(Path(args.input), layout, args.skeleton, getattr(args, "fps", None),
                       calib=getattr(args, "calib", None), **opts)
    return scene


def print_warnings(scene: Any) -> None:
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


def _num(v: float | None, width: int, digits: int) -> str:
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
                     f"{_num(p.mpjpe_mm, 11, 4)}{_num(by_id, 10, 4)}")
    return "\n".join(lines)


def report_truth(scene: Any, tracks: Any, name: str, max_dist_m: float = 1.0) -> None:
    """Print errors against the input's truth: boxes/positions and/or keypoints; tracking scores
    count an estimate within ``max_dist_m`` (ground plane) of a true object as a match."""

    if scene.truth is None:
        return
    print(f"against {scene.truth.source}:")
    if scene.association is not None:

        tracks = relabel_to_truth(tracks, scene.truth, scene.rig.up, max_dist_m)
        print("(ids are gt3dkit's cross-view association: each matched to its truth id for the errors)")
    if np.isfinite(scene.truth.center_world).any():

        t = tracking_scores(tracks, scene.truth, scene.rig.up, max_dist_m)
        print(error_table([(name, box_errors(tracks, scene.truth, scene.rig.up, max_dist_m, mot=t))]))
        print(f"ground plane, {max_dist_m:g} m: MOTA {100 * t['mota']:.1f}  IDF1 {100 * t['idf1']:.1f}  "
              f"FP {t['fp']}  FN {t['fn']}  IDs {t['ids']}  HOTA {100 * t['hota']:.1f}  "
              f"OSPA(2) {t['ospa2_m']:.4f} m")
    if scene.truth.kpt_world.shape[1] and tracks.kpt_world.shape[1]:
        sets = [("all joints", None)]
        if scene.skeleton == "coco19":
            sets.append(("15 body joints", np.arange(15)))
        print(pose_table([(f"{name}, {label}", score_tracks(tracks, scene.truth, j),
                           mpjpe_by_id(tracks, scene.truth, j)[0]) for label, j in sets]))


class Stages:
    """A one-line progress display of a run's stages on stderr (``stage [elapsed] k/n``): only on
    a terminal, only once the run has taken a second, never with ``--quiet``; erased at the end
    so that the summary and ``warning:`` lines stay as they are."""

    def __init__(self, total: int, quiet: bool) -> None:
        import time

        self.total, self.k, self.name = total, 0, ""
        self.t0 = time.monotonic()
        self.shown = False
        self._stop = threading.Event()
        self.on = not quiet and sys.stderr.isatty()
        if self.on:
            threading.Thread(target=self._tick, daemon=True).start()

    def _line(self) -> str:
        import time

        s = int(time.monotonic() - self.t0)
        return f"\r{self.name} [{s // 60:02d}:{s % 60:02d}] {self.k}/{self.total}\x1b[K"

    def _tick(self) -> None:
        while not self._stop.wait(0.5):
            import time

            if time.monotonic() - self.t0 >= 1.0:
                with contextlib.suppress(Exception):
                    sys.stderr.write(self._line())
                    sys.stderr.flush()
                    self.shown = True

    def __call__(self, name: str) -> None:
        self.k, self.name = min(self.k + 1, self.total), name

    def close(self) -> None:
        self._stop.set()
        if self.on and self.shown:
            with contextlib.suppress(Exception):
                sys.stderr.write("\r\x1b[K")
                sys.stderr.flush()


def cmd_reconstruct(args: argparse.Namespace) -> int:

    config = _estimator_config(args)
    stages = Stages(5, args.quiet)
    stages("loading")
    scene = _load(args)
    extra = None
    if args.refine_calib:

        res = refine(scene)
        extra = {"calibration_refinement": {**res.report, "rig_sha256": {
            "input": rig_digest(scene.rig), "refined": rig_digest(res.rig)},
            "refined_rig": json.loads(json.dumps(cameras_doc(res.rig, None)))}}
        scene = dataclasses.replace(scene, rig=res.rig)
        print(f"calibration refined: {', '.join(res.report['refined_cameras']) or 'no camera'} "
              f"({res.report['seconds']:.1f} s; meta.json: calibration_refinement)")
    try:
        tracks = reconstruct(scene, args.estimator, out=args.out, extra_meta=extra, on_stage=stages,
                             **config)
    finally:
        stages.close()
    print_warnings(scene)
    info = tracks.info
    kinds = " + ".join(k for k, v in (("boxes", scene.obs.has_box.any()),
                                      (f"{scene.skeleton} keypoints", scene.obs.n_joints > 0)) if v)
    fps = f"{scene.fps:g} fps" + (" (assumed)" if scene.fps_assumed else "")
    rob = info.get("robust", {})
    flagged = (f", {rob['rejected']} measurements rejected and {rob['downweighted']} "
               f"down-weighted (downweighted.csv)" if rob.get("enabled") else "")
    qa = info.get("qa", {}).get("anomalies", {})
    flagged += (", anomalies: " + ", ".join(f"{v} {k}" for k, v in qa.items()) + " (anomalies.csv)"
                if qa else ", no anomalies")
    print(f"{scene.layout}: {len(scene.obs)} annotation rows ({kinds}), {len(scene.rig.cameras)} "
          f"cameras, {fps} -> {len(tracks)} object-frames of {len(set(tracks.track_id.tolist()))} "
          f"objects ({args.estimator}, {info.get('seconds', 0):.2f} s{flagged}) written to "
          f"{args.out}")
    report_truth(scene, tracks, args.estimator)
    return 0


def _errors(args: argparse.Namespace) -> Any:

    gap = None
    if args.gap:
        try:
            a, b = (int(v) for v in args.gap.split(":"))
        except ValueError:
            raise InputError("--gap", f"expected FIRST:END frame indices, got {args.gap!r}") from None
        if not 0 <= a < b <= args.frames:
            raise InputError("--gap", f"expected 0 <= FIRST < END <= --frames ({args.frames}), "
                                      f"got {args.gap}")
        gap = (a, b)
    try:
        return Errors(outliers=args.outliers, swaps=args.swaps, glitch=args.glitch,
                      shifted=args.shifted, gap=gap, single_view=args.single_view)
    except ValueError as e:
        raise InputError("simulate", str(e)) from None


#: Largest simulated scene, in 2D annotations (boxes, or keypoints): about 2 GB of memory.
SIM_MAX_POINTS = 20_000_000


#: simulate options that apply to one kind of scene only.
_SIM_ONLY = {"boxes": ("motion", "dropout", "shifted", "global_ids"),
             "skeleton": ("missing", "skeleton", "conf", "outliers", "swaps", "glitch")}


def cmd_simulate(args: argparse.Namespace) -> int:

    check_output(args.out)
    for kind, names in _SIM_ONLY.items():
        for n in names:
            if args.kind != kind and getattr(args, n) not in (None, False, 0.0):
                raise InputError(f"--{n}", f"applies to --kind {kind} scenes")
    kinds = {"mot": "boxes", "cvat": "boxes", "coco": "skeleton", "openpose": "skeleton"}
    if args.format and kinds[args.format] != args.kind:
        raise InputError("--format", f"{args.format} is written for --kind {kinds[args.format]} scenes")
    if args.global_ids and args.format not in ("mot", "cvat"):
        raise InputError("--global-ids", "applies to --format mot or cvat")
    if args.no_track_ids and args.format != "coco":
        raise InputError("--no-track-ids", "applies to --format coco")
    if args.format == "openpose" and args.skeleton is None:
        args.skeleton = "body25"
    args.motion, args.dropout = args.motion or "smooth", 0.15 if args.dropout is None else args.dropout
    args.missing = 0.05 if args.missing is None else args.missing
    args.skeleton = args.skeleton or "coco19"
    errors = _errors(args)
    cams = args.cameras or (10 if args.kind == "skeleton" else 6)
    per = SKELETONS[args.skeleton].n_joints if args.kind == "skeleton" else 1
    size = args.frames * args.people * cams * per
    if size > SIM_MAX_POINTS:
        raise InputError("--frames/--people/--cameras",
                         f"{args.frames} frames x {args.people} people x {cams} cameras"
                         + (f" x {per} joints" if per > 1 else "")
                         + f" = {size:.3g} annotations, more than the {SIM_MAX_POINTS:.0e} "
                           "gt3d simulate writes")
    n_err = ""
    if args.kind == "skeleton":
        try:
            sk = simulate_skeletons(args.layout, seed=args.seed, frames=args.frames,
                                    people=args.people, noise_px=args.noise_px,
                                    missing=args.missing, cameras=args.cameras or 10,
                                    skeleton=args.skeleton, errors=errors,
                                    confidences=args.conf, fps=args.fps or 30.0)
        except ValueError as e:
            raise InputError("simulate", str(e)) from None
        if args.format == "openpose":

            if args.skeleton not in {n for v in DETECTOR_SKELETONS.values() for n in v}:
                raise InputError("--skeleton", "OpenPose files hold a detector skeleton (body25, body25b, "
                                               f"halpe26, coco18, coco17), not {args.skeleton}")
            write_openpose(to_z_up(sk), Path(args.out), seed=args.seed)
        elif args.format == "coco":

            write_coco(sk, Path(args.out), track_ids=not args.no_track_ids, seed=args.seed)
        else:
            write_skeleton_scene(sk, Path(args.out), args.layout)
        if sk.injected:
            n_err = f", {len(sk.injected)} injected errors (injected.csv)"
        print(f"wrote {args.format or args.layout} skeleton scene to {args.out}: {args.cameras or 10} "
              "cameras, "
              f"{args.frames} frames, {args.people} people ({args.skeleton}), "
              f"{'z-up' if args.format == 'openpose' else 'y-down'} world{n_err}")
        return 0
    if args.layout == "panoptic":
        raise InputError("simulate", "box scenes are native, wildtrack or multiviewx")
    try:
        sim = simulate(args.layout, seed=args.seed, frames=args.frames, people=args.people,
                       noise_px=args.noise_px, dropout=args.dropout, errors=errors,
                       motion=args.motion, cameras=args.cameras, fps=args.fps)
    except ValueError as e:
        raise InputError("simulate", str(e)) from None
    if args.format in ("mot", "cvat"):
        write_scene(sim, Path(args.out), args.format, id_seed=None if args.global_ids else args.seed)
    else:
        write_scene(sim, Path(args.out), args.layout)
    seen = int(np.isfinite(sim.boxes[..., 0]).sum())
    if sim.injected:
        n_err = f", {len(sim.injected)} injected errors (injected.csv)"
    form = (f"{args.layout} rig as {args.format.upper()} files per camera ("
            + ("global ids" if args.global_ids else "ids numbered per camera") + ")"
            if args.format else args.layout)
    print(f"wrote {form} scene to {args.out}: {len(sim.rig.cameras)} cameras, "
          f"{len(sim.frames)} frames at {sim.fps:g} fps, {args.people} people, {seen} boxes, "
          f"truth.csv{n_err}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:

    if not Path(args.out).is_dir():
        raise InputError(str(args.out), "not a folder (expected a gt3d reconstruct output)")
    if not (Path(args.out) / "tracks.csv").is_file():
        raise InputError(str(args.out), "no tracks.csv (expected a gt3d reconstruct output)")
    tracks = read_tracks_csv(Path(args.out) / "tracks.csv")
    scene = load_scene(Path(args.truth), args.layout)
    if scene.truth is None:
        raise InputError(str(args.truth), "this input carries no truth (positions, truth.csv, "
                                          "truth_keypoints.csv or Panoptic joints)")
    kp = Path(args.out) / "keypoints.csv"
    if kp.exists() and scene.obs.n_joints:
        tracks = read_keypoints_csv(kp, tracks, scene.obs.n_joints)
    print(f"{args.out} against the truth of {args.truth}:")
    report_truth(scene, tracks, Path(args.out).name, args.max_dist_m)
    return 0


def cmd_compare(args: argparse.Namespace) -> int:

    scene = _load(args)
    table = compare(scene, Path(args.out), progress=not args.no_progress)
    print_warnings(scene)
    print(f"{scene.layout}: {len(scene.obs)} annotation rows -> {args.out}/comparison.csv")
    names = [r["estimator"] for r in table if "failed" not in r]
    head = f"{'estimator':<15}{'rows':>6}{'reproj px':>10}{'p95 px':>8}" + "".join(
        f"{'to ' + n + ' m':>20}" for n in names) + f"{'sec':>8}" + (
        f"{'truth err m':>13}" if scene.truth is not None else "")
    print(head)
    print("-" * len(head))
    for r in table:
        if "failed" in r:
            print(f"{r['estimator']:<15}failed: {r['failed']}")
            continue
        line = (f"{r['estimator']:<15}{r['rows']:>6}{_num(r['reproj_mean_px'], 10, 3)}"
                f"{_num(r['reproj_p95_px'], 8, 3)}")
        for n in names:
            v = r.get(f"dist_to_{n}_mean_m")
            line += _num(v, 20, 5)
        line += f"{r['seconds']:>8.1f}"
        if scene.truth is not None:
            v = r.get("truth_mpjpe_m", r.get("truth_centre_mean_m"))
            if v is None or not np.isfinite(v):
                v = r.get("truth_ground_mean_m")
            line += _num(v, 13, 5)
        print(line)
    return 0


def cmd_calib_show(args: argparse.Namespace) -> int:

    scene = None
    try:
        scene = load_scene(Path(args.input))
        rig = scene.rig
        what = f"{scene.layout} input {args.input}"
    except InputError:
        if Path(args.input).is_dir() and (Path(args.input) / "cameras.json").exists():
            raise  # an input folder with a problem: say it
        rig = read_calibration(Path(args.input))
        fmt = detect_format(Path(args.input))
        what = f"{fmt} calibration {args.input}"
        if fmt in ("opencv", "toml", "colmap"):
            what += " (the format has no up vector: +z assumed)"
    print(f"{what}: {len(rig.cameras)} cameras, up {np.round(rig.up, 4).tolist()}")
    head = (f"{'camera':<12}{'centre x':>9}{'y':>8}{'z':>8}{'height':>8}{'tilt°':>7}"
            f"{'fx':>8}{'fy':>8}{'cx':>7}{'cy':>7}{'k1':>8}{'k2':>8}{'size':>11}")
    print(head)
    print("-" * len(head))
    for t in camera_table(rig):
        x, y, z = t["centre_m"]
        print(f"{t['camera']:<12}{x:>9.3f}{y:>8.3f}{z:>8.3f}{t['height_m']:>8.3f}{t['tilt_deg']:>7.1f}"
              f"{t['fx_px']:>8.1f}{t['fy_px']:>8.1f}{t['cx_px']:>7.1f}{t['cy_px']:>7.1f}"
              f"{t['dist'][0]:>8.4f}{t['dist'][1]:>8.4f}{t['size'][0]:>6}x{t['size'][1]:<4}")
    warns = rig_warnings(rig) + (scene_warnings(scene) if scene is not None else [])
    if scene is not None:
        print_warnings(scene)
    for w in warns:
        print(f"warning: {w}", file=sys.stderr)
    print(f"{len(warns)} calibration warnings")
    return 0


def cmd_calib_refine(args: argparse.Namespace) -> int:

    scene = _load(args)
    res = refine(scene, RefineConfig(refine_intrinsics=args.refine_intrinsics))
    write_refined_calibration(Path(args.out), scene, res, args.format)
    print_warnings(scene)
    rep = res.report
    print(f"{scene.layout}: {len(scene.rig.cameras)} cameras, {rep['method']} -> refined "
          f"{len(rep['refined_cameras'])} ({', '.join(rep['refined_cameras']) or 'none'}) in "
          f"{rep['seconds']:.1f} s; written to {args.out}")
    print(f"{'camera':<12}{'refined':>8}{'moved cm':>10}{'moved °':>9}{'px before':>11}{'px after':>10}  why")
    for name, c in rep["cameras"].items():
        print(f"{name:<12}{'yes' if c['refined'] else 'no':>8}{100 * c['centre_moved_m']:>10.2f}"
              f"{c['rotation_moved_deg']:>9.3f}{_num(c['median_px_before'], 11, 3)}"
              f"{_num(c['median_px_after'], 10, 3)}  {c['why']}")
    return 0


def cmd_reconstruct_many(args: argparse.Namespace) -> int:

    inputs = read_manifest(Path(args.manifest))
    rows = run_many(inputs, Path(args.out), args.estimator, args.jobs, args.scheduler, args.report,
                    progress=not args.quiet)
    width = max(len(Path(r["input"]).name) for r in rows)
    for r in rows:
        print(f"{Path(r['input']).name:<{width}}  {r['status']:<10} {r['seconds']:>8.1f} s  "
              f"{r['object_frames'] or '':>6} object-frames  {r['error']}")
    failed = [Path(r["input"]).name for r in rows if r["status"] == "failed"]
    done = sum(r["status"] == "done" for r in rows)
    print(f"{len(rows)} sequences: {done} reconstructed, {sum(r['status'] == 'up to date' for r in rows)} up "
          f"to date, {len(failed)} failed -> {args.out}/summary.csv"
          + (f", {args.out}/index.html" if args.report else ""))
    if failed:
        print(f"error: {len(failed)} sequence{'s' if len(failed) > 1 else ''} failed: {', '.join(failed)} "
              f"(see {args.out}/summary.csv)", file=sys.stderr)
        return 1
    return 0


def cmd_associate(args: argparse.Namespace) -> int:

    scene = _load(args)
    if scene.association is None:
        raise InputError(args.input, f"{scene.layout}: its ids are already global (nothing to associate)")
    write_dir_atomically(Path(args.out), lambda tmp: scene.association.write(tmp / "association.csv"))
    print_warnings(scene)
    print(f"{scene.layout}: {scene.association.summary()} -> {args.out}/association.csv")
    return 0


def cmd_report(args: argparse.Namespace) -> int:

    out = Path(args.out)
    if out.is_dir() and (out / "report").exists():
        check_output(out / "report")
    index, warnings = write_report(out)
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    n = sum(1 for _ in index.parent.rglob("*.png"))
    print(f"report: {index} ({n} pictures; open it in a browser)")
    return 0


def cmd_export(args: argparse.Namespace) -> int:

    out = Path(args.out)
    dest = Path(args.to) if args.to else out / f"export_{args.format}"
    res = read_result(out)
    root = ((res.meta.get("input") or {}).get("load") or {}).get("root") or res.meta["input"].get("root")
    check_out_apart(dest, out, "--to", inside_ok=True)
    if isinstance(root, str) and root:
        check_out_apart(dest, root, "--to")
    check_output(dest)
    info = export(out, args.format, dest)
    files = info.get("files") or [info.get("file")]
    print(f"{args.format}: {', '.join(str(f) for f in files)} in {dest} ({info.get('units', '')}"
          f"{'; ' + info['world'] if 'world' in info else ''}"
          f"{'; open with: ' + info['open'] if 'open' in info else ''})")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:

    src = bundled("multiviewx")
    outs = [Path(args.out) / n for n in (*ESTIMATORS, "panoptic_noise0px", "panoptic_noise2px")]
    for o in outs:  # every check before any work
        check_output(o, (src, bundled("panoptic_160906_band1")))
    scene = load_scene(src)
    print(f"MultiviewX subset bundled in {src} (see its PROVENANCE.md): "
          f"{len(scene.rig.cameras)} cameras, {len(scene.frames)} frames, "
          f"{len(scene.truth.frame) if scene.truth else 0} person-frames, {len(scene.obs)} boxes")

    rows, mot = [], []
    for name in ESTIMATORS:
        out = Path(args.out) / name
        tracks = reconstruct(scene, name, out=out)
        if scene.truth is not None:
            mot.append((name, tracking_scores(tracks, scene.truth, scene.rig.up)))
            rows.append((name, box_errors(tracks, scene.truth, scene.rig.up, mot=mot[-1][1])))
        print(f"  {name}: {len(tracks)} rows in {tracks.info['seconds']:.2f} s -> {out}/tracks.csv")
    print("\nErrors against the dataset's own positions (positionID grid, 2.5 cm cells):")
    print(error_table(rows))
    p = PAPER["multiviewx"]
    print(f"\n{'ground plane, 1 m':<20}{'MOTA%':>7}{'IDF1%':>7}{'HOTA%':>7}{'OSPA(2) m':>11}")
    for name, t in mot:
        print(f"{name:<20}{100 * t['mota']:>7.1f}{100 * t['idf1']:>7.1f}{100 * t['hota']:>7.1f}"
              f"{t['ospa2_m']:>11.4f}")
    print(f"{'paper (Ma et al.)':<20}{p['MOTA']:>7.1f}{'-':>7}{'-':>7}{p['OSPA2_m']:>11.2f}")


    src = bundled("panoptic_160906_band1")
    print(f"\nCMU Panoptic 160906_band1 bundled in {src} (see its PROVENANCE.md): the paper's "
          "protocol, 3D joints projected into the HD cameras and reconstructed from 2D alone")
    rows = []
    for noise in (0.0, 2.0):
        scene = load_scene(src, noise_px=noise, seed=0)
        tracks = reconstruct(scene, "ukf", out=Path(args.out) / f"panoptic_noise{noise:g}px")
        truth = scene.truth
        if truth is None:
            continue
        for label, j in (("19 joints", None), ("15 body joints", np.arange(15))):
            rows.append((f"ukf {noise:g}px, {label}", score_tracks(tracks, truth, j),
                         mpjpe_by_id(tracks, truth, j)[0]))
        print(f"  {noise:g} px noise: {len(tracks)} poses from {len(scene.rig.cameras)} HD cameras "
              f"in {tracks.info['seconds']:.1f} s")
    print(pose_table(rows))
    lo, hi = PAPER["panoptic"]["MPJPE_mm"]
    print(f"\nPaper (Ma et al., UKF) on CMU Panoptic: MPJPE {lo}-{hi} mm")

    print("\nReports (3D renders, each camera's worst frame, residuals, anomalies):")
    for name in ("ukf", "panoptic_noise2px"):
        index, warnings = write_report(Path(args.out) / name)
        for w in warnings:
            print(f"warning: {w}", file=sys.stderr)
        print(f"  {index}")
    return 0


class _Parser(argparse.ArgumentParser):
    """argparse with the one-line ``error: <entry>: <problem>`` (exit 2) of every other error."""

    def error(self, message: str) -> Any:  # type: ignore[override]
        print(f"error: {self.prog}: {message} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(2)


def _number(kind: type, lo: float, hi: float, *, lo_open: bool = False,
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


FRACTION = _number(float, 0, 1)
PIXELS = _number(float, 0, 1000)              # image noise, px
SIGMA_PX = _number(float, 1e-3, 1000)
ACCEL = _number(float, 1e-6, 1000)             # m/s^2/sqrt(Hz)
FPS = _number(float, 1e-3, 1e6)                # one frame per 17 minutes .. 1 MHz
SEED = _number(int, 0, 2**32 - 1)


def build_parser() -> argparse.ArgumentParser:

    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true",
                        help="show the Python traceback of an unexpected error")
    p = _Parser(prog="gt3d", description=__doc__, parents=[common])
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    r = sub.add_parser("reconstruct", parents=[common],
                       help="2D boxes from calibrated cameras -> 3D ellipsoid tracks")
    r.add_argument("input", help="input folder (native, WILDTRACK or MultiviewX layout)")
    r.add_argument("--out", required=True, help="output folder (tracks.csv, meta.json)")
    r.add_argument("--layout", choices=LAYOUTS, help="input layout (default: detected)")
    r.add_argument("--estimator", choices=ESTIMATORS, default="ukf")
    r.add_argument("--sigma-px", type=SIGMA_PX, help="box-edge noise (default: from the data)")
    r.add_argument("--accel-sd", type=ACCEL,
                   help="acceleration noise, m/s^2/sqrt(Hz) (default: max likelihood)")
    r.add_argument("--fps", type=FPS, help="frame-number rate (default: the layout's)")
    r.add_argument("--calib", help="calibration file or folder in any format (cameras.json, "
                                   "WILDTRACK/MultiviewX calibrations/, OpenCV .yml/.xml, Anipose/"
                                   "Pose2Sim .toml, COLMAP model) in place of the input's own")
    r.add_argument("--association", metavar="FILE",
                   help="per-camera ids (mot): an edited association.csv whose rows override the "
                        "automatic cross-view association")
    r.add_argument("--refine-calib", action="store_true",
                   help="refine the cameras from the annotations first (see gt3d calib refine)")
    r.add_argument("--no-smooth", action="store_true", help="forward filter only (no RTS)")
    r.add_argument("--quiet", action="store_true", help="no progress display")
    r.add_argument("--no-bones", action="store_true", help="do not tie bone lengths")
    r.add_argument("--skeleton", choices=sorted(SKELETONS),
                   help="joint order of keypoints.csv (default: from the data)")
    r.add_argument("--cameras", help="CMU Panoptic: comma-separated HD cameras (default all)")
    r.add_argument("--noise-px", type=PIXELS, default=0.0,
                   help="CMU Panoptic: Gaussian noise added to the projected 2D joints")
    r.add_argument("--seed", type=SEED, help="CMU Panoptic: seed of that noise (default 0)")
    r.set_defaults(func=cmd_reconstruct)

    s = sub.add_parser("simulate", parents=[common],
                       help="write a seeded synthetic scene with its truth")
    s.add_argument("--kind", choices=("boxes", "skeleton"), default="boxes")
    s.add_argument("--layout", choices=(*SIM_LAYOUTS, "panoptic"), default="native",
                   help="boxes: native|wildtrack|multiviewx; skeleton: native|panoptic")
    s.add_argument("--cameras", type=_number(int, 1, 1000),
                   help="cameras (skeleton scenes: HD cameras, default 10; native boxes: 6)")
    s.add_argument("--fps", type=FPS, help="frame rate (skeletons: 30; native boxes: 10)")
    s.add_argument("--motion", choices=("smooth", "walk"),
                   help="box scenes: smooth paths (default) or real-trajectory-like walking")
    s.add_argument("--outliers", type=FRACTION, default=0.0,
                   help="skeletons: fraction of keypoints replaced by far-off points")
    s.add_argument("--swaps", type=FRACTION, default=0.0,
                   help="skeletons: fraction of person-views with one left/right pair swapped")
    s.add_argument("--glitch", type=FRACTION, default=0.0,
                   help="skeletons: fraction of keypoints at x = 0 with a high confidence")
    s.add_argument("--shifted", type=FRACTION, default=0.0,
                   help="boxes: fraction of boxes moved by 0.3-1 of their size")
    s.add_argument("--gap", help="FIRST:END frame indices with no annotation at all")
    s.add_argument("--single-view", type=FRACTION, default=0.0,
                   help="fraction of people annotated in one camera only")
    s.add_argument("--conf", action="store_true",
                   help="skeletons: write a detector confidence per keypoint")
    s.add_argument("--missing", type=_number(float, 0, 1, hi_open=True),
                   help="skeleton scenes: fraction of 2D points dropped at random (default 0.05)")
    s.add_argument("--skeleton", choices=sorted(SKELETONS), help="skeleton scenes (default coco19)")
    s.add_argument("--out", required=True)
    s.add_argument("--seed", type=SEED, default=0)
    s.add_argument("--frames", type=_number(int, 1, 10**7), default=40)
    s.add_argument("--people", type=_number(int, 1, 10**5), default=10)
    s.add_argument("--noise-px", type=PIXELS, default=0.0)
    s.add_argument("--dropout", type=_number(float, 0, 1, hi_open=True),
                   help="box scenes: fraction of boxes dropped (default 0.15)")
    s.add_argument("--format", choices=("mot", "cvat", "coco", "openpose"),
                   help="write the annotations as users' tools do: boxes as mot/<camera>.txt "
                        "(MOTChallenge) or cvat/<camera>.xml (CVAT for video 1.1), each camera "
                        "numbering its people itself; skeletons as coco/<camera>.json (COCO "
                        "keypoints) or a Pose2Sim/OpenPose trial (z-up world, TOML calibration, "
                        "no ids)")
    s.add_argument("--global-ids", action="store_true",
                   help="with --format mot or cvat: keep one id per person across cameras")
    s.add_argument("--no-track-ids", action="store_true",
                   help="with --format coco: no track ids (detections per frame)")
    s.set_defaults(func=cmd_simulate)

    c = sub.add_parser("compare", parents=[common],
                       help="UKF, GTSAM smoother and triangulation side by side")
    c.add_argument("input", help="input folder (any layout)")
    c.add_argument("--out", required=True, help="output folder (<estimator>/, comparison.csv)")
    c.add_argument("--layout", choices=LAYOUTS)
    c.add_argument("--skeleton", choices=sorted(SKELETONS))
    c.add_argument("--cameras", help="CMU Panoptic: comma-separated HD cameras")
    c.add_argument("--noise-px", type=PIXELS, default=0.0, help="CMU Panoptic: 2D noise")
    c.add_argument("--seed", type=SEED, help="CMU Panoptic: seed of that noise (default 0)")
    c.add_argument("--fps", type=FPS)
    c.add_argument("--calib", help="calibration file or folder in any format, in place of the "
                                   "input's own")
    c.add_argument("--association", metavar="FILE", help="as for reconstruct")
    c.add_argument("--no-progress", "--quiet", dest="no_progress", action="store_true",
                   help="no progress bar")
    c.set_defaults(func=cmd_compare)

    e = sub.add_parser("evaluate", parents=[common],
                       help="score OUT/tracks.csv against an input's truth")
    e.add_argument("out", help="a reconstruct output folder")
    e.add_argument("--truth", required=True, help="the input folder that carries the truth")
    e.add_argument("--layout", choices=LAYOUTS)
    e.add_argument("--max-dist-m", type=_number(float, 1e-6, 1e6), default=1.0,
                   help="ground-plane distance within which an estimate matches a true object "
                        "(MOTA, IDF1, HOTA, OSPA cut-off)")
    e.set_defaults(func=cmd_evaluate)

    k = sub.add_parser("calib", parents=[common], help="show, check and refine calibrations")
    ksub = k.add_subparsers(dest="calib_command", required=True, parser_class=_Parser)
    ks = ksub.add_parser("show", parents=[common],
                         help="a table per camera and warnings for common calibration mistakes")
    ks.add_argument("input", help="an input folder (checked with its annotations) or a calibration "
                                  "file or folder in any format")
    ks.set_defaults(func=cmd_calib_show)
    kr = ksub.add_parser("refine", parents=[common],
                         help="refine the rig from the annotations (validated on held-out frames)")
    kr.add_argument("input", help="input folder (any layout)")
    kr.add_argument("--out", required=True, help="output folder (cameras.json, calib_report.json)")
    kr.add_argument("--calib", help="start from this calibration instead of the input's own")
    kr.add_argument("--refine-intrinsics", action="store_true",
                    help="refine focal length and distortion too (keypoints only)")
    kr.add_argument("--format", choices=WRITABLE, default=None,
                    help="also write the refined rig in this format (into OUT/calibration/)")
    kr.add_argument("--layout", choices=LAYOUTS)
    kr.add_argument("--skeleton", choices=sorted(SKELETONS))
    kr.add_argument("--fps", type=FPS)
    kr.add_argument("--cameras", help="CMU Panoptic: comma-separated HD cameras")
    kr.add_argument("--noise-px", type=PIXELS, default=0.0, help="CMU Panoptic: 2D noise")
    kr.add_argument("--seed", type=SEED, help="CMU Panoptic: seed of that noise (default 0)")
    kr.set_defaults(func=cmd_calib_refine)

    m = sub.add_parser("reconstruct-many", parents=[common],
                       help="many input folders in parallel (local processes or a Dask cluster)")
    m.add_argument("manifest", help="a text file: one input folder (or a glob) per line")
    m.add_argument("--out", required=True, help="output folder: OUT/<input folder name>/ per sequence")
    m.add_argument("--estimator", choices=ESTIMATORS, default="ukf")
    m.add_argument("--jobs", type=_number(int, 1, 4096), help="local worker processes (default: cores)")
    m.add_argument("--scheduler", metavar="ADDRESS",
                   help="a running Dask distributed scheduler (tcp://host:8786) instead of local processes")
    m.add_argument("--report", action="store_true", help="also each sequence's report and OUT/index.html")
    m.add_argument("--quiet", action="store_true", help="no progress bar")
    m.set_defaults(func=cmd_reconstruct_many)

    a = sub.add_parser("associate", parents=[common],
                       help="per-camera ids (MOT files) -> global identities: OUT/association.csv")
    a.add_argument("input", help="input folder with per-camera ids (mot/<camera>.txt + calibration)")
    a.add_argument("--out", required=True, help="output folder (association.csv)")
    a.add_argument("--calib", help="calibration file or folder in any format")
    a.add_argument("--fps", type=FPS)
    a.add_argument("--association", metavar="FILE", help="an edited association.csv to apply")
    a.set_defaults(func=cmd_associate, layout=None, skeleton=None, cameras=None, noise_px=0.0, seed=None)

    rp = sub.add_parser("report", parents=[common],
                        help="OUT/report/index.html for a reconstruct or compare output: 3D renders, "
                             "per-camera pictures, residuals, anomalies with pictures")
    rp.add_argument("out", metavar="OUT", help="a gt3d reconstruct or gt3d compare output folder")
    rp.set_defaults(func=cmd_report)

    ex = sub.add_parser("export", parents=[common],
                        help="a reconstruct output as C3D, TRC (OpenSim), JSON or a Rerun recording")
    ex.add_argument("out", metavar="OUT", help="a gt3d reconstruct output folder")
    ex.add_argument("--format", required=True, choices=("c3d", "trc", "json", "rerun"))
    ex.add_argument("--to", metavar="DIR", help="folder to write (default OUT/export_FORMAT)")
    ex.set_defaults(func=cmd_export)

    d = sub.add_parser("demo", parents=[common],
                       help="reconstruct the bundled MultiviewX and Panoptic data, print errors")
    d.add_argument("--out", default="out/demo", help="where to write (default out/demo)")
    d.set_defaults(func=cmd_demo)
    return p


class Terminated(BaseException):
    """SIGTERM or SIGHUP, raised where the program is so that clean-ups run."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


#: signals received during this run: an exception raised by a signal handler inside a C
#: extension's initialisation (numba loading its thread pool) reaches us as an ImportError
_RECEIVED: list[int] = []


def _terminate(signum: int, frame: Any) -> None:
    _RECEIVED.append(signum)
    raise Terminated(signum)


def _interrupt(signum: int, frame: Any) -> None:
    _RECEIVED.append(signum)
    raise KeyboardInterrupt


def _quiet_stdout() -> None:
    """After a broken pipe: send what Python still flushes at exit nowhere."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def main(argv: list[str] | None = None) -> int:
    """The ``gt3d`` command. Exit status: 0 done, 2 bad input or option (one ``error:`` line),
    1 an unexpected error (one line; ``--debug`` shows the traceback), 130 / 143 interrupted
    (SIGINT / SIGTERM); in every failure no output is written or changed."""
    argv = sys.argv[1:] if argv is None else list(argv)
    debug = "--debug" in argv
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2, already printed)
        return int(e.code or 0)
    previous = {}
    handlers = [(signal.SIGTERM, _terminate), (signal.SIGHUP, _terminate)]
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not ignored (background job)
        handlers.append((signal.SIGINT, _interrupt))
    _RECEIVED.clear()
    for sig, handler in handlers:
        try:
            previous[sig] = signal.signal(sig, handler)
        except ValueError:  # not the main thread
            pass
    try:

        with warnings.catch_warnings(), small_matrix_blas():
            if not debug:  # numerical warnings are ours to handle, never the user's to read
                warnings.simplefilter("ignore", RuntimeWarning)
            code = int(args.func(args))
        sys.stdout.flush()  # here, where a closed pipe is handled, not at interpreter exit
        return code
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except EstimationError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # ``gt3d ... | head``: the reader left; the output is complete
        _quiet_stdout()
        return 141
    except KeyboardInterrupt:
        print("error: interrupted (Ctrl-C): no output written or changed", file=sys.stderr)
        return 130
    except Terminated as e:
        print(f"error: stopped by {e}: no output written or changed", file=sys.stderr)
        return 128 + e.signum
    except OSError as e:  # the machine, not the input: a full disk, a vanished folder
        print(f"error: {e.filename or 'system'}: {e.strerror or e}", file=sys.stderr)
        return 1
    except MemoryError:
        print("error: out of memory: the input is too large for this machine", file=sys.stderr)
        return 1
    except Exception as e:  # noqa: BLE001 - the one place that turns a bug into one line
        if _RECEIVED:  # a signal's exception, wrapped by the code it interrupted
            how = ("interrupted (Ctrl-C)" if _RECEIVED[0] == signal.SIGINT
                   else f"stopped by {signal.Signals(_RECEIVED[0]).name}")
            print(f"error: {how}: no output written or changed", file=sys.stderr)
            return 128 + _RECEIVED[0]
        if debug:
            traceback.print_exc()
        where = traceback.extract_tb(e.__traceback__)[-1]
        print(f"error: internal error, {type(e).__name__}: {e} (at {Path(where.filename).name}:"
              f"{where.lineno}; please report it, --debug shows the traceback)", file=sys.stderr)
        return 1
    finally:
        for sig, h in previous.items():
            signal.signal(sig, h)


if __name__ == "__main__":
    sys.exit(main())

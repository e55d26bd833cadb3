"""``gt3d reconstruct``, ``compare``, ``evaluate``, ``reconstruct-many``, ``associate``, ``report``,
``export``."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from gt3dkit.api import load_scene, reconstruct
from gt3dkit.calib.formats.native import cameras_doc
from gt3dkit.commands.common import (
    Stages,
    check_out_apart,
    check_output,
    estimator_config,
    load_input,
    scene_from_people,
    with_reposed_cameras,
)
from gt3dkit.commands.printing import TruthTally, fmt_num, print_run, print_warnings, report_truth
from gt3dkit.compare import compare
from gt3dkit.errors import InputError
from gt3dkit.export import export
from gt3dkit.fusion.base import over_time
from gt3dkit.io.atomic import write_dir_atomically
from gt3dkit.io.results import read_result
from gt3dkit.io.skeletonfile import named_skeleton
from gt3dkit.io.writers import read_keypoints_csv, read_tracks_csv
from gt3dkit.jsondoc import json_list, json_num, json_str
from gt3dkit.many import ReadAs, read_manifest, run_many
from gt3dkit.project import project
from gt3dkit.refine import refine, rig_digest
from gt3dkit.types import JsonDict, Options, Scene
from gt3dkit.viz.overlays import OverlayOptions
from gt3dkit.viz.report import write_report
from gt3dkit.windows import Cluster, Plan, auto_plan, connect_scheduler, reconstruct_windows


def cmd_reconstruct(args: argparse.Namespace) -> int:

    config = estimator_config(args)
    with early_cluster(args, config) as cluster:
        return reconstructed(args, config, cluster)


def early_cluster(args: argparse.Namespace, config: Options) -> Any:
    """``--scheduler``'s Dask cluster, connected before the input loads and its first worker
    warmed while it loads (:class:`gt3dkit.windows.Cluster`); a null context where the run uses
    none (``--window 0`` and the triangulation are refused after the input loads, by
    :func:`window_plan`); ``args.early``: the connection :mod:`gt3dkit.cli` made to it before
    its imports, taken over (:func:`gt3dkit.early.connect_early`)."""
    if not args.scheduler or args.window == 0 or not over_time(args.estimator):
        return contextlib.nullcontext()
    return Cluster(args.scheduler, args.estimator, config, early=args.early)


def reconstructed(args: argparse.Namespace, config: Options, cluster: Cluster | None) -> int:
    """``gt3d reconstruct``'s run, on ``cluster`` where given."""
    stages = Stages(5, args.quiet)
    stages("loading")
    extra: JsonDict | None = None
    into = None
    if args.calib == "people":
        scene, extra, into = scene_from_people(args)
    else:
        scene = load_input(args, by_windows=args.window != 0 and over_time(args.estimator)
                           and not args.refine_calib and args.every_frame is None)
    scene = with_clock_note(scene, args.estimator)
    if args.refine_calib:
        given = rig_digest(scene.rig)
        scene, reposed_doc = with_reposed_cameras(args, scene)
        res = refine(scene)
        extra = {**(extra or {}), "calibration_refinement": {**res.report, **reposed_doc, "rig_sha256": {
            "input": given, "refined": rig_digest(res.rig)},
            "refined_rig": json.loads(json.dumps(cameras_doc(res.rig, None)))}}
        scene = dataclasses.replace(scene, rig=res.rig)
        refined = ", ".join(str(c) for c in json_list(res.report, "refined_cameras")) or "no camera"
        print(f"calibration refined: {refined} ({json_num(res.report, 'seconds') or 0.0:.1f} s; "
              "meta.json: calibration_refinement)")
        for w in json_list(res.report, "large_moves"):
            print(f"warning: {w}", file=sys.stderr)
    try:
        plan = window_plan(args, scene)
        if scene.index is not None and plan is None:  # it runs whole: read whole, from what was read
            scene = load_input(args, head=scene)
        elif scene.index is not None:  # each window reads its own frames
            scene = dataclasses.replace(scene, index=dataclasses.replace(scene.index, ahead=None))
        tally = None
        if plan is not None:
            stages("windows")
            tally = TruthTally(scene.rig.up)
            tracks, scene = reconstruct_windows(scene, args.estimator, plan, args.out, extra,
                                                args.every_frame, lambda k, n: stages.part("windows", k, n),
                                                cluster, tally, **config)
        else:
            tracks = reconstruct(scene, args.estimator, out=args.out, extra_meta=extra, on_stage=stages,
                                 every_frame=args.every_frame, **config)
    finally:
        stages.close()
    print_run(scene, tracks, args.estimator, args.out, into, tally)
    return 0


def with_clock_note(scene: Scene, estimator: str) -> Scene:
    """``scene`` with a ``warning:`` where views filed off their frames (``--time-offsets``) are
    taken at the frame they are filed under: by an estimator other than the UKF."""
    off = scene.obs.frame_offset
    if off is None or not np.any(off != 0):
        return scene
    if estimator == "ukf":
        return scene
    why = (f"--time-offsets: the {estimator} takes each view at the whole frame nearest its own time "
           "(the UKF alone predicts each joint and box to it)")
    return dataclasses.replace(scene, warnings=(*scene.warnings, why))


def window_plan(args: argparse.Namespace, scene: Scene) -> Plan | None:
    """How ``gt3d reconstruct`` runs the sequence: whole (None), or in windows (``--window
    FRAMES``; by itself when the whole would not fit in memory, :func:`gt3dkit.windows.auto_plan`;
    as many as ``--jobs`` or a Dask scheduler's workers when only those are given)."""
    spread = args.jobs or args.scheduler
    option = "--jobs" if args.jobs else "--scheduler"
    if args.window and not over_time(args.estimator):
        raise InputError("--window", f"the {args.estimator} fits each frame on its own: it needs no window")
    if args.window == 0 or not over_time(args.estimator):
        if spread:
            raise InputError(option, "runs windows of the sequence in parallel: not with --window 0 or the "
                                     f"{args.estimator} (which fits each frame on its own)")
        return None
    plan = Plan(args.window) if args.window else auto_plan(scene)
    if plan is None and spread:  # the sequence fits: one window per worker
        plan = Plan(0, why="one per worker")
    return None if plan is None else dataclasses.replace(plan, jobs=args.jobs or 1, scheduler=args.scheduler)


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

    scene = load_input(args)
    table = compare(scene, Path(args.out), progress=not args.no_progress)
    print_warnings(scene)
    print(f"{scene.layout}: {len(scene.obs)} annotation rows -> {args.out}/comparison.csv")
    names = [str(r["estimator"]) for r in table if "failed" not in r]
    head = f"{'estimator':<15}{'rows':>6}{'reproj px':>10}{'p95 px':>8}" + "".join(
        f"{'to ' + n + ' m':>20}" for n in names) + f"{'sec':>8}" + (
        f"{'truth err m':>13}" if scene.truth is not None else "")
    print(head)
    print("-" * len(head))
    for r in table:
        if "failed" in r:
            print(f"{r['estimator']:<15}failed: {r['failed']}")
            continue
        line = (f"{r['estimator']!s:<15}{r['rows']!s:>6}{fmt_num(json_num(r, 'reproj_mean_px'), 10, 3)}"
                f"{fmt_num(json_num(r, 'reproj_p95_px'), 8, 3)}")
        for n in names:
            line += fmt_num(json_num(r, f"dist_to_{n}_mean_m"), 20, 5)
        line += f"{json_num(r, 'seconds') or 0.0:>8.1f}"
        if scene.truth is not None:
            v = json_num(r, "truth_mpjpe_m") if "truth_mpjpe_m" in r else json_num(r, "truth_centre_mean_m")
            if v is None or not np.isfinite(v):
                v = json_num(r, "truth_ground_mean_m")
            line += fmt_num(v, 13, 5)
        print(line)
    return 0


def cmd_reconstruct_many(args: argparse.Namespace) -> int:

    inputs = read_manifest(Path(args.manifest))
    skeleton = args.skeleton
    if skeleton is not None:
        named_skeleton(skeleton)  # checked once, here (one error line, nothing written)
        if skeleton.lower().endswith(".toml"):
            skeleton = str(Path(skeleton).resolve())  # the workers' folder may be another
    rows = run_many(inputs, Path(args.out), args.estimator, args.jobs, args.scheduler, args.report,
                    progress=not args.quiet, read=ReadAs(skeleton, args.fps, args.calib_units))
    width = max(len(Path(str(r["input"])).name) for r in rows)
    for r in rows:
        seconds = json_num(r, "seconds") or 0.0
        print(f"{Path(str(r['input'])).name:<{width}}  {r['status']!s:<10} {seconds:>8.1f} s  "
              f"{r['object_frames'] or ''!s:>6} object-frames  {r['error']}")
    failed = [Path(str(r["input"])).name for r in rows if r["status"] == "failed"]
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

    scene = load_input(args)
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
    frames = None
    if args.frames:
        check_out_apart(out / "report", args.frames, "--frames")
        frames = OverlayOptions(Path(args.frames), args.frame_offset, args.overlay_step, args.overlay_width)
    if args.scheduler and frames is None:
        raise InputError("--scheduler", "report: the workers draw the overlays of --frames; give --frames")
    client = connect_scheduler(args.scheduler) if args.scheduler else None
    try:
        index, warnings = write_report(out, frames, progress=not args.quiet, client=client)
    finally:
        if client is not None:
            client.close()
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    n = sum(1 for _ in index.parent.rglob("*.png"))
    print(f"report: {index} ({n} pictures; open it in a browser)")
    return 0


def cmd_export(args: argparse.Namespace) -> int:

    out = Path(args.out)
    dest = Path(args.to) if args.to else out / f"export_{args.format}"
    res = read_result(out)
    check_out_apart(dest, out, "--to", inside_ok=True)
    root = json_str(res.meta, "input", "load", "root") or json_str(res.meta, "input", "root")
    if root:
        check_out_apart(dest, root, "--to")
    check_output(dest, option="--to")
    info = export(out, args.format, dest, args.joint_map)
    files = json_list(info, "files") or [info.get("file")]
    for note in json_list(info, "notes"):
        print(f"warning: {note}", file=sys.stderr)
    said = [f"{k}: {info[k]}" if k == "open with" else str(info[k])
            for k in ("units", "world", "open with") if info.get(k)]
    print(f"{args.format}: {', '.join(str(f) for f in files)} in {dest}"
          + (f" ({'; '.join(said)})" if said else ""))
    return 0


def cmd_project(args: argparse.Namespace) -> int:

    out, dest = Path(args.out), Path(args.to)
    res = read_result(out)
    check_out_apart(dest, out, "--to", inside_ok=True)
    root = json_str(res.meta, "input", "load", "root") or json_str(res.meta, "input", "root")
    if root:
        check_out_apart(dest, root, "--to")
    for parent in dest.resolve().parents:  # not inside another run's output
        if parent != out.resolve() and (parent / "meta.json").is_file() and (parent / "tracks.csv").is_file():
            raise InputError("--to", f"{dest} lies inside another gt3d output ({parent}): choose a "
                                     "folder of its own")
    check_output(dest, option="--to")
    cameras = None
    if args.cameras is not None:
        cameras = tuple(c.strip() for c in args.cameras.split(",") if c.strip())
        if not cameras:
            raise InputError("--cameras", f"no camera names in {args.cameras!r}")
    info = project(out, args.format, dest, args.every_frame, cameras, args.only_flagged)
    for note in json_list(info, "notes"):
        print(f"warning: {note}", file=sys.stderr)
    print(f"{args.format}: {info['shapes']} shapes in {len(json_list(info, 'cameras'))} cameras -> {dest}/"
          f"{args.format}/ ({info['annotated']} labels, {info['proposed']} proposed, "
          f"{info['interpolated']} interpolated; {info['flagged']} flagged, {info['occluded']} "
          f"occluded); read it back: gt3d reconstruct {dest} --association {dest}/association.csv")
    return 0

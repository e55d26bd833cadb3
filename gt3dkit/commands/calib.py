"""``gt3d calib show`` and ``gt3d calib refine``."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gt3dkit.api import load_scene
from gt3dkit.calib.board import UNITS_M, read_board
from gt3dkit.calib.boardcal import BoardConfig, calibrate_board, identity_poses
from gt3dkit.calib.boardinput import board_views, find_cameras
from gt3dkit.calib.formats import detect_format, read_calibration, write_calibration
from gt3dkit.calib.formats.native import write as write_native
from gt3dkit.calib.show import camera_table, far_apart, rig_warnings
from gt3dkit.commands.common import (
    calibration_of,
    check_output,
    detections_input,
    load_input,
    people_rig,
    print_clocks,
)
from gt3dkit.commands.printing import fmt_num, print_warnings
from gt3dkit.errors import InputError
from gt3dkit.io.atomic import check_out, write_dir_atomically
from gt3dkit.io.writers import write_refined_calibration
from gt3dkit.jsondoc import json_at, json_list, json_num, json_obj, json_str
from gt3dkit.refine import RefineConfig, refine, scene_warnings
from gt3dkit.refine.people import PeopleConfig
from gt3dkit.rig import LENSES, Camera
from gt3dkit.synchronise import find_clocks
from gt3dkit.version import __version__
from gt3dkit.viz.boardreport import write_board_report


def cmd_calib_show(args: argparse.Namespace) -> int:

    scene = None
    units = args.calib_units or "m"
    alone: list[str] = []  # a calibration file's own warnings (an input's are the scene's)
    try:
        scene = load_scene(Path(args.input), calib=calibration_of(args, None))
        rig = scene.rig
        what = f"{scene.layout} input {args.input}"
    except InputError:
        if Path(args.input).is_dir() and (Path(args.input) / "cameras.json").exists():
            raise  # an input folder with a problem: say it
        rig = read_calibration(Path(args.input)).in_metres(UNITS_M[units])
        fmt = detect_format(Path(args.input))
        what = f"{fmt} calibration {args.input}" + (f" (in {units}, shown in metres)" if units != "m" else "")
        if fmt in ("opencv", "toml", "colmap"):
            what += " (the format has no up vector: +z assumed)"
        said = far_apart(rig) if units == "m" else None
        alone = [said] if said else []
    print(f"{what}: {len(rig.cameras)} cameras, up {np.round(rig.up, 4).tolist()}")
    head = (f"{'camera':<12}{'centre x':>9}{'y':>8}{'z':>8}{'height':>8}{'tilt°':>7}"
            f"{'fx':>8}{'fy':>8}{'cx':>7}{'cy':>7}{'lens':>8}{'k1':>8}{'k2':>8}{'size':>11}")
    print(head)
    print("-" * len(head))
    for t in camera_table(rig):
        x, y, z = np.round(t.centre_m, 4)
        d = np.round(t.dist, 6)
        print(f"{t.camera:<12}{x:>9.3f}{y:>8.3f}{z:>8.3f}{t.height_m:>8.3f}{t.tilt_deg:>7.1f}"
              f"{t.fx_px:>8.1f}{t.fy_px:>8.1f}{t.cx_px:>7.1f}{t.cy_px:>7.1f}{t.lens:>8}"
              f"{d[0]:>8.4f}{d[1]:>8.4f}{t.size[0]:>6}x{t.size[1]:<4}")
    warns = alone + rig_warnings(rig) + (scene_warnings(scene) if scene is not None else [])
    if scene is not None:
        print_warnings(scene)
    for w in warns:
        print(f"warning: {w}", file=sys.stderr)
    print(f"{len(warns)} calibration warnings")
    return 0


def cmd_calib_refine(args: argparse.Namespace) -> int:

    scene = load_input(args)
    res = refine(scene, RefineConfig(refine_intrinsics=args.refine_intrinsics))
    write_refined_calibration(Path(args.out), scene, res, args.format)
    print_warnings(scene)
    rep = res.report
    refined = [str(c) for c in json_list(rep, "refined_cameras")]
    print(f"{scene.layout}: {len(scene.rig.cameras)} cameras, {rep['method']} -> refined "
          f"{len(refined)} ({', '.join(refined) or 'none'}) in "
          f"{json_num(rep, 'seconds') or 0.0:.1f} s; written to {args.out}")
    print(f"{'camera':<12}{'refined':>8}{'moved cm':>10}{'moved °':>9}{'px before':>11}{'px after':>10}  why")
    for name, c in json_obj(rep, "cameras").items():
        print(f"{name:<12}{'yes' if json_at(c, 'refined') else 'no':>8}"
              f"{100 * (json_num(c, 'centre_moved_m') or 0.0):>10.2f}"
              f"{json_num(c, 'rotation_moved_deg') or 0.0:>9.3f}"
              f"{fmt_num(json_num(c, 'median_px_before'), 11, 3)}"
              f"{fmt_num(json_num(c, 'median_px_after'), 10, 3)}  {json_str(c, 'why')}")
    for w in json_list(rep, "large_moves"):
        print(f"warning: {w}", file=sys.stderr)
    return 0


def cmd_calib_people(args: argparse.Namespace) -> int:
    """``gt3d calib people``: the cameras' poses from the people in the scene
    (:mod:`gt3dkit.refine.people`)."""
    check_output(args.out, (args.input,))
    scene = detections_input(args, args.intrinsics)
    res = people_rig(scene, PeopleConfig(height_m=args.height, focal_known=not args.focal_unknown,
                                               clocks=args.clocks))
    clocks = None
    if res.clocks is not None:  # the pairwise clocks, held to the people reconstructed through this rig
        with tempfile.TemporaryDirectory() as tmp:
            cal = str(Path(tmp) / "cameras.json")
            write_native(res.rig, Path(tmp) / "cameras.json", fps=None if scene.fps_assumed else scene.fps)
            clocks, sync = find_clocks(scene, lambda on: load_input(args, calib=cal, clocks=on), res.clocks)
        res.report["clocks"] = {"cameras": clocks.doc(), "pairwise": res.clocks.report(),
                                "rounds": json_list(sync, "rounds"), "seconds": json_num(sync, "seconds")}
    extra = {} if clocks is None else {"time_offsets.csv": clocks.text()}
    write_refined_calibration(Path(args.out), scene, res, args.format, extra)
    print_warnings(scene)
    rep = res.report
    print(f"{scene.layout}: {len(res.rig.cameras)} cameras placed from {rep['people']} people-frames "
          f"({rep['tracks']} {'box points (feet, heads)' if rep.get('from') == 'boxes' else 'joints'} in the "
          f"last adjustment, median {json_num(rep, 'reprojection_median_px') or 0.0:.2f} px) "
          f"in {json_num(rep, 'seconds') or 0.0:.1f} s; written to {args.out}")
    print(f"world: {json_str(rep, 'world', 'frame')}")
    given = json_obj(rep, "against_input_calibration")
    vs = f"{'vs input cm':>12}{'vs input °':>11}" if given else ""
    print(f"{'camera':<12}{'centre x':>9}{'y':>8}{'z':>8}{'fx':>8}{'ctr sd cm':>10}{'rot sd °':>9}"
          f"{'median px':>10}{vs}")
    for cam in res.rig.cameras:
        c = json_obj(rep, "cameras", cam.name)
        x, y, z = cam.center_world
        g = (f"{100 * (json_num(given, 'cameras', cam.name, 'centre_m') or 0.0):>12.2f}"
             f"{json_num(given, 'cameras', cam.name, 'rotation_deg') or 0.0:>11.3f}") if given else ""
        print(f"{cam.name:<12}{x:>9.3f}{y:>8.3f}{z:>8.3f}{cam.K[0, 0]:>8.1f}"
              f"{100 * (json_num(c, 'centre_sd_m') or 0.0):>10.2f}"
              f"{json_num(c, 'rotation_sd_deg') or 0.0:>9.3f}{fmt_num(json_num(c, 'median_px'), 10, 2)}{g}")
    if given:
        print("vs input: the input's own calibration, after the similarity that best maps the camera centres "
              f"(its scale over ours {json_num(given, 'scale_given_over_found') or 0.0:.4f})")
    if clocks is not None:
        print_clocks(clocks.names, clocks.late_frames, clocks.sd_frames, "OUT/time_offsets.csv")
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)
    return 0


def parse_lens(text: str, names: list[str]) -> tuple[str, tuple[tuple[str, str], ...]]:
    """``--lens``: the rig's lens model and per-camera ones (``auto``, ``fisheye,top=pinhole``)."""
    models = (*LENSES, "auto")
    lens, pairs = "auto", []
    for item in (x.strip() for x in text.split(",") if x.strip()):
        name, _, model = item.rpartition("=")
        if model not in models:
            raise InputError("--lens", f"{item!r}: the model must be one of {', '.join(models)}")
        if not name:
            lens = model
        elif name not in names:
            raise InputError("--lens", f"{item!r}: no camera {name} (the cameras: {', '.join(names)})")
        else:
            pairs.append((name, model))
    return lens, tuple(pairs)


def cmd_calib_board(args: argparse.Namespace) -> int:
    """``gt3d calib board``: a rig from board views (see :mod:`gt3dkit.calib.boardcal`)."""
    t0 = time.perf_counter()
    out = Path(args.out)
    inputs = [Path(p).resolve() for p in args.input]
    if any(out.resolve() == p or p in out.resolve().parents for p in inputs if p.is_dir()):
        raise InputError("--out", f"{out} lies inside the input {args.input[0]}: never write into an "
                                  "input folder")
    check_out(out)
    board = read_board(args.board, args.board_units)
    sources = find_cameras(args.input, args.cam_regex, args.intrinsics_only)
    fixed: tuple[Camera, ...] = ()
    if args.intrinsics:
        given = read_calibration(Path(args.intrinsics))
        fixed = given.cameras
        unknown = sorted({s.name for s in sources} - set(given.names))
        if unknown:
            raise InputError(args.intrinsics, f"has no camera {', '.join(unknown)} (it has "
                                              f"{', '.join(given.names)})")
    lens, lens_of = parse_lens(args.lens, sorted({s.name for s in sources}))
    bv = board_views(sources, board, args.step)
    cfg = BoardConfig(origin=args.origin, floor_frame=args.floor_frame, holdout_every=args.holdout,
                      fixed=fixed, lens=lens, lens_of=lens_of)
    cal = calibrate_board(list(bv.views), board, bv.names, bv.sizes, cfg)
    if args.intrinsics_only:
        cal = dataclasses.replace(cal, rig=identity_poses(cal.rig))
    seconds = time.perf_counter() - t0
    command = "gt3d calib board " + " ".join(sys.argv[3:]) if len(sys.argv) > 3 else "gt3d calib board"

    def write(tmp: Path) -> None:
        write_native(cal.rig, tmp / "cameras.json")
        if args.format and args.format != "native":
            write_calibration(cal.rig, tmp / "calibration", args.format)
        doc = {"gt3dkit_version": __version__, "input": [str(p) for p in args.input],
               "cameras_read": {n: {"source": [str(s.path) for s in bv.sources if s.name == n],
                                    "frames_read": bv.frames_read[i],
                                    "frames_without_board": bv.frames_empty[i]}
                                for i, n in enumerate(bv.names)},
               "seconds": seconds, **cal.report()}
        (tmp / "board_report.json").write_text(json.dumps(doc, indent=2, allow_nan=True))
        write_board_report(cal, tmp / "report", command)

    write_dir_atomically(out, write)
    for w in cal.warnings:
        print(f"warning: {w}", file=sys.stderr)
    print(f"{board.describe()}: {len(bv.names)} cameras, {len(bv.views)} board views in "
          f"{sum(bv.frames_read)} frames, {seconds:.1f} s; {cal.rig.frame_name}; written to {out}")
    print(f"{'camera':<12}{'lens':>8}{'views':>6}{'RMS px':>8}{'p95 px':>8}{'held px':>9}{'fx':>9}{'fy':>9}"
          f"{'cx':>8}{'cy':>8}"
          f"{'f sd':>6}{'ctr sd mm':>10}{'rot sd °':>9}{'left out':>9}")
    for rep, cam in zip(cal.cameras, cal.rig.cameras, strict=True):
        print(f"{rep.name:<12}{cam.lens:>8}{rep.views_used:>6}{rep.rms_px:>8.3f}{rep.p95_px:>8.3f}"
              f"{fmt_num(rep.holdout_rms_px, 9, 3)}{cam.K[0, 0]:>9.1f}{cam.K[1, 1]:>9.1f}{cam.K[0, 2]:>8.1f}"
              f"{cam.K[1, 2]:>8.1f}{rep.focal_sd_px:>6.2f}{rep.centre_sd_mm:>10.2f}"
              f"{rep.rotation_sd_deg:>9.3f}"
              f"{len(rep.dropped):>9}")
    for rep in cal.cameras:
        for v, why in rep.dropped:
            print(f"left out: {rep.name} {v}: {why}")
    return 0

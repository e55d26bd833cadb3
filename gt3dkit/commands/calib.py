"""``gt3d calib show`` and ``gt3d calib refine``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from gt3dkit.api import load_scene
from gt3dkit.calib.formats import detect_format, read_calibration
from gt3dkit.calib.show import camera_table, rig_warnings
from gt3dkit.commands.common import (
    fmt_num,
    load_input,
    print_warnings,
)
from gt3dkit.errors import InputError
from gt3dkit.io.writers import write_refined_calibration
from gt3dkit.refine import RefineConfig, refine, scene_warnings


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

    scene = load_input(args)
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
              f"{c['rotation_moved_deg']:>9.3f}{fmt_num(c['median_px_before'], 11, 3)}"
              f"{fmt_num(c['median_px_after'], 10, 3)}  {c['why']}")
    return 0

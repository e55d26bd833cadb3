"""``gt3d demo``: the bundled MultiviewX and CMU Panoptic data reconstructed, scored and reported."""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from gt3dkit.api import ESTIMATORS, load_scene, reconstruct
from gt3dkit.commands.common import PAPER, PAPER_PANOPTIC_MPJPE_MM, bundled, check_output
from gt3dkit.commands.printing import error_table, pose_table
from gt3dkit.eval.metrics import box_errors
from gt3dkit.eval.pose import mpjpe_by_id, score_tracks
from gt3dkit.eval.tracking import tracking_scores
from gt3dkit.viz.report import write_report


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
        print(f"  {name}: {len(tracks)} rows in {tracks.info.seconds:.2f} s -> {out}/tracks.csv")
    print("\nErrors against the dataset's own positions (positionID grid, 2.5 cm cells):")
    print(error_table(rows))
    p = PAPER["multiviewx"]
    print(f"\n{'ground plane, 1 m':<20}{'MOTA%':>7}{'IDF1%':>7}{'HOTA%':>7}{'OSPA(2) m':>11}")
    for name, t in mot:
        print(f"{name:<20}{100 * t['mota']:>7.1f}{100 * t['idf1']:>7.1f}{100 * t['hota']:>7.1f}"
              f"{t['ospa2_m']:>11.4f}")
    print(f"{'paper (Ma et al.)':<20}{p['MOTA']:>7.1f}{'-':>7}{'-':>7}{p['OSPA2_m']:>11.2f}")
    # the MultiviewX report drawn in a second process while Panoptic runs here (the reports'
    # figures were 13 of the demo's 17 s, one after the other)
    with ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as pool:
        first = pool.submit(write_report, Path(args.out) / "ukf")
        _panoptic(args)
        second = write_report(Path(args.out) / "panoptic_noise2px")
        reports = [first.result(), second]
    print("\nReports (3D renders, each camera's worst frame, residuals, anomalies):")
    for index, warnings in reports:
        for w in warnings:
            print(f"warning: {w}", file=sys.stderr)
        print(f"  {index}")
    return 0


def _panoptic(args: argparse.Namespace) -> None:
    """The bundled Panoptic joints reconstructed at 0 and 2 px of noise, scored against the truth."""
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
              f"in {tracks.info.seconds:.1f} s")
    print(pose_table(rows))
    lo, hi = PAPER_PANOPTIC_MPJPE_MM
    print(f"\nPaper (Ma et al., UKF) on CMU Panoptic: MPJPE {lo}-{hi} mm")

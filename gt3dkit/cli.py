"""``gt3d``: parse, call the library, print. No maths here."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from gt3dkit.errors import InputError

#: Published numbers of Ma et al. for the datasets we can compare on.
PAPER = {"multiviewx": {"MOTA": 96.5, "OSPA2_m": 0.17}, "wildtrack": {"MOTA": 98.7, "OSPA2_m": 0.10},
         "panoptic": {"MPJPE_mm": (6.1, 14.7)}}


def bundled(name: str) -> Path:
    """Path of a dataset bundled with the package (``gt3dkit/data/<name>``)."""
    return Path(str(resources.files("gt3dkit") / "data" / name))


def _estimator_config(args: argparse.Namespace) -> dict[str, Any]:
    cfg: dict[str, Any] = {}
    if args.estimator == "gtsam":
        if args.sigma_px is not None:
            cfg["sigma_px"] = args.sigma_px
        if args.accel_sd is not None:
            cfg["accel_sd"] = args.accel_sd
    if args.estimator == "ukf":
        if args.sigma_px is not None:
            cfg["sigma_px"] = args.sigma_px
        if args.accel_sd is not None:
            cfg["accel_sd"] = args.accel_sd
        if args.no_smooth:
            cfg["smooth"] = False
        if getattr(args, "no_bones", False):
            cfg["bones"] = False
    return cfg


def check_out_apart(out: str | Path, inp: str | Path) -> None:
    """Refuse an output folder that is, contains or lies inside the input folder: results
    must never overwrite (or be mistaken for) annotations."""
    o, i = Path(out).resolve(), Path(inp).resolve()
    if o == i or i in o.parents or o in i.parents:
        raise InputError("--out", f"{out} is, contains or lies inside the input folder {inp}: "
                                  "choose an output folder apart from the input")


def _load(args: argparse.Namespace) -> Any:
    from gt3dkit.io.datasets import detect_layout, load_scene

    if getattr(args, "out", None) is not None:
        check_out_apart(args.out, args.input)
    layout = args.layout or detect_layout(Path(args.input))
    opts: dict[str, Any] = {}
    if layout == "panoptic":
        if args.cameras:
            opts["cameras"] = [c.strip() for c in args.cameras.split(",") if c.strip()]
        opts["noise_px"], opts["seed"] = args.noise_px, args.seed
        if not args.noise_px >= 0:
            raise InputError("--noise-px", f"must be >= 0, got {args.noise_px}")
    elif args.cameras or args.noise_px:
        raise InputError("--cameras/--noise-px", "apply to CMU Panoptic inputs only")
    scene = load_scene(Path(args.input), layout, args.skeleton, **opts)
    if getattr(args, "fps", None) is not None:
        if not (np.isfinite(args.fps) and args.fps > 0):
            raise InputError("--fps", f"must be positive and finite, got {args.fps}")
        scene = dataclasses.replace(scene, fps=float(args.fps), fps_assumed="")
    for w in scene.all_warnings:
        print(f"warning: {w}", file=sys.stderr)
    return scene


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


def pose_table(rows: list[tuple[str, Any, float]]) -> str:
    """Fixed-width table of (name, PoseScores, MPJPE by id in mm)."""
    head = (f"{'estimator':<26}{'AP@25':>7}{'AP@50':>7}{'AP@100':>8}{'AP@150':>8}"
            f"{'Rec@500':>9}{'MPJPE mm':>11}{'by id mm':>10}")
    lines = [head, "-" * len(head)]
    for name, p, by_id in rows:
        lines.append(f"{name:<26}{100 * p.ap[25]:>7.1f}{100 * p.ap[50]:>7.1f}"
                     f"{100 * p.ap[100]:>8.1f}{100 * p.ap[150]:>8.1f}{100 * p.recall_500:>9.1f}"
                     f"{p.mpjpe_mm:>11.4f}{by_id:>10.4f}")
    return "\n".join(lines)


def report_truth(scene: Any, tracks: Any, name: str) -> None:
    """Print errors against the input's truth: boxes/positions and/or keypoints."""
    from gt3dkit.eval.metrics import box_errors
    from gt3dkit.eval.pose import mpjpe_by_id, score_tracks

    if scene.truth is None:
        return
    print(f"against {scene.truth.source}:")
    if np.isfinite(scene.truth.center_world).any():
        from gt3dkit.eval.tracking import tracking_scores

        print(error_table([(name, box_errors(tracks, scene.truth, scene.rig.up))]))
        t = tracking_scores(tracks, scene.truth, scene.rig.up)
        print(f"ground plane, 1 m: MOTA {100 * t['mota']:.1f}  IDF1 {100 * t['idf1']:.1f}  "
              f"FP {t['fp']}  FN {t['fn']}  IDs {t['ids']}  HOTA {100 * t['hota']:.1f}  "
              f"OSPA(2) {t['ospa2_m']:.4f} m")
    if scene.truth.kpt_world.shape[1] and tracks.kpt_world.shape[1]:
        sets = [("all joints", None)]
        if scene.skeleton == "coco19":
            sets.append(("15 body joints", np.arange(15)))
        print(pose_table([(f"{name}, {label}", score_tracks(tracks, scene.truth, j),
                           mpjpe_by_id(tracks, scene.truth, j)[0]) for label, j in sets]))


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from gt3dkit.api import reconstruct

    scene = _load(args)
    tracks = reconstruct(scene, args.estimator, out=args.out, **_estimator_config(args))
    info = tracks.info
    kinds = " + ".join(k for k, v in (("boxes", scene.obs.has_box.any()),
                                      (f"{scene.skeleton} keypoints", scene.obs.n_joints > 0)) if v)
    fps = f"{scene.fps:g} fps" + (" (assumed)" if scene.fps_assumed else "")
    rob = info.get("robust", {})
    flagged = (f", {rob['rejected']} measurements rejected and {rob['downweighted']} "
               f"down-weighted (downweighted.csv)" if rob.get("enabled") else "")
    print(f"{scene.layout}: {len(scene.obs)} annotation rows ({kinds}), {len(scene.rig.cameras)} "
          f"cameras, {fps} -> {len(tracks)} object-frames of {len(set(tracks.track_id.tolist()))} "
          f"objects ({args.estimator}, {info.get('seconds', 0):.2f} s{flagged}) written to "
          f"{args.out}")
    report_truth(scene, tracks, args.estimator)
    return 0


def _errors(args: argparse.Namespace) -> Any:
    from gt3dkit.sim import Errors

    gap = None
    if args.gap:
        try:
            a, b = (int(v) for v in args.gap.split(":"))
        except ValueError:
            raise InputError("--gap", f"expected FIRST:END frame indices, got {args.gap!r}") from None
        gap = (a, b)
    for k in ("outliers", "swaps", "glitch", "shifted", "single_view"):
        v = getattr(args, k)
        if not 0 <= v <= 1:  # NaN fails too
            raise InputError(f"--{k.replace('_', '-')}", f"must be a fraction in [0, 1], got {v}")
    try:
        return Errors(outliers=args.outliers, swaps=args.swaps, glitch=args.glitch,
                      shifted=args.shifted, gap=gap, single_view=args.single_view)
    except ValueError as e:
        raise InputError("simulate", str(e)) from None


def cmd_simulate(args: argparse.Namespace) -> int:
    from gt3dkit.sim import simulate, simulate_skeletons, write_scene, write_skeleton_scene

    errors = _errors(args)
    if not args.noise_px >= 0:
        raise InputError("--noise-px", f"must be >= 0, got {args.noise_px}")
    n_err = ""
    if args.kind == "skeleton":
        if args.shifted:
            raise InputError("--shifted", "applies to box scenes")
        try:
            sk = simulate_skeletons(args.layout, seed=args.seed, frames=args.frames,
                                    people=args.people, noise_px=args.noise_px,
                                    missing=args.missing, cameras=args.cameras or 10,
                                    skeleton=args.skeleton, errors=errors,
                                    confidences=args.conf, fps=args.fps or 30.0)
        except ValueError as e:
            raise InputError("simulate", str(e)) from None
        write_skeleton_scene(sk, Path(args.out), args.layout)
        if sk.injected:
            n_err = f", {len(sk.injected)} injected errors (injected.csv)"
        print(f"wrote {args.layout} skeleton scene to {args.out}: {args.cameras or 10} cameras, "
              f"{args.frames} frames, {args.people} people ({args.skeleton}), y-down world{n_err}")
        return 0
    if args.layout == "panoptic":
        raise InputError("simulate", "box scenes are native, wildtrack or multiviewx")
    if errors.outliers or errors.swaps or errors.glitch or args.conf:
        raise InputError("--outliers/--swaps/--glitch/--conf", "apply to skeleton scenes "
                                                              "(boxes: --shifted)")
    try:
        sim = simulate(args.layout, seed=args.seed, frames=args.frames, people=args.people,
                       noise_px=args.noise_px, dropout=args.dropout, errors=errors,
                       motion=args.motion, cameras=args.cameras, fps=args.fps)
    except ValueError as e:
        raise InputError("simulate", str(e)) from None
    write_scene(sim, Path(args.out), args.layout)
    seen = int(np.isfinite(sim.boxes[..., 0]).sum())
    if sim.injected:
        n_err = f", {len(sim.injected)} injected errors (injected.csv)"
    print(f"wrote {args.layout} scene to {args.out}: {len(sim.rig.cameras)} cameras, "
          f"{len(sim.frames)} frames at {sim.fps:g} fps, {args.people} people, {seen} boxes, "
          f"truth.csv{n_err}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from gt3dkit.io.datasets import load_scene
    from gt3dkit.io.writers import read_keypoints_csv, read_tracks_csv

    tracks = read_tracks_csv(Path(args.out) / "tracks.csv")
    scene = load_scene(Path(args.truth), args.layout)
    if scene.truth is None:
        raise InputError(str(args.truth), "this input carries no truth (positions, truth.csv, "
                                          "truth_keypoints.csv or Panoptic joints)")
    kp = Path(args.out) / "keypoints.csv"
    if kp.exists() and scene.obs.n_joints:
        tracks = read_keypoints_csv(kp, tracks, scene.obs.n_joints)
    print(f"{args.out} against the truth of {args.truth}:")
    report_truth(scene, tracks, Path(args.out).name)
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from gt3dkit.compare import compare

    scene = _load(args)
    table = compare(scene, Path(args.out), progress=not args.no_progress)
    print(f"{scene.layout}: {len(scene.obs)} annotation rows -> {args.out}/comparison.csv")
    names = [r["estimator"] for r in table]
    head = f"{'estimator':<15}{'rows':>6}{'reproj px':>10}{'p95 px':>8}" + "".join(
        f"{'to ' + n + ' m':>20}" for n in names) + f"{'sec':>8}" + (
        f"{'truth err m':>13}" if scene.truth is not None else "")
    print(head)
    print("-" * len(head))
    for r in table:
        line = f"{r['estimator']:<15}{r['rows']:>6}{r['reproj_mean_px']:>10.3f}{r['reproj_p95_px']:>8.3f}"
        for n in names:
            v = r.get(f"dist_to_{n}_mean_m")
            line += f"{'-':>20}" if v is None else f"{v:>20.5f}"
        line += f"{r['seconds']:>8.1f}"
        if scene.truth is not None:
            v = r.get("truth_mpjpe_m", r.get("truth_centre_mean_m"))
            if v is None or not np.isfinite(v):
                v = r.get("truth_ground_mean_m", float("nan"))
            line += f"{v:>13.5f}"
        print(line)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from gt3dkit.api import reconstruct
    from gt3dkit.eval.metrics import box_errors
    from gt3dkit.io.datasets import load_scene

    src = bundled("multiviewx")
    scene = load_scene(src)
    print(f"MultiviewX subset bundled in {src} (see its PROVENANCE.md): "
          f"{len(scene.rig.cameras)} cameras, {len(scene.frames)} frames, "
          f"{len(scene.truth.frame) if scene.truth else 0} person-frames, {len(scene.obs)} boxes")
    from gt3dkit.eval.tracking import tracking_scores

    rows, mot = [], []
    from gt3dkit.api import ESTIMATORS

    for name in ESTIMATORS:
        out = Path(args.out) / name
        tracks = reconstruct(scene, name, out=out)
        if scene.truth is not None:
            rows.append((name, box_errors(tracks, scene.truth, scene.rig.up)))
            mot.append((name, tracking_scores(tracks, scene.truth, scene.rig.up)))
        print(f"  {name}: {len(tracks)} rows in {tracks.info['seconds']:.2f} s -> {out}/tracks.csv")
    print("\nErrors against the dataset's own positions (positionID grid, 2.5 cm cells):")
    print(error_table(rows))
    p = PAPER["multiviewx"]
    print(f"\n{'ground plane, 1 m':<20}{'MOTA%':>7}{'IDF1%':>7}{'HOTA%':>7}{'OSPA(2) m':>11}")
    for name, t in mot:
        print(f"{name:<20}{100 * t['mota']:>7.1f}{100 * t['idf1']:>7.1f}{100 * t['hota']:>7.1f}"
              f"{t['ospa2_m']:>11.4f}")
    print(f"{'paper (Ma et al.)':<20}{p['MOTA']:>7.1f}{'-':>7}{'-':>7}{p['OSPA2_m']:>11.2f}")

    from gt3dkit.eval.pose import mpjpe_by_id, score_tracks

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
    return 0


def build_parser() -> argparse.ArgumentParser:
    from gt3dkit.api import ESTIMATORS
    from gt3dkit.io.datasets import LAYOUTS
    from gt3dkit.sim import SIM_LAYOUTS
    from gt3dkit.skeletons import SKELETONS

    p = argparse.ArgumentParser(prog="gt3d", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("reconstruct", help="2D boxes from calibrated cameras -> 3D ellipsoid tracks")
    r.add_argument("input", help="input folder (native, WILDTRACK or MultiviewX layout)")
    r.add_argument("--out", required=True, help="output folder (tracks.csv, meta.json)")
    r.add_argument("--layout", choices=LAYOUTS, help="input layout (default: detected)")
    r.add_argument("--estimator", choices=ESTIMATORS, default="ukf")
    r.add_argument("--sigma-px", type=float, help="box-edge noise (default: from the data)")
    r.add_argument("--accel-sd", type=float,
                   help="acceleration noise, m/s^2/sqrt(Hz) (default: max likelihood)")
    r.add_argument("--fps", type=float, help="frame-number rate (default: the layout's)")
    r.add_argument("--no-smooth", action="store_true", help="forward filter only (no RTS)")
    r.add_argument("--no-bones", action="store_true", help="do not tie bone lengths")
    r.add_argument("--skeleton", choices=sorted(SKELETONS),
                   help="joint order of keypoints.csv (default: from the data)")
    r.add_argument("--cameras", help="CMU Panoptic: comma-separated HD cameras (default all)")
    r.add_argument("--noise-px", type=float, default=0.0,
                   help="CMU Panoptic: Gaussian noise added to the projected 2D joints")
    r.add_argument("--seed", type=int, default=0, help="CMU Panoptic: seed of that noise")
    r.set_defaults(func=cmd_reconstruct)

    s = sub.add_parser("simulate", help="write a seeded synthetic scene with its truth")
    s.add_argument("--kind", choices=("boxes", "skeleton"), default="boxes")
    s.add_argument("--layout", choices=(*SIM_LAYOUTS, "panoptic"), default="native",
                   help="boxes: native|wildtrack|multiviewx; skeleton: native|panoptic")
    s.add_argument("--cameras", type=int,
                   help="cameras (skeleton scenes: HD cameras, default 10; native boxes: 6)")
    s.add_argument("--fps", type=float, help="frame rate (skeletons: 30; native boxes: 10)")
    s.add_argument("--motion", choices=("smooth", "walk"), default="smooth",
                   help="box scenes: smooth paths or real-trajectory-like walking")
    s.add_argument("--outliers", type=float, default=0.0,
                   help="skeletons: fraction of keypoints replaced by far-off points")
    s.add_argument("--swaps", type=float, default=0.0,
                   help="skeletons: fraction of person-views with one left/right pair swapped")
    s.add_argument("--glitch", type=float, default=0.0,
                   help="skeletons: fraction of keypoints at x = 0 with a high confidence")
    s.add_argument("--shifted", type=float, default=0.0,
                   help="boxes: fraction of boxes moved by 0.3-1 of their size")
    s.add_argument("--gap", help="FIRST:END frame indices with no annotation at all")
    s.add_argument("--single-view", type=float, default=0.0,
                   help="fraction of people annotated in one camera only")
    s.add_argument("--conf", action="store_true",
                   help="skeletons: write a detector confidence per keypoint")
    s.add_argument("--missing", type=float, default=0.05,
                   help="skeleton scenes: fraction of 2D points dropped at random")
    s.add_argument("--skeleton", choices=sorted(SKELETONS), default="coco19")
    s.add_argument("--out", required=True)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--frames", type=int, default=40)
    s.add_argument("--people", type=int, default=10)
    s.add_argument("--noise-px", type=float, default=0.0)
    s.add_argument("--dropout", type=float, default=0.15)
    s.set_defaults(func=cmd_simulate)

    c = sub.add_parser("compare", help="UKF, GTSAM smoother and triangulation side by side")
    c.add_argument("input", help="input folder (any layout)")
    c.add_argument("--out", required=True, help="output folder (<estimator>/, comparison.csv)")
    c.add_argument("--layout", choices=LAYOUTS)
    c.add_argument("--skeleton", choices=sorted(SKELETONS))
    c.add_argument("--cameras", help="CMU Panoptic: comma-separated HD cameras")
    c.add_argument("--noise-px", type=float, default=0.0, help="CMU Panoptic: 2D noise")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--fps", type=float)
    c.add_argument("--no-progress", action="store_true", help="no progress bar")
    c.set_defaults(func=cmd_compare)

    e = sub.add_parser("evaluate", help="score OUT/tracks.csv against an input's truth")
    e.add_argument("out", help="a reconstruct output folder")
    e.add_argument("--truth", required=True, help="the input folder that carries the truth")
    e.add_argument("--layout", choices=LAYOUTS)
    e.add_argument("--max-dist-m", type=float, default=1.0, help="MOT match distance")
    e.set_defaults(func=cmd_evaluate)

    d = sub.add_parser("demo", help="reconstruct the bundled MultiviewX and Panoptic data, "
                                    "print errors")
    d.add_argument("--out", default="out/demo", help="where to write (default out/demo)")
    d.set_defaults(func=cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except (OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

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
PAPER = {"multiviewx": {"MOTA": 96.5, "OSPA2_m": 0.17}, "wildtrack": {"MOTA": 98.7, "OSPA2_m": 0.10}}


def bundled(name: str) -> Path:
    """Path of a dataset bundled with the package (``gt3dkit/data/<name>``)."""
    return Path(str(resources.files("gt3dkit") / "data" / name))


def _estimator_config(args: argparse.Namespace) -> dict[str, Any]:
    cfg: dict[str, Any] = {}
    if args.estimator == "ukf":
        if args.sigma_px is not None:
            cfg["sigma_px"] = args.sigma_px
        if args.accel_sd is not None:
            cfg["accel_sd"] = args.accel_sd
        if args.no_smooth:
            cfg["smooth"] = False
    return cfg


def _load(args: argparse.Namespace) -> Any:
    from gt3dkit.io.datasets import load_scene

    scene = load_scene(Path(args.input), args.layout)
    if getattr(args, "fps", None) is not None:
        if not args.fps > 0:
            raise InputError("--fps", f"must be positive, got {args.fps}")
        scene = dataclasses.replace(scene, fps=float(args.fps))
    return scene


def error_table(rows: list[tuple[str, Any]]) -> str:
    """Fixed-width table of (estimator, BoxErrors)."""
    head = (f"{'estimator':<14}{'rows':>6}{'cover%':>8}{'ground mm':>11}{'median mm':>11}"
            f"{'centre mm':>11}{'height mm':>11}{'radius mm':>11}{'MOTA%':>8}{'IDF1%':>8}")
    lines = [head, "-" * len(head)]
    for name, e in rows:
        lines.append(f"{name:<14}{e.rows_matched:>6}{100 * e.coverage:>8.1f}"
                     f"{1000 * e.ground_mean_m:>11.2f}{1000 * e.ground_median_m:>11.2f}"
                     f"{1000 * e.centre_mean_m:>11.2f}{1000 * e.height_mean_m:>11.2f}"
                     f"{1000 * e.radius_mean_m:>11.2f}{100 * e.mota:>8.1f}{100 * e.idf1:>8.1f}")
    return "\n".join(lines)


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from gt3dkit.api import reconstruct
    from gt3dkit.eval.metrics import box_errors

    scene = _load(args)
    tracks = reconstruct(scene, args.estimator, out=args.out, **_estimator_config(args))
    info = tracks.info
    print(f"{scene.layout}: {len(scene.obs)} annotations, {len(scene.rig.cameras)} cameras -> "
          f"{len(tracks)} object-frames of {len(set(tracks.track_id.tolist()))} objects "
          f"({args.estimator}, {info.get('seconds', 0):.2f} s) written to {args.out}")
    if scene.truth is not None:
        e = box_errors(tracks, scene.truth, scene.rig.up)
        print(f"against {scene.truth.source}:")
        print(error_table([(args.estimator, e)]))
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from gt3dkit.sim import simulate, write_scene

    try:
        sim = simulate(args.layout, seed=args.seed, frames=args.frames, people=args.people,
                       noise_px=args.noise_px, dropout=args.dropout)
    except ValueError as e:
        raise InputError("simulate", str(e)) from None
    write_scene(sim, Path(args.out), args.layout)
    seen = int(np.isfinite(sim.boxes[..., 0]).sum())
    print(f"wrote {args.layout} scene to {args.out}: {len(sim.rig.cameras)} cameras, "
          f"{len(sim.frames)} frames, {args.people} people, {seen} boxes, truth.csv")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from gt3dkit.eval.metrics import box_errors
    from gt3dkit.io.datasets import load_scene
    from gt3dkit.io.writers import read_tracks_csv

    tracks = read_tracks_csv(Path(args.out) / "tracks.csv")
    scene = load_scene(Path(args.truth), args.layout)
    if scene.truth is None:
        raise InputError(str(args.truth), "this input carries no truth (positions or truth.csv)")
    e = box_errors(tracks, scene.truth, scene.rig.up, args.max_dist_m)
    print(f"{args.out} against {scene.truth.source} of {args.truth}:")
    print(error_table([(Path(args.out).name, e)]))
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
    rows = []
    for name in ("ukf", "triangulation"):
        out = Path(args.out) / name
        tracks = reconstruct(scene, name, out=out)
        if scene.truth is not None:
            rows.append((name, box_errors(tracks, scene.truth, scene.rig.up)))
        print(f"  {name}: {len(tracks)} rows in {tracks.info['seconds']:.2f} s -> {out}/tracks.csv")
    print("\nErrors against the dataset's own positions (positionID grid, 2.5 cm cells):")
    print(error_table(rows))
    p = PAPER["multiviewx"]
    print(f"\nPaper (Ma et al., UKF) on MultiviewX: MOTA {p['MOTA']}%, OSPA(2) {p['OSPA2_m']} m")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from gt3dkit.api import ESTIMATORS
    from gt3dkit.io.datasets import LAYOUTS
    from gt3dkit.sim import SIM_LAYOUTS

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
    r.set_defaults(func=cmd_reconstruct)

    s = sub.add_parser("simulate", help="write a seeded synthetic scene with its truth")
    s.add_argument("--layout", choices=SIM_LAYOUTS, default="native")
    s.add_argument("--out", required=True)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--frames", type=int, default=40)
    s.add_argument("--people", type=int, default=10)
    s.add_argument("--noise-px", type=float, default=0.0)
    s.add_argument("--dropout", type=float, default=0.15)
    s.set_defaults(func=cmd_simulate)

    e = sub.add_parser("evaluate", help="score OUT/tracks.csv against an input's truth")
    e.add_argument("out", help="a reconstruct output folder")
    e.add_argument("--truth", required=True, help="the input folder that carries the truth")
    e.add_argument("--layout", choices=LAYOUTS)
    e.add_argument("--max-dist-m", type=float, default=1.0, help="MOT match distance")
    e.set_defaults(func=cmd_evaluate)

    d = sub.add_parser("demo", help="reconstruct the bundled MultiviewX subset, print errors")
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

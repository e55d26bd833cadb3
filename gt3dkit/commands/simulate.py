"""``gt3d simulate``: the option rules and the call of the simulator."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from gt3dkit.commands.common import (
    check_output,
)
from gt3dkit.errors import InputError
from gt3dkit.io.clocks import CameraClocks
from gt3dkit.io.skeletonfile import named_skeleton
from gt3dkit.sim import (
    Errors,
    simulate,
    simulate_skeletons,
    to_z_up,
    write_coco,
    write_openpose,
    write_scene,
    write_skeleton_scene,
)
from gt3dkit.skeletons import DETECTOR_SKELETONS


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
    for name, v in (("--dropout", args.dropout), ("--missing", args.missing)):
        if not 0 <= v < 1:
            raise InputError(name, f"expected a fraction in [0, 1), got {v}")
    try:
        return Errors(outliers=args.outliers, swaps=args.swaps, glitch=args.glitch,
                      shifted=args.shifted, gap=gap, single_view=args.single_view,
                      cut_by_nearer=args.cut_by_nearer,
                      dropped=args.missing if args.kind == "skeleton" else args.dropout)
    except ValueError as e:
        raise InputError("simulate", str(e)) from None


#: Largest simulated scene, in 2D annotations (boxes, or keypoints): about 2 GB of memory.
SIM_MAX_POINTS = 20_000_000


#: simulate options that apply to one kind of scene only.
_SIM_ONLY = {"boxes": ("motion", "dropout", "shifted", "global_ids", "cut_by_nearer"),
             "skeleton": ("missing", "skeleton", "conf", "outliers", "swaps", "glitch", "late_frames",
                          "camera_fps")}


def per_camera(text: str | None, option: str, cameras: int) -> np.ndarray | None:
    """A comma-separated number per camera (``--late-frames``, ``--camera-fps``), or None."""
    if text is None:
        return None
    try:
        v = np.array([float(x) for x in text.split(",")])
    except ValueError:
        raise InputError(option, f"{text!r}: expected numbers separated by commas") from None
    if len(v) != cameras or not np.all(np.isfinite(v)):
        raise InputError(option, f"needs one finite number per camera ({cameras}), got {len(v)}")
    return v


def _write_skeletons(args: argparse.Namespace, errors: Errors, cams: int) -> int:
    """``gt3d simulate --kind skeleton``: the scene simulated and written (native, Panoptic, OpenPose or
    COCO), with the cameras' clocks where they are given."""
    n_err = ""
    late, rates = (per_camera(v, option, cams) for v, option in ((args.late_frames, "--late-frames"),
                                                                   (args.camera_fps, "--camera-fps")))
    try:
        sk = simulate_skeletons(args.layout, seed=args.seed, frames=args.frames,
                                people=args.people, noise_px=args.noise_px,
                                cameras=args.cameras or 10,
                                skeleton=args.skeleton, errors=errors,
                                confidences=args.conf, fps=args.fps or 30.0, lens=args.lens,
                                late_frames=late, camera_fps=rates)
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
    if late is not None or rates is not None:
        C = len(sk.rig.cameras)
        clocks = CameraClocks(tuple(sk.rig.names), np.zeros(C) if late is None else late, np.zeros(C),
                              np.full(C, np.nan) if rates is None else rates)
        (Path(args.out) / "true_time_offsets.csv").write_text(clocks.text(), encoding="utf-8")
        n_err += ", cameras on their own clocks (true_time_offsets.csv)"
    print(f"wrote {args.format or args.layout} skeleton scene to {args.out}: {args.cameras or 10} "
          "cameras, "
          f"{args.frames} frames, {args.people} people ({args.skeleton}), "
          f"{'z-up' if args.format == 'openpose' else 'y-down'} world{n_err}")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:

    check_output(args.out)
    for kind, names in _SIM_ONLY.items():
        for n in names:
            if args.kind != kind and getattr(args, n) not in (None, False, 0.0):
                raise InputError("--" + n.replace("_", "-"), f"applies to --kind {kind} scenes")
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
    per = named_skeleton(args.skeleton).n_joints if args.kind == "skeleton" else 1
    size = args.frames * args.people * cams * per
    if size > SIM_MAX_POINTS:
        raise InputError("--frames/--people/--cameras",
                         f"{args.frames} frames x {args.people} people x {cams} cameras"
                         + (f" x {per} joints" if per > 1 else "")
                         + f" = {size:.3g} annotations, more than the {SIM_MAX_POINTS:.0e} "
                           "gt3d simulate writes")
    n_err = ""
    if args.lens != "pinhole" and args.layout != "native":
        raise InputError("--lens", f"the {args.layout} layout's calibration holds OpenCV's pinhole lens "
                                   "only: a fisheye scene is written in the native layout")
    if args.kind == "skeleton":
        return _write_skeletons(args, errors, cams)
    if args.layout == "panoptic":
        raise InputError("simulate", "box scenes are native, wildtrack or multiviewx")
    try:
        sim = simulate(args.layout, seed=args.seed, frames=args.frames, people=args.people,
                       noise_px=args.noise_px, errors=errors,
                       motion=args.motion, cameras=args.cameras, fps=args.fps, labels=args.labels,
                       lens=args.lens)
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

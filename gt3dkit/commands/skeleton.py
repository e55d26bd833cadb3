"""``gt3d skeleton``: the skeletons gt3dkit knows, one described and checked, or written to a file
to start one's own from (:mod:`gt3dkit.io.skeletonfile`)."""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from gt3dkit.errors import InputError
from gt3dkit.io.skeletonfile import named_skeleton, read_skeleton, shipped_skeletons, write_skeleton
from gt3dkit.skeletons import SKELETONS, Skeleton


def _row(sk: Skeleton, where: str) -> str:
    return (f"{sk.name:<14}{sk.n_joints:>7}{len(sk.bone_names):>7}{len(sk.left_right):>7}"
            f"{len(sk.groups):>8}  {'yes' if sk.up and sk.floor else 'no':<10}{where}")


def _described(sk: Skeleton) -> list[str]:
    """What a skeleton holds, line by line."""
    def names(xs: tuple[str, ...] | list[str]) -> str:
        return ", ".join(xs) if xs else "none"

    return [
        f"{sk.name}: {sk.n_joints} joints, {len(sk.bone_names)} bones, {len(sk.left_right)} left/right "
        f"pairs, {len(sk.groups)} rigid groups ({len(sk.tie_names)} distances held)",
        f"  joints: {names(sk.joints)}",
        f"  bones: {names([f'{a}-{b}' for a, b in sk.bone_names])}",
        f"  left/right: {names([f'{a}/{b}' for a, b in sk.left_right])}",
        *(f"  group {k}: {names(g)}" for k, g in enumerate(sk.groups)),
        f"  up: {names(sk.up)}; floor: {names(sk.floor)}"
        + ("" if sk.up and sk.floor else " (a rig from people needs both)"),
        f"  pose: {'its own [pose]' if sk.pose else 'the standing person by joint name'}"
        + (f"; a detector writes {sk.detector_points} points, the first {sk.n_joints} read"
           if sk.detector_points else ""),
    ]


def cmd_skeleton(args: argparse.Namespace) -> int:
    if args.skeleton is None:
        if args.write is not None:
            raise InputError("--write", "name the skeleton to write (gt3d skeleton NAME --write FILE)")
        print(f"{'name':<14}{'joints':>7}{'bones':>7}{'pairs':>7}{'groups':>8}  {'up/floor':<10}where")
        for sk in SKELETONS.values():
            print(_row(sk, "built in (gt3dkit/data/skeletons/human)"))
        for path in shipped_skeletons().values():
            print(_row(read_skeleton(path), f"shipped file ({path.name})"))
        print("gt3d skeleton NAME|FILE describes and checks one; --write FILE copies it to start your own")
        return 0
    sk = named_skeleton(args.skeleton)  # read and checked: one error line otherwise
    out = Path(args.write) if args.write is not None else None
    if out is not None:
        if out.suffix.lower() != ".toml":
            raise InputError(str(out), "a skeleton file ends in .toml")
        if out.exists():
            raise InputError(str(out), "exists: not overwritten")
        if not out.parent.is_dir():
            raise InputError(str(out.parent), "no such folder")
    for line in _described(sk):
        print(line)
    if out is not None:
        fd, tmp = tempfile.mkstemp(prefix=".skeleton-", suffix=".toml", dir=out.parent)
        os.close(fd)
        try:
            write_skeleton(sk, Path(tmp))
            os.replace(tmp, out)  # whole or not at all
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        print(f"written to {out} (gt3d ... --skeleton {out})")
    return 0

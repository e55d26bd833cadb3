"""Dataset loaders. Every loader returns the same :class:`gt3dkit.types.Scene`."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.types import Scene

LAYOUTS = ("native", "wildtrack", "multiviewx", "panoptic")


def detect_layout(root: Path) -> str:
    """Name the layout of an input folder from the files it holds."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(str(root), "not a directory")
    if (root / "cameras.json").exists():
        return "native"
    if (root / "calibrations" / "intrinsic_zero").is_dir():
        return "wildtrack"
    if (root / "calibrations" / "intrinsic").is_dir():
        return "multiviewx"
    if any(root.glob("calibration_*.json")):
        return "panoptic"
    raise InputError(str(root), "unknown input layout: expected cameras.json (native), "
                                "calibrations/intrinsic_zero (WILDTRACK), "
                                "calibrations/intrinsic (MultiviewX) or "
                                "calibration_<seq>.json (CMU Panoptic)")


def load_scene(root: Path | str, layout: str | None = None, skeleton: str | None = None,
               fps: float | None = None, **panoptic_options: Any) -> Scene:
    """Load any supported input folder (layout detected when not given).

    ``skeleton`` names the joint order of native ``keypoints.csv`` (default: from the
    data); ``fps`` overrides the input's frame rate. ``panoptic_options`` go to
    :func:`gt3dkit.io.datasets.panoptic.load` (``cameras``, ``noise_px``, ``seed``,
    ``min_conf``). Every scene then goes through :func:`checks.check_scene`.
    """
    from gt3dkit.io.datasets import checks, native, panoptic, wildtrack

    layout = layout or detect_layout(Path(root))
    if skeleton is not None and layout != "native":
        raise InputError("--skeleton", f"applies to native keypoints.csv inputs, not {layout}")
    if panoptic_options and layout != "panoptic":
        raise InputError(str(root), f"options {sorted(panoptic_options)} apply to the panoptic "
                                    "layout only")
    if layout == "native":
        scene = native.load(Path(root), skeleton)
    elif layout == "panoptic":
        scene = panoptic.load(Path(root), **panoptic_options)
    elif layout in wildtrack.LAYOUTS:
        scene = wildtrack.load(Path(root), wildtrack.LAYOUTS[layout])
    else:
        raise InputError(str(root), f"unknown layout {layout!r} (known: {', '.join(LAYOUTS)})")
    if len(scene.obs) == 0:
        raise InputError(str(root), "no annotations in any frame")
    if fps is not None:
        if not (np.isfinite(fps) and native.FPS_RANGE[0] <= fps <= native.FPS_RANGE[1]):
            raise InputError("fps", f"must be in [{native.FPS_RANGE[0]:g}, {native.FPS_RANGE[1]:g}]"
                                    f", got {fps}")
        scene = dataclasses.replace(scene, fps=float(fps), fps_assumed="")
    return checks.check_scene(scene)

"""Dataset loaders. Every loader returns the same :class:`gt3dkit.types.Scene`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

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
               **panoptic_options: Any) -> Scene:
    """Load any supported input folder (layout detected when not given).

    ``skeleton`` names the joint order of native ``keypoints.csv`` (default: from the
    data). ``panoptic_options`` go to :func:`gt3dkit.io.datasets.panoptic.load`
    (``cameras``, ``noise_px``, ``seed``, ``min_conf``).
    """
    from gt3dkit.io.datasets import native, panoptic, wildtrack

    layout = layout or detect_layout(Path(root))
    if panoptic_options and layout != "panoptic":
        raise ValueError(f"options {sorted(panoptic_options)} apply to the panoptic layout only")
    if layout == "native":
        return native.load(Path(root), skeleton)
    if layout == "panoptic":
        return panoptic.load(Path(root), **panoptic_options)
    if layout in wildtrack.LAYOUTS:
        return wildtrack.load(Path(root), wildtrack.LAYOUTS[layout])
    raise InputError(str(root), f"unknown layout {layout!r} (known: {', '.join(LAYOUTS)})")

"""Dataset loaders. Every loader returns the same :class:`gt3dkit.types.Scene`."""

from __future__ import annotations

from pathlib import Path

from gt3dkit.errors import InputError
from gt3dkit.types import Scene

LAYOUTS = ("native", "wildtrack", "multiviewx")


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
    raise InputError(str(root), "unknown input layout: expected cameras.json (native), "
                                "calibrations/intrinsic_zero (WILDTRACK) or "
                                "calibrations/intrinsic (MultiviewX)")


def load_scene(root: Path, layout: str | None = None) -> Scene:
    """Load any supported input folder (layout detected when not given)."""
    from gt3dkit.io.datasets import native, wildtrack

    layout = layout or detect_layout(root)
    if layout == "native":
        return native.load(Path(root))
    if layout in wildtrack.LAYOUTS:
        return wildtrack.load(Path(root), wildtrack.LAYOUTS[layout])
    raise InputError(str(root), f"unknown layout {layout!r} (known: {', '.join(LAYOUTS)})")

"""Every calibration format our users have, read into (and written from) one
:class:`~gt3dkit.rig.Rig`.

=============  ======================================================  =====
format         files                                                   write
=============  ======================================================  =====
native         ``cameras.json``                                        yes
grid           WILDTRACK / MultiviewX ``calibrations/`` OpenCV XML     yes
opencv         OpenCV FileStorage ``.yml``/``.yaml``/``.xml`` per camera  yes
toml           Anipose / Pose2Sim calibration ``.toml``                yes
colmap         COLMAP sparse model (``cameras``/``images`` .bin/.txt)   yes
panoptic       CMU Panoptic ``calibration_<seq>.json`` (HD cameras)    no
=============  ======================================================  =====

:func:`read_calibration` detects the format of a file or folder.
"""

from __future__ import annotations

from pathlib import Path

from gt3dkit.calib.formats import colmap, grid, native, opencv, panoptic, toml
from gt3dkit.calib.formats.grid import LAYOUTS
from gt3dkit.errors import InputError
from gt3dkit.rig import Rig

FORMATS = ("native", "grid", "opencv", "toml", "colmap", "panoptic")
WRITABLE = ("native", "grid", "opencv", "toml", "colmap")


def detect_format(path: Path) -> str:
    """The calibration format of a file or folder (see the module table)."""
    path = Path(path)
    if not path.exists():
        raise InputError(str(path), "no such file or folder")
    if path.is_file():
        if path.suffix == ".toml":
            return "toml"
        if path.suffix in opencv.SUFFIXES:
            return "opencv"
        if path.name in ("cameras.bin", "cameras.txt", "images.bin", "images.txt"):
            return "colmap"
        if path.suffix == ".json":
            return "panoptic" if path.name.startswith("calibration_") else "native"
        raise InputError(str(path), "unknown calibration file (expected .json, .toml, .yml, .yaml, "
                                    ".xml or a COLMAP cameras/images file)")
    if (path / "cameras.json").is_file():
        return "native"
    if any(path.glob("calibration_*.json")):
        return "panoptic"
    if grid.layout_of(path) is not None:
        return "grid"
    if colmap.model_folder(path) is not None:
        return "colmap"
    tomls = sorted(path.glob("*.toml"))
    if len(tomls) == 1:
        return "toml"
    if any(p.suffix in opencv.SUFFIXES for p in path.iterdir()):
        return "opencv"
    raise InputError(str(path), "no calibration found (cameras.json, calibration_<seq>.json, "
                                "calibrations/, a COLMAP model, one .toml, or OpenCV .yml/.xml files)")


def read_calibration(path: str | Path, fmt: str | None = None) -> Rig:
    """The rig of a calibration file or folder in any supported format."""
    path = Path(path)
    fmt = fmt or detect_format(path)
    if fmt == "native":
        return native.read(path / "cameras.json" if path.is_dir() else path)
    if fmt == "toml":
        return toml.read(path if path.is_file() else sorted(path.glob("*.toml"))[0])
    reader = {"grid": grid.read, "opencv": opencv.read, "colmap": colmap.read,
              "panoptic": panoptic.read}.get(fmt)
    if reader is None:
        raise InputError("--format", f"unknown calibration format {fmt!r} (known: {', '.join(FORMATS)})")
    return reader(path)


def write_calibration(rig: Rig, path: str | Path, fmt: str = "native") -> Path:
    """Write ``rig`` in ``fmt`` into the folder ``path``; returns the file or folder written.

    Left-handed rigs (MultiviewX's Unity export, ``depth_sign = -1``) exist in the native
    format and the WILDTRACK/MultiviewX layout only.
    """
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    if fmt not in ("native", "grid") and any(c.depth_sign < 0 for c in rig.cameras):
        raise InputError("--format", f"a left-handed rig (depth_sign -1) cannot be written as {fmt}")
    if fmt == "native":
        native.write(rig, path / "cameras.json")
        return path / "cameras.json"
    if fmt == "toml":
        toml.write(rig, path / "calibration.toml")
        return path / "calibration.toml"
    if fmt == "opencv":
        opencv.write(rig, path)
    elif fmt == "colmap":
        colmap.write(rig, path)
    elif fmt == "grid":
        g = LAYOUTS["multiviewx" if any(c.depth_sign < 0 for c in rig.cameras) else "wildtrack"]
        if not set(rig.names) <= set(g.cameras):
            raise InputError("--format", f"the {g.name} layout names its cameras {', '.join(g.cameras)}")
        grid.write(rig, path, g)
    else:
        raise InputError("--format", f"cannot write {fmt!r} (writable: {', '.join(WRITABLE)})")
    return path

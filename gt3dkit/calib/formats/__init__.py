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

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from gt3dkit.calib.formats import colmap, grid, native, opencv, panoptic, toml
from gt3dkit.calib.formats.grid import LAYOUTS
from gt3dkit.errors import InputError
from gt3dkit.rig import Rig


@dataclass(frozen=True)
class CalibFormat:
    """One calibration format: whether a file or a folder holds it (``is_file``,
    ``is_folder``), its reader (of that file or folder) and its writer into a folder (returns
    the file or folder written; None: not writable)."""

    name: str
    is_file: Callable[[Path], bool]
    is_folder: Callable[[Path], bool]
    read: Callable[[Path], Rig]
    write: Callable[[Rig, Path], Path] | None = None


def _write_native(rig: Rig, folder: Path) -> Path:
    native.write(rig, folder / "cameras.json")
    return folder / "cameras.json"


def _write_toml(rig: Rig, folder: Path) -> Path:
    toml.write(rig, folder / "calibration.toml")
    return folder / "calibration.toml"


def _write_in(writer: Callable[[Rig, Path], None]) -> Callable[[Rig, Path], Path]:
    def write(rig: Rig, folder: Path) -> Path:
        writer(rig, folder)
        return folder

    return write


def _write_grid(rig: Rig, folder: Path) -> Path:
    g = LAYOUTS["multiviewx" if any(c.depth_sign < 0 for c in rig.cameras) else "wildtrack"]
    if not set(rig.names) <= set(g.cameras):
        raise InputError("--format", f"the {g.name} layout names its cameras {', '.join(g.cameras)}")
    grid.write(rig, folder, g)
    return folder


def _toml_files(path: Path) -> list[Path]:
    return sorted(path.glob("*.toml"))


#: Every format, in the order a folder is tested for it (the first that matches is its format).
REGISTRY: dict[str, CalibFormat] = {f.name: f for f in (
    CalibFormat("native", lambda p: p.suffix == ".json" and not p.name.startswith("calibration_"),
                lambda p: (p / "cameras.json").is_file(),
                lambda p: native.read(p / "cameras.json" if p.is_dir() else p), _write_native),
    CalibFormat("panoptic", lambda p: p.suffix == ".json" and p.name.startswith("calibration_"),
                lambda p: any(p.glob("calibration_*.json")), panoptic.read),
    CalibFormat("grid", lambda p: False, lambda p: grid.layout_of(p) is not None, grid.read, _write_grid),
    CalibFormat("colmap", lambda p: p.name in ("cameras.bin", "cameras.txt", "images.bin", "images.txt"),
                lambda p: colmap.model_folder(p) is not None, colmap.read, _write_in(colmap.write)),
    CalibFormat("toml", lambda p: p.suffix == ".toml", lambda p: len(_toml_files(p)) == 1,
                lambda p: toml.read(p if p.is_file() else _toml_files(p)[0]), _write_toml),
    CalibFormat("opencv", lambda p: p.suffix in opencv.SUFFIXES,
                lambda p: any(q.suffix in opencv.SUFFIXES for q in p.iterdir()), opencv.read,
                _write_in(opencv.write)),
)}
FORMATS = tuple(REGISTRY)
WRITABLE = tuple(k for k, f in REGISTRY.items() if f.write is not None)


def detect_format(path: Path) -> str:
    """The calibration format of a file or folder (see the module table)."""
    path = Path(path)
    if not path.exists():
        raise InputError(str(path), "no such file or folder")
    test = "is_file" if path.is_file() else "is_folder"
    for name, f in REGISTRY.items():
        if getattr(f, test)(path):
            return name
    if path.is_file():
        raise InputError(str(path), "unknown calibration file (expected .json, .toml, .yml, .yaml, "
                                    ".xml or a COLMAP cameras/images file)")
    raise InputError(str(path), "no calibration found (cameras.json, calibration_<seq>.json, "
                                "calibrations/, a COLMAP model, one .toml, or OpenCV .yml/.xml files)")


def read_calibration(path: str | Path, fmt: str | None = None) -> Rig:
    """The rig of a calibration file or folder in any supported format."""
    path = Path(path)
    fmt = fmt or detect_format(path)
    if fmt not in REGISTRY:
        raise InputError("--format", f"unknown calibration format {fmt!r} (known: {', '.join(FORMATS)})")
    return REGISTRY[fmt].read(path)


#: Writable formats that have no fisheye lens (the WILDTRACK / MultiviewX layout's readers assume
#: OpenCV's pinhole model).
PINHOLE_ONLY = ("grid",)


def write_calibration(rig: Rig, path: str | Path, fmt: str = "native") -> Path:
    """Write ``rig`` in ``fmt`` into the folder ``path``; returns the file or folder written.

    Left-handed rigs (MultiviewX's Unity export, ``depth_sign = -1``) exist in the native
    format and the WILDTRACK/MultiviewX layout only.
    """
    path = Path(path)
    writer = REGISTRY[fmt].write if fmt in REGISTRY else None
    if writer is None:
        raise InputError("--format", f"cannot write {fmt!r} (writable: {', '.join(WRITABLE)})")
    path.mkdir(parents=True, exist_ok=True)
    if fmt not in ("native", "grid") and any(c.depth_sign < 0 for c in rig.cameras):
        raise InputError("--format", f"a left-handed rig (depth_sign -1) cannot be written as {fmt}")
    fisheye = [c.name for c in rig.cameras if c.lens == "fisheye"]
    if fmt in PINHOLE_ONLY and fisheye:
        raise InputError("--format", f"{fmt} holds OpenCV's pinhole lens only; {', '.join(fisheye)} "
                                     "have a fisheye lens (write native, opencv, toml or colmap)")
    return writer(rig, path)

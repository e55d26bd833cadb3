"""An anipose session folder, as anipose lays it out and its users have it::

    config.toml                      # the project's (here or up to three folders above)
    <session>/calibration/calibration.toml
    <session>/pose-2d/<video>-camA.h5   # DeepLabCut's output per camera (.h5 or .csv)

The session is the folder given. Its cameras are named as anipose names them: the first group of
``[triangulation] cam_regex`` in a file's name (anipose's default ``-cam([A-Z])$``), matched to
the calibration's camera names. The bones are ``[labeling] scheme``'s chains (each chain's
neighbours joined), or ``--skeleton FILE``'s; the left/right pairs those the body parts' names
say where the bones mirror them. ``[pipeline] pose_2d`` and ``calibration_results`` rename the
two folders as anipose reads them. The files are read as :mod:`gt3dkit.io.datasets.dlc` reads
DeepLabCut's.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from gt3dkit.errors import InputError
from gt3dkit.io.datasets.dlc import body_skeleton, camera_files, dlc_files, scene_of
from gt3dkit.io.datasets.mot import calibration_beside
from gt3dkit.io.datasets.sleap import side_pairs
from gt3dkit.skeletons import Skeleton, skeleton_from_doc
from gt3dkit.types import JsonDict, JsonValue, Scene

#: anipose's defaults (anipose/anipose.py, DEFAULT_CONFIG and its docs)
CAM_REGEX = "-cam([A-Z])$"
POSE_2D = "pose-2d"
CALIBRATION = "calibration"
#: how many folders above the session a project's config.toml may sit (anipose nests sessions)
CONFIG_DEPTH = 3


def _config(root: Path) -> tuple[Path | None, JsonDict]:
    """The nearest ``config.toml`` at or above ``root`` and its tables (none: anipose's defaults)."""
    for folder in [root, *root.resolve().parents][:CONFIG_DEPTH + 1]:
        p = folder / "config.toml"
        if p.is_file():
            try:
                return p, tomllib.loads(p.read_text(encoding="utf-8"))
            except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
                raise InputError(str(p), f"not TOML ({e})") from None
    return None, {}


def _setting(cfg: JsonDict, table: str, key: str, default: str, where: str) -> str:
    t = cfg.get(table, {})
    v = t.get(key, default) if isinstance(t, dict) else default
    if not isinstance(v, str) or not v:
        raise InputError(f"{where}: {table}.{key}", f"expected a text, got {v!r}")
    return v


def found(root: Path) -> bool:
    """A session folder: its ``pose-2d/`` holds DeepLabCut files."""
    return (root / POSE_2D).is_dir() and bool(dlc_files(root / POSE_2D))


def _scheme_skeleton(parts: list[str], scheme: JsonValue, where: str) -> Skeleton:
    """The body parts as a skeleton whose bones are the scheme's chains (each chain's neighbours)."""
    if not isinstance(scheme, list) or not all(isinstance(c, list) and all(isinstance(x, str) for x in c)
                                               for c in scheme):
        raise InputError(f"{where}: labeling.scheme", "expected a list of chains of body part names")
    bones: list[tuple[str, str]] = []
    for k, chain in enumerate(scheme):
        unknown = [x for x in chain if x not in parts]
        if unknown:
            raise InputError(f"{where}: labeling.scheme[{k}]", f"{unknown[0]!r} is no body part of the files "
                                                               f"({', '.join(parts)})")
        bones += [(a, b) for a, b in zip(chain, chain[1:], strict=False)
                  if a != b and (a, b) not in bones and (b, a) not in bones]
    doc: JsonDict = {"name": "anipose", "joints": parts, "bones": [list(b) for b in bones],
                     "pairs": [list(p) for p in side_pairs(parts, bones)]}
    return skeleton_from_doc(doc, f"{where}: labeling.scheme")


def load(root: Path, skeleton: str | None = None, calib: Path | str | None = None,
         fps: float | None = None) -> Scene:
    root = Path(root)
    cfg_path, cfg = _config(root)
    where = str(cfg_path) if cfg_path else "anipose's defaults"
    cam_regex = _setting(cfg, "triangulation", "cam_regex", CAM_REGEX, where)
    pose = root / _setting(cfg, "pipeline", "pose_2d", POSE_2D, where)
    results = root / _setting(cfg, "pipeline", "calibration_results", CALIBRATION, where)
    if calib is None and (results / "calibration.toml").is_file():
        calib = results / "calibration.toml"
    rig, fps_doc, cal = calibration_beside(root, calib)
    files = camera_files(pose, rig, cam_regex)
    if not files:
        raise InputError(str(pose), "no DeepLabCut file (.h5 or .csv) per camera")
    labeling = cfg.get("labeling")
    scheme = labeling.get("scheme") if isinstance(labeling, dict) else None

    def skeleton_of(parts: list[str]) -> Skeleton:
        if skeleton is not None or scheme is None:
            return body_skeleton(parts, skeleton)
        return _scheme_skeleton(parts, scheme, where)

    return scene_of(root, files, (rig, fps_doc, cal), skeleton_of, fps, "anipose")

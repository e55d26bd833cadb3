"""MOTChallenge boxes per camera: ``mot/<camera>.txt`` beside a calibration.

Each ``mot/<camera>.txt`` is MOTChallenge's comma-separated text without a header:
``frame,id,left,top,width,height,conf,x,y,z`` (frames as written, usually 1-based; pixels of
the distorted image; ``x,y,z`` ignored). The ids are the camera's own (every annotation task
numbers its people): :mod:`gt3dkit.fusion.preparation.associate` turns them into global identities.
Rows with ``conf`` 0 are MOTChallenge's "ignore" boxes and are skipped (with a warning); an id
of -1 (a detection without a track) is an error, as the tracklets are what is associated. In a
folder ``gt3d project`` wrote (it holds its ``projection.json``), rows with ``conf`` below 1
are the shapes it drew from the estimate (:mod:`gt3dkit.io.labels`) that nobody changed (an
annotation tool exporting MOT writes 1): not labels but the estimate's own projection, left out
with a warning (see :mod:`gt3dkit.io.datasets.tasks`).

The calibration is the first of ``cameras.json``, ``calibration/``, ``*.toml`` (not Pose2Sim's
``Config.toml``) or ``sparse/`` in the folder (any format of :mod:`gt3dkit.calib.formats`), or
``--calib``. Cameras are matched by name (file stem = calibration name), or, when the names
differ but the counts agree, in natural sorted order (as Pose2Sim does), with a warning naming
every pair.
Frame rate: the calibration's (``cameras.json`` ``fps``), or ``--fps``, else 25 assumed.
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import numpy as np

from gt3dkit.calib.formats import detect_format, read_calibration
from gt3dkit.calib.formats.native import load_cameras
from gt3dkit.errors import InputError
from gt3dkit.io import labels
from gt3dkit.io.datasets.checks import check_pixels
from gt3dkit.io.datasets.common import RowBuilder, camera_ids, sim_box_labels
from gt3dkit.io.datasets.native import write_cameras
from gt3dkit.io.datasets.wildtrack import read_truth_csv
from gt3dkit.parse import HashedFile, iter_csv_rows, parse_frame, parse_int, sha256
from gt3dkit.types import Rig, Scene, SimScene

MOT_COLUMNS = ("frame", "id", "left", "top", "width", "height", "conf")
DEFAULT_FPS = 25.0


def natural_key(s: str) -> list[object]:
    """``cam_2`` before ``cam_10``."""
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", s)]


def calibration_candidates(root: Path) -> list[Path]:
    """Every calibration beside the annotations in ``root`` that a format reads, in the order one
    is taken: ``cameras.json``, ``calibration/``, the ``*.toml`` (``calibration*.toml`` first; not
    Pose2Sim's ``Config.toml``, nor a TOML of no table, such as anipose's ``board.toml``),
    ``sparse/``."""
    tomls = [p for p in sorted(root.glob("*.toml")) if p.name.lower() != "config.toml"]  # not Pose2Sim's
    tomls.sort(key=lambda p: not p.stem.lower().startswith("calib"))  # anipose's calibration.toml first
    out = []
    for p in [root / "cameras.json", root / "calibration", *tomls, root / "sparse"]:
        if p.exists() and not (p.suffix.lower() == ".toml" and _flat_toml(p)):
            try:
                detect_format(p)
            except InputError:
                continue
            out.append(p)
    return out


def _flat_toml(path: Path) -> bool:
    """A TOML file of keys without a table (anipose's ``board.toml``: a board, not cameras; a
    calibration holds a table per camera). One that does not parse is not called flat: read as
    the calibration, its error names it."""
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return False
    return not any(isinstance(v, dict) for v in doc.values())


def find_calibration(root: Path) -> Path | None:
    """The first of :func:`calibration_candidates` (None: none)."""
    found = calibration_candidates(root)
    return found[0] if found else None


def calibration_beside(root: Path, calib: Path | str | None) -> tuple[Rig, float | None, Path]:
    """The rig of ``--calib`` or of the calibration found beside the annotations
    (:func:`find_calibration`), its frame rate (``cameras.json`` only) and its path."""
    cal = Path(calib) if calib is not None else find_calibration(root)
    if cal is None:
        raise InputError(str(root), "no calibration beside the annotations (cameras.json, calibration/, "
                                    "*.toml or sparse/): pass --calib")
    if detect_format(cal) == "native":
        rig, fps, _ = load_cameras(cal / "cameras.json" if cal.is_dir() else cal)
        return rig, fps, cal
    return read_calibration(cal), None, cal


def match_cameras(files: list[str], rig: Rig, where: str, warnings: list[str]) -> dict[str, int]:
    """file stem -> camera index: by name, else by natural sorted order (warned)."""
    names = list(rig.names)
    if all(f in names for f in files):
        return {f: names.index(f) for f in files}
    if len(files) != len(names):
        missing = [f for f in files if f not in names]
        raise InputError(where, f"camera file {missing[0]!r} matches no calibrated camera "
                                f"({', '.join(names)}), and {len(files)} files cannot be paired with "
                                f"{len(names)} cameras by order")
    fs, ns = sorted(files, key=natural_key), sorted(names, key=natural_key)
    warnings.append("cameras paired by sorted order, names differ: " +
                    ", ".join(f"{f} -> {n}" for f, n in zip(fs, ns, strict=True)))
    return {f: names.index(n) for f, n in zip(fs, ns, strict=True)}


def load(root: Path, calib: Path | str | None = None, fps: float | None = None) -> Scene:
    root = Path(root)
    folder = root / "mot"
    txts = sorted(folder.glob("*.txt"), key=lambda p: natural_key(p.stem))
    if not txts:
        raise InputError(str(folder), "no <camera>.txt files")
    rig, fps_doc, cal = calibration_beside(root, calib)
    warnings: list[str] = []
    files = {f"mot/{p.name}": "" for p in txts}  # each file's digest as it is read
    cam_of = match_cameras([p.stem for p in txts], rig, str(folder), warnings)
    rb = RowBuilder()
    ignored = 0
    projected = (root / "projection.json").is_file()
    drawn = 0
    for p in txts:
        cam = cam_of[p.stem]
        with HashedFile(p) as hashed:  # opened once: read and hashed as it is read
            for line, r in iter_csv_rows(p, MOT_COLUMNS, warnings, header=False, shared=hashed):
                where = f"{p}: line {line}"
                frame, tid = parse_frame(where, r["frame"]), parse_int(where, r["id"], "id")
                vals = []
                for k in ("left", "top", "width", "height", "conf"):
                    try:
                        vals.append(float(r[k]))
                    except ValueError:
                        raise InputError(where, f"malformed value: {k} must be a number, "
                                                f"got {r[k]!r}") from None
                x, y, w, h, conf = vals
                if conf == 0:
                    ignored += 1
                    continue
                if projected and conf < 1:
                    drawn += 1
                    continue
                if tid < 0:
                    raise InputError(where, f"id {tid}: a detection without a track id (gt3dkit associates "
                                            "per-camera tracks; run a tracker per camera first)")
                if not all(math.isfinite(v) for v in vals):
                    raise InputError(where, f"box has a non-finite value {vals[:4]}")
                if w <= 0 or h <= 0:
                    raise InputError(where, f"degenerate box: width {w:g}, height {h:g}")
                box = [x, y, x + w, y + h]
                check_pixels(where, rig.cameras[cam], box, "box")
                rb.add_box(frame, cam, tid, box, where)
            files[f"mot/{p.name}"] = hashed.hexdigest()
    if ignored:
        warnings.append(f"{folder}: {ignored} boxes with conf 0 (MOTChallenge's ignore flag) skipped")
    if drawn:
        warnings.append(f"{folder}: {drawn} boxes gt3d project drew that nobody changed (conf below 1 "
                        "beside its projection.json) left out (the estimate's own projection, not labels)")
    obs = rb.build()
    if len(obs) == 0:
        raise InputError(str(root), "no annotations in any frame")
    files[f"calibration:{cal.name}"] = sha256(cal) if cal.is_file() else "folder"
    truth = None
    if (root / "truth.csv").exists():
        truth = read_truth_csv(root / "truth.csv", files, root)
    return Scene(rig=rig, obs=obs, layout="mot", truth=truth, fps=float(fps or fps_doc or DEFAULT_FPS),
                 frames=np.unique(obs.frame), skeleton=None, files=files, root=str(root),
                 warnings=tuple(warnings),
                 fps_assumed="" if (fps or fps_doc) else f"{cal} gives no frame rate")


def write(sim: SimScene, tmp: Path, id_seed: int | None) -> None:
    """A simulated scene as ``cameras.json`` + ``mot/<camera>.txt`` in ``tmp``, each camera's ids
    a random permutation of the people (``id_seed``; None keeps the global ids), written by
    :func:`gt3dkit.io.labels.write_mot` (what ``gt3d project`` writes), read by :func:`load`."""
    write_cameras(sim.rig, sim.fps, tmp)
    ids = camera_ids(sim.truth_id, len(sim.rig.cameras), id_seed)
    labels.write_mot(sim_box_labels(sim, ids), sim.rig, tmp / "mot")

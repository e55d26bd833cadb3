"""DeepLabCut's 2D output as CSV, one file per camera (the ``*.csv`` DeepLabCut writes beside each
analysed video, or ``save_as_csv``), with the calibration beside them::

    calibration.toml                  # or any calibration format (--calib; --calib-units)
    <video of camera back>DLC_<scorer>.csv
    <video of camera mid>DLC_<scorer>.csv  ...

A file is matched to the calibration camera whose name its file name holds (exactly one). Its
header rows name the scorer, for a multi-animal project the ``individuals``, the ``bodyparts``
and the ``coords`` (``x, y, likelihood``); each following row is a frame (its index first, or an
image path of a labelled-data file, whose frame number is taken from the file name). Every file
must name one scorer and the same body parts in the same order, else the error names the file.
The body parts are the joints; the bones come from ``--skeleton FILE`` (a skeleton file whose
joints are those body parts: DeepLabCut's ``config.yaml`` keeps its ``skeleton`` there), else
there are none. A likelihood is read as the detector's confidence (above 1 read as 1, 0 or
below left out, each said). Each camera's individuals are its own ids: the animals are found
across cameras frame by frame (:func:`gt3dkit.fusion.preparation.detections.associate_detections`).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import os
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.io.datasets.common import JointBlock, RowBuilder
from gt3dkit.io.datasets.mot import calibration_beside
from gt3dkit.io.skeletonfile import named_skeleton
from gt3dkit.parse import read_hashed
from gt3dkit.rig import Rig
from gt3dkit.skeletons import Skeleton
from gt3dkit.types import JsonDict, Scene

DEFAULT_FPS = 30.0
H5 = ".h5"
#: header rows of a DeepLabCut CSV (single animal; a multi-animal one has ``individuals`` too)
HEADER = ("scorer", "bodyparts", "coords")


def is_dlc_csv(path: Path) -> bool:
    """A CSV whose first cell is DeepLabCut's ``scorer``."""
    try:
        with open(path, encoding="utf-8-sig") as f:
            return f.readline().split(",", 1)[0].strip() == "scorer"
    except (OSError, UnicodeDecodeError):
        return False


def found(root: Path) -> bool:
    """A folder holding DeepLabCut CSVs or ``.h5`` files (one per camera) beside a calibration."""
    return any(is_dlc_csv(p) for p in root.glob("*.csv")) or any(root.glob(f"*{H5}"))


def have_tables() -> bool:
    """Whether DeepLabCut's ``.h5`` can be read here (pandas and PyTables)."""
    import importlib.util

    return all(importlib.util.find_spec(m) is not None for m in ("pandas", "tables"))


def _preferred(paths: list[Path]) -> list[Path]:
    """Where DeepLabCut wrote a video's ``.h5`` and ``.csv`` both, the one read: the ``.h5`` (its
    own format) where PyTables is here, else the CSV."""
    stems = {p.stem for p in paths if p.suffix.lower() == H5} & {p.stem for p in paths if p.suffix == ".csv"}
    drop = ".csv" if have_tables() else H5
    return [p for p in paths if not (p.stem in stems and p.suffix.lower() == drop)]


def dlc_files(root: Path) -> list[Path]:
    """DeepLabCut's files in ``root``: its CSVs (first cell ``scorer``) and ``.h5`` files. A CSV
    named as DeepLabCut names its output (``<video>DLC_<network>...``) that is empty or not UTF-8
    text is an error (a CSV of another first cell, such as DeepLabCut's skeleton analysis, is
    not read)."""
    csvs = []
    for p in sorted(root.glob("*.csv")):
        if is_dlc_csv(p):
            csvs.append(p)
        elif "DLC_" in p.stem:
            _not_dlc_said(p)
    return _preferred(sorted(csvs + list(root.glob(f"*{H5}"))))


def _not_dlc_said(path: Path) -> None:
    """The error of a file named as DeepLabCut names its CSVs that is empty or not text (one of
    another first cell is passed over)."""
    try:
        with open(path, encoding="utf-8-sig") as f:
            text = f.read(65536)
    except UnicodeDecodeError:
        raise InputError(str(path), "not UTF-8 text: not a DeepLabCut CSV") from None
    except OSError as e:
        raise InputError(str(path), f"cannot be read ({e.strerror})") from None
    if not text.strip():
        raise InputError(str(path), "empty: a DeepLabCut CSV starts with its header rows (scorer, "
                                    "[individuals,] bodyparts, coords)")
    if "\x00" in text:
        raise InputError(str(path), "not text: not a DeepLabCut CSV")


def camera_files(root: Path, rig: Rig, cam_regex: str | None = None) -> dict[str, Path]:
    """Camera name -> its DeepLabCut file: the one file whose name holds the camera's name (or
    whose name ``cam_regex``'s first group gives it, as anipose names cameras)."""
    files = dlc_files(root)
    out: dict[str, Path] = {}
    for cam in rig.names:
        mine = [p for p in files if _camera_of(p, cam_regex) == cam] if cam_regex is not None else [
            p for p in files if re.search(rf"(?<![A-Za-z0-9]){re.escape(cam)}(?![A-Za-z0-9])", _video(p))]
        if len(mine) > 1:
            raise InputError(str(mine[1]), f"a second DeepLabCut file for camera {cam} "
                                           f"(first: {mine[0].name})")
        if mine:
            out[cam] = mine[0]
    loose = [p for p in files if p not in out.values()]
    if loose:
        how = f" (by cam_regex {cam_regex!r}: {_camera_of(loose[0], cam_regex)!r})" if cam_regex else ""
        raise InputError(str(loose[0]), f"its name gives no calibrated camera's "
                                        f"({', '.join(rig.names)}){how}")
    return out


def _camera_of(path: Path, cam_regex: str | None) -> str | None:
    """The camera anipose's ``cam_regex`` finds in a file's name (its first group, stripped)."""
    m = re.search(cam_regex or "", path.stem)
    return m.groups()[0].strip() if m and m.groups() else None


def _video(path: Path) -> str:
    """The video's name in a DeepLabCut file's name (``<video>DLC_<network>...``)."""
    return path.stem.split("DLC_", 1)[0]


class DlcFile:
    """One DeepLabCut file read (its CSV, or its ``.h5``: pandas' table through PyTables):
    ``frames (F,)``, ``individuals``, ``bodyparts``, ``uv (F, I, J, 2)`` (NaN: not found),
    ``likelihood (F, I, J)``, and where each frame is in the file: ``lines (F,)``, counted in
    ``unit`` (a CSV's ``line``, 1-based; an ``.h5`` table's ``row``, 0-based)."""

    def __init__(self, path: Path) -> None:
        raw, self.digest = read_hashed(path)
        table = _h5_table(path, raw) if path.suffix.lower() == H5 else _csv_table(path, raw)
        names, cols, frames, vals, self.lines, self.unit = table
        uniq, first = np.unique(frames, return_index=True)
        if len(first) < len(frames):  # a frame again: name the first repeat and where it was first
            again = int(np.flatnonzero(~np.isin(np.arange(len(frames)), first))[0])
            was = int(first[np.searchsorted(uniq, frames[again])])
            raise InputError(f"{path}: {self.unit} {self.lines[again]}",
                             f"frame {frames[again]} again (first at {self.unit} {self.lines[was]})")
        multi = names[:4] == ["scorer", "individuals", "bodyparts", "coords"]
        if not multi and names[:3] != list(HEADER):
            raise InputError(str(path), "not a DeepLabCut file (header rows scorer, [individuals,] "
                                        f"bodyparts, coords; got {names[:3]})")
        scorers = set(cols[0])
        if len(scorers) != 1:
            named = ", ".join(sorted(scorers))
            raise InputError(f"{path}: scorer", f"columns of {len(scorers)} scorers ({named}): one file "
                                                "is one network's output")
        coords = cols[-1]
        if len(coords) % 3 or coords != ["x", "y", "likelihood"] * (len(coords) // 3):
            raise InputError(f"{path}: coords", "expected x, y, likelihood for every body part")
        parts = cols[-2][::3]
        inds = cols[1][::3] if multi else ["single"] * len(parts)
        self.individuals = list(dict.fromkeys(inds))
        self.bodyparts = list(dict.fromkeys(parts))
        key = {(i, b): k for k, (i, b) in enumerate(zip(inds, parts, strict=True))}
        if len(key) != len(parts):
            raise InputError(f"{path}: bodyparts", "a body part named twice for one individual")
        if np.isinf(vals).any():  # DeepLabCut writes NaN (an empty cell) where a part is not found
            n, k = (int(v[0]) for v in np.nonzero(np.isinf(vals)))
            raise InputError(f"{path}: {self.unit} {self.lines[n]}",
                             f"an infinite value (column {cols[-1][k]} of {cols[-2][k]})")
        F, I, J = len(frames), len(self.individuals), len(self.bodyparts)
        self.frames = frames
        self.uv = np.full((F, I, J, 2), np.nan)
        self.likelihood = np.full((F, I, J), np.nan)
        for (i, b), k in key.items():
            ii, jj = self.individuals.index(i), self.bodyparts.index(b)
            self.uv[:, ii, jj] = vals[:, 3 * k:3 * k + 2]
            self.likelihood[:, ii, jj] = vals[:, 3 * k + 2]


#: a DeepLabCut table: the header levels' names, each level's column labels, ``frames (F,)``, the
#: values ``(F, columns)``, each frame's place ``(F,)`` and what that counts (``line``, ``row``)
Table = tuple[list[str], list[list[str]], np.ndarray, np.ndarray, np.ndarray, str]


def _csv_table(path: Path, raw: bytes) -> Table:
    rows = list(csv.reader(io.StringIO(raw.decode("utf-8-sig"))))
    names = [r[0].strip() if r else "" for r in rows[:4]]
    head = rows[:4] if names[:2] == ["scorer", "individuals"] else rows[:3]
    n_index = next((k for k, v in enumerate(head[-1]) if v.strip() in ("x", "y", "likelihood")), 1)
    cols = [[c.strip() for c in r[n_index:]] for r in head]
    body = [(ln, r) for ln, r in enumerate(rows[len(head):], start=len(head) + 1)
            if r and any(x.strip() for x in r)]
    width = len(cols[-1])
    vals = np.full((len(body), width), np.nan)
    frames = np.zeros(len(body), np.int64)
    lines = np.array([ln for ln, _ in body], np.int64)
    for n, (ln, r) in enumerate(body):
        where = f"{path}: line {ln}"
        frames[n] = _frame_of(where, r[:n_index])
        if len(r) - n_index != width:
            raise InputError(where, f"expected {width} values after the index, got {len(r) - n_index}")
        try:
            vals[n] = [float(x) if x.strip() else np.nan for x in r[n_index:]]
        except ValueError:
            raise InputError(where, "a value is not a number") from None
    return names[:len(head)], cols, frames, vals, lines, "line"


def _h5_table(path: Path, raw: bytes) -> Table:
    """DeepLabCut's ``.h5``: one pandas table (key ``df_with_missing`` or ``keypoints``), read from
    the bytes already read (PyTables' in-memory driver)."""
    try:
        import pandas as pd
        import tables  # noqa: F401  (pandas reads HDF5 tables through it)
    except ImportError:
        raise InputError(str(path), "reading DeepLabCut's .h5 needs pandas and PyTables: "
                                    "pip install 'gt3dkit[dlc]' (or give its .csv)") from None
    try:
        with pd.HDFStore(f"{os.devnull}/{path.name}", mode="r", driver="H5FD_CORE", driver_core_image=raw,
                         driver_core_backing_store=0) as store:
            keys = store.keys()
            if len(keys) != 1:
                raise InputError(str(path), f"{len(keys)} tables ({', '.join(keys)}): a DeepLabCut file "
                                            "holds one")
            df = store[keys[0]]
    except (OSError, ValueError, TypeError) as e:
        raise InputError(str(path), f"not a DeepLabCut .h5 ({str(e).splitlines()[-1][:120]})") from None
    if not isinstance(df, pd.DataFrame) or not isinstance(df.columns, pd.MultiIndex):
        raise InputError(str(path), "not a DeepLabCut .h5 (no table of scorer, bodyparts and coords columns)")
    names = [str(n) for n in df.columns.names]
    cols = [[str(v) for v in df.columns.get_level_values(k)] for k in range(df.columns.nlevels)]
    index = [[str(x) for x in (i if isinstance(i, tuple) else (i,))] for i in df.index]
    frames = np.array([_frame_of(f"{path}: row {n}", ["/".join(i)]) for n, i in enumerate(index)], np.int64)
    try:
        vals = df.to_numpy(dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(str(path), "a value is not a number") from None
    return names, cols, frames, vals, np.arange(len(frames), dtype=np.int64), "row"


def _frame_of(where: str, index: list[str]) -> int:
    """The frame of a row: its integer index, or the number in an image file name
    (``labeled-data/video/img0042.png``)."""
    text = index[-1].strip() if index else ""
    if re.fullmatch(r"[+-]?\d+(\.0*)?", text):  # an index (pandas may write 3.0)
        if text.startswith("-"):
            raise InputError(where, f"negative frame index {text!r}")
        return int(float(text))
    m = re.findall(r"(\d+)", Path(text).stem)
    if not m:
        raise InputError(where, f"no frame number in {text!r}")
    return int(m[-1])


def load(root: Path, skeleton: str | None = None, calib: Path | str | None = None,
         fps: float | None = None) -> Scene:
    root = Path(root)
    rig, fps_doc, cal = calibration_beside(root, calib)
    files = camera_files(root, rig)
    if not files:
        raise InputError(str(root), "no DeepLabCut file (a CSV whose first cell is 'scorer', or its .h5)")
    return scene_of(root, files, (rig, fps_doc, cal), lambda parts: body_skeleton(parts, skeleton), fps,
                    "dlc")


def scene_of(root: Path, files: dict[str, Path], calibration: tuple[Rig, float | None, Path],
             skeleton_of: Callable[[list[str]], Skeleton], fps: float | None, layout: str) -> Scene:
    """The scene of one DeepLabCut file per camera (``files``: camera name -> file) and the
    calibration (its rig, frame rate and path); ``skeleton_of`` makes the skeleton of the files'
    body parts."""
    rig, fps_doc, cal = calibration
    read = {cam: DlcFile(p) for cam, p in files.items()}
    first_cam = next(iter(read))
    parts = read[first_cam].bodyparts
    for cam, f in read.items():
        if f.bodyparts != parts:
            raise InputError(str(files[cam]), f"its body parts differ from {files[first_cam].name}'s")
    skel = skeleton_of(parts)
    rb = RowBuilder(n_joints=len(parts))
    above = dropped = 0
    for cam, f in read.items():
        c = rig.index(cam)
        like = np.where(np.isfinite(f.likelihood), f.likelihood, 1.0)
        labelled = np.isfinite(f.uv).all(axis=-1)
        dropped += int(np.sum(labelled & (like <= 0)))
        above += int(np.sum(labelled & (like > 1)))
        seen = labelled & (like > 0)
        fr, ind, j = np.nonzero(seen)
        if len(fr):
            rb.add_joint_block(JointBlock(f.frames[fr], np.full(len(fr), c, np.int64), ind.astype(np.int64),
                                          j.astype(np.int64), f.uv[fr, ind, j],
                                          np.minimum(like[fr, ind, j], 1.0), f.lines[fr],
                                          str(files[cam]), f.unit))
    obs = rb.build()
    if len(obs) == 0:
        raise InputError(str(root), "no body part found in any DeepLabCut file")
    warnings = []
    if above:
        warnings.append(f"{above} DeepLabCut likelihoods above 1 read as 1")
    if dropped:
        warnings.append(f"{dropped} body parts of likelihood 0 or below left out")
    if not skel.bone_names:
        warnings.append("no bones: DeepLabCut's files name body parts only (give them with --skeleton FILE)")
    rate = fps or fps_doc
    digests = {str(p.relative_to(root)): read[c].digest for c, p in files.items()}
    doc: JsonDict = skel.doc()
    return Scene(rig=rig, obs=obs, layout=layout, fps=float(rate or DEFAULT_FPS), frames=np.unique(obs.frame),
                 skeleton=skel.name, skeleton_doc=doc, root=str(root), warnings=tuple(warnings),
                 files={f"calibration:{cal.name}": "folder" if cal.is_dir() else read_hashed(cal)[1],
                        **digests},
                 fps_assumed="" if rate else f"{cal.name} and DeepLabCut's files give no frame rate",
                 association="detections")


def body_skeleton(parts: list[str], skeleton: str | None, what: str = "DeepLabCut's body parts") -> Skeleton:
    """The body parts as a skeleton: ``--skeleton``'s (its joints those parts, in any order; its
    bones, pairs, groups, up and floor kept), else the parts without bones."""
    if skeleton is None:
        return Skeleton("dlc", tuple(parts), ())
    sk = named_skeleton(skeleton)
    if set(sk.joints) != set(parts):
        raise InputError("--skeleton", f"its joints ({', '.join(sk.joints)}) are not {what} "
                                       f"({', '.join(parts)})")
    if list(sk.joints) != parts:  # reordered as the files hold them (its up, floor and groups kept)
        order = {j: k for k, j in enumerate(sk.joints)}
        sk = dataclasses.replace(sk, joints=tuple(parts), detector_points=0,
                                 labels=tuple(sk.labels[order[p]] for p in parts) if sk.labels else (),
                                 pose=tuple(sk.pose[order[p]] for p in parts) if sk.pose else ())
    return sk

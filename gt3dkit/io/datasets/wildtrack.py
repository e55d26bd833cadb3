"""WILDTRACK and MultiviewX: OpenCV XML calibrations + per-frame JSON boxes.

Layouts
-------
WILDTRACK
    ``calibrations/intrinsic_zero/intr_<CAM>.xml``, ``calibrations/extrinsic/extr_<CAM>.xml``
    (``tvec`` in centimetres), cameras CVLab1-4, IDIAP1-3 = viewNum 0-6, 1920x1080,
    positionID on a 480 x 1440 grid of 2.5 cm cells starting at (-3 m, -9 m), 10 fps
    frame numbers.
MultiviewX
    ``calibrations/intrinsic/`` and ``tvec`` in metres, Camera1-6 = viewNum 0-5,
    positionID on a 1000 x 640 grid of 2.5 cm cells starting at (0, 0), 2 fps.

MultiviewX's box edges were truncated to integers by its generator; the loader
adds half a pixel (away from zero) to undo that bias (see ``MULTIVIEWX``).

Both: ``annotations_positions/<frame>.json`` = list of
``{personID, positionID, views: [{viewNum, xmin, ymin, xmax, ymax}]}``; a box of -1s
means not seen. World z is up, the ground is z = 0. A synthetic scene written by
``gt3d simulate`` adds ``truth.csv`` (full ellipsoids), which then replaces the
positionID truth.
"""

from __future__ import annotations

import csv
import functools
import hashlib
import itertools
import json
import math
from pathlib import Path
from types import GenericAlias
from typing import Any

import numpy as np

from gt3dkit.arrays import unique_rows
from gt3dkit.calib.formats.grid import GridLayout, load_camera, write as write_grid
from gt3dkit.errors import InputError
from gt3dkit.io.datasets.checks import FAR_IMAGES, check_pixels
from gt3dkit.io.datasets.common import BoxBlock, RowBuilder
from gt3dkit.parse import (
    FRAME_MAX,
    ID_MAX,
    CsvBlock,
    HashedFile,
    iter_csv_blocks,
    iter_csv_rows,
    json_of,
    parse_frame,
    parse_int,
    parse_metres,
    read_hashed,
    sha256,
)
from gt3dkit.types import (
    F64,
    MAX_WORLD_M,
    Camera,
    FrameIndex,
    GroundTruth,
    Origins,
    ReadAhead,
    Rig,
    Scene,
    SimScene,
)

#: Frame files read, decoded and checked together (:func:`_checked_views`): the numpy checks'
#: cost is per call, and a block's Python objects are all a long folder holds at once.
FILES_PER_BLOCK = 256


def load(root: Path, g: GridLayout, span: tuple[int, int] | None = None, ahead: ReadAhead | None = None
         ) -> Scene:
    """Load a WILDTRACK- or MultiviewX-layout folder into a :class:`Scene`; ``span``: only the
    frame files of the frame numbers ``lo..hi`` (a window's, :mod:`gt3dkit.windows`: the truth
    is the positionID grid's of those frames, or None where ``truth.csv`` gives it); ``ahead``:
    the cameras and frame files :func:`index` read (not read again)."""
    root = Path(root)
    files: dict[str, str] = {}
    if ahead is not None:
        cams, frame_bytes = list(ahead.cameras), ahead.frame_bytes
        files.update(ahead.files)
    else:
        cams, frame_bytes = [load_camera(root, g, n, files) for n in g.cameras], {}
    paths, frame_of = _frame_files(root)
    if span is not None:
        inside = (frame_of >= span[0]) & (frame_of <= span[1])
        paths, frame_of = [p for p, m in zip(paths, inside, strict=True) if m], frame_of[inside]
    _, first, counts = np.unique(frame_of, return_index=True, return_counts=True)
    shared = np.zeros(len(paths), bool)  # a frame number two files give ("7.json", "007.json")
    shared[np.isin(frame_of, frame_of[first[counts > 1]])] = True
    rb = RowBuilder()
    truth_rows: list[np.ndarray] = []  # (k, 3) frame, personID, positionID, in reading order
    seen_ids: dict[int, dict[int, int]] = {}  # frame -> personID -> entry (the shared frames')
    for at in range(0, len(paths), FILES_PER_BLOCK):
        block = list(range(at, min(at + FILES_PER_BLOCK, len(paths))))
        raws = []
        for i in block:
            kept = frame_bytes.get(str(paths[i]))
            raw, files[str(paths[i].relative_to(root))] = (
                read_hashed(paths[i]) if kept is None else (kept, hashlib.sha256(kept).hexdigest()))
            raws.append(raw)
        bad, persons, views = _checked_views(raws, cams, g)
        bad |= shared[block]
        good = np.flatnonzero(~bad)
        truth = [np.c_[persons[:, 0], frame_of[block][persons[:, 0]], persons[:, 1:]][
            ~bad[persons[:, 0]] & (persons[:, 2] >= 0)]]
        v = views[~bad[views[:, 0].astype(np.int64)]]
        if len(good):
            k = v[:, 0].astype(np.int64)
            tid, vn = v[:, 1].astype(np.int64), v[:, 2].astype(np.int64)
            rank = np.full(len(block), -1)
            rank[good] = np.arange(len(good))
            where = Origins(tuple(f"{Origins.literal(str(paths[block[j]]))}: personID {{0}}, viewNum {{1}}"
                                  for j in good), rank[k], np.stack([tid, vn], 1))
            rb.add_box_block(BoxBlock(frame_of[block][k], vn, tid, v[:, 3:], where))
        for j in np.flatnonzero(bad):  # entry by entry, with the exact error for the first bad one
            p, frame = paths[block[j]], int(frame_of[block[j]])
            rows = _entries(p, frame, raws[j], cams, g, rb, seen_ids.setdefault(frame, {}))
            truth.append(np.c_[np.full(len(rows), j), rows])
        t = np.concatenate(truth)
        truth_rows.append(t[np.argsort(t[:, 0], kind="stable"), 1:])
    rig, remap = _rig(root, cams, g)
    obs = rb.build()
    obs = type(obs)(obs.frame, remap[obs.cam], obs.track_id, obs.box_xyxy_px, obs.kpt_uv_px,
                    obs.origin)
    frames = np.unique(frame_of)
    gt: GroundTruth | None = None  # with a span: read once for the sequence (gt3dkit.windows)
    if span is None or not (root / "truth.csv").exists():
        gt = truth_csv(root, files) or _truth_positions(g, truth_rows)
    return Scene(rig=rig, obs=obs, layout=g.name, fps=g.fps, frames=frames, truth=gt,
                 files=files, root=str(root))


def _rig(root: Path, cams: list[Camera | None], g: GridLayout) -> tuple[Rig, np.ndarray]:
    """The rig of the layout's cameras that have a calibration, and ``(C,)`` each layout camera's
    index in it (-1: none)."""
    present = [i for i, c in enumerate(cams) if c is not None]
    if not present:
        raise InputError(str(root / "calibrations"), "no camera calibrations found")
    remap = np.full(len(cams), -1)
    remap[present] = np.arange(len(present))
    return Rig(tuple(c for c in cams if c is not None), up=np.array([0.0, 0.0, 1.0]),
               frame_name=f"{g.name} world (x, y on the ground, z up)"), remap


def _frame_files(root: Path) -> tuple[list[Path], np.ndarray]:
    """The folder's frame files, sorted, and ``(n,)`` the frame number each file name gives."""
    ann_dir = root / "annotations_positions"
    paths = sorted(ann_dir.glob("*.json"), key=lambda p: p.name)  # one folder: as paths sort, 4x faster
    if not paths:
        raise InputError(str(ann_dir), "no annotation files (*.json)")
    for p in paths:
        if not p.stem.isdigit():
            raise InputError(str(p), "file name is not a frame number")
    return paths, np.array([parse_frame(str(p), p.stem) for p in paths], dtype=np.int64)


#: The frame files' bytes :func:`index` keeps for a whole reading (:class:`ReadAhead`), at most:
#: a sequence that runs whole holds at most ~15 000 object-frames of boxes
#: (:data:`gt3dkit.windows.plan.MEMORY_BUDGET_BYTES` over 13 kB each), ~11 MB of these files at
#: WILDTRACK's ~700 bytes an object with its 7 views; past this the run goes in windows, each
#: reading its own frames, and the bytes are dropped as the index reads on.
READ_AHEAD_BYTES = 32 << 20


def index(root: Path, g: GridLayout, keep_bytes: int = READ_AHEAD_BYTES) -> Scene:
    """The folder without its boxes (:class:`gt3dkit.types.FrameIndex`): its cameras, frames and
    each frame's objects, counted by their ``"personID"`` keys (a valid file's count; each
    window checks its frames as :func:`load` does when it reads them). The frame files are read
    as bytes, not decoded: 0.2 s for 4 000 files of 40 people, where :func:`load` takes 2.3 s.
    Their bytes and the cameras are kept (``FrameIndex.ahead``) while they come to at most
    ``keep_bytes`` (:data:`READ_AHEAD_BYTES`), for :func:`load` to read the folder whole without
    opening them again."""
    root = Path(root)
    files: dict[str, str] = {}
    cams = [load_camera(root, g, n, files) for n in g.cameras]
    paths, frame_of = _frame_files(root)
    rig, _ = _rig(root, cams, g)
    kept: dict[str, bytes] | None = {}
    total, count = 0, np.zeros(len(paths), np.int64)
    for i, p in enumerate(paths):
        raw = p.read_bytes()
        count[i] = raw.count(b'"personID"')
        total += len(raw)
        if kept is not None and total <= keep_bytes:
            kept[str(p)] = raw
        else:
            kept = None
    frames, inv = np.unique(frame_of, return_inverse=True)
    objects = np.bincount(inv.ravel(), weights=count, minlength=len(frames)).astype(np.int64)
    ahead = None if kept is None else ReadAhead(kept, tuple(cams), dict(files))
    return Scene(rig=rig, obs=RowBuilder().build(), layout=g.name, fps=g.fps, frames=frames, files=files,
                 root=str(root), index=FrameIndex(frames[objects > 0], objects[objects > 0], ahead=ahead))


def _entries(p: Path, frame: int, raw: bytes, cams: list[Camera | None], g: GridLayout, rb: RowBuilder,
             seen: dict[int, int]) -> np.ndarray:
    """One frame file read entry by entry, its boxes added to ``rb`` one by one, with the exact
    error for its first bad entry; ``seen``: the frame's persons so far (personID -> entry).
    Returns its truth rows ``(k, 3)`` frame, personID, positionID."""
    people = json_of(p, raw)
    if not isinstance(people, list):
        raise InputError(str(p), "expected a list of people")
    truth = []
    for i, person in enumerate(people):
        where = f"{p}: entry {i}"
        if not (isinstance(person, dict) and {"personID", "positionID", "views"} <= person.keys()
                and isinstance(person["views"], list)):
            raise InputError(where, "expected {personID, positionID, views: [...]}")
        pid = parse_int(where, person["personID"], "personID")
        where = f"{p}: personID {pid}"
        pos = parse_int(where, person["positionID"], "positionID", -1, g.n_positions - 1)
        if seen.setdefault(pid, i) != i:
            raise InputError(where, f"second entry for this person (entries {seen[pid]} and {i})")
        if pos >= 0:  # -1: the dataset knows no ground position for this person-frame
            truth.append((frame, pid, pos))
        for v in person["views"]:
            if not (isinstance(v, dict) and {"viewNum", "xmin", "ymin", "xmax", "ymax"} <= v.keys()):
                raise InputError(where, f"malformed view {str(v)[:80]} (expected viewNum, "
                                        "xmin, ymin, xmax, ymax)")
            vn = parse_int(where, v["viewNum"], "viewNum", -1, 10_000)
            try:
                box = [float(v[k]) for k in ("xmin", "ymin", "xmax", "ymax")]
            except (TypeError, ValueError, OverflowError):
                raise InputError(f"{where}, viewNum {vn}", f"box values must be numbers, got "
                                                           f"{str(v)[:80]}") from None
            if all(b == -1 for b in box):
                continue
            w = f"{where}, viewNum {vn}"
            if g.truncated_px:
                box = [b + (0.5 if b >= 0 else -0.5) for b in box]
            if not 0 <= vn < len(g.cameras):
                raise InputError(w, f"unknown camera (viewNum must be 0..{len(g.cameras) - 1})")
            cam = cams[vn]
            if cam is None:
                raise InputError(w, f"no calibration for camera {g.cameras[vn]} "
                                    f"(calibrations/{g.intrinsic_dir}/intr_{g.cameras[vn]}.xml)")
            if all(math.isfinite(b) for b in box):
                check_pixels(w, cam, box, "box")
            rb.add_box(frame, vn, pid, box, w)
    return np.array(truth, dtype=np.int64).reshape(-1, 3)


@functools.cache
def _people_decoder() -> Any:
    """msgspec's JSON decoder of a frame file as ``list[person]``, every type checked as it reads
    (ints for ``personID``, ``positionID``, ``viewNum``; numbers for the box edges). The structs
    are left out of Python's cycle collector (``gc=False``: they hold numbers and a list of
    views, never a cycle): it decoded a 4 000-file folder in half the time (0.72 s to 0.36 s)."""
    import msgspec

    view = msgspec.defstruct("View", [("viewNum", int), ("xmin", float), ("ymin", float),
                                      ("xmax", float), ("ymax", float)], gc=False)
    person = msgspec.defstruct("Person", [("personID", int), ("positionID", int),
                                          ("views", GenericAlias(list, (view,)))], gc=False)
    return msgspec.json.Decoder(GenericAlias(list, (person,)))


def _checked_views(raws: list[bytes], cams: list[Camera | None], g: GridLayout
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A block of frame files' bytes as arrays, every check of the entry-by-entry path
    (:func:`_entries`) made on the whole block's arrays at once: ``bad (n,)`` the files where
    anything is unusual (the caller reads those entry by entry and reports the first bad one
    exactly), ``persons (P, 3)`` = file, personID, positionID and ``views (V, 7)`` = file,
    personID, viewNum, xmin, ymin, xmax, ymax of the boxes to add (``-1`` boxes left out,
    truncated pixels shifted; float64: ids are checked to be within ``ID_MAX``, exact in it).
    The types are checked by msgspec as it decodes (:func:`_people_decoder`; a 4 000-file
    folder's decoding and checks under cProfile: 1.7 s file by file, 1.3 s in blocks, and its
    ``load_scene`` 3.3 s and 2.9 s)."""
    import msgspec

    decoder = _people_decoder()
    bad = np.zeros(len(raws), bool)
    persons: list[tuple[int, int, int]] = []
    ids: list[tuple[int, int, int]] = []
    boxes: list[tuple[float, float, float, float]] = []
    for i, raw in enumerate(raws):
        try:
            people = decoder.decode(raw)
        except msgspec.MsgspecError:
            bad[i] = True
            continue
        persons += [(i, q.personID, q.positionID) for q in people]
        ids += [(i, q.personID, v.viewNum) for q in people for v in q.views]
        boxes += [(v.xmin, v.ymin, v.xmax, v.ymax) for q in people for v in q.views]
    try:
        pp = _flat(persons, 3, np.int64)
        iv = _flat(ids, 3, np.int64)
    except OverflowError:  # an id beyond int64 (msgspec reads up to 2**64 - 1): find its file
        return np.ones(len(raws), bool), np.zeros((0, 3), np.int64), np.zeros((0, 7))
    box = _flat(boxes, 4, np.float64)
    bad[pp[(np.abs(pp[:, 1]) > ID_MAX) | (pp[:, 2] < -1) | (pp[:, 2] > g.n_positions - 1), 0]] = True
    bad[_repeated(pp[:, :2])] = True  # a person twice in a file
    bad[_repeated(iv)] = True  # a camera twice for one person
    vn = iv[:, 2]
    bad[iv[(vn < -1) | (vn > 10_000), 0]] = True
    keep = ~np.all(box == -1, axis=1)
    iv, box, vn = iv[keep], box[keep], vn[keep]
    if g.truncated_px:
        box = box + np.where(box >= 0, 0.5, -0.5)
    has = np.array([c is not None for c in cams] + [False])
    known = (vn >= 0) & (vn < len(g.cameras))
    bad[iv[~known | ~has[np.where(known, vn, -1)], 0]] = True
    wh = np.array([[c.width, c.height] if c is not None else [1, 1] for c in cams] + [[1, 1]],
                  dtype=np.float64)
    size = np.tile(wh[np.where(known, vn, -1)], 2)  # (V, 4): w, h, w, h
    odd = (~np.isfinite(box).all(axis=1) | (box[:, 2] <= box[:, 0]) | (box[:, 3] <= box[:, 1])
           | ((box < -FAR_IMAGES * size) | (box > (1 + FAR_IMAGES) * size)).any(axis=1))
    bad[iv[odd, 0]] = True
    return bad, pp, np.concatenate([iv.astype(np.float64), box], axis=1)


def _flat(rows: list[tuple[Any, ...]], width: int, dtype: type) -> np.ndarray:
    """``rows`` (tuples of ``width`` numbers) as an ``(n, width)`` array: through one flat iterator,
    3.5x faster than ``np.array`` of the tuples (0.68 s to 0.19 s for a 4 000-file folder's
    730 000 boxes and their ids). OverflowError for an int beyond ``dtype``, as ``np.array``."""
    return np.fromiter(itertools.chain.from_iterable(rows), dtype, width * len(rows)).reshape(-1, width)


def _repeated(keys: np.ndarray) -> np.ndarray:
    """The first column (a file) of every row of ``keys (N, k)`` int64 that an earlier row repeats."""
    if len(keys) < 2:
        return np.zeros(0, np.int64)
    s = keys[np.lexsort(keys.T[::-1])]
    return s[1:][np.all(s[1:] == s[:-1], axis=1), 0]


def _truth_positions(g: GridLayout, rows: list[np.ndarray]) -> GroundTruth:
    """The grid positions ``rows`` (blocks of ``(k, 3)`` frame, personID, positionID) as truth."""
    arr = np.concatenate([np.zeros((0, 3), np.int64), *rows]).astype(np.int64)
    xy = g.position_to_xy(arr[:, 2])
    center = np.concatenate([xy, np.full((len(arr), 1), np.nan)], axis=1)
    return GroundTruth(frame=arr[:, 0], track_id=arr[:, 1], center_world=center,
                       semi_axes=np.full((len(arr), 3), np.nan),
                       kpt_world=np.zeros((len(arr), 0, 3)), source=f"{g.name} positionID grid")


TRUTH_COLUMNS = ("frame", "id", "x", "y", "z", "a", "b", "c")


def truth_csv(root: Path, files: dict[str, str]) -> GroundTruth | None:
    """``root/truth.csv`` (:func:`read_truth_csv`), its digest added to ``files``; None without one."""
    p = root / "truth.csv"
    if not p.exists():
        return None
    return read_truth_csv(p, files, root)


def read_truth_csv(p: Path, files: dict[str, str], root: Path) -> GroundTruth:
    """``truth.csv`` = ``frame,id,x,y,z,a,b,c`` (metres), as written by ``gt3d simulate``: read in
    numpy-checked blocks (:func:`_checked_truth`), row by row where a block fails a check (to
    say where)."""
    with HashedFile(p) as hashed:  # opened once where every block passes: hashed as it is read
        read = iter_csv_blocks(p, TRUTH_COLUMNS, None, 65536, "iiffffff", hashed)
        blocks = [_checked_truth(block) for block in read]
        digest = hashed.hexdigest()
    a = np.concatenate([np.zeros((0, 8))] + [b for b in blocks if b is not None])
    if all(b is not None for b in blocks) and len(unique_rows(a[:, :2].astype(np.int64))) == len(a):
        files[str(p.relative_to(root))] = digest
        return _truth_of(a)
    rows = []
    keys: set[tuple[int, int]] = set()
    for line, r in iter_csv_rows(p, TRUTH_COLUMNS):
        where = f"{p}: line {line}"
        key = (parse_frame(where, r["frame"]), parse_int(where, r["id"], "id"))
        if key in keys:
            raise InputError(where, f"second row for object {key[1]} in frame {key[0]}")
        keys.add(key)
        vals = [parse_metres(where, r[k], k) for k in TRUTH_COLUMNS[2:]]
        if min(vals[3:]) <= 0:
            raise InputError(where, f"semi-axes must be positive, got {vals[3:]}")
        rows.append((*key, *vals))
    files[str(p.relative_to(root))] = sha256(p)
    return _truth_of(np.array(rows, dtype=np.float64).reshape(-1, 8))


def _checked_truth(block: CsvBlock) -> F64 | None:
    """``(P, 8)`` a block of ``truth.csv`` rows parsed and checked as :func:`read_truth_csv`
    checks each row (but for a row given twice), or None when any fails."""
    try:
        key = np.stack([block.ints(k) for k in (0, 1)], 1)
        val = np.stack([block.floats(k) for k in range(2, 8)], 1)
    except (ValueError, OverflowError):
        return None
    ok = ((key[:, 0] >= 0) & (key[:, 0] <= FRAME_MAX) & (np.abs(key[:, 1]) <= ID_MAX)
          & np.all(np.isfinite(val) & (np.abs(val) <= MAX_WORLD_M), axis=1) & np.all(val[:, 3:] > 0, axis=1))
    return np.concatenate([key, val], 1) if ok.all() else None


def _truth_of(a: F64) -> GroundTruth:
    """``(M, 8)`` frame, id, centre, semi-axes as the simulator's truth."""
    return GroundTruth(frame=a[:, 0].astype(np.int64), track_id=a[:, 1].astype(np.int64),
                       center_world=a[:, 2:5], semi_axes=a[:, 5:8],
                       kpt_world=np.zeros((len(a), 0, 3)), source="truth.csv")


def write_truth_csv(sim: SimScene, path: Path) -> None:
    """``truth.csv`` (:data:`TRUTH_COLUMNS`) of a simulated scene, read by :func:`read_truth_csv`."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(TRUTH_COLUMNS)
        for i in range(len(sim.truth_frame)):
            w.writerow([int(sim.truth_frame[i]), int(sim.truth_id[i]),
                        *(f"{v:.6f}" for v in sim.center_world[i]),
                        *(f"{v:.6f}" for v in sim.semi_axes[i])])


def write(sim: SimScene, tmp: Path, g: GridLayout) -> None:
    """A simulated scene as a WILDTRACK/MultiviewX folder ``tmp`` (``calibrations/`` and
    ``annotations_positions/``), read by :func:`load`."""
    write_grid(sim.rig, tmp, g)
    ann = tmp / "annotations_positions"
    ann.mkdir()
    width = 8 if g.name == "wildtrack" else 5
    pos = g.xy_to_position(sim.center_world[:, :2])
    for f in sim.frames:
        people = []
        for i in np.flatnonzero(sim.truth_frame == f):
            views = []
            for c in range(len(sim.rig.cameras)):
                b = sim.boxes[i, c]
                vals = [-1, -1, -1, -1] if not np.all(np.isfinite(b)) else [int(v) for v in b]
                views.append(dict(zip(("viewNum", "xmin", "ymin", "xmax", "ymax"), [c, *vals], strict=True)))
            people.append({"personID": int(sim.truth_id[i]), "positionID": int(pos[i]),
                           "views": views})
        (ann / f"{int(f):0{width}d}.json").write_text(json.dumps(people, indent=1))

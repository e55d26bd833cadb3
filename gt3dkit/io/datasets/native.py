"""The native layout: ``cameras.json`` + ``boxes.csv`` (and ``truth.csv`` if present).

``cameras.json``::

    {"up": [0, 0, 1], "fps": 10,
     "cameras": [{"name", "width", "height", "K": 3x3, "dist": [k1, k2, p1, p2, k3],
                  "R": 3x3, "t": [3]}]}

``R``, ``t`` are ``cam_from_world``, ``t`` in metres. ``fps`` is optional: without it 10 is
assumed and the run says so (a warning and the summary line).

``boxes.csv``: header ``frame,camera,id,xmin,ymin,xmax,ymax``; pixels of the distorted image.

``keypoints.csv``: header ``frame,camera,id,joint,u,v`` and optionally ``conf`` (a detector's
confidence in [0, 1], in every row or none; a heatmap peak up to 2 is read as 1 with a
warning); pixels of the distorted image; a missing row means not seen, and so does a
confidence of 0 (OpenPose writes undetected joints as ``0,0,0``). A confidence scales the
point's variance by a factor learnt from the data (:mod:`gt3dkit.fusion.preparation.confidence`).
Its joint order is ``--skeleton`` (or ``"skeleton"`` in ``cameras.json``), else the smallest known skeleton
holding the largest joint index.
Boxes and keypoints of the same (frame, camera, id) update the same object.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gt3dkit.arrays import unique_rows
from gt3dkit.calib.formats.native import FPS_RANGE, cameras_doc, load_cameras  # noqa: F401
from gt3dkit.errors import InputError
from gt3dkit.io.datasets.checks import FAR_IMAGES, check_pixels
from gt3dkit.io.datasets.common import BoxBlock, JointBlock, RowBuilder
from gt3dkit.io.datasets.wildtrack import read_truth_csv
from gt3dkit.io.skeletonfile import named_skeleton, write_skeleton
from gt3dkit.parse import (
    FRAME_MAX,
    ID_MAX,
    CsvBlock,
    HashedFile,
    iter_csv_blocks,
    iter_csv_rows,
    parse_frame,
    parse_int,
    parse_metres,
    read_hashed,
    sha256,
)
from gt3dkit.skeletons import SKELETONS, skeleton_for, skeleton_from_doc
from gt3dkit.types import F64, MAX_WORLD_M, GroundTruth, Origins, Rig, Scene, SimScene, SkeletonScene

BOX_COLUMNS = ("frame", "camera", "id", "xmin", "ymin", "xmax", "ymax")
KPT_COLUMNS = ("frame", "camera", "id", "joint", "u", "v")
DEFAULT_FPS = 10.0
#: The largest confidence read (as 1): detectors' heatmap peaks pass 1 (OpenPose up to ~1.04);
#: beyond this it is no confidence.
MAX_CONFIDENCE = 2.0
#: keypoints.csv rows parsed and checked at once (:func:`_checked_keypoints`)
KEYPOINT_BLOCK_ROWS = 65536

#: the skeleton file a simulated native folder of a described skeleton holds (cameras.json names it)
SKELETON_FILE = "skeleton.toml"

def camera_index(rig: Rig, name: str, where: str) -> int:
    try:
        return rig.index(name)
    except KeyError:
        raise InputError(where, f"unknown camera {name!r} (cameras.json has {rig.names})") from None


def load(root: Path, skeleton: str | None = None) -> Scene:
    """Read a native folder (the module doc); ``keypoints.csv`` opened once (its passes read
    through one open file, hashed as it is read)."""
    with contextlib.ExitStack() as stack:
        return _load(Path(root), skeleton, stack)


def _load(root: Path, skeleton: str | None, stack: contextlib.ExitStack) -> Scene:
    files: dict[str, str] = {}
    cam_path = root / "cameras.json"
    raw, digest = read_hashed(cam_path)  # read once: hashed, then parsed
    rig, fps_doc, skel_doc = load_cameras(cam_path, raw)
    files["cameras.json"] = digest
    warnings: list[str] = []
    fps = fps_doc if fps_doc is not None else DEFAULT_FPS
    kpt_path = root / "keypoints.csv"
    has_kpts = False
    skel_name = skeleton or skel_doc
    described = None  # a skeleton file's (--skeleton FILE, or the file cameras.json names beside it)
    if skel_name is not None and skel_name not in SKELETONS:
        beside = root / skel_name if skeleton is None else None
        described = named_skeleton(str(beside) if beside is not None and beside.is_file() else skel_name)
        skel_name = described.name
    kpt_cols: tuple[str, ...] = KPT_COLUMNS
    kpts: HashedFile | None = None
    if kpt_path.exists():
        kpts = stack.enter_context(HashedFile(kpt_path))
        files["keypoints.csv"] = ""  # its digest once read
        kpt_cols, has_kpts, skel_name = _keypoints_kind(kpt_path, kpts, skel_name)
    if skeleton is not None and not has_kpts:
        raise InputError("--skeleton", f"{root} has no keypoints (keypoints.csv missing or empty)")
    n_joints = (described or SKELETONS[skel_name]).n_joints if skel_name and has_kpts else 0
    rb = RowBuilder(n_joints=n_joints)
    box_path = root / "boxes.csv"
    if box_path.exists():
        unseen = 0
        with HashedFile(box_path) as hashed:  # opened once: read and hashed as it is read
            files["boxes.csv"] = ""
            for block in iter_csv_blocks(box_path, BOX_COLUMNS, warnings, KEYPOINT_BLOCK_ROWS, "isiffff",
                                         hashed):
                checked = _checked_boxes(box_path, rig, block)  # streamed
                if checked is not None and rb.add_box_block(checked[0]):
                    unseen += checked[1]
                    continue
                for line, row in zip(block.lines.tolist(), block.rows(), strict=True):  # say where it failed
                    r = dict(zip(BOX_COLUMNS, (x.strip() for x in row), strict=False))
                    unseen += _add_box(rb, rig, f"{box_path}: line {line}", r)
            files["boxes.csv"] = hashed.hexdigest()
        if unseen:
            warnings.append(f"{box_path}: {unseen} boxes of -1s read as not seen")
    undetected = 0
    above: list[float] = []
    blocks = (iter_csv_blocks(kpt_path, kpt_cols, warnings, KEYPOINT_BLOCK_ROWS, "isiifff", kpts) if has_kpts
              else ())
    for block in blocks:  # streamed
        joints = _checked_keypoints(kpt_path, rig, n_joints, block, "conf" in kpt_cols, above)
        if joints is not None:
            rb.add_joint_block(joints[0])
            undetected += joints[1]
            continue
        for line, row in zip(block.lines.tolist(), block.rows(), strict=True):  # say where it failed
            r = dict(zip(kpt_cols, (x.strip() for x in row), strict=False))
            undetected += _add_keypoint(rb, rig, f"{kpt_path}: line {line}", r, above)
    if kpts is not None:
        files["keypoints.csv"] = kpts.hexdigest()
    if above:
        warnings.append(f"{kpt_path}: {len(above)} keypoint(s) with a confidence above 1 (up to "
                        f"{max(above):.4g}; a detector's heatmap peak): read as 1")
    if undetected:
        warnings.append(f"{kpt_path}: {undetected} keypoints with confidence 0 read as not "
                        "detected")
    obs = rb.build()
    if len(obs) == 0:
        raise InputError(str(root), "no annotations (boxes.csv and keypoints.csv missing or empty)")
    truth = read_truth_csv(root / "truth.csv", files, root) if (root / "truth.csv").exists() else None
    if (root / "truth_keypoints.csv").exists():
        got, files["truth_keypoints.csv"] = read_kpt_truth_hashed(root / "truth_keypoints.csv", n_joints)
        truth = _merge_kpt_truth(truth, got)
    frames = np.unique(obs.frame)
    return Scene(rig=rig, obs=obs, layout="native", fps=fps, frames=frames, truth=truth,
                 skeleton=skel_name if n_joints else None,
                 skeleton_doc=described.doc() if described is not None and n_joints else None,
                 files=files, root=str(root),
                 warnings=tuple(warnings),
                 fps_assumed=f"{cam_path} has no \"fps\"" if fps_doc is None else "")


def _add_box(rb: RowBuilder, rig: Rig, where: str, r: dict[str, str]) -> int:
    """One row of ``boxes.csv``, checked and added; 1 if it is a box of -1s (not seen: skipped),
    else 0."""
    frame, tid = parse_frame(where, r["frame"]), parse_int(where, r["id"], "id")
    box = [_number(where, r[k], k) for k in ("xmin", "ymin", "xmax", "ymax")]
    cam = camera_index(rig, r["camera"], where)
    if all(b == -1 for b in box):  # the WILDTRACK convention for "not seen"
        return 1
    if all(math.isfinite(b) for b in box):
        check_pixels(where, rig.cameras[cam], box, "box")
    rb.add_box(frame, cam, tid, box, where)
    return 0


def _camera_column(rig: Rig, names: Sequence[str] | np.ndarray) -> np.ndarray:
    """``(P,)`` the camera index of each name (stripped), -1 for an unknown one."""
    known = {n: k for k, n in enumerate(rig.names)}
    index = {n: known.get(n.strip(), -1) for n in set(names)}
    return np.fromiter(map(index.__getitem__, names), np.int64, len(names))


def _checked_boxes(path: Path, rig: Rig, block: CsvBlock) -> tuple[BoxBlock, int] | None:
    """A block of ``boxes.csv`` rows parsed and checked at once, as :func:`_add_box` checks each
    row, and the count of boxes of -1s (not seen) it drops; None when any row fails a check (the
    caller then goes row by row to say which and why)."""
    try:
        frame, tid = (block.ints(k) for k in (0, 2))
        box = np.stack([block.floats(k) for k in range(3, 7)], 1)
    except (ValueError, OverflowError):
        return None
    cam = _camera_column(rig, block.texts(1))
    unseen = np.all(box == -1, axis=1)
    wh = np.array([[c.width, c.height] for c in rig.cameras], dtype=np.float64)
    size = np.tile(wh[np.maximum(cam, 0)], 2)
    ok = ((frame >= 0) & (frame <= FRAME_MAX) & (np.abs(tid) <= ID_MAX) & (cam >= 0)
          & (unseen | (np.all(np.isfinite(box), axis=1) & (box[:, 2] > box[:, 0]) & (box[:, 3] > box[:, 1])
                       & np.all((box >= -FAR_IMAGES * size) & (box <= (1 + FAR_IMAGES) * size), axis=1))))
    if not ok.all():
        return None
    k = ~unseen
    where = Origins.formatted(Origins.literal(str(path)) + ": line {0}", block.lines[k])
    return BoxBlock(frame[k], cam[k], tid[k], box[k], where), int(unseen.sum())


def _add_keypoint(rb: RowBuilder, rig: Rig, where: str, r: dict[str, str], above: list[float]) -> int:
    """One row of ``keypoints.csv``, checked and added; 1 if it is an undetected point
    (confidence 0: skipped), else 0. A confidence above 1 (a detector's heatmap peak, as
    OpenPose writes up to ~1.04) is read as 1 and listed in ``above``."""
    frame, tid = parse_frame(where, r["frame"]), parse_int(where, r["id"], "id")
    joint = parse_int(where, r["joint"], "joint", 0, 10_000)
    uv = (_number(where, r["u"], "u"), _number(where, r["v"], "v"))
    conf = _number(where, r["conf"], "conf") if "conf" in r else None
    if conf is not None and not (0 <= conf <= MAX_CONFIDENCE):  # NaN fails too
        raise InputError(where, f"confidence must be in [0, 1] (a detector's peak up to "
                                f"{MAX_CONFIDENCE:g}), got {r['conf']}")
    if conf is not None and conf > 1:
        above.append(conf)
        conf = 1.0
    cam = camera_index(rig, r["camera"], where)
    if conf == 0:
        return 1
    if all(math.isfinite(v) for v in uv):
        check_pixels(where, rig.cameras[cam], list(uv), "keypoint")
    rb.add_joint(frame, cam, tid, joint, uv, where, conf)
    return 0


def _checked_keypoints(path: Path, rig: Rig, n_joints: int, block: CsvBlock, with_conf: bool,
                       above: list[float]) -> tuple[JointBlock, int] | None:
    """A block of ``keypoints.csv`` rows parsed and checked at once, as :func:`_add_keypoint` checks
    each row, and the count of undetected points (confidence 0) it drops; None when any row fails
    a check (the caller then goes row by row to say which and why). A 4-million-point file reads in
    seconds and is held as arrays."""
    try:
        ints = [block.ints(k) for k in (0, 2, 3)]  # frame, id, joint
        uv = np.stack([block.floats(4), block.floats(5)], 1)
        conf = block.floats(6) if with_conf else None
    except (ValueError, OverflowError):
        return None
    frame, tid, joint = ints
    cam = _camera_column(rig, block.texts(1))
    size = np.array([[c.width, c.height] for c in rig.cameras], dtype=np.float64)[np.maximum(cam, 0)]
    ok = ((frame >= 0) & (frame <= FRAME_MAX) & (np.abs(tid) <= ID_MAX) & (joint >= 0) & (joint < n_joints)
          & (cam >= 0) & np.all(np.isfinite(uv), axis=1)
          & np.all((uv >= -FAR_IMAGES * size) & (uv <= (1 + FAR_IMAGES) * size), axis=1))
    undetected = 0
    if conf is not None:
        ok &= (conf >= 0) & (conf <= MAX_CONFIDENCE)
        seen = conf > 0
        undetected = int(np.sum(~seen & ok))
    if not ok.all():
        return None
    if conf is not None and (conf > 1).any():  # as _add_keypoint: read as 1, listed
        above.extend(conf[conf > 1].tolist())
        conf = np.minimum(conf, 1.0)
    keep = seen if conf is not None else slice(None)
    line = block.lines[keep]
    out = JointBlock(frame[keep], cam[keep], tid[keep], joint[keep], uv[keep],
                     None if conf is None else conf[keep], line, str(path))
    return out, undetected


def _number(where: str, text: str, name: str) -> float:
    """A number field; NaN and inf are kept for the checks that name them (box, keypoint)."""
    try:
        return float(text)
    except ValueError:
        raise InputError(where, f"malformed value: {name} must be a number, got {text!r}") from None


def _keypoints_kind(path: Path, kpts: HashedFile, skel_name: str | None
                    ) -> tuple[tuple[str, ...], bool, str | None]:
    """``keypoints.csv``'s columns (a ``conf`` column or not), whether it has a row, and its
    skeleton: ``skel_name`` where given, else the smallest known with its largest joint index (a
    first streamed pass through ``kpts``)."""
    cols = (*KPT_COLUMNS, "conf") if _header(kpts)[len(KPT_COLUMNS):len(KPT_COLUMNS) + 1] == ["conf"] \
        else KPT_COLUMNS
    top, has_kpts = -1, False
    with contextlib.closing(iter_csv_rows(path, cols, [], shared=kpts)) as rows:  # closed where it stops
        for line, r in rows:
            has_kpts = True
            if skel_name is not None:
                break
            top = max(top, parse_int(f"{path}: line {line}", r["joint"], "joint", 0, 10_000))
    if skel_name is None and has_kpts:
        try:
            skel_name = skeleton_for(top + 1).name
        except ValueError as e:
            raise InputError(str(path), f"joint index {top}: {e}") from None
    return cols, has_kpts, skel_name


def _header(f: HashedFile) -> list[str]:
    """The stripped header fields of a CSV (empty if unreadable; the reader reports why)."""
    text = io.TextIOWrapper(f.at(0), newline="", encoding="utf-8-sig")
    try:
        return [h.strip() for h in next(csv.reader(text), [])]
    except (OSError, UnicodeDecodeError, csv.Error):
        return []
    finally:
        text.detach()  # the file stays open for the reading


KPT_TRUTH_COLUMNS = ("frame", "id", "joint", "x", "y", "z")


def read_kpt_truth(path: Path, n_joints: int) -> GroundTruth:
    """``truth_keypoints.csv`` = ``frame,id,joint,x,y,z`` (metres), as ``gt3d simulate`` writes:
    read in numpy-checked blocks (:func:`_checked_kpt_truth`), row by row where a block fails a
    check or a joint is given twice (to say where)."""
    return read_kpt_truth_hashed(path, n_joints)[0]


def read_kpt_truth_hashed(path: Path, n_joints: int) -> tuple[GroundTruth, str]:
    """:func:`read_kpt_truth` and the file's SHA-256, the file opened once where every block
    passes (hashed as it is read)."""
    with HashedFile(path) as hashed:
        blocks = [_checked_kpt_truth(block, n_joints) for block in
                  iter_csv_blocks(path, KPT_TRUTH_COLUMNS, None, KEYPOINT_BLOCK_ROWS, "iiifff", hashed)]
        digest = hashed.hexdigest()
    a = np.concatenate([np.zeros((0, 6))] + [b for b in blocks if b is not None])
    ijk = a[:, :3].astype(np.int64)
    if all(b is not None for b in blocks) and len(unique_rows(ijk)) == len(a):
        keys, row = unique_rows(ijk[:, :2], return_inverse=True)
        kpt = np.full((len(keys), n_joints, 3), np.nan)
        kpt[row, ijk[:, 2]] = a[:, 3:]
        return _kpt_truth_of(keys, kpt), digest
    poses: dict[tuple[int, int], np.ndarray] = {}
    for line, r in iter_csv_rows(path, KPT_TRUTH_COLUMNS):
        where = f"{path}: line {line}"
        key = (parse_frame(where, r["frame"]), parse_int(where, r["id"], "id"))
        j = parse_int(where, r["joint"], "joint", 0, max(n_joints - 1, 0))
        xyz = [parse_metres(where, r[k], k) for k in ("x", "y", "z")]
        if not n_joints:
            raise InputError(where, "keypoint truth, but the input has no keypoints")
        pose = poses.setdefault(key, np.full((n_joints, 3), np.nan))
        if np.isfinite(pose[j]).all():
            raise InputError(where, f"second row for joint {j} of object {key[1]} in frame {key[0]}")
        pose[j] = xyz
    keys = sorted(poses)
    return _kpt_truth_of(np.array(keys, dtype=np.int64).reshape(-1, 2),
                         np.array([poses[q] for q in keys]).reshape(len(keys), n_joints, 3)), sha256(path)


def _checked_kpt_truth(block: CsvBlock, n_joints: int) -> F64 | None:
    """``(P, 6)`` a block of ``truth_keypoints.csv`` rows (frame, id, joint, x, y, z) parsed and
    checked as :func:`read_kpt_truth` checks each row (but for a joint given twice), or None
    when any fails."""
    if not n_joints:
        return None
    try:
        key = np.stack([block.ints(k) for k in (0, 1, 2)], 1)
        xyz = np.stack([block.floats(k) for k in (3, 4, 5)], 1)
    except (ValueError, OverflowError):
        return None
    ok = ((key[:, 0] >= 0) & (key[:, 0] <= FRAME_MAX) & (np.abs(key[:, 1]) <= ID_MAX) & (key[:, 2] >= 0)
          & (key[:, 2] < n_joints) & np.all(np.isfinite(xyz) & (np.abs(xyz) <= MAX_WORLD_M), axis=1))
    return np.concatenate([key, xyz], 1) if ok.all() else None


def _kpt_truth_of(keys: np.ndarray, kpt_world: F64) -> GroundTruth:
    """``keys (n, 2)`` frame and id (sorted), ``kpt_world (n, J, 3)`` as the keypoint truth."""
    n = len(keys)
    return GroundTruth(frame=keys[:, 0], track_id=keys[:, 1], center_world=np.full((n, 3), np.nan),
                       semi_axes=np.full((n, 3), np.nan), kpt_world=kpt_world, source="truth_keypoints.csv")


def _merge_kpt_truth(boxes: GroundTruth | None, kpts: GroundTruth) -> GroundTruth:
    if boxes is None:
        return kpts
    key = {(int(f), int(i)): r for r, (f, i) in enumerate(zip(boxes.frame, boxes.track_id,
                                                              strict=True))}
    kw = np.full((len(boxes.frame), kpts.kpt_world.shape[1], 3), np.nan)
    for r, (f, i) in enumerate(zip(kpts.frame, kpts.track_id, strict=True)):
        if (int(f), int(i)) in key:
            kw[key[(int(f), int(i))]] = kpts.kpt_world[r]
    return GroundTruth(boxes.frame, boxes.track_id, boxes.center_world, boxes.semi_axes, kw,
                       source=boxes.source + " + truth_keypoints.csv")


def write_cameras(rig: Rig, fps: float, tmp: Path) -> None:
    """``cameras.json`` of a simulated rig (with its frame rate)."""
    doc = cameras_doc(rig, fps, frame=rig.frame_name, units="m")
    (tmp / "cameras.json").write_text(json.dumps(doc, indent=1))


def write_boxes(sim: SimScene, tmp: Path, id_seed: int | None = None) -> None:
    """A simulated scene as a native folder ``tmp`` (``cameras.json``, ``boxes.csv``), read by
    :func:`load` (``id_seed``: unused, the ids are global)."""
    write_cameras(sim.rig, sim.fps, tmp)
    with open(tmp / "boxes.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(BOX_COLUMNS)
        for i in range(len(sim.truth_frame)):
            for c, cam in enumerate(sim.rig.cameras):
                b = sim.boxes[i, c]
                if np.all(np.isfinite(b)):
                    w.writerow([int(sim.truth_frame[i]), cam.name, int(sim.truth_id[i]),
                                *(f"{v:g}" for v in b)])


def write_keypoints(sim: SkeletonScene, tmp: Path) -> None:
    """A simulated skeleton scene as a native folder ``tmp`` (``cameras.json``,
    ``keypoints.csv``, ``truth_keypoints.csv``), read by :func:`load`."""
    skeleton = sim.skeleton
    if sim.skeleton_doc is not None:  # a skeleton a file describes: the file beside, named by cameras.json
        write_skeleton(skeleton_from_doc(sim.skeleton_doc, sim.skeleton), tmp / SKELETON_FILE)
        skeleton = SKELETON_FILE
    doc = cameras_doc(sim.rig, sim.fps, skeleton=skeleton, units="m", frame="synthetic y-down world")
    (tmp / "cameras.json").write_text(json.dumps(doc, indent=1))
    with open(tmp / "keypoints.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(list(KPT_COLUMNS)
                   + (["conf"] if sim.conf is not None else []))
        m, c, j = np.nonzero(np.isfinite(sim.uv[..., 0]))
        for a, b, k in zip(m, c, j, strict=True):
            w.writerow([int(sim.truth_frame[a]), sim.rig.cameras[b].name,
                        int(sim.truth_id[a]), int(k), f"{sim.uv[a, b, k, 0]:.4f}",
                        f"{sim.uv[a, b, k, 1]:.4f}"]
                       + ([f"{sim.conf[a, b, k]:.3f}"] if sim.conf is not None else []))
    write_kpt_truth(sim, tmp / "truth_keypoints.csv")


def write_kpt_truth(sim: SkeletonScene, path: Path) -> None:
    """``truth_keypoints.csv`` = ``frame,id,joint,x,y,z`` (metres), every joint of every pose."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(KPT_TRUTH_COLUMNS)
        for a in range(len(sim.truth_frame)):
            for k in range(sim.kpt_world.shape[1]):
                w.writerow([int(sim.truth_frame[a]), int(sim.truth_id[a]), k,
                            *(f"{v:.6f}" for v in sim.kpt_world[a, k])])

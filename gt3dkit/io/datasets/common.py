"""Helpers shared by the dataset loaders: box validation, row building (field parsing is
:mod:`gt3dkit.parse`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from gt3dkit.arrays import unique_rows
from gt3dkit.errors import InputError
from gt3dkit.io.labels import Shapes
from gt3dkit.types import F64, Observations, Origins, SimScene


def check_box(where: str, box: list[float]) -> None:
    """Raise :class:`InputError` for a NaN/inf or degenerate box."""
    if not all(math.isfinite(v) for v in box):
        raise InputError(where, f"box has a non-finite value {box}")
    if box[2] <= box[0] or box[3] <= box[1]:
        raise InputError(where, f"degenerate box (need xmax > xmin and ymax > ymin): {box}")


@dataclass(frozen=True)
class JointBlock:
    """Keypoints read and checked as a block (:meth:`RowBuilder.add_joint_block`, which gathers
    them into rows at once), one per point: ``frame, cam, tid, joint, line (P,)`` int64, ``uv (P,
    2)``, ``conf (P,)`` or None; ``path`` names the file the line numbers are of, ``unit`` what
    they count (a text file's ``line``, a table's ``row``)."""

    frame: np.ndarray
    cam: np.ndarray
    tid: np.ndarray
    joint: np.ndarray
    uv: F64
    conf: F64 | None
    line: np.ndarray
    path: str
    unit: str = "line"


@dataclass(frozen=True)
class JointRows:
    """Keypoints as rows (:func:`gather_rows`, or a detector's detections, one row each):
    ``keys (r, 3)`` frame, camera, id; ``joints (k,)`` the joints the rows hold; ``uv (r, k, 2)``
    (NaN: none), ``conf (r, k)`` or None; ``line (r, k)`` each point's place in reading order
    (-1: none); ``origin`` each row's (its first point's). A point's own origin is
    ``point_template.format(line)`` (a CSV line), or its row's when that is None (a detection's
    points share it). A row's 19 points held as one row, not 19 sets of five integers (a
    10 000-frame, 3-person, 8-camera file peaked at 1.15 GB read as points, 0.1 GB of keypoints
    in the end)."""

    keys: np.ndarray
    joints: np.ndarray
    uv: F64
    conf: F64 | None
    line: np.ndarray
    origin: Origins
    point_template: str | None = None

    def point_origin(self, r: int, c: int) -> str:
        """Where the point of row ``r`` and joint column ``c`` came from."""
        if self.point_template is None:
            return self.origin[r]
        return self.point_template.format(int(self.line[r, c]))


def gather_rows(b: JointBlock) -> JointRows:
    """``b``'s points as rows; :class:`InputError` at the later of two points of one joint of a
    row (the block's points are in reading order)."""
    keys, row = unique_rows(np.stack([b.frame, b.cam, b.tid], 1), return_inverse=True)
    joints, col = np.unique(b.joint, return_inverse=True)
    k = len(joints)
    slot = row * k + col.reshape(-1)
    twice = _later_repeats(slot, np.zeros(len(keys) * k, bool))
    if len(twice):
        q = int(twice[0])
        raise InputError(f"{b.path}: line {b.line[q]}", _repeat(b.joint[q], b.tid[q], b.frame[q]))
    uv = np.full((len(keys), k, 2), np.nan)
    uv.reshape(-1, 2)[slot] = b.uv
    conf = None
    if b.conf is not None:
        conf = np.full((len(keys), k), np.nan)
        conf.reshape(-1)[slot] = b.conf
    line = np.full((len(keys), k), -1, dtype=np.int64)
    line.reshape(-1)[slot] = b.line
    _, first = np.unique(row, return_index=True)  # each row's first point (the points are in line order)
    template = Origins.literal(b.path) + f": {b.unit} {{0}}"
    return JointRows(keys, joints, uv, conf, line, Origins.formatted(template, b.line[first]), template)


def _repeat(joint: int, tid: int, frame: int) -> str:
    return f"second keypoint {joint} for object {tid} in frame {frame} and this camera"


@dataclass(frozen=True)
class BoxBlock:
    """Boxes read and checked as a block (:meth:`RowBuilder.add_box_block`): ``frame, cam, tid (V,)``
    int64, ``box (V, 4)`` (finite, not degenerate), ``origin`` each box's."""

    frame: np.ndarray
    cam: np.ndarray
    tid: np.ndarray
    box: F64
    origin: Origins


@dataclass
class RowBuilder:
    """Accumulates observation rows keyed by (frame, cam, id), merging boxes and joints: one by
    one (:meth:`add_box`, :meth:`add_joint`: checked as they come) or as checked blocks of arrays
    (:meth:`add_box_block`, :meth:`add_joint_block`: no Python object per row; a row given twice
    is found by :meth:`build`)."""

    n_joints: int = 0
    rows: dict[tuple[int, int, int], int] = field(default_factory=dict)
    boxes: list[list[float]] = field(default_factory=list)
    kpts: list[np.ndarray] = field(default_factory=list)
    confs: list[np.ndarray] = field(default_factory=list)
    origin: list[str] = field(default_factory=list)
    has_conf: bool = False
    blocks: list[JointRows] = field(default_factory=list)
    box_blocks: list[BoxBlock] = field(default_factory=list)

    def _row(self, frame: int, cam: int, tid: int, where: str) -> int:
        key = (frame, cam, tid)
        r = self.rows.get(key)
        if r is None:
            r = len(self.boxes)
            self.rows[key] = r
            self.boxes.append([math.nan] * 4)
            if self.n_joints:
                self.kpts.append(np.full((self.n_joints, 2), np.nan))
                self.confs.append(np.full(self.n_joints, np.nan))
            self.origin.append(where)
        return r

    def add_box(self, frame: int, cam: int, tid: int, box: list[float], where: str) -> None:
        check_box(where, box)
        r = self._row(frame, cam, tid, where)
        if not math.isnan(self.boxes[r][0]):
            raise InputError(where, f"second box for object {tid} in frame {frame} and this camera")
        self.boxes[r] = [float(v) for v in box]

    def add_box_block(self, block: BoxBlock) -> bool:
        """Boxes already checked (finite, not degenerate) added at once. Nothing is added and False
        returned when one of them has a row added one by one already (then :meth:`add_box` says
        whether and why that is wrong); two boxes of one (frame, camera, id) in blocks are found by
        :meth:`build`."""
        if self.rows and any(k in self.rows for k in zip(block.frame.tolist(), block.cam.tolist(),
                                                             block.tid.tolist(), strict=True)):
            return False
        self.box_blocks.append(block)
        return True

    def add_joint(self, frame: int, cam: int, tid: int, joint: int, uv: tuple[float, float],
                  where: str, conf: float | None = None) -> None:
        """One keypoint; ``conf`` in (0, 1] (a detector's score) or None (not given)."""
        if not (math.isfinite(uv[0]) and math.isfinite(uv[1])):
            raise InputError(where, f"keypoint has a non-finite pixel {uv}")
        if not 0 <= joint < self.n_joints:
            raise InputError(where, f"joint index {joint} outside the skeleton (0..{self.n_joints - 1})")
        if conf is not None:
            if not (math.isfinite(conf) and 0 < conf <= 1):
                raise InputError(where, f"confidence must be in (0, 1], got {conf}")
            self.has_conf = True
        r = self._row(frame, cam, tid, where)
        if not math.isnan(self.kpts[r][joint][0]):
            raise InputError(where, f"second keypoint {joint} for object {tid} in frame {frame} "
                                    "and this camera")
        self.kpts[r][joint] = uv
        self.confs[r][joint] = 1.0 if conf is None else conf

    def add_joint_block(self, block: JointBlock) -> None:
        """Keypoints already checked one by one as :meth:`add_joint` checks them (finite pixels,
        joints of the skeleton, confidences in (0, 1]), added at once, gathered into rows
        (:func:`gather_rows`: a point given twice in the block is an error here); one given twice
        across blocks (or before, one by one) is found by :meth:`build`."""
        if block.conf is not None:
            self.has_conf = True
        self.blocks.append(gather_rows(block))

    def add_joint_rows(self, rows: JointRows) -> None:
        """Keypoint rows already checked as :meth:`add_joint` checks each point, each (row, joint)
        once among them, added at once; a row's joint given again (here or before) is found by
        :meth:`build`."""
        if rows.conf is not None:
            self.has_conf = True
        self.blocks.append(rows)

    def build(self) -> Observations:
        """The rows, sorted by (frame, camera, id): those added one by one, the box blocks' and the
        keypoint blocks' merged per (frame, camera, id). A box or point given twice is an
        :class:`InputError` at the later one (a block's after the rows added one by one)."""
        J = self.n_joints
        one = np.array(list(self.rows), dtype=np.int64).reshape(-1, 3)
        idx = np.array(list(self.rows.values()), dtype=np.int64)
        bb, jb = self.box_blocks, self.blocks
        bkeys = np.concatenate([np.zeros((0, 3), np.int64)]
                               + [np.stack([b.frame, b.cam, b.tid], 1) for b in bb])
        pkeys = np.concatenate([np.zeros((0, 3), np.int64)] + [p.keys for p in jb])
        keys, inv = unique_rows(np.concatenate([one, bkeys, pkeys]), return_inverse=True)
        row_one, row_box, row_pt = np.split(inv, [len(one), len(one) + len(bkeys)])
        n = len(keys)
        box = np.full((n, 4), np.nan)
        kpt = np.full((n, J, 2), np.nan)
        cf = np.full((n, J), np.nan)
        if len(one):
            box[row_one] = np.array(self.boxes, dtype=np.float64).reshape(-1, 4)[idx]
            if J:
                kpt[row_one] = np.array(self.kpts, dtype=np.float64).reshape(-1, J, 2)[idx]
                cf[row_one] = np.array(self.confs, dtype=np.float64).reshape(-1, J)[idx]
        box_origin = Origins.concat([b.origin for b in bb])
        if len(bkeys):
            twice = _later_repeats(row_box, np.isfinite(box[:, 0]))
            if len(twice):
                b = int(twice[0])
                raise InputError(box_origin[b], f"second box for object {bkeys[b, 2]} in frame "
                                                f"{bkeys[b, 0]} and this camera")
            box[row_box] = np.concatenate([b.box for b in bb])
        rows_of = np.split(row_pt, np.cumsum([len(p.keys) for p in jb])[:-1]) if jb else []
        if jb:
            _merge_joint_rows(jb, rows_of, kpt, cf if self.has_conf else None)
        pt_origin = Origins.concat([p.origin for p in jb])
        # each row's origin: where it was added one by one, else its box's, else its first point's
        # (the blocks are in reading order: a row's first block holds its first point)
        first = np.full(n, -1)
        parts = [Origins.of(self.origin), box_origin, pt_origin]
        offset = np.cumsum([0] + [len(p) for p in parts])
        if len(row_pt):
            for_rows, at = np.unique(row_pt, return_index=True)
            first[for_rows] = offset[2] + at
        first[row_box] = offset[1] + np.arange(len(row_box))
        first[row_one] = idx
        return Observations(frame=keys[:, 0], cam=keys[:, 1], track_id=keys[:, 2], box_xyxy_px=box,
                            kpt_uv_px=kpt, origin=Origins.concat(parts).take(first),
                            kpt_conf=cf if self.has_conf and J else None)


def _merge_joint_rows(parts: list[JointRows], rows_of: list[np.ndarray], kpt: F64, conf: F64 | None) -> None:
    """The blocks' points into ``kpt (n, J, 2)`` (and ``conf (n, J)``) at their rows ``rows_of``
    (one ``(r,)`` per block), after the rows added one by one (the points there already);
    :class:`InputError` at the later of two points of one joint of a row, in reading order."""
    J = kpt.shape[1]
    count = np.isfinite(kpt[..., 0]).reshape(-1).astype(np.int32)  # points per (row, joint) slot
    slots = []
    for p, rows in zip(parts, rows_of, strict=True):
        on = p.line >= 0
        s = (rows[:, None] * J + p.joints[None, :])[on]
        count[s] += 1  # a block holds each slot once (gather_rows)
        slots.append(s)
    if (count > 1).any():
        _raise_repeat(parts, slots, count > 1, np.isfinite(kpt[..., 0]).reshape(-1))
    for p, s in zip(parts, slots, strict=True):
        on = p.line >= 0
        kpt.reshape(-1, 2)[s] = p.uv[on]
        if conf is not None:
            conf.reshape(-1)[s] = p.conf[on] if p.conf is not None else 1.0


def _raise_repeat(parts: list[JointRows], slots: list[np.ndarray], shared: np.ndarray, taken: np.ndarray
                  ) -> None:
    """The :class:`InputError` of the first point (blocks in reading order, lines within a block)
    whose (row, joint) slot an earlier point holds; ``shared`` the slots held twice, ``taken``
    those held by rows added one by one."""
    src, line, slot, where = [], [], [], []
    for k, (p, s) in enumerate(zip(parts, slots, strict=True)):
        r, c = np.nonzero(p.line >= 0)
        hit = shared[s]
        src.append(np.full(int(hit.sum()), k))
        line.append(p.line[r[hit], c[hit]])
        slot.append(s[hit])
        where.append(np.stack([r[hit], c[hit]], 1))
    src_a, line_a, slot_a, rc = (np.concatenate(a) for a in (src, line, slot, where))
    order = np.lexsort((line_a, src_a))
    q = int(order[_later_repeats(slot_a[order], taken)[0]])
    p, (r, c) = parts[int(src_a[q])], rc[q]
    raise InputError(p.point_origin(r, c), _repeat(int(p.joints[c]), int(p.keys[r, 2]), int(p.keys[r, 0])))


def _later_repeats(slot: np.ndarray, taken: np.ndarray) -> np.ndarray:
    """Positions (ascending) of the entries of ``slot (P,)`` (in reading order) whose slot an
    earlier entry, or ``taken`` (already filled), holds already."""
    _, first = np.unique(slot, return_index=True)
    again = np.ones(len(slot), bool)
    again[first] = False
    return np.flatnonzero(again | taken[slot])


def camera_ids(truth_id: np.ndarray, n_cameras: int, id_seed: int | None) -> list[dict[int, int]]:
    """Each camera's :func:`local_ids` of the people in ``truth_id``, drawn in camera order from
    one generator seeded ``id_seed`` (None: the people's own ids), as separate per-camera
    annotation tasks number them."""
    people = np.unique(truth_id)
    rng = np.random.default_rng(id_seed) if id_seed is not None else None
    return [local_ids(people, rng) for _ in range(n_cameras)]


def local_ids(people: np.ndarray, rng: np.random.Generator | None) -> dict[int, int]:
    """Per-camera ids of ``people (P,)``: a random permutation of ``1..P`` (``rng``), or the
    people's own ids (None), as separate per-camera annotation tasks number them."""
    ids = rng.permutation(len(people)) + 1 if rng is not None else people
    return dict(zip(people.tolist(), ids.tolist(), strict=True))


def sim_box_labels(sim: SimScene, ids: list[dict[int, int]]) -> Shapes:
    """A simulated box scene's boxes as label shapes: every (person, camera) where it is seen,
    under the camera's id of the person (``ids``, :func:`camera_ids`)."""
    k, c = np.nonzero(np.isfinite(sim.boxes).all(axis=2))
    return Shapes.labelled(sim.truth_frame[k], c, camera_track_ids(ids, c, sim.truth_id[k]), sim.boxes[k, c],
                           np.zeros((len(k), 0, 2)))


def camera_track_ids(ids: list[dict[int, int]], cam: np.ndarray, person: np.ndarray) -> np.ndarray:
    """(S,) each (camera ``cam``, person ``person``) pair's id in that camera (``ids``,
    :func:`camera_ids`), looked up as one table."""
    people = np.array(sorted(ids[0]), dtype=np.int64) if ids else np.zeros(0, np.int64)
    table = np.array([[d[int(p)] for p in people] for d in ids], dtype=np.int64)
    table = table.reshape(len(ids), len(people))
    return table[np.asarray(cam, dtype=np.int64), np.searchsorted(people, person)]

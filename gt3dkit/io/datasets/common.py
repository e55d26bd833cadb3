"""Helpers shared by the dataset loaders: box validation, row building (field parsing is
:mod:`gt3dkit.parse`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.types import F64, Observations


def check_box(where: str, box: list[float]) -> None:
    """Raise :class:`InputError` for a NaN/inf or degenerate box."""
    if not all(math.isfinite(v) for v in box):
        raise InputError(where, f"box has a non-finite value {box}")
    if box[2] <= box[0] or box[3] <= box[1]:
        raise InputError(where, f"degenerate box (need xmax > xmin and ymax > ymin): {box}")


@dataclass(frozen=True)
class JointBlock:
    """Keypoints read and checked as a block (:meth:`RowBuilder.add_joint_block`), one per point:
    ``frame, cam, tid, joint, line (P,)`` int64, ``uv (P, 2)``, ``conf (P,)`` or None; ``path``
    names the file the line numbers are of."""

    frame: np.ndarray
    cam: np.ndarray
    tid: np.ndarray
    joint: np.ndarray
    uv: F64
    conf: F64 | None
    line: np.ndarray
    path: str


@dataclass
class RowBuilder:
    """Accumulates observation rows keyed by (frame, cam, id), merging boxes and joints."""

    n_joints: int = 0
    rows: dict[tuple[int, int, int], int] = field(default_factory=dict)
    boxes: list[list[float]] = field(default_factory=list)
    kpts: list[np.ndarray] = field(default_factory=list)
    confs: list[np.ndarray] = field(default_factory=list)
    origin: list[str] = field(default_factory=list)
    has_conf: bool = False
    blocks: list[JointBlock] = field(default_factory=list)

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

    def add_checked_boxes(self, frame: int, cams: np.ndarray, tids: np.ndarray, boxes: F64,
                          origin: str) -> bool:
        """Boxes ``(V, 4)`` of one frame already checked (finite, not degenerate, no (camera, id)
        twice) added at once; ``origin`` is formatted with each row's id and camera
        (``origin.format(tid, cam)``). Nothing is added and False returned when a row exists
        already or the rows hold keypoints too (then :meth:`add_box` says what is wrong)."""
        keys = [(frame, c, i) for c, i in zip(cams.tolist(), tids.tolist(), strict=True)]
        if self.n_joints or any(k in self.rows for k in keys):
            return False
        start = len(self.boxes)
        self.rows.update(zip(keys, range(start, start + len(keys)), strict=True))
        self.boxes.extend(boxes.tolist())
        self.origin.extend(origin.format(i, c) for _, c, i in keys)
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
        joints of the skeleton, confidences in (0, 1]), added at once; a point given twice (here
        or before) is found by :meth:`build`. Held as arrays, not a Python object per point."""
        if block.conf is not None:
            self.has_conf = True
        self.blocks.append(block)

    def build(self) -> Observations:
        if self.blocks:
            return self._build_with_blocks()
        keys = list(self.rows)
        n = len(keys)
        arr = np.array(keys, dtype=np.int64).reshape(n, 3)
        order = np.lexsort((arr[:, 2], arr[:, 1], arr[:, 0]))
        idx = np.array([self.rows[k] for k in keys], dtype=np.int64)[order]
        return Observations(
            frame=arr[order, 0], cam=arr[order, 1], track_id=arr[order, 2],
            box_xyxy_px=np.array(self.boxes, dtype=np.float64).reshape(-1, 4)[idx],
            kpt_uv_px=(np.array(self.kpts, dtype=np.float64).reshape(n, self.n_joints, 2)[idx]
                       if self.n_joints else np.zeros((n, 0, 2))),  # boxes only: no per-row arrays
            origin=tuple(self.origin[i] for i in idx),
            kpt_conf=(np.array(self.confs, dtype=np.float64).reshape(n, self.n_joints)[idx]
                      if self.has_conf and self.n_joints else None),
        )

    def _build_with_blocks(self) -> Observations:
        """:meth:`build` when keypoints came in blocks: every (frame, camera, id) of the rows added
        one by one and of the blocks, in one sorted set of rows."""
        J = self.n_joints
        one = np.array(list(self.rows), dtype=np.int64).reshape(-1, 3)
        idx = np.array(list(self.rows.values()), dtype=np.int64)
        cat = {k: np.concatenate([getattr(b, k) for b in self.blocks]) for k in
               ("frame", "cam", "tid", "joint", "line")}
        uv = np.concatenate([b.uv for b in self.blocks])
        conf = (np.concatenate([b.conf if b.conf is not None else np.ones(len(b.frame)) for b in self.blocks])
                if self.has_conf else None)
        src = np.concatenate([np.full(len(b.frame), k) for k, b in enumerate(self.blocks)])
        pts = np.stack([cat["frame"], cat["cam"], cat["tid"]], axis=1)
        keys, inv = np.unique(np.concatenate([one, pts]), axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        row_one, row_pt = inv[: len(one)], inv[len(one):]
        n = len(keys)
        box = np.full((n, 4), np.nan)
        kpt = np.full((n, J, 2), np.nan)
        cf = np.full((n, J), np.nan)
        if len(one):
            box[row_one] = np.array(self.boxes, dtype=np.float64).reshape(-1, 4)[idx]
            if J:
                kpt[row_one] = np.array(self.kpts, dtype=np.float64).reshape(-1, J, 2)[idx]
                cf[row_one] = np.array(self.confs, dtype=np.float64).reshape(-1, J)[idx]
        # a point twice: in two blocks, or in a block and one by one (reported at the later line)
        slot = row_pt * max(J, 1) + cat["joint"]
        order = np.lexsort((cat["line"], src, slot))
        twice = np.flatnonzero(slot[order][1:] == slot[order][:-1])
        taken = np.isfinite(kpt.reshape(-1, 2)[slot, 0])
        bad = np.concatenate([order[twice + 1], np.flatnonzero(taken)])
        if len(bad):
            b = bad[np.lexsort((cat["line"][bad], src[bad]))[0]]
            raise InputError(f"{self.blocks[src[b]].path}: line {cat['line'][b]}",
                             f"second keypoint {cat['joint'][b]} for object {cat['tid'][b]} in frame "
                             f"{cat['frame'][b]} and this camera")
        kpt.reshape(-1, 2)[slot] = uv
        if conf is not None:
            cf.reshape(-1)[slot] = conf
        origin = [""] * n
        for r, i in zip(row_one.tolist(), idx.tolist(), strict=True):
            origin[r] = self.origin[i]  # a row added one by one keeps where it was first seen
        in_file = np.lexsort((cat["line"], src))  # the points in reading order
        rows, first = np.unique(row_pt[in_file], return_index=True)
        fresh = np.ones(n, bool)
        fresh[row_one] = False
        for r, p in zip(rows.tolist(), in_file[first].tolist(), strict=True):
            if fresh[r]:
                origin[r] = f"{self.blocks[src[p]].path}: line {cat['line'][p]}"
        return Observations(frame=keys[:, 0], cam=keys[:, 1], track_id=keys[:, 2], box_xyxy_px=box,
                            kpt_uv_px=kpt, origin=tuple(origin),
                            kpt_conf=cf if self.has_conf and J else None)


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

"""Helpers shared by the dataset loaders: checksums, box validation, row building."""

from __future__ import annotations

import csv
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.types import Observations


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_json_field(path: Path, key: str, what: str) -> Any:
    """``json.load(path)[key]``, or :class:`InputError` naming the file (malformed, truncated
    or without ``key``)."""
    try:
        return json.loads(Path(path).read_text())[key]
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(str(path), f"malformed or truncated JSON ({e})") from None
    except (KeyError, TypeError):
        raise InputError(str(path), f"expected {{'{key}': {what}}}") from None


def check_box(where: str, box: list[float]) -> None:
    """Raise :class:`InputError` for a NaN/inf or degenerate box."""
    if not all(math.isfinite(v) for v in box):
        raise InputError(where, f"box has a non-finite value {box}")
    if box[2] <= box[0] or box[3] <= box[1]:
        raise InputError(where, f"degenerate box (need xmax > xmin and ymax > ymin): {box}")


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

    def _row(self, frame: int, cam: int, tid: int, where: str) -> int:
        key = (frame, cam, tid)
        r = self.rows.get(key)
        if r is None:
            r = len(self.boxes)
            self.rows[key] = r
            self.boxes.append([math.nan] * 4)
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
        self.kpts[r][joint] = uv
        self.confs[r][joint] = 1.0 if conf is None else conf

    def build(self) -> Observations:
        keys = list(self.rows)
        n = len(keys)
        arr = np.array(keys, dtype=np.int64).reshape(n, 3)
        order = np.lexsort((arr[:, 2], arr[:, 1], arr[:, 0]))
        idx = np.array([self.rows[k] for k in keys], dtype=np.int64)[order]
        return Observations(
            frame=arr[order, 0], cam=arr[order, 1], track_id=arr[order, 2],
            box_xyxy_px=np.array(self.boxes, dtype=np.float64).reshape(-1, 4)[idx],
            kpt_uv_px=np.array(self.kpts, dtype=np.float64).reshape(n, self.n_joints, 2)[idx],
            origin=tuple(self.origin[i] for i in idx),
            kpt_conf=(np.array(self.confs, dtype=np.float64).reshape(n, self.n_joints)[idx]
                      if self.has_conf else None),
        )


def read_csv_rows(path: Path, columns: tuple[str, ...]) -> list[tuple[int, dict[str, str]]]:
    """Rows of a CSV with the given leading header; (line number, row)."""
    try:
        with open(path, newline="") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None or tuple(h.strip() for h in header[: len(columns)]) != columns:
                raise InputError(str(path), f"expected header {','.join(columns)}, got {header}")
            out = []
            for line, row in enumerate(reader, start=2):
                if not row or all(not x.strip() for x in row):
                    continue
                if len(row) < len(columns):
                    raise InputError(f"{path}: line {line}",
                                     f"expected {len(columns)} fields, got {len(row)}")
                out.append((line, dict(zip(columns, (x.strip() for x in row), strict=False))))
            return out
    except UnicodeDecodeError as e:
        raise InputError(str(path), f"not a text CSV file ({e})") from None

"""Helpers shared by the dataset loaders: checksums, box validation, row building."""

from __future__ import annotations

import csv
import hashlib
import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.types import F64, MAX_WORLD_M, Observations


def sha256(path: Path) -> str:
    """Hex SHA-256 of a file, or :class:`InputError` if it cannot be read (a folder, no
    permission)."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
    except OSError as e:
        raise InputError(str(path), f"cannot read ({e.strerror})") from None
    return h.hexdigest()


#: Frame numbers are 0 .. FRAME_MAX; ids are integers of magnitude up to ID_MAX (exact in a
#: float64, so they survive every array and file they pass through).
FRAME_MAX = 2**31 - 1
ID_MAX = 2**53


def load_json(path: Path) -> Any:
    """The document in a JSON file, or :class:`InputError` naming the file: unreadable,
    malformed, truncated or absurdly nested. A UTF-8 byte-order mark is allowed."""
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise InputError(str(path), f"not a UTF-8 text file ({e.reason} at byte {e.start})") from None
    except OSError as e:
        raise InputError(str(path), f"cannot read ({e.strerror})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(str(path), f"malformed JSON ({e})") from None
    except RecursionError:
        raise InputError(str(path), "malformed JSON (nested too deeply)") from None


def read_json_field(path: Path, key: str, what: str) -> Any:
    """``json.load(path)[key]``, or :class:`InputError` naming the file (malformed, truncated
    or without ``key``)."""
    doc = load_json(path)
    if not isinstance(doc, dict) or key not in doc:
        raise InputError(str(path), f"expected {{'{key}': {what}}}")
    return doc[key]


def parse_int(where: str, text: Any, name: str, lo: int = -ID_MAX, hi: int = ID_MAX) -> int:
    """An integer field (text or JSON value) in ``[lo, hi]``, or :class:`InputError`."""
    if isinstance(text, bool) or isinstance(text, float) and not text.is_integer():
        raise InputError(where, f"{name} must be an integer, got {text!r}")
    try:
        v = int(text)
    except (TypeError, ValueError, OverflowError):
        raise InputError(where, f"{name} must be an integer, got {text!r}") from None
    if not lo <= v <= hi:
        raise InputError(where, f"{name} {v} is outside {lo}..{hi}")
    return v


def parse_frame(where: str, text: Any) -> int:
    return parse_int(where, text, "frame", 0, FRAME_MAX)


def parse_float(where: str, text: Any, name: str, limit: float = math.inf) -> float:
    """A finite number field of magnitude up to ``limit``, or :class:`InputError`."""
    try:
        v = float(text)
    except (TypeError, ValueError, OverflowError):
        raise InputError(where, f"{name} must be a number, got {text!r}") from None
    if not math.isfinite(v):
        raise InputError(where, f"{name} is not finite ({text})")
    if abs(v) > limit:
        raise InputError(where, f"{name} {v:g} is beyond {limit:g}")
    return v


def parse_metres(where: str, text: Any, name: str) -> float:
    """A world coordinate or length (m): finite, within :data:`MAX_WORLD_M`."""
    return parse_float(where, text, f"{name} (m)", MAX_WORLD_M)


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

    def build(self) -> Observations:
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


def read_csv_rows(path: Path, columns: tuple[str, ...], warnings: list[str] | None = None,
                  header: bool = True) -> list[tuple[int, dict[str, str]]]:
    """:func:`iter_csv_rows` as a list."""
    return list(iter_csv_rows(path, columns, warnings, header))


def iter_csv_rows(path: Path, columns: tuple[str, ...], warnings: list[str] | None = None,
                  header: bool = True) -> Iterator[tuple[int, dict[str, str]]]:
    """Rows of a CSV whose header starts with ``columns``; (line number, row), one at a time
    (a bad line 2 is reported before line 2 million is read, and the file is never held whole).

    Every row must have as many fields as the header. Header columns beyond ``columns``
    are ignored, with a note in ``warnings`` (an error when ``warnings`` is None). A UTF-8
    byte-order mark (Excel's "CSV UTF-8") is allowed. ``header=False``: a file without a
    header (MOTChallenge), each row with at least ``len(columns)`` fields, the same number in
    every row.
    """
    where = str(path)
    reader = None
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            if not header:
                width = None
                for row in reader:
                    line = reader.line_num
                    if not row or all(not x.strip() for x in row):
                        continue
                    width = len(row) if width is None else width
                    if len(row) < len(columns) or len(row) != width:
                        want = width if len(row) >= len(columns) else len(columns)
                        raise InputError(f"{path}: line {line}",
                                         f"expected {want} fields ({','.join(columns)}, ...), got {len(row)}")
                    yield line, dict(zip(columns, (x.strip() for x in row), strict=False))
                return
            header = next(reader, None)
            if header is None or tuple(h.strip() for h in header[: len(columns)]) != columns:
                raise InputError(where, f"expected header {','.join(columns)}, got "
                                        f"{','.join(header) if header else 'an empty file'}")
            extra = [h.strip() for h in header[len(columns):]]
            if extra:
                if warnings is None:
                    raise InputError(where, f"unexpected columns {extra} after {','.join(columns)}")
                warnings.append(f"{path}: columns {', '.join(extra)} ignored")
            for row in reader:
                line = reader.line_num
                where = f"{path}: line {line}"
                if not row or all(not x.strip() for x in row):
                    continue
                if len(row) != len(header):
                    raise InputError(where, f"expected {len(header)} fields (as the header), "
                                            f"got {len(row)}")
                yield line, dict(zip(columns, (x.strip() for x in row), strict=False))
    except UnicodeDecodeError as e:
        raise InputError(where, f"not a UTF-8 text CSV file ({e.reason} at byte {e.start})") from None
    except csv.Error as e:
        line = f": line {reader.line_num}" if reader is not None else ""
        raise InputError(f"{path}{line}", f"malformed CSV ({e})") from None
    except OSError as e:
        raise InputError(str(path), f"cannot read ({e.strerror})") from None

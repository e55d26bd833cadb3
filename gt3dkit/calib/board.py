"""Calibration boards: what they look like, how users describe them, and finding them in an image.

Two kinds, both OpenCV's:

* ``charuco``: a chessboard of ``squares_x`` x ``squares_y`` squares with ArUco markers in the
  white squares (``cv2.aruco.CharucoBoard``, found by ``cv2.aruco.CharucoDetector``); every inner
  corner has an id, so a partly seen board still gives known corners;
* ``checkerboard``: plain squares (found by ``cv2.findChessboardCornersSB``, all inner corners
  or none). Its corner grid looks the same turned by 180 degrees, so an image gives the corners
  in one of two orders: the multi-camera fit chooses the order that agrees with the other
  cameras (:mod:`gt3dkit.calib.boardcal`).

Inner corner ``i`` lies at ``((i % (squares_x - 1) + 1) * square_m, (i // (squares_x - 1) + 1) *
square_m, 0)`` in the board frame (x along the first side, y along the second, z into the board,
metres), as ``CharucoBoard.getChessboardCorners`` places them.

Descriptions read (:func:`read_board`): anipose's ``board.toml`` as sleap-anipose writes it
(``board_x``, ``board_y``, ``square_length``, ``marker_length``, ``marker_bits``, ``dict_size``),
anipose's ``config.toml`` ``[calibration]`` section (``board_type``, ``board_size``,
``board_square_side_length``, ``board_marker_length``, ``board_marker_bits``,
``board_marker_dict_number``), Pose2Sim's ``Config.toml`` (``[calibration.calculate.intrinsics]``
``intrinsics_corners_nb`` (inner corners), ``intrinsics_square_size``, and
``intrinsics_marker_size`` / ``intrinsics_aruco_dict`` for a ChArUco board), and a spec given on
the command line: ``charuco:8x11:24:18.75:DICT_4X4_1000`` or ``checkerboard:9x6:25`` (squares,
lengths in the board units, ``--board-units``, millimetres unless told).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.parse import load_toml
from gt3dkit.types import F64

if TYPE_CHECKING:
    import cv2

BoardKind = Literal["charuco", "checkerboard"]

#: Board units a description's lengths may be in, in metres.
UNITS_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}


@dataclass(frozen=True)
class Board:
    """A planar calibration board.

    Attributes
    ----------
    kind : "charuco" or "checkerboard"
    squares_x, squares_y : int
        Squares along the board's two sides (inner corners: one fewer each).
    square_m : float
        Side of a square, metres.
    marker_m : float
        Side of an ArUco marker, metres (ChArUco only; 0 for a checkerboard).
    dictionary : str
        OpenCV's name of the ArUco dictionary (``"DICT_4X4_1000"``).
    legacy : bool
        OpenCV's legacy ChArUco layout (boards printed before OpenCV 4.6 with an even number
        of rows start with a white square); tried automatically when the other finds nothing.
    """

    kind: BoardKind
    squares_x: int
    squares_y: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = "DICT_4X4_50"
    legacy: bool = False

    def __post_init__(self) -> None:
        if self.kind not in ("charuco", "checkerboard"):
            raise ValueError(f"board kind must be charuco or checkerboard, got {self.kind!r}")
        if min(self.squares_x, self.squares_y) < 3:
            raise ValueError(f"a board needs at least 3 x 3 squares, got {self.squares_x} x {self.squares_y}")
        if not 0 < self.square_m < 10:
            raise ValueError(f"square side must be in (0, 10) m, got {self.square_m:g} m")
        if self.kind == "charuco":
            if not 0 < self.marker_m < self.square_m:
                raise ValueError(
                    f"a ChArUco marker ({self.marker_m * 1e3:g} mm) must be smaller than its "
                    f"square ({self.square_m * 1e3:g} mm)"
                )
            if self.dictionary not in aruco_dictionaries():
                raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}")

    @property
    def inner(self) -> tuple[int, int]:
        """Inner corners along x and y."""
        return self.squares_x - 1, self.squares_y - 1

    @property
    def n_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)

    def corners_board(self) -> F64:
        """(N, 3) inner corners in the board frame, metres, in id order."""
        nx, ny = self.inner
        i = np.arange(nx * ny)
        return np.stack(
            [(i % nx + 1) * self.square_m, (i // nx + 1) * self.square_m, np.zeros(nx * ny)], axis=1
        )

    def describe(self) -> str:
        s = f"{self.kind} {self.squares_x}x{self.squares_y} squares of {self.square_m * 1e3:g} mm"
        if self.kind == "charuco":
            s += f", markers {self.marker_m * 1e3:g} mm, {self.dictionary}"
        return s

    def opencv_board(self, legacy: bool | None = None) -> cv2.aruco.CharucoBoard:
        """OpenCV's ChArUco board (lengths in metres), with a dictionary of the board's own markers.

        The board carries markers ``0 .. n-1`` of its dictionary; the detector compares every
        candidate square in an image with every marker of the dictionary it is given, so it is
        given those ``n`` only (the same ids): on the shared mouse rig's DICT_4X4_1000 board,
        detection takes 9 ms a frame instead of 65 ms, and finds the same corners.
        """
        import cv2

        full = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        n = (self.squares_x * self.squares_y) // 2
        d = cv2.aruco.Dictionary(full.bytesList[:n].copy(), full.markerSize, full.maxCorrectionBits)
        b = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m, d)
        b.setLegacyPattern(self.legacy if legacy is None else legacy)
        return b


def aruco_dictionaries() -> tuple[str, ...]:
    """OpenCV's predefined ArUco dictionary names."""
    import cv2

    return tuple(n for n in dir(cv2.aruco) if n.startswith("DICT_") and n.upper() == n)


def _dict_name(bits: int, size: int) -> str:
    return f"DICT_{bits}X{bits}_{size}"


def board_from_spec(spec: str, units: str = "mm") -> Board:
    """A board from ``charuco:SXxSY:SQUARE:MARKER[:DICT]`` or ``checkerboard:SXxSY:SQUARE``."""
    scale = UNITS_M[units]
    m = re.fullmatch(
        r"(charuco|checkerboard|checker):(\d+)x(\d+):([0-9.eE+-]+)(?::([0-9.eE+-]+))?"
        r"(?::(DICT_\w+))?",
        spec.strip(),
    )
    if m is None:
        raise InputError(
            "--board",
            f"{spec!r} is neither a file nor a board spec (charuco:8x11:24:18.75:"
            "DICT_4X4_1000 or checkerboard:9x6:25, lengths in --board-units)",
        )
    kind: BoardKind = "checkerboard" if m.group(1).startswith("checker") else "charuco"
    try:
        square = float(m.group(4)) * scale
        marker = float(m.group(5)) * scale if m.group(5) else 0.0
        if kind == "charuco" and not m.group(5):
            raise ValueError("a ChArUco spec needs the marker length")
        return Board(
            kind,
            int(m.group(2)),
            int(m.group(3)),
            square,
            marker,
            m.group(6) or "DICT_4X4_50",
        )
    except ValueError as e:
        raise InputError("--board", str(e)) from None


def read_board(path_or_spec: str, units: str = "mm") -> Board:
    """The board of a description file (see the module docstring) or a command-line spec."""
    path = Path(path_or_spec)
    if not path.is_file():
        if path.suffix == ".toml" or path.exists():
            raise InputError(str(path), "no such board file")
        return board_from_spec(path_or_spec, units)
    doc = load_toml(path)
    try:
        board = _board_of_doc(doc, UNITS_M[units], str(path))
    except InputError:
        raise
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(str(path), f"not a board description ({e})") from None
    if board is None:
        raise InputError(
            str(path),
            "no board found (expected board_x/board_y/square_length as anipose's "
            "board.toml, a [calibration] section with board_size (anipose), or "
            "[calibration.calculate.intrinsics] intrinsics_corners_nb (Pose2Sim))",
        )
    return board


_NONE = object()


def _number(v: Any, kind: type, where: str) -> Any:
    """``v`` as an ``int`` or a ``float`` (``kind``), else an :class:`InputError` naming ``where``."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (kind is int and float(v) != int(v)):
        what = "an integer" if kind is int else "a number"
        raise InputError(where, f"expected {what}, got {v!r}")
    return kind(v)


def _value(d: dict[str, Any], key: str, kind: type, where: str, default: Any = _NONE) -> Any:
    """:func:`_number` of ``d[key]`` (``where: key``); ``default`` where the key is absent (else
    missing is an error too)."""
    if key not in d:
        if default is _NONE:
            raise InputError(f"{where}: {key}", "missing")
        return default
    return _number(d[key], kind, f"{where}: {key}")


def _board_of_doc(doc: dict[str, Any], scale: float, where: str) -> Board | None:
    if "board_x" in doc:  # sleap-anipose's board.toml
        kind: BoardKind = "charuco" if doc.get("marker_length") else "checkerboard"
        return Board(
            kind,
            _value(doc, "board_x", int, where),
            _value(doc, "board_y", int, where),
            _value(doc, "square_length", float, where) * scale,
            _value(doc, "marker_length", float, where, 0.0) * scale,
            _dict_name(_value(doc, "marker_bits", int, where, 4), _value(doc, "dict_size", int, where, 50)),
        )
    cal = doc.get("calibration")
    if isinstance(cal, dict) and "board_size" in cal:  # anipose's config.toml
        at = f"{where}: calibration"
        if cal.get("board_type", "charuco") not in ("charuco", "checkerboard", "checker"):
            raise InputError(f"{at}: board_type", f"{cal['board_type']!r} (charuco or checkerboard)")
        kind = "checkerboard" if str(cal.get("board_type", "charuco")).startswith("checker") else "charuco"
        size = cal["board_size"]
        if not isinstance(size, list) or len(size) != 2:
            raise InputError(f"{at}: board_size", f"expected [squares x, squares y], got {size!r}")
        sx, sy = (_number(v, int, f"{at}: board_size") for v in size)
        return Board(
            kind,
            sx,
            sy,
            _value(cal, "board_square_side_length", float, at) * scale,
            _value(cal, "board_marker_length", float, at, 0.0) * scale if kind == "charuco" else 0.0,
            _dict_name(_value(cal, "board_marker_bits", int, at, 4),
                       _value(cal, "board_marker_dict_number", int, at, 50)),
        )
    intr = (cal or {}).get("calculate", {}).get("intrinsics") if isinstance(cal, dict) else None
    if isinstance(intr, dict) and "intrinsics_corners_nb" in intr:  # Pose2Sim's Config.toml
        at = f"{where}: calibration.calculate.intrinsics"
        nb = intr["intrinsics_corners_nb"]
        if not isinstance(nb, list) or len(nb) != 2:
            raise InputError(f"{at}: intrinsics_corners_nb", f"expected [inner corners x, y], got {nb!r}")
        a, b = (_number(v, int, f"{at}: intrinsics_corners_nb") for v in nb)
        marker = _value(intr, "intrinsics_marker_size", float, at, 0.0)
        kind = "charuco" if marker else "checkerboard"
        return Board(
            kind,
            a + 1,
            b + 1,
            _value(intr, "intrinsics_square_size", float, at) * scale,
            marker * scale,
            str(intr.get("intrinsics_aruco_dict", "DICT_6X6_250")),
        )
    return None


@dataclass(frozen=True)
class Detection:
    """The board's corners found in one image.

    Attributes
    ----------
    ids : (N,) int64
        Inner corner ids (see :meth:`Board.corners_board`).
    uv_px : (N, 2) float64
        Their image positions, distorted pixels, pixel centres at integers.
    """

    ids: np.ndarray
    uv_px: F64


class BoardDetector:
    """Finds a :class:`Board` in grey images (one instance per thread: OpenCV's detectors keep
    state)."""

    def __init__(self, board: Board) -> None:
        import cv2

        self.board = board
        self._cv2 = cv2
        if board.kind == "charuco":
            self._detectors = [
                cv2.aruco.CharucoDetector(board.opencv_board(legacy))
                for legacy in (board.legacy, not board.legacy)
            ]
            self._which = 0

    def detect(self, grey: np.ndarray) -> Detection | None:
        """The corners in ``grey`` (H, W) uint8, or None when fewer than 6 are found (too few to
        pose a board)."""
        cv2 = self._cv2
        if self.board.kind == "checkerboard":
            ok, corners = cv2.findChessboardCornersSB(
                grey, self.board.inner, flags=cv2.CALIB_CB_NORMALIZE_IMAGE
            )
            if not ok or corners is None:
                return None
            return Detection(np.arange(self.board.n_corners), corners.reshape(-1, 2).astype(np.float64))
        best: Detection | None = None
        for k in (self._which, 1 - self._which):  # the layout that last worked first
            cc, ci, _, _ = self._detectors[k].detectBoard(grey)
            if ci is not None and len(ci) >= 6:
                det = Detection(ci.reshape(-1).astype(np.int64), cc.reshape(-1, 2).astype(np.float64))
                if best is None or len(det.ids) > len(best.ids):
                    best = det
                if len(det.ids) >= 0.5 * self.board.n_corners:
                    self._which = k
                    return det
        return best

"""Each camera's clock, as a file (``time_offsets.csv``) and as what it does to a scene: every
view moved onto one clock (issue 63).

A camera *late* by ``d`` frames shows at its frame ``g`` what the scene's clock shows at
``g - d``; a camera recording at its own rate ``fps_c`` shows at its frame ``g`` the scene's time
``g / fps_c`` (seconds from frame 0). Together: camera ``c``'s frame ``g`` is seen at the scene's
frame

.. math::
    t = g \\, \\frac{f}{f_c} - d_c,

``f`` the scene's frame rate. :func:`on_one_clock` numbers each view by the nearest whole frame
``floor(t + 1/2)`` and keeps the rest (within half a frame), as
:attr:`gt3dkit.types.Observations.frame_offset`: the UKF predicts each joint to the moment its
view was taken (:mod:`gt3dkit.fusion.ukf.jointupdate`), not to the frame it is filed under.

``time_offsets.csv``: a header, then one line per camera::

    camera,late_frames,sd_frames,fps
    cam_1,0.0,0.0,
    cam_2,2.35,0.04,

``sd_frames`` and ``fps`` may be left empty (unknown; the scene's rate); a camera the file does
not name is on the scene's clock. ``gt3d calib people --clocks`` writes the file, ``gt3d
reconstruct --time-offsets FILE`` reads it.
"""

from __future__ import annotations

import csv
import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.rig import as_array
from gt3dkit.types import F64, JsonDict, Scene

HEADER = ("camera", "late_frames", "sd_frames", "fps")
#: A view filed under a frame whose fraction is below this is taken as on it (storage precision).
ON_FRAME = 1e-9


@dataclass(frozen=True)
class CameraClocks:
    """Per camera ``names (C,)``: ``late_frames (C,)`` (module docstring), ``sd_frames (C,)``
    (NaN: unknown) and ``fps (C,)`` (NaN: the scene's rate); ``source``: where they come from (a
    file's path, for messages)."""

    names: tuple[str, ...]
    late_frames: F64
    sd_frames: F64
    fps: F64
    source: str = "time offsets"

    def __post_init__(self) -> None:
        C = len(self.names)
        for name in ("late_frames", "sd_frames", "fps"):  # NaN: unknown (late_frames: never)
            a = as_array(getattr(self, name), (C,), name, finite=name == "late_frames")
            object.__setattr__(self, name, a)

    @staticmethod
    def of(names: tuple[str, ...], late_frames: F64, sd_frames: F64 | None = None,
           source: str = "time offsets") -> CameraClocks:
        """Offsets at the scene's rate."""
        C = len(names)
        return CameraClocks(names, late_frames, np.full(C, np.nan) if sd_frames is None else sd_frames,
                            np.full(C, np.nan), source)

    def text(self) -> str:
        """The file's text (module docstring)."""

        def num(v: float) -> str:
            return "" if not np.isfinite(v) else f"{v:.4f}"

        return ",".join(HEADER) + "\n" + "".join(
            f"{n},{d + 0.0:.4f},{num(s)},{'' if not np.isfinite(f) else f'{f:g}'}\n"
            for n, d, s, f in zip(self.names, self.late_frames, self.sd_frames, self.fps, strict=True))

    def doc(self) -> JsonDict:
        """For ``meta.json`` (read back by :meth:`from_doc`)."""
        return {n: {"late_frames": round(float(d), 6) + 0.0,
                    "sd_frames": None if not np.isfinite(s) else round(float(s), 6),
                    "fps": None if not np.isfinite(f) else float(f)}
                for n, d, s, f in zip(self.names, self.late_frames, self.sd_frames, self.fps, strict=True)}

    @staticmethod
    def from_doc(doc: JsonDict, where: str) -> CameraClocks:
        def col(key: str) -> F64:
            out = np.full(len(names), np.nan)
            for i, n in enumerate(names):
                cam = doc[n]
                if not isinstance(cam, Mapping):
                    raise TypeError(f"camera {n}: expected an object")
                v = cam.get(key)
                if v is not None and not isinstance(v, int | float | str):
                    raise TypeError(f"camera {n}: {key} must be a number")
                out[i] = np.nan if v is None else float(v)
            return out

        try:
            names = tuple(doc)
            late, sd, fps = (col(k) for k in HEADER[1:])
            return CameraClocks(names, late, sd, fps, where)
        except (TypeError, KeyError, ValueError, AttributeError) as e:
            raise InputError(where, f"time offsets: {e}") from None


def read_time_offsets(path: Path) -> CameraClocks:
    """``time_offsets.csv`` (module docstring), or :class:`InputError` naming the line."""
    where = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(where, f"cannot read: {e}") from None
    rows = list(csv.reader(text.splitlines()))
    if not rows or [h.strip() for h in rows[0][:2]] != list(HEADER[:2]):
        raise InputError(where, f"line 1: expected the header {','.join(HEADER)} (camera,late_frames at "
                                "least)")
    head = [h.strip() for h in rows[0]]
    unknown = [h for h in head if h not in HEADER]
    if unknown:
        raise InputError(where, f"line 1: unknown column {unknown[0]!r} (columns: {', '.join(HEADER)})")
    names: list[str] = []
    vals: list[list[float]] = []
    for i, row in enumerate(rows[1:], start=2):
        if not any(v.strip() for v in row):
            continue
        if len(row) > len(head):
            raise InputError(where, f"line {i}: {len(row)} fields, the header has {len(head)}")
        cell = dict(zip(head, (v.strip() for v in row), strict=False))
        name = cell.get("camera", "")
        if not name:
            raise InputError(where, f"line {i}: no camera name")
        if name in names:
            raise InputError(where, f"line {i}: camera {name} given twice")
        got = []
        for col in HEADER[1:]:
            v = cell.get(col, "")
            if v == "" and col != "late_frames":
                got.append(np.nan)
                continue
            try:
                x = float(v)
            except ValueError:
                raise InputError(where, f"line {i}: {col} {v!r} is not a number") from None
            least = {"fps": " and > 0", "sd_frames": " and >= 0"}.get(col, "")
            if not np.isfinite(x) or (col == "fps" and x <= 0) or (col == "sd_frames" and x < 0):
                raise InputError(where, f"line {i}: {col} {v!r} must be finite{least}")
            got.append(x)
        names.append(name)
        vals.append(got)
    if not names:
        raise InputError(where, "no camera lines")
    a = np.array(vals)
    return CameraClocks(tuple(names), a[:, 0], a[:, 1], a[:, 2], where)


def on_one_clock(scene: Scene, clocks: CameraClocks) -> Scene:
    """``scene`` with every view numbered by the scene's frame it was seen nearest and the rest
    kept as its ``frame_offset`` (module docstring); the frame grid made anew. Where a camera
    faster than the scene puts two of its frames on one of the scene's, the nearer is kept (a
    ``warning:``)."""
    rig = scene.rig
    where = clocks.source
    unknown = [n for n in clocks.names if n not in rig.names]
    if unknown:
        raise InputError(where, f"camera {unknown[0]}: not in the calibration (cameras: "
                                f"{', '.join(rig.names)})")
    C = len(rig.cameras)
    late, ratio = np.zeros(C), np.ones(C)
    for k, n in enumerate(clocks.names):
        c = rig.index(n)
        late[c] = clocks.late_frames[k]
        if np.isfinite(clocks.fps[k]):
            ratio[c] = scene.fps / clocks.fps[k]
    obs = scene.obs
    t = obs.frame * ratio[obs.cam] - late[obs.cam]
    frame = np.floor(t + 0.5).astype(np.int64)  # halves up: a camera at the scene's rate never meets itself
    off = t - frame
    off[np.abs(off) < ON_FRAME] = 0.0
    # a camera faster than the scene: of two of its frames on one of the scene's, the nearer
    # (ties: the earlier frame)
    _, grp = np.unique(np.stack([obs.cam, frame], 1), axis=0, return_inverse=True)
    grp = grp.reshape(-1)
    order = np.lexsort((obs.frame, np.abs(off), grp))
    first = np.r_[True, grp[order][1:] != grp[order][:-1]]
    chosen = np.empty(grp.max() + 1 if len(grp) else 0, np.int64)
    chosen[grp[order][first]] = obs.frame[order][first]
    keep = obs.frame == chosen[grp]
    warnings = list(scene.warnings)
    if not keep.all():
        warnings.append(f"{where}: {int((~keep).sum())} views of cameras faster than the scene's "
                        f"{scene.fps:g} frames per second left out (another frame of theirs is nearer "
                        "the same frame of the scene)")
    moved = dataclasses.replace(obs, frame=frame, frame_offset=off)
    order = np.flatnonzero(keep)
    # in the order the readers give: by frame, then camera
    moved = moved.select(order[np.lexsort((order, moved.cam[order], moved.frame[order]))])
    return dataclasses.replace(scene, obs=moved, frames=np.unique(moved.frame), warnings=tuple(warnings))

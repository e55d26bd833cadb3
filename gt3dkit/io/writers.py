"""``tracks.csv`` and ``meta.json``, written atomically; and reading ``tracks.csv`` back."""

from __future__ import annotations

import csv
import datetime as _dt
import io
import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TextIO

import numpy as np

from gt3dkit.calib.formats import write_calibration
from gt3dkit.calib.formats.native import write as write_native
from gt3dkit.errors import InputError
from gt3dkit.io.atomic import write_dir_atomically
from gt3dkit.io.numtext import format_rows
from gt3dkit.parse import iter_csv_rows, parse_float, parse_frame, parse_int, parse_metres
from gt3dkit.rig import Rig
from gt3dkit.skeletons import skeleton_of
from gt3dkit.types import BOX_EDGES, JsonDict, JsonValue, RunInfo, Scene, TrackSet
from gt3dkit.version import __version__

TRACK_COLUMNS = ("frame", "id", "x", "y", "z", "a", "b", "c", "sx", "sy", "sz")
KPT_COLUMNS = ("frame", "id", "joint", "x", "y", "z", "sd")
DOWNWEIGHTED_COLUMNS = ("frame", "camera", "id", "joint", "edge", "weight", "residual_px", "score")
ANOMALY_COLUMNS = ("frame", "camera", "id", "joint", "kind", "score", "detail")


class AnomalyRows(Protocol):
    """What the writers read of the QA's findings (:class:`gt3dkit.qa.anomalies.Anomalies`, a
    layer above): one tuple per finding, in :data:`ANOMALY_COLUMNS`' order."""

    @property
    def rows(self) -> Sequence[tuple[int, str, int | str, int | str, str, float, str]]: ...


class RefinedRig(Protocol):
    """What the writers read of a calibration refinement (:class:`gt3dkit.refine.RefineResult`,
    a layer above): the refined rig and the report of how it was found."""

    @property
    def rig(self) -> Rig: ...

    @property
    def report(self) -> JsonDict: ...


def _jsonable(x: object) -> JsonValue:
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if x is None or isinstance(x, str | int | float):
        return x
    raise TypeError(f"{type(x).__name__} is not a JSON value")


def meta_of(scene: Scene, tracks: TrackSet) -> JsonDict:
    """What ``meta.json`` says: frame, axes, units, estimator, input and counts."""
    up = scene.rig.up
    wfb = scene.rig.world_from_body()
    return {
        "gt3dkit_version": __version__,
        "created_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "frame": {
            "name": scene.rig.frame_name,
            "up": up.tolist(),
            "units": "m",
            "centre": "x, y, z: ellipsoid centre in the input's world frame",
            "semi_axes": {"a": wfb[:, 0].tolist(), "b": wfb[:, 1].tolist(), "c": wfb[:, 2].tolist(),
                          "note": "directions in the world frame; c is along up"},
            "sd": "sx, sy, sz: standard deviation of the centre along world x, y, z, widened by "
                  "the correlation between the axes (sqrt of the correlation matrix's largest "
                  "eigenvalue) so that sum((error/sd)^2) over the axes is at most a chi-square "
                  "with 3 dof: each axis can be checked on its own",
            **({"keypoints": "keypoints.csv: frame,id,joint,x,y,z,sd in the world frame (m); sd = "
                             "the joint's largest standard deviation over all directions (m)",
                "skeleton": scene.skeleton,
                "joints": list(skel.joints) if (skel := skeleton_of(scene)) is not None else None,
                **({"skeleton_doc": scene.skeleton_doc} if scene.skeleton_doc is not None else {})}
               if tracks.kpt_world.shape[1] else {}),
        },
        "estimator": _jsonable(tracks.info.as_json()),
        "input": {"root": scene.root, "layout": scene.layout, "fps": scene.fps,
                  "fps_assumed": scene.fps_assumed or None, "warnings": list(scene.all_warnings),
                  "calibration_notes": scene.calibration_notes,
                  "cameras": scene.rig.names, "files_sha256": scene.files,
                  "load": scene.load_options},
        "counts": {
            "objects": int(len(np.unique(tracks.track_id))),
            "frames": int(len(np.unique(tracks.frame))),
            "rows": int(len(tracks)),
            "rows_seen_by_0_views": int(np.sum(tracks.n_views == 0)),
            "rows_seen_by_1_view": int(np.sum(tracks.n_views == 1)),
            "annotations": scene.n_annotations,
        },
    }


def write_tracks_csv(path: Path, tracks: TrackSet) -> None:
    """One row per (frame, id); a run with rows no camera saw (a dense run's, ``info.every_frame``,
    or a short gap bridged) or rows one camera saw adds the column ``n_views`` (0: interpolated,
    1: from one view)."""
    with open(path, "w", newline="") as f:
        csv.writer(f).writerow(_tracks_header(tracks))
        _tracks_rows(f, tracks)


def _dense(tracks: TrackSet) -> bool:
    """Whether ``tracks.csv`` says each row's views: a run with rows no camera saw (a dense run's,
    or a bridged gap's) or rows one camera saw (no triangulation: the sd says how far along that
    camera's ray the object may be)."""
    return tracks.info.every_frame is not None or bool(np.any((tracks.n_views >= 0) & (tracks.n_views <= 1)))


def _tracks_header(tracks: TrackSet) -> tuple[str, ...]:
    """``tracks.csv``'s columns: ``n_views`` last in a dense run."""
    return TRACK_COLUMNS + (("n_views",) if _dense(tracks) else ())


def _tracks_rows(f: TextIO, tracks: TrackSet) -> None:
    """``tracks``' rows of :func:`write_tracks_csv` into the open file ``f``."""
    dense = _dense(tracks)
    cols = [tracks.frame, tracks.track_id, tracks.center_world, tracks.semi_axes, tracks.center_sd,
            *([tracks.n_views] if dense else [])]
    fixed = np.r_[False, False, np.ones(9, bool), np.zeros(int(dense), bool)]
    f.write(format_rows(np.column_stack(cols), fixed))  # as csv.writer writes them


def write_keypoints_csv(path: Path, tracks: TrackSet) -> None:
    """One row per (frame, id, joint) with a finite estimate (metres)."""
    with open(path, "w", newline="") as f:
        csv.writer(f).writerow(KPT_COLUMNS)
        _keypoint_rows(f, tracks)


def _keypoint_rows(f: TextIO, tracks: TrackSet) -> None:
    """``tracks``' rows of :func:`write_keypoints_csv` into the open file ``f``: the bytes
    ``csv.writer`` wrote of each row's numbers (``%d`` and ``%.6f``, CRLF line ends), by
    :func:`gt3dkit.io.numtext.format_rows` (541 000 joint-rows: 3.9 s row by row, 2.3 s as one
    ``%``-template per row)."""
    r, j = np.nonzero(np.isfinite(tracks.kpt_world).all(axis=-1))
    v = np.column_stack([tracks.frame[r], tracks.track_id[r], j, tracks.kpt_world[r, j], tracks.kpt_sd[r, j]])
    f.write(format_rows(v, np.r_[False, False, False, np.ones(4, bool)]))


@dataclass(frozen=True)
class PartText:
    """A part's rows as :class:`StreamedRows` writes them, text made where the part was made (a
    window's worker, :func:`gt3dkit.windows.stitch.run_window`): ``tracks.csv``'s,
    ``keypoints.csv``'s (empty where it has no joints) and ``anomalies.csv``'s, without headers."""

    tracks: str
    keypoints: str
    anomalies: str

    @classmethod
    def of(cls, tracks: TrackSet, anomaly_rows: list[tuple[Any, ...]]) -> PartText:
        t, k, a = io.StringIO(), io.StringIO(), io.StringIO()
        _tracks_rows(t, tracks)
        if tracks.kpt_world.shape[1]:
            _keypoint_rows(k, tracks)
        csv.writer(a).writerows(anomaly_rows)
        return cls(t.getvalue(), k.getvalue(), a.getvalue())


class StreamedRows:
    """``tracks.csv``, ``keypoints.csv`` and ``anomalies.csv`` of a run that comes in parts, written
    into the folder ``d`` as the parts come: the windows of a long sequence
    (:mod:`gt3dkit.windows`), each a :class:`TrackSet` of its own frames (rows by frame, then id)
    and its QA findings (sorted as :func:`write_anomalies_csv` writes them), the windows in frame
    order. Part ``k``'s rows go out as soon as parts ``0..k`` are all in (they are final, and
    the files then read as the whole run's), so that little is left to write when the last one
    comes; each part is checked as :func:`check_tracks` checks a whole run. ``also``: given each
    part's tracks too, in order, once written (the truth report's counts as the run goes,
    :class:`gt3dkit.commands.common.TruthTally`). Each part's text is the one made with it
    (:class:`PartText`: on a Dask worker, which has the compiled formatter loaded; this process
    then loads no compiled code, 0.24 s of CPU), or made here. A context manager;
    :func:`write_result_files` with ``streamed`` writes the rest."""

    def __init__(self, d: Path, also: Callable[[TrackSet], None] | None = None) -> None:
        self.d = Path(d)
        self._also = also
        self._next = 0
        self._waiting: dict[int, tuple[TrackSet, list[tuple[Any, ...]], PartText | None]] = {}
        self._files: dict[str, TextIO] = {}

    def add(self, k: int, tracks: TrackSet, anomaly_rows: list[tuple[Any, ...]], text: PartText | None = None
            ) -> None:
        """Part ``k`` (from 0) is in, with its ``text`` where it was made with it: it and every part
        after it that waited for it are written."""
        check_tracks(tracks)
        self._waiting[k] = (tracks, anomaly_rows, text)
        while self._next in self._waiting:
            t, rows, made = self._waiting.pop(self._next)
            self._write(t, made if made is not None else PartText.of(t, rows))
            self._next += 1
            if self._also is not None:
                self._also(t)

    def _file(self, name: str, header: tuple[str, ...]) -> TextIO:
        if name not in self._files:
            f = open(self.d / name, "w", newline="")  # noqa: SIM115 (closed by close())
            csv.writer(f).writerow(header)
            self._files[name] = f
        return self._files[name]

    def _write(self, tracks: TrackSet, text: PartText) -> None:
        self._file("tracks.csv", _tracks_header(tracks)).write(text.tracks)
        if tracks.kpt_world.shape[1]:
            self._file("keypoints.csv", KPT_COLUMNS).write(text.keypoints)
        self._file("anomalies.csv", ANOMALY_COLUMNS).write(text.anomalies)

    def close(self, complete: bool = True) -> None:
        """Close the files; with ``complete``, every part must be in (a gap is a RuntimeError)."""
        for f in self._files.values():
            f.close()
        self._files = {}
        if complete and self._waiting:
            raise RuntimeError(f"parts {sorted(self._waiting)} came without part {self._next}")

    def __enter__(self) -> StreamedRows:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close(complete=exc[0] is None)  # a failed run's folder is thrown away


def write_downweighted_csv(path: Path, scene: Scene, tracks: TrackSet) -> None:
    """Every measurement the robust update down-weighted (weight < 1) or rejected (0): the
    keypoint (joint) or box edge (edge), its weight, its residual (px) and its score (its
    residual in standard deviations, judged against the other views)."""
    d = tracks.downweighted
    names = scene.rig.names
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(DOWNWEIGHTED_COLUMNS)
        if d is None:
            return
        order = np.lexsort((d.edge, d.joint, d.cam, d.track_id, d.frame))
        for i in order:
            w.writerow([int(d.frame[i]), names[int(d.cam[i])], int(d.track_id[i]),
                        "" if d.joint[i] < 0 else int(d.joint[i]),
                        "" if d.edge[i] < 0 else BOX_EDGES[int(d.edge[i])],
                        f"{d.weight[i]:.4f}", f"{d.residual_px[i]:.3f}", f"{d.score[i]:.3f}"])


def check_tracks(tracks: TrackSet) -> None:
    """Refuse to write a result with non-finite numbers (a numerical failure, never a result):
    raises ``FloatingPointError`` naming the first bad row."""
    a = np.column_stack([tracks.center_world, tracks.semi_axes, tracks.center_sd])
    bad = ~np.isfinite(a).all(axis=1)
    kb = np.isnan(tracks.kpt_world).any(axis=-1) != np.isnan(tracks.kpt_world).all(axis=-1)
    kb |= np.isinf(tracks.kpt_world).any(axis=-1)
    kb |= np.isfinite(tracks.kpt_world).all(axis=-1) & ~(tracks.kpt_sd >= 0)
    bad |= kb.any(axis=1)
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        raise FloatingPointError(
            f"the {tracks.info.estimator or 'estimator'} result has non-finite values in "
            f"{int(bad.sum())} rows (first: frame {int(tracks.frame[r])}, object "
            f"{int(tracks.track_id[r])}); nothing was written")


def write_anomalies_csv(path: Path, anomalies: AnomalyRows) -> None:
    """``frame,camera,id,joint,kind,score,detail`` (see :mod:`gt3dkit.qa.anomalies`)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(ANOMALY_COLUMNS)
        w.writerows(anomalies.rows)


def write_result_files(d: Path, scene: Scene, tracks: TrackSet, extra_meta: JsonDict | None = None,
                       anomalies: AnomalyRows | None = None, streamed: bool = False) -> None:
    """``tracks.csv``, ``keypoints.csv`` (with joints), ``anomalies.csv`` (when QA ran),
    ``segments.csv`` (when an id was split) and ``meta.json`` into folder ``d``; ``streamed``:
    the first three are there already (:class:`StreamedRows`)."""
    if not streamed:
        check_tracks(tracks)
        if anomalies is not None:
            write_anomalies_csv(d / "anomalies.csv", anomalies)
        write_tracks_csv(d / "tracks.csv", tracks)
        if tracks.kpt_world.shape[1]:
            write_keypoints_csv(d / "keypoints.csv", tracks)
    if scene.association is not None:
        scene.association.write(d / "association.csv")
    meta = meta_of(scene, tracks)
    if extra_meta:
        meta.update({k: _jsonable(v) for k, v in extra_meta.items()})
    if tracks.downweighted is not None:
        write_downweighted_csv(d / "downweighted.csv", scene, tracks)
    if tracks.info.segments:
        write_segments_csv(d / "segments.csv", tracks.info.segments)
    (d / "meta.json").write_text(json.dumps(_jsonable(meta), indent=2, allow_nan=False,
                                            default=_jsonable))


SEGMENT_COLUMNS = ("id", "segment", "first_frame", "last_frame", "rows")


def write_segments_csv(path: Path, segments: Sequence[Mapping[str, JsonValue]]) -> None:
    """``segments.csv``: the pieces an id was split into (:mod:`gt3dkit.fusion.preparation.identity`), each
    estimated on its own: which frames of the input's id each piece holds."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(SEGMENT_COLUMNS)
        w.writerows([s[k] for k in SEGMENT_COLUMNS] for s in segments)


def read_segments_csv(path: Path) -> tuple[tuple[int, int, int, int], ...]:
    """An edited ``segments.csv`` (:func:`write_segments_csv`; the ``rows`` column may be left as
    it is or empty): ``(id, segment, first_frame, last_frame)`` per piece, sorted by id and first
    frame; one id's pieces may not overlap."""
    path = Path(path)
    out = []
    for line, r in iter_csv_rows(path, SEGMENT_COLUMNS[:4], warnings=[]):
        where = f"{path}: line {line}"
        i = parse_int(where, r["id"], "id")
        seg = parse_int(where, r["segment"], "segment", 0)
        a, b = parse_frame(where, r["first_frame"]), parse_frame(where, r["last_frame"])
        if b < a:
            raise InputError(where, f"last_frame {b} is before first_frame {a}")
        out.append((i, seg, a, b, line))
    if not out:
        raise InputError(str(path), "no pieces (only a header)")
    out.sort(key=lambda p: (p[0], p[2]))
    for p, q in zip(out, out[1:], strict=False):
        if p[0] == q[0] and q[2] <= p[3]:
            raise InputError(f"{path}: line {q[4]}", f"id {q[0]}: frames {q[2]}-{q[3]} overlap the piece of "
                                                     f"line {p[4]} (frames {p[2]}-{p[3]})")
    return tuple(p[:4] for p in out)


def write_outputs(out: Path, scene: Scene, tracks: TrackSet,
                  extra_meta: JsonDict | None = None, anomalies: AnomalyRows | None = None) -> None:
    """Write ``OUT/tracks.csv`` (+ ``keypoints.csv``, ``anomalies.csv``) and ``OUT/meta.json``
    (all or nothing)."""
    write_dir_atomically(Path(out), lambda tmp: write_result_files(tmp, scene, tracks, extra_meta,
                                                                   anomalies))


def read_tracks_csv(path: Path) -> TrackSet:
    """Read a ``tracks.csv`` written by :func:`write_tracks_csv` (one row per frame and id,
    finite numbers, semi-axes and sds >= 0)."""
    path = Path(path)
    rows: list[list[float]] = []
    keys: dict[tuple[int, int], int] = {}
    views: list[int] = []
    columns = TRACK_COLUMNS + (("n_views",) if _header(path)[len(TRACK_COLUMNS):][:1] == ["n_views"] else ())
    for line, r in iter_csv_rows(path, columns):
        where = f"{path}: line {line}"
        key = (parse_frame(where, r["frame"]), parse_int(where, r["id"], "id"))
        if key in keys:
            raise InputError(where, f"second row for object {key[1]} in frame {key[0]} (first "
                                    f"on line {keys[key]})")
        keys[key] = line
        # positions and sizes are world lengths; an sd may be huge (a depth one view leaves open)
        vals = [parse_metres(where, r[k], k) for k in TRACK_COLUMNS[2:8]] + \
            [parse_float(where, r[k], f"{k} (m)") for k in TRACK_COLUMNS[8:]]
        if min(vals[3:]) < 0:
            raise InputError(where, "negative semi-axis or standard deviation")
        rows.append(vals)
        if len(columns) > len(TRACK_COLUMNS):
            views.append(parse_int(where, r["n_views"], "n_views"))
            if views[-1] < 0:
                raise InputError(where, f"n_views: {views[-1]} is negative")
    if not rows:
        raise InputError(str(path), "no tracks (only a header)")
    k = np.array(list(keys), dtype=np.int64).reshape(-1, 2)
    a = np.array(rows, dtype=np.float64).reshape(-1, len(TRACK_COLUMNS) - 2)
    n = len(a)
    return TrackSet(frame=k[:, 0], track_id=k[:, 1], center_world=a[:, 0:3], semi_axes=a[:, 3:6],
                    center_sd=a[:, 6:9],
                    n_views=np.array(views, dtype=np.int64) if views else np.full(n, -1, dtype=np.int64),
                    kpt_world=np.zeros((n, 0, 3)), kpt_sd=np.zeros((n, 0)),
                    info=RunInfo(details={"source": str(path)}))


def _header(path: Path) -> list[str]:
    """The first line of a CSV file as fields ([] when it cannot be read: the reader reports
    why)."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            return [x.strip() for x in next(csv.reader(f), [])]
    except (OSError, UnicodeDecodeError, csv.Error):
        return []


def read_keypoints_csv(path: Path, tracks: TrackSet, n_joints: int) -> TrackSet:
    """Attach ``keypoints.csv`` to tracks read by :func:`read_tracks_csv`."""
    import dataclasses

    path = Path(path)
    key = {(int(f), int(i)): r for r, (f, i) in enumerate(zip(tracks.frame, tracks.track_id,
                                                              strict=True))}
    kpt = np.full((len(tracks), n_joints, 3), np.nan)
    sd = np.full((len(tracks), n_joints), np.nan)
    for line, r in iter_csv_rows(path, KPT_COLUMNS):
        where = f"{path}: line {line}"
        fr, tid = parse_frame(where, r["frame"]), parse_int(where, r["id"], "id")
        j = parse_int(where, r["joint"], "joint", 0, max(n_joints - 1, 0))
        xyz = [parse_metres(where, r[k], k) for k in ("x", "y", "z")]
        s = parse_float(where, r["sd"], "sd (m)")
        if (fr, tid) not in key:
            raise InputError(where, f"object {tid} in frame {fr} has no row in tracks.csv")
        if np.isfinite(kpt[key[(fr, tid)], j]).all():
            raise InputError(where, f"second row for joint {j} of object {tid} in frame {fr}")
        if s < 0:
            raise InputError(where, "negative standard deviation")
        kpt[key[(fr, tid)], j] = xyz
        sd[key[(fr, tid)], j] = s
    return dataclasses.replace(tracks, kpt_world=kpt, kpt_sd=sd)


def write_refined_calibration(out: Path, scene: Scene, result: RefinedRig, fmt: str | None = None,
                              extra: dict[str, str] | None = None) -> None:
    """``OUT/cameras.json`` (the refined rig, with the scene's fps), ``OUT/calib_report.json``,
    with ``fmt`` ``OUT/calibration/`` in that format, and ``extra`` files (name -> text), all or
    nothing."""
    def write(tmp: Path) -> None:
        for name, text in (extra or {}).items():
            (tmp / name).write_text(text)
        write_native(result.rig, tmp / "cameras.json", fps=scene.fps)
        if fmt is not None and fmt != "native":
            write_calibration(result.rig, tmp / "calibration", fmt)
        doc = {"gt3dkit_version": __version__,
               "created_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
               "input": {"root": scene.root, "layout": scene.layout, "files_sha256": scene.files},
               **result.report}
        (tmp / "calib_report.json").write_text(json.dumps(_jsonable(doc), indent=2, allow_nan=False,
                                                          default=_jsonable))

    write_dir_atomically(Path(out), write)

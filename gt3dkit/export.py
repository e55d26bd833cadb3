"""``gt3d export OUT --format c3d|trc|json|rerun``: a reconstruct output in the formats other
tools read. Every file goes into one folder, written atomically.

* **C3D** (ezc3d): one file, every object's markers named ``<joint>`` (one object) or
  ``id<k>_<joint>`` (several; ``id<k>`` for box objects: the ellipsoid centre), millimetres,
  ``POINT:RATE`` from the input's frame rate and frame step, missing samples as C3D's invalid
  points (residual -1), each valid sample's residual = the estimate's sd in mm. The world frame
  is the input's (C3D prescribes none); ``GT3DKIT:UP`` and ``GT3DKIT:FRAME`` say what it is.
* **TRC** (OpenSim): one file per object (OpenSim scales one subject at a time), metres, the
  world rotated so that up is +Y as OpenSim expects (x along the body frame's first axis,
  z = x cross y); blank fields for missing markers. ``export.json`` records the rotation.
* **JSON**: ``tracks.json`` = a header (units, up, world frame, fps, skeleton and joints) and
  one record per frame with every object's centre, semi-axes, sds, keypoints and their sds.
* **Rerun** (rerun-sdk): ``tracks.rrd`` with the cameras (pinhole + pose), each camera's 2D
  annotations, the ellipsoids and skeletons with their sd over time, and the anomalies as a
  text log, on a ``frame`` timeline; ``rerun tracks.rrd`` opens it.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gt3dkit.api import load_run
from gt3dkit.arrays import frame_grid
from gt3dkit.calib.board import UNITS_M
from gt3dkit.errors import InputError
from gt3dkit.io.atomic import write_dir_atomically
from gt3dkit.io.jointmap import read_joint_map
from gt3dkit.io.results import Result, read_result
from gt3dkit.jsondoc import json_at, json_obj, json_str
from gt3dkit.skeletons import skeleton_of
from gt3dkit.types import F64, I64, JsonDict
from gt3dkit.viz.overview import colour_of


def markers(res: Result) -> tuple[list[str], I64, F64, F64, list[int]]:
    """Marker names, the frame grid (N,), positions (N, M, 3) m and sds (N, M) m (NaN where
    missing), and the object id of each marker."""
    tr = res.tracks
    grid, _ = frame_grid(tr.frame)
    ids = [int(i) for i in np.unique(tr.track_id)]
    joints = res.marker_names if tr.kpt_world.shape[1] else ()
    per = list(joints) if joints else ["centre"]
    names, owner = [], []
    for i in ids:
        for j in per:
            names.append(j if len(ids) == 1 and joints else (f"id{i}_{j}" if joints else f"id{i}"))
            owner.append(i)
    N, M, J = len(grid), len(names), len(per)
    X = np.full((N, M, 3), np.nan)
    S = np.full((N, M), np.nan)
    t = np.searchsorted(grid, tr.frame)
    o = np.searchsorted(np.array(ids), tr.track_id)
    for k in range(len(tr)):
        sl = slice(o[k] * J, (o[k] + 1) * J)
        if joints:
            X[t[k], sl] = tr.kpt_world[k]
            S[t[k], sl] = tr.kpt_sd[k]
        else:
            X[t[k], sl] = tr.center_world[k]
            S[t[k], sl] = tr.center_sd[k].max()
    return names, grid, X, S, owner


def rate_of(res: Result) -> float:
    """Samples per second of the frame grid."""
    _, step = frame_grid(res.tracks.frame)
    if not res.fps > 0:
        raise InputError(str(res.out / "meta.json"), "input.fps: no frame rate recorded")
    return res.fps / step


def y_up_rotation(up: F64, world_from_body: F64) -> F64:
    """(3, 3) rotation taking world coordinates to OpenSim's: y = up, x = the body frame's
    first axis (horizontal), z = x cross y."""
    y = up / np.linalg.norm(up)
    x = world_from_body[:, 0] - (world_from_body[:, 0] @ y) * y
    x /= np.linalg.norm(x)
    return np.stack([x, y, np.cross(x, y)])


def _frame_info(res: Result) -> tuple[F64, F64, str]:
    fr = json_obj(res.meta, "frame")
    up = np.asarray(fr.get("up", [0, 0, 1]), dtype=np.float64)
    axes = json_obj(fr, "semi_axes")
    wfb = np.stack([np.asarray(axes.get(k, d), dtype=np.float64) for k, d in
                    (("a", [1, 0, 0]), ("b", [0, 1, 0]), ("c", list(up)))], axis=1)
    return up, wfb, str(fr.get("name", ""))


def write_c3d(res: Result, path: Path) -> JsonDict:
    import ezc3d

    names, grid, X, S, _ = markers(res)
    up, _, frame_name = _frame_info(res)
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate_of(res)]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(names)
    c["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = tuple("gt3dkit estimate, sd in residual (mm)"
                                                              for _ in names)
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    pts = np.ones((4, len(names), len(grid)))
    pts[:3] = np.transpose(X, (2, 1, 0)) * 1000.0
    pts[:, ~np.isfinite(pts[:3]).all(axis=0)] = np.nan
    c["data"]["points"] = pts
    resid = np.where(np.isfinite(S), S * 1000.0, -1.0).T[None]
    resid[:, ~np.isfinite(pts[:3]).all(axis=0)] = -1.0
    c["data"]["meta_points"]["residuals"] = resid
    c.add_parameter("GT3DKIT", "UP", [float(v) for v in up])
    c.add_parameter("GT3DKIT", "FRAME", [frame_name or "input world frame"])
    c.add_parameter("GT3DKIT", "FIRST_FRAME", [int(grid[0])])
    c.write(str(path))
    return {"file": path.name, "markers": len(names), "samples": len(grid), "units": "mm",
            "rate_hz": rate_of(res), "world": "the input's world frame (C3D prescribes none); "
            f"up = {up.tolist()} (GT3DKIT:UP)", "first_frame": int(grid[0])}


def write_trc(res: Result, folder: Path) -> JsonDict:
    names, grid, X, _, owner = markers(res)
    up, wfb, _ = _frame_info(res)
    R = y_up_rotation(up, wfb)
    rate = rate_of(res)
    files = []
    for i in sorted(set(owner)):
        cols = [k for k, o in enumerate(owner) if o == i]
        label = [names[k].split("_", 1)[1] if names[k].startswith(f"id{i}_") else names[k] for k in cols]
        Y = X[:, cols] @ R.T  # (N, m, 3)
        name = f"id{i}.trc"
        lines = [f"PathFileType\t4\t(X/Y/Z)\t{name}",
                 "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\t"
                 "OrigNumFrames",
                 f"{rate:g}\t{rate:g}\t{len(grid)}\t{len(cols)}\tm\t{rate:g}\t1\t{len(grid)}",
                 "Frame#\tTime\t" + "\t\t\t".join(label) + "\t\t",
                 "\t\t" + "\t".join(f"X{k + 1}\tY{k + 1}\tZ{k + 1}" for k in range(len(cols)))]
        for n in range(len(grid)):
            vals = [("" if not np.isfinite(v) else f"{v:.6f}") for v in Y[n].ravel()]
            lines.append(f"{n + 1}\t{n / rate:.6f}\t" + "\t".join(vals))
        (folder / name).write_text("\n".join(lines) + "\n")
        files.append(name)
    return {"files": files, "units": "m", "rate_hz": rate, "world": "rotated so that up is +Y "
            "(OpenSim): trc = R @ world", "R": R.tolist(), "first_frame": int(grid[0])}


def write_anipose(res: Result, folder: Path) -> JsonDict:
    """anipose's ``points3d`` CSV (``anipose triangulate``'s output, which its downstream tools
    read): a row per frame, per joint ``{joint}_x, _y, _z``, ``_error`` (empty: the run keeps no
    per-joint reprojection), ``_ncams`` (the cameras that saw the object in that frame; empty
    where the run wrote none), ``_score`` (1 where estimated, 0 where not), then ``M_00 .. M_22``
    (the identity: the world is gt3dkit's), ``center_0 .. 2`` (0) and ``fnum``; one file per id
    (``points3d.csv`` for one). The positions are in the units of the calibration the run read:
    millimetres or centimetres where it was given with ``--calib-units`` (as anipose's own
    triangulation writes them beside that ``calibration.toml``), else metres."""
    tr = res.tracks
    if not tr.kpt_world.shape[1]:
        raise InputError("--format", "anipose's points3d holds joints: this run has none")
    names, grid, X, _, owner = markers(res)
    ids = sorted(set(owner))
    views = np.zeros((len(ids), len(grid)))
    t = np.searchsorted(grid, tr.frame)
    views[np.searchsorted(np.array(ids), tr.track_id), t] = tr.n_views
    joints = list(res.marker_names)
    given = json_str(res.meta, "input", "load", "calib_units")
    units = given if given in ("mm", "cm") else "m"
    X = X / UNITS_M[units]
    files = []
    for k, i in enumerate(ids):
        cols = [m for m, o in enumerate(owner) if o == i]
        head = [f"{j}_{c}" for j in joints for c in ("x", "y", "z", "error", "ncams", "score")]
        head += [f"M_{a}{b}" for a in range(3) for b in range(3)]
        head += [f"center_{a}" for a in range(3)] + ["fnum"]
        lines = [",".join(head)]
        for n in range(len(grid)):
            row: list[str] = []
            for m in cols:
                seen = bool(np.isfinite(X[n, m]).all())
                row += [f"{v:.6f}" if seen else "" for v in X[n, m]]
                known = seen and views[k, n] >= 0  # (tracks.csv has n_views with --every-frame only)
                row += ["", f"{int(views[k, n])}" if known else "" if seen else "0", "1" if seen else "0"]
            row += ["1", "0", "0", "0", "1", "0", "0", "0", "1", "0", "0", "0", str(int(grid[n]))]
            lines.append(",".join(row))
        name = "points3d.csv" if len(ids) == 1 else f"points3d_id{i}.csv"
        (folder / name).write_text("\n".join(lines) + "\n")
        files.append(name)
    where = "" if units == "m" else f", in the calibration's own units (--calib-units {units})"
    return {"files": files, "units": units, "world": f"gt3dkit's (M the identity, center 0){where}",
            "note": "_error is left empty (gt3dkit keeps each joint's sd in keypoints.csv, not a "
                    "reprojection error); _ncams counts the cameras that saw the animal in that frame"}


def write_json(res: Result, path: Path) -> JsonDict:
    tr = res.tracks
    up, wfb, frame_name = _frame_info(res)
    joints = res.joints if tr.kpt_world.shape[1] else ()

    def num(a: np.ndarray) -> list[float | None]:
        return [None if not np.isfinite(v) else round(float(v), 6) for v in np.ravel(a)]

    frames = []
    order = np.lexsort((tr.track_id, tr.frame))
    for f in np.unique(tr.frame):
        objs = []
        for k in order[tr.frame[order] == f]:
            o: JsonDict = {"id": int(tr.track_id[k]), "centre": num(tr.center_world[k]),
                                 "semi_axes": num(tr.semi_axes[k]), "centre_sd": num(tr.center_sd[k])}
            if joints:
                o["keypoints"] = [None if not np.isfinite(x).all() else num(x) for x in tr.kpt_world[k]]
                o["keypoint_sd"] = num(tr.kpt_sd[k])
            objs.append(o)
        frames.append({"frame": int(f), "time_s": float(f) / res.fps if res.fps > 0 else None,
                       "objects": objs})
    doc = {"header": {"generator": "gt3dkit", "units": "m", "up": up.tolist(), "world": frame_name,
                      "semi_axes_directions": {"a": wfb[:, 0].tolist(), "b": wfb[:, 1].tolist(),
                                               "c": wfb[:, 2].tolist()},
                      "fps": res.fps, "skeleton": json_at(res.meta, "frame", "skeleton"),
                      "joints": list(joints), "marker_names": list(res.marker_names if joints else ()),
                      "sd": "centre_sd: per world axis (see meta.json frame.sd); keypoint_sd: the joint's "
                            "largest sd over all directions", "source": str(res.out)},
           "frames": frames}
    path.write_text(json.dumps(doc, allow_nan=False))
    return {"file": path.name, "frames": len(frames), "units": "m"}


def write_rerun(res: Result, path: Path) -> JsonDict:
    import rerun as rr


    run = load_run(res.out, "the Rerun recording shows the annotations in every camera")
    sc, tr = run.scene, run.tracks
    up, wfb, _ = _frame_info(res)
    rec = rr.RecordingStream("gt3dkit", recording_id=f"gt3dkit-{res.out.resolve()}")
    rec.save(str(path))
    ax = int(np.argmax(np.abs(up)))
    coords = {(2, 1): rr.ViewCoordinates.RIGHT_HAND_Z_UP, (2, -1): rr.ViewCoordinates.RIGHT_HAND_Z_DOWN,
              (1, 1): rr.ViewCoordinates.RIGHT_HAND_Y_UP, (1, -1): rr.ViewCoordinates.RIGHT_HAND_Y_DOWN,
              (0, 1): rr.ViewCoordinates.RIGHT_HAND_X_UP, (0, -1): rr.ViewCoordinates.RIGHT_HAND_X_DOWN}
    if abs(up[ax]) > 0.99:
        rec.log("world", coords[(ax, int(np.sign(up[ax])))], static=True)
    from scipy.spatial.transform import Rotation

    quat = rr.Quaternion(xyzw=Rotation.from_matrix(wfb).as_quat())  # body axes -> world
    for c in sc.rig.cameras:
        base = f"world/cameras/{c.name}"
        rec.log(base, rr.Transform3D(translation=c.center_world, mat3x3=c.R.T), static=True)
        rec.log(f"{base}/image", rr.Pinhole(image_from_camera=c.K, resolution=[c.width, c.height],
                                            camera_xyz=rr.ViewCoordinates.RDF), static=True)
    obs = sc.obs
    names = sc.rig.names

    skel = skeleton_of(sc)
    bones = [(int(a), int(b)) for a, b in skel.bones] if skel is not None else []
    frames = np.unique(np.concatenate([tr.frame, obs.frame]))
    for f in frames:
        rec.set_time("frame", sequence=int(f))
        if sc.fps > 0:
            rec.set_time("time", duration=float(f) / sc.fps)
        m = np.flatnonzero(tr.frame == f)
        if len(m):
            cols = [colour_of(i) for i in tr.track_id[m]]
            rec.log("world/ellipsoids", rr.Ellipsoids3D(
                centers=tr.center_world[m], half_sizes=tr.semi_axes[m], quaternions=[quat] * len(m),
                colors=cols, labels=[str(int(i)) for i in tr.track_id[m]]))
            for k in m:
                tid = int(tr.track_id[k])
                rec.log(f"sd/centre_mm/id{tid}", rr.Scalars(1000.0 * float(tr.center_sd[k].max())))
                if tr.kpt_world.shape[1] and np.isfinite(tr.kpt_world[k]).any():
                    X = tr.kpt_world[k]
                    ok = np.isfinite(X).all(axis=1)
                    rec.log(f"world/skeletons/id{tid}", rr.Points3D(
                        X[ok], radii=np.clip(np.nan_to_num(tr.kpt_sd[k][ok], nan=0.01), 0.005, 0.2),
                        colors=colour_of(tid)))
                    strips = [X[[a, b]] for a, b in bones if ok[a] and ok[b]]
                    if strips:
                        rec.log(f"world/skeletons/id{tid}/bones",
                                rr.LineStrips3D(strips, colors=colour_of(tid)))
        o = np.flatnonzero(obs.frame == f)
        for ci, cam in enumerate(names):
            oc = o[obs.cam[o] == ci]
            if not len(oc):
                continue
            base = f"world/cameras/{cam}/image"
            hb = oc[obs.has_box[oc]]
            if len(hb):
                rec.log(f"{base}/boxes", rr.Boxes2D(
                    array=obs.box_xyxy_px[hb], array_format=rr.Box2DFormat.XYXY,
                    colors=[colour_of(i) for i in obs.track_id[hb]],
                    labels=[str(int(i)) for i in obs.track_id[hb]]))
            if obs.n_joints:
                pts = obs.kpt_uv_px[oc].reshape(-1, 2)
                ids = np.repeat(obs.track_id[oc], obs.n_joints)
                ok = np.isfinite(pts).all(axis=1)
                if ok.any():
                    rec.log(f"{base}/keypoints", rr.Points2D(pts[ok], colors=[colour_of(i) for i in ids[ok]],
                                                             radii=3.0))
    for r in run.anomalies:
        rec.set_time("frame", sequence=int(r["frame"]))
        text = (f"{r['kind']} camera {r['camera'] or '-'} id {r['id'] or '-'} joint {r['joint'] or '-'}: "
                f"{r['detail']}")
        rec.log("anomalies", rr.TextLog(text, level=rr.TextLogLevel.WARN))
    rec.flush()
    rec.disconnect()
    return {"file": path.name, "frames": len(frames), "cameras": len(names), "anomalies": len(run.anomalies),
            "open with": f"rerun {path.name}", "notes": list(run.notes)}


@dataclass(frozen=True)
class Exporter:
    """An export format: ``write(result, folder)`` (returns what it wrote), and whether it
    writes the result's joints as given (so a ``--joint-map`` can change them); the Rerun
    recording draws the run with its input, the detector's skeleton and its bones."""

    write: Callable[[Result, Path], JsonDict]
    maps_joints: bool = True


#: Every export format, registered once (the command line's choices and :func:`export` read it).
EXPORTERS: dict[str, Exporter] = {
    "c3d": Exporter(lambda res, tmp: write_c3d(res, tmp / "tracks.c3d")),
    "trc": Exporter(write_trc),
    "anipose": Exporter(write_anipose),
    "json": Exporter(lambda res, tmp: write_json(res, tmp / "tracks.json")),
    "rerun": Exporter(lambda res, tmp: write_rerun(res, tmp / "tracks.rrd"), maps_joints=False),
}
FORMATS = tuple(EXPORTERS)


def mapped(res: Result, path: Path) -> tuple[Result, JsonDict]:
    """``res`` with its joints mapped by the user's joint map in ``path``
    (:mod:`gt3dkit.io.jointmap`): the output joints as the run's joints and markers, and what
    ``export.json`` says of the map."""
    tr = res.tracks
    frame = json_obj(res.meta, "frame")
    skeleton = frame.get("skeleton")
    if not tr.kpt_world.shape[1]:
        raise InputError("--joint-map", "the run has no keypoints to map")
    jm = read_joint_map(path, skeleton if isinstance(skeleton, str) else None, res.joints, res.marker_names)
    X, sd = jm.apply(tr.kpt_world, tr.kpt_sd)
    meta = {**res.meta, "frame": {**frame, "skeleton": jm.name, "joints": list(jm.names)}}
    info: JsonDict = {"joint_map": {"file": str(Path(path).resolve()), "sha256": jm.sha256, "name": jm.name,
                                    "from": skeleton, "joints": list(jm.names),
                                    "applied_by": "gt3d export --joint-map (the run's keypoints.csv keeps "
                                                  "the detector's joints)"}}
    return dataclasses.replace(res, meta=meta, tracks=dataclasses.replace(tr, kpt_world=X, kpt_sd=sd)), info


def export(out: Path, fmt: str, dest: Path, joint_map: Path | None = None) -> JsonDict:
    """Export the reconstruct output ``out`` as ``fmt`` into the folder ``dest`` (atomically),
    its joints mapped by the user's ``joint_map`` file when given (:func:`mapped`); returns what
    was written (also in ``dest/export.json``)."""
    if fmt not in FORMATS:
        raise InputError("--format", f"unknown format {fmt!r} (known: {', '.join(FORMATS)})")
    res = read_result(Path(out))
    info: JsonDict = {}
    if joint_map is not None:
        if not EXPORTERS[fmt].maps_joints:
            can = ", ".join(k for k, v in EXPORTERS.items() if v.maps_joints)
            raise InputError("--joint-map", f"{fmt} draws the run with its input and the detector's "
                                            f"skeleton: a joint map applies to {can}")
        res, info = mapped(res, Path(joint_map))

    def write(tmp: Path) -> None:
        info.update(EXPORTERS[fmt].write(res, tmp))
        info.update({"format": fmt, "source": str(Path(out).resolve())})
        (tmp / "export.json").write_text(json.dumps(info, indent=1))

    write_dir_atomically(Path(dest), write, "--to")
    return info

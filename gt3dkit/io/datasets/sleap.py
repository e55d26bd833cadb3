"""SLEAP's analysis export, one file per camera (``File > Export Analysis HDF5`` or
``sleap-convert --format analysis``), as an anipose + SLEAP project keeps it::

    calibration.toml                   # or any calibration beside the folders (--calib)
    <camera>/<anything>.analysis.h5    # one folder per camera, named as the calibration names it

Each file holds (h5py reads them as stored; MATLAB reads them transposed):

    tracks        (n_tracks, 2, n_nodes, n_frames)  x, y in pixels; NaN where not labelled
    point_scores  (n_tracks, n_nodes, n_frames)     the model's score; NaN for a person's label
    track_names   (n_tracks,)                       SLEAP's tracks of this camera
    node_names    (n_nodes,), edge_names (n_edges, 2)  the skeleton

The skeleton is the files' own (every camera's must be the same): its nodes the joints, its
edges the bones, and the left/right pairs its names say (``Ear_L``/``Ear_R``,
``Shoulder_left``/``Shoulder_right``, ``LEye``/``REye``) where their bones mirror each other.
A track is an identity of its camera only: the animals are found across cameras frame by frame
from their keypoints (:func:`gt3dkit.fusion.preparation.detections.associate_detections`). A
score is read as the detector's confidence; a person's label (no score) as 1. The frame rate
is the calibration's, ``--fps``, else 30 (said).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.io.datasets.common import JointBlock, RowBuilder
from gt3dkit.io.datasets.mot import calibration_beside, match_cameras
from gt3dkit.parse import read_hashed
from gt3dkit.skeletons import skeleton_from_doc
from gt3dkit.types import JsonDict, Scene

SUFFIX = ".analysis.h5"
DEFAULT_FPS = 30.0
#: name pairs that say left and right (either order; case as written)
_SIDES = (("_L", "_R"), ("_left", "_right"), ("_Left", "_Right"), ("Left", "Right"), ("left", "right"))


def found(root: Path) -> bool:
    """A folder with a camera folder holding a SLEAP analysis file."""
    return any(root.glob(f"*/*{SUFFIX}"))


def _files(root: Path) -> dict[str, Path]:
    """Camera folder name -> its one analysis file."""
    out: dict[str, Path] = {}
    for p in sorted(root.glob(f"*/*{SUFFIX}")):
        cam = p.parent.name
        if cam in out:
            raise InputError(str(p), f"a second SLEAP analysis file in {cam}/ (first: {out[cam].name}): "
                                     "one file per camera")
        out[cam] = p
    return out


def _names(raw: object) -> list[str]:
    return [x.decode() if isinstance(x, bytes) else str(x) for x in np.asarray(raw).reshape(-1)]


def side_pairs(joints: list[str], bones: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """The left/right pairs the joints' names say (``_L``/``_R``, ``_left``/``_right``,
    ``Left``/``Right``, ``LEye``/``REye``), kept where the two joints' bones mirror each other (a
    pair the names suggest but the bones deny is no pair)."""
    have = set(joints)

    def partner(j: str) -> str | None:
        for left, right in _SIDES:
            if left in j and j.replace(left, right, 1) in have:
                return j.replace(left, right, 1)
        if len(j) > 1 and j[0] == "L" and j[1].isupper() and "R" + j[1:] in have:
            return "R" + j[1:]
        return None

    pairs: list[tuple[str, str]] = []
    for j in joints:
        other = partner(j)
        if other is None or any(j in p or other in p for p in pairs):
            continue
        try:
            skeleton_from_doc({"name": "pair", "joints": joints, "bones": [list(b) for b in bones],
                               "pairs": [[j, other]]}, "")
        except InputError:
            continue
        pairs.append((j, other))
    return pairs


def _read(path: Path) -> tuple[np.ndarray, np.ndarray, list[str], list[str], list[tuple[str, str]], str]:
    """One analysis file: ``tracks (T, 2, J, F)``, ``scores (T, J, F)``, the track names, the
    node names, the edges and the file's SHA-256 (read once: hashed as it is read)."""
    import h5py

    raw, digest = read_hashed(path)  # read once: hashed, then opened from memory
    try:
        with h5py.File(io.BytesIO(raw), "r") as f:
            missing = [k for k in ("tracks", "node_names") if k not in f]
            if missing:
                raise InputError(str(path), f"not a SLEAP analysis file (no {missing[0]!r})")
            tracks = np.asarray(f["tracks"][()], dtype=np.float64)
            nodes = _names(f["node_names"][()])
            scores = (np.asarray(f["point_scores"][()], dtype=np.float64) if "point_scores" in f
                      else np.full((tracks.shape[0],) + tracks.shape[2:], np.nan))
            track_names = _names(f["track_names"][()]) if "track_names" in f else []
            edges_raw = np.asarray(f["edge_names"][()]) if "edge_names" in f else np.zeros((0, 2))
    except OSError as e:
        raise InputError(str(path), f"not an HDF5 file ({e})") from None
    if tracks.ndim != 4 or tracks.shape[1] != 2 or tracks.shape[2] != len(nodes):
        raise InputError(f"{path}: tracks", f"expected (tracks, 2, {len(nodes)} nodes, frames), got "
                                            f"{tracks.shape}")
    if scores.shape != (tracks.shape[0],) + tracks.shape[2:]:
        raise InputError(f"{path}: point_scores", f"expected {(tracks.shape[0],) + tracks.shape[2:]}, got "
                                                  f"{scores.shape}")
    edges = [tuple(_names(e)) for e in edges_raw.reshape(-1, 2)] if edges_raw.size else []
    return tracks, scores, track_names, nodes, [(a, b) for a, b in edges], digest


def load(root: Path, calib: Path | str | None = None, fps: float | None = None) -> Scene:
    root = Path(root)
    rig, fps_doc, cal = calibration_beside(root, calib)
    files_of = _files(root)
    warnings: list[str] = []
    cam_of = match_cameras(list(files_of), rig, str(root), warnings)
    digests: dict[str, str] = {}
    above = dropped = 0
    first: tuple[Path, list[str], list[tuple[str, str]]] | None = None
    rb: RowBuilder | None = None
    for name, path in files_of.items():
        tracks, scores, _, nodes, edges, digest = _read(path)
        digests[str(path.relative_to(root))] = digest
        if first is None:
            first = (path, nodes, edges)
            rb = RowBuilder(n_joints=len(nodes))
        elif (nodes, sorted(map(sorted, edges))) != (first[1], sorted(map(sorted, first[2]))):
            raise InputError(str(path), f"its skeleton differs from {first[0]}'s (nodes or edges)")
        T, _, J, F = tracks.shape
        uv = np.transpose(tracks, (0, 3, 2, 1)).reshape(T * F, J, 2)  # (track, frame) rows
        conf = np.transpose(scores, (0, 2, 1)).reshape(T * F, J)
        conf = np.where(np.isfinite(conf), conf, 1.0)  # a person's label has no score
        labelled = np.isfinite(uv).all(axis=2)
        dropped += int(np.sum(labelled & (conf <= 0)))
        above += int(np.sum(labelled & (conf > 1)))
        seen = labelled & (conf > 0)
        keep = seen.any(axis=1)
        uv = np.where(seen[..., None], uv, np.nan)[keep]
        conf = np.minimum(conf, 1.0)[keep]
        track = np.repeat(np.arange(T), F)[keep]
        frame = np.tile(np.arange(F), T)[keep]
        if rb is not None and len(frame):
            rb.add_joint_block(_block(frame, cam_of[name], track, uv, conf, str(path)))
    if first is None or rb is None:
        raise InputError(str(root), f"no SLEAP analysis file (<camera>/*{SUFFIX})")
    obs = rb.build()
    if len(obs) == 0:
        raise InputError(str(root), "no labelled keypoints in any SLEAP file")
    nodes, edges = first[1], first[2]
    doc: JsonDict = {"name": "sleap", "joints": nodes, "bones": [list(e) for e in edges],
                     "pairs": [list(p) for p in side_pairs(nodes, edges)]}
    skeleton_from_doc(doc, str(first[0]))  # checked as a skeleton file is
    rate = fps or fps_doc
    files = {f"calibration:{cal.name}": "folder" if cal.is_dir() else read_hashed(cal)[1], **digests}
    if above:
        warnings.append(f"{above} SLEAP scores above 1 read as 1")
    if dropped:
        warnings.append(f"{dropped} keypoints scored 0 or below left out")
    return Scene(rig=rig, obs=obs, layout="sleap", fps=float(rate or DEFAULT_FPS),
                 frames=np.unique(obs.frame), skeleton="sleap", skeleton_doc=doc, files=files, root=str(root),
                 warnings=tuple(warnings),
                 fps_assumed="" if rate else f"{cal.name} and the SLEAP files give no frame rate",
                 association="detections")


def _block(frame: np.ndarray, cam: int, track: np.ndarray, uv: np.ndarray, conf: np.ndarray,
           where: str) -> JointBlock:
    """The keypoints of one camera as rows ``(frame, camera, track, joint)``."""
    N, J = conf.shape
    seen = np.isfinite(uv[..., 0])
    n, j = np.nonzero(seen)
    return JointBlock(frame[n].astype(np.int64), np.full(len(n), cam, np.int64), track[n].astype(np.int64),
                      j.astype(np.int64), uv[n, j], conf[n, j], np.zeros(len(n), np.int64), where)


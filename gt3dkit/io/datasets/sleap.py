"""SLEAP's labels, one file per camera, as an anipose + SLEAP project keeps them::

    calibration.toml                   # or any calibration beside the folders (--calib)
    <camera>/<anything>.slp            # one folder per camera, named as the calibration names it
    <camera>/<anything>.analysis.h5    # or SLEAP's analysis export of it

A ``.slp`` (SLEAP's own project or predictions file, one video) is read with ``sleap-io``
(``pip install 'gt3dkit[sleap]'``): its user instances where a person labelled the frame, else
its predictions, with their scores; its skeleton's symmetries are the left/right pairs. Where a
folder has both, the ``.slp`` is read. Without ``sleap-io`` the analysis file beside it is read
(said), and a ``.slp`` alone is an error that says what to install.

An analysis file (``File > Export Analysis HDF5`` or ``sleap-convert --format analysis``) holds
(h5py reads them as stored; MATLAB reads them transposed):

    tracks        (n_tracks, 2, n_nodes, n_frames)  x, y in pixels; NaN where not labelled
    point_scores  (n_tracks, n_nodes, n_frames)     the model's score; NaN for a person's label
    track_names   (n_tracks,)                       SLEAP's tracks of this camera
    node_names    (n_nodes,), edge_names (n_edges, 2)  the skeleton

The skeleton is the files' own (every camera's must be the same): its nodes the joints, its
edges the bones, and the left/right pairs the ``.slp`` declares, else those its names say
(``Ear_L``/``Ear_R``, ``Shoulder_left``/``Shoulder_right``, ``LEye``/``REye``), where their bones
mirror each other.
A track is an identity of its camera only: the animals are found across cameras frame by frame
from their keypoints (:func:`gt3dkit.fusion.preparation.detections.associate_detections`). A
score is read as the detector's confidence; a person's label (no score) as 1. The frame rate
is the calibration's, ``--fps``, else 30 (said).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.io.datasets.common import JointBlock, RowBuilder
from gt3dkit.io.datasets.dlc import body_skeleton
from gt3dkit.io.datasets.mot import calibration_beside, match_cameras
from gt3dkit.parse import read_hashed
from gt3dkit.skeletons import skeleton_from_doc, unmirrored
from gt3dkit.types import JsonDict, Scene

SUFFIX = ".analysis.h5"
SLP = ".slp"
DEFAULT_FPS = 30.0
#: name pairs that say left and right (either order; case as written)
_SIDES = (("_L", "_R"), ("_left", "_right"), ("_Left", "_Right"), ("Left", "Right"), ("left", "right"))


def found(root: Path) -> bool:
    """A folder with a camera folder holding a SLEAP file (``.slp`` or analysis ``.h5``)."""
    return any(root.glob(f"*/*{SUFFIX}")) or any(root.glob(f"*/*{SLP}"))


def _have_sleap_io() -> bool:
    import importlib.util

    return importlib.util.find_spec("sleap_io") is not None


def _one_per_camera(paths: list[Path], what: str) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for p in paths:
        cam = p.parent.name
        if cam in out:
            raise InputError(str(p), f"a second SLEAP {what} in {cam}/ (first: {out[cam].name}): "
                                     "one file per camera")
        out[cam] = p
    return out


def _files(root: Path, warnings: list[str]) -> dict[str, Path]:
    """Camera folder name -> its one SLEAP file: the ``.slp`` where there is one (and
    ``sleap-io`` to read it), else the analysis file."""
    slp = _one_per_camera(sorted(root.glob(f"*/*{SLP}")), f"labels file ({SLP})")
    analysis = _one_per_camera(sorted(root.glob(f"*/*{SUFFIX}")), "analysis file")
    if slp and not _have_sleap_io():
        alone = [p for cam, p in slp.items() if cam not in analysis]
        if alone:
            raise InputError(str(alone[0]), "reading SLEAP's .slp needs sleap-io: "
                                            f"pip install 'gt3dkit[sleap]' (or export it as {SUFFIX})")
        warnings.append(f"sleap-io is not installed: read the {SUFFIX} files beside the .slp files")
        slp = {}
    return {cam: slp.get(cam) or analysis[cam] for cam in sorted(set(slp) | set(analysis))}


def _names(raw: object) -> list[str]:
    return [x.decode() if isinstance(x, bytes) else str(x) for x in np.asarray(raw).reshape(-1)]


def side_pairs(joints: list[str], bones: list[tuple[str, str]],
               declared: list[tuple[str, str]] | None = None) -> list[tuple[str, str]]:
    """The left/right pairs: those ``declared`` (a ``.slp``'s symmetries), else those the joints'
    names say (``_L``/``_R``, ``_left``/``_right``, ``Left``/``Right``, ``LEye``/``REye``); kept
    where the two joints' bones mirror each other (a pair the names suggest but the bones deny is
    no pair)."""
    have = set(joints)

    def partner(j: str) -> str | None:
        for left, right in _SIDES:
            if left in j and j.replace(left, right, 1) in have:
                return j.replace(left, right, 1)
        if len(j) > 1 and j[0] == "L" and j[1].isupper() and "R" + j[1:] in have:
            return "R" + j[1:]
        return None

    candidates = declared if declared is not None else [
        (j, other) for j in joints if (other := partner(j)) is not None]
    pairs: list[tuple[str, str]] = []
    for j, other in candidates:  # each joint in one pair at most, both joints the skeleton's
        if j != other and {j, other} <= have and not any(j in p or other in p for p in pairs):
            pairs.append((j, other))
    while bad := unmirrored(bones, pairs):  # a pair whose bones deny it goes, then the rest again
        pairs = [p for k, p in enumerate(pairs) if k not in bad]
    return pairs


@dataclass(frozen=True)
class _SleapFile:
    """One camera's SLEAP labels, as the analysis export lays them out."""

    tracks: np.ndarray  # (T, 2, J, F) x, y in pixels; NaN where not labelled
    scores: np.ndarray  # (T, J, F) the score; NaN for a person's label
    nodes: list[str]
    edges: list[tuple[str, str]]
    pairs: list[tuple[str, str]] | None  # the file's declared left/right pairs; None: not declared
    digest: str  # the file's SHA-256


def _read(path: Path) -> _SleapFile:
    """One camera's file, read once: hashed, then parsed from memory."""
    raw, digest = read_hashed(path)
    if path.name.endswith(SLP):
        return _read_slp(path, raw, digest)
    return _read_analysis(path, raw, digest)


def _read_slp(path: Path, raw: bytes, digest: str) -> _SleapFile:
    """A ``.slp`` through ``sleap-io``: ``Labels.numpy`` (user instances preferred, a user
    label scored 1), tracked instances only where the file has tracks."""
    import sleap_io

    try:
        labels = sleap_io.load_slp(io.BytesIO(raw), open_videos=False)
    except (OSError, KeyError, ValueError) as e:
        raise InputError(str(path), f"not a SLEAP labels file ({e})") from None
    if len(labels.videos) != 1:
        raise InputError(str(path), f"{len(labels.videos)} videos in one file: one camera's video per file")
    if not labels.skeletons:
        raise InputError(str(path), "no skeleton")
    sk = labels.skeletons[-1]
    nodes = [str(n) for n in sk.node_names]
    if not labels.labeled_frames:
        arr = np.full((0, 1, len(nodes), 3), np.nan)
    else:
        arr = np.asarray(labels.numpy(video=0, untracked=not labels.tracks, return_confidence=True),
                         dtype=np.float64)  # (F, T, J, 3)
    tracks = np.transpose(arr[..., :2], (1, 3, 2, 0))
    scores = np.transpose(arr[..., 2], (1, 2, 0))
    edges = [(str(a), str(b)) for a, b in sk.edge_names]
    pairs = [(str(a), str(b)) for a, b in sk.symmetry_names]
    return _SleapFile(tracks, scores, nodes, edges, pairs or None, digest)


def _read_analysis(path: Path, raw: bytes, digest: str) -> _SleapFile:
    """One analysis file: ``tracks (T, 2, J, F)``, ``point_scores (T, J, F)``, the node names
    and the edges."""
    import h5py

    try:
        with h5py.File(io.BytesIO(raw), "r") as f:
            missing = [k for k in ("tracks", "node_names") if k not in f]
            if missing:
                raise InputError(str(path), f"not a SLEAP analysis file (no {missing[0]!r})")
            tracks = np.asarray(f["tracks"][()], dtype=np.float64)
            nodes = _names(f["node_names"][()])
            scores = (np.asarray(f["point_scores"][()], dtype=np.float64) if "point_scores" in f
                      else np.full((tracks.shape[0],) + tracks.shape[2:], np.nan))
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
    return _SleapFile(tracks, scores, nodes, [(a, b) for a, b in edges], None, digest)


def load(root: Path, calib: Path | str | None = None, fps: float | None = None, skeleton: str | None = None
         ) -> Scene:
    """The SLEAP files of ``root``'s camera folders; their own skeleton, or ``skeleton`` (a name or
    a file, ``--skeleton``) where given: one of the same nodes (in any order) that adds what SLEAP
    cannot say, such as up, the floor and rigid groups."""
    root = Path(root)
    rig, fps_doc, cal = calibration_beside(root, calib)
    warnings: list[str] = []
    files_of = _files(root, warnings)
    cam_of = match_cameras(list(files_of), rig, str(root), warnings)
    digests: dict[str, str] = {}
    above = dropped = 0
    first: tuple[Path, _SleapFile] | None = None
    rb: RowBuilder | None = None
    for name, path in files_of.items():
        got = _read(path)
        tracks, scores, nodes, edges = got.tracks, got.scores, got.nodes, got.edges
        digests[str(path.relative_to(root))] = got.digest
        if first is None:
            first = (path, got)
            rb = RowBuilder(n_joints=len(nodes))
        elif (nodes, sorted(map(sorted, edges))) != (first[1].nodes, sorted(map(sorted, first[1].edges))):
            raise InputError(str(path), f"its skeleton differs from {first[0]}'s (nodes or edges)")
        T, _, J, F = tracks.shape
        if np.isinf(tracks).any():  # SLEAP writes NaN where a node is not labelled, never infinity
            t, _, j, f = (int(v[0]) for v in np.nonzero(np.isinf(tracks)))
            raise InputError(f"{path}: tracks", f"an infinite pixel (track {t}, node {nodes[j]}, frame {f})")
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
        raise InputError(str(root), f"no SLEAP file (<camera>/*{SLP} or <camera>/*{SUFFIX})")
    obs = rb.build()
    if len(obs) == 0:
        raise InputError(str(root), "no labelled keypoints in any SLEAP file")
    nodes, edges = first[1].nodes, first[1].edges
    pairs = side_pairs(nodes, edges, first[1].pairs)
    if first[1].pairs is not None and len(pairs) < len(first[1].pairs):
        warnings.append(f"{first[0].name}: {len(first[1].pairs) - len(pairs)} of its symmetries are no "
                        "left/right pair of the bones (their sides' bones do not mirror): not used as pairs")
    doc: JsonDict = {"name": "sleap", "joints": nodes, "bones": [list(e) for e in edges],
                     "pairs": [list(p) for p in pairs]}
    skeleton_from_doc(doc, str(first[0]))  # checked as a skeleton file is
    name = "sleap"
    if skeleton is not None:  # the user's description of the same nodes
        given = body_skeleton(list(nodes), skeleton, "the SLEAP files' nodes")
        doc, name = given.doc(), given.name
    rate = fps or fps_doc
    files = {f"calibration:{cal.name}": "folder" if cal.is_dir() else read_hashed(cal)[1], **digests}
    if above:
        warnings.append(f"{above} SLEAP scores above 1 read as 1")
    if dropped:
        warnings.append(f"{dropped} keypoints scored 0 or below left out")
    return Scene(rig=rig, obs=obs, layout="sleap", fps=float(rate or DEFAULT_FPS),
                 frames=np.unique(obs.frame), skeleton=name, skeleton_doc=doc, files=files, root=str(root),
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


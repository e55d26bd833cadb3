"""2D labels per camera for the annotation tools: CVAT for video 1.1, MOTChallenge, COCO.

What ``gt3d project`` writes (:mod:`gt3dkit.project` computes the shapes), in the layouts the
readers of :mod:`gt3dkit.io.datasets` take back (``cvat/<camera>.xml``, ``mot/<camera>.txt``,
``coco/<camera>.json``, beside a ``cameras.json``), so that a reviewed set goes straight into
``gt3d reconstruct``.

Every shape says where it came from (:data:`SOURCES`): ``annotated`` (an input label exists:
it is written as it was labelled, so that an untouched label comes back unchanged),
``proposed`` (the estimate drawn into a view without a label), ``interpolated`` (the estimate
at a frame between labelled frames). With it: the anomaly kinds that concern it, the estimate's
sd in pixels, a confidence (1 for a label; for a drawn estimate ``sigma / sqrt(sigma^2 +
sd^2)``, ``sigma`` the labels' own noise: 1 when the estimate is as sure as a label can be),
and ``occluded`` where nearer objects cover more than half of it. A drawn shape carries the
digest of its coordinates (``drawn_digest``, :func:`shape_digest`): read back unchanged it is
left out (it is the estimate's own projection, no new label), moved by an annotator it is a
label.

* **CVAT for video 1.1** (the "Interpolation" part of CVAT's XML format): one file per camera
  (one CVAT task per camera video), one ``<track>`` per object (per piece of an id that the
  identity check split; track ids are the run's ids in every camera, a split id's later pieces
  numbered after the largest id: :func:`piece_ids`, the map in ``projection.json``), every
  shape a keyframe carrying the track's id as a ``track_id`` attribute too (CVAT numbers the
  tracks 0, 1, ... when it exports; the reader takes the attribute), an ``outside="1"`` shape
  on the frame after each run of frames (CVAT would otherwise carry the box on), the
  attributes as ``<attribute>`` children (declared in the task's label, as CVAT exports them),
  ``occluded`` as CVAT's own.
  Keypoint runs write ``<skeleton>`` shapes with a ``<points>`` per joint.
* **MOTChallenge**: ``frame,id,left,top,width,height,conf,x,y,z`` without a header, ``conf``
  the confidence (1 for a label; at most 0.9999 for a drawn shape, which is how the reader
  tells them apart beside ``projection.json``), ``x,y,z`` the estimate's centre (m; the 3D
  columns of the format; ``-1,-1,-1`` for labels without one).
* **COCO**: per camera ``images`` (``frame_id``), ``annotations`` (``bbox``, ``area``,
  ``track_id``, ``score`` = the confidence, ``attributes`` with the rest, keypoints with
  visibility 2 / 1 (occluded) / 0 for keypoint runs), ``categories`` (``person``, its joint
  names and bones). COCO wants a ``bbox`` on every annotation: where a keypoint shape's box is
  the estimate's (a keypoint label without a box, a drawn shape), ``bbox_digest`` (its
  :func:`shape_digest`) tells the reader to leave that bbox out unless an annotator changed it.
"""

from __future__ import annotations

import hashlib
import json
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gt3dkit.arrays import lookup_rows
from gt3dkit.types import F64, I64, Rig

SOURCES = ("annotated", "proposed", "interpolated")
LABEL = "person"


@dataclass(frozen=True)
class Shapes:
    """The shapes of ``S`` (frame, camera, object) triples.

    frame, cam, track, segment : (S,) int64; ``track`` the run's id, ``segment`` the piece of
        it (identity splits; 0 for an id kept whole)
    box_xyxy_px : (S, 4) float64 pixels of the distorted image (NaN: no box)
    kpt_uv_px : (S, J, 2) float64 (NaN: joint not drawn; J may be 0)
    source : (S,) int64 index into :data:`SOURCES`
    occluded : (S,) bool; sd_px, confidence : (S,) float64
    anomalies : (S,) the anomaly kinds that concern the shape, ``;``-joined ('' none)
    center_world : (S, 3) float64 metres, the estimate's centre
    step : the frame step of the sequence (a track's frames further apart are two runs)
    piece_id : (S,) int64 the track id written (:func:`piece_track_ids`); None: ``track``
    box_drawn : (S,) bool the box is the estimate's, not a label's (a keypoint label without a
        box, or a drawn shape); None: where ``source`` is not ``annotated``
    """

    frame: I64
    cam: I64
    track: I64
    segment: I64
    box_xyxy_px: F64
    kpt_uv_px: F64
    source: I64
    occluded: np.ndarray
    sd_px: F64
    confidence: F64
    anomalies: tuple[str, ...]
    center_world: F64
    step: int = 1
    piece_id: I64 | None = None
    box_drawn: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.frame)

    def take(self, m: np.ndarray) -> Shapes:
        idx = np.flatnonzero(m) if np.asarray(m).dtype == bool else np.asarray(m)
        return Shapes(self.frame[idx], self.cam[idx], self.track[idx], self.segment[idx],
                      self.box_xyxy_px[idx], self.kpt_uv_px[idx], self.source[idx],
                      self.occluded[idx], self.sd_px[idx], self.confidence[idx],
                      tuple(self.anomalies[i] for i in idx), self.center_world[idx], self.step,
                      None if self.piece_id is None else self.piece_id[idx],
                      None if self.box_drawn is None else self.box_drawn[idx])

    @classmethod
    def labelled(cls, frame: I64, cam: I64, track: I64, box_xyxy_px: F64, kpt_uv_px: F64,
                 step: int = 1) -> Shapes:
        """``S`` labels as an annotation tool holds them (``source`` annotated, confidence 1,
        not occluded, no estimate: ``center_world`` NaN), e.g. a simulated scene's: ``frame, cam,
        track (S,)``, ``box_xyxy_px (S, 4)``, ``kpt_uv_px (S, J, 2)``."""
        n = len(frame)
        zeros = np.zeros(n, np.int64)
        return cls(np.asarray(frame, np.int64), np.asarray(cam, np.int64), np.asarray(track, np.int64),
                   zeros, np.asarray(box_xyxy_px, np.float64), np.asarray(kpt_uv_px, np.float64), zeros,
                   np.zeros(n, bool), np.zeros(n), np.ones(n), ("",) * n, np.full((n, 3), np.nan), step)

    def attributes(self, k: int, joints: tuple[str, ...] = (), with_box: bool = True) -> dict[str, str]:
        """The attributes of shape ``k`` as the tools' text; ``drawn_digest`` of a drawn shape
        (:func:`shape_digest` of its box if the format writes it, ``with_box``, and its joints
        named ``joints``)."""
        drawn = ""
        if self.source[k] != 0:
            pts = {n: (float(x), float(y)) for n, (x, y) in zip(joints, self.kpt_uv_px[k], strict=False)
                   if np.isfinite(x) and np.isfinite(y)}
            drawn = shape_digest(self.box_xyxy_px[k] if with_box else None, pts)
        return {"source": SOURCES[int(self.source[k])], "anomalies": self.anomalies[k],
                "sd_px": f"{self.sd_px[k]:.2f}", "confidence": f"{self.confidence[k]:.3f}",
                "gt3d_id": str(int(self.track[k])), "segment": str(int(self.segment[k])),
                "drawn_digest": drawn}


def shape_digest(box: F64 | None, points: dict[str, tuple[float, float]]) -> str:
    """12 hex digits of a drawn shape's coordinates as its file holds them (``box (4,)`` or
    None; ``points``: joint name -> pixel, the joints drawn), each to 0.01 px (CVAT writes two
    decimals): the ``drawn_digest`` attribute, by which a reader tells a drawn shape nobody
    changed."""
    parts = [] if box is None else [f"{v:.2f}" for v in np.asarray(box, dtype=np.float64)]
    parts += [f"{n}:{x:.2f},{y:.2f}" for n, (x, y) in sorted(points.items())]
    return hashlib.blake2b(";".join(parts).encode(), digest_size=6).hexdigest()


def _num(x: float) -> str:
    """A pixel as text: the shortest text that reads back as the same float (a label written
    back unchanged reads back equal)."""
    return repr(float(x))


def _tracks(shapes: Shapes, c: int) -> list[np.ndarray]:
    """Camera ``c``'s shapes grouped by (id, piece), each sorted by frame."""
    idx = np.flatnonzero(shapes.cam == c)
    key = np.c_[shapes.track[idx], shapes.segment[idx], shapes.frame[idx]]
    idx = idx[np.lexsort(key.T[::-1])]
    if not len(idx):
        return []
    k2 = np.c_[shapes.track[idx], shapes.segment[idx]]
    cut = np.flatnonzero(np.any(np.diff(k2, axis=0) != 0, axis=1)) + 1
    return np.split(idx, cut)


def write_cvat(shapes: Shapes, rig: Rig, joints: tuple[str, ...], folder: Path) -> list[Path]:
    """``folder/<camera>.xml`` per camera (CVAT for video 1.1; see the module doc)."""
    folder.mkdir(parents=True, exist_ok=True)
    keypoints = shapes.kpt_uv_px.shape[1] > 0
    size = int(shapes.frame.max()) + 1 + shapes.step if len(shapes) else 0
    names = ("source", "anomalies", "sd_px", "confidence", "gt3d_id", "segment", "drawn_digest",
             "track_id")
    tid = piece_ids(shapes)
    out = []
    for c, cam in enumerate(rig.cameras):
        root = ET.Element("annotations")
        ET.SubElement(root, "version").text = "1.1"
        task = ET.SubElement(ET.SubElement(root, "meta"), "task")
        ET.SubElement(task, "name").text = cam.name
        ET.SubElement(task, "size").text = str(size)
        ET.SubElement(task, "mode").text = "interpolation"
        label = ET.SubElement(ET.SubElement(task, "labels"), "label")
        ET.SubElement(label, "name").text = LABEL
        ET.SubElement(label, "type").text = "skeleton" if keypoints else "rectangle"
        attrs = ET.SubElement(label, "attributes")
        for n in names:
            a = ET.SubElement(attrs, "attribute")
            ET.SubElement(a, "name").text = n
            ET.SubElement(a, "mutable").text = "False" if n in ("gt3d_id", "segment", "drawn_digest",
                                                                 "track_id") else "True"
            ET.SubElement(a, "input_type").text = "text"
            ET.SubElement(a, "default_value").text = ""
            ET.SubElement(a, "values").text = ""
        osz = ET.SubElement(task, "original_size")
        ET.SubElement(osz, "width").text = str(cam.width)
        ET.SubElement(osz, "height").text = str(cam.height)
        for idx in _tracks(shapes, c):
            tr = ET.SubElement(root, "track", id=str(int(tid[idx[0]])), label=LABEL, source="auto")
            frames = shapes.frame[idx]
            for pos, k in enumerate(idx):
                _cvat_shape(tr, shapes, int(k), joints, outside=False, track_id=int(tid[idx[0]]))
                nxt = frames[pos + 1] if pos + 1 < len(idx) else None
                if nxt is None or nxt > frames[pos] + shapes.step:  # the run ends: end the track
                    _cvat_shape(tr, shapes, int(k), joints, outside=True,
                                frame=int(frames[pos]) + shapes.step, track_id=int(tid[idx[0]]))
        ET.indent(root)
        path = folder / f"{cam.name}.xml"
        ET.ElementTree(root).write(path, encoding="utf-8", xml_declaration=True)
        out.append(path)
    return out


def _cvat_shape(track: ET.Element, shapes: Shapes, k: int, joints: tuple[str, ...], outside: bool,
                frame: int | None = None, track_id: int = -1) -> None:
    common = {"frame": str(int(shapes.frame[k]) if frame is None else frame),
              "outside": "1" if outside else "0", "occluded": str(int(shapes.occluded[k])),
              "keyframe": "1", "z_order": "0"}
    if shapes.kpt_uv_px.shape[1]:
        el = ET.SubElement(track, "skeleton", common)
        for j, name in enumerate(joints):
            uv = shapes.kpt_uv_px[k, j]
            seen = bool(np.isfinite(uv).all())
            ET.SubElement(el, "points", label=name, outside="0" if seen and not outside else "1",
                          occluded="0", keyframe="1",
                          points=f"{_num(uv[0])},{_num(uv[1])}" if seen else "0.0,0.0")
    else:
        b = shapes.box_xyxy_px[k]
        el = ET.SubElement(track, "box", {**common, "xtl": _num(b[0]), "ytl": _num(b[1]),
                                          "xbr": _num(b[2]), "ybr": _num(b[3])})
    attrs = shapes.attributes(k, joints, with_box=not shapes.kpt_uv_px.shape[1])
    for n, v in {**attrs, "track_id": str(track_id)}.items():
        ET.SubElement(el, "attribute", name=n).text = v


def write_association(shapes: Shapes, rig: Rig, path: Path) -> None:
    """``association.csv`` (:func:`gt3dkit.fusion.preparation.associate.read_overrides`' columns): every
    camera's track id is the run's (piece) id, so that reading the files back with
    ``--association`` keeps the run's identities instead of associating the views again."""
    tid = piece_ids(shapes)
    pairs = np.unique(np.c_[shapes.cam, tid], axis=0)
    lines = ["camera,local_id,frame,global_id"]
    lines += [f"{rig.cameras[int(c)].name},{int(i)},,{int(i)}" for c, i in pairs]
    path.write_text("".join(f"{s}\n" for s in lines))


def write_mot(shapes: Shapes, rig: Rig, folder: Path) -> list[Path]:
    """``folder/<camera>.txt`` per camera (MOTChallenge; see the module doc)."""
    folder.mkdir(parents=True, exist_ok=True)
    mot_id = piece_ids(shapes)
    out = []
    for c, cam in enumerate(rig.cameras):
        idx = np.flatnonzero(shapes.cam == c)
        idx = idx[np.lexsort((mot_id[idx], shapes.frame[idx]))]
        lines = []
        for k in idx:
            b, x = shapes.box_xyxy_px[k], shapes.center_world[k]
            conf = "1" if shapes.source[k] == 0 else f"{min(shapes.confidence[k], 0.9999):.4f}"
            xyz = f"{x[0]:.4f},{x[1]:.4f},{x[2]:.4f}" if np.isfinite(x).all() else "-1,-1,-1"
            lines.append(f"{int(shapes.frame[k])},{int(mot_id[k])},{_num(b[0])},{_num(b[1])},"
                         f"{_num(b[2] - b[0])},{_num(b[3] - b[1])},{conf},{xyz}")
        path = folder / f"{cam.name}.txt"
        path.write_text("".join(f"{s}\n" for s in lines))
        out.append(path)
    return out


def piece_ids(shapes: Shapes) -> I64:
    """(S,) the track id each shape is written under (:func:`piece_track_ids`)."""
    return shapes.track if shapes.piece_id is None else shapes.piece_id


def piece_of(frame: I64, track_id: I64, pieces: tuple[tuple[int, int, int, int], ...]) -> I64:
    """(M,) the piece (``segments.csv``: id, segment, first, last frame) each row belongs to; 0
    for ids kept whole."""
    out = np.zeros(len(frame), np.int64)
    for i, seg, a, b in pieces:
        out[(track_id == i) & (frame >= a) & (frame <= b)] = seg
    return out


def piece_track_ids(track_id: I64, segment: I64, pieces: tuple[tuple[int, int, int, int], ...],
                    top: int) -> I64:
    """(M,) one integer per (id, piece), as formats whose track ids are integers need: the id
    for its first piece; the further pieces of split ids (``pieces``, ``segments.csv``'s rows)
    ``top + 1, top + 2, ...`` in (id, piece) order, ``top`` the run's largest id. A function of
    the run alone, so that every file written from it and the report agree."""
    later = np.array(sorted({(int(i), int(s)) for i, s, _, _ in pieces if s > 0}),
                     dtype=np.int64).reshape(-1, 2)
    out = np.asarray(track_id, dtype=np.int64).copy()
    at = lookup_rows(later, np.c_[track_id, segment])
    out[at >= 0] = top + 1 + at[at >= 0]
    return out


def write_coco(shapes: Shapes, rig: Rig, joints: tuple[str, ...], bones: tuple[tuple[int, int], ...],
               folder: Path, track_ids: bool = True) -> list[Path]:
    """``folder/<camera>.json`` per camera (COCO; see the module doc); without ``track_id``s when
    not ``track_ids`` (plain COCO detections, as a detector's export has them)."""
    folder.mkdir(parents=True, exist_ok=True)
    tid = piece_ids(shapes)
    out = []
    J = shapes.kpt_uv_px.shape[1]
    for c, cam in enumerate(rig.cameras):
        idx = np.flatnonzero(shapes.cam == c)
        frames = np.unique(shapes.frame[idx])
        image_of = {int(f): n + 1 for n, f in enumerate(frames)}
        images = [{"id": image_of[int(f)], "file_name": f"{cam.name}/frame_{int(f):06d}.jpg",
                   "frame_id": int(f), "width": cam.width, "height": cam.height} for f in frames]
        anns: list[dict[str, object]] = []
        for k in idx[np.lexsort((tid[idx], shapes.frame[idx]))]:
            b = shapes.box_xyxy_px[k]
            attributes: dict[str, object] = {**shapes.attributes(k, joints),
                                             "occluded": bool(shapes.occluded[k])}
            ann: dict[str, object] = {
                "id": len(anns) + 1, "image_id": image_of[int(shapes.frame[k])], "category_id": 1,
                "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])],
                "area": float((b[2] - b[0]) * (b[3] - b[1])), "iscrowd": 0,
                "track_id": int(tid[k]), "score": round(float(shapes.confidence[k]), 4),
                "attributes": attributes}
            if not track_ids:  # no identity anywhere in the file
                del ann["track_id"]
                for key in ("gt3d_id", "segment"):
                    del attributes[key]
            if J:
                if shapes.source[k] != 0 or (shapes.box_drawn is not None and shapes.box_drawn[k]):
                    # COCO wants a bbox: the estimate's, which a reader does not take for a label
                    attributes["bbox_digest"] = shape_digest(b, {})
                uv = shapes.kpt_uv_px[k]
                seen = np.isfinite(uv).all(axis=1)
                vis = np.where(seen, 1 if shapes.occluded[k] else 2, 0)
                ann["keypoints"] = [float(v) for v in np.c_[np.where(seen[:, None], uv, 0.0),
                                                           vis].ravel()]
                ann["num_keypoints"] = int(seen.sum())
            anns.append(ann)
        cat: dict[str, object] = {"id": 1, "name": LABEL, "supercategory": LABEL}
        if J:
            cat["keypoints"] = list(joints)
            cat["skeleton"] = [[int(a) + 1, int(b) + 1] for a, b in bones]
        doc = {"info": {"description": f"gt3d project: camera {cam.name}"}, "images": images,
               "annotations": anns, "categories": [cat]}
        path = folder / f"{cam.name}.json"
        path.write_text(json.dumps(doc))
        out.append(path)
    return out


@dataclass(frozen=True)
class LabelFormat:
    """One format ``gt3d project`` writes: ``write(shapes, rig, joints, bones, folder)`` (the
    files, one per camera) and whether it holds keypoints."""

    write: Callable[[Shapes, Rig, tuple[str, ...], tuple[tuple[int, int], ...], Path], list[Path]]
    keypoints: bool


#: Every label format by its ``--format`` name, registered once (the command line's choices
#: and ``gt3d project`` read it).
LABEL_WRITERS: dict[str, LabelFormat] = {
    "cvat": LabelFormat(lambda shapes, rig, joints, bones, folder: write_cvat(shapes, rig, joints, folder),
                        keypoints=True),
    "mot": LabelFormat(lambda shapes, rig, joints, bones, folder: write_mot(shapes, rig, folder),
                       keypoints=False),
    "coco": LabelFormat(write_coco, keypoints=True),
}
LABEL_FORMATS = tuple(LABEL_WRITERS)

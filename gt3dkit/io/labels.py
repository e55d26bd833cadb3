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
and ``occluded`` where nearer objects cover more than half of it.

* **CVAT for video 1.1** (the "Interpolation" part of CVAT's XML format): one file per camera
  (one CVAT task per camera video), one ``<track>`` per object (per piece of an id that the
  identity check split; track ids are the run's ids in every camera, a split id's later pieces
  numbered after the largest id: :func:`piece_ids`, the map in ``projection.json``), every
  shape a keyframe, an ``outside="1"`` shape on the frame after each
  run of frames (CVAT would otherwise carry the box on), the attributes as ``<attribute>``
  children (declared in the task's label, as CVAT exports them), ``occluded`` as CVAT's own.
  Keypoint runs write ``<skeleton>`` shapes with a ``<points>`` per joint.
* **MOTChallenge**: ``frame,id,left,top,width,height,conf,x,y,z`` without a header, ``conf``
  the confidence, ``x,y,z`` the estimate's centre (m; the 3D columns of the format).
* **COCO**: per camera ``images`` (``frame_id``), ``annotations`` (``bbox``, ``area``,
  ``track_id``, ``score`` = the confidence, ``attributes`` with the rest, keypoints with
  visibility 2 / 1 (occluded) / 0 for keypoint runs), ``categories`` (``person``, its joint
  names and bones).
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gt3dkit.types import F64, I64, Rig

SOURCES = ("annotated", "proposed", "interpolated")
LABEL = "person"
LABEL_FORMATS = ("cvat", "mot", "coco")


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

    def __len__(self) -> int:
        return len(self.frame)

    def take(self, m: np.ndarray) -> Shapes:
        idx = np.flatnonzero(m) if np.asarray(m).dtype == bool else np.asarray(m)
        return Shapes(self.frame[idx], self.cam[idx], self.track[idx], self.segment[idx],
                      self.box_xyxy_px[idx], self.kpt_uv_px[idx], self.source[idx],
                      self.occluded[idx], self.sd_px[idx], self.confidence[idx],
                      tuple(self.anomalies[i] for i in idx), self.center_world[idx], self.step)

    def attributes(self, k: int) -> dict[str, str]:
        """The attributes of shape ``k`` as the tools' text."""
        return {"source": SOURCES[int(self.source[k])], "anomalies": self.anomalies[k],
                "sd_px": f"{self.sd_px[k]:.2f}", "confidence": f"{self.confidence[k]:.3f}",
                "gt3d_id": str(int(self.track[k])), "segment": str(int(self.segment[k]))}


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
    names = ("source", "anomalies", "sd_px", "confidence", "gt3d_id", "segment")
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
            ET.SubElement(a, "mutable").text = "False" if n in ("gt3d_id", "segment") else "True"
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
                _cvat_shape(tr, shapes, int(k), joints, outside=False)
                nxt = frames[pos + 1] if pos + 1 < len(idx) else None
                if nxt is None or nxt > frames[pos] + shapes.step:  # the run ends: end the track
                    _cvat_shape(tr, shapes, int(k), joints, outside=True,
                                frame=int(frames[pos]) + shapes.step)
        ET.indent(root)
        path = folder / f"{cam.name}.xml"
        ET.ElementTree(root).write(path, encoding="utf-8", xml_declaration=True)
        out.append(path)
    return out


def _cvat_shape(track: ET.Element, shapes: Shapes, k: int, joints: tuple[str, ...], outside: bool,
                frame: int | None = None) -> None:
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
    for n, v in shapes.attributes(k).items():
        ET.SubElement(el, "attribute", name=n).text = v


def write_association(shapes: Shapes, rig: Rig, path: Path) -> None:
    """``association.csv`` (:func:`gt3dkit.fusion.associate.read_overrides`' columns): every
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
            lines.append(f"{int(shapes.frame[k])},{int(mot_id[k])},{_num(b[0])},{_num(b[1])},"
                         f"{_num(b[2] - b[0])},{_num(b[3] - b[1])},{shapes.confidence[k]:.4f},"
                         f"{x[0]:.4f},{x[1]:.4f},{x[2]:.4f}")
        path = folder / f"{cam.name}.txt"
        path.write_text("".join(f"{s}\n" for s in lines))
        out.append(path)
    return out


def piece_ids(shapes: Shapes) -> I64:
    """(S,) one integer per (id, piece): the id for its first piece, numbers after the largest
    id for the further pieces of split ids (formats whose track ids are integers)."""
    out = shapes.track.copy()
    extra = np.flatnonzero(shapes.segment > 0)
    if len(extra):
        pairs, inv = np.unique(np.c_[shapes.track[extra], shapes.segment[extra]], axis=0,
                               return_inverse=True)
        out[extra] = int(shapes.track.max()) + 1 + inv.reshape(-1)
    return out


def write_coco(shapes: Shapes, rig: Rig, joints: tuple[str, ...], bones: tuple[tuple[int, int], ...],
               folder: Path) -> list[Path]:
    """``folder/<camera>.json`` per camera (COCO; see the module doc)."""
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
        anns = []
        for k in idx[np.lexsort((tid[idx], shapes.frame[idx]))]:
            b = shapes.box_xyxy_px[k]
            ann: dict[str, object] = {
                "id": len(anns) + 1, "image_id": image_of[int(shapes.frame[k])], "category_id": 1,
                "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])],
                "area": float((b[2] - b[0]) * (b[3] - b[1])), "iscrowd": 0,
                "track_id": int(tid[k]), "score": round(float(shapes.confidence[k]), 4),
                "attributes": {**shapes.attributes(k), "occluded": bool(shapes.occluded[k])}}
            if J:
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

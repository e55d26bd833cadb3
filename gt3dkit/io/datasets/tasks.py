"""Per-camera annotation-task exports: CVAT for video 1.1 XML and COCO keypoints JSON.

* ``cvat/<camera>.xml``: one CVAT task per camera, exported as "CVAT for video 1.1": ``<track
  id label>`` holding ``<box frame outside xtl ytl xbr ybr>`` and/or ``<skeleton frame
  outside>`` with ``<points label outside points="x,y">`` per joint. Shapes with
  ``outside="1"`` are not annotations. Track ids are the task's own (per camera).
* ``coco/<camera>.json``: COCO keypoints, one file per camera: ``images`` (``id``, and the frame
  as ``frame_id`` or ``frame``, else the last number in ``file_name``), ``annotations``
  (``image_id``, ``keypoints`` = x, y, v per joint with v = 0 not labelled, ``bbox`` = x, y, w,
  h, and the track as ``track_id``, ``instance_id`` or ``attributes.track_id`` when present),
  ``categories[].keypoints`` = the joint names.

A shape ``gt3d project`` drew from an estimate (a proposal or an interpolation: its
``drawn_digest`` attribute, CVAT shape attributes or COCO ``attributes``) that nobody changed
(its coordinates still give that digest, :func:`gt3dkit.io.labels.shape_digest`) is not a
label: it is the estimate's own projection, and reading it as a measurement would count the
estimate's information twice (a narrower sd than the labels support, and with the filter's
nonlinearity a moved estimate). Such shapes are left out, with a warning; a drawn shape an
annotator moved is a label like any other.

CVAT numbers the tracks 0, 1, ... when it exports a task: a track whose shapes carry a
``track_id`` attribute (``gt3d project`` writes one) keeps that id; tracks without one (drawn
in the tool) are numbered after the largest, with a warning.

Joint names in any usual spelling are matched to the smallest known skeleton holding them all
(:func:`gt3dkit.skeletons.skeleton_for_names`). With track ids, the per-camera tracks are
associated across cameras (:func:`gt3dkit.fusion.preparation.associate.associate`); without, each frame's
detections are (:func:`~gt3dkit.fusion.preparation.detections.associate_detections`). Calibration, camera
matching and frame rate as for :mod:`gt3dkit.io.datasets.mot`.
"""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any
from xml.etree.ElementTree import Element

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.io import labels
from gt3dkit.io.datasets.checks import check_pixels
from gt3dkit.io.datasets.common import RowBuilder, camera_ids, camera_track_ids, sim_box_labels
from gt3dkit.io.datasets.mot import DEFAULT_FPS, calibration_beside, match_cameras, natural_key
from gt3dkit.io.datasets.native import SKELETON_FILE, read_kpt_truth_hashed, write_cameras, write_kpt_truth
from gt3dkit.io.datasets.wildtrack import read_truth_csv
from gt3dkit.io.labels import Shapes, shape_digest
from gt3dkit.io.skeletonfile import given_skeleton
from gt3dkit.parse import json_of, parse_frame, parse_int, read_hashed, sha256
from gt3dkit.skeletons import SKELETONS, _norm_joint, skeleton_for_names
from gt3dkit.types import Scene, SimScene, SkeletonScene

#: (frame, track id, detection index, box or None, {joint: (x, y, conf)}, where, untouched):
#: ``untouched`` a shape gt3d drew that nobody changed (see the module doc)
Item = tuple[int, int, int, list[float] | None, dict[str, tuple[float, float, float]], str, bool]


def _untouched(digest: str | None, box: list[float] | None,
               pts: dict[str, tuple[float, float, float]]) -> bool:
    """Whether a shape whose ``drawn_digest`` attribute is ``digest`` still has the coordinates
    gt3d drew."""
    if not digest:
        return False
    return str(digest).strip() == shape_digest(None if box is None else np.asarray(box),
                                               {n: (x, y) for n, (x, y, _) in pts.items()})


def _num(where: str, v: object, name: str) -> float:
    try:
        if not isinstance(v, str | int | float):
            raise TypeError
        x = float(v)
    except (TypeError, ValueError):
        raise InputError(where, f"{name} must be a number, got {v!r}") from None
    if not math.isfinite(x):
        raise InputError(where, f"{name} is not finite ({v})")
    return x


def _cvat_track_ids(path: Path, root: Element, warnings: list[str]) -> dict[int, int]:
    """Element id -> the track's id: its shapes' ``track_id`` attribute where every shape of
    it carries the same one, else (a track drawn in the tool) numbers after the largest."""
    out: dict[int, int] = {}
    new: list[int] = []
    for t in root.iter("track"):
        where_t = f"{path}: track {t.get('id')!r}"
        tid = parse_int(where_t, t.get("id"), "track id")
        vals = {(a.text or "").strip() for sh in t for a in sh.findall("attribute")
                if a.get("name") == "track_id"}
        vals.discard("")
        if len(vals) > 1:
            raise InputError(where_t, f"its shapes carry different track_id attributes {sorted(vals)}")
        if vals:
            out[tid] = parse_int(where_t, vals.pop(), "track_id attribute")
        else:
            new.append(tid)
    if out and new:
        top = max(out.values())
        out.update({t: top + 1 + k for k, t in enumerate(sorted(new))})
        warnings.append(f"{path}: {len(new)} tracks without a track_id attribute (new in the annotation "
                        f"tool) numbered {top + 1} and up")
    return out or {t: t for t in new}


def _read_cvat(path: Path, raw: bytes, warnings: list[str]) -> list[Item]:
    """(frame, track id, -1, box or None, {joint: (x, y, 1)}, where, untouched) per shape, from
    ``raw``, the bytes of ``path``."""
    import xml.etree.ElementTree as ET

    import defusedxml.ElementTree as DET
    from defusedxml import DefusedXmlException

    try:
        root = DET.parse(io.BytesIO(raw)).getroot()
    except ET.ParseError as e:
        raise InputError(f"{path}: line {e.position[0]}", f"malformed XML ({e})") from None
    except DefusedXmlException as e:
        raise InputError(str(path), f"refused: {e}") from None
    except (LookupError, UnicodeError, ValueError) as e:  # a declared encoding Python does not know
        raise InputError(str(path), f"unreadable XML ({e})") from None
    except OSError as e:
        raise InputError(str(path), f"cannot read ({e.strerror})") from None
    if root.tag != "annotations":
        raise InputError(str(path), f"expected <annotations> (CVAT for video 1.1), got <{root.tag}>")
    out: list[Item] = []
    ids = _cvat_track_ids(path, root, warnings)
    for t in root.iter("track"):
        where_t = f"{path}: track {t.get('id')!r}"
        tid = ids[parse_int(where_t, t.get("id"), "track id")]
        for shape in t:
            if shape.tag not in ("box", "skeleton") or shape.get("outside", "0") == "1":
                continue
            where = f"{where_t} frame {shape.get('frame')!r}"
            f = parse_frame(where, shape.get("frame"))
            box, pts = None, {}
            if shape.tag == "box":
                box = [_num(where, shape.get(k), k) for k in ("xtl", "ytl", "xbr", "ybr")]
            else:
                for p in shape.iter("points"):
                    if p.get("outside", "0") == "1":
                        continue
                    xy = (p.get("points") or "").split(",")
                    if len(xy) != 2:
                        raise InputError(f"{where} joint {p.get('label')!r}", f"points must be x,y, got "
                                                                              f"{p.get('points')!r}")
                    pts[str(p.get("label"))] = (_num(where, xy[0], "x"), _num(where, xy[1], "y"), 1.0)
            digest = next((a.text for a in shape.findall("attribute") if a.get("name") == "drawn_digest"),
                          None)
            out.append((f, tid, -1, box, pts, where, _untouched(digest, box, pts)))
    return out


def _read_coco(path: Path, raw: bytes) -> list[Item]:
    doc = json_of(path, raw)
    if not isinstance(doc, dict) or not isinstance(doc.get("annotations"), list):
        raise InputError(str(path), 'expected {"images": [...], "annotations": [...], "categories": [...]}')
    names: list[str] = []
    for c in doc.get("categories") or []:
        if isinstance(c, dict) and isinstance(c.get("keypoints"), list) and c["keypoints"]:
            names = [str(k) for k in c["keypoints"]]
            break
    frame_of: dict[Any, int] = {}
    import re

    for i, im in enumerate(doc.get("images") or []):
        where = f"{path}: images[{i}]"
        if not isinstance(im, dict) or "id" not in im:
            raise InputError(where, "expected an object with an id")
        if "frame_id" in im or "frame" in im:
            frame_of[im["id"]] = parse_frame(where, im.get("frame_id", im.get("frame")))
        else:
            nums = re.findall(r"\d+", str(im.get("file_name", "")))
            if not nums:
                raise InputError(where, "no frame: give frame_id or a file_name with the frame number")
            frame_of[im["id"]] = parse_frame(where, nums[-1])
    out: list[Item] = []
    counter: dict[int, int] = {}
    for i, a in enumerate(doc["annotations"]):
        where = f"{path}: annotations[{i}]"
        if not isinstance(a, dict):
            raise InputError(where, "expected an object")
        if a.get("image_id") not in frame_of:
            raise InputError(where, f"image_id {a.get('image_id')!r} is not in images")
        f = frame_of[a["image_id"]]
        tid = a.get("track_id", a.get("instance_id", (a.get("attributes") or {}).get("track_id")))
        det = counter.get(f, 0)
        counter[f] = det + 1
        box = None
        if a.get("bbox") is not None:
            b = [_num(where, v, "bbox") for v in (a["bbox"] if isinstance(a["bbox"], list) else [None])]
            if len(b) != 4:
                raise InputError(where, "bbox must be x, y, width, height")
            box = [b[0], b[1], b[0] + b[2], b[1] + b[3]]
        pts = {}
        kp = a.get("keypoints") or []
        if kp:
            if not names or len(kp) != 3 * len(names):
                raise InputError(where, f"{len(kp)} keypoint values for {len(names)} joints named in "
                                        "categories")
            for j, n in enumerate(names):
                x, y, v = (_num(where, kp[3 * j + k], "keypoints") for k in range(3))
                if v > 0:
                    pts[n] = (x, y, 1.0 if v >= 2 else 0.5)
        attrs = a.get("attributes")
        digest = attrs.get("drawn_digest") if isinstance(attrs, dict) else None
        untouched = _untouched(digest, box, pts)
        drawn_box = attrs.get("bbox_digest") if isinstance(attrs, dict) else None
        if pts and box is not None and _untouched(drawn_box, box, {}):
            box = None  # the bbox gt3d drew for COCO around keypoints, unchanged: not a box label
        out.append((f, -1 if tid is None else parse_int(where, tid, "track_id"), det, box, pts, where,
                    untouched))
    return out


def load(root: Path, kind: str, skeleton: str | None = None, calib: Path | str | None = None,
         fps: float | None = None) -> Scene:
    """``kind`` = ``cvat`` or ``coco``."""
    root = Path(root)
    ext = {"cvat": "xml", "coco": "json"}[kind]
    paths = sorted((root / kind).glob(f"*.{ext}"), key=lambda p: natural_key(p.stem))
    if not paths:
        raise InputError(str(root / kind), f"no <camera>.{ext} files")
    rig, fps_doc, cal = calibration_beside(root, calib)
    warnings: list[str] = []
    cam_of = match_cameras([p.stem for p in paths], rig, str(root / kind), warnings)
    read = {p: read_hashed(p) for p in paths}  # each file opened once: parsed and hashed from its bytes
    items = {p: (_read_cvat(p, raw, warnings) if kind == "cvat" else _read_coco(p, raw))
             for p, (raw, _) in read.items()}
    names = sorted({n for its in items.values() for it in its for n in it[4]})
    if skeleton is None and (root / SKELETON_FILE).is_file():  # beside the labels (gt3d project writes one)
        skeleton = str(root / SKELETON_FILE)
    skel = None
    doc = None
    index: dict[str, int] = {}
    if names:
        try:
            if skeleton is None:
                skel, idx = skeleton_for_names(names)
            else:
                (skel, doc), idx = given_skeleton(skeleton), []
        except ValueError as e:
            raise InputError(str(root / kind), str(e)) from None
        if skeleton is not None:
            # a label's name as the skeleton spells it, else in any usual spelling (LEye, l_eye)
            spelt = {_norm_joint(j): k for k, j in enumerate(skel.joints)}
            idx = [skel.joints.index(n) if n in skel.joints else spelt.get(_norm_joint(n), -1) for n in names]
            bad = [n for n, k in zip(names, idx, strict=True) if k < 0]
            if bad:
                raise InputError("--skeleton", f"{skeleton} has no joints {bad}")
        index = dict(zip(names, idx, strict=True))
    with_ids = all(it[1] >= 0 for its in items.values() for it in its)
    rb = RowBuilder(n_joints=skel.n_joints if skel else 0)
    untouched = 0
    for p, its in items.items():
        c = cam_of[p.stem]
        for f, tid, det, box, pts, where, as_drawn in its:
            key = tid if with_ids else det
            if as_drawn:
                untouched += 1
                continue
            if box is not None:
                check_pixels(where, rig.cameras[c], box, "box")
                rb.add_box(f, c, key, box, where)
            for n, (x, y, conf) in pts.items():
                check_pixels(where, rig.cameras[c], [x, y], "keypoint")
                rb.add_joint(f, c, key, index[n], (x, y), f"{where} joint {n!r}", conf)
    if untouched:
        warnings.append(f"{root / kind}: {untouched} shapes gt3d project drew that nobody changed left out "
                        "(the estimate's own projection, not labels; move one to make it a label)")
    obs = rb.build()
    if len(obs) == 0:
        raise InputError(str(root), "no annotations in any frame")
    if not with_ids and not obs.n_joints:
        raise InputError(str(root / kind), "boxes without track ids: nothing to tell people apart by "
                                           "(give track ids, or keypoints)")
    files = {f"{kind}/{p.name}": digest for p, (_, digest) in read.items()}
    files[f"calibration:{cal.name}"] = sha256(cal) if cal.is_file() else "folder"
    truth = None
    if (root / "truth.csv").exists():
        truth = read_truth_csv(root / "truth.csv", files, root)
    if (root / "truth_keypoints.csv").exists() and skel is not None:
        truth, files["truth_keypoints.csv"] = read_kpt_truth_hashed(root / "truth_keypoints.csv",
                                                                    skel.n_joints)
    return Scene(rig=rig, obs=obs, layout=kind, fps=float(fps or fps_doc or DEFAULT_FPS), truth=truth,
                 frames=np.unique(obs.frame), skeleton=skel.name if skel else None, skeleton_doc=doc,
                 files=files,
                 root=str(root), warnings=tuple(warnings),
                 fps_assumed="" if (fps or fps_doc) else f"{cal} gives no frame rate",
                 association="tracks" if with_ids else "detections")


def write_cvat(sim: SimScene, tmp: Path, id_seed: int | None) -> None:
    """``cvat/<camera>.xml``: one "CVAT for video 1.1" task per camera, one track per person
    seen there (its own id), a box in every frame it is seen, written by
    :func:`gt3dkit.io.labels.write_cvat` (what ``gt3d project`` writes)."""
    write_cameras(sim.rig, sim.fps, tmp)
    ids = camera_ids(sim.truth_id, len(sim.rig.cameras), id_seed)
    labels.write_cvat(sim_box_labels(sim, ids), sim.rig, (), tmp / "cvat")


def write_coco(sim: SkeletonScene, tmp: Path, track_ids: bool = True, seed: int = 0) -> None:
    """A simulated skeleton scene as ``coco/<camera>.json`` in ``tmp`` (COCO keypoints per camera,
    joint names in ``categories``, each ``bbox`` its joints' extent; ``track_id`` numbered per
    camera when ``track_ids``, else none; :func:`gt3dkit.io.labels.write_coco`, what ``gt3d
    project`` writes) + ``cameras.json`` + ``truth_keypoints.csv``, read by :func:`load`."""
    skel = SKELETONS[sim.skeleton]
    write_cameras(sim.rig, sim.fps, tmp)
    ids = camera_ids(sim.truth_id, len(sim.rig.cameras), seed)
    k, c = np.nonzero(np.asarray(np.isfinite(sim.uv).all(axis=3)).any(axis=2))
    uv = sim.uv[k, c]
    box = np.c_[np.nanmin(uv, axis=1), np.nanmax(uv, axis=1)]
    shapes = Shapes.labelled(sim.truth_frame[k], c, camera_track_ids(ids, c, sim.truth_id[k]), box, uv)
    labels.write_coco(shapes, sim.rig, tuple(skel.marker_names), tuple(skel.bones), tmp / "coco", track_ids)
    write_kpt_truth(sim, tmp / "truth_keypoints.csv")

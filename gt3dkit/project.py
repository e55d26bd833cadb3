"""``gt3d project OUT --format cvat|mot|coco --to DIR``: the 3D estimate drawn back into every
camera as labels for the annotation tool, for review and completion.

For every object and frame of the run (and, with ``every_frame``, every ``step``-th frame between
its first and last, the estimate interpolated: centre and log semi-axes linearly, the sd the
larger of the two sides'), in every camera the object is in front of and whose image its box
reaches: the box of its ellipsoid under the run's box model (lens distortion included; clipped
to the image), its joints for keypoint runs. A view with an input label writes the label itself
(``annotated``), a view without one the estimate (``proposed``), a frame no view labelled the
estimate (``interpolated``); each with the anomalies that name it (its frame and id, and its
camera where the anomaly has one), the estimate's sd in pixels (the box's largest edge change
when the centre moves by its sd along each axis, summed in quadrature; for joints the joint's sd
over the depth times the focal length) and ``occluded`` (nearer objects' boxes cover more than
half of it: :func:`gt3dkit.geom.conics.covered_fraction`). ``only_flagged`` keeps what needs a
person: labels with anomalies, proposals and interpolations. Formats: :mod:`gt3dkit.io.labels`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gt3dkit.api import Run, load_run
from gt3dkit.arrays import frame_grid
from gt3dkit.errors import InputError
from gt3dkit.geom.camera import Cams, project_points
from gt3dkit.geom.conics import covered_fraction, model_boxes
from gt3dkit.io.atomic import write_dir_atomically
from gt3dkit.io.datasets.native import SKELETON_FILE, write_cameras
from gt3dkit.io.labels import (
    LABEL_FORMATS,
    LABEL_WRITERS,
    SOURCES,
    Shapes,
    piece_ids,
    piece_of,
    piece_track_ids,
    write_association,
)
from gt3dkit.io.skeletonfile import write_skeleton
from gt3dkit.io.writers import read_segments_csv
from gt3dkit.jsondoc import json_num
from gt3dkit.skeletons import skeleton_of
from gt3dkit.types import F64, I64, JsonDict, Scene, TrackSet

OCCLUDED_ABOVE = 0.5  # covered fraction above which a shape is ``occluded`` (CVAT's meaning)


def _lost(scene: Scene) -> list[str]:
    """What the labels cannot carry of the run's input: a detector's per-keypoint confidences."""
    conf = scene.obs.kpt_conf
    if conf is None or not np.any(np.isfinite(conf) & (conf < 1.0)):
        return []
    return ["the labels carry no per-keypoint confidence (the input's detector confidences): read back, "
            "every keypoint weighs alike, so the estimate moves from this run's"]


def _states(tr: TrackSet, seg: I64, step: int | None) -> dict[str, np.ndarray]:
    """The estimate's rows, and with ``step`` every ``step``-th frame from each (id, piece)'s first
    to its last frame, interpolated where the run has no row. ``interpolated (M,)``: rows no
    view labelled (the motion model's or this interpolation's)."""
    base = {"frame": tr.frame, "id": tr.track_id, "seg": seg, "centre": tr.center_world,
            "log_axes": np.log(tr.semi_axes), "sd": tr.center_sd, "kpt": tr.kpt_world,
            "interpolated": tr.n_views == 0}
    if step is None:
        return base
    parts: dict[str, list[np.ndarray]] = {k: [] for k in base}
    key = np.c_[tr.track_id, seg]
    for i, s in np.unique(key, axis=0):
        m = np.flatnonzero((tr.track_id == i) & (seg == s))
        m = m[np.argsort(tr.frame[m])]
        f = tr.frame[m]
        grid = np.union1d(np.arange(f[0], f[-1] + 1, step), f)
        at = np.searchsorted(f, grid)
        have = (at < len(f)) & (f[np.minimum(at, len(f) - 1)] == grid)
        lo = np.clip(np.searchsorted(f, grid, side="right") - 1, 0, len(f) - 1)
        hi = np.minimum(lo + 1, len(f) - 1)
        w = np.where(hi > lo, (grid - f[lo]) / np.maximum(f[hi] - f[lo], 1), 0.0)
        for k in ("centre", "log_axes", "kpt"):
            a = base[k][m]
            ww = w.reshape((-1,) + (1,) * (a.ndim - 1))
            parts[k].append(a[lo] * (1 - ww) + a[hi] * ww)
        parts["sd"].append(np.where(have[:, None], base["sd"][m][lo], np.fmax(base["sd"][m][lo],
                                                                              base["sd"][m][hi])))
        parts["frame"].append(grid)
        parts["id"].append(np.full(len(grid), i))
        parts["seg"].append(np.full(len(grid), s))
        parts["interpolated"].append(~have | base["interpolated"][m][lo] & have)
    return {k: np.concatenate(v) for k, v in parts.items()}


def _sd_px(centre: F64, semi: F64, sd: F64, cams: Cams, box: F64) -> F64:
    """(M, C) the box's largest edge change (px) when the centre moves by its sd along each
    world axis, the three summed in quadrature."""
    d2 = np.zeros(box.shape)
    for a in range(3):
        moved = centre.copy()
        moved[:, a] += np.nan_to_num(sd[:, a])
        b, _ = model_boxes(moved, semi, cams)
        d2 += (b - box) ** 2
    return np.sqrt(d2.max(axis=-1))


def _occluded(frame: I64, box: F64, depth: F64) -> np.ndarray:
    """(M, C) boxes covered by nearer objects' boxes by more than :data:`OCCLUDED_ABOVE`."""
    out = np.zeros(depth.shape, bool)
    order = np.argsort(frame, kind="stable")
    cuts = np.flatnonzero(np.diff(frame[order])) + 1
    for rows in np.split(order, cuts):
        if len(rows) > 1:
            out[rows] = covered_fraction(box[rows], depth[rows]) > OCCLUDED_ABOVE
    return out


def _anomaly_kinds(anomalies: list[dict[str, str]]) -> dict[tuple[int, int], list[tuple[str, str]]]:
    """(frame, id) -> [(camera or '', kind)] of the run's anomalies that name a frame and an id."""
    out: dict[tuple[int, int], list[tuple[str, str]]] = {}
    for a in anomalies:
        try:
            key = (int(a["frame"]), int(a["id"]))
        except (KeyError, TypeError, ValueError):
            continue
        out.setdefault(key, []).append((a.get("camera") or "", a.get("kind") or ""))
    return out


def project_run(run: Run, step: int | None = None, cameras: tuple[str, ...] | None = None,
                only_flagged: bool = False) -> Shapes:
    """The shapes of ``run`` (see the module doc) in ``cameras`` (names; None: all)."""
    scene, tr = run.scene, run.tracks
    rig, obs = scene.rig, scene.obs
    names = [c.name for c in rig.cameras]
    keep_cam = np.ones(len(names), bool)
    if cameras is not None:
        bad = [c for c in cameras if c not in names]
        if bad:
            raise InputError("--cameras", f"the run has no camera {bad[0]!r} (it has {', '.join(names)})")
        keep_cam = np.isin(names, cameras)
    pieces: tuple[tuple[int, int, int, int], ...] = ()
    if (run.out / "segments.csv").is_file():
        pieces = read_segments_csv(run.out / "segments.csv")
    st = _states(tr, piece_of(tr.frame, tr.track_id, pieces), step)
    cams = Cams.of(rig, scene.box_model)
    semi = np.exp(st["log_axes"])
    box, margin = model_boxes(st["centre"], semi, cams)  # (M, C, 4), (M, C)
    W, H = rig.wh[:, 0], rig.wh[:, 1]
    clipped = np.stack([np.clip(box[..., 0], 0, W), np.clip(box[..., 1], 0, H),
                        np.clip(box[..., 2], 0, W), np.clip(box[..., 3], 0, H)], -1)
    visible = (margin > 0) & np.all(np.isfinite(box), -1) & (clipped[..., 2] > clipped[..., 0]) \
        & (clipped[..., 3] > clipped[..., 1]) & keep_cam
    sd_px = _sd_px(st["centre"], semi, st["sd"], cams, box)
    occluded = _occluded(st["frame"], np.where(np.isfinite(box), box, 0.0),
                         np.where(visible, margin, np.nan))
    J = tr.kpt_world.shape[1]
    uv = np.full(box.shape[:2] + (J, 2), np.nan)
    if J:
        p, _ = project_points(st["kpt"], cams.K, cams.dist, cams.R, cams.t, cams.depth_sign)
        p = np.swapaxes(p, 1, 2)  # (M, C, J, 2)
        inside = (p[..., 0] >= 0) & (p[..., 0] <= W[None, :, None]) & (p[..., 1] >= 0) \
            & (p[..., 1] <= H[None, :, None])
        uv = np.where(inside[..., None], p, np.nan)
    # the labels: (frame, camera, id) -> obs row
    labelled = np.isfinite(obs.box_xyxy_px).all(1)
    if J:
        labelled |= np.isfinite(obs.kpt_uv_px).all(-1).any(-1)
    lab = np.flatnonzero(labelled & keep_cam[obs.cam])
    row_of = {(int(f), int(i)): r for r, (f, i) in enumerate(zip(st["frame"], st["id"], strict=True))}
    lab_row = np.array([row_of.get((int(obs.frame[k]), int(obs.track_id[k])), -1) for k in lab],
                       dtype=np.int64)
    lab, lab_row = lab[lab_row >= 0], lab_row[lab_row >= 0]
    has_label = np.zeros(visible.shape, bool)
    has_label[lab_row, obs.cam[lab]] = True
    r_p, c_p = np.nonzero(visible & ~has_label)
    rows = np.r_[lab_row, r_p]
    cam = np.r_[obs.cam[lab], c_p]
    source = np.r_[np.zeros(len(lab), np.int64),
                   np.where(st["interpolated"][r_p], SOURCES.index("interpolated"),
                            SOURCES.index("proposed"))]
    shape_box = np.r_[obs.box_xyxy_px[lab], np.round(clipped[r_p, c_p], 2)]  # drawn: 0.01 px
    kpt = np.r_[obs.kpt_uv_px[lab].reshape(len(lab), J, 2) if J else np.zeros((len(lab), 0, 2)),
                np.round(uv[r_p, c_p], 2)]
    box_drawn = source != 0
    if J:  # a keypoint label has no box of its own: the estimate's
        no_box = ~np.isfinite(shape_box).all(1)
        shape_box[no_box] = np.round(clipped[rows[no_box], cam[no_box]], 2)
        box_drawn |= no_box
    sd = sd_px[rows, cam]
    sigma = json_num(run.meta, "estimator", "params", "sigma_px") or 1.0
    conf = np.where(source == 0, 1.0, sigma / np.sqrt(sigma**2 + sd**2))
    kinds = _anomaly_kinds(run.anomalies)
    anomalies = tuple(";".join(sorted({k for c, k in kinds.get((int(st["frame"][r]), int(st["id"][r])), [])
                                       if c in ("", names[cc])}))
                      for r, cc in zip(rows, cam, strict=True))
    top = int(tr.track_id.max()) if len(tr.track_id) else 0
    shapes = Shapes(st["frame"][rows], cam, st["id"][rows], st["seg"][rows], shape_box, kpt, source,
                    occluded[rows, cam], sd, conf, anomalies, st["centre"][rows],
                    step=int(step or frame_grid(tr.frame)[1]),
                    piece_id=piece_track_ids(st["id"][rows], st["seg"][rows], pieces, top),
                    box_drawn=box_drawn)
    if only_flagged:
        shapes = shapes.take((shapes.source != 0) | np.array([a != "" for a in anomalies], bool))
    return shapes


def project(out: Path, fmt: str, dest: Path, step: int | None = None,
            cameras: tuple[str, ...] | None = None, only_flagged: bool = False) -> JsonDict:
    """Write the shapes of the run ``out`` to ``dest`` (atomically): ``<fmt>/<camera>.*``, the
    calibration as ``cameras.json`` (so that ``gt3d reconstruct dest`` reads the reviewed set)
    ``association.csv`` (the run's ids in every camera: ``gt3d reconstruct dest --association
    dest/association.csv`` keeps them) and ``projection.json`` (what was written from what).
    Returns that summary."""
    if fmt not in LABEL_FORMATS:
        raise InputError("--format", f"{fmt!r} is not one of {', '.join(LABEL_FORMATS)}")
    run = load_run(out, "the labels are drawn into its cameras beside its annotations")
    scene = run.scene
    J = run.tracks.kpt_world.shape[1]
    if J and not LABEL_WRITERS[fmt].keypoints:
        others = " or ".join(k for k, v in LABEL_WRITERS.items() if v.keypoints)
        raise InputError("--format", f"{fmt} holds boxes only: this run has keypoints (use {others})")
    shapes = project_run(run, step, cameras, only_flagged)
    skel = skeleton_of(scene)
    joints = tuple(skel.marker_names) if skel is not None else ()
    bones = tuple(skel.bones) if skel is not None else ()
    counts = {s: int((shapes.source == k).sum()) for k, s in enumerate(SOURCES)}
    ids = piece_ids(shapes)
    summary: JsonDict = {
        "run": str(Path(out).resolve()), "format": fmt, "shapes": len(shapes), **counts,
        "flagged": int(sum(a != "" for a in shapes.anomalies)),
        "occluded": int(shapes.occluded.sum()), "frame_step": shapes.step,
        "only_flagged": only_flagged, "notes": list(run.notes) + _lost(scene),
        "cameras": [c.name for k, c in enumerate(scene.rig.cameras) if (shapes.cam == k).any()],
    }
    pieces = sorted({(int(i), int(t), int(s)) for i, t, s in
                     zip(ids, shapes.track, shapes.segment, strict=True) if s > 0})
    summary["pieces"] = pieces

    def write(tmp: Path) -> None:
        write_cameras(scene.rig, scene.fps, tmp)
        write_association(shapes, scene.rig, tmp / "association.csv")
        if skel is not None and scene.skeleton_doc is not None:  # described, not a built-in's name
            write_skeleton(skel, tmp / SKELETON_FILE)
        LABEL_WRITERS[fmt].write(shapes, scene.rig, joints, bones, tmp / fmt)
        doc = {**summary, "pieces": [{"track_id": a, "id": b, "segment": c} for a, b, c in pieces]}
        (tmp / "projection.json").write_text(json.dumps(doc, indent=1))

    write_dir_atomically(Path(dest), write, "--to")
    return summary

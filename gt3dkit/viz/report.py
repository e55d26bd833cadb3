"""``gt3d report OUT``: ``OUT/report/index.html`` with its PNGs beside it (opens from disk).

For a ``gt3d reconstruct`` output: the numbers (input, counts, estimator and its noise levels,
frame and units, calibration and its refinement), the 3D overview and a close-up (open3d,
:mod:`gt3dkit.viz.overview`), per camera its worst frame (annotations against the projected
estimate, at the camera's image size, over the dataset's image when it has one), residual
histograms per camera, each track's residual and sd over time, and the anomaly table with a
small picture of the views of each row. For a ``gt3d compare`` output: the comparison table,
the estimators' tracks side by side and where they disagree, then the first estimator's pages.

The input is read again from where ``meta.json`` says it was loaded (with the same options
and, after ``--refine-calib``, the refined cameras); the report says so when the input files
changed since the run.
"""

from __future__ import annotations

import contextlib
import csv
import html
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gt3dkit.api import Run, load_run
from gt3dkit.errors import InputError
from gt3dkit.eval.metrics import match_rows
from gt3dkit.fusion.preparation.prepare import prepare
from gt3dkit.io.atomic import write_dir_atomically
from gt3dkit.io.labels import piece_of, piece_track_ids
from gt3dkit.io.writers import read_segments_csv
from gt3dkit.jsondoc import json_at, json_list, json_obj
from gt3dkit.parse import read_csv_rows
from gt3dkit.skeletons import skeleton_of
from gt3dkit.types import JsonDict, Scene, TrackSet
from gt3dkit.viz.overlays import (
    FLAG_BGR,
    LABEL_BGR,
    TRACK_BGR,
    FrameSource,
    Overlay,
    OverlayOptions,
    prepared_sources,
    write_overlays,
)
from gt3dkit.viz.overview import colour_of, start_overviews
from gt3dkit.viz.panels import (
    ANNOTATION_NOTE,
    ViewResiduals,
    _plt,
    anomaly_thumbnail,
    residual_histograms,
    track_plots,
    view_residuals,
    worst_frames,
)
from gt3dkit.viz.render3d import RenderError
from gt3dkit.viz.scene3d import write_scene_page

if TYPE_CHECKING:
    from distributed import Client

#: anomaly rows shown with a picture (the highest scores); the table lists up to MAX_ROWS
MAX_PICTURES = 60
MAX_ROWS = 2000

STYLE = ("body{font-family:sans-serif;max-width:1500px;margin:auto;padding:0 12px;color:#222}"
         "table{border-collapse:collapse;font-size:13px;margin:6px 0}td,th{border:1px solid #ccc;"
         "padding:3px 7px;text-align:left;vertical-align:top}th{background:#f0f0f0}"
         "figure{display:inline-block;width:48%;margin:6px 0.5%;vertical-align:top}figure img{width:100%}"
         "figcaption{font-size:13px;color:#444}.wide{width:100%}.warn{color:#a33}"
         "td img{max-height:190px}h2{border-bottom:1px solid #ddd;margin-top:28px}")


def _table(rows: list[list[Any]], head: list[str] | None = None, raw_cols: tuple[int, ...] = ()) -> str:
    def cell(i: int, x: object) -> str:
        return str(x) if i in raw_cols else html.escape(str(x))

    h = "<tr>" + "".join(f"<th>{html.escape(str(x))}</th>" for x in head) + "</tr>" if head else ""
    b = "".join("<tr>" + "".join(f"<td>{cell(i, x)}</td>" for i, x in enumerate(r)) + "</tr>" for r in rows)
    return f"<table>{h}{b}</table>"


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return "-" if not np.isfinite(v) else f"{v:.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k} {_fmt(x)}" for k, x in v.items())
    if isinstance(v, list):
        return ", ".join(_fmt(x) for x in v)
    return "-" if v is None else str(v)


def _keypoint_noise(run: Run) -> str:
    """The keypoint noise the run learnt from the data (:mod:`gt3dkit.fusion.preparation.confidence`): each
    joint's pixel sd at full confidence, and how the detector's confidence scales it; '' when
    the run has no keypoints."""
    kp = json_obj(run.meta, "estimator", "preparation", "keypoints")
    per_joint = [float(v) if isinstance(v, int | float) else float("nan")
                 for v in json_list(kp, "sigma_px_per_joint")]
    skel = skeleton_of(run.scene)
    if not per_joint or skel is None:
        return ""
    names = skel.marker_names
    rows = [[n, f"{v:.2f}"] for n, v in sorted(zip(names, per_joint, strict=False), key=lambda nv: -nv[1])]
    parts = ["<h2>Keypoint noise learnt from the data</h2>",
             "<p>Each joint's pixel sd at the detector's full confidence (the per-frame "
             "triangulation's residuals; " + html.escape(str(kp.get("sigma_source", ""))) + ").</p>",
             _table(rows, ["joint", "sd (px)"])]
    curve = kp.get("confidence")
    if isinstance(curve, Mapping) and curve.get("confidence"):
        conf = np.asarray(json_list(curve, "confidence"), dtype=np.float64)
        factor = np.asarray(json_list(curve, "factor"), dtype=np.float64)
        parts += ["<p>" + html.escape(f"{curve['rule']}: {curve['source']}.") + "</p>",
                  _table([[f"{c:.3f}", f"{f:.3g}", f"{np.sqrt(f):.2f}x"]
                          for c, f in zip(conf, factor, strict=True)],
                         ["confidence", "variance factor", "sd"])]
    elif isinstance(curve, Mapping):
        parts.append("<p>" + html.escape(f"{curve['rule']}: {curve['source']}.") + "</p>")
    return "".join(parts)


def _numbers(run: Run, res: ViewResiduals) -> list[list[Any]]:
    sc, tr, meta = run.scene, run.tracks, run.meta
    est = json_obj(meta, "estimator")
    prep = json_obj(est, "preparation")
    params = json_obj(est, "params")
    vals = [v for v in (res.box_err, res.kpt_err) if v is not None]
    allv = np.concatenate([v[np.isfinite(v)] for v in vals]) if vals else np.zeros(0)
    qa = json_obj(est, "qa", "anomalies")
    rob = json_obj(est, "robust")
    rows = [
        ["input", f"{sc.layout}: {sc.root}"],
        ["cameras", f"{len(sc.rig.cameras)}: {', '.join(sc.rig.names)}"],
        ["frames", f"{len(sc.frames)} ({int(sc.frames.min())}..{int(sc.frames.max())}) at {sc.fps:g} fps"
                   + (" (assumed)" if sc.fps_assumed else "")],
        ["annotations", f"{len(sc.obs)} rows" + (f", {sc.skeleton} keypoints" if sc.skeleton else "")
                        + (", boxes" if sc.obs.has_box.any() else "")],
        ["output", f"{len(tr)} object-frames of {len(np.unique(tr.track_id))} objects"],
        ["estimator", f"{est.get('estimator', '?')} ({est.get('update_form', '')}); "
                      f"{_fmt(est.get('seconds'))} s"],
        ["noise levels the run chose",
         "; ".join(f"{k}: {_fmt(v)}" for k, v in (
             ("box edge sd (px)", params.get("sigma_px", json_at(prep, "boxes", "sigma_px"))),
             ("keypoint sd (px)", params.get("kpt_sigma_px", json_at(prep, "keypoints", "sigma_px"))),
             ("centre acceleration sd (m/s^2)", params.get("accel_sd")),
             ("log semi-axis sd (per sqrt s)", params.get("shape_sd")),
             ("joint acceleration sd (m/s^2)", params.get("joint_accel_sd") if run.scene.skeleton else None),
             ("bone length sd (m)", params.get("bone_sd_m") if run.scene.skeleton else None))
             if v is not None) or "-"],
        ["reprojection residuals",
         f"median {np.median(allv):.2f} px, p95 {np.percentile(allv, 95):.2f} px over {allv.size} box edges "
         "and keypoints" if allv.size else "-"],
        ["robust update", f"{rob.get('rejected', 0)} measurements rejected, {rob.get('downweighted', 0)} "
                          "down-weighted (downweighted.csv)" if rob.get("enabled") else "off"],
        ["anomalies", ", ".join(f"{v} {k}" for k, v in qa.items()) if qa else
         (f"{len(run.anomalies)} rows" if run.anomalies else "none")],
        ["world frame", f"{sc.rig.frame_name}; metres; up = {np.round(sc.rig.up, 4).tolist()}"],
        ["warnings", "; ".join(sc.all_warnings) or "none"],
    ]
    return rows


def _calibration(run: Run) -> str:
    cams = run.scene.rig.cameras
    rows = [[c.name, f"{c.width} x {c.height}", f"{c.K[0, 0]:.1f}, {c.K[1, 1]:.1f}",
             f"{c.K[0, 2]:.1f}, {c.K[1, 2]:.1f}",
             ("fisheye: " if c.lens == "fisheye" else "") + ", ".join(f"{v:.3g}" for v in c.coefficients),
             ", ".join(f"{v:.3f}" for v in c.center_world)] for c in cams]
    out = _table(rows, ["camera", "image (px)", "focal fx, fy (px)", "principal point (px)", "distortion",
                        "centre in the world (m)"])
    people = run.meta.get("calibration_from_people")
    if isinstance(people, dict):
        out += _people_rig(people)
    clocks = json_at(run.meta, "input", "load", "clocks")
    if isinstance(clocks, dict):
        out += _clocks(clocks)
    ref = run.meta.get("calibration_refinement")
    if isinstance(ref, dict):
        keep = {k: v for k, v in ref.items() if k not in ("refined_rig", "rig_sha256") and
                not isinstance(v, dict | list) or k in ("refined_cameras",)}
        out += "<h3>Refinement</h3>" + _table([[k, _fmt(v)] for k, v in keep.items()])
        per = ref.get("cameras") or ref.get("per_camera")
        if isinstance(per, dict):
            head = sorted({k for v in per.values() if isinstance(v, dict) for k in v})
            body = [[n] + [_fmt(v.get(k)) for k in head] for n, v in per.items() if isinstance(v, dict)]
            out += _table(body, ["camera", *head])
    return out


def _people_rig(people: JsonDict) -> str:
    """The rig found from the people (``meta.json`` ``calibration_from_people``): per camera its sd,
    its median reprojection, and how far it lies from the input's own calibration."""
    per = people.get("cameras")
    if not isinstance(per, dict):
        return ""
    given = people.get("against_input_calibration")
    vs = given.get("cameras") if isinstance(given, dict) else None
    rows = []
    for name, c in per.items():
        if not isinstance(c, dict):
            continue
        g = vs.get(name) if isinstance(vs, dict) else None
        beside = [_fmt(100 * float(g["centre_m"])), _fmt(g["rotation_deg"])] if isinstance(g, dict) else []
        rows.append([name, _fmt(100 * float(c.get("centre_sd_m") or float("nan"))),
                     _fmt(c.get("rotation_sd_deg")), _fmt(c.get("median_px")), *beside])
    head = ["camera", "centre sd (cm)", "rotation sd (deg)", "median reprojection (px)"]
    if isinstance(vs, dict):
        head += ["from the input's calibration (cm)", "(deg)"]
    world = people.get("world")
    note = f"<p>{_fmt(world.get('frame'))}</p>" if isinstance(world, dict) else ""
    return ("<h3>The rig found from the people</h3>" + note + _table(rows, head)
            + ("<p>Beside the input's own calibration after the similarity that best maps the camera "
               "centres.</p>" if isinstance(vs, dict) else ""))


def _clocks(clocks: JsonDict) -> str:
    """Each camera's clock the run took its views on (``meta.json`` ``input.load.clocks``,
    :mod:`gt3dkit.io.clocks`)."""
    rows = [[name, _fmt(c.get("late_frames")), _fmt(c.get("sd_frames")), _fmt(c.get("fps") or "the scene's")]
            for name, c in clocks.items() if isinstance(c, dict)]
    return ("<h3>Clocks</h3><p>Each camera's frame <i>g</i> was taken at the scene's frame <i>g</i> f / "
            "f<sub>camera</sub> minus its frames late; the UKF predicts each joint and box to its view's own "
            "time.</p>" + _table(rows, ["camera", "frames late", "sd (frames)", "frame rate"]))


def _anomaly_section(run: Run, res: ViewResiduals, folder: Path, stills: Mapping[tuple[int, str], str]
                     ) -> str:
    rows = run.anomalies
    if not (run.out / "anomalies.csv").is_file():
        return ("<p>This output has no anomalies.csv (gt3d compare does not run the annotation QA; "
                "gt3d reconstruct does).</p>")
    if not rows:
        return "<p>No annotation was flagged.</p>"

    def score(r: dict[str, str]) -> float:
        try:
            return float(r["score"])
        except ValueError:
            return 0.0

    order = sorted(range(len(rows)), key=lambda i: -score(rows[i]))
    pictured = set(order[:MAX_PICTURES])
    before = _split_frames(run.out)
    joints = _joint_names(run.scene)
    body = []
    (folder / "anomalies").mkdir(exist_ok=True)
    shown = sorted(order[:MAX_ROWS], key=lambda i: (int(rows[i]["frame"]), rows[i]["id"], rows[i]["camera"]))
    where = dict(zip(shown, cvat_pointers(run, [rows[i] for i in shown]), strict=True))
    for i in shown:
        r = rows[i]
        pic = ""
        if i in pictured and r["id"].strip().lstrip("-").isdigit():
            name = f"anomalies/{i:05d}.png"
            j = int(r["joint"]) if r["joint"].strip().lstrip("-").isdigit() else None
            prev = before.get((int(r["id"]), int(r["frame"]))) if r["kind"] == "identity_split" else None
            if anomaly_thumbnail(run.scene, res, int(r["frame"]), int(r["id"]), r["camera"], j,
                                 folder / name, before=prev):
                pic = f'<img src="{name}">'
        named = r["joint"].isdigit() and int(r["joint"]) < len(joints)
        joint = joints[int(r["joint"])] if named else r["joint"]
        fix = "; ".join(f"{c}.xml track {t} frame {f}" for c, t, f in where[i])
        still = stills.get((int(r["frame"]), r["camera"])) if r["frame"].lstrip("-").isdigit() else None
        if still:
            pic += f' <a href="{still}">on your frame</a>'
        body.append([r["frame"], r["camera"] or "(all)", r["id"] or "(all)", joint, r["kind"], r["score"],
                     html.escape(r["detail"]), fix, pic])
    more = (f"<p>{len(rows) - MAX_ROWS} more rows in anomalies.csv.</p>" if len(rows) > MAX_ROWS else "")
    return (f"<p>{len(rows)} rows (anomalies.csv); pictures for the {min(len(rows), MAX_PICTURES)} highest "
            "scores: the flagged view (red name) and the object's other views at that frame, "
            f"{html.escape(_annotation_note())}; a flagged joint is circled red.</p>"
            + "<p>open in CVAT: the task of that camera from <code>gt3d project OUT --format cvat</code>, "
              "the track and frame to fix (a split id's later pieces are tracks of their own).</p>"
            + _table(body, ["frame", "camera", "id", "joint", "kind", "score", "detail", "open in CVAT",
                            "views"], raw_cols=(6, 8)) + more)


def cvat_pointers(run: Run, rows: list[dict[str, str]]) -> list[list[tuple[str, int, int]]]:
    """For each anomaly row, where to fix it in the files ``gt3d project`` writes from this run:
    ``[(camera, track id, frame)]``, the row's camera or every camera that labelled the object
    in that frame, the track id of the object's piece there (:func:`gt3dkit.io.labels.piece_track_ids`,
    as the CVAT, MOT and COCO files number it). Empty for rows without a frame and id."""
    pieces: tuple[tuple[int, int, int, int], ...] = ()
    if (run.out / "segments.csv").is_file():
        try:
            pieces = read_segments_csv(run.out / "segments.csv")
        except InputError:
            pieces = ()
    obs, names = run.scene.obs, run.scene.rig.names
    top = int(run.tracks.track_id.max()) if len(run.tracks.track_id) else 0
    out: list[list[tuple[str, int, int]]] = []
    for r in rows:
        try:
            f, i = int(r["frame"]), int(r["id"])
        except (KeyError, TypeError, ValueError):
            out.append([])
            continue
        one = np.array([f]), np.array([i])
        track = int(piece_track_ids(one[1], piece_of(*one, pieces), pieces, top)[0])
        cams = [r["camera"]] if r.get("camera") else \
            [names[c] for c in np.unique(obs.cam[(obs.frame == f) & (obs.track_id == i)])]
        out.append([(c, track, f) for c in cams])
    return out


def _split_frames(out: Path) -> dict[tuple[int, int], int]:
    """``(id, first frame of a piece) -> last frame of the piece before it`` from ``segments.csv``
    (an identity split's picture shows the id there and at the split)."""
    path = out / "segments.csv"
    if not path.is_file():
        return {}
    try:
        pieces = read_segments_csv(path)  # sorted by id, then first frame
    except InputError:
        return {}  # an edited file: the pictures go without the earlier place
    return {(q[0], q[2]): p[3] for p, q in zip(pieces, pieces[1:], strict=False) if p[0] == q[0]}


def _annotation_note() -> str:
    return ANNOTATION_NOTE


def _joint_names(scene: Scene) -> tuple[str, ...]:
    skel = skeleton_of(scene)
    return skel.joints if skel is not None else ()


def _busiest_frame(tracks: TrackSet) -> int:
    frames, counts = np.unique(tracks.frame, return_counts=True)
    best = np.flatnonzero(counts == counts.max())
    return int(frames[best[len(best) // 2]])


def _figure(src: str, caption: str, wide: bool = False) -> str:
    cls = ' class="wide"' if wide else ""
    return f'<figure{cls}><img src="{src}"><figcaption>{html.escape(caption)}</figcaption></figure>'


def run_sections(run: Run, tmp: Path, prefix: str = "", tracks_b: TrackSet | None = None,
                 title_b: str = "", stills: Mapping[tuple[int, str], str] | None = None
                 ) -> tuple[list[str], list[str]]:
    """The HTML sections of one run's report written into ``tmp`` (PNG names start with
    ``prefix``); returns (sections, warnings). ``stills``: the overlay's still of a flagged frame
    by (frame, camera), which the anomaly table links to."""
    sc, tr = run.scene, run.tracks
    pre = prepare(sc)
    res = view_residuals(tr, pre)
    frame = _busiest_frame(tr)
    warnings: list[str] = []
    sub = tmp / prefix if prefix else tmp
    sub.mkdir(parents=True, exist_ok=True)
    p = f"{prefix}/" if prefix else ""
    pictures = (("overview.png", False, f"The rig and every track; ellipsoids or skeletons at frame {frame}"),
                ("closeup.png", True, f"The objects at frame {frame}, closer"))
    def not_made(e: RenderError) -> None:
        warnings.append(f"3D renders {', '.join(n for n, _, _ in pictures)} not made: {e}")

    with contextlib.ExitStack() as stack:
        # open3d renders in its own process while the panels below are drawn here (2 s of a
        # 9 s report on the bundled Panoptic run)
        shots = [(sub / name, close) for name, close, _ in pictures]
        finish: Callable[[], None] | None = None
        try:
            pending, finish = start_overviews(sc, tr, frame, shots, tracks_b=tracks_b, title=title_b)
            stack.enter_context(pending)
        except RenderError as e:
            not_made(e)
        parts = ["<h2>Numbers</h2>", _table([[k, v] for k, v in _numbers(run, res)])]
        if run.notes:
            parts.append("".join(f'<p class="warn">{html.escape(n)}</p>' for n in run.notes))
        parts.append(_keypoint_noise(run))
        renders_at = len(parts) + 1
        parts += ["<h2>3D (open3d, off-screen)</h2>", ""]
        panels = worst_frames(sc, res, sub)
        parts += ["<h2>Annotations against the estimate: each camera's worst frame</h2>",
                  "".join(_figure(p + n, c) for n, c in panels)]
        histograms = residual_histograms(sc, res, sub)
        parts += ["<h2>Reprojection residuals per camera</h2>",
                  _figure(p + histograms, "box edges and keypoints, pixels", wide=True)]
        parts += ["<h2>Tracks over time</h2>", _figure(p + track_plots(tr, res, sub), "", wide=True)]
        section = _anomaly_section(run, res, sub, stills or {})
        parts += [f"<h2>Anomalies ({len(run.anomalies)})</h2>",
                  section.replace('src="anomalies/', f'src="{p}anomalies/')]
        parts += ["<h2>Calibration</h2>", _calibration(run)]
        if finish is not None:
            try:
                finish()
                parts[renders_at] = "".join(_figure(p + name, caption, wide=not close)
                                            for name, close, caption in pictures)
            except RenderError as e:
                not_made(e)
        if not parts[renders_at]:
            parts[renders_at] = '<p class="warn">' + html.escape("; ".join(warnings)) + "</p>"
    return parts, warnings


def _page(title: str, parts: list[str]) -> str:
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>{''.join(parts)}"
            "</body></html>")


def write_report(out: Path, frames: OverlayOptions | None = None, progress: bool = True,
                 client: Client | None = None) -> tuple[Path, list[str]]:
    """Write ``out/report/`` for a reconstruct or compare output folder (atomically); returns
    the index.html path and warnings (a 3D render that failed, a camera without frames).
    ``frames``: the estimate drawn over the cameras' own frames too (:mod:`gt3dkit.viz.overlays`,
    checked before anything is written; ``client``: a Dask cluster's, whose workers draw them, a
    camera each)."""
    out = Path(out)
    if not out.is_dir():
        raise InputError(str(out), "not a folder")
    if (out / "comparison.csv").is_file():
        if frames is not None:
            raise InputError("--frames", "draws one reconstruct output over its frames, not a comparison")
        return _write_compare_report(out)
    run = load_run(out, "the report draws the annotations")
    warnings: list[str] = []
    sources: list[FrameSource] = []
    if frames is not None:
        sources, said = prepared_sources(run.scene, frames)
        warnings += said

    def write(tmp: Path) -> None:
        from tqdm import tqdm

        videos: list[Overlay] = []
        stills: dict[tuple[int, str], str] = {}
        if frames is not None:  # its own bar, frame by frame
            videos, stills = write_overlays(run.scene, run.tracks, run.anomalies, sources, frames,
                                            tmp / "overlays", progress, client)
        shown = None if progress else True  # tqdm: None = shown on a terminal only
        with tqdm(total=2, desc="report", unit="part", disable=shown, leave=False) as bar:
            bar.set_postfix_str("pictures and tables")
            parts, w = run_sections(run, tmp, stills=stills)
            warnings.extend(w)
            bar.update(1)
            if frames is not None:
                parts.insert(1, _overlay_section(videos, frames))
            if len(run.tracks):
                bar.set_postfix_str("the 3D page")
                page = write_scene_page(run.scene, run.tracks, tmp, videos, frames.offset if frames else 0,
                                        frames.step if frames else 1)
                parts.insert(1, f'<p><a href="{page}">The scene in 3D over time</a>: turn it around, scrub '
                                "through the frames, hover an object for its id and sd"
                                + (", each camera's overlay beside it" if videos else "") + ".</p>")
            bar.update(1)
        (tmp / "index.html").write_text(_page(f"gt3dkit report: {out.resolve()}", parts), encoding="utf-8")

    write_dir_atomically(out / "report", write)
    return out / "report" / "index.html", warnings


def _overlay_section(videos: list[Overlay], opts: OverlayOptions) -> str:
    """The overlay videos, with what each colour is and how they were made."""
    def swatch(bgr: tuple[int, int, int], what: str) -> str:
        return (f'<span style="display:inline-block;width:12px;height:12px;background:rgb{bgr[::-1]};'
                f'margin:0 4px 0 10px"></span>{html.escape(what)}')

    legend = (swatch(LABEL_BGR, "the annotation as drawn (boxes, keypoint crosses)")
              + swatch(TRACK_BGR[0], "the estimate's projection, in its track's colour (outline or skeleton)")
              + swatch(TRACK_BGR[1], "a circle: its sd projected (1 sd), where over 3 px")
              + swatch(FLAG_BGR, "a QA flag of that frame and camera"))
    rows = [[v.camera, f'<video controls muted preload="metadata" style="max-width:640px" src="{v.file}">'
             f'</video>', f"{v.frames} frames, {v.width} x {v.height} px, {v.fps:.3g} fps", v.source]
            for v in videos]
    return ("<h2>Overlays on your frames</h2><p>" + legend + "</p><p>Each camera's frames with the "
            f"estimate drawn over them (H.264), at most {opts.width} px wide, every {opts.step}. frame; "
            f"annotation frame f is shown at the video's frame f + {opts.offset} (--frame-offset).</p>"
            + _table(rows, ["camera", "video", "made", "from"], raw_cols=(1,)))


def _write_compare_report(out: Path) -> tuple[Path, list[str]]:
    with open(out / "comparison.csv", newline="", encoding="utf-8") as f:
        header = next(csv.reader(f), [])
    if "estimator" not in header:
        raise InputError(str(out / "comparison.csv"), "no estimator column: not a gt3d compare output")
    table = [dict(r) for _, r in read_csv_rows(out / "comparison.csv", tuple(header))]
    names = [r["estimator"] for r in table
             if not r.get("failed") and (out / r["estimator"] / "tracks.csv").is_file()]
    if not names:
        raise InputError(str(out / "comparison.csv"), "no estimator's output beside it")
    runs = {n: load_run(out / n, "the report draws the annotations") for n in names}
    first = runs[names[0]]
    warnings: list[str] = []

    def write(tmp: Path) -> None:
        cols = [c for c in header if any(r.get(c) for r in table)]
        parts = ["<h2>The estimators</h2>", _table([[r.get(c, "") for c in cols] for r in table], cols)]
        parts += ["<h2>Side by side</h2>", _figure(_side_by_side(runs, tmp), "", wide=True)]
        if len(names) > 1:
            parts += ["<h2>Where they disagree</h2>",
                      _figure(_disagreement_plot(runs, tmp), "", wide=True)]
        other = runs[names[1]].tracks if len(names) > 1 else None
        sec, w = run_sections(first, tmp, prefix=names[0], tracks_b=other,
                              title_b=f"{names[0]} (colours)" + (f" and {names[1]} (black)" if other else ""))
        warnings.extend(w)
        parts += [f"<h1>{html.escape(names[0])} in detail</h1>", *sec]
        page = _page(f"gt3dkit comparison: {out.resolve()}", parts)
        (tmp / "index.html").write_text(page, encoding="utf-8")

    write_dir_atomically(out / "report", write)
    return out / "report" / "index.html", warnings


def _side_by_side(runs: dict[str, Run], tmp: Path) -> str:
    """Each estimator's tracks seen from above (ground plane), one panel each."""
    plt = _plt()
    n = len(runs)
    ground = {name: run.tracks.center_world @ run.scene.rig.world_from_body()[:, :2]
              for name, run in runs.items()}
    allxy = np.concatenate(list(ground.values()))
    allxy = allxy[np.isfinite(allxy).all(axis=1)]
    span = np.ptp(allxy, axis=0) + 1.0 if len(allxy) else np.ones(2)
    panel_w = float(np.clip(4.6 * span[0] / span[1], 2.8, 8.0))
    fig, axes = plt.subplots(1, n, figsize=(panel_w * n + 0.6, 5.0), dpi=100, squeeze=False, sharex=True,
                             sharey=True)
    for ax, (name, run) in zip(axes.flat, runs.items(), strict=True):
        tr = run.tracks
        xy = ground[name]
        for tid in np.unique(tr.track_id):
            m = tr.track_id == tid
            ax.plot(xy[m, 0], xy[m, 1], "-", color=colour_of(tid), lw=1.2)
            ax.text(xy[m][0, 0], xy[m][0, 1], str(int(tid)), fontsize=7, color=colour_of(tid))
        ax.set_title(f"{name}: {len(tr)} object-frames", fontsize=10)
        ax.set_aspect("equal")
        ax.set_xlabel("ground x (m)")
        ax.grid(alpha=0.3)
    axes.flat[0].set_ylabel("ground y (m)")
    fig.tight_layout()
    fig.savefig(tmp / "side_by_side.png")
    plt.close(fig)
    return "side_by_side.png"


def _disagreement_plot(runs: dict[str, Run], tmp: Path) -> str:
    """Per object over time, the distance between the first estimator and each other one (mean
    joint distance for skeletons, else centre distance)."""
    plt = _plt()
    names = list(runs)
    a = runs[names[0]].tracks
    fig, axes = plt.subplots(len(names) - 1, 1, figsize=(10, 3.0 * (len(names) - 1)), dpi=100, squeeze=False)
    for ax, other in zip(axes.flat, names[1:], strict=True):
        b = runs[other].tracks
        ia, ib = match_rows(a, b)
        if a.kpt_world.shape[1] and b.kpt_world.shape[1]:
            both = np.isfinite(a.kpt_world[ia]).all(-1) & np.isfinite(b.kpt_world[ib]).all(-1)
            dj = np.where(both, np.linalg.norm(a.kpt_world[ia] - b.kpt_world[ib], axis=-1), np.nan)
            n_j = both.sum(axis=1)
            d = np.where(n_j > 0, np.nansum(np.nan_to_num(dj), axis=1) / np.maximum(n_j, 1), np.nan)
            what = "mean joint distance"
        else:
            d = np.linalg.norm(a.center_world[ia] - b.center_world[ib], axis=1)
            what = "centre distance"
        for tid in np.unique(a.track_id[ia]):
            m = a.track_id[ia] == tid
            ax.plot(a.frame[ia][m], 1000 * d[m], color=colour_of(tid), lw=1.0)
        ax.set_yscale("log")
        ax.set_ylabel(f"{what} (mm)")
        ax.set_title(f"{names[0]} vs {other}, per object (colour = id): median "
                     f"{1000 * np.nanmedian(d):.1f} mm" if np.isfinite(d).any() else f"{names[0]} vs {other}",
                     fontsize=10)
    axes.flat[-1].set_xlabel("frame")
    fig.tight_layout()
    fig.savefig(tmp / "disagreement.png")
    plt.close(fig)
    return "disagreement.png"

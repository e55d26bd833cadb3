"""Run several estimators on one input and say where they disagree (``gt3d compare``)."""

from __future__ import annotations

import csv
import time
from pathlib import Path

import numpy as np

from gt3dkit.api import estimate_scene, make_estimator, split_scene
from gt3dkit.errors import EstimationError
from gt3dkit.eval.metrics import box_errors, match_rows, relabel_to_truth
from gt3dkit.eval.pose import mpjpe_by_id
from gt3dkit.fusion.base import ESTIMATORS as COMPARE_ESTIMATORS
from gt3dkit.fusion.preparation.identity import identity_segments
from gt3dkit.fusion.preparation.prepare import prepare
from gt3dkit.fusion.preparation.rows import Rows, build_rows
from gt3dkit.geom.camera import Cams, project_points
from gt3dkit.geom.conics import model_boxes
from gt3dkit.io.atomic import write_dir_atomically
from gt3dkit.io.writers import write_result_files
from gt3dkit.types import F64, JsonDict, Scene, TrackSet


def _row_of(tracks: TrackSet, rows: Rows) -> np.ndarray:
    """(M,) index into ``rows`` of each output row (-1 where the input has no such row)."""
    key = {(int(rows.frames[t]), int(rows.obj_ids[o])): r
           for r, (t, o) in enumerate(zip(rows.row_t, rows.row_o, strict=True))}
    return np.array([key.get((int(f), int(i)), -1) for f, i in
                     zip(tracks.frame, tracks.track_id, strict=True)], dtype=np.int64)


def reprojection_residuals(tracks: TrackSet, scene: Scene, rows: Rows) -> F64:
    """Image residuals (px) of every usable box edge (absolute) and every keypoint (distance)."""
    cams = Cams.of(scene.rig, scene.box_model)
    r_of = _row_of(tracks, rows)
    ok = r_of >= 0
    out = []
    if np.isfinite(rows.box_z).any():
        box, _ = model_boxes(tracks.center_world[ok], tracks.semi_axes[ok], cams)
        m = rows.box_mask[r_of[ok]]
        out.append(np.abs(box - rows.box_z[r_of[ok]])[m])
    if tracks.kpt_world.shape[1] and np.isfinite(rows.kpt_z).any():
        uv, _ = project_points(tracks.kpt_world[ok], cams.K, cams.dist, cams.R, cams.t,
                               cams.depth_sign)  # (n, J, C, 2)
        z = np.swapaxes(rows.kpt_z[r_of[ok]], 1, 2)  # (n, J, C, 2)
        d = np.linalg.norm(uv - z, axis=-1)
        out.append(d[np.isfinite(d)])
    return np.concatenate(out) if out else np.zeros(0)


def seen_joints(tracks: TrackSet, rows: Rows, min_views: int = 2) -> np.ndarray:
    """(M, J) joints of each output row that ``min_views`` or more cameras saw in that frame."""
    out = np.zeros((len(tracks), tracks.kpt_world.shape[1]), bool)
    if out.shape[1]:
        r_of = _row_of(tracks, rows)
        nv = np.isfinite(rows.kpt_z[..., 0]).sum(axis=1)  # (R, J)
        out[r_of >= 0] = nv[r_of[r_of >= 0]] >= min_views
    return out


def disagreement(a: TrackSet, b: TrackSet, seen_a: np.ndarray | None = None) -> F64:
    """Per matched (frame, id): mean joint distance if both have joints, else centre distance (m).

    ``seen_a`` (M_a, J) restricts the joints to those the cameras saw in that frame: a joint
    out of sight for many frames is an extrapolation with a large sd in every estimator,
    and would swamp the comparison.
    """
    ia, ib = match_rows(a, b)
    if a.kpt_world.shape[1] and b.kpt_world.shape[1]:
        d = np.linalg.norm(a.kpt_world[ia] - b.kpt_world[ib], axis=-1)
        if seen_a is not None:
            d = np.where(seen_a[ia], d, np.nan)
        n = np.isfinite(d).sum(axis=1)
        per = np.where(np.isfinite(d), d, 0.0).sum(axis=1) / np.maximum(n, 1)
        return per[n > 0]
    return np.linalg.norm(a.center_world[ia] - b.center_world[ib], axis=1)


def compare(scene: Scene, out: Path, estimators: tuple[str, ...] = COMPARE_ESTIMATORS,
            progress: bool = True) -> list[JsonDict]:
    """Run ``estimators`` on ``scene``; write ``out/<name>/`` outputs and ``out/comparison.csv``
    (all at once, atomically). Returns the comparison rows."""
    from tqdm import tqdm


    results: dict[str, TrackSet] = {}
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    pre = prepare(scene)  # the robust per-frame fits and noise levels, shared
    # split ids: the same pieces as gt3d reconstruct's
    segs = identity_segments(pre, scene.fps, pieces=scene.identity_pieces)
    shared = split_scene(scene, pre, segs) if segs.splits else None  # the pieces, prepared once
    t_pre = time.perf_counter() - t0
    failed: dict[str, str] = {}
    for name in tqdm(estimators, desc="estimators", disable=not progress, unit="est"):
        t0 = time.perf_counter()
        try:
            results[name] = estimate_scene(scene, make_estimator(name), pre, segs, split=shared)
        except EstimationError as e:  # one estimator's failure is a finding, not the end
            failed[name] = e.problem
            continue
        seconds[name] = time.perf_counter() - t0 + t_pre
    if not results:
        raise EstimationError("compare", "; ".join(f"{k}: {v}" for k, v in failed.items()))
    table = []
    rows = build_rows(scene)
    seen = {name: seen_joints(tr, rows) for name, tr in results.items()}
    for name, tr in results.items():
        res = reprojection_residuals(tr, scene, rows)
        row: JsonDict = {
            "estimator": name, "rows": len(tr),
            "skipped_rows": int(tr.info.skipped_lt2_views or 0),
            "reproj_mean_px": float(np.mean(res)) if res.size else float("nan"),
            "reproj_median_px": float(np.median(res)) if res.size else float("nan"),
            "reproj_p95_px": float(np.percentile(res, 95)) if res.size else float("nan"),
        }
        for other in results:
            if other != name:
                d = disagreement(tr, results[other], seen[name])
                row[f"dist_to_{other}_mean_m"] = float(np.mean(d)) if d.size else float("nan")
                row[f"dist_to_{other}_p95_m"] = float(np.percentile(d, 95)) if d.size else float("nan")
        row["seconds"] = seconds[name]
        if scene.truth is not None and scene.association is not None:  # gt3dkit's own ids

            tr = relabel_to_truth(tr, scene.truth, scene.rig.up)
        if scene.truth is not None:
            if np.isfinite(scene.truth.center_world).any():
                errs = box_errors(tr, scene.truth, scene.rig.up)
                row["truth_ground_mean_m"] = errs.ground_mean_m
                row["truth_centre_mean_m"] = errs.centre_mean_m
                row["truth_coverage"] = errs.coverage
            if scene.truth.kpt_world.shape[1] and tr.kpt_world.shape[1]:
                mm, matched, total = mpjpe_by_id(tr, scene.truth)
                row["truth_mpjpe_m"] = mm / 1000
                row["truth_coverage"] = matched / max(total, 1)
        table.append(row)
    for name, problem in failed.items():
        table.append({"estimator": name, "rows": 0, "failed": problem})
    names = list(results)
    cols = (["estimator", "rows", "skipped_rows", "reproj_mean_px", "reproj_median_px",
             "reproj_p95_px"] + [f"dist_to_{n}_{s}" for n in names for s in ("mean_m", "p95_m")]
            + ["seconds"])
    for r in table:
        cols += [k for k in r if k not in cols]

    def write(tmp: Path) -> None:
        for name, tr in results.items():
            (tmp / name).mkdir()
            write_result_files(tmp / name, scene, tr)
        with open(tmp / "comparison.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=cols)
            w.writeheader()
            for r in table:
                w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})

    write_dir_atomically(Path(out), write)
    return table

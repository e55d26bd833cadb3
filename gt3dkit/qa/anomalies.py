"""Annotation QA: score every input annotation against the robust estimate, flag the bad ones.

Every score is in units of the noise level the run estimated from the data (box edges per
kind, keypoints per joint and confidence) or in metres, so a noisy label set is judged by its
own standard, and every threshold is in :class:`QAConfig`. Kinds (``OUT/anomalies.csv``):

``shifted_box``      a box whose edges disagree with the estimate's tangent box (the other views)
``size_outlier``     a box in the right place but much larger or smaller than the object's own
``keypoint_outlier`` a keypoint far from the estimate's projection
``swapped_joints``   a left/right pair that fits the estimate exchanged in one view
``identity_jump``    an object-frame whose views agree on a place the object cannot have reached
                     (its per-frame fit far from the line between its neighbours' fits)
``world_frame``      an object standing below the floor or floating above it

Not yet: ``missing_view`` (needs occlusion reasoning) and ``time_offset``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from gt3dkit.types import F64, Scene, TrackSet

COLUMNS = ("frame", "camera", "id", "joint", "kind", "score", "detail")


@dataclass(frozen=True)
class QAConfig:
    box_sigmas: float = 8.0  # a box edge this many noise levels off is flagged
    size_ratio: float = 1.6  # area ratio beyond which a well-placed box is a size outlier
    kpt_sigmas: float = 8.0  # a keypoint this many noise levels off is flagged
    swap_gain: float = 0.35  # swapped pair cost below this fraction of the unswapped one
    jump_m: float = 1.0  # per-frame fit this far off its neighbours' line (and jump_sigmas)
    jump_sigmas: float = 6.0
    floor_tol_m: float = 0.2  # people stand on the floor when their bottoms' median is within
    below_floor_m: float = 0.3
    floating_m: float = 0.5


@dataclass
class Anomalies:
    rows: list[tuple[int, str, int, int | str, str, float, str]]

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for r in self.rows:
            out[r[4]] = out.get(r[4], 0) + 1
        return dict(sorted(out.items()))


def _key_index(tracks: TrackSet) -> dict[tuple[int, int], int]:
    return {(int(f), int(i)): k for k, (f, i) in enumerate(zip(tracks.frame, tracks.track_id, strict=True))}


def _iou(a: F64, b: F64) -> F64:
    w = np.clip(np.minimum(a[..., 2], b[..., 2]) - np.maximum(a[..., 0], b[..., 0]), 0, None)
    h = np.clip(np.minimum(a[..., 3], b[..., 3]) - np.maximum(a[..., 1], b[..., 1]), 0, None)
    inter = w * h
    area = lambda x: (x[..., 2] - x[..., 0]) * (x[..., 3] - x[..., 1])  # noqa: E731
    return inter / np.maximum(area(a) + area(b) - inter, 1e-9)


def find_anomalies(scene: Scene, tracks: TrackSet, pre: Any, cfg: QAConfig | None = None,
                   jumps: list[tuple[int, float, int, int]] | None = None) -> Anomalies:
    """Every flagged annotation of ``scene`` against ``tracks`` (see the module docstring);
    ``jumps`` = :func:`identity_jumps` if already found."""
    from gt3dkit.geom.camera import project_points
    from gt3dkit.geom.conics import ellipsoid_boxes

    cfg = cfg or QAConfig()
    rows, cams = pre.rows, pre.cams
    names = scene.rig.names
    out: list[tuple[int, str, int, int | str, str, float, str]] = []
    key = _key_index(tracks)
    r_of = np.array([key.get((int(rows.frames[t]), int(rows.obj_ids[o])), -1)
                     for t, o in zip(rows.row_t, rows.row_o, strict=True)], dtype=np.int64)
    have = r_of >= 0
    frame_of = rows.frames[rows.row_t]
    id_of = rows.obj_ids[rows.row_o]

    # identity jumps first: the views of such an object-frame are not flagged one by one
    jumped = _identity_jumps(pre, cfg, out, frame_of, id_of,
                             identity_jumps(pre, scene.fps, cfg) if jumps is None else jumps)

    if pre.use_box and have.any():
        idx = np.flatnonzero(have)
        box, _ = ellipsoid_boxes(tracks.center_world[r_of[idx]], tracks.semi_axes[r_of[idx]],
                                 cams.world_from_body, cams.K, cams.dist, cams.R, cams.t, cams.depth_sign)
        z = rows.box_z[idx]
        usable = rows.box_mask[idx] & np.isfinite(z)
        zs = np.where(usable, np.abs(box - z) / np.asarray(pre.sigma_box)[None, None, :], 0.0)
        score = zs.max(axis=2)  # (n, C)
        iou = _iou(box, z)
        area = lambda x: (x[..., 2] - x[..., 0]) * (x[..., 3] - x[..., 1])  # noqa: E731
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = area(z) / area(box)
            size = np.sqrt(np.maximum(area(box), 1e-9))
            off = np.hypot((z[..., 0] + z[..., 2] - box[..., 0] - box[..., 2]) / 2,
                           (z[..., 1] + z[..., 3] - box[..., 1] - box[..., 3]) / 2) / size
        bad = (score > cfg.box_sigmas) & usable.any(axis=2) & ~jumped[idx][:, None]
        for n, c in zip(*np.nonzero(bad), strict=True):
            r = idx[n]
            sized = (ratio[n, c] > cfg.size_ratio or ratio[n, c] < 1 / cfg.size_ratio) and off[n, c] < 0.25
            kind = "size_outlier" if sized else "shifted_box"
            out.append((int(frame_of[r]), names[c], int(id_of[r]), "", kind, round(float(score[n, c]), 2),
                        f"IoU {iou[n, c]:.2f} with the estimate's box; area ratio {ratio[n, c]:.2f}; "
                        f"largest edge residual {score[n, c]:.1f} sigma"))

    if pre.use_kpt and have.any() and tracks.kpt_world.shape[1]:
        _keypoints(scene, tracks, pre, cfg, r_of, have, jumped, frame_of, id_of, out, project_points)

    _world_frame(scene, tracks, cfg, out)
    out.sort(key=lambda x: (x[0], x[2], x[1], str(x[3]), x[4]))
    return Anomalies(out)


def identity_jumps(pre: Any, fps: float, cfg: QAConfig | None = None) -> list[tuple[int, float, int, int]]:
    """Object-frames whose per-frame fit (two or more views agreeing) lies far off the line
    between the fits of the nearest unflagged frames before and after: a swapped or mis-keyed
    id. Returns (row, metres off, row before, row after), the worst found first, each found
    with the rows already flagged left out."""
    cfg = cfg or QAConfig()
    rows = pre.rows
    x0, var0, _ = pre.frame_state()
    c = x0[:, pre.layout.center]
    sd = np.sqrt(var0[:, pre.layout.center].max(axis=1))  # inf where the frame has no fit
    ok = np.isfinite(sd) & np.isfinite(c).all(axis=1) & (rows.n_views >= 2)
    t_all = rows.frames[rows.row_t] / fps
    found = []
    for o in np.unique(rows.row_o):
        r = list(np.flatnonzero((rows.row_o == o) & ok))  # sorted by frame within an object
        while len(r) >= 3:
            t = t_all[r]
            w = (t[1:-1] - t[:-2]) / np.maximum(t[2:] - t[:-2], 1e-12)
            pred = (1 - w)[:, None] * c[r[:-2]] + w[:, None] * c[r[2:]]
            d = np.linalg.norm(c[r[1:-1]] - pred, axis=1)
            s = np.sqrt(sd[r[1:-1]] ** 2 + sd[r[:-2]] ** 2 + sd[r[2:]] ** 2)
            flag = (d > cfg.jump_m) & (d > cfg.jump_sigmas * s)
            if not flag.any():
                break
            k = int(np.argmax(np.where(flag, d, -1)))
            found.append((r[k + 1], float(d[k]), r[k], r[k + 2]))
            del r[k + 1]
    return found


def _identity_jumps(pre: Any, cfg: QAConfig, out: list, frame_of: np.ndarray, id_of: np.ndarray,
                    jumps: list[tuple[int, float, int, int]]) -> np.ndarray:
    jumped = np.zeros(len(pre.rows), bool)
    for r, d, a, b in jumps:
        jumped[r] = True
        out.append((int(frame_of[r]), "", int(id_of[r]), "", "identity_jump", round(d, 3),
                    f"its views agree on a point {d:.2f} m off the line between frames "
                    f"{int(frame_of[a])} and {int(frame_of[b])}: left out of the estimate"))
    return jumped


def _keypoints(scene: Scene, tracks: TrackSet, pre: Any, cfg: QAConfig, r_of: np.ndarray,
               have: np.ndarray, jumped: np.ndarray, frame_of: np.ndarray, id_of: np.ndarray,
               out: list, project_points: Any) -> None:
    from gt3dkit.skeletons import SKELETONS

    rows, cams = pre.rows, pre.cams
    names = scene.rig.names
    joints = SKELETONS[scene.skeleton].joints if scene.skeleton else ()
    ix = {j: i for i, j in enumerate(joints)}
    pairs = [(ix[j], ix["r_" + j[2:]]) for j in joints if j.startswith("l_") and "r_" + j[2:] in ix]
    idx = np.flatnonzero(have & ~jumped)
    X = tracks.kpt_world[r_of[idx]]  # (n, J, 3)
    uv, _ = project_points(X, cams.K, cams.dist, cams.R, cams.t, cams.depth_sign)  # (n, J, C, 2)
    uv = np.swapaxes(uv, 1, 2)  # (n, C, J, 2)
    z = rows.kpt_z[idx]  # (n, C, J, 2)
    sd = np.sqrt(pre.kpt_var[idx])  # (n, C, J)
    err = np.linalg.norm(uv - z, axis=-1)  # (n, C, J)
    score = err / sd
    bad = np.isfinite(score) & (score > cfg.kpt_sigmas)
    for i, j in pairs:  # swapped pairs: one row instead of two outliers
        swapped = np.linalg.norm(uv[:, :, i] - z[:, :, j], axis=-1) + np.linalg.norm(uv[:, :, j] - z[:, :, i],
                                                                                      axis=-1)
        plain = err[:, :, i] + err[:, :, j]
        sw = (bad[:, :, i] | bad[:, :, j]) & np.isfinite(swapped) & (swapped < cfg.swap_gain * plain)
        for n, c in zip(*np.nonzero(sw), strict=True):
            r = idx[n]
            out.append((int(frame_of[r]), names[c], int(id_of[r]), int(i), "swapped_joints",
                        round(float(max(score[n, c, i], score[n, c, j])), 2),
                        f"{joints[i]} and {joints[j]} exchanged: {plain[n, c]:.1f} px apart as labelled, "
                        f"{swapped[n, c]:.1f} px exchanged"))
        bad[:, :, i] &= ~sw
        bad[:, :, j] &= ~sw
    for n, c, j in zip(*np.nonzero(bad), strict=True):
        r = idx[n]
        out.append((int(frame_of[r]), names[c], int(id_of[r]), int(j), "keypoint_outlier",
                    round(float(score[n, c, j]), 2),
                    f"{err[n, c, j]:.1f} px from the estimate's projection ({score[n, c, j]:.1f} sigma)"))


def _world_frame(scene: Scene, tracks: TrackSet, cfg: QAConfig, out: list) -> None:
    """Objects under the floor or floating, where the people of the scene stand on the floor."""
    up = scene.rig.up
    if tracks.kpt_world.shape[1] and np.isfinite(tracks.kpt_world).any():
        h = np.where(np.isfinite(tracks.kpt_world[..., 0]), tracks.kpt_world @ up, np.inf)
        bottom = h.min(axis=1)
    else:
        bottom = tracks.center_world @ up - tracks.semi_axes[:, 2]
    ok = np.isfinite(bottom)
    if not ok.any() or abs(float(np.median(bottom[ok]))) > cfg.floor_tol_m:
        return  # the scene's people do not stand on z = 0 along up: no floor to judge by
    for i in np.unique(tracks.track_id):
        m = ok & (tracks.track_id == i)
        if not m.any():
            continue
        b = float(np.median(bottom[m]))
        if b < -cfg.below_floor_m or b > cfg.floating_m:
            f = int(tracks.frame[m][0])
            out.append((f, "", int(i), "", "world_frame", round(abs(b), 3),
                        f"stands {abs(b):.2f} m {'below' if b < 0 else 'above'} the floor (median "
                        "over its frames)"))

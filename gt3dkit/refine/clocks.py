"""Each camera's clock from the people in the scene: how late its frames are against the first
camera's, to a fraction of a frame (issue 63).

Given a rig (the input's, or :func:`gt3dkit.refine.people.calibrate_people`'s):

1. **Each camera's people over time**: a detection is followed to the next frame's detection of the
   same camera whose joints lie nearest (mutually nearest, within :data:`FOLLOW_GATE`): tracks.
2. **Each camera pair's whole-frame offset**: for each shift ``k`` within ``max_frames``, every
   detection of camera ``a`` at frame ``f`` against every one of camera ``b`` at ``f + k`` (the
   median Sampson distance of their joints under the rig's essential matrix), gathered per pair of
   tracks (the median over the frames they share); each of ``a``'s tracks takes its best track of
   ``b``. A person's whole path, not one frame's pose, must agree: where people move, the wrong
   ``k`` does not fit.
3. **The fraction**: the matched tracks' joints at ``f`` against ``b``'s track read at ``f + s``
   (joints interpolated between its frames) for ``s`` within a frame of ``k``, in ``step`` steps:
   the mean of the squared Sampson distances (each capped at :data:`CAP_PX`) over one fixed set of
   joints, smallest at the offset; a parabola through the smallest three.
4. **One offset per camera**: ``late_b - late_a = s_ab`` over every pair, the first camera at 0,
   least squares reweighted (Cauchy at half a frame: a wrong pair is down-weighted, and cannot cut
   a camera off). Each camera's sd from the residuals of the pairs within half a frame.

A camera ``late`` by ``d`` frames shows at its frame ``f`` what the first camera shows at ``f - d``.
The frame rates are taken as equal. Where the people hardly move, the offset is not observable:
the pair's curve is flat and its sd says so.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.geom.camera import project_points
from gt3dkit.refine.persons import PersonViews, candidates, essential, pair_errors, signed_px
from gt3dkit.rig import Rig
from gt3dkit.types import F64, I64, JsonDict, Scene, TrackSet

#: A detection is followed to the next frame's nearest within this mean joint distance (normalised
#: image coordinates: 0.05 is ~50 px at a focal length of 1000 px).
FOLLOW_GATE = 0.05
#: The jackknife of :func:`offset_steps` leaves out a person's stretch of this many frames at a time.
JACKKNIFE_FRAMES = 10
#: Gauss-Newton steps of the fraction (module docstring, step 3).
GN_STEPS = 6
#: Sampson distances above this (px) count as this much in the fine search (a detector's misplaced
#: joint must not decide it).
CAP_PX = 10.0


@dataclass(frozen=True)
class ClockConfig:
    max_frames: int = 10  # the largest offset searched, frames
    step: float = 0.05  # the fine search's step, frames
    min_frames: int = 10  # frames a pair of tracks must share to count
    match_px: float = 6.0  # a pair of tracks matches below this median Sampson distance


@dataclass(frozen=True)
class Clocks:
    """``late_frames (C,)``: camera ``c``'s frame ``f`` shows what the first camera shows at
    ``f - late_frames[c]``; ``sd_frames (C,)``; per camera pair what it measured."""

    names: tuple[str, ...]
    late_frames: F64
    sd_frames: F64
    pairs: tuple[JsonDict, ...]

    def report(self) -> JsonDict:
        return {"late_frames": dict(zip(self.names, self.late_frames.round(4).tolist(), strict=True)),
                "sd_frames": dict(zip(self.names, self.sd_frames.round(4).tolist(), strict=True)),
                "pairs": list(self.pairs)}


def follow(pv: PersonViews) -> tuple[I64, I64]:
    """(N,) each detection's successor and predecessor: the same camera's detection in the next
    (previous) frame whose joints lie nearest, both ways, within :data:`FOLLOW_GATE` (-1: none)."""
    N = len(pv.cam)
    succ = np.full(N, -1, np.int64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        centre = np.nanmean(pv.xy, axis=1)  # (N, 2)
    key = pv.cam * (int(pv.frame.max()) + 2) + pv.frame
    order = np.argsort(key, kind="stable")
    uniq, starts = np.unique(key[order], return_index=True)
    ends = np.r_[starts[1:], N]
    groups = {int(k): order[s:e] for k, s, e in zip(uniq, starts, ends, strict=True)}
    for k, here in groups.items():
        there = groups.get(k + 1)
        if there is None:
            continue
        d = np.linalg.norm(centre[here][:, None] - centre[there][None], axis=-1)
        d = np.where(np.isfinite(d), d, np.inf)
        i_best, j_best = np.argmin(d, axis=1), np.argmin(d, axis=0)
        for i, j in enumerate(i_best):
            if j_best[j] == i and d[i, j] < FOLLOW_GATE:
                succ[here[i]] = there[j]
    pred = np.full(N, -1, np.int64)
    has = succ >= 0
    pred[succ[has]] = np.flatnonzero(has)
    return succ, pred


def tracks_of(succ: I64, pred: I64) -> I64:
    """(N,) each detection's track (the chain of successors it belongs to)."""
    track = np.full(len(succ), -1, np.int64)
    n = 0
    for s in np.flatnonzero(pred < 0):
        i = int(s)
        while i >= 0:
            track[i] = n
            i = int(succ[i])
        n += 1
    return track


def _walk(succ: I64, pred: I64, start: I64, steps: int) -> I64:
    """(n,) the detection ``steps`` frames along each one's track from ``start`` (-1: none)."""
    out = start.copy()
    link = succ if steps > 0 else pred
    for _ in range(abs(steps)):
        ok = out >= 0
        out[ok] = link[out[ok]]
    return out


def _drift(pv: PersonViews, E: F64, P: I64, group: I64, f_px: float) -> float:
    """How much the signed Sampson distances (px) of the detection pairs ``P`` drift over time
    within each pair of tracks and joint (``group``: the pair of tracks of each row): their
    within-group RMS, each capped at :data:`CAP_PX`, in the better reading of each pair. A
    person's constant misplacement does not count; the wrong shift makes the moving joints slide."""
    x1 = pv.xy[P[:, 0]]
    d = signed_px(E, x1, pv.xy[P[:, 1]], f_px)
    dm = signed_px(E, x1, pv.xy[P[:, 1]][:, pv.mirror], f_px)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        use_m = np.nanmedian(np.abs(dm), 1) < np.nanmedian(np.abs(d), 1)
    d = np.clip(np.where(use_m[:, None], dm, d), -CAP_PX, CAP_PX)  # (n, J)
    gid = (group[:, None] * d.shape[1] + np.arange(d.shape[1])[None]).reshape(-1)
    dv = d.reshape(-1)
    ok = np.isfinite(dv)
    gid, dv = np.unique(gid[ok], return_inverse=True)[1], dv[ok]
    n = np.bincount(gid).astype(float)
    mean = np.bincount(gid, dv) / n
    dev = (dv - mean[gid]) ** 2
    many = n[gid] >= 3
    if not many.any():
        return np.inf
    return float(np.sqrt(np.sum(dev[many]) / np.sum(many * (1 - 1 / n[gid]))))


def pair_offset(pv: PersonViews, succ: I64, pred: I64, track: I64, rig: Rig, a: int, b: int,
                cfg: ClockConfig) -> tuple[float, float, int, float] | None:
    """``late_b - late_a`` (frames), the fine cost there (mean squared px), the joints it rests on
    and how much the cost rises a frame away (px^2: how observable the offset is); None where the
    pair shares no matched tracks."""
    E = essential(rig, a, b)
    f_px = float(np.sqrt(pv.f_px[a] * pv.f_px[b]))
    # (cost, k, the matched (M, 2) detection pairs, their pair of tracks)
    tried: dict[int, tuple[float, int, I64, I64]] = {}  # k -> (drift, matched frames, pairs, tracks)
    for k in range(-cfg.max_frames, cfg.max_frames + 1):
        moved = PersonViews(pv.xy, pv.ok, pv.cam, np.where(pv.cam == b, pv.frame - k, pv.frame), pv.uv,
                            pv.mirror, pv.f_px)
        P = candidates(moved, a, b)
        if not len(P):
            continue
        err, _ = pair_errors(moved, E, P, f_px)
        key = track[P[:, 0]] * (int(track.max()) + 1) + track[P[:, 1]]
        uk, inv = np.unique(key, return_inverse=True)
        n = np.bincount(inv)
        med = np.array([np.median(err[inv == u]) for u in range(len(uk))])
        ta = uk // (int(track.max()) + 1)
        good = (n >= cfg.min_frames) & (med < cfg.match_px)
        if not good.any():
            continue
        chosen: dict[int, int] = {}  # each track of a: its best track pair
        for u in np.flatnonzero(good):
            if int(ta[u]) not in chosen or med[u] < med[chosen[int(ta[u])]]:
                chosen[int(ta[u])] = int(u)
        sel = np.isin(inv, list(chosen.values()))
        tried[k] = (_drift(moved, E, P[sel], inv[sel], f_px), int(sel.sum()), P[sel], inv[sel])
    if not tried:
        return None
    # the least drift among the shifts that match at least half the frames the best-matched one
    # does (a shift that matches a few frames can drift little by chance)
    most = max(v[1] for v in tried.values())
    k0 = min((k for k, v in tried.items() if v[1] >= 0.5 * most), key=lambda k: tried[k][0])
    _, _, M, pair_of = tried[k0]
    # the fraction: b's joints' signed distances at k0 regressed on their rates of change
    # (Savitzky-Golay over b's track, frames -2..2), a constant per pair of tracks and joint
    # removed. The distances themselves are never interpolated: an average of two noisy frames is
    # less noisy than one, which would pull the fit towards half frames.
    ib = M[:, 1]
    steps = {d: _walk(succ, pred, ib, d) for d in (-2, -1, 1, 2)}
    keep = np.all([v >= 0 for v in steps.values()], axis=0)
    if keep.sum() < cfg.min_frames:
        return None
    ia, ib, pair_of = M[keep, 0], ib[keep], pair_of[keep]
    x1 = pv.xy[ia]
    xb = pv.xy[ib]
    rate = (-2 * pv.xy[steps[-2][keep]] - pv.xy[steps[-1][keep]] + pv.xy[steps[1][keep]]
            + 2 * pv.xy[steps[2][keep]]) / 10.0  # (n, J, 2) per frame
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mirror = (np.nanmedian(np.abs(signed_px(E, x1, xb[:, pv.mirror], f_px)), 1)
                  < np.nanmedian(np.abs(signed_px(E, x1, xb, f_px)), 1))
    xb = np.where(mirror[:, None, None], xb[:, pv.mirror], xb)
    rate = np.where(mirror[:, None, None], rate[:, pv.mirror], rate)
    d0 = signed_px(E, x1, xb, f_px)
    g = (signed_px(E, x1, xb + 0.5 * rate, f_px) - signed_px(E, x1, xb - 0.5 * rate, f_px))  # px/frame
    J = d0.shape[1]
    group = pair_of[:, None] * J + np.arange(J)[None]
    ok = np.isfinite(d0) & np.isfinite(g) & (np.abs(d0) < CAP_PX)
    if ok.sum() < 3 * cfg.min_frames:
        return None
    gid = np.unique(group[ok], return_inverse=True)[1]
    dv, gv = d0[ok], g[ok]
    n = np.bincount(gid).astype(float)
    dc = dv - (np.bincount(gid, dv) / n)[gid]
    gc = gv - (np.bincount(gid, gv) / n)[gid]
    inl = np.abs(dc) < 3 * (1.4826 * np.median(np.abs(dc)) + 1e-9)  # a joint misplaced in one frame
    # the rates carry noise too (Savitzky-Golay's: a tenth of a frame's variance): taken out of the
    # denominator, or the fraction shrinks towards 0
    resid = dc[inl] + gc[inl] * float(-np.sum(dc[inl] * gc[inl]) / max(np.sum(gc[inl] ** 2), 1e-12))
    noise = 0.5 * float(np.mean(resid ** 2)) / 10.0
    den = float(np.sum(gc[inl] ** 2)) - noise * int(inl.sum())
    if den <= 0:
        return None
    frac = float(np.clip(-np.sum(dc[inl] * gc[inl]) / den, -1.0, 1.0))
    return k0 + frac, float(np.mean(dc[inl] ** 2)), int(inl.sum()), den / max(int(inl.sum()), 1)


def _tree_start(rows: list[tuple[int, int, float]], quality: F64, C: int) -> F64:
    """Offsets from camera 0 along the pairs of a maximum spanning tree by quality (each pair's
    rise times its joints): a start that no single wrong pair averages into the others."""
    late = np.full(C, np.nan)
    late[0] = 0.0
    for r in np.argsort(-quality, kind="stable").tolist() * C:  # passes until the tree spans
        a, b, s = rows[r]
        if np.isnan(late[b]) and not np.isnan(late[a]):
            late[b] = late[a] + s
        elif np.isnan(late[a]) and not np.isnan(late[b]):
            late[a] = late[b] - s
    return np.nan_to_num(late)


def _reweighted(A: F64, y: F64, start: F64) -> tuple[F64, F64]:
    """Least squares of ``A x = y`` reweighted from ``start`` (Cauchy at half a frame; the last row,
    the reference, always whole)."""
    late = start
    w = np.ones(len(y))
    for _ in range(10):
        res = A @ late - y
        w = 1.0 / (1.0 + (res / 0.5) ** 2)
        w[-1] = 1.0
        sw = np.sqrt(w)
        late = np.asarray(np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)[0], dtype=np.float64)
    return late, w


def estimate_clocks(pv: PersonViews, rig: Rig, cfg: ClockConfig | None = None) -> Clocks:
    """Every camera's offset (module docstring) from the detections ``pv`` (camera indices into
    ``rig``)."""
    cfg = cfg or ClockConfig()
    C = len(rig.cameras)
    succ, pred = follow(pv)
    track = tracks_of(succ, pred)
    rows: list[tuple[int, int, float]] = []
    pairs: list[JsonDict] = []
    quality_of: list[float] = []
    for a in range(C):
        for b in range(a + 1, C):
            got = pair_offset(pv, succ, pred, track, rig, a, b, cfg)
            if got is None:
                continue
            rows.append((a, b, got[0]))
            pairs.append({"cameras": [rig.cameras[a].name, rig.cameras[b].name], "late_frames": got[0],
                          "mean_sq_px": got[1], "joints": got[2], "rise_sq_px": got[3]})
            quality_of.append(got[3] * got[2])
    if not rows:
        raise InputError("cameras", "no two cameras share a followed person: no clock can be found")
    A = np.zeros((len(rows) + 1, C))
    y = np.zeros(len(rows) + 1)
    for i, (a, b, s) in enumerate(rows):
        A[i, b], A[i, a], y[i] = 1.0, -1.0, s
    A[-1, 0] = 1.0  # the first camera's clock is the reference
    if np.linalg.matrix_rank(A) < C:
        seen = {c for a, b, _ in rows for c in (a, b)}
        missing = [rig.cameras[c].name for c in range(C) if c not in seen] or [rig.cameras[C - 1].name]
        raise InputError(", ".join(missing), "shares no followed person with the cameras linked to the "
                                             "first: its clock cannot be found")
    quality = np.array(quality_of)
    best_cost = np.inf
    least_squares = np.asarray(np.linalg.lstsq(A, y, rcond=None)[0], dtype=np.float64)
    for start in (least_squares, _tree_start(rows, quality, C)):
        sol, wts = _reweighted(A, y, start)
        r = A @ sol - y
        cost = float(np.sum(np.log1p((r[:-1] / 0.5) ** 2)))
        if cost < best_cost:
            best_cost, late, w, res = cost, sol, wts, r
    use = np.abs(res[:-1]) <= 0.5
    n_used = int(use.sum())
    s_res = max(float(np.sqrt(np.sum(res[:-1][use] ** 2) / max(n_used - (C - 1), 1))), cfg.step / np.sqrt(12))
    sd = np.sqrt(np.clip(np.diag(np.linalg.pinv((A * w[:, None]).T @ A)), 0, None)) * s_res
    sd[0] = 0.0
    for p, u in zip(pairs, use, strict=True):
        p["used"] = bool(u)
    return Clocks(tuple(rig.names), late, sd, tuple(pairs))


def synchronised(pv: PersonViews, succ: I64, late_frames: F64) -> PersonViews:
    """``pv`` with every camera's detections moved to the first camera's clock: camera ``c``'s
    detection at its frame ``g`` is read ``frac`` of a frame on along its track and numbered
    ``g - floor(late)``, ``frac = late - floor(late)`` (NaN where its track ends there)."""
    xy, uv, ok, frame = pv.xy.copy(), pv.uv.copy(), pv.ok.copy(), pv.frame.copy()
    for c, d in enumerate(late_frames):
        idx = np.flatnonzero(pv.cam == c)
        whole = int(np.floor(d))
        frac = float(d - whole)
        frame[idx] = pv.frame[idx] - whole
        if frac < 1e-9:
            continue
        nxt = succ[idx]
        has = nxt >= 0
        for arr, src in ((xy, pv.xy), (uv, pv.uv)):
            moved = np.full((len(idx),) + src.shape[1:], np.nan)
            moved[has] = (1 - frac) * src[idx[has]] + frac * src[nxt[has]]
            arr[idx] = moved
        ok[idx] = np.isfinite(xy[idx][..., 0]) & pv.ok[idx]
    return PersonViews(np.where(ok[..., None], xy, np.nan), ok, pv.cam, frame, uv, pv.mirror, pv.f_px)


class Steps(NamedTuple):
    """Per camera ``(K,)``: how much later than its clock says it took its views ``step`` (frames,
    at the scene's frame ``at_frame``) and how much more so each frame on ``drift`` (frames per
    frame: its clock runs slow by that share), their jackknife sds ``step_sd, drift_sd`` and the
    joints they rest on ``joints`` (NaN, 0 where fewer than ten)."""

    step: F64
    step_sd: F64
    drift: F64
    drift_sd: F64
    at_frame: F64
    joints: I64

    @staticmethod
    def unknown(K: int) -> Steps:
        """Of ``K`` cameras, nothing found yet (NaN, no joints)."""
        return Steps(np.full(K, np.nan), np.full(K, np.nan), np.full(K, np.nan), np.full(K, np.nan),
                     np.full(K, np.nan), np.zeros(K, np.int64))


def offset_steps(scene: Scene, tracks: TrackSet, cams: I64, max_px: float = CAP_PX) -> Steps:
    r"""How much later than its clock says each camera ``cams (K,)`` took its views, against a
    reconstruction ``tracks`` made without them: one Gauss-Newton step of

    .. math::
        \min_{\delta_c, \beta_c} \sum \lVert z - \pi_c\big(p(t) + (o + \delta_c + \beta_c (t + o -
        \bar t_c)) v(t)\big) \rVert^2

    over camera ``c``'s views ``z`` at frames ``t`` of the reconstructed joints ``p`` (velocities
    ``v`` by central differences along each track, per frame), ``o`` the view's ``frame_offset``,
    ``\bar t_c`` the mean frame of its views. The sds are the jackknife's over stretches of
    :data:`JACKKNIFE_FRAMES` frames of each person (a person's errors are correlated over its
    frames: the step's own formula would take them as independent). Views off by more than
    ``max_px`` are left out (a detector's misplaced joint; the wrong person)."""
    obs, rig = scene.obs, scene.rig
    key_t = tracks.track_id.astype(np.int64) * (1 << 32) + tracks.frame
    order = np.argsort(key_t)
    ks = key_t[order]

    def row_of(track: I64, frame: I64) -> I64:
        if not len(ks):
            return np.full(len(track), -1, np.int64)
        k = track * (1 << 32) + frame
        i = np.clip(np.searchsorted(ks, k), 0, len(ks) - 1)
        return np.where(ks[i] == k, order[i], -1)

    K = len(cams)
    out = Steps.unknown(K)
    for k, c in enumerate(cams):
        i = np.flatnonzero(obs.cam == c)
        r0 = row_of(obs.track_id[i], obs.frame[i])
        rp, rn = row_of(obs.track_id[i], obs.frame[i] - 1), row_of(obs.track_id[i], obs.frame[i] + 1)
        use = (r0 >= 0) & (rp >= 0) & (rn >= 0)
        i, r0, rp, rn = i[use], r0[use], rp[use], rn[use]
        V = 0.5 * (tracks.kpt_world[rn] - tracks.kpt_world[rp])  # (n, J, 3) per frame
        off = obs.frame_offset[i] if obs.frame_offset is not None else np.zeros(len(i))
        X = tracks.kpt_world[r0] + off[:, None, None] * V
        args = (rig.K[c:c + 1], rig.dist[c:c + 1], rig.R[c:c + 1], rig.t[c:c + 1])
        h = 0.25  # of the frame's motion: the projection's derivative along it
        at = project_points(X, *args)[0][:, :, 0]
        g = (project_points(X + h * V, *args)[0] - project_points(X - h * V, *args)[0])[:, :, 0] / (2 * h)
        res = obs.kpt_uv_px[i] - at  # (n, J, 2) px; g px per frame
        ok = np.isfinite(res).all(-1) & np.isfinite(g).all(-1) & (np.linalg.norm(res, axis=-1) < max_px)
        if ok.sum() < 10:
            continue
        block = obs.track_id[i] * (1 << 32) + obs.frame[i] // JACKKNIFE_FRAMES  # a person's stretch of frames
        who = np.broadcast_to(block[:, None], ok.shape)[ok]
        t = np.broadcast_to((obs.frame[i] + off)[:, None], ok.shape)[ok]
        gr = np.einsum("nd,nd->n", g[ok], res[ok])
        gg = np.einsum("nd,nd->n", g[ok], g[ok])
        t_mean = float(np.sum(gg * t) / max(np.sum(gg), 1e-12))
        t = t - t_mean
        ids, inv = np.unique(who, return_inverse=True)
        # each stretch's normal equations of (step, drift)
        parts = np.stack([np.bincount(inv, w) for w in (gg, gg * t, gg * t * t, gr, gr * t)], 1)  # (B, 5)

        def solve(p: F64) -> F64:
            A = np.array([[p[0], p[1]], [p[1], p[2]]])
            if p[2] * p[0] - p[1] ** 2 <= 1e-12 * max(p[0] * p[2], 1e-300):  # no spread in time: no drift
                return np.array([p[3] / p[0] if p[0] > 0 else np.nan, 0.0])
            return np.linalg.solve(A, p[3:5])

        whole = parts.sum(0)
        if whole[0] <= 0:
            continue
        out.step[k], out.drift[k] = solve(whole)
        out.at_frame[k], out.joints[k] = t_mean, int(ok.sum())
        if len(ids) >= 3:  # the jackknife over the people's stretches
            loo = np.array([solve(whole - p) for p in parts])
            spread = np.sqrt((len(ids) - 1) / len(ids) * np.sum((loo - loo.mean(0)) ** 2, axis=0))
            out.step_sd[k], out.drift_sd[k] = spread
    return out

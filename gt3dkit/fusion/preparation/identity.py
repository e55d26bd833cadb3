r"""Identity integrity: an id's track is split where its own views place it somewhere it cannot
have got to.

Real label sets reuse ids (an id handed to the next person to walk in) and mis-key them for a
frame or a few. Each frame's views still agree on where *that* person stands, so every
object-frame that two or more views determine is reconstructed from its own views; what must not
happen is a smoother pulling one person's track through another's. :func:`identity_segments`
walks each id's multi-view per-frame fits in time and splits the id between two consecutive ones
farther apart than the scene's objects move:

.. math::
    d > v_{lim} \, \Delta t + k \sqrt{s_a^2 + s_b^2},\qquad
    v_{lim} = \max(f \, v_{95}, v_{min}),

with ``v_95`` the 95th percentile over ids of each id's median speed between its consecutive
multi-view fits (the scene's own scale: people or cars; an id's median ignores the jumps of its
own id errors, which in a short or crowded scene are more than 5 % of all steps), ``s`` the
fits' largest centre sd. Rows between the two
fits (seen by fewer views) stay with the earlier piece. Each piece is then an object of its own
for every estimator (:func:`gt3dkit.api.estimate_scene`); the outputs keep the input's ids, and
``segments.csv`` says which frames of an id form which piece.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gt3dkit.fusion.preparation.prepare import Prepared
from gt3dkit.fusion.preparation.rows import Rows
from gt3dkit.types import I64


@dataclass(frozen=True)
class IdentityConfig:
    """speed_factor, min_speed_mps : ``f`` and ``v_min`` of the module doc; sigmas : ``k``."""

    speed_factor: float = 2.0
    min_speed_mps: float = 3.0
    sigmas: float = 4.0


@dataclass(frozen=True)
class Split:
    """Where an id was split: between its multi-view frames ``frame_before`` and ``frame_after``
    (the first of the new piece, ``segment``), ``distance_m`` apart (``speed_mps``), seen by
    ``views_before`` and ``views_after`` cameras; ``limit_m`` the distance allowed."""

    track_id: int
    segment: int
    frame_before: int
    frame_after: int
    distance_m: float
    speed_mps: float
    views_before: int
    views_after: int
    limit_m: float
    given: bool = False  # a piece boundary of the corrections file, not found here


@dataclass(frozen=True)
class Exchange:
    """Two ids split at the same frame, each where the other was: their labels exchanged there
    (``frame``: the first frame of the exchange; ``distance_m``: how far each id's new place is
    from the other's last one)."""

    frame: int
    track_id: int
    other_id: int
    distance_m: tuple[float, float]
    views: tuple[int, int]


@dataclass(frozen=True)
class Segments:
    """``segment (R,)``: the piece of its id each row belongs to (0 = the first); ``splits``;
    ``speed_limit_mps``: ``v_lim``."""

    segment: I64
    splits: tuple[Split, ...]
    speed_limit_mps: float
    exchanges: tuple[Exchange, ...] = ()


def identity_segments(pre: Prepared, fps: float, cfg: IdentityConfig | None = None,
                      pieces: tuple[tuple[int, int, int, int], ...] = ()) -> Segments:
    """The pieces of every id of ``pre.rows`` (a :class:`gt3dkit.fusion.preparation.prepare.Prepared`) at
    frame rate ``fps`` (see the module doc). ``pieces``: ``(id, segment, first frame, last
    frame)`` of an edited ``segments.csv``: the ids it lists are cut where it says instead
    (splits marked ``given``; their exchanges are not looked for)."""
    cfg = cfg or IdentityConfig()
    rows = pre.rows
    R = len(rows)
    x0, var0, _ = pre.frame_state()
    centre = x0[:, pre.layout.center]
    sd = np.sqrt(var0[:, pre.layout.center].max(axis=1))
    ok = np.isfinite(sd) & np.isfinite(centre).all(axis=1) & (rows.n_views >= 2)
    t_s = rows.frames[rows.row_t] / fps
    order = np.lexsort((t_s, rows.row_o))
    order = order[ok[order]]
    same = rows.row_o[order[1:]] == rows.row_o[order[:-1]]
    a, b = order[:-1][same], order[1:][same]  # consecutive multi-view fits of one id
    dist = np.linalg.norm(centre[b] - centre[a], axis=1)
    dt = np.maximum(t_s[b] - t_s[a], 1e-9)
    speed = dist / dt
    v95 = float(np.percentile(group_medians(speed, rows.row_o[a]), 95)) if len(speed) else 0.0
    v_lim = max(cfg.speed_factor * v95, cfg.min_speed_mps)
    limit = v_lim * dt + cfg.sigmas * np.hypot(sd[a], sd[b])
    cut = np.flatnonzero(dist > limit)
    step = np.zeros(R, np.int64)
    step[b[cut]] = 1  # a new piece starts at the first multi-view fit after the jump ...
    # ... and the rows between (fewer views) stay with the earlier piece: count per id in time
    by_time = np.lexsort((t_s, rows.row_o))
    seg = np.zeros(R, np.int64)
    run = np.cumsum(step[by_time])
    first = np.r_[True, rows.row_o[by_time[1:]] != rows.row_o[by_time[:-1]]]
    base = np.maximum.accumulate(np.where(first, run - step[by_time], 0))
    seg[by_time] = run - base
    frame_of = rows.frames[rows.row_t]
    splits = tuple(Split(int(rows.obj_ids[rows.row_o[b[k]]]), int(seg[b[k]]), int(frame_of[a[k]]),
                         int(frame_of[b[k]]), round(float(dist[k]), 3), round(float(speed[k]), 2),
                         int(rows.n_views[a[k]]), int(rows.n_views[b[k]]), round(float(limit[k]), 3))
                   for k in cut)
    if not pieces:
        return Segments(seg, splits, v_lim, _exchanges(cut, a, b, centre, limit, rows))
    listed = {p[0] for p in pieces}
    auto = [k for k, s in zip(cut, splits, strict=True) if s.track_id not in listed]
    splits = tuple(s for s in splits if s.track_id not in listed)
    id_of = rows.obj_ids[rows.row_o]
    for i in sorted(listed):
        mine = np.flatnonzero(id_of == i)
        if not len(mine):
            continue
        mine = mine[np.argsort(t_s[mine], kind="stable")]
        spans = sorted((p[2], p[3]) for p in pieces if p[0] == i)
        f = frame_of[mine]
        # a row between two pieces (no annotation there) stays with the earlier piece
        seg[mine] = np.maximum(np.searchsorted([s[0] for s in spans], f, side="right") - 1, 0)
        for k in range(1, len(spans)):
            at, before = mine[seg[mine] == k], mine[seg[mine] == k - 1]
            if not (len(at) and len(before)):
                continue
            ra, rb = before[-1], at[0]
            d = float(np.linalg.norm(centre[rb] - centre[ra]))
            dt_k = max(float(t_s[rb] - t_s[ra]), 1e-9)
            splits += (Split(int(i), k, int(frame_of[ra]), int(frame_of[rb]), round(d, 3), round(d / dt_k, 2),
                             int(rows.n_views[ra]), int(rows.n_views[rb]), float("nan"), given=True),)
    return Segments(seg, splits, v_lim, _exchanges(np.asarray(auto, np.int64), a, b, centre, limit, rows))


def group_medians(values: np.ndarray, group: I64) -> np.ndarray:
    """The median of ``values (N,)`` within each group of ``group (N,)``, groups in sorted order."""
    order = np.lexsort((values, group))
    v = values[order]
    _, first, count = np.unique(group[order], return_index=True, return_counts=True)
    return (v[first + (count - 1) // 2] + v[first + count // 2]) / 2


def _exchanges(cut: I64, a: I64, b: I64, centre: np.ndarray, limit: np.ndarray, rows: Rows
               ) -> tuple[Exchange, ...]:
    """The pairs of splits (``cut``: indices into the consecutive-fit pairs ``a -> b``) at the
    same frame where each id's new place is within the other's allowed distance of where the
    other was: an exchange of two labels, not two independent errors."""
    frame_of = rows.frames[rows.row_t]
    out, used = [], set()
    for i, k in enumerate(cut):
        for m in cut[i + 1:]:
            if k in used or m in used or frame_of[b[k]] != frame_of[b[m]] \
                    or rows.row_o[b[k]] == rows.row_o[b[m]]:
                continue
            d1 = float(np.linalg.norm(centre[b[k]] - centre[a[m]]))  # k's new place vs m's old
            d2 = float(np.linalg.norm(centre[b[m]] - centre[a[k]]))
            if d1 <= limit[m] and d2 <= limit[k]:
                used |= {k, m}
                out.append(Exchange(int(frame_of[b[k]]), int(rows.obj_ids[rows.row_o[b[k]]]),
                                    int(rows.obj_ids[rows.row_o[b[m]]]), (round(d1, 3), round(d2, 3)),
                                    (int(rows.n_views[b[k]]), int(rows.n_views[b[m]]))))
    return tuple(out)

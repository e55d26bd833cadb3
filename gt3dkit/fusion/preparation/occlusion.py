"""Box edges cut by a nearer object.

A box drawn around the visible part of a person (by a detector, or an annotator in CVAT) ends
where a nearer person begins: that edge says where the occluder is, not where the person ends.
Like an edge at the image border, it only bounds the person.

:func:`cut_edges_of` finds, after the per-frame fits, the labelled edges that lie within a nearer
object's extent in that view (its label there, or its fit's box; up to ``CUT_TOL_SIGMAS`` edge
noise levels outside it, since the cut edge lies on the occluder's own edge), and learns from
the fits' residuals, per edge kind, how much more such edges vary than the others. A kind whose
cut edges vary at least ``RobustConfig.cut_variance_ratio`` times as much (a cut edge then says less than
40 % of what another edge says, and is pulled towards the occluder) has them left out, as the
border's; where the label set draws people whole (WILDTRACK's and MultiviewX's boxes are an
annotation tool's solids) the cut edges vary as the others and every edge is kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gt3dkit.fusion.preparation.boxfit import BoxFit, state_boxes
from gt3dkit.fusion.preparation.rows import Rows
from gt3dkit.geom.camera import Cams
from gt3dkit.geom.conics import cut_by
from gt3dkit.types import B8, BOX_EDGES, F64, I64, JsonDict

#: A nearer object's extent reaches this many edge noise levels beyond its box.
CUT_TOL_SIGMAS = 2.0
#: An object at least this much nearer the camera (m) can cut a box.
CUT_DEPTH_TOL_M = 0.3
#: Cut edges of one kind needed to compare their spread with the others': the median of n
#: squared normal residuals has a relative sd of about 2.3 / sqrt(n), half its value at 20 (windows
#: of a run then decided apart from the whole run), a quarter at 100.
CUT_MIN_EDGES = 100
#: A recording longer than this many frames is judged on a sample of its frames first.
CUT_SAMPLE_FRAMES = 400
#: ... and searched whole where a kind's sampled ratio reaches this share of the ratio needed.
CUT_SAMPLE_GATE = 0.8


@dataclass(frozen=True)
class CutEdges:
    """The kept edges found inside a nearer object's extent ``found (R, C, 4)``, each edge kind's
    variance ratio ``ratio (4,)`` (NaN: too few cut edges to tell), the edges left out,
    ``dropped (R, C, 4)``, and for each found edge the row of a nearer object it lies in,
    ``by (R, C, 4)`` (-1 elsewhere); ``needed``: the ratio that leaves a kind's cut edges out
    (``RobustConfig.cut_variance_ratio``)."""

    found: B8
    ratio: F64
    dropped: B8
    by: I64
    needed: float

    def as_json(self) -> JsonDict:
        """For meta.json: counts and ratios per edge kind."""
        return {"found": dict(zip(BOX_EDGES, self.found.sum(axis=(0, 1)).tolist(), strict=True)),
                "variance_ratio": {k: (round(float(v), 3) if np.isfinite(v) else None)
                                   for k, v in zip(BOX_EDGES, self.ratio, strict=True)},
                "left_out": dict(zip(BOX_EDGES, self.dropped.sum(axis=(0, 1)).tolist(), strict=True)),
                "rule": f"an edge within a nearer object's box (its label or its fit; {CUT_TOL_SIGMAS:g} "
                        f"noise levels beyond it, {CUT_DEPTH_TOL_M:g} m nearer) is cut; a kind's cut edges "
                        f"are left out when their median squared residual is {self.needed:g}x the "
                        f"others' or more ({CUT_MIN_EDGES} cut edges at least)"}


#: Rows of consecutive frames whose pairs are judged together in :func:`find_cut` (every pair of
#: a frame's rows, both ways: a block's arrays stay a few tens of MB).
CUT_BLOCK_ROWS = 2048


def same_frame_pairs(row_t: I64) -> tuple[I64, I64]:
    """Every pair ``a < b`` of rows of one frame (``row_t (R,)`` sorted): ``(P,)`` each, grouped by
    the frames' row counts."""
    starts = np.flatnonzero(np.r_[True, row_t[1:] != row_t[:-1]]) if len(row_t) else np.zeros(0, np.int64)
    sizes = np.diff(np.r_[starts, len(row_t)])
    out_a, out_b = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for n in np.unique(sizes[sizes >= 2]):
        lo = starts[sizes == n]
        i, j = np.triu_indices(int(n), 1)
        out_a.append((lo[:, None] + i).reshape(-1))
        out_b.append((lo[:, None] + j).reshape(-1))
    return np.concatenate(out_a), np.concatenate(out_b)


def find_cut(rows: Rows, cams: Cams, fit: BoxFit, keep: B8, tol_px: float, frames: I64 | None = None
             ) -> tuple[B8, I64]:
    """The kept edges ``keep (R, C, 4)`` of the labels ``rows.box_z`` that lie inside the extent
    of another object of their frame at least :data:`CUT_DEPTH_TOL_M` nearer that camera (its
    label there, or its fit's box; widened by ``tol_px``): ``(R, C, 4)``, in the frames (indices
    into ``rows.frames``) ``frames`` only (None: all), by blocks of about :data:`CUT_BLOCK_ROWS`
    rows of whole frames; and for each such edge the row of a nearer object it lies in
    ``(R, C, 4)`` (-1 elsewhere)."""
    own = state_boxes(fit.center_world, fit.log_axes, cams)  # (R, C, 4)
    own = np.where(fit.ok[:, None, None], own, np.nan)
    label_or_own = np.where(np.isfinite(rows.box_z), rows.box_z, own)
    depth = np.linalg.norm(fit.center_world[:, None, :] - cams.centres[None], axis=-1)
    depth = np.where(fit.ok[:, None], depth, np.nan)
    cut = np.zeros(rows.box_z.shape, bool)
    by = np.full(rows.box_z.shape, -1, np.int64)
    sel = np.arange(len(rows.row_t)) if frames is None else np.flatnonzero(np.isin(rows.row_t, frames))
    t = rows.row_t[sel]
    starts = np.flatnonzero(np.r_[True, t[1:] != t[:-1]]) if len(t) else np.zeros(0, np.int64)
    bounds = np.r_[starts, len(t)]
    k = 0
    while k < len(starts):
        k1 = max(int(np.searchsorted(bounds, bounds[k] + CUT_BLOCK_ROWS, side="right")) - 1, k + 1)
        lo, hi = int(bounds[k]), int(bounds[k1])
        a, b = same_frame_pairs(t[lo:hi])
        a, b = sel[a + lo], sel[b + lo]
        for i, j in ((a, b), (b, a)):  # label i against object j
            c = cut_by(rows.box_z[i], own[j], depth[i], depth[j], CUT_DEPTH_TOL_M, -tol_px)
            c |= cut_by(rows.box_z[i], label_or_own[j], depth[i], depth[j], CUT_DEPTH_TOL_M, -tol_px)
            p, cam, e = np.nonzero(c)
            cut[i[p], cam, e] = True
            by[i[p], cam, e] = j[p]
        k = k1
    cut &= keep
    return cut, np.where(cut, by, -1)


def cut_variance_ratio(residual_px: F64, keep: B8, cut: B8) -> F64:
    """``(4,)`` per edge kind the median squared residual of the kept cut edges over that of the
    other kept edges, each residual first divided by its camera's level for that kind (the median
    of its uncut edges': a camera whose boxes all fit worse, an unsynchronised one, does not make
    its cut edges look cut); NaN with fewer than :data:`CUT_MIN_EDGES` cut edges."""
    out = np.full(4, np.nan)
    ok = keep & np.isfinite(residual_px)
    r2 = np.where(ok, residual_px, 0.0) ** 2
    uncut = ok & ~cut
    for e in range(4):
        level = np.array([np.median(r2[:, c, e][uncut[:, c, e]]) if uncut[:, c, e].any() else np.nan
                          for c in range(r2.shape[1])])  # (C,)
        n2 = r2[..., e] / np.where(level > 0, level, np.nan)[None, :]
        a = n2[ok[..., e] & cut[..., e] & np.isfinite(n2)]
        b = n2[uncut[..., e] & np.isfinite(n2)]
        if len(a) >= CUT_MIN_EDGES and len(b) and np.median(b) > 0:
            out[e] = np.median(a) / np.median(b)
    return out


def cut_edges_of(rows: Rows, cams: Cams, fit: BoxFit, keep: B8, sigma_px: float, needed: float
                 ) -> CutEdges:
    """The edges cut by nearer objects and those the data say to leave out (module doc);
    ``sigma_px`` the typical edge's noise (px); ``needed`` the variance ratio that leaves a kind's
    cut edges out (``RobustConfig.cut_variance_ratio``). A long recording is first judged on every k-th
    frame (:data:`CUT_SAMPLE_FRAMES` of them): the whole is searched only where the sample comes
    near the ratio that leaves edges out (a 4 000-frame crowd of whole boxes took 3.6 s to search,
    a third of its preparation); ``found`` then holds the sample's."""
    tol = CUT_TOL_SIGMAS * sigma_px
    n_frames = len(rows.t_start) - 1
    step = -(-n_frames // CUT_SAMPLE_FRAMES)
    if step > 1:
        sample = np.arange(0, n_frames, step)
        found, by = find_cut(rows, cams, fit, keep, tol, sample)
        ratio = cut_variance_ratio(fit.residual_px, keep & np.isin(rows.row_t, sample)[:, None, None], found)
        if not (np.nan_to_num(ratio) >= CUT_SAMPLE_GATE * needed).any():
            return CutEdges(found, ratio, np.zeros_like(found), by, needed)
    found, by = find_cut(rows, cams, fit, keep, tol)
    ratio = cut_variance_ratio(fit.residual_px, keep, found)
    bad = np.nan_to_num(ratio) >= needed
    return CutEdges(found, ratio, found & bad[None, None, :], by, needed)

r"""Multi-object tracking metrics on ground-plane positions, as the paper reports them.

* MOTA, IDF1, FP, FN, IDs: ``motmetrics``' rules (:func:`gt3dkit.eval.metrics.clear_mot`).
* HOTA (Luiten et al., IJCV 2021): TrackEval's ``HOTA`` metric (its algorithm on arrays,
  :func:`hota`; the tests hold it to TrackEval), with the similarity of a
  truth and a track position ``max(0, 1 - d / cutoff)`` (the ground-plane similarity used
  for multi-view detection), averaged over TrackEval's localisation thresholds.
* OSPA(2) (Beard, Vo & Vo, "A solution for large-scale multi-object tracking", IEEE TSP
  68, 2020, eq. 9-10): no maintained Python package implements it, so it is written out
  here. For tracks ``x`` and ``y`` over the frames ``D_x ∪ D_y`` where either exists,

  .. math::
      \tilde d^{(c)}(x, y) = \frac{1}{|D_x \cup D_y|} \sum_{t \in D_x \cup D_y}
      d^{(c)}(x_t, y_t),\quad d^{(c)} = \min(c, \|x_t - y_t\|)\ \text{if both exist,}\ c
      \ \text{otherwise};

  then OSPA of order ``p`` and cut-off ``c`` between the sets of tracks,
  ``(\frac{1}{n}(\min_\pi \sum_{i \le m} \tilde d(x_i, y_{\pi(i)})^p + c^p (n - m)))^{1/p}``,
  ``m <= n``, over the whole sequence (one window). Defaults: ``c = 1`` m, ``p = 1``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gt3dkit.eval.metrics import (
    BoxErrors,
    MotCounts,
    NearPairs,
    RowErrors,
    errors_of,
    frame_blocks,
    ground_coords,
    idtp,
    near_pairs,
    pair_counts,
    row_errors,
)
from gt3dkit.types import F64, GroundTruth, TrackSet


def ospa2(truth_frame: np.ndarray, truth_id: np.ndarray, truth_xy: F64, est_frame: np.ndarray,
          est_id: np.ndarray, est_xy: F64, cutoff: float = 1.0, order: float = 1.0,
          pairs: NearPairs | None = None) -> float:
    """OSPA(2) between two sets of tracks (see module doc). Positions ``(N, D)``, metres; one row
    per frame and id (of two, the later counts); a row with a non-finite position is absent.

    The track distance over the frames either track is in, ``U = n_x + n_y - n_xy`` (``n_xy``
    the frames both are in), is ``(c U - sum (c - d_t)) / U``: the frames where both are within
    ``c`` of each other (:func:`gt3dkit.eval.metrics.near_pairs`; ``pairs``: the two tables'
    within at least ``c``, when known) bring it below ``c``."""
    ids, code = np.unique(est_id, return_inverse=True)
    if pairs is None:
        pairs = near_pairs(truth_frame, truth_xy, est_frame, est_xy, cutoff)
    parts = Ospa2Parts(truth_frame, id_index(truth_id), truth_xy, cutoff, order)
    parts.part(np.arange(len(truth_frame)), est_frame, code.ravel(), est_xy)
    return parts.result(pairs, np.arange(len(ids)), code.ravel())


def id_index(ids: np.ndarray) -> np.ndarray:
    """Each row's identity as its place among the sorted distinct ids ``(N,)``."""
    return np.unique(ids, return_inverse=True)[1].ravel()


class Ospa2Parts:
    """:func:`ospa2` of tracks that come in parts, each part's frames after the parts' before it
    (:class:`TrackingTally`): each part's track rows (their identities as codes, any numbering
    the parts share) add the frames each track is in and the frames each pair of identities
    shares as they come; the pairs' distances and the assignment come at the end
    (:meth:`result`), exactly the whole tracks' number."""

    def __init__(self, truth_frame: np.ndarray, truth_idx: np.ndarray, truth_xy: F64, cutoff: float = 1.0,
                 order: float = 1.0) -> None:
        """``truth_idx (M,)``: each truth row's identity (:func:`id_index`)."""
        self.cutoff, self.order = float(cutoff), float(order)
        self.truth_frame, self.ti = np.asarray(truth_frame), truth_idx
        self.n_tx = int(truth_idx.max(initial=-1)) + 1  # truth identities
        f = self.truth_frame
        t_rows = _present(self.ti, f - f.min(initial=0), truth_xy)
        self.n_x = np.bincount(self.ti[t_rows], minlength=self.n_tx).astype(float)
        self.on = np.zeros(len(f), bool)
        self.on[t_rows] = True
        self.n_y = np.zeros(0)  # each code's frames
        self.both = np.zeros((self.n_tx, 0))  # each truth id's and code's shared frames
        self._on_e: list[np.ndarray] = []

    def part(self, t_rows: np.ndarray, e_frame: np.ndarray, e_code: np.ndarray, e_xy: F64) -> None:
        """The next part: the truth rows of its frames (``t_rows``, the truth's row numbers), its
        track rows' frames, identity codes and positions."""
        n = max(int(e_code.max(initial=-1)) + 1, len(self.n_y))
        self.n_y = np.r_[self.n_y, np.zeros(n - len(self.n_y))]
        self.both = np.c_[self.both, np.zeros((self.n_tx, n - self.both.shape[1]))]
        e_rows = _present(e_code, e_frame - e_frame.min(initial=0), e_xy)
        on_e = np.zeros(len(e_frame), bool)
        on_e[e_rows] = True
        self._on_e.append(on_e)
        self.n_y += np.bincount(e_code[e_rows], minlength=n)
        t_on = t_rows[self.on[t_rows]]
        frames = np.union1d(self.truth_frame[t_on], e_frame[e_rows])
        if len(frames):
            at_t = np.searchsorted(frames, self.truth_frame[t_on])
            at_e = np.searchsorted(frames, e_frame[e_rows])
            self.both += _frames_shared(self.ti[t_on], at_t, self.n_tx, e_code[e_rows], at_e, n,
                                        len(frames))

    def result(self, pairs: NearPairs, by_id: np.ndarray, ei: np.ndarray) -> float:
        """OSPA(2) of every part: ``pairs`` the truth's and every track row's
        (:func:`gt3dkit.eval.metrics.near_pairs`, in frame order), ``by_id`` the codes in their
        ids' order, ``ei`` every track row's identity (:func:`id_index`)."""
        from scipy.optimize import linear_sum_assignment  # heavy to import (scipy): only where it runs

        c, order, n_tx, n_ey = self.cutoff, self.order, self.n_tx, len(by_id)
        if not n_tx and not n_ey:
            return 0.0
        if not n_tx or not n_ey:
            return c
        n_y = np.r_[self.n_y, np.zeros(n_ey - len(self.n_y))][by_id]
        both = np.c_[self.both, np.zeros((n_tx, n_ey - self.both.shape[1]))][:, by_id]
        union = self.n_x[:, None] + n_y[None] - both
        a, b, d = pairs
        on_e = np.concatenate(self._on_e) if self._on_e else np.zeros(len(ei), bool)
        k = self.on[a] & on_e[b] & (d < c)
        closer = np.bincount(self.ti[a[k]] * n_ey + ei[b[k]], weights=c - d[k],
                             minlength=n_tx * n_ey).reshape(n_tx, n_ey)
        D = (c * union - closer) / np.maximum(union, 1)
        n, m = max(n_tx, n_ey), min(n_tx, n_ey)
        C = D if n_tx <= n_ey else D.T
        r, cc = linear_sum_assignment(C**order)
        cost = float(np.sum(C[r, cc] ** order)) + c**order * (n - m)
        return float((cost / n) ** (1.0 / order))


def _present(ident: np.ndarray, frame_at: np.ndarray, xy: F64) -> np.ndarray:
    """The rows that place an id in a frame: a finite position, the last of an id's rows in a
    frame."""
    key = ident.astype(np.int64) * (int(frame_at.max(initial=0)) + 1) + frame_at
    _, last = np.unique(key[::-1], return_index=True)
    rows = np.sort(len(key) - 1 - last)
    return rows[np.isfinite(xy[rows]).all(axis=1)]


def _frames_shared(a_id: np.ndarray, a_frame: np.ndarray, n_a: int, b_id: np.ndarray, b_frame: np.ndarray,
                   n_b: int, n_frames: int) -> F64:
    """``(n_a, n_b)`` the frames in which each id of table ``a`` and each of ``b`` are both
    present (one row per frame and id): the product of the two sparse presence matrices."""
    from scipy.sparse import csr_matrix

    pa = csr_matrix((np.ones(len(a_id)), (a_id, a_frame)), shape=(n_a, n_frames))
    pb = csr_matrix((np.ones(len(b_id)), (b_id, b_frame)), shape=(n_b, n_frames))
    return np.asarray((pa @ pb.T).toarray(), dtype=float)


#: HOTA's localisation thresholds (TrackEval's ``HOTA.array_labels``)
HOTA_ALPHAS = np.arange(0.05, 0.99, 0.05)


def hota(truth_frame: np.ndarray, truth_id: np.ndarray, truth_xy: F64, est_frame: np.ndarray,
         est_id: np.ndarray, est_xy: F64, cutoff: float = 1.0, pairs: NearPairs | None = None
         ) -> dict[str, float]:
    """HOTA, DetA, AssA on ground positions (similarity ``max(0, 1 - d / cutoff)``), averaged
    over :data:`HOTA_ALPHAS`: TrackEval's ``HOTA.eval_sequence`` written out on arrays.

    (1) Each truth and track identity's potential matches: per frame, the similarity over the
    union of the two rows' similarities (``s / (row sum + column sum - s)``), summed over the
    frames; the global alignment ``A = potential / (n_truth + n_track - potential)``. (2) Per
    frame, the assignment maximising ``A * s`` (Hungarian); a pair counts at threshold alpha
    when ``s >= alpha``. DetA ``= TP / (TP + FN + FP)``, AssA the TP-weighted mean of each
    matched pair's ``matches / (n_truth + n_track - matches)``, HOTA ``= sqrt(DetA AssA)``.

    Written out rather than calling TrackEval because its per-frame loop (threshold by
    threshold in Python) took 1.3 s of a 4 000-frame, 40-person evaluation, the longest part of
    ``gt3d reconstruct``'s truth report; ``tests/eval/test_metrics.py`` holds this to TrackEval
    itself on random scenes with misses, false positives and identity swaps. Only the pairs of
    a frame with a similarity above 0 are looked at (:func:`gt3dkit.eval.metrics.near_pairs`;
    ``pairs``: the two tables' within at least ``cutoff``, when known)."""
    ids, code = np.unique(est_id, return_inverse=True)
    if pairs is None:
        pairs = near_pairs(truth_frame, truth_xy, est_frame, est_xy, cutoff)
    parts = HotaParts(truth_frame, id_index(truth_id), cutoff)
    parts.part(np.arange(len(truth_frame)), est_frame, pairs)
    return parts.result(len(ids), code.ravel())


class HotaParts:
    """:func:`hota` of tracks that come in parts, each part's frames after the parts' before it
    (:class:`TrackingTally`): what each pair of rows brings to (1) (its similarity over the
    union of its two rows') and to (2) (its place in its frame's truth x tracks block) found as
    its part comes; the global alignment, the per-frame assignments and the scores at the end
    (:meth:`result`), exactly the whole tracks' numbers."""

    def __init__(self, truth_frame: np.ndarray, truth_idx: np.ndarray, cutoff: float = 1.0) -> None:
        """``truth_idx (M,)``: each truth row's identity (:func:`id_index`)."""
        self.cutoff, self.truth_frame, self.g_inv = float(cutoff), np.asarray(truth_frame), truth_idx
        self.n_g = int(self.g_inv.max(initial=-1)) + 1
        self.g_count = np.bincount(self.g_inv, minlength=self.n_g).astype(float)
        self._n_est = 0
        # each pair within reach: its truth row, track row, similarity, share of (1), place in its
        # frame's block; each frame's first pair and block shape
        self._pairs: list[tuple[np.ndarray, ...]] = []
        self._frames: list[tuple[np.ndarray, ...]] = []
        self._n_pairs = 0

    def part(self, t_rows: np.ndarray, e_frame: np.ndarray, pairs: NearPairs) -> None:
        """The next part: the truth rows of its frames (``t_rows``, the truth's row numbers), its
        track rows' frames, and their pairs (``a`` into ``t_rows``, ``b`` into the part's rows,
        in frame order: :func:`gt3dkit.eval.metrics.near_pairs`)."""
        c = self.cutoff
        t_frame = self.truth_frame[t_rows]
        k = pairs.d < c  # farther pairs add nothing to (1) and (2): a similarity of 0
        a, b, d = pairs.a[k], pairs.b[k], pairs.d[k]
        sim = 1.0 - d / c
        rows = np.bincount(a, weights=sim, minlength=len(t_rows))  # a truth row's pairs: one frame's
        cols = np.bincount(b, weights=sim, minlength=len(e_frame))
        denom = rows[a] + cols[b] - sim
        iou = np.where(denom > np.finfo(float).eps, sim / np.where(denom > 0, denom, 1.0), 0.0)
        frames = np.union1d(t_frame, e_frame)
        _, lo_t, hi_t, pos_t = frame_blocks(t_frame, frames)
        _, lo_e, hi_e, pos_e = frame_blocks(e_frame, frames)
        at = np.searchsorted(frames, t_frame[a])
        starts = np.flatnonzero(np.r_[True, at[1:] != at[:-1]]) if len(a) else np.zeros(0, np.int64)
        f = at[starts]
        self._pairs.append((t_rows[a], b + self._n_est, sim, iou, pos_t[a], pos_e[b]))
        self._frames.append((starts + self._n_pairs, hi_t[f] - lo_t[f], hi_e[f] - lo_e[f]))
        self._n_est += len(e_frame)
        self._n_pairs += len(a)

    def result(self, n_e: int, e_inv: np.ndarray) -> dict[str, float]:
        """HOTA, DetA, AssA of every part: ``n_e`` track identities, ``e_inv`` every track row's
        (numbered in the ids' order)."""
        from scipy.optimize import linear_sum_assignment  # heavy to import (scipy): only where it runs

        n_a, n_g = len(HOTA_ALPHAS), self.n_g
        if not len(e_inv) or not len(self.g_inv):  # TrackEval's early return: every score 0
            return {"hota": 0.0, "deta": 0.0, "assa": 0.0}
        e_count = np.bincount(e_inv, minlength=n_e).astype(float)
        both = self.g_count.repeat(n_e) + np.tile(e_count, n_g)  # (n_g * n_e,) the two identities' rows
        none = np.zeros(0, np.int64)
        a, b, sim, iou, i_all, j_all = (np.concatenate(x) for x in zip(
            *self._pairs, strict=True)) if self._pairs else (none, none, np.zeros(0), np.zeros(0), none, none)
        starts, n_t, n_h = (np.concatenate(x).tolist() for x in zip(*self._frames, strict=True)
                            ) if self._frames else ([], [], [])
        cell = self.g_inv[a] * n_e + e_inv[b]
        potential = np.bincount(cell, weights=iou, minlength=n_g * n_e)  # (1)
        align = potential / (both - potential)
        score = align[cell] * sim
        picked = []
        for k0, k1, nt, nh in zip(starts, [*starts[1:], len(a)][:len(starts)], n_t, n_h, strict=True):  # (2)
            block = np.zeros((nt, nh))  # the frame's truth x tracks
            i, j = i_all[k0:k1], j_all[k0:k1]
            block[i, j] = score[k0:k1]
            pair = np.full(block.shape, -1)
            pair[i, j] = np.arange(k0, k1)
            r, c = linear_sum_assignment(-block)
            picked.append(pair[r, c])
        m = np.concatenate(picked) if picked else np.zeros(0, np.int64)
        m = m[m >= 0]  # a pair without similarity counts at no threshold
        ok = sim[m][None] >= HOTA_ALPHAS[:, None] - np.finfo(float).eps  # (A, M)
        tp = ok.sum(axis=1).astype(float)
        matches = np.stack([np.bincount(cell[m[ok[k]]], minlength=n_g * n_e)
                            for k in range(n_a)]).astype(float)
        fn, fp = len(self.g_inv) - tp, len(e_inv) - tp
        ass = (matches * (matches / np.maximum(1.0, both - matches))).sum(axis=1) / np.maximum(1.0, tp)
        det = tp / np.maximum(1.0, tp + fn + fp)
        return {"hota": float(np.mean(np.sqrt(det * ass))), "deta": float(np.mean(det)),
                "assa": float(np.mean(ass))}


def tracking_scores(tracks: TrackSet, truth: GroundTruth, up: F64, cutoff_m: float = 1.0
                    ) -> dict[str, float | int]:
    """MOTA, IDF1, FP, FN, IDs, HOTA, DetA, AssA and OSPA(2) on ground positions (the tracks in
    one part: :class:`TrackingTally`)."""
    return TrackingTally(truth, up, cutoff_m).add(tracks).scores()


class TrackingTally:
    """:func:`tracking_scores` and :func:`gt3dkit.eval.metrics.box_errors` of tracks that come in
    parts, each part's frames after every frame of the parts before it (a long sequence's
    windows, as they finish: :mod:`gt3dkit.windows`). What adds up is done as each part comes:
    the pairs within reach (:func:`gt3dkit.eval.metrics.near_pairs`, frame by frame), CLEAR-MOT's
    frame loop, from the state the parts before it left
    (:class:`gt3dkit.eval.metrics.MotCounts`), and the matched rows' errors. What needs every
    frame is done at the end, on them: IDF1's identity pairing, HOTA's alignment and per-frame
    assignment, OSPA(2)'s track assignment. The numbers are the whole tracks' however they are
    cut (:func:`tracking_scores` is the one-part case; ``tests/eval/test_metrics.py``).

    On the 8 000-frame, 60-person box scene the whole computation took 1.3 s after the last
    window; cut in 30 parts, the parts take 0.7-0.9 s in all, while the windows run, and the end
    0.23 s (HOTA's per-frame assignments, 0.18 s of it, need the alignment of every frame)."""

    def __init__(self, truth: GroundTruth, up: F64, cutoff_m: float = 1.0) -> None:
        self.truth, self.up, self.cutoff = truth, np.asarray(up, float), float(cutoff_m)
        self._g_t = ground_coords(np.nan_to_num(truth.center_world), self.up)
        self._t_idx = id_index(truth.track_id)
        self._by_frame = np.argsort(truth.frame, kind="stable")
        self._t_frames = np.asarray(truth.frame)[self._by_frame]
        self._done = 0  # the truth rows (in frame order) whose frames are done
        self._through: int | None = None  # the last frame done
        self._mot = MotCounts(int(self._t_idx.max(initial=-1)) + 1)
        self._hota = HotaParts(truth.frame, self._t_idx, self.cutoff)
        self._ospa = Ospa2Parts(truth.frame, self._t_idx, self._g_t, self.cutoff)
        self._ids, self._codes = np.zeros(0, np.int64), np.zeros(0, np.int64)  # the tracks' ids seen
        self._code: list[np.ndarray] = []  # each part's rows' identity codes
        self._pairs: list[NearPairs] = []
        self._errors: list[RowErrors] = []
        self._n = 0  # track rows so far
        self._covered = 0  # truth rows with an estimate so far
        self._result: tuple[dict[str, float | int], BoxErrors] | None = None

    def add(self, tracks: TrackSet) -> TrackingTally:
        """The next part: rows whose frames all come after the previous parts' (in any order)."""
        if self._result is not None:
            raise ValueError("the tally is closed: its scores were taken")
        if len(tracks):  # (an empty part's frames are done with the next part's)
            first, last = int(np.min(tracks.frame)), int(np.max(tracks.frame))
            if self._through is not None and first <= self._through:
                raise ValueError(f"a part's frames ({first}-{last}) must come after the previous parts' "
                                 f"(to {self._through})")
            self._block(tracks, last)
        return self

    def _block(self, tracks: TrackSet | None, through: int | None) -> None:
        """The truth's frames after the last done and up to ``through`` (None: every one left),
        with the track rows ``tracks`` (all in those frames; None: none)."""
        t_frames = self._t_frames
        end = len(t_frames) if through is None else int(np.searchsorted(t_frames, through, "right"))
        rows = np.sort(self._by_frame[self._done:end])  # in the truth's table order
        self._done, self._through = end, through
        truth, g_t = self.truth.select(rows), self._g_t[rows]
        if tracks is None:  # frames with truth rows alone
            none = np.zeros(0, np.int64)
            self._mot.block(truth.frame, self._t_idx[rows], g_t, none, none, np.zeros((0, 3)),
                            NearPairs.concat([]), self.cutoff)
            return
        g_e = ground_coords(tracks.center_world, self.up)
        # a hair beyond the cut-off: each metric makes its own test
        pairs = near_pairs(truth.frame, g_t, tracks.frame, g_e, self.cutoff * (1.0 + 1e-9))
        code = self._coded(tracks.track_id)
        self._mot.block(truth.frame, self._t_idx[rows], g_t, tracks.frame, code, g_e, pairs, self.cutoff)
        self._hota.part(rows, tracks.frame, pairs)
        self._ospa.part(rows, tracks.frame, code, g_e)
        self._pairs.append(NearPairs(rows[pairs.a], pairs.b + self._n, pairs.d))
        e = row_errors(tracks, truth, self.up)
        self._errors.append(dataclasses.replace(e, truth_row=rows[e.truth_row]))
        self._covered += len(np.unique(e.truth_row))  # (a part's truth rows are its own)
        self._code.append(code)
        self._n += len(tracks)

    def _coded(self, ids: np.ndarray) -> np.ndarray:
        """Each track id's code for CLEAR-MOT's state: the order the ids were first seen in (within
        a part, sorted; so one part's codes are the ids' ranks)."""
        u = np.unique(ids)
        new = u[~np.isin(u, self._ids)]
        if len(new):
            ids_all = np.r_[self._ids, new]
            codes = np.r_[self._codes, np.arange(len(self._codes), len(self._codes) + len(new))]
            o = np.argsort(ids_all, kind="stable")
            self._ids, self._codes = ids_all[o], codes[o]
        return self._codes[np.searchsorted(self._ids, ids)]

    def _finished(self) -> tuple[dict[str, float | int], BoxErrors]:
        if self._result is None:
            self._block(None, None)
            t, c = self.truth, self.cutoff
            code = np.concatenate(self._code) if self._code else np.zeros(0, np.int64)
            rank = np.empty(len(self._codes), np.int64)  # each code's place among the ids (sorted)
            rank[self._codes] = np.arange(len(self._codes))
            ei = rank[code]
            pairs = NearPairs.concat(self._pairs)
            out: dict[str, float | int] = dict(self._mot.scores(
                len(t.frame), len(code), idtp(pair_counts(self._ids[ei], t.track_id, pairs, c)[0])))
            out.update(self._hota.result(len(self._ids), ei))
            out["ospa2_m"] = self._ospa.result(pairs, self._codes, ei)
            self._result = out, errors_of(RowErrors.concat(self._errors), self._covered, len(t.frame), out)
            self._code, self._pairs, self._errors = [], [], []
        return self._result

    def scores(self) -> dict[str, float | int]:
        """:func:`tracking_scores` of every part (none comes after)."""
        return self._finished()[0]

    def errors(self) -> BoxErrors:
        """:func:`gt3dkit.eval.metrics.box_errors` of every part (none comes after)."""
        return self._finished()[1]

    @property
    def rows(self) -> int:
        """The track rows added so far."""
        return self._n

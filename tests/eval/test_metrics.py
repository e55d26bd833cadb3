"""Tracking metrics on hand-worked toy sequences."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from gt3dkit.eval.metrics import box_errors, clear_mot, ground_coords, near_pairs
from gt3dkit.eval.tracking import hota, ospa2, tracking_scores
from gt3dkit.types import GroundTruth, TrackSet

UP = np.array([0.0, 0.0, 1.0])


def _truth(frame, tid, xy) -> GroundTruth:
    xy = np.asarray(xy, float)
    n = len(frame)
    return GroundTruth(np.array(frame), np.array(tid), np.c_[xy, np.full(n, 0.9)],
                       np.full((n, 3), 0.3), np.zeros((n, 0, 3)))


def _tracks(frame, tid, xy) -> TrackSet:
    xy = np.asarray(xy, float)
    n = len(frame)
    return TrackSet(np.array(frame), np.array(tid), np.c_[xy, np.full(n, 0.9)],
                    np.full((n, 3), 0.3), np.full((n, 3), 0.01), np.full(n, 2),
                    np.zeros((n, 0, 3)), np.zeros((n, 0)))


# Two people over two frames; the estimate of person 1 is missing in frame 2.
TRUTH = _truth([1, 1, 2, 2], [0, 1, 0, 1], [[0, 0], [5, 5], [0, 0], [5, 5]])
EST = _tracks([1, 1, 2], [0, 1, 0], [[0.1, 0], [5, 5.2], [0, 0.3]])


def test_ospa2_hand_worked() -> None:
    # track 0: (0.1 + 0.3) / 2 = 0.2; track 1: (0.2 + c) / 2 = 0.6; (0.2 + 0.6) / 2 = 0.4
    assert ospa2(TRUTH.frame, TRUTH.track_id, TRUTH.center_world[:, :2], EST.frame, EST.track_id,
                 EST.center_world[:, :2], cutoff=1.0, order=1) == pytest.approx(0.4)
    # an extra false track adds c / n: tracks (0.2, 0.6, 1) over n = 3
    est3 = _tracks([1, 1, 2, 2], [0, 1, 0, 9], [[0.1, 0], [5, 5.2], [0, 0.3], [20, 20]])
    assert ospa2(TRUTH.frame, TRUTH.track_id, TRUTH.center_world[:, :2], est3.frame,
                 est3.track_id, est3.center_world[:, :2]) == pytest.approx((0.2 + 0.6 + 1) / 3)
    # identical tracks: 0; order 2 of the first case: sqrt((0.2^2 + 0.6^2) / 2)
    assert ospa2(TRUTH.frame, TRUTH.track_id, TRUTH.center_world[:, :2], TRUTH.frame,
                 TRUTH.track_id, TRUTH.center_world[:, :2]) == 0.0
    assert ospa2(TRUTH.frame, TRUTH.track_id, TRUTH.center_world[:, :2], EST.frame, EST.track_id,
                 EST.center_world[:, :2], order=2) == pytest.approx(np.sqrt((0.04 + 0.36) / 2))


def test_clear_mot_hand_worked() -> None:
    m = clear_mot(EST, TRUTH, UP)
    # 4 truth objects, 1 miss, no false positive, no switch: MOTA = 1 - 1/4
    assert m["mota"] == pytest.approx(0.75) and m["fn"] == 1 and m["fp"] == 0 and m["ids"] == 0
    # IDF1 = 2 IDTP / (2 IDTP + IDFP + IDFN) = 6 / (6 + 0 + 1)
    assert m["idf1"] == pytest.approx(6 / 7)


def test_metrics_ignore_relabelling() -> None:
    relabel = _tracks(EST.frame, EST.track_id + 100, EST.center_world[:, :2])
    a, b = tracking_scores(EST, TRUTH, UP), tracking_scores(relabel, TRUTH, UP)
    for k in ("mota", "idf1", "hota", "ospa2_m"):
        assert a[k] == pytest.approx(b[k])


def test_hota_perfect_and_id_switch() -> None:
    xy = TRUTH.center_world[:, :2]
    assert hota(TRUTH.frame, TRUTH.track_id, xy, TRUTH.frame, TRUTH.track_id, xy)["hota"] == \
        pytest.approx(1.0)
    swapped = np.array([0, 1, 1, 0])  # identities swap between frames
    s = hota(TRUTH.frame, TRUTH.track_id, xy, TRUTH.frame, swapped, xy)
    # every TP (g, p) has TPA 1, FNA 1 (g matched to the other p), FPA 1: A = 1/3
    assert s["deta"] == pytest.approx(1.0) and s["assa"] == pytest.approx(1 / 3)
    assert s["hota"] == pytest.approx(np.sqrt(1 / 3))


def test_box_errors_hand_worked() -> None:
    e = box_errors(EST, TRUTH, UP)
    assert e.ground_mean_m == pytest.approx((0.1 + 0.2 + 0.3) / 3)
    assert e.coverage == pytest.approx(0.75) and e.height_mean_m == 0.0


def _random_tracking(rng: np.random.Generator) -> tuple[TrackSet, GroundTruth]:
    """Walkers (crowded or sparse) with misses, noisy estimates, identity swaps, false tracks."""
    F, P = int(rng.integers(3, 30)), int(rng.integers(1, 12))
    spread = float(rng.choice([2.0, 5.0, 20.0]))
    pos, vel = rng.uniform(0, spread, (P, 2)), rng.normal(0, 0.1, (P, 2))
    rows = [(f, p, *(pos[p] + f * vel[p])) for f in range(F) for p in range(P) if rng.random() < 0.9]
    t = np.array(rows).reshape(-1, 4)
    keep = rng.random(len(t)) > float(rng.choice([0.0, 0.1]))
    e = t[keep].copy()
    e[:, 1] += 100
    e[:, 2:] += rng.normal(0, float(rng.choice([0.1, 0.4])), (len(e), 2))
    swap = rng.random(len(e)) < float(rng.choice([0.0, 0.05]))
    e[swap, 1] = rng.integers(100, 100 + P, swap.sum())
    n_fp = int(rng.integers(0, 10))
    fake = np.c_[rng.integers(0, F, n_fp), rng.integers(500, 505, n_fp), rng.uniform(0, spread, (n_fp, 2))]
    e = np.concatenate([e, fake])
    _, first = np.unique(e[:, :2], axis=0, return_index=True)  # one row per (frame, id)
    e = e[np.sort(first)]
    i8 = np.int64
    return (_tracks(e[:, 0].astype(i8), e[:, 1].astype(i8), e[:, 2:]),
            _truth(t[:, 0].astype(i8), t[:, 1].astype(i8), t[:, 2:]))


def _trackeval_hota(tf: np.ndarray, ti: np.ndarray, txy: np.ndarray, ef: np.ndarray, ei: np.ndarray,
                    exy: np.ndarray) -> dict[str, float]:
    """TrackEval's own HOTA, its input built frame by frame as its docs describe."""
    from trackeval.metrics import HOTA

    frames = np.union1d(tf, ef)
    _, g_inv = np.unique(ti, return_inverse=True)
    e_ids, e_inv = np.unique(ei, return_inverse=True)
    data: dict[str, Any] = {"num_timesteps": len(frames), "num_gt_ids": len(np.unique(ti)),
                            "num_tracker_ids": len(e_ids), "num_gt_dets": len(ti),
                            "num_tracker_dets": len(ei),
                            "gt_ids": [], "tracker_ids": [], "similarity_scores": []}
    for f in frames:
        gi, hi = np.flatnonzero(tf == f), np.flatnonzero(ef == f)
        d = np.linalg.norm(txy[gi][:, None] - exy[hi][None], axis=-1)
        data["gt_ids"].append(g_inv[gi])
        data["tracker_ids"].append(e_inv[hi])
        data["similarity_scores"].append(np.maximum(0.0, 1.0 - d))
    res = HOTA({"PRINT_CONFIG": False}).eval_sequence(data)
    return {"hota": float(np.mean(res["HOTA"])), "deta": float(np.mean(res["DetA"])),
            "assa": float(np.mean(res["AssA"]))}


def test_hota_equals_trackeval() -> None:
    """Our HOTA against TrackEval's ``HOTA.eval_sequence`` (the algorithm it is written from)."""
    rng = np.random.default_rng(2)
    for _ in range(150):
        est, truth = _random_tracking(rng)
        args = (truth.frame, truth.track_id, truth.center_world[:, :2], est.frame, est.track_id,
                est.center_world[:, :2])
        ours, theirs = hota(*args), _trackeval_hota(*args)
        for k in ("hota", "deta", "assa"):
            assert ours[k] == pytest.approx(theirs[k], abs=1e-12), (k, ours, theirs)
    empty = np.zeros(0, np.int64)
    assert hota(TRUTH.frame, TRUTH.track_id, TRUTH.center_world[:, :2], empty, empty,
                np.zeros((0, 2)))["hota"] == 0.0


def test_near_pairs_are_every_close_same_frame_pair_once() -> None:
    """Every pair of rows in the same frame within the cut-off, once, grouped by frame, against
    brute force; in small chunks too; a NaN position pairs with none; the distance exactly
    ``np.linalg.norm``'s."""
    import gt3dkit.eval.metrics as metrics

    rng = np.random.default_rng(3)
    for trial in range(40):
        n_a, n_b = int(rng.integers(0, 200)), int(rng.integers(0, 150))
        fa, fb = rng.integers(0, 30, n_a), rng.integers(5, 40, n_b)
        scale = float(rng.choice([1.0, 5.0, 100.0]))
        xa, xb = rng.uniform(0, scale, (n_a, 3)), rng.uniform(0, scale, (n_b, 3))
        if n_a and trial % 3 == 0:
            xa[rng.integers(0, n_a)] = np.nan
        if n_b and trial % 4 == 0:  # exactly at the cut-off counts
            i = int(rng.integers(0, n_b))
            if n_a:
                fb[i], xb[i] = fa[0], xa[0] + np.array([0.0, 1.0, 0.0])
        want = [(i, j) for i in range(n_a) for j in range(n_b)
                if fa[i] == fb[j] and np.linalg.norm(xa[i] - xb[j]) <= 1.0]
        want.sort(key=lambda p: (fa[p[0]], p[0], p[1]))
        for chunk in (1 << 20, 7):
            old, metrics.CANDIDATES_PER_CHUNK = metrics.CANDIDATES_PER_CHUNK, chunk
            try:
                ia, ib, d = near_pairs(fa, xa, fb, xb, 1.0)
            finally:
                metrics.CANDIDATES_PER_CHUNK = old
            got = list(zip(ia.tolist(), ib.tolist(), strict=True))
            assert sorted(got, key=lambda p: (fa[p[0]], p[0], p[1])) == want  # each pair once
            by = [(fa[i], i) for i in ia.tolist()]
            assert by == sorted(by)  # by frame, a's rows in table order
            assert np.array_equal(d, np.linalg.norm(xa[ia] - xb[ib], axis=-1))


def _ospa2_brute(tf: np.ndarray, ti: np.ndarray, txy: np.ndarray, ef: np.ndarray, ei: np.ndarray,
                 exy: np.ndarray, c: float, p: float) -> float:
    """OSPA(2) straight from its definition (Beard, Vo & Vo 2020, eq. 9-10), track by track and
    frame by frame, every assignment of the smaller set tried."""
    from itertools import permutations

    def tracks(f: np.ndarray, ids: np.ndarray, xy: np.ndarray) -> list[dict[int, np.ndarray]]:
        return [{int(f[k]): xy[k] for k in np.flatnonzero(ids == i)} for i in np.unique(ids)]

    def dist(x: dict[int, np.ndarray], y: dict[int, np.ndarray]) -> float:
        frames = set(x) | set(y)
        return sum(min(c, float(np.linalg.norm(x[f] - y[f]))) if f in x and f in y else c
                   for f in frames) / len(frames)

    xs, ys = tracks(tf, ti, txy), tracks(ef, ei, exy)
    if len(xs) > len(ys):
        xs, ys = ys, xs
    n, m = len(ys), len(xs)
    best = min(sum(dist(x, ys[j]) ** p for x, j in zip(xs, perm, strict=True))
               for perm in permutations(range(n), m))
    return float(((best + c**p * (n - m)) / n) ** (1 / p))


def test_ospa2_equals_its_definition() -> None:
    """OSPA(2) against the definition written out by brute force on random small scenes."""
    rng = np.random.default_rng(4)
    for _ in range(60):
        F, nt, ne = int(rng.integers(1, 8)), int(rng.integers(1, 5)), int(rng.integers(1, 5))
        def table(n: int, F: int = F) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            rows = [(f, i) for f in range(F) for i in range(n) if rng.random() < 0.7] or [(0, 0)]
            fr, ids = np.array(rows).T
            return fr, ids, rng.uniform(0, float(rng.choice([0.5, 3.0])), (len(fr), 2))
        tf, ti, txy = table(nt)
        ef, ei, exy = table(ne)
        for c, p in ((1.0, 1.0), (0.7, 2.0)):
            assert ospa2(tf, ti, txy, ef, ei + 10, exy, c, p) == pytest.approx(
                _ospa2_brute(tf, ti, txy, ef, ei + 10, exy, c, p), abs=1e-12)


def test_clear_mot_equals_motmetrics() -> None:
    """Our CLEAR MOT against motmetrics' own accumulator (the rules it is written from)."""
    import motmetrics as mm

    rng = np.random.default_rng(1)
    switches = 0
    for _ in range(150):
        est, truth = _random_tracking(rng)
        acc = mm.MOTAccumulator(auto_id=False)
        for f in np.union1d(truth.frame, est.frame):
            gi, hi = np.flatnonzero(truth.frame == f), np.flatnonzero(est.frame == f)
            d2 = mm.distances.norm2squared_matrix(truth.center_world[gi, :2], est.center_world[hi, :2],
                                                  max_d2=1.0)
            acc.update(truth.track_id[gi].tolist(), est.track_id[hi].tolist(), d2, frameid=int(f))
        s = mm.metrics.create().compute(acc, metrics=["mota", "idf1", "num_false_positives", "num_misses",
                                                      "num_switches"], name="x")
        ours = clear_mot(est, truth, UP)
        assert ours["mota"] == pytest.approx(float(s["mota"].iloc[0]), abs=1e-12)
        assert ours["idf1"] == pytest.approx(float(s["idf1"].iloc[0]), abs=1e-12)
        assert (ours["fp"], ours["fn"], ours["ids"]) == (int(s["num_false_positives"].iloc[0]),
                                                         int(s["num_misses"].iloc[0]),
                                                         int(s["num_switches"].iloc[0]))
        switches += ours["ids"]
    assert switches > 50  # the cases exercise identity switches


def test_tracking_scores_share_one_set_of_pairs() -> None:
    """``tracking_scores`` finds the pairs once for every metric: each score as its own
    function gives it alone, at two reaches."""
    rng = np.random.default_rng(5)
    for _ in range(40):
        est, truth = _random_tracking(rng)
        g_t, g_e = ground_coords(truth.center_world, UP), ground_coords(est.center_world, UP)
        for reach in (1.0, 0.3):
            got = tracking_scores(est, truth, UP, reach)
            want = {**clear_mot(est, truth, UP, reach),
                    **hota(truth.frame, truth.track_id, g_t, est.frame, est.track_id, g_e, reach),
                    "ospa2_m": ospa2(truth.frame, truth.track_id, g_t, est.frame, est.track_id, g_e, reach)}
            for k, v in want.items():
                assert got[k] == pytest.approx(v, abs=1e-12), (k, got, want)
    far = _tracks(EST.frame, EST.track_id, EST.center_world[:, :2] + 10.0)  # no pair within reach
    s = tracking_scores(far, TRUTH, UP)
    assert (s["hota"], s["idf1"], s["ospa2_m"]) == (0.0, 0.0, 1.0)
    assert (s["fp"], s["fn"]) == (len(EST.frame), len(TRUTH.frame))


def test_tally_in_parts_gives_the_whole_scores() -> None:
    """``TrackingTally`` fed the tracks in parts of consecutive frames (a long sequence's windows
    as they finish), parts with no row, truth-only frames between parts and after the last
    among them, truth rows given twice and positions not given, gives exactly the whole tracks'
    scores and errors; the identity switches are the whole run's across the cuts too (the state
    goes on from part to part)."""
    from gt3dkit.api import take_rows
    from gt3dkit.eval.tracking import TrackingTally

    rng = np.random.default_rng(7)
    switches = cut_at_switch = matched = 0
    for _ in range(120):
        est, truth = _random_tracking(rng)
        order = np.lexsort((est.track_id, est.frame))  # as the windows' rows come
        est = take_rows(est, order)
        if rng.random() < 0.5:  # the truth's ids (the box errors pair rows by frame and id)
            est = dataclasses.replace(est, track_id=est.track_id - 100)
        if rng.random() < 0.3:  # truth rows twice, positions not given (NaN), in both tables
            again = rng.random(len(truth.frame)) < 0.05
            truth = GroundTruth.concat([truth, truth.select(again)])
            off = rng.random(len(truth.frame))[:, None] < 0.05
            truth = dataclasses.replace(truth, center_world=np.where(off, np.nan, truth.center_world))
            off = rng.random(len(est.frame))[:, None] < 0.05
            est = dataclasses.replace(est, center_world=np.where(off, np.nan, est.center_world))
        for reach in (1.0, 0.4):
            frames = np.union1d(truth.frame, est.frame)
            cuts = np.sort(rng.choice(frames, size=min(len(frames), int(rng.integers(1, 6))), replace=False))
            tally = TrackingTally(truth, UP, reach)
            lo = -1
            for hi in [*cuts.tolist(), int(frames.max())]:
                part = (est.frame > lo) & (est.frame <= hi)
                tally.add(take_rows(est, part))
                lo = hi
            assert tally.rows == len(est.frame)
            whole = tracking_scores(est, truth, UP, reach)
            assert tally.scores() == whole
            got, want = tally.errors().as_dict(), box_errors(est, truth, UP, reach, mot=whole).as_dict()
            np.testing.assert_equal(got, want)  # (NaN where no row pairs)
            matched += got["rows_matched"]
            switches += int(whole["ids"])
            cut_at_switch += int(whole["ids"] > 0 and len(cuts) > 1)
    assert switches > 50 and cut_at_switch > 20 and matched > 1000  # switches, in runs that were cut
    tally = TrackingTally(TRUTH, UP).add(take_rows(EST, EST.frame == 2))
    with pytest.raises(ValueError, match="must come after"):
        tally.add(take_rows(EST, EST.frame == 1))

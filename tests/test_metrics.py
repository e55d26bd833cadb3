"""Tracking metrics on hand-worked toy sequences."""

from __future__ import annotations

import numpy as np
import pytest

from gt3dkit.eval.metrics import box_errors, clear_mot
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

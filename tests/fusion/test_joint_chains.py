"""The joints' compiled chains (gt3dkit.fusion.ukf.jointupdate.run_joints: every joint of every person
its own six-entry filter, the ellipsoid by the boxes' chains) against the filter over frames
(run_frames, joints split): the same steps in another loop order, so with one update pass the
same numbers to rounding, and with several within the iterated update's convergence tolerance
(a joint's filter stops iterating on its own entries' spread). Fading, the spread of a
manoeuvre over a gap, the bones' information, some objects at per-row noise, boxes beside the
keypoints; and the steps written anew for the chains against numpy."""

from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.api import dense_frames, load_scene
from gt3dkit.fusion.motion import StateLayout, joint_step
from gt3dkit.fusion.ukf import smoother as us
from gt3dkit.fusion.ukf.bones import JointInfo
from gt3dkit.fusion.ukf.jointupdate import add_info, run_joints
from gt3dkit.fusion.ukf.measurement import Model
from gt3dkit.sim import Errors, simulate_skeletons, write_skeleton_scene
from tests.oracles_frames import add_joint_info, run_frames


def _held(a, b, lay: StateLayout, one_pass: bool, entries: np.ndarray | None = None) -> None:
    """``b`` (the chains) against ``a`` (the frames' filter) on the state entries ``entries``
    (default: the joints')."""
    e = np.arange(lay.joints.start, lay.n) if entries is None else entries
    Pa, Pb = np.asarray(a.P)[:, e][:, :, e], np.asarray(b.P)[:, e][:, :, e]
    ran = np.einsum("rii->r", Pa) > 0
    sd = np.sqrt(np.abs(np.einsum("rii->ri", Pa[ran])))  # (abs: see the boxes' test)
    dx = np.abs(b.x[ran][:, e] - a.x[ran][:, e]) / sd
    assert dx.max() < (1e-8 if one_pass else 0.02)
    np.testing.assert_allclose(Pb, Pa, rtol=1e-7 if one_pass else 0.05, atol=1e-12 if one_pass else 1e-9)
    np.testing.assert_allclose(b.loglik_rows, a.loglik_rows, rtol=1e-9 if one_pass else 1e-4, atol=1e-8)
    np.testing.assert_allclose(b.nis, a.nis, rtol=1e-8 if one_pass else 1e-3, atol=1e-8)
    np.testing.assert_array_equal(b.dof, a.dof)
    assert a.predictions_faded == b.predictions_faded
    if a.weights is not None:
        np.testing.assert_allclose(b.weights, a.weights, atol=1e-9 if one_pass else 1e-3)


@pytest.mark.parametrize("case", ["plain", "fade", "bones", "search"])
@pytest.mark.parametrize("passes", [1, 4])
def test_joint_chains_equal_the_filter_over_frames(skeleton_prepared, case: str, passes: int) -> None:
    scene, pre, model, cfg = skeleton_prepared
    cfg = replace(cfg, iterations=passes, joint_accel_sd=0.01 if case == "fade" else cfg.joint_accel_sd)
    init = us.initial_states(model, cfg)
    kw: dict = {"collect": True, "fade": True, "on": None, "noise_rows": None}
    if case == "bones":
        first = run_frames(model, init, cfg, scene.fps, collect=True)
        msgs, _ = us.bone_messages_of(model, cfg, first, pre.skeleton)
        assert msgs.info.any()
        model = replace(model, joint_info=msgs)
    if case == "search":
        on = model.rows.row_o == 1
        kw = {"collect": True, "fade": False, "on": on,
              "noise_rows": {"joint_accel_sd": np.where(model.rows.frames[model.rows.row_t] % 2, 0.3, 1.5)}}
        cfg = replace(cfg, smooth=False)
    a = run_frames(model, init, cfg, scene.fps, **kw)
    b = run_joints(model, init, cfg, scene.fps, **kw)
    if case == "fade":
        assert b.predictions_faded > 0
    _held(a, b, model.layout, passes == 1)
    if case == "search":
        assert np.all(b.loglik_rows[~kw["on"]] == 0) and np.all(b.x[~kw["on"]] == 0)


def test_joint_chains_spread_a_manoeuvre_over_a_gap_as_the_frames_filter(tmp_path: Path) -> None:
    """Rows without views between labelled ones (a gap in a dense grid) and a process noise far
    too small: predictions after the gap are faded and the manoeuvre spread over the gap."""
    root = tmp_path / "in"
    sim = simulate_skeletons("native", seed=3, frames=14, people=2, cameras=5, noise_px=1.0,
                             errors=Errors(gap=(4, 9)))
    write_skeleton_scene(sim, root, "native")
    est = us.UKFSmoother()
    model = Model.of(est.prepare(dense_frames(load_scene(root), None)))
    assert not model.mask.any(axis=1).all()  # rows without a view
    cfg = replace(est.config, accel_sd=0.5, shape_sd=0.01, joint_accel_sd=0.003, iterations=1)
    init = us.initial_states(model, cfg)
    a = run_frames(model, init, cfg, 30.0, collect=True)
    b = run_joints(model, init, cfg, 30.0, collect=True)
    assert b.predictions_faded > 0
    _held(a, b, model.layout, True)


def _with_boxes(root: Path) -> None:
    """Add ``boxes.csv`` to a native keypoint folder: each person-view's keypoints' bounding box,
    10 % wider on each side."""
    pts: dict[tuple[str, str, str], list[tuple[float, float]]] = {}
    with open(root / "keypoints.csv", newline="") as f:
        for r in csv.DictReader(f):
            pts.setdefault((r["frame"], r["camera"], r["id"]), []).append((float(r["u"]), float(r["v"])))
    with open(root / "boxes.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "camera", "id", "xmin", "ymin", "xmax", "ymax"])
        for (fr, cam, i), p in pts.items():
            a = np.array(p)
            lo, hi = a.min(axis=0), a.max(axis=0)
            pad = 0.1 * (hi - lo)
            w.writerow([fr, cam, i, *(lo - pad).round(2), *(hi + pad).round(2)])


@pytest.mark.parametrize("passes", [1, 4])
def test_joint_chains_with_boxes_equal_the_filter_over_frames(tmp_path: Path, passes: int) -> None:
    """Boxes beside the keypoints: the ellipsoid's filter (the boxes' chains) and the joints'. (Both
    smooth a log semi-axis's variance a little below zero in a few rows of this 8-frame scene,
    whose boxes are the keypoints' outlines: alike, to rounding.)"""
    root = tmp_path / "in"
    write_skeleton_scene(simulate_skeletons("native", seed=4, frames=8, people=2, cameras=4, noise_px=1.0),
                         root, "native")
    _with_boxes(root)
    est = us.UKFSmoother()
    pre = est.prepare(load_scene(root))
    assert pre.use_box and pre.use_kpt
    model = Model.of(pre)
    cfg = replace(est.config, accel_sd=0.5, shape_sd=0.01, joint_accel_sd=0.5, iterations=passes)
    init = us.initial_states(model, cfg)
    a = run_frames(model, init, cfg, 30.0, collect=True)
    b = run_joints(model, init, cfg, 30.0, collect=True)
    _held(a, b, model.layout, passes == 1, np.arange(model.layout.n))


def test_joint_steps_equal_numpy() -> None:
    """The chains' transition against the layout's (one joint), and the bones' information added
    to one joint against :func:`tests.oracles_frames.add_joint_info`."""
    lay = StateLayout(1)
    F, Q = lay.transition(np.array([0.04]), 0.3, 0.01, joint_accel_sd=1.7)
    Fj, Qj = np.empty((6, 6)), np.empty((6, 6))
    joint_step(0.04, 1.7, Fj, Qj)
    e = np.r_[lay.joints.start:lay.n]
    np.testing.assert_allclose(Fj, F[0][np.ix_(e, e)], rtol=0, atol=0)
    np.testing.assert_allclose(Qj, Q[0][np.ix_(e, e)], rtol=1e-15, atol=0)
    rng = np.random.default_rng(5)
    A = rng.normal(size=(6, 6))
    P = A @ A.T + 0.1 * np.eye(6)
    x = rng.normal(size=6)
    B = rng.normal(size=(3, 3))
    lam, eta = B @ B.T, rng.normal(size=3)
    info = JointInfo(lam[None, None], eta[None, None])
    ref_x, ref_P = add_joint_info(x[None], P[None], info, np.arange(3)[None])
    xo, Po = x.copy(), P.copy()
    add_info(xo, Po, lam, eta)
    np.testing.assert_allclose(xo, ref_x[0], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(Po, ref_P[0], rtol=1e-10, atol=1e-12)

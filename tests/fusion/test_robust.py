"""Robust and honest estimation (issue 8): outliers, gaps, weak priors, confidences,
calibration precision, and the bad input around them."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from gt3dkit import load_scene, reconstruct
from gt3dkit.cli import main
from gt3dkit.eval.metrics import match_rows
from gt3dkit.fusion.preparation.robust import (
    RobustConfig,
    deleted_score2,
    point_weight,
    point_weights,
    robust_variance,
)
from gt3dkit.geom.triangulate import normalized_points, robust_triangulate
from gt3dkit.sim import Errors, simulate, simulate_skeletons, write_scene, write_skeleton_scene


def _csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _skel(root: Path, seed: int = 4, **kw) -> Path:
    kw = {"frames": 10, "people": 2, "cameras": 6, "noise_px": 1.0, **kw}
    write_skeleton_scene(simulate_skeletons("native", seed=seed, **kw), root, "native")
    return root


@pytest.fixture(scope="module")
def clean_and_bad(tmp_path_factory):
    d = Path(tmp_path_factory.mktemp("robust"))
    err = Errors(outliers=0.02, swaps=0.05, glitch=0.01)
    clean = load_scene(_skel(d / "clean", confidences=True))
    bad = load_scene(_skel(d / "bad", confidences=True, errors=err))
    inj = _csv(d / "bad" / "injected.csv")
    return clean, bad, inj


# -- the weights themselves -------------------------------------------------------------------

def test_point_weights_follow_the_chi_square_thresholds() -> None:
    cfg = RobustConfig(huber_p=1e-3, reject_p=1e-6)
    for dof in (1, 2):
        c2, g2 = chi2.isf(1e-3, dof), chi2.isf(1e-6, dof)
        e2 = np.array([0.0, 0.99 * c2, 1.2 * c2, 0.999 * g2, g2, 10 * g2])
        w = point_weights(e2, dof, cfg)
        assert w[0] == w[1] == 1.0
        assert 0 < w[2] < 1 and 0 <= w[3] < w[2]
        assert w[4] == w[5] == 0.0
        assert np.all(np.diff(w) <= 0)
    assert np.all(point_weights(np.array([1e9]), 2, RobustConfig(enabled=False)) == 1.0)


def test_point_weights_are_the_one_rule_on_any_shape() -> None:
    """The arrays' weights are the per-point rule the compiled update calls (one definition), the
    shape kept; against the rule written out here: Huber's c/e times the squared taper."""
    from gt3dkit.fusion.ukf import update

    assert update.point_weight is point_weight
    cfg = RobustConfig(huber_p=1e-3, reject_p=1e-6)
    c, g = cfg.thresholds(2)
    e2 = np.random.default_rng(0).uniform(0, 1.2 * g * g, (5, 7))
    e2[0, :3] = np.nan, np.inf, -1.0
    w = point_weights(e2, 2, cfg)
    assert w.shape == (5, 7)
    e = np.sqrt(np.clip(np.nan_to_num(e2[1:]), 0, None))
    ref = np.where(e <= c, 1.0, np.where(e >= g, 0.0, c / e * (1 - ((e - c) / (g - c)) ** 2) ** 2))
    np.testing.assert_allclose(w[1:], ref, rtol=1e-12, atol=0)
    assert list(w[0, :3]) == [1.0, 0.0, 1.0]  # NaN: no score; inf: rejected; negative: 0
    assert [point_weight(float(v), c, g) for v in e2[2]] == list(w[2])


def test_deleted_score_equals_brute_force_leave_one_out() -> None:
    """Linear regression: the score of each point equals refitting without it (scipy lstsq)."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(12, 3))
    y = A @ np.array([1.0, -2.0, 0.5]) + 0.1 * rng.normal(size=12)
    y[4] += 3.0  # one outlier
    D = 0.1**2
    P = np.linalg.inv(A.T @ A / D)
    x = P @ A.T @ y / D
    r = y - A @ x
    p = np.einsum("ij,jk,ik->i", A, P, A)
    e2 = deleted_score2(r, np.full(12, D), p, np.ones(12))
    for i in range(12):
        keep = np.arange(12) != i
        xi = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
        Pi = np.linalg.inv(A[keep].T @ A[keep] / D)
        brute = (y[i] - A[i] @ xi) ** 2 / (D + A[i] @ Pi @ A[i])
        assert e2[i] == pytest.approx(brute, rel=1e-9)
    assert np.argmax(e2) == 4


def test_robust_variance_ignores_a_few_gross_errors() -> None:
    rng = np.random.default_rng(1)
    r = rng.normal(scale=2.0, size=5000)
    r[:50] = 300.0
    v = robust_variance(r**2, np.ones(5000))
    assert v == pytest.approx(4.0, rel=0.06)
    assert np.mean(r**2) > 100  # what a plain estimate would say


def test_robust_triangulation_rejects_the_bad_view() -> None:
    """One view 200 px off among five: the point is where the four agree (vs OpenCV's DLT
    on the four good views)."""
    import cv2

    sim = simulate_skeletons("native", seed=1, frames=2, people=1, cameras=5, errors=Errors(dropped=0.0))
    rig = sim.rig
    uv = sim.uv[0, :, 3].copy()  # (C, 2) joint 3, frame 0
    bad = uv.copy()
    bad[2] += [200.0, -40.0]
    xy = normalized_points(bad[None], rig.K, rig.dist)
    f = rig.K[:, 0, 0]
    X, inl, _ = robust_triangulate(xy, rig.R, rig.t, f, thr_px=20.0)
    assert inl[0].tolist() == [True, True, False, True, True]
    assert np.linalg.norm(X[0] - sim.kpt_world[0, 3]) < 1e-6
    P0 = np.hstack([rig.R[0], rig.t[0][:, None]])
    P1 = np.hstack([rig.R[1], rig.t[1][:, None]])
    Xh = cv2.triangulatePoints(P0, P1, xy[0, 0].reshape(2, 1), xy[0, 1].reshape(2, 1))
    assert np.linalg.norm(X[0] - (Xh[:3, 0] / Xh[3, 0])) < 1e-6


def test_two_view_hypothesis_is_opencvs_point() -> None:
    """The scored two-view hypotheses (the compiled 3x3 inhomogeneous solve) give OpenCV's two-view
    DLT point on clean views, within a millimetre of the eigenvector at 1 px of noise, and NaN
    from one view (a ray)."""
    import cv2

    from gt3dkit.geom.triangulate import _dlt_rows, _null_point
    from gt3dkit.geom.trikernel import _inhomogeneous

    def two_view(O: np.ndarray) -> np.ndarray:  # (N, 4, 4) -> (N, 3)
        out = np.empty((len(O), 3))
        for n in range(len(O)):
            _inhomogeneous(np.ascontiguousarray(O[n]), out[n])
        return out

    sim = simulate_skeletons("native", seed=2, frames=3, people=2, cameras=4)
    rig = sim.rig
    uv = np.swapaxes(sim.uv, 1, 2).reshape(-1, rig.K.shape[0], 2)  # (rows * J, C, 2), no noise
    xy = normalized_points(uv, rig.K, rig.dist)
    xy = xy[np.isfinite(xy[:, :2]).all(axis=(1, 2))]
    O = _dlt_rows(xy, rig.R, rig.t)
    X = two_view(O[:, 0] + O[:, 1])
    P0 = np.hstack([rig.R[0], rig.t[0][:, None]])
    P1 = np.hstack([rig.R[1], rig.t[1][:, None]])
    Xh = cv2.triangulatePoints(P0, P1, xy[:, 0].T.copy(), xy[:, 1].T.copy())
    assert np.abs(X - (Xh[:3] / Xh[3]).T).max() < 1e-6
    noisy = xy + np.random.default_rng(0).normal(0, 1 / rig.K[0, 0, 0], xy.shape)
    On = _dlt_rows(noisy, rig.R, rig.t)
    d = np.linalg.norm(two_view(On[:, 0] + On[:, 1]) - _null_point(On[:, 0] + On[:, 1]), axis=1)
    assert np.median(d) < 1e-3
    assert np.isnan(two_view(O[:1, 0])).all()  # one view: a ray, no point


@pytest.mark.parametrize("cameras", [5, 14])
def test_compiled_robust_triangulation_equals_the_numpy_formulation(cameras: int) -> None:
    """The compiled MSAC triangulation against the batched numpy one it replaced
    (``tests/oracles.py``): detector errors (outliers, swaps, zero glitches), missing views,
    per-view variances, a camera behind some points, all pairs (5 views) and a spread of pairs
    (14 views: 91 pairs > 64)."""
    from tests.oracles import robust_triangulate_numpy

    sim = simulate_skeletons("native", seed=7, frames=6, people=3, cameras=cameras, noise_px=1.5,
                             errors=Errors(outliers=0.1, swaps=0.1, glitch=0.05))
    rig = sim.rig
    uv = np.swapaxes(sim.uv, 1, 2).reshape(-1, cameras, 2)
    xy = normalized_points(uv, rig.K, rig.dist)
    rng = np.random.default_rng(3)
    s = rng.uniform(0.5, 2.0, xy.shape[:2])
    f = rig.K[:, 0, 0]
    ds = np.ones(cameras)
    ds[1] = -1.0  # this camera sees every point behind it
    for thr in (4.0, 20.0):
        X, inl, e2 = robust_triangulate(xy, rig.R, rig.t, f, thr, s, ds)
        Xr, inr, er = robust_triangulate_numpy(xy, rig.R, rig.t, f, thr, s, ds, chunk=50)
        assert np.isfinite(Xr).all(axis=1).sum() > 0.8 * len(Xr)
        np.testing.assert_array_equal(np.isfinite(X), np.isfinite(Xr))
        np.testing.assert_allclose(X, Xr, rtol=1e-8, atol=1e-9)
        np.testing.assert_array_equal(inl, inr)
        np.testing.assert_allclose(e2, er, rtol=1e-6, atol=1e-9)
        assert np.isinf(e2[:, 1]).all()


# -- outliers --------------------------------------------------------------------------------

def test_injected_errors_barely_move_the_joints(clean_and_bad) -> None:
    clean, bad, inj = clean_and_bad
    assert {r["kind"] for r in inj} >= {"keypoint_outlier", "swapped_joints", "glitch"}
    tc, tb = reconstruct(clean), reconstruct(bad)
    ia, ib = match_rows(tb, tc)
    d = np.linalg.norm(tb.kpt_world[ia] - tc.kpt_world[ib], axis=-1)
    d = d[np.isfinite(d)]
    # measured: p95 0.33 mm, max 1.2 mm; the plain (non-robust) UKF moves one by 2.9 m
    assert np.percentile(d, 95) < 1e-3 and d.max() < 0.01
    plain = reconstruct(bad, robust=False)
    dp = np.linalg.norm(plain.kpt_world[ia] - tc.kpt_world[ib], axis=-1)
    assert np.nanmax(dp) > 0.05


def test_every_far_off_point_is_reported(clean_and_bad) -> None:
    _, bad, inj = clean_and_bad
    tb = reconstruct(bad)
    dw = tb.downweighted
    names = bad.rig.names
    low = {(int(f), names[c], int(i), int(j)) for f, c, i, j, w in
           zip(dw.frame, dw.cam, dw.track_id, dw.joint, dw.weight, strict=True) if w < 0.1}
    far = [(int(r["frame"]), r["camera"], int(r["id"]), int(r["joint"])) for r in inj
           if r["kind"] in ("keypoint_outlier", "glitch")]
    assert far and all(k in low for k in far)
    assert tb.info.robust is not None and tb.info.robust.rejected >= len(far)


def test_downweighted_csv_is_written(tmp_path, clean_and_bad) -> None:
    _, bad, _ = clean_and_bad
    from gt3dkit.io.writers import DOWNWEIGHTED_COLUMNS, write_outputs

    tb = reconstruct(bad)
    write_outputs(tmp_path / "out", bad, tb)
    with open(tmp_path / "out" / "downweighted.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == DOWNWEIGHTED_COLUMNS and len(rows) - 1 == len(tb.downweighted)
    assert all(r[1] in bad.rig.names and 0 <= float(r[5]) < 1 for r in rows[1:])


def test_shifted_box_is_rejected_and_does_not_move_the_ellipsoid(tmp_path) -> None:
    sim = simulate("native", seed=5, frames=12, people=3, noise_px=1.0, errors=Errors(dropped=0.0))
    write_scene(sim, tmp_path / "a", "native")
    boxes = (tmp_path / "a" / "boxes.csv").read_text().splitlines()
    f, cam, i, *b = boxes[20].split(",")
    x0, y0, x1, y1 = (float(v) for v in b)
    boxes[20] = ",".join([f, cam, i, f"{x0 + 80:g}", f"{y0:g}", f"{x1 + 80:g}", f"{y1:g}"])
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    (tmp_path / "b" / "boxes.csv").write_text("\n".join(boxes) + "\n")
    ta = reconstruct(load_scene(tmp_path / "a"))
    tb = reconstruct(load_scene(tmp_path / "b"))
    d = np.linalg.norm(ta.center_world - tb.center_world, axis=1)
    assert d.max() < 0.005  # mm-level; unweighted it moves by several cm
    dw = tb.downweighted
    hit = (dw.frame == int(f)) & (dw.track_id == int(i)) & (dw.weight == 0)
    assert {int(e) for e in dw.edge[hit]} >= {0, 2}  # both side edges rejected


# -- gaps, weak priors, process noise ----------------------------------------------------------

def test_long_gap_uses_the_late_frames_own_views(tmp_path) -> None:
    kw = dict(seed=2, frames=60, people=4, noise_px=1.0, motion="walk", cameras=6)
    write_scene(simulate("native", **kw, errors=Errors(dropped=0.0, gap=(5, 55))), tmp_path / "g", "native")
    sc = load_scene(tmp_path / "g")
    assert set(sc.frames.tolist()) <= set(range(5)) | set(range(55, 60))
    tr = reconstruct(sc)
    it, ig = match_rows(tr, sc.truth)
    e = np.linalg.norm(tr.center_world[it] - sc.truth.center_world[ig], axis=1)
    assert e.max() < 0.05  # was 8 m before linearising at the per-frame fit
    chi = np.sum(((tr.center_world[it] - sc.truth.center_world[ig]) / tr.center_sd[it]) ** 2, 1)
    assert np.mean(chi < 6.25) >= 0.85


@pytest.mark.parametrize("accel", [0.01, 1000.0])
def test_no_divergence_at_extreme_process_noise(tmp_path, accel) -> None:
    write_scene(simulate("native", seed=3, frames=15, people=3, noise_px=1.0), tmp_path, "native")
    sc = load_scene(tmp_path)
    tr = reconstruct(sc, accel_sd=accel)
    it, ig = match_rows(tr, sc.truth)
    e = np.linalg.norm(tr.center_world[it] - sc.truth.center_world[ig], axis=1)
    assert e.max() < 0.3 and tr.info.details["pd_repairs"] == 0


def test_single_view_track_reports_an_honest_spread(tmp_path) -> None:
    """A person seen by one camera in all its frames: its depth comes from the shape prior,
    and the reported sd must say so."""
    sim = simulate("native", seed=6, frames=20, people=6, noise_px=1.0, errors=Errors(dropped=0.0,
                                                                                      single_view=0.2))
    write_scene(sim, tmp_path, "native")
    sc = load_scene(tmp_path)
    tr = reconstruct(sc)
    one = {int(p) for _, _, p, _, k, _ in sim.injected if k == "single_view"}
    assert one
    it, ig = match_rows(tr, sc.truth)
    sel = np.isin(tr.track_id[it], list(one))
    e = tr.center_world[it][sel] - sc.truth.center_world[ig][sel]
    chi = np.sum((e / tr.center_sd[it][sel]) ** 2, axis=1)
    assert np.mean(chi < 6.25) >= 0.9
    assert tr.center_sd[it][sel].max(axis=1).min() > 0.1  # decimetres, not centimetres


# -- confidences and bad input ---------------------------------------------------------------

def test_confidence_scales_the_variance(tmp_path) -> None:
    """A low confidence on an otherwise good point only widens it; the same point at full
    confidence gives the same joint within noise."""
    root = _skel(tmp_path / "a", confidences=True)
    sc = load_scene(root)
    assert sc.obs.kpt_conf is not None and np.nanmin(sc.obs.kpt_conf) > 0
    tr = reconstruct(sc)
    assert "factor" in tr.info.details["preparation"]["keypoints"]["confidence"]


def _write_kpt(root: Path, mutate) -> int:
    p = root / "keypoints.csv"
    lines = p.read_text().splitlines()
    line = mutate(lines)
    p.write_text("\n".join(lines) + "\n")
    return line


@pytest.mark.parametrize("value,needle", [("2.5", "confidence must be in [0, 1]"),
                                          ("nan", "confidence must be in [0, 1]"),
                                          ("-0.1", "confidence must be in [0, 1]"),
                                          ("high", "malformed")])
def test_bad_confidence(tmp_path, capsys, value, needle) -> None:
    root = _skel(tmp_path / "in", confidences=True)

    def mutate(lines):
        parts = lines[7].split(",")
        parts[-1] = value
        lines[7] = ",".join(parts)
        return 8

    line = _write_kpt(root, mutate)
    code = main(["reconstruct", str(root), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and f"keypoints.csv: line {line}" in err and needle in err, err
    assert err.count("\n") == 1 and not (tmp_path / "out").exists()


def test_confidence_in_only_some_rows(tmp_path, capsys) -> None:
    root = _skel(tmp_path / "in", confidences=True)

    def mutate(lines):
        lines[5] = ",".join(lines[5].split(",")[:-1])
        return 6

    line = _write_kpt(root, mutate)
    code = main(["reconstruct", str(root), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and f"line {line}" in err and "expected 7 fields" in err, err


def test_zero_confidence_means_not_detected(tmp_path, capsys) -> None:
    root = _skel(tmp_path / "in", confidences=True)

    def mutate(lines):
        parts = lines[3].split(",")
        lines[3] = ",".join(parts[:4] + ["0", "0", "0"])
        return 4

    _write_kpt(root, mutate)
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "warning:" in err and "1 keypoints with confidence 0" in err


def test_rotation_stored_to_seven_digits_is_accepted(tmp_path, capsys) -> None:
    write_scene(simulate("native", seed=0, frames=4, people=2), tmp_path / "in", "native")
    p = tmp_path / "in" / "cameras.json"
    doc = json.loads(p.read_text())
    doc["cameras"][1]["R"] = [[float(f"{v:.7f}") for v in row] for row in doc["cameras"][1]["R"]]
    doc["cameras"][1]["R"][0][0] += 1.2e-6
    p.write_text(json.dumps(doc))
    assert main(["reconstruct", str(tmp_path / "in"), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "warning: camera cam1: R re-orthonormalised (1 camera," in err
    meta = json.loads((tmp_path / "out" / "meta.json").read_text())
    assert "cam1" in meta["input"]["calibration_notes"]
    R = np.array(load_scene(tmp_path / "in").rig.cameras[1].R)
    assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12


def test_missing_fps_is_said(tmp_path, capsys) -> None:
    write_scene(simulate("native", seed=0, frames=4, people=2), tmp_path / "in", "native")
    p = tmp_path / "in" / "cameras.json"
    doc = json.loads(p.read_text())
    del doc["fps"]
    p.write_text(json.dumps(doc))
    assert main(["reconstruct", str(tmp_path / "in"), "--out", str(tmp_path / "out")]) == 0
    cap = capsys.readouterr()
    assert "warning:" in cap.err and "no \"fps\"" in cap.err and "assuming 10" in cap.err
    assert "10 fps (assumed)" in cap.out
    meta = json.loads((tmp_path / "out" / "meta.json").read_text())
    assert meta["input"]["fps_assumed"]
    # --fps settles it: no warning
    assert main(["reconstruct", str(tmp_path / "in"), "--out", str(tmp_path / "o2"),
                 "--fps", "25"]) == 0
    cap = capsys.readouterr()
    assert "warning" not in cap.err and "25 fps" in cap.out and "assumed" not in cap.out


@pytest.mark.parametrize("fps", ['"ten"', "-4", "1e999"])
def test_bad_fps(tmp_path, capsys, fps) -> None:
    write_scene(simulate("native", seed=0, frames=4, people=2), tmp_path / "in", "native")
    p = tmp_path / "in" / "cameras.json"
    p.write_text(p.read_text().replace('"fps": 10.0', f'"fps": {fps}'))
    code = main(["reconstruct", str(tmp_path / "in"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and "cameras.json" in err and "fps" in err, err


def test_simulator_writes_what_it_injected(tmp_path, capsys) -> None:
    assert main(["simulate", "--kind", "skeleton", "--out", str(tmp_path / "s"), "--frames", "6",
                 "--people", "2", "--cameras", "5", "--outliers", "0.05", "--swaps", "0.1",
                 "--glitch", "0.02", "--gap", "2:4", "--conf", "--noise-px", "1"]) == 0
    rows = _csv(tmp_path / "s" / "injected.csv")
    kinds = {r["kind"] for r in rows}
    assert kinds >= {"keypoint_outlier", "swapped_joints"}
    kp = _csv(tmp_path / "s" / "keypoints.csv")
    assert "conf" in kp[0] and not {int(r["frame"]) for r in kp} & {102, 103}
    capsys.readouterr()
    assert main(["simulate", "--out", str(tmp_path / "b"), "--shifted", "0.5",
                 "--outliers", "0.1"]) == 2
    assert "skeleton" in capsys.readouterr().err


@pytest.mark.parametrize("where", [".", "sub/out", ".."])
def test_out_must_not_touch_the_input(tmp_path, capsys, where) -> None:
    """--out equal to, inside or around the input folder is refused before anything is read
    or written: the annotations stay byte for byte."""
    root = _skel(tmp_path / "in" / "scene")
    before = {p.name: p.read_bytes() for p in root.iterdir()}
    out = root / where
    code = main(["reconstruct", str(root), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: --out:") and "input folder" in err
    assert {p.name: p.read_bytes() for p in root.iterdir()} == before
    assert not (root / "sub").exists()


def test_a_label_put_on_another_joint_is_named_in_its_flag(tmp_path) -> None:
    """A labeller (or a model) that puts a hidden left ankle on the left knee, in one camera over
    several frames: each flag says the label lies at the knee, and no other flag says so."""
    root = _skel(tmp_path / "in", skeleton="coco17")
    rows = _csv(root / "keypoints.csv")
    head = list(rows[0])
    ankle, knee = "15", "13"  # coco17: l_ankle, l_knee
    at = {(r["frame"], r["camera"], r["id"]): r for r in rows if r["joint"] == knee}
    moved = set()
    for r in rows:
        key = (r["frame"], r["camera"], r["id"])
        if r["joint"] == ankle and r["camera"] == "00_02" and r["id"] == "0" and key in at:
            r["u"], r["v"] = at[key]["u"], at[key]["v"]
            moved.add(int(r["frame"]))
    assert len(moved) >= 5
    with open(root / "keypoints.csv", "w", newline="") as f:
        w = csv.DictWriter(f, head)
        w.writeheader()
        w.writerows(rows)
    reconstruct(load_scene(root), "ukf", out=tmp_path / "out")
    flags = _csv(tmp_path / "out" / "anomalies.csv")
    named = [r for r in flags if "labelled at l_knee?" in r["detail"]]
    assert {int(r["frame"]) for r in named} == moved, named
    assert all(r["camera"] == "00_02" and r["joint"] == ankle and r["kind"] == "keypoint_outlier"
               for r in named)

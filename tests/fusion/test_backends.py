"""The filter's loop orders (tests/oracles_frames.BACKENDS: every object's rows as one
compiled chain, or frame by frame with the objects batched) call the same steps and must give the
same result; each is also held to what a filter must do. And the ways work is shared (the box
block's compiled regression, joints as separate filters, several noise values in one pass, the
linearised noise search) against the plain computation they replace."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.api import dense_frames, load_scene
from gt3dkit.fusion.motion import accel_shape
from gt3dkit.fusion.preparation.boxfit import state_boxes as box_function
from gt3dkit.fusion.preparation.robust import RobustConfig
from gt3dkit.fusion.preparation.rows import replicate_rows
from gt3dkit.fusion.ukf import smoother as us
from gt3dkit.fusion.ukf.filtering import backend_for
from gt3dkit.fusion.ukf.initial import InitialCov, rows_of
from gt3dkit.fusion.ukf.measurement import Model
from gt3dkit.fusion.ukf.noise import LinearisedSearch, search_rows
from gt3dkit.fusion.ukf.sigma import Block, Robust, SigmaWeights
from gt3dkit.fusion.ukf.update import Measured
from gt3dkit.sim import Errors, simulate, write_scene
from tests.oracles_frames import BACKENDS, run_frames, ukf_update_information


@pytest.fixture(scope="module")
def box_scene(tmp_path_factory: pytest.TempPathFactory):
    root = Path(tmp_path_factory.mktemp("boxupd")) / "in"
    sim = simulate("wildtrack", seed=5, frames=6, people=12, noise_px=1.0, errors=Errors(outliers=0.05))
    write_scene(sim, root, "wildtrack")
    return sim, Model.of(us.UKFSmoother().prepare(load_scene(root)))


@pytest.fixture(scope="module")
def gap_model(tmp_path_factory: pytest.TempPathFactory) -> Model:
    """Walkers at 2 fps who stop and turn, no labels in frames 3-6, rows at every frame (a dense
    run): rows without measurements between measured ones."""
    root = Path(tmp_path_factory.mktemp("boxgap")) / "in"
    sim = simulate("native", seed=6, frames=14, people=8, noise_px=1.0, motion="stop-and-turn", fps=2.0,
                   errors=Errors(gap=(3, 7), dropped=0.0))
    write_scene(sim, root, "native")
    return Model.of(us.UKFSmoother().prepare(dense_frames(load_scene(root), None)))


@pytest.fixture(params=["frames", "objects"])  # "joints" runs a boxes-only model as "objects"
def backend(request: pytest.FixtureRequest):
    return request.param, BACKENDS[request.param]


@pytest.mark.parametrize("sigma", ["cubature", "scaled"])
def test_compiled_box_regression_equals_the_sigma_points_of_the_tangent_box(box_scene, sigma: str) -> None:
    """The box block's compiled regression (gt3dkit.fusion.ukf.boxupdate.box_regression) against the
    generic regression of the same block through the numpy-called tangent box, inside the whole
    iterated, robust update: priors off the truth by up to half a metre, an outlier edge, edges
    masked, robust weights moving, a linearisation point of its own."""
    _, model = box_scene
    rng = np.random.default_rng(11)
    r = np.flatnonzero(np.all(np.isfinite(model.x_frame), axis=1))[:40]
    B, n = len(r), model.layout.n
    x = model.x_frame[r] + rng.normal(size=(B, n)) * np.r_[[0.2] * 3, [0.3] * 3, [0.05] * 3]
    A = rng.normal(size=(B, n, n)) * 0.05
    P = A @ np.swapaxes(A, 1, 2) + np.diag(np.r_[[0.1] * 3, [0.5] * 3, [0.01] * 3])
    z, mask = model.z[r].copy(), model.mask[r].copy()
    z[0, 2] += 60.0  # an outlier edge
    z[3, 5] += 25.0
    mask[1, :4] = False  # a camera without its box
    xl, Pl = x.copy(), P.copy()
    xl[2] = model.x_frame[r[2]]  # the frame's own fit as linearisation point
    w = SigmaWeights(n) if sigma == "cubature" else SigmaWeights(n, alpha=0.8, beta=2.0, kappa=1.0)
    (compiled,) = model.blocks()
    assert compiled.regress is not None
    C = len(model.cams.K)

    def boxes(X: np.ndarray, use: np.ndarray) -> np.ndarray:  # (B, 1, S, 6) -> (B, 1, S, 4C)
        want = use.reshape(use.shape[:2] + (1, C, 4)).any(axis=-1)
        return box_function(X[..., :3], X[..., 3:], model.cams, want).reshape(X.shape[:3] + (C * 4,))

    plain = replace(compiled, h=boxes, masked=True, regress=None)
    kw = dict(weight0=model.weight0[r], robust=Robust(RobustConfig(), model.robust_blocks))
    meas = Measured(z, mask, model.var[r])
    xc, Pc, ic = ukf_update_information(x, P, meas, [compiled], w, 4, (xl, Pl), **kw)
    xr, Pr, ir = ukf_update_information(x, P, meas, [plain], w, 4, (xl, Pl), **kw)
    assert ic["weights"][0, 2] < 1 and ic["passes"] > 1  # the outlier is down-weighted
    assert ic["weights"][0, 2] == 0 or ic["score2"][0, 2] > 20
    np.testing.assert_allclose(xc, xr, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(Pc, Pr, rtol=1e-8, atol=1e-12)
    for k in ("loglik_rows", "nis_rows", "dof_rows", "passes_rows"):
        np.testing.assert_allclose(ic[k], ir[k], rtol=1e-9, atol=1e-9, err_msg=k)
    for k in ("weights", "score2", "residual"):
        np.testing.assert_allclose(ic[k], ir[k], rtol=1e-7, atol=1e-9, err_msg=k)


def test_block_regression_equals_the_whole_state_on_a_linear_model() -> None:
    """For a linear ``h`` the statistical linear regression is exact on any sigma points: the
    per-block update must equal the whole-state one."""
    rng = np.random.default_rng(4)
    B, n, m = 3, 9, 6
    A = rng.normal(size=(B, n, n))
    P = A @ np.swapaxes(A, 1, 2) / n + 0.1 * np.eye(n)
    x = rng.normal(size=(B, n))
    H = rng.normal(size=(6, m))  # the measurements see entries 0-2 and 6-8 only
    dims = np.r_[0:3, 6:9]
    z = rng.normal(size=(B, m))
    mask = np.ones((B, m), bool)
    mask[1, 2] = False

    def whole(X: np.ndarray) -> np.ndarray:
        return X[..., dims] @ H

    block = Block(dims[None], np.arange(m)[None], lambda X: X @ H)
    a = ukf_update_information(x, P, Measured(z, mask, 0.05), whole, SigmaWeights(n), iterations=3)
    b = ukf_update_information(x, P, Measured(z, mask, 0.05), [block], SigmaWeights(n), iterations=3)
    np.testing.assert_allclose(b[0], a[0], atol=1e-10)
    np.testing.assert_allclose(b[1], a[1], atol=1e-10)
    assert b[2]["loglik"] == pytest.approx(a[2]["loglik"], rel=1e-10)


def _box_run(model: Model, case: str):
    """A run's config, initial states and options: ``fade`` (a process noise far too small for
    walkers: predictions are faded), ``search`` (some objects only, per-row noise, no fading, no
    smoothing)."""
    cfg = replace(us.UKFSmoother().config, accel_sd=0.02 if case == "fade" else 0.4, shape_sd=0.02)
    init = us.initial_states(model, cfg)
    kw: dict = {"collect": True, "fade": True, "on": None, "noise_rows": None}
    if case == "search":
        on = search_rows(model.rows, len(model.rows) // 2, seed=1)
        kw = {"on": on, "fade": False, "noise_rows": {"accel_sd": np.where(model.rows.row_o % 2, 0.3, 1.5)},
              "collect": True}
        cfg = replace(cfg, smooth=False)
    return cfg, init, kw


@pytest.mark.parametrize("case", ["fade", "search"])
def test_the_backends_agree_on_a_box_model(box_scene, case: str) -> None:
    """Objects as compiled chains (split over threads) against the loop over frames."""
    _, model = box_scene
    assert backend_for(model) == "objects"
    cfg, init, kw = _box_run(model, case)
    a = BACKENDS["objects"](model, init, cfg, 10.0, **kw)
    b = BACKENDS["frames"](model, init, cfg, 10.0, **kw)
    np.testing.assert_allclose(a.x, b.x, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-8, atol=1e-12)
    for k in ("loglik_rows", "nis", "dof", "weights", "score2", "residual"):
        np.testing.assert_allclose(getattr(a, k), getattr(b, k), rtol=1e-7, atol=1e-8, err_msg=k)
    for k in ("predictions_faded", "object_frames", "pd_repairs", "update_passes_mean"):
        assert getattr(a, k) == getattr(b, k), k
    assert (a.predictions_faded > 0) == (case == "fade")


def test_the_backends_agree_where_a_gap_ends_in_a_faded_prediction(gap_model: Model) -> None:
    """A prediction faded at the first labelled frame after a gap: both loop orders predict the
    gap's rows again with the scaled noise (the same numbers)."""
    model = gap_model
    unmeasured = ~model.mask.any(axis=1)
    assert unmeasured.sum() >= 8
    cfg, init, kw = _box_run(model, "fade")
    a = BACKENDS["objects"](model, init, cfg, 2.0, **kw)
    b = BACKENDS["frames"](model, init, cfg, 2.0, **kw)
    assert a.predictions_faded == b.predictions_faded > 0
    np.testing.assert_allclose(a.x, b.x, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(a.loglik_rows, b.loglik_rows, rtol=1e-7, atol=1e-8)


def test_each_backend_tracks_the_truth_and_rejects_outliers(box_scene, backend) -> None:
    """Absolute: with eight box edges moved 80 px (1 px noise elsewhere), the smoothed centres
    within 3 cm (median) and 6 cm (95 %) of the simulated truth, each moved edge rejected or
    down-weighted and almost nothing else."""
    sim, model = box_scene
    name, run = backend
    rng = np.random.default_rng(8)
    edges = np.argwhere(model.mask)
    bad = edges[rng.choice(len(edges), 8, replace=False)]
    z = model.z.copy()
    z[bad[:, 0], bad[:, 1]] += 80.0
    model = replace(model, z=z)
    cfg = replace(us.UKFSmoother().config, accel_sd=1.0, shape_sd=0.02)
    init = us.initial_states(model, cfg)
    r = run(model, init, cfg, 10.0, True, True, None, None)
    x, P = r.x, r.P
    rows = model.rows
    truth = {(int(f), int(i)): c for f, i, c in zip(sim.truth_frame, sim.truth_id, sim.center_world,
                                                    strict=True)}
    key = zip(rows.frames[rows.row_t].tolist(), rows.obj_ids[rows.row_o].tolist(), strict=True)
    err = np.linalg.norm(x[:, :3] - np.array([truth[k] for k in key]), axis=1)
    assert np.median(err) < 0.03, name
    assert np.percentile(err, 95) < 0.06, name
    w = r.weights
    assert np.all(w[bad[:, 0], bad[:, 1]] < 0.5), name
    assert ((w < 1) & model.mask).sum() <= 2 * len(bad), name
    assert np.all(np.linalg.eigvalsh(P[:, :3, :3]) > 0)


@pytest.fixture(scope="module")
def skeleton_model(skeleton_prepared):
    scene, _, model, cfg = skeleton_prepared
    return model, us.initial_states(model, cfg), cfg, scene.fps


def test_split_joint_filters_equal_the_whole_state_filter(skeleton_model) -> None:
    """Joints as separate filters against the whole state: the same filter, except that each part
    stops iterating its update on its own (within the convergence tolerance, 0.01 sd per pass),
    the whole state when its last joint has; with one pass they are equal to rounding."""
    model, init, cfg, fps = skeleton_model
    assert backend_for(model) == "joints"
    for it in (1, 4):
        c = replace(cfg, iterations=it)
        a = run_frames(model, init, c, fps, collect=True, split=False)
        b = run_frames(model, init, c, fps, collect=True, split=True)
        sd = np.sqrt(np.einsum("rii->ri", a.P))
        assert np.max(np.abs(b.x - a.x) / sd) < (1e-8 if it == 1 else 0.02)
        np.testing.assert_allclose(b.P, a.P, rtol=1e-3 if it > 1 else 1e-9, atol=1e-9)
        np.testing.assert_allclose(b.loglik_rows, a.loglik_rows, rtol=1e-8 if it == 1 else 1e-4, atol=1e-8)
        np.testing.assert_array_equal(b.weights, a.weights)


def test_several_noise_values_in_one_pass_equal_separate_passes(skeleton_model) -> None:
    model, init, cfg, fps = skeleton_model
    values = [0.1, 1.0, 5.0]
    sel = np.arange(len(model.rows))
    rows_k, src, copy = replicate_rows(model.rows, sel, len(values))
    run = us.run_filter(model.take(rows_k, src), us.Init(init.x0[src], init.P0[src]),
                        replace(cfg, smooth=False, iterations=1), fps, fade=False,
                        noise_rows={"joint_accel_sd": np.asarray(values)[copy]})
    together = np.bincount(copy, weights=run.loglik_rows)
    for k, v in enumerate(values):
        alone = us.run_filter(model, init, replace(cfg, joint_accel_sd=v, smooth=False, iterations=1),
                              fps, fade=False).loglik
        assert together[k] == pytest.approx(alone, rel=1e-9)


def test_linearised_search_pass_is_a_plain_kalman_filter(box_scene) -> None:
    """The noise search's linear pass (boxes regressed once per row) against a Kalman filter
    written with numpy and scipy's Gaussian density on the same regression: the same
    log-likelihood at two noise values."""
    from scipy.stats import multivariate_normal

    _, model = box_scene
    cfg = replace(us.UKFSmoother().config, accel_sd=0.5, shape_sd=0.01)
    init = us.initial_states(model, cfg)
    sm = us.run_filter(model, init, cfg, 10.0)
    x_s, P_s = sm.x, sm.P
    rng = np.random.default_rng(2)
    w = np.where(rng.uniform(size=model.z.shape) < 0.05, 0.3, 1.0)  # some weights below 1
    lin = LinearisedSearch(model, init, cfg, 10.0, x_s, P_s, w, None)
    rows, lay = model.rows, model.layout
    dims = lay.ellipsoid_dims
    for accel, shape, pos in ((0.5, 0.01, 0.0), (2.0, 0.001, 0.0), (0.3, 0.01, 0.05)):
        total = 0.0
        for start in np.flatnonzero(rows.prev_row < 0):
            r, prev = int(start), -1
            x, P = init.x0[r], init.P0[r]
            while r >= 0:
                if prev >= 0:
                    dt = (rows.frames[rows.row_t[r]] - rows.frames[rows.row_t[prev]]) / 10.0
                    F, Q = lay.transition(np.array([dt]), accel, shape, up=model.cams.up,
                                          vertical_ratio=cfg.vertical_ratio)
                    # the position's own random walk, written out here (motion.py adds it to Q)
                    A = accel_shape(model.cams.up, cfg.vertical_ratio)
                    Q[0, lay.center, lay.center] += pos**2 * dt * A
                    x, P = F[0] @ x, F[0] @ P @ F[0].T + Q[0]
                use = lin.lins.used[r] & (w[r] > 0)
                H = np.zeros((use.sum(), lay.n))
                H[:, dims] = lin.lins.At[r][use]
                Rm = np.diag(lin.lins.D[r][use] / w[r][use])
                S = H @ P @ H.T + Rm
                y = lin.lins.c[r][use]
                total += multivariate_normal(H @ x, S).logpdf(y)
                Kg = P @ H.T @ np.linalg.inv(S)
                x, P = x + Kg @ (y - H @ x), P - Kg @ S @ Kg.T
                prev, r = r, int(rows.next_row[r])
        setting = {"accel_sd": accel, "shape_sd": shape, "position_sd": pos}
        assert lin.logliks([setting])[0] == pytest.approx(total, rel=1e-9)


def test_linearised_search_finds_the_full_search_values(tmp_path: Path) -> None:
    """The noise values found with the boxes' regression fixed per row (posterior
    linearisation) against re-linearising at every prediction, on a scene with outliers."""
    sim = simulate("wildtrack", seed=3, frames=60, people=10, noise_px=1.0, motion="walk",
                   errors=Errors(outliers=0.05))
    write_scene(sim, tmp_path / "in", "wildtrack")
    scene = load_scene(tmp_path / "in")
    found = {}
    for lin in (True, False):
        est = us.UKFSmoother(replace(us.UKFConfig(), search_linearised=lin))
        tr = est.estimate(scene)
        found[lin] = tr.info.params
        assert ("linearisation" in tr.info.details["noise_search"]["provisional"]["use"]) == lin
    for k in ("accel_sd", "shape_sd"):
        assert found[True][k] == pytest.approx(found[False][k], rel=0.15), k


def test_initial_covariances_made_when_indexed_equal_the_dense_ones(skeleton_model, monkeypatch) -> None:
    """The per-frame fits' covariances as initial ones (made only where read) against the dense
    array written out: a diagonal with the fit's 6 x 6 block, by rows, by the joint split's
    broadcast index arrays (in chunks), and whole."""
    model, init, _, _ = skeleton_model
    P0, lay = init.P0, model.layout
    assert isinstance(P0, InitialCov)
    R, n = model.x_frame.shape
    dims = np.r_[np.arange(lay.center.start, lay.center.stop),
                 np.arange(lay.log_axes.start, lay.log_axes.stop)]
    dense = P0.var[:, :, None] * np.eye(n)
    ok = np.flatnonzero(np.all(np.isfinite(model.cov6_frame), axis=(1, 2)))
    assert len(ok) > 0
    dense[np.ix_(ok, dims, dims)] = model.cov6_frame[ok]
    monkeypatch.setattr(InitialCov, "CHUNK_ENTRIES", 1000)  # many chunks
    rows = np.array([3, 0, R - 1, 3])
    np.testing.assert_array_equal(P0[rows], dense[rows])
    mask = np.arange(R) % 3 == 0
    np.testing.assert_array_equal(P0[mask], dense[mask])
    d = np.stack([np.r_[np.arange(9), 9 + 6 * j + np.arange(6)] for j in range(4)] * 2)
    src = np.repeat(rows[:2], 4)
    idx = (src[:, None, None], d[:, :, None], d[:, None, :])
    np.testing.assert_array_equal(P0[idx], dense[idx])
    sub = P0.entries(src, d)  # the joint split's parts, still made where read
    np.testing.assert_array_equal(sub[np.arange(len(src))], dense[idx])
    np.testing.assert_array_equal(sub.rows(np.array([5, 1]))[np.arange(2)], dense[idx][[5, 1]])
    np.testing.assert_array_equal(np.asarray(sub.rows(np.array([5, 1]))), dense[idx][[5, 1]])
    np.testing.assert_array_equal(np.asarray(P0), dense)
    np.testing.assert_array_equal(rows_of(P0, rows)[np.arange(4)], dense[rows])


def test_objects_run_again_into_the_first_runs_covariances_equal_a_separate_run(skeleton_model) -> None:
    """The robust second pass over some objects, written into the first pass's arrays, and over
    all of them (the first pass's arrays gone first), against runs merged as before."""
    model, init, cfg, fps = skeleton_model
    on = model.rows.row_o == 0
    assert 0 < on.sum() < len(on)
    w = replace(model, weight0=np.where(np.random.default_rng(1).uniform(size=model.z.shape) < 0.1, 0.5, 1.0))
    first = us.run_filter(model, init, cfg, fps, collect=True)
    ref = us.run_filter(model, init, cfg, fps, collect=True).merged(
        us.run_filter(w, init, cfg, fps, collect=True, on=on), on)
    got = us.rerun_objects(w, init, cfg, fps, first, on)
    assert got.P is first.P
    for k in ("x", "P", "nis", "loglik_rows", "weights"):
        np.testing.assert_array_equal(getattr(got, k), getattr(ref, k), err_msg=k)
    assert got.scalars() == ref.scalars()
    every = np.ones(len(on), bool)
    ref_all = us.run_filter(model, init, cfg, fps, collect=True).merged(
        us.run_filter(w, init, cfg, fps, collect=True), every)
    got_all = us.run_filter(w, init, cfg, fps, collect=True).after(first.scalars())
    for k in ("x", "P", "nis", "weights"):
        np.testing.assert_array_equal(getattr(got_all, k), getattr(ref_all, k), err_msg=k)
    assert got_all.scalars() == ref_all.scalars()

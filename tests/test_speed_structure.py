"""The speed-ups of issue 13 change how the work is done, never the result: each is held to the
plain computation it replaces (the numpy tangent box, the whole-state regression, the
unsplit filter, one pass per noise value, GTSAM's own optimizer)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.api import load_scene
from gt3dkit.fusion import ukf_smoother as us
from gt3dkit.fusion.measurement import Model
from gt3dkit.fusion.rows import replicate_rows
from gt3dkit.fusion.ukf import Block, SigmaWeights, ukf_update_information
from gt3dkit.geom.conics import ellipsoid_boxes, ellipsoid_boxes_numpy
from gt3dkit.sim import Errors, simulate, simulate_skeletons, write_scene, write_skeleton_scene


def _rot(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _random_cameras(rng: np.random.Generator, C: int, kind: str) -> tuple[np.ndarray, ...]:
    """``R, t, K, dist`` of ``C`` cameras ~8 m from the origin: ``kind`` distorted, pinhole or
    skewed."""
    R = np.stack([_rot(rng) for _ in range(C)])
    t = rng.normal(size=(C, 3)) + [0, 0, 8.0]
    K = np.tile(np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]]), (C, 1, 1))
    if kind == "skewed":
        K[:, 0, 1] = 3.0
    dist = np.zeros((C, 5))
    if kind == "distorted":
        dist[:] = rng.normal(size=(C, 5)) * [0.05, 0.01, 0.001, 0.001, 0.001]
    return R, t, K, dist


@pytest.mark.parametrize("kind", ["distorted", "pinhole", "skewed"])
def test_compiled_tangent_box_equals_the_numpy_reference(kind: str) -> None:
    rng = np.random.default_rng({"distorted": 0, "pinhole": 1, "skewed": 2}[kind])
    C, N = 5, 400
    R, t, K, dist = _random_cameras(rng, C, kind)
    c = rng.normal(size=(N, 3)) * 2.0
    s = np.exp(rng.normal(size=(N, 3)) * 0.3) * 0.4
    args = (_rot(rng), K, dist, R, t, np.ones(C))
    b1, m1 = ellipsoid_boxes(c, s, *args)
    b2, m2 = ellipsoid_boxes_numpy(c, s, *args)
    np.testing.assert_allclose(m1, m2, atol=1e-12)
    np.testing.assert_array_equal(np.isnan(b1), np.isnan(b2))
    inside = np.all((b2 > 0) & (b2 < 1920), axis=-1)
    assert inside.sum() > 100
    np.testing.assert_allclose(b1[inside], b2[inside], atol=1e-6)


def test_split_and_masked_tangent_box_equal_the_whole_call(monkeypatch) -> None:
    from gt3dkit.geom import boxkernel as bk

    rng = np.random.default_rng(3)
    C, N = 6, 3000  # large enough to be split over threads
    R = np.stack([_rot(rng) for _ in range(C)])
    t = rng.normal(size=(C, 3)) + [0, 0, 8.0]
    K = np.tile(np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]]), (C, 1, 1))
    dist = rng.normal(size=(C, 5)) * [0.05, 0.01, 0.001, 0.001, 0.001]
    c = rng.normal(size=(N, 3)) * 2.0
    s = np.exp(rng.normal(size=(N, 3)) * 0.3) * 0.4
    Rb = _rot(rng)
    want = rng.uniform(size=(N, C)) < 0.7
    box, margin = np.empty((N, C, 4)), np.empty((N, C))
    bk.kernel(c, s, Rb, K, dist, R, t, np.ones(C), 2, bk.EVERY_CAMERA, box, margin)  # one call, one thread
    monkeypatch.setenv("GT3D_THREADS", "3")
    b3, m3 = ellipsoid_boxes(c, s, Rb, K, dist, R, t, np.ones(C))
    np.testing.assert_array_equal(b3, box)
    np.testing.assert_array_equal(m3, margin)
    bw, mw = ellipsoid_boxes(c, s, Rb, K, dist, R, t, np.ones(C), want=want)
    np.testing.assert_array_equal(mw, margin)  # margins of every pair
    np.testing.assert_array_equal(bw[want], box[want])
    assert np.isnan(bw[~want]).all()


@pytest.fixture(scope="module")
def box_model(tmp_path_factory: pytest.TempPathFactory):
    root = Path(tmp_path_factory.mktemp("boxupd")) / "in"
    sim = simulate("wildtrack", seed=5, frames=6, people=12, noise_px=1.0, errors=Errors(outliers=0.05))
    write_scene(sim, root, "wildtrack")
    pre = us.UKFSmoother().prepare(load_scene(root))
    return Model.of(pre)


@pytest.mark.parametrize("sigma", ["cubature", "scaled"])
def test_compiled_box_update_equals_the_numpy_update_row_by_row(box_model, sigma: str) -> None:
    """The compiled box update (gt3dkit.fusion.boxupdate) against the numpy update of the same
    block, one row at a time (the numpy path stops iterating when the whole batch has
    converged, the compiled one per row): priors off the truth by up to half a metre, an
    outlier edge, edges masked, robust weights moving, a linearisation point of its own."""
    from gt3dkit.fusion import boxupdate
    from gt3dkit.fusion.robust import RobustConfig

    model = box_model
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
    blocks = model.blocks()
    assert boxupdate.applies(blocks, z.shape[1], model.robust_blocks)
    plain = [replace(b, compiled=None) for b in blocks]
    kw = dict(weight0=model.weight0[r], robust=RobustConfig(), robust_blocks=model.robust_blocks)
    xc, Pc, ic = boxupdate.box_update(x, P, z, mask, model.var[r], blocks, w, 4, xl, Pl, **kw)
    assert ic["weights"][0, 2] < 1 and ic["passes"] > 1  # the outlier is down-weighted
    for b in range(B):
        one = slice(b, b + 1)
        xr, Pr, ir = ukf_update_information(x[one], P[one], z[one], mask[one], model.var[r][one], plain, w,
                                            4, xl[one], Pl[one], weight0=model.weight0[r][one],
                                            robust=kw["robust"], robust_blocks=model.robust_blocks)
        np.testing.assert_allclose(xc[b], xr[0], rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(Pc[b], Pr[0], rtol=1e-8, atol=1e-12)
        for k in ("loglik_rows", "nis_rows", "dof_rows"):
            assert ic[k][b] == pytest.approx(ir[k][0], rel=1e-9, abs=1e-9), k
        for k in ("weights", "score2", "residual"):
            np.testing.assert_allclose(ic[k][b], ir[k][0], rtol=1e-7, atol=1e-9, err_msg=k)


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
    a = ukf_update_information(x, P, z, mask, 0.05, whole, SigmaWeights(n), iterations=3)
    b = ukf_update_information(x, P, z, mask, 0.05, [block], SigmaWeights(n), iterations=3)
    np.testing.assert_allclose(b[0], a[0], atol=1e-10)
    np.testing.assert_allclose(b[1], a[1], atol=1e-10)
    assert b[2]["loglik"] == pytest.approx(a[2]["loglik"], rel=1e-10)


@pytest.fixture(scope="module")
def skeleton_model(tmp_path_factory: pytest.TempPathFactory):
    root = Path(tmp_path_factory.mktemp("split")) / "in"
    sim = simulate_skeletons("native", seed=6, frames=10, people=2, cameras=5, noise_px=1.0)
    write_skeleton_scene(sim, root, "native")
    scene = load_scene(root)
    est = us.UKFSmoother()
    pre = est.prepare(scene)
    model = Model.of(pre)
    cfg = replace(est.config, accel_sd=0.5, shape_sd=0.01, joint_accel_sd=0.5)
    return model, us.initial_states(model, cfg), cfg, scene.fps


def test_split_joint_filters_equal_the_whole_state_filter(skeleton_model) -> None:
    model, init, cfg, fps = skeleton_model
    xa, Pa, ia = us.run_filter(model, init, cfg, fps, collect=True, split=False)
    xb, Pb, ib = us.run_filter(model, init, cfg, fps, collect=True, split=True)
    np.testing.assert_allclose(xb, xa, atol=1e-8)
    np.testing.assert_allclose(Pb, Pa, atol=1e-9)
    np.testing.assert_allclose(ib["loglik_rows"], ia["loglik_rows"], rtol=1e-8, atol=1e-8)
    np.testing.assert_array_equal(ib["weights"], ia["weights"])


def test_several_noise_values_in_one_pass_equal_separate_passes(skeleton_model) -> None:
    model, init, cfg, fps = skeleton_model
    values = [0.1, 1.0, 5.0]
    sel = np.arange(len(model.rows))
    rows_k, src, copy = replicate_rows(model.rows, sel, len(values))
    run = us.run_filter(model.take(rows_k, src), us.Init(init.x0[src], init.P0[src]),
                        replace(cfg, smooth=False, iterations=1), fps, fade=False,
                        noise_rows={"joint_accel_sd": np.asarray(values)[copy]})[2]
    together = np.bincount(copy, weights=run["loglik_rows"])
    for k, v in enumerate(values):
        alone = us.run_filter(model, init, replace(cfg, joint_accel_sd=v, smooth=False, iterations=1),
                              fps, fade=False)[2]["loglik"]
        assert together[k] == pytest.approx(alone, rel=1e-9)


def test_the_search_finds_the_top_of_a_curve() -> None:
    calls: list[int] = []

    def f(values: list[float]) -> list[float]:
        calls.append(len(values))
        return [-(np.log(v) - np.log(0.37)) ** 2 for v in values]

    best, seen = us.maximise_log(f, 0.01, 100.0, 5)
    assert best == pytest.approx(0.37, rel=1e-6)  # a parabola in log q: the vertex is exact
    assert max(seen, key=lambda v: seen[v]) == best
    assert len(calls) == 3  # the scan and two rounds, each one batch


def test_gauss_newton_reaches_gtsam_levenberg_marquardt() -> None:
    import gtsam

    from gt3dkit.fusion.smoother_gtsam import _gauss_newton

    rng = np.random.default_rng(7)
    g = gtsam.NonlinearFactorGraph()
    vals = gtsam.Values()
    K = gtsam.Cal3_S2(800, 800, 0, 320, 240)
    cams = [gtsam.PinholeCameraCal3_S2(gtsam.Pose3(gtsam.Rot3.Ypr(0.3 * i, 0, 0), gtsam.Point3(
        -3 * np.sin(0.3 * i), 0, -3 * np.cos(0.3 * i))), K) for i in range(4)]
    huber = gtsam.noiseModel.mEstimator.Huber.Create(1.345)
    for j in range(5):
        p = rng.normal(size=3) * 0.3
        for cam in cams:
            uv = cam.project(p) + rng.normal(size=2)
            g.add(gtsam.TriangulationFactorCal3_S2(cam, uv, gtsam.noiseModel.Robust.Create(
                huber, gtsam.noiseModel.Isotropic.Sigma(2, 1.0)), j))
        vals.insert(j, p + rng.normal(size=3) * 0.05)
    ours, iters, err = _gauss_newton(g, vals, 100, 1e-12)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    params.setMaxIterations(200)
    ref = gtsam.LevenbergMarquardtOptimizer(g, vals, params).optimize()
    assert 1 <= iters < 100
    assert err == pytest.approx(g.error(ref), rel=1e-6)
    for j in range(5):
        np.testing.assert_allclose(ours.atPoint3(j), ref.atPoint3(j), atol=1e-6)


@pytest.mark.parametrize("case", ["fade", "search"])
def test_compiled_box_filter_equals_the_frame_loop(box_model, case: str) -> None:
    """The compiled forward pass and RTS smoother of a boxes-only model (objects as chains of
    rows, split over threads) against run_filter's loop over frames with the same update."""
    from gt3dkit.fusion import boxupdate

    model = box_model
    assert boxupdate.applies_to_model(model)
    # a process noise far too small for walkers: predictions are faded (Model.prior_conflict)
    cfg = replace(us.UKFSmoother().config, accel_sd=0.02 if case == "fade" else 0.4, shape_sd=0.02)
    init = us.initial_states(model, cfg)
    kw: dict = {"collect": True}
    if case == "search":  # some objects only, per-row noise, no fading, no smoothing
        on = us.search_rows(model.rows, len(model.rows) // 2, seed=1)
        kw = {"on": on, "fade": False, "noise_rows": {"accel_sd": np.where(model.rows.row_o % 2, 0.3, 1.5)},
              "collect": True}
        cfg = replace(cfg, smooth=False)
    a = us.run_filter(model, init, cfg, 10.0, **kw)
    b = us.run_filter(model, init, cfg, 10.0, compiled=False, **kw)
    np.testing.assert_allclose(a[0], b[0], rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(a[1], b[1], rtol=1e-8, atol=1e-12)
    for k in ("loglik_rows", "nis_rows", "dof_rows", "weights", "score2", "residual"):
        np.testing.assert_allclose(a[2][k], b[2][k], rtol=1e-7, atol=1e-8, err_msg=k)
    for k in ("predictions_faded", "object_frames", "pd_repairs"):
        assert a[2][k] == b[2][k], k
    assert (a[2]["predictions_faded"] > 0) == (case == "fade")


def test_compiled_box_fit_equals_the_numpy_fit() -> None:
    """The compiled per-frame LM fit (gt3dkit.fusion.boxlm) against the batched numpy fit:
    lens distortion, an object behind a camera, a camera without a box, a clipped edge, an
    outlier, one-view rows, per-edge noise and a shape prior (both stop on the same test, but
    their step sizes differ by rounding, so the minima agree to the convergence tolerance)."""
    from gt3dkit.fusion.boxfit import fit_boxes
    from gt3dkit.geom.camera import Cams

    cams = Cams.of(simulate("wildtrack", seed=7, frames=2, people=1).rig)
    rng = np.random.default_rng(4)
    N = 60
    centre = np.c_[rng.uniform(-2, 10, N), rng.uniform(-5, 25, N), np.full(N, 0.9)]
    axes = np.c_[rng.uniform(0.2, 0.35, (N, 2)), rng.uniform(0.75, 0.95, N)]
    z, margin = ellipsoid_boxes(centre, axes, cams.world_from_body, cams.K, cams.dist, cams.R, cams.t,
                                cams.depth_sign)
    z = z + rng.normal(size=z.shape) * 1.0
    size = np.tile(cams.wh, 2)  # (C, 4)
    on_image = np.all((z > -0.5 * size) & (z < 1.5 * size), axis=-1)  # as an annotator draws them
    mask = np.isfinite(z) & ((margin > 0) & on_image)[..., None]
    z[3, :, 0] += 40.0  # an outlier edge (in every camera that sees it)
    mask[5, :2] = False  # cameras without a box
    mask[6, :, 3] = False  # a clipped bottom edge
    lone = np.flatnonzero(mask.any(-1).sum(-1) >= 2)[:5]
    view = np.argmax(mask[lone].any(-1), axis=1)
    mask[lone] = False
    mask[lone, view] = True  # one view each
    z = np.where(mask, z, np.nan)
    p0 = np.full((N, 6), np.nan)
    p0[10] = np.r_[centre[10] + [0.5, -0.4, 0.2], np.log(axes[10]) + 0.3]  # a start of its own
    for kw in ({}, {"sigma_px": np.array([1.0, 2.0, 1.0, 3.0]), "prior_log_axes": np.log([0.3, 0.3, 0.85]),
                    "prior_sd": np.array([0.1, 0.1, 0.05]), "p0": p0}):
        a = fit_boxes(z, mask, cams, **kw)
        b = fit_boxes(z, mask, cams, compiled=False, **kw)
        assert a.ok.sum() > 40
        np.testing.assert_array_equal(a.ok, b.ok)
        # one view fixes depth through the weak prior alone: LM crawls there, and where the two
        # stop differs; the compiled fit must end no worse
        assert np.all(a.rss_px2[a.ok] <= b.rss_px2[a.ok] * (1 + 1e-5) + 1e-6)  # both stop at 0.1 um steps
        ok = a.ok & (mask.any(-1).sum(-1) >= 2)
        np.testing.assert_allclose(a.center_world[ok], b.center_world[ok], atol=2e-5)
        np.testing.assert_allclose(a.log_axes[ok], b.log_axes[ok], atol=2e-5)
        np.testing.assert_allclose(a.rss_px2[ok], b.rss_px2[ok], rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(a.cov[ok], b.cov[ok], rtol=1e-3, atol=1e-9)
        np.testing.assert_array_equal(np.isnan(a.residual_px), np.isnan(b.residual_px))
        np.testing.assert_allclose(a.leverage[ok], b.leverage[ok], atol=1e-4)
        assert (~ok & a.ok).sum() >= 5
    # a start 50 m off (the numpy reference's batched solve fails on its singular steps)
    p0[10] = [50.0, 50.0, 0.9, -1.2, -1.2, -0.2]
    far = fit_boxes(z, mask, cams, p0=p0)
    assert np.isfinite(far.center_world[10]).all()


def test_linearised_search_pass_is_a_plain_kalman_filter(box_model) -> None:
    """The noise search's linear pass (boxes regressed once per row) against a Kalman filter
    written with numpy and scipy's Gaussian density on the same regression: the same
    log-likelihood at two noise values."""
    from scipy.stats import multivariate_normal

    from gt3dkit.fusion.boxupdate import LinearisedSearch

    model = box_model
    cfg = replace(us.UKFSmoother().config, accel_sd=0.5, shape_sd=0.01)
    init = us.initial_states(model, cfg)
    x_s, P_s, _ = us.run_filter(model, init, cfg, 10.0)
    rng = np.random.default_rng(2)
    w = np.where(rng.uniform(size=model.z.shape) < 0.05, 0.3, 1.0)  # some weights below 1
    lin = LinearisedSearch(model, init, cfg, 10.0, x_s, P_s, w, None)
    rows, lay = model.rows, model.layout
    dims = lin.dims
    for accel, shape in ((0.5, 0.01), (2.0, 0.001)):
        total = 0.0
        for start in np.flatnonzero(rows.prev_row < 0):
            r, prev = int(start), -1
            x, P = init.x0[r], init.P0[r]
            while r >= 0:
                if prev >= 0:
                    dt = (rows.frames[rows.row_t[r]] - rows.frames[rows.row_t[prev]]) / 10.0
                    F, Q = lay.transition(np.array([dt]), accel, shape, up=model.cams.up,
                                          vertical_ratio=cfg.vertical_ratio)
                    x, P = F[0] @ x, F[0] @ P @ F[0].T + Q[0]
                use = lin.mk[r] & (w[r] > 0)
                H = np.zeros((use.sum(), lay.n))
                H[:, dims] = lin.At[r][:, use].T
                Rm = np.diag(lin.D[r][use] / w[r][use])
                S = H @ P @ H.T + Rm
                y = lin.cvec[r][use]
                total += multivariate_normal(H @ x, S).logpdf(y)
                Kg = P @ H.T @ np.linalg.inv(S)
                x, P = x + Kg @ (y - H @ x), P - Kg @ S @ Kg.T
                prev, r = r, int(rows.next_row[r])
        assert lin.logliks([accel], [shape])[0] == pytest.approx(total, rel=1e-9)


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
        found[lin] = tr.info["params"]
        assert ("linearisation" in tr.info["noise_search"]["provisional"]["use"]) == lin
    for k in ("accel_sd", "shape_sd"):
        assert found[True][k] == pytest.approx(found[False][k], rel=0.15), k


@pytest.mark.parametrize("kind", ["distorted", "pinhole", "skewed"])
def test_tangent_box_gradient_equals_finite_differences(kind: str) -> None:
    """The tangent box's analytic derivatives (envelope theorem, forward mode) against central
    differences of the numpy reference."""
    from gt3dkit.geom.boxkernel import camera_setup, pair_box_grad

    rng = np.random.default_rng({"distorted": 5, "pinhole": 6, "skewed": 7}[kind])
    C, N = 4, 60
    R, t, K, dist = _random_cameras(rng, C, kind)
    Rb = _rot(rng)
    Rc, gx, gy = camera_setup(Rb, K, R)
    ds = np.ones(C)
    eps = np.r_[[1e-6] * 3, [1e-7] * 3]
    checked = 0
    for _ in range(N):
        p = np.r_[rng.normal(size=3) * 2.0, np.log(np.exp(rng.normal(size=3) * 0.3) * 0.4)]
        steps = np.concatenate([np.diag(eps), -np.diag(eps)])
        P = p[None] + steps
        ref, _ = ellipsoid_boxes_numpy(P[:, :3], np.exp(P[:, 3:]), Rb, K, dist, R, t, ds)  # (12, C, 4)
        fd = np.moveaxis((ref[:6] - ref[6:]) / (2 * eps[:, None, None]), 0, -1)  # (C, 4, 6)
        b0, _ = ellipsoid_boxes_numpy(p[None, :3], np.exp(p[None, 3:]), Rb, K, dist, R, t, ds)
        for c in range(C):
            box, grad = np.empty(4), np.empty((4, 6))
            pair_box_grad(*p, c, Rc, gx, gy, K, dist, R, t, ds, 2, box, grad)
            inside = np.all((b0[0, c] > 0) & (b0[0, c] < 1920)) and np.isfinite(fd[c]).all()
            if not inside:
                continue
            np.testing.assert_allclose(box, b0[0, c], atol=1e-6)
            np.testing.assert_allclose(grad, fd[c], rtol=2e-4, atol=2e-3 * np.abs(fd[c]).max())
            checked += 1
    assert checked > 40

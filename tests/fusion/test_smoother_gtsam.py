"""The GTSAM smoother's own Gauss-Newton loop (gt3dkit.fusion.graph.smoother) against GTSAM's
Levenberg-Marquardt optimizer."""

from __future__ import annotations

import numpy as np
import pytest


def test_gauss_newton_reaches_gtsam_levenberg_marquardt() -> None:
    import gtsam

    from gt3dkit.fusion.graph.factors import gtsam_gauss_newton

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
    ours, iters, err = gtsam_gauss_newton(g, vals, 100, 1e-12)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    params.setMaxIterations(200)
    ref = gtsam.LevenbergMarquardtOptimizer(g, vals, params).optimize()
    assert 1 <= iters < 100
    assert err == pytest.approx(g.error(ref), rel=1e-6)
    for j in range(5):
        np.testing.assert_allclose(ours.atPoint3(j), ref.atPoint3(j), atol=1e-6)

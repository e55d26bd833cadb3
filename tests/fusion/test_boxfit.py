"""The per-frame box fit (gt3dkit.fusion.preparation.boxfit.fit_boxes, compiled Levenberg-Marquardt) against
scipy's least_squares on the same residuals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from gt3dkit.fusion.preparation.boxfit import PERSON_SEMI_AXES_M, fit_boxes, inverse_rows, state_boxes
from gt3dkit.geom.camera import Cams
from gt3dkit.geom.conics import ellipsoid_boxes
from gt3dkit.sim import simulate


def _scene(seed: int = 4):
    """60 person-sized ellipsoids on the WILDTRACK rig's ground: lens distortion, an object
    behind a camera, cameras without a box, a clipped edge, an outlier, one-view rows."""
    cams = Cams.of(simulate("wildtrack", seed=7, frames=2, people=1).rig)
    rng = np.random.default_rng(seed)
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
    return cams, np.where(mask, z, np.nan), mask, centre, axes


def _scipy_fit(p0, z, mask, cams, sigma, prior, prior_sd):
    def res(q):
        box = state_boxes(q[None, :3], q[None, 3:], cams, mask.any(-1)[None])[0]
        r = np.where(mask, (box - np.nan_to_num(z)) / sigma, 0.0).ravel()
        return np.r_[np.nan_to_num(r, nan=1e6), (q[3:] - prior) / prior_sd]

    return least_squares(res, p0, method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12)


def test_box_fit_reaches_scipys_least_squares_minimum() -> None:
    cams, z, mask, centre, axes = _scene()
    sigma = np.array([1.0, 2.0, 1.0, 3.0])
    prior, prior_sd = np.log([0.3, 0.3, 0.85]), np.array([0.1, 0.1, 0.05])
    for kw in ({}, {"sigma_px": sigma, "prior_log_axes": prior, "prior_sd": prior_sd}):
        fit = fit_boxes(z, mask, cams, **kw)
        s = kw.get("sigma_px", 1.0)
        pr = kw.get("prior_log_axes", np.log(PERSON_SEMI_AXES_M))
        ps = kw.get("prior_sd", 1.0)
        multi = fit.ok & (mask.any(-1).sum(-1) >= 2)
        assert multi.sum() > 40
        for n in np.flatnonzero(multi):
            p = np.r_[fit.center_world[n], fit.log_axes[n]]
            ref = _scipy_fit(p + [0.05, -0.05, 0.02, 0.05, -0.05, 0.02], z[n], mask[n], cams,
                             np.broadcast_to(s, (4,)), pr, np.broadcast_to(ps, (3,)))
            ours = 2 * _scipy_fit(p, z[n], mask[n], cams, np.broadcast_to(s, (4,)), pr,
                                  np.broadcast_to(ps, (3,))).cost  # scipy's cost is half the sum
            assert ours <= 2 * ref.cost * (1 + 1e-6) + 1e-6, n  # no better minimum nearby
            np.testing.assert_allclose(p[:3], ref.x[:3], atol=5e-5)
            np.testing.assert_allclose(p[3:], ref.x[3:], atol=5e-5)
        ok = fit.ok
        assert np.allclose(fit.rss_px2[ok], np.nansum(fit.residual_px[ok] ** 2, axis=(1, 2)))
        assert np.all(np.linalg.eigvalsh(fit.cov[ok]) > 0)
        assert np.linalg.norm(fit.center_world[multi] - centre[multi], axis=1).max() < 0.3


def test_box_fit_from_a_start_behind_the_cameras_stays_finite() -> None:
    """A start 50 m off (behind cameras: every trial step is infinitely bad) ends finite."""
    cams, z, mask, _, _ = _scene()
    p0 = np.full((len(z), 6), np.nan)
    p0[10] = [50.0, 50.0, 0.9, -1.2, -1.2, -0.2]
    far = fit_boxes(z, mask, cams, p0=p0)
    assert np.isfinite(far.center_world[10]).all()
    assert np.isfinite(far.cov[10]).all()


def test_a_singular_fit_has_no_covariance_and_does_not_sink_the_batch() -> None:
    """numpy's batched inverse raises for the whole batch when one matrix is singular: that
    row's covariance is NaN, every other row's is its own inverse."""
    rng = np.random.default_rng(3)
    B = rng.normal(size=(5, 6, 6))
    A = B @ np.swapaxes(B, 1, 2) + np.eye(6)
    A[2] = 0.0
    A[2, 0, 0] = 1.0  # rank one: LAPACK finds it singular
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.inv(A)
    cov = inverse_rows(A)
    assert np.isnan(cov[2]).all()
    keep = [0, 1, 3, 4]
    np.testing.assert_allclose(cov[keep], np.linalg.inv(A[keep]), rtol=1e-12)
    np.testing.assert_array_equal(inverse_rows(A[keep]), np.linalg.inv(A[keep]))

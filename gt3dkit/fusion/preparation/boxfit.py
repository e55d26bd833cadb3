r"""Boxes -> ellipsoids without a temporal model.

* :func:`state_boxes`: the measurement function, ellipsoid parameters -> tangent boxes.
* :func:`ground_init`: the paper's initialisation (box bottom-centre through the
  ground-plane homography, averaged over views), with box size for the semi-axes.
* :func:`fit_boxes`: a batched Levenberg-Marquardt least-squares fit of one
  ellipsoid (centre, log semi-axes) per object-frame to all its views' boxes: the
  triangulation baseline for boxes and the UKF's initialisation.
* :func:`choose_box_model`: which of the box models draws a label set's boxes.

Every function takes the box model from ``cams.box_model``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gt3dkit.fusion.preparation.boxlm import fit_compiled
from gt3dkit.geom.boxrig import BoxCameras
from gt3dkit.geom.camera import Cams, pixel_rays
from gt3dkit.geom.conics import model_boxes, outline_ellipse
from gt3dkit.types import B8, BOX_MODELS, F64

#: Prior semi-axes (m) for a standing person, used only as a weak regulariser and
#: for a view with no usable bottom edge.
PERSON_SEMI_AXES_M = np.array([0.3, 0.3, 0.85])


def state_boxes(center_world: F64, log_axes: F64, cams: Cams, want: np.ndarray | None = None) -> F64:
    """(..., 3) centres and (..., 3) log semi-axes -> (..., C, 4) boxes (px), NaN if behind;
    ``want`` (broadcastable to ``(..., C)``): only these cameras' boxes (the others NaN)."""
    box, _ = model_boxes(center_world, np.exp(log_axes), cams, want)
    return box


def ground_init(box_z: F64, box_mask: B8, cams: Cams) -> tuple[F64, F64, B8]:
    """Initial ellipsoids from boxes via the ground plane ``up . X = 0``.

    Each view's box bottom-centre is back-projected and met with the ground (the
    paper's homography ``K [r1 r2 t]``, generalised to any up vector and to lens
    distortion); the ground points are averaged. The semi-axes come from the box
    size at that depth. Views whose bottom edge is clipped fall back to the box
    centre at the depth a person-sized object would have.

    Parameters
    ----------
    box_z : (N, C, 4) boxes, NaN = none; box_mask : (N, C, 4) usable edges

    Returns
    -------
    center_world : (N, 3), log_axes : (N, 3), ok : (N,) at least one view was usable
    """
    up = cams.up
    fx, fy = cams.K[:, 0, 0], cams.K[:, 1, 1]
    has = np.all(np.isfinite(box_z), axis=-1)
    bz = np.where(has[..., None], box_z, 0.0)
    w = bz[..., 2] - bz[..., 0]
    h = bz[..., 3] - bz[..., 1]
    bottom = np.stack([(bz[..., 0] + bz[..., 2]) / 2, bz[..., 3]], -1)
    o, d = pixel_rays(bottom, cams.K, cams.dist, cams.R, cams.t, cams.depth_sign)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -(o @ up)[None, :] / (d @ up)
    g = o + lam[..., None] * d
    depth = (np.einsum("cj,...cj->...c", cams.R[:, 2, :], g) + cams.t[:, 2]) * cams.depth_sign
    ok_g = has & box_mask[..., 3] & (lam > 0) & (depth > 0)
    half_h = 0.5 * h * depth / fy
    half_w = 0.5 * w * depth / fx
    center_g = g + half_h[..., None] * up
    # fallback: box centre at the depth of a person-sized object
    mid = np.stack([(bz[..., 0] + bz[..., 2]) / 2, (bz[..., 1] + bz[..., 3]) / 2], -1)
    o2, d2 = pixel_rays(mid, cams.K, cams.dist, cams.R, cams.t, cams.depth_sign)
    with np.errstate(divide="ignore", invalid="ignore"):
        dep2 = fy * 2 * PERSON_SEMI_AXES_M[2] / np.maximum(h, 1.0)
    dz = np.einsum("cj,...cj->...c", cams.R[:, 2, :], d2) * cams.depth_sign
    center_f = o2 + (dep2 / np.maximum(dz, 1e-6))[..., None] * d2
    use_g = ok_g.any(axis=1)
    wts = np.where(use_g[:, None], ok_g, has).astype(np.float64)
    n = np.maximum(wts.sum(axis=1), 1.0)
    cen = np.where(use_g[:, None, None], center_g, center_f)
    center = np.einsum("nc,nci->ni", wts, np.nan_to_num(cen)) / n[:, None]
    hh = np.where(use_g[:, None], half_h, PERSON_SEMI_AXES_M[2])
    hw = np.where(use_g[:, None], half_w, PERSON_SEMI_AXES_M[0])
    c_ax = np.einsum("nc,nc->n", wts, np.nan_to_num(hh)) / n
    a_ax = np.einsum("nc,nc->n", wts, np.nan_to_num(hw)) / n
    ok = wts.sum(axis=1) > 0
    a_ax = np.where(ok & (a_ax > 0.01), a_ax, PERSON_SEMI_AXES_M[0])
    c_ax = np.where(ok & (c_ax > 0.01), c_ax, PERSON_SEMI_AXES_M[2])
    log_axes = np.log(np.stack([a_ax, a_ax, c_ax], -1))
    return center, log_axes, ok


@dataclass(frozen=True)
class BoxFit:
    """Per-object-frame least-squares ellipsoids.

    center_world : (N, 3) m; log_axes : (N, 3); cov : (N, 6, 6) of (centre, log axes)
    rss_px2 : (N,) sum of squared edge residuals (px^2); n_edges : (N,) usable edges
    margin : (N, C) depth margin of the fitted ellipsoid in each camera (m, > 0 = in front)
    ok : (N,) had at least one box
    residual_px : (N, C, 4) fitted minus annotated edge (NaN where the edge is not used)
    leverage : (N, C, 4) each used edge's leverage ``J_i (J^T J)^{-1} J_i^T`` in [0, 1]
    """

    center_world: F64
    log_axes: F64
    cov: F64
    rss_px2: F64
    n_edges: F64
    margin: F64
    ok: B8
    residual_px: F64
    leverage: F64


def inverse_rows(A: F64) -> F64:
    """``(N, k, k)`` inverses of ``A (N, k, k)``; a matrix LAPACK finds singular (a fit whose
    Jacobian overflowed or vanished) gets NaN, the others their inverse (numpy's batched inverse
    raises for the whole batch on one singular matrix)."""
    try:
        return np.asarray(np.linalg.inv(A), dtype=np.float64)
    except np.linalg.LinAlgError:
        out = np.full(A.shape, np.nan)
        for i, a in enumerate(A):
            try:
                out[i] = np.linalg.inv(a)
            except np.linalg.LinAlgError:
                pass  # stays NaN: the fit has no covariance, its row is not ok
        return out


def fit_boxes(box_z: F64, box_mask: B8, cams: Cams, sigma_px: F64 | float = 1.0,
              prior_log_axes: F64 | None = None, prior_sd: F64 | float = 1.0,
              iters: int = 40, p0: F64 | None = None) -> BoxFit:
    """Fit one ellipsoid to each object-frame's boxes (batched Levenberg-Marquardt).

    Parameters
    ----------
    box_z : (N, C, 4) boxes in distorted pixels (NaN = none)
    box_mask : (N, C, 4) usable edges
    sigma_px : edge noise (px), scalar or ``(4,)`` per edge (xmin, ymin, xmax, ymax): the
        residuals are whitened by it, so ``cov`` is the fit's covariance in parameter units
    prior_log_axes : (3,) weak prior mean of the log semi-axes (default: a person)
    prior_sd : its standard deviation (log units, scalar or (3,)); keeps one-view fits defined
    p0 : (N, 6) start (centre, log axes); default the ground-plane initialisation

    The LM loop is compiled (:mod:`gt3dkit.fusion.preparation.boxlm`), one object-frame at a time.
    """
    N = box_z.shape[0]
    prior = np.log(PERSON_SEMI_AXES_M) if prior_log_axes is None else prior_log_axes
    c0, la0, ok = ground_init(box_z, box_mask, cams)
    p = np.concatenate([c0, la0], axis=1)
    if p0 is not None:
        start = np.all(np.isfinite(p0), axis=1)
        p[start] = p0[start]
    z = np.where(box_mask, box_z, 0.0)
    p, r, J = fit_compiled(p, z, box_mask, ok, np.asarray(sigma_px, dtype=np.float64), prior,
                           np.asarray(prior_sd, dtype=np.float64), iters, BoxCameras.of(cams))
    cov = inverse_rows(np.matmul(J.transpose(0, 2, 1), J) + 1e-12 * np.eye(6))
    ok = ok & np.all(np.isfinite(cov), axis=(1, 2))
    n_edges = box_mask.reshape(N, -1).sum(axis=1).astype(np.float64)
    m = box_mask.reshape(N, -1).shape[1]
    Jm = J[:, :m]
    lev = np.sum(np.matmul(Jm, cov) * Jm, axis=-1).reshape(box_mask.shape)
    res_px = np.where(box_mask, r[:, :m].reshape(box_mask.shape) * sigma_px, np.nan)
    rss = np.sum(np.nan_to_num(res_px) ** 2, axis=(1, 2))
    _, _, margin = outline_ellipse(p[:, :3], np.exp(p[:, 3:]), cams.world_from_body, cams.R,
                                   cams.t, cams.depth_sign)
    return BoxFit(center_world=p[:, :3], log_axes=p[:, 3:], cov=cov, rss_px2=rss,
                  n_edges=n_edges, margin=margin, ok=ok, residual_px=res_px,
                  leverage=np.where(box_mask, lev, np.nan))


#: A box model other than the paper's ellipsoid is chosen only when its per-frame fits leave the
#: edges at most this fraction of the ellipsoid's median residual (a clear, not a marginal, win).
OTHER_MODEL_GAIN = 0.9
#: Object-frames (seen by three or more cameras, evenly spread) the choice fits.
CHOICE_ROWS = 400


def choose_box_model(box_z: F64, box_mask: B8, cams: Cams) -> tuple[str, dict[str, float]]:
    """The box model (:data:`gt3dkit.types.BOX_MODELS`) that draws these boxes: the one whose
    per-frame fits (the same six parameters under every model) leave the smallest median
    absolute edge residual, on up to :data:`CHOICE_ROWS` object-frames seen by three or more
    cameras. A label set's boxes are made one way: a tight box around a person (the ellipsoid),
    a cylinder's projection, or the occupancy-map generator's rectangle from an annotated
    ground position; fitting the wrong one leaves a misfit of several pixels that depends on
    the viewing angle, which no noise level absorbs. Another model than the ellipsoid must beat
    it by :data:`OTHER_MODEL_GAIN`.

    Returns the name and each model's median residual (px); ``("ellipsoid", {})`` when fewer
    than 20 object-frames are seen three times (nothing to choose from).
    """
    n_views = box_mask.any(axis=2).sum(axis=1)
    idx = np.flatnonzero(n_views >= 3)
    if idx.size < 20:
        return "ellipsoid", {}
    idx = idx[np.unique(np.linspace(0, idx.size - 1, min(CHOICE_ROWS, idx.size)).astype(np.int64))]
    px: dict[str, float] = {}
    for k, name in enumerate(BOX_MODELS):
        fit = fit_boxes(box_z[idx], box_mask[idx], cams._replace(box_model=k))
        r = np.abs(fit.residual_px[fit.ok])
        px[name] = float(np.median(r[np.isfinite(r)]))
    best = min(px, key=lambda m: px[m])
    if px[best] > OTHER_MODEL_GAIN * px["ellipsoid"]:
        best = "ellipsoid"
    return best, px

"""The UKF's stacked measurement model: what a row's state predicts in every camera.

Measurement vector of a row: ``[box edges (C*4) | keypoints (C*J*2)]``, each block present
only when the scene has it. Box edges are the exact tangent box of the projected ellipsoid
(:func:`gt3dkit.fusion.preparation.boxfit.state_boxes`), keypoints the projection with distortion. Bones
reach the joints as information added after the views (:mod:`gt3dkit.fusion.ukf.bones`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np

from gt3dkit.arrays import contiguous
from gt3dkit.fusion.motion import SPACE, StateLayout
from gt3dkit.fusion.preparation.boxfit import state_boxes
from gt3dkit.fusion.preparation.prepare import Prepared
from gt3dkit.fusion.preparation.robust import RobustConfig
from gt3dkit.fusion.preparation.rows import Rows
from gt3dkit.fusion.ukf.bones import JointInfo
from gt3dkit.fusion.ukf.boxupdate import box_regressions, box_sigma
from gt3dkit.fusion.ukf.rowsmodel import OUTLINE_STEPS, BoxModel
from gt3dkit.fusion.ukf.sigma import Block, Robust, SigmaWeights, block_columns
from gt3dkit.fusion.ukf.update import Columns, Measured, Regression
from gt3dkit.geom.boxkernel import EDGES
from gt3dkit.geom.boxrig import BoxCameras, BoxRig, box_rig
from gt3dkit.geom.camera import Cams, project_points
from gt3dkit.types import F64


@dataclass
class Model:
    """Everything one filter run needs besides the noise settings.

    z, mask, var, weight0 : (R, m) measurements, which are present, their variances and
    the weights the update starts from (the per-frame fits' verdicts, 1 kept, 0 rejected;
    where a frame's verdict is contested the prior soon overrules it: such a frame neither
    fades the prediction nor sets the linearisation point); robust_blocks : the ``(slice,
    entries per point)`` blocks whose points the update may down-weight;
    x_frame, var_frame, cov6_frame : each row's own per-frame state (see
    :meth:`gt3dkit.fusion.preparation.prepare.Prepared.frame_state`).
    """

    rows: Rows
    cams: Cams
    layout: StateLayout
    use_box: bool
    z: F64
    mask: np.ndarray
    var: F64
    weight0: F64
    robust_blocks: tuple[tuple[slice, int], ...]
    x_frame: F64
    var_frame: F64
    cov6_frame: F64
    centre_determined: np.ndarray  # (R,) the per-frame box fit rests on 2+ views
    kpt_cov_frame: F64 | None = None  # (R, J, 3, 3) per-frame joints' covariance
    joint_info: JointInfo | None = None  # added to the joints after each frame's views (bones)
    box_tail: float = 1.0  # box edges are tested at this multiple of their variance (Prepared.box_tail)

    @classmethod
    def of(cls, pre: Prepared) -> Model:
        rows, cams, lay = pre.rows, pre.cams, pre.layout
        R, C, J = len(rows), len(cams.K), lay.n_joints
        zs, masks, vars_, w0, blocks = [], [], [], [], []
        at = 0
        if pre.use_box:
            zs.append(rows.box_z.reshape(R, C * 4))
            masks.append(rows.box_mask.reshape(R, C * 4))
            var = np.broadcast_to(np.tile(pre.sigma_box**2, C), (R, C * 4))
            if pre.box_var_scale is not None:  # edges of crowded views (gt3dkit.fusion.preparation.crowd)
                var = var * pre.box_var_scale.reshape(R, C * 4)
            vars_.append(var)
            w0.append(pre.box_keep.reshape(R, C * 4).astype(np.float64))
            blocks.append((slice(at, at + C * 4), 1))
            at += C * 4
        if pre.use_kpt:
            zk = rows.kpt_z.reshape(R, C * J * 2)
            zs.append(zk)
            masks.append(np.isfinite(zk))
            vars_.append(np.repeat(pre.kpt_var.reshape(R, C * J), 2, axis=1))
            w0.append(np.repeat(pre.kpt_keep.reshape(R, C * J), 2, axis=1).astype(np.float64))
            blocks.append((slice(at, at + C * J * 2), 2))
        mask = np.concatenate(masks, 1)
        x_f, v_f, c6 = pre.frame_state()
        det = pre.fit_reliable
        kcov = None
        if pre.use_kpt and pre.kpt0_cov is not None:
            # only reliable per-frame joints may fade a prediction or set a linearisation point
            kcov = np.where(pre.kpt_reliable[..., None, None], pre.kpt0_cov, np.inf)
            v_f = v_f.copy()
            v_f[:, lay.joints] = np.where(np.repeat(pre.kpt_reliable, SPACE, axis=1),
                                          v_f[:, lay.joints], np.inf)
        return cls(rows, cams, lay, pre.use_box, np.where(mask, np.concatenate(zs, 1), 0.0),
                   mask, np.concatenate(vars_, 1), np.concatenate(w0, 1),
                   tuple(blocks) if pre.robust.enabled else (), x_f, v_f, c6, det, kcov,
                   box_tail=pre.box_tail)

    def take(self, rows: Rows, src: np.ndarray) -> Model:
        """This model for ``rows`` whose row ``i`` is this model's row ``src[i]``
        (:func:`gt3dkit.fusion.preparation.rows.replicate_rows`)."""
        return replace(self, rows=rows, z=self.z[src], mask=self.mask[src], var=self.var[src],
                       weight0=self.weight0[src], x_frame=self.x_frame[src],
                       var_frame=self.var_frame[src], cov6_frame=self.cov6_frame[src],
                       centre_determined=self.centre_determined[src],
                       kpt_cov_frame=None if self.kpt_cov_frame is None else self.kpt_cov_frame[src])


    @functools.cached_property
    def frame_centre_trace(self) -> F64:
        """(R,) trace of each row's per-frame centre covariance where that fit determines the
        centre (2+ views, finite), else inf (:meth:`linearisation_point`)."""
        c6 = self.cov6_frame
        ok6 = (np.all(np.isfinite(c6), axis=(1, 2)) & self.centre_determined
               & np.all(np.isfinite(self.x_frame[:, self.layout.center]), axis=1))
        return np.where(ok6, np.einsum("rii->r", np.nan_to_num(c6[:, :SPACE, :SPACE])), np.inf)


    @functools.cached_property
    def box_cameras(self) -> BoxCameras:
        return BoxCameras.of(self.cams)

    @functools.cached_property
    def box_rig(self) -> BoxRig:
        return box_rig(self.box_cameras, OUTLINE_STEPS)

    def box_measurement(self, alpha: float, beta: float, kappa: float,
                        robust: RobustConfig | None, seen_s: F64 | None = None) -> BoxModel:
        """The box update's :class:`gt3dkit.fusion.ukf.boxupdate.BoxModel` under the sigma rule
        ``alpha, beta, kappa``, the measurement points judged by ``robust`` (None: none); one
        pass, not reweighting; ``seen_s (R, C)``: each view's time after its row's (seconds; the
        boxes then regressed on the velocity too), None: every view at its row's time."""
        timed = seen_s is not None
        dims = self.layout.timed_ellipsoid_dims if timed else self.layout.ellipsoid_dims
        return BoxModel(box_sigma(dims, alpha, beta, kappa), self.box_rig, self.columns(robust, timed), at=0,
                        iterations=1, robust=False,
                        seen_s=contiguous(seen_s if seen_s is not None else np.zeros((0, len(self.cams.K)))))

    def columns(self, robust: RobustConfig | None, timed: bool = False) -> Columns:
        """The measurement vector's :class:`gt3dkit.fusion.ukf.update.Columns`
        (:func:`gt3dkit.fusion.ukf.sigma.block_columns`; ``timed``: the boxes on the velocity too)."""
        rule = Robust(robust, self.robust_blocks) if robust is not None and self.robust_blocks else None
        cols = block_columns(self.blocks(timed), self.z.shape[1], rule)
        if not (self.use_box and self.box_tail != 1.0):
            return cols
        scale = np.ones(self.z.shape[1])
        scale[:self.n_box_columns] = np.sqrt(self.box_tail)
        return cols._replace(c_thr=cols.c_thr * scale, g_thr=cols.g_thr * scale)

    @property
    def n_box_columns(self) -> int:
        """The box edges lead the measurement vector: 4 per camera (0 without boxes)."""
        return 4 * len(self.cams.K) if self.use_box else 0

    def test_variance(self) -> F64:
        """(m,) the variance factor each column's outlier test is made at (``box_tail`` for
        box edges, 1 for the rest)."""
        out = np.ones(self.z.shape[1])
        out[:self.n_box_columns] = self.box_tail
        return out

    def blocks(self, timed: bool = False) -> list[Block]:
        """The measurement vector as :class:`gt3dkit.fusion.ukf.sigma.Block` groups: the box edges of
        all cameras (centre and log semi-axes, ``timed``: and the velocity; regressed by
        :func:`gt3dkit.fusion.ukf.boxupdate.box_regression`), each joint's projections into all
        cameras (its three coordinates)."""
        C, J = len(self.cams.K), self.layout.n_joints
        lay, cams = self.layout, self.cams
        out: list[Block] = []
        at = 0
        if self.use_box:
            ell = lay.timed_ellipsoid_dims if timed else lay.ellipsoid_dims

            def regress(active: np.ndarray, xj: F64, Pj: F64, meas: Measured, w: SigmaWeights,
                        lin: Regression, repaired: np.ndarray) -> None:
                box_regressions(active.astype(np.int64), xj, Pj, meas, box_sigma(ell, w.alpha, w.beta,
                                                                                 w.kappa),
                                self.box_rig, 0, lin, repaired)

            out.append(Block(ell[None], np.arange(C * EDGES)[None], None, regress=regress))
            at = C * EDGES
        if J:
            jdims = lay.joint_dims(np.arange(J))  # (J, 3)
            cols = at + 2 * (np.arange(C)[None, :, None] * J + np.arange(J)[:, None, None]) + np.arange(2)

            def project(X: F64) -> F64:  # (B, J, S, 3) -> (B, J, S, 2C)
                uv, _ = project_points(X, cams.K, cams.dist, cams.R, cams.t, cams.depth_sign)
                return uv.reshape(X.shape[:3] + (2 * C,))

            out.append(Block(jdims, cols.reshape(J, 2 * C), project))
        return out

    def h(self, X: F64) -> F64:
        """(B, S, n) -> (B, S, m) predicted measurements of all sigma points."""
        B, S = X.shape[:2]
        C, J = len(self.cams.K), self.layout.n_joints
        lay = self.layout
        parts = []
        if self.use_box:
            parts.append(state_boxes(X[..., lay.center], X[..., lay.log_axes],
                                     self.cams).reshape(B, S, C * 4))
        if J:
            P3 = X[..., lay.joints].reshape(B, S, J, SPACE)
            uv, _ = project_points(P3, self.cams.K, self.cams.dist, self.cams.R, self.cams.t,
                                   self.cams.depth_sign)  # (B,S,J,C,2)
            parts.append(np.swapaxes(uv, 2, 3).reshape(B, S, C * J * 2))
        return np.concatenate(parts, axis=-1)

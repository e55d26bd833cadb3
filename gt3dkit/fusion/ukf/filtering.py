"""The UKF's filter loop: the initial states, the filter (forward, fading, the update, then the
RTS pass) by the model's backend (boxes alone: per-object compiled chains,
:func:`gt3dkit.fusion.ukf.boxupdate.run_boxes`; with joints: per-joint compiled chains,
:func:`gt3dkit.fusion.ukf.jointupdate.run_joints`), a run of some objects again, and the weights a
smoothed estimate gives every measurement."""

from __future__ import annotations

import numpy as np

from gt3dkit.fusion.preparation.robust import point_weights
from gt3dkit.fusion.preparation.rows import Rows
from gt3dkit.fusion.ukf.boxupdate import run_boxes
from gt3dkit.fusion.ukf.config import NoiseRows, UKFConfig
from gt3dkit.fusion.ukf.filterrun import FilterRun
from gt3dkit.fusion.ukf.initial import Init, InitialCov
from gt3dkit.fusion.ukf.jointupdate import run_joints
from gt3dkit.fusion.ukf.measurement import Model
from gt3dkit.types import F64


def initial_states(model: Model, cfg: UKFConfig) -> Init:
    lay = model.layout
    x0 = model.x_frame.copy()
    v = model.var_frame.copy()
    v[:, lay.velocity] = cfg.init_vel_sd_mps**2
    if lay.n_joints:
        v[:, lay.joint_velocity] = cfg.init_vel_sd_mps**2
        j = v[:, lay.joints]
        v[:, lay.joints] = np.where(np.isfinite(j), j, cfg.init_canon_sd_m**2)
    v = np.where(np.isfinite(v), v, 1.0)
    c6 = model.cov6_frame
    ok = np.all(np.isfinite(c6), axis=(1, 2))
    dims = np.r_[np.arange(lay.center.start, lay.center.stop),
                 np.arange(lay.log_axes.start, lay.log_axes.stop)]
    return Init(x0, InitialCov(v, c6, ok, dims))


def objects_rows(rows: Rows, hit: np.ndarray) -> np.ndarray:
    """(R,) every row of the objects that have a row in ``hit (R,)``."""
    obj = np.zeros(len(rows.obj_ids), bool)
    obj[rows.row_o[hit]] = True
    return obj[rows.row_o]


def smoothed_weights(model: Model, x_s: F64, cfg: UKFConfig) -> F64:
    """(R, m) weights of every measurement judged by its residual at the smoothed estimate
    ``x_s (R, n)`` in units of its noise (:func:`gt3dkit.fusion.preparation.robust.point_weights`), 1
    outside the robust blocks. The smoothed state rests on many frames, so its own spread
    is left out of the score (a slightly stricter test)."""
    w = np.ones_like(model.z)
    zhat = model.h(x_s[:, None, :])[:, 0, :]
    r = np.where(model.mask & np.isfinite(zhat), model.z - zhat, 0.0)
    e2 = r * r / (model.var * model.test_variance())
    B = len(x_s)
    for sl, d in model.robust_blocks:
        e2b = e2[:, sl].reshape(B, -1, d).sum(axis=2)
        w[:, sl] = np.repeat(point_weights(e2b, d, cfg.robust_config), d, axis=1)
    return np.where(model.mask, w, 1.0)


def rerun_objects(model: Model, init: Init, cfg: UKFConfig, fps: float, run: FilterRun, on: np.ndarray
                  ) -> FilterRun:
    """``run`` with the rows ``on (R,)`` (whole objects) run again: by the frames' filter their
    covariances are written into ``run``'s own (no second array of every row's)."""
    if backend_for(model) == "joints":
        return run.merged(run_joints(model, init, cfg, fps, collect=True, on=on, into=run.P), on)
    return run.merged(run_filter(model, init, cfg, fps, collect=True, on=on), on)


def run_filter(model: Model, init: Init, cfg: UKFConfig, fps: float, collect: bool = False,
               fade: bool = True, on: np.ndarray | None = None,
               noise_rows: NoiseRows | None = None) -> FilterRun:
    """Forward UKF, then (optionally) RTS, by the backend that serves the model
    (:func:`backend_for`): a :class:`gt3dkit.fusion.ukf.filterrun.FilterRun`; with ``collect`` it
    holds the final weights, scores and residuals ``(R, m)``. ``fade`` lets the frame's own
    views weaken a contradicted prediction (the fading rule of :mod:`gt3dkit.fusion.ukf.kalman`); the
    noise search runs without it, so that its likelihood judges the motion model as it is.
    ``on (R,)`` runs the rows of some objects only (whole objects: each object's filter is
    independent of the others); the other rows' outputs are zero and their statistics absent
    (:meth:`FilterRun.merged` combines runs). ``noise_rows`` gives some of ``accel_sd``,
    ``shape_sd``, ``joint_accel_sd`` per row ``(R,)`` instead of ``cfg``'s (the noise search runs
    several values at once)."""
    if cfg.accel_sd is None or cfg.shape_sd is None:
        raise ValueError("run_filter needs numeric accel_sd and shape_sd")
    return BACKENDS[backend_for(model)](model, init, cfg, fps, collect, fade, on, noise_rows)


def backend_for(model: Model) -> str:
    """The filter that runs ``model``: ``"objects"`` (a boxes-only model: every object's rows as
    one compiled chain, objects in parallel, :func:`gt3dkit.fusion.ukf.boxupdate.run_boxes`) or
    ``"joints"`` (a model with joints: every joint of every person as a compiled chain, the
    ellipsoid by the boxes' chains, :func:`gt3dkit.fusion.ukf.jointupdate.run_joints`). The tests hold
    both to a filter over the frame grid (``tests/oracles_frames.py``), which calls the same
    steps."""
    return "joints" if model.layout.n_joints else "objects"


BACKENDS = {"objects": run_boxes, "joints": run_joints}

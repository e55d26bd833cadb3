r"""The reference filter over the frame grid and what only it uses, held here as an oracle: the
package's filters (``gt3dkit.fusion.ukf.boxupdate.run_boxes`` for boxes, ``gt3dkit.fusion.ukf.jointupdate.
run_joints`` for joints) are held to it by the tests; it is run by nothing else.

* :func:`run_frames`: per frame the prediction, fading and linearisation point of its rows as
  one batch, their update (:func:`ukf_update_information`: the sigma-point regression of every
  block, :func:`block_regression`, then the package's compiled update), then RTS backwards;
* :func:`prior_conflict`, :func:`linearisation_point`: the batched fading rule and linearisation
  point of a :class:`gt3dkit.fusion.ukf.measurement.Model`;
* :func:`add_joint_info`: the bones' information added to a batch of rows;
* :func:`predict_linear`, :func:`rts_step`: the batched prediction and RTS step;
* the split into per-joint filters (:func:`split_joints`, :class:`JointSplit`), whose module
  doc follows.

The keypoint filter factorised by joint.

Nothing in a view couples two joints of a person: a joint's
projections depend on its own three coordinates, the motion model moves it by its own
velocity, and no initial covariance ties it to another joint or to the ellipsoid. The
covariance then stays block-diagonal, one (position, velocity) block per joint and one block
for the ellipsoid (centre, velocity, log semi-axes), and the filter over the stacked
``9 + 6J`` state is ``J + 1`` independent filters (exactly, but for when the iterated update
stops: each part on its own, within the update's convergence tolerance). :func:`split_joints` turns a
:class:`gt3dkit.fusion.ukf.measurement.Model` into ``(J + 1) R`` rows of a 15-entry state (the
ellipsoid and one joint: ``StateLayout(1)``), part 0 measured by the boxes, part ``j + 1`` by
joint ``j``'s keypoints; :meth:`JointSplit.merge` puts the results back. Per frame that is
``(J + 1) B`` rows of ``15 x 15`` algebra instead of ``B`` rows of ``(9 + 6J)^2``: for 19
joints, 123-state matrices (one inverse is 1.9 Mflop) become 20 of 15 states (3.4 kflop each).
Bones reach each part as information added after the views (:mod:`gt3dkit.fusion.ukf.bones`), so
the bone pass runs split too.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from gt3dkit.arrays import contiguous
from gt3dkit.fusion.motion import SPACE, StateLayout
from gt3dkit.fusion.preparation.robust import chi2_isf
from gt3dkit.fusion.preparation.rows import Rows
from gt3dkit.fusion.ukf.blockcov import BlockCov
from gt3dkit.fusion.ukf.bones import JointInfo
from gt3dkit.fusion.ukf.boxupdate import run_boxes
from gt3dkit.fusion.ukf.config import UKFConfig
from gt3dkit.fusion.ukf.filterrun import FilterRun
from gt3dkit.fusion.ukf.initial import Init, InitialCov
from gt3dkit.fusion.ukf.jointupdate import run_joints
from gt3dkit.fusion.ukf.kalman import (
    ellipsoid_linearisations,
    fade_factors_of,
    predict_rows,
    rts_rows,
)
from gt3dkit.fusion.ukf.measurement import Model
from gt3dkit.fusion.ukf.sigma import Block, MeasureFn, Robust, SigmaWeights, block_columns, safe_cholesky
from gt3dkit.fusion.ukf.update import Columns, Measured, Regression, pass_rows, row_state, statistics_rows
from gt3dkit.types import F64, I64

#: The state of one part: the ellipsoid entries and one joint with its velocity.
SUB = StateLayout(1)


@dataclass(frozen=True)
class JointSplit:
    """How the rows of a split model map back: ``src (R',)`` the original row, ``part (R',)``
    (0 ellipsoid, ``j + 1`` joint ``j``), ``dims (R', 15)`` the original state entry of every
    sub-state entry, ``owned (R', 15)`` the entries a part estimates (its own), ``cols (R', m')``
    the original measurement column of every sub-column (-1: none)."""

    R: int
    n: int
    m: int
    src: I64
    part: I64
    dims: I64
    owned: np.ndarray
    cols: I64

    @property
    def n_parts(self) -> int:
        """Parts per original row (the ellipsoid and each joint)."""
        return int(self.part.max()) + 1

    def merge(self, run: FilterRun, covariances: bool = True, on: np.ndarray | None = None,
              into: BlockCov | None = None) -> FilterRun:
        """The run of the original rows (states ``(R, n)``, block-diagonal covariances as their
        blocks, :class:`gt3dkit.fusion.ukf.blockcov.BlockCov`: 6 kB a row with 19 joints, the whole
        ``(R, n, n)`` would be 121 kB; per-row statistics summed over the parts, per-entry arrays
        in the original columns) from a run of the split model. ``covariances=False``: ``P`` is
        ``(R, 0, 0)`` (a caller that reads only the statistics, as the noise search). ``on
        (R,)``: the rows that ran (the others' covariances are zero); ``into``: the covariances
        ``P`` is (the rows ``on`` written, the others left as they are)."""
        x, P = run.x, run.P
        xo = np.zeros((self.R, self.n))
        rr = np.broadcast_to(self.src[:, None], self.dims.shape)
        xo[rr[self.owned], self.dims[self.owned]] = x[self.owned]
        Po: BlockCov | F64 = np.zeros((self.R, 0, 0))
        if covariances:
            groups = []
            for own in (self.part == 0, self.part > 0):
                first = np.flatnonzero(own)[0]
                k = np.flatnonzero(self.owned[first])
                blocks = self.part[first:first + self.n_parts][own[first:first + self.n_parts]]
                dims = self.dims[first:first + self.n_parts][own[first:first + self.n_parts]][:, k]
                v = P[np.flatnonzero(own)[:, None, None], k[None, :, None], k[None, None, :]]
                groups.append((dims, v.reshape(self.R, len(blocks), len(k), len(k))))
            ran = np.ones(self.R, bool) if on is None else on
            Po = BlockCov(self.n, groups).rows_that_ran(ran, into)
        ok = self.cols >= 0

        def entries(v: F64 | None) -> F64 | None:
            if v is None:
                return None
            full = np.zeros((self.R, self.m), dtype=v.dtype)
            full[np.broadcast_to(self.src[:, None], ok.shape)[ok], self.cols[ok]] = v[ok]
            return full

        def rows(v: F64) -> F64:
            return np.bincount(self.src, weights=v, minlength=self.R)

        return replace(run, x=xo, P=Po, nis=rows(run.nis), dof=rows(run.dof),
                       loglik_rows=rows(run.loglik_rows), weights=entries(run.weights),
                       score2=entries(run.score2), residual=entries(run.residual),
                       object_frames=run.object_frames * self.R // len(self.src))


def split_joints(model: Model, x0: F64, P0: F64) -> tuple[Model, F64, F64, JointSplit]:
    """The model, initial states ``(R, n)`` and covariances ``(R, n, n)`` as ``J + 1`` parts
    per row (see the module doc). The model's :class:`gt3dkit.fusion.ukf.bones.JointInfo` goes with
    each joint's part."""
    rows, lay = model.rows, model.layout
    R, J, C = len(rows), lay.n_joints, len(model.cams.K)
    parts = J + 1
    src = np.repeat(np.arange(R), parts)  # rows stay ordered by frame, then (object, part)
    part = np.tile(np.arange(parts), R)
    jj = np.maximum(part - 1, 0)
    E = lay.joints.start  # the ellipsoid's entries (centre, velocity, log semi-axes) come first
    dims = np.concatenate([np.broadcast_to(np.arange(E), (len(src), E)),
                           lay.joints.start + 3 * jj[:, None] + np.arange(3),
                           lay.joint_velocity.start + 3 * jj[:, None] + np.arange(3)],
                          axis=1)  # (R', SUB.n), in SUB's order
    owned = np.zeros(dims.shape, bool)
    owned[part == 0, :E] = True
    owned[part > 0, E:] = True
    # measurement columns: [box 4C | this joint's keypoints 2C]
    at = 4 * C if model.use_box else 0
    m_sub = at + 2 * C
    cols = np.full((len(src), m_sub), -1, dtype=np.int64)
    if model.use_box:
        cols[part == 0, :at] = np.arange(at)
    kcols = at + 2 * (np.arange(C)[None, :, None] * J + jj[part > 0][:, None, None]) + np.arange(2)
    cols[part > 0, at:] = kcols.reshape(-1, 2 * C)
    ok = cols >= 0
    cs = np.maximum(cols, 0)
    rs = src[:, None]

    def take(a: F64, fill: float) -> F64:
        return np.where(ok, a[rs, cs], fill)

    def link(other: I64) -> I64:
        o = other[src]
        return np.where(o >= 0, o * parts + part, -1)

    box0 = (part == 0)[:, None, None]
    sub_rows = Rows(frames=rows.frames, obj_ids=np.repeat(rows.obj_ids, parts), row_t=rows.row_t[src],
                    row_o=rows.row_o[src] * parts + part, prev_row=link(rows.prev_row),
                    next_row=link(rows.next_row), t_start=rows.t_start * parts,
                    box_z=np.where(box0, rows.box_z[src], np.nan),
                    box_mask=np.where(box0, rows.box_mask[src], False),
                    kpt_z=rows.kpt_z[src, :, jj][:, :, None], kpt_conf=rows.kpt_conf[src, :, jj][:, :, None],
                    obs_row=rows.obs_row[src], seen_at=rows.seen_at[src])
    var_frame = model.var_frame[rs, dims]
    var_frame[part == 0, E:] = np.inf  # part 0 has no joint of its own
    kcov = None
    if model.kpt_cov_frame is not None:
        kcov = np.where((part > 0)[:, None, None], model.kpt_cov_frame[src, jj], np.inf)[:, None]
    blocks: list[tuple[slice, int]] = []
    if model.robust_blocks:
        if model.use_box:
            blocks.append((slice(0, at), 1))
        blocks.append((slice(at, m_sub), 2))
    sub = replace(model, rows=sub_rows, layout=SUB, z=take(model.z, 0.0),
                  mask=ok & model.mask[rs, cs], var=take(model.var, 1.0),
                  weight0=take(model.weight0, 1.0), robust_blocks=tuple(blocks),
                  x_frame=model.x_frame[rs, dims], var_frame=var_frame,
                  cov6_frame=np.where(box0, model.cov6_frame[src], np.inf),
                  centre_determined=model.centre_determined[src] & (part == 0), kpt_cov_frame=kcov,
                  joint_info=None if model.joint_info is None else model.joint_info.take(src, part - 1))
    sp = JointSplit(R, lay.n, model.z.shape[1], src, part, dims, owned, cols)
    P0_sub = P0.entries(src, dims) if isinstance(P0, InitialCov) else \
        P0[src[:, None, None], dims[:, :, None], dims[:, None, :]]
    return sub, x0[rs, dims], P0_sub, sp


def whole_state_block(n: int, m: int, h: MeasureFn) -> Block:
    """A measurement function ``(B, S, n) -> (B, S, m)`` of the whole state as one block."""
    return Block(np.arange(n)[None], np.arange(m)[None], lambda X: h(X[:, 0])[:, None])



def block_regression(blk: Block, rows: np.ndarray, xj: F64, Pj: F64, meas: Measured, w: SigmaWeights,
                     lin: Regression, repaired: np.ndarray) -> None:
    """Statistical linear regression of one block's columns for the batch rows ``rows`` about
    ``N(xj[rows], Pj[rows])`` (``(B, n)``, ``(B, n, n)``; ``meas``: the batch's ``z, mask, var
    (B, m)``) on each group's marginal's sigma points, into ``lin``'s rows (``(B, ...)``
    arrays, :class:`gt3dkit.fusion.ukf.update.Regression`); each row's factor repairs added to
    ``repaired (B,)``."""
    if blk.regress is not None:
        blk.regress(rows, xj, Pj, meas, w, lin, repaired)
        return
    dims, cols = blk.dims, blk.cols
    G, d = dims.shape
    k = cols.shape[1]
    ws = SigmaWeights(d, w.alpha, w.beta, w.kappa)
    xb = xj[rows][:, dims]  # (B, G, d)
    Pb = Pj[rows][:, dims[:, :, None], dims[:, None, :]]  # (B, G, d, d)
    B = len(rows)
    L, rep = _safe_cholesky_rows(Pb.reshape(B * G, d, d))
    repaired[rows] += rep.reshape(B, G).sum(axis=1)
    offs = (np.sqrt(ws.n + ws.lam) * np.swapaxes(L, -1, -2)).reshape(B, G, d, d)
    Wm, Wc = ws.Wm, ws.Wc
    centre = bool(Wm[0] != 0.0 or Wc[0] != 0.0)  # the cubature rule gives it no weight
    pts = [xb[:, :, None, :]] if centre else []
    X = np.concatenate(pts + [xb[:, :, None, :] + offs, xb[:, :, None, :] - offs], axis=2)
    if not centre:
        Wm, Wc = Wm[1:], Wc[1:]
    mask = meas.mask[rows][:, cols]
    assert blk.h is not None
    Z = blk.h(X, mask) if blk.masked else blk.h(X)  # (B, G, S, k)
    mk = mask & np.all(np.isfinite(Z), axis=2)
    Zm = np.where(mk[:, :, None, :], Z, 0.0)
    zhat = np.einsum("s,bgsk->bgk", Wm, Zm)
    dX = X - xb[:, :, None, :]
    dZ = Zm - zhat[:, :, None, :]
    Pxz = np.swapaxes(dX * Wc[:, None], -1, -2) @ dZ  # (B, G, d, k)
    At = np.linalg.solve(Pb, Pxz)
    var_z = np.einsum("s,bgsk->bgk", Wc, dZ * dZ)
    omega = np.maximum(var_z - np.sum(Pxz * At, axis=2), 0.0)
    c = meas.z[rows][:, cols] - zhat + np.einsum("bgdk,bgd->bgk", At, xb)
    flat = cols.reshape(-1)
    r2 = rows[:, None]
    lin.used[r2, flat] = mk.reshape(B, G * k)
    lin.At[r2, flat, :d] = np.swapaxes(At, 2, 3).reshape(B, G * k, d)
    lin.c[r2, flat] = c.reshape(B, G * k)
    lin.D[r2, flat] = meas.var[rows][:, flat] + omega.reshape(B, G * k)



def _safe_cholesky_rows(P: F64) -> tuple[F64, np.ndarray]:
    """:func:`safe_cholesky` with the repairs per matrix ``(N,)``."""
    L, rep = safe_cholesky(P)
    if not rep:
        return L, np.zeros(len(P), np.int64)
    w = np.linalg.eigvalsh(0.5 * (P + np.swapaxes(P, -1, -2)))
    return L, (w.min(axis=-1) <= 1e-15 * np.maximum(w.max(axis=-1), 1e-300)).astype(np.int64)



def ukf_update_information(
    x: F64, P: F64, meas: Measured, h: MeasureFn | Sequence[Block], w: SigmaWeights, iterations: int = 1,
    lin_point: tuple[F64, F64] | None = None, weight0: F64 | None = None, robust: Robust | None = None,
    columns: Columns | None = None,
) -> tuple[F64, F64, dict[str, Any]]:
    r"""The iterated, optionally robust unscented update of a batch of rows in information form:
    the regression of every block (:func:`block_regression`), then the update of
    :mod:`gt3dkit.fusion.ukf.update` per row (:func:`gt3dkit.fusion.ukf.update.pass_rows`), until every
    row is done.

    Each pass linearises ``h`` by statistical linear regression at ``(x_j, P_j)`` (``A, b`` and
    the diagonal of the linearisation error ``Omega``) and updates the prior in state space,

    .. math::
        P^+ = (P^{-1} + A^\top W D^{-1} A)^{-1},\quad
        x^+ = x + P^+ A^\top W D^{-1} (z - A x - b),\quad D = R + \mathrm{diag}(\Omega),

    which costs ``O(n^3 + m n^2)`` instead of ``O(m^3)``. Keeping only the diagonal of
    ``Omega`` is the one approximation; ``Omega`` vanishes as the posterior tightens. With one
    pass and the prior as linearisation point this is the standard UKF update (the tests hold
    it to filterpy's through a covariance-form oracle).

    Parameters
    ----------
    x, P : (B, n), (B, n, n) the priors
    meas : the batch's measurements ``z``, present entries ``mask`` and noise variances ``var``,
        ``(B, m)`` each
    h : a function ``(B, S, n) -> (B, S, m)`` of the whole state, or a list of :class:`Block`
        (each regressed on its own marginal's sigma points)
    lin_point : ``(x_lin, P_lin)`` where the first pass linearises (default: the prior)
    weight0 : (B, m) the weights the first pass uses (default 1; 0 removes an entry exactly)
    robust : after every pass but the last, the points of ``robust.blocks`` are reweighted by
        their leave-one-out scores against the new posterior (:mod:`gt3dkit.fusion.preparation.robust`)
    columns : the blocks' :class:`gt3dkit.fusion.ukf.update.Columns` (default: made here from
        ``h`` and ``robust``)

    A row stops once a pass's posterior is where it linearised and no weight changes
    (``info["passes_rows"]``): a further pass would repeat it.

    Returns ``x_post, P_post, info``: ``nis``, ``dof``, ``loglik`` (of the last pass with its
    weights: noise ``D / w`` for the kept entries, what the estimate rests on), the same per
    row (``nis_rows``, ``dof_rows``, ``loglik_rows``, ``(B,)``), ``passes``, ``repaired``
    (factors that needed an eigenvalue repair), ``weights (B, m)`` (those the last pass used),
    ``score2 (B, m)`` (each entry's point's squared leave-one-out score at the final posterior)
    and ``residual (B, m)`` (``z - h(x_post)``, linearised).
    """
    z = contiguous(meas.z)
    B, m = z.shape
    n = x.shape[1]
    blocks = [whole_state_block(n, m, h)] if callable(h) else list(h)
    cols = columns if columns is not None else block_columns(blocks, m, robust)
    mask = contiguous(meas.mask, np.bool_)
    meas = Measured(z, mask, contiguous(np.broadcast_to(np.asarray(meas.var, dtype=np.float64),
                                                                  (B, m))))
    xj, Pj = (x, P) if lin_point is None else lin_point
    wt = np.ones((B, m)) if weight0 is None else weight0
    st = row_state(x, P, xj, Pj, wt)
    lin = Regression(np.zeros((B, m), np.bool_), np.zeros((B, m, cols.dims.shape[1])), np.zeros((B, m)),
                     np.ones((B, m)))
    done = np.zeros(B, np.bool_)
    repaired = np.zeros(B, np.int64)
    passes = np.zeros(B, np.int64)
    active = np.arange(B, dtype=np.int64)
    on = bool(np.any(cols.size > 0))
    for it in range(iterations):
        for blk in blocks:
            block_regression(blk, active, st.xj, st.Pj, meas, w, lin, repaired)
        pass_rows(active, it, it == iterations - 1, on, lin, cols, st, done, repaired)
        passes[active] = it + 1
        active = active[~done[active]]
        if not len(active):
            break
    stats = np.empty((B, 3))
    statistics_rows(lin, st, stats)
    quad, dof_b, ll_b = stats[:, 0], stats[:, 1].astype(np.int64), stats[:, 2]
    info: dict[str, Any] = {
        "nis": float(quad.sum()), "dof": int(dof_b.sum()), "loglik": float(ll_b.sum()),
        "nis_rows": quad, "dof_rows": dof_b, "loglik_rows": ll_b, "passes_rows": passes,
        "passes": int(passes.max()) if B else 0, "repaired": int(repaired.sum()),
        "weights": np.where(mask, st.wt, 1.0), "score2": st.scores.score2, "residual": st.scores.resid}
    return st.post.x, st.post.P, info



def predict_linear(x: F64, P: F64, F: F64, Q: F64) -> tuple[F64, F64]:
    """Linear prediction of ``(B, n)``, ``(B, n, n)`` with ``F, Q (B, n, n)`` or ``(n, n)``."""
    c = contiguous
    B, n = x.shape
    x_out, P_out = np.empty((B, n)), np.empty((B, n, n))
    predict_rows(c(x), c(P), c(np.broadcast_to(F, P.shape)), c(np.broadcast_to(Q, P.shape)), x_out, P_out)
    return x_out, P_out



def rts_step(x_f: F64, P_f: F64, x_p_next: F64, P_p_next: F64, x_s_next: F64, P_s_next: F64, F: F64
             ) -> tuple[F64, F64]:
    """:func:`rts_row` of a batch: means ``(B, n)``, covariances ``(B, n, n)``, ``F (B, n, n)`` or
    ``(n, n)``; returns the smoothed ``(B, n)``, ``(B, n, n)``."""
    c = contiguous
    B, n = x_f.shape
    x_out, P_out = np.empty((B, n)), np.empty((B, n, n))
    rts_rows(c(x_f), c(P_f), c(x_p_next), c(P_p_next), c(x_s_next), c(P_s_next),
             c(np.broadcast_to(F, P_f.shape)), x_out, P_out)
    return x_out, P_out



def prior_conflict(model: Model, r: np.ndarray, x: F64, P: F64, tail_p: float = 1e-3) -> F64:
    r"""Per-state-entry fading scales ``(B, n)`` >= 1 for predictions the frame's own views
    contradict.

    The frame's per-frame fits (no prior) are compared with the prediction, block by
    block: the centre where two or more box views determine it, and every joint two views
    triangulate,

    .. math:: d^2 = (x_{fit} - x^-)^\top (P^- + P_{fit})^{-1} (x_{fit} - x^-).

    Beyond the ``1 - tail_p`` quantile of chi-square(3) the motion model has failed for
    that block (a turn at 4 fps, a process noise set far too small): the block's position
    and velocity are scaled by :func:`gt3dkit.fusion.ukf.kalman.fade_factor` (``sqrt(1 + (d^2 -
    limit) / 3)``) in ``P^- <- S P^- S`` (a fading-memory
    filter, per block), so that its views are not rejected as outliers against a
    confident but wrong prediction. Other joints are left alone.
    """
    lay = model.layout
    B = len(r)
    scale = np.ones((B, lay.n))
    lim = chi2_isf(tail_p, SPACE)
    if model.use_box:
        ok = model.centre_determined[r]
        if ok.any():
            e = (model.x_frame[r, lay.center] - x[:, lay.center])[ok]
            S = P[ok][:, lay.center, lay.center] + model.cov6_frame[r[ok], :SPACE, :SPACE]
            f = np.ones(B)
            f[ok] = fade_factors_of(e, S, lim)
            scale[:, lay.center] = f[:, None]
            scale[:, lay.velocity] = f[:, None]
    J = lay.n_joints
    if J and model.kpt_cov_frame is not None:
        C0 = model.kpt_cov_frame[r]  # (B, J, 3, 3)
        ok = np.all(np.isfinite(C0), axis=(2, 3))
        if ok.any():
            idx = lay.joint_dims(np.arange(J))
            Pj = P[:, idx[:, :, None], idx[:, None, :]]  # (B, J, 3, 3)
            e = model.x_frame[r][:, lay.joints].reshape(B, J, SPACE) - x[:, lay.joints].reshape(B, J,
                                                                                               SPACE)
            f = np.ones((B, J))
            f[ok] = fade_factors_of(e[ok], Pj[ok] + C0[ok], lim)
            scale[:, lay.joints] = np.repeat(f, SPACE, axis=1)
            scale[:, lay.joint_velocity] = np.repeat(f, SPACE, axis=1)
    return scale



def linearisation_point(model: Model, r: np.ndarray, x: F64, P: F64) -> tuple[F64 | None, F64 | None]:
    """Where the first update pass linearises for rows ``r`` with priors ``x, P``.

    The prior, except where the row's own views say more than the prior does: an
    object after a gap, re-appearing, at its first frame, or a joint the filter has
    lost. There the ellipsoid (centre, axes) and the joints are taken from the per-frame
    fits with their covariance, so that the sigma points stay where the views put the
    object instead of far out along a weak prediction (where some of them fall behind
    a camera and the views would be ignored).
    """
    lay = model.layout
    B = len(r)
    xl, Pl = x, P
    changed = False
    if model.use_box:
        xl, Pl, moved = np.empty_like(x), np.empty_like(P), np.zeros(B, np.bool_)
        ellipsoid_linearisations(contiguous(x), contiguous(P), contiguous(model.x_frame[r]),
                                 contiguous(model.cov6_frame[r]), contiguous(model.frame_centre_trace[r]),
                                 lay.ellipsoid_dims, lay.index, xl, Pl, moved)
        changed = bool(moved.any())
        if not changed:
            xl, Pl = x, P
    J = lay.n_joints
    if J:
        sl = lay.joints
        vj = np.diagonal(P, axis1=1, axis2=2)[:, sl].reshape(B, J, SPACE).sum(axis=2)
        vf = model.var_frame[r][:, sl].reshape(B, J, SPACE).sum(axis=2)
        lost = np.isfinite(vf) & (vj > vf)
        if lost.any():
            if not changed:
                xl, Pl = x.copy(), P.copy()
            bb, jj = np.nonzero(lost)
            dims = lay.joint_dims(jj)  # (L, 3)
            xl[bb[:, None], dims] = model.x_frame[r[bb][:, None], dims]
            for k in range(SPACE):  # decorrelate the replaced joints
                Pl[bb, dims[:, k], :] = 0.0
                Pl[bb, :, dims[:, k]] = 0.0
            vals = model.var_frame[r[bb][:, None], dims]
            Pl[bb[:, None], dims, dims] = vals
            changed = True
    return (xl, Pl) if changed else (None, None)



def add_joint_info(x: F64, P: F64, ji: JointInfo, dims: I64) -> tuple[F64, F64]:
    r"""States ``x (B, n)``, ``P (B, n, n)`` with the information ``ji`` (``(B, J, ...)``) on
    each joint's entries ``dims (J, 3)`` added: ``P^{+-1} = P^{-1} + E^\top \Lambda E``,
    ``P^{+-1} x^+ = P^{-1} x + E^\top \eta``, joint by joint (information adds: the order does
    not matter), without inverting ``P``:

    .. math::
        P^+ = P - U M U^\top,\quad M = \Lambda (I + C \Lambda)^{-1},\quad
        x^+ = x + P^+ E^\top (\eta - \Lambda E x),

    ``U = P E^\top``, ``C = E P E^\top``. Rows without any information are returned as they are."""
    has = np.any(ji.info != 0.0, axis=(1, 2, 3))
    if not has.any():
        return x, P
    x, P = x.copy(), P.copy()
    at = np.flatnonzero(has)
    for j in range(dims.shape[0]):
        lam, eta = ji.info[at, j], ji.eta[at, j]
        on = np.any(lam != 0.0, axis=(1, 2))
        if not on.any():
            continue
        b, lam, eta = at[on], lam[on], eta[on]
        e = dims[j]
        U = P[b][:, :, e]  # (N, n, 3)
        C = U[:, e, :]
        # M^T = (I + Lam C)^-1 Lam (Lam, C symmetric); M is symmetric but for rounding
        M = np.swapaxes(np.linalg.solve(np.eye(3) + lam @ C, lam), -1, -2)
        M = 0.5 * (M + np.swapaxes(M, -1, -2))
        Pn = P[b] - U @ M @ np.swapaxes(U, -1, -2)
        Pn = 0.5 * (Pn + np.swapaxes(Pn, -1, -2))
        innov = eta - np.einsum("nab,nb->na", lam, x[b][:, e])
        x[b] = x[b] + np.einsum("nsa,na->ns", Pn[:, :, e], innov)
        P[b] = Pn
    return x, P



def run_frames(model: Model, init: Init, cfg: UKFConfig, fps: float, collect: bool = False,
               fade: bool = True, on: np.ndarray | None = None,
               noise_rows: dict[str, F64] | None = None, split: bool = True,
               covariances: bool = True) -> FilterRun:
    """The filter over the frame grid (arguments and outputs of :func:`run_filter`): per frame
    the prediction, fading and linearisation point of its rows as one batch, their update
    (:func:`gt3dkit.fusion.ukf.sigma.ukf_update_information`), then RTS backwards. ``split``: run
    the joints as separate filters (:mod:`gt3dkit.fusion.split`; the same result,
    faster); False runs the whole state (the reference the tests hold it to). ``covariances=False``:
    a split run's ``P`` is not put back together (``(R, 0, 0)``: for callers that read the
    statistics only)."""
    if split and model.layout.n_joints > 1:
        # the joints are independent filters, run as one batch of small ones
        sub, x0, P0, sp = split_joints(model, init.x0, init.P0)
        return sp.merge(run_frames(sub, Init(x0, P0), cfg, fps, collect, fade,
                                   None if on is None else on[sp.src],
                                   {k: v[sp.src] for k, v in (noise_rows or {}).items()}), covariances, on)
    rows, cams, layout = model.rows, model.cams, model.layout
    n, R = layout.n, len(rows)
    w = SigmaWeights(n, cfg.alpha, cfg.beta, cfg.kappa)
    robust = cfg.robust_config if cfg.robust else None
    # per row: the prediction's mean, the filtered mean and covariance, and the scales that
    # made the prediction's covariance (``fade S (F P_f F^T + Q') S``, ``Q' = q Q q``): the RTS
    # makes it again from the previous row's filtered one instead of holding one more ``(n, n)``
    # per row (121 kB with 19 joints)
    x_p = np.zeros((R, n))
    x_f = np.zeros((R, n))
    P_f = np.zeros((R, n, n))
    fade_s = np.ones((R, n))
    q_s = np.ones((R, n))
    frame_s = rows.frames / fps
    m = model.z.shape[1]
    out = {k: np.zeros((R, m)) for k in ("weights", "score2", "residual")} if collect else {}

    per = noise_rows or {}

    cache: dict[tuple[float, ...], tuple[F64, F64]] = {}

    def transition(dt: F64, r: np.ndarray) -> tuple[F64, F64]:
        """``F, Q (B, n, n)`` of rows ``r``, each distinct (time step, noise) computed once per
        run (a frame's rows mostly share one: then read-only broadcast views)."""
        dt = np.asarray(dt, dtype=np.float64).reshape(-1)
        names = ("accel_sd", "shape_sd", "joint_accel_sd", "position_sd")
        vals = [per[k][r] if k in per else getattr(cfg, k) for k in names]
        cols = [dt] + [np.broadcast_to(np.asarray(-1.0 if v is None else v, dtype=np.float64), dt.shape)
                       for v in vals]  # -1: not set (noise is >= 0; NaN would never compare equal)
        keys = np.stack(cols, axis=1)
        uniq, inv = (keys[:1], np.zeros(len(dt), np.int64)) if (keys == keys[0]).all() else \
            np.unique(keys, axis=0, return_inverse=True)
        FQ = []
        for key in map(tuple, uniq.tolist()):
            if key not in cache:
                q = {k: (None if v == -1.0 else v) for k, v in zip(names, key[1:], strict=True)}
                q["position_sd"] = q["position_sd"] or 0.0
                F1, Q1 = layout.transition(np.array(key[:1]), **q, up=cams.up,
                                           vertical_ratio=cfg.vertical_ratio)
                cache[key] = F1[0], Q1[0]
            FQ.append(cache[key])
        if len(FQ) == 1:
            shape = (len(dt),) + FQ[0][0].shape
            return np.broadcast_to(FQ[0][0], shape), np.broadcast_to(FQ[0][1], shape)
        F = np.stack([f for f, _ in FQ])
        Q = np.stack([q for _, q in FQ])
        return F[inv.reshape(-1)], Q[inv.reshape(-1)]

    measured = model.mask.any(axis=1)

    def predicted_cov(r: np.ndarray, nr: np.ndarray) -> F64:
        """The prediction covariances ``(B, n, n)`` of rows ``nr`` made again from the filtered
        ones of their previous rows ``r``, as the forward pass made them (the same bits)."""
        F, Q = transition(frame_s[rows.row_t[nr]] - frame_s[rows.row_t[r]], nr)
        qs = q_s[nr]
        _, P = predict_linear(x_f[r], P_f[r], F, qs[:, :, None] * Q * qs[:, None, :])
        fs = fade_s[nr]
        return fs[:, :, None] * P * fs[:, None, :]

    def spread_over_gap(row: int, scale: F64) -> F64 | None:
        """Where row ``row``'s prediction, contradicted by the frame's own views (the fading
        scales ``scale (n,)``), follows rows without measurements: the process noise of every
        step since the last measured row as ``S Q S`` and those rows predicted again (as
        :func:`gt3dkit.fusion.ukf.filterloop.spread_over_gap`); returns the row's new prediction
        covariance ``(n, n)``. None where no measured row precedes the gap."""
        gap = []
        k = int(rows.prev_row[row])
        while k >= 0 and (on is None or on[k]) and not measured[k]:
            gap.append(k)
            k = int(rows.prev_row[k])
        if k < 0 or (on is not None and not on[k]) or not gap:
            return None
        prev = k
        for cur in gap[::-1] + [row]:
            F, Q = transition(frame_s[rows.row_t[cur]] - frame_s[rows.row_t[prev]], np.array([cur]))
            x, P = predict_linear(x_f[prev][None], P_f[prev][None], F, scale[:, None] * Q * scale[None, :])
            x_p[cur] = x[0]
            q_s[cur], fade_s[cur] = scale, 1.0
            if cur != row:
                x_f[cur], P_f[cur] = x[0], P[0]
            prev = cur
        return P[0]

    blocks = model.blocks()
    columns = model.columns(robust)
    joint_dims = layout.joint_dims(np.arange(layout.n_joints))
    per_row = {k: np.zeros(R) for k in ("nis_rows", "dof_rows", "loglik_rows")}
    repaired = 0
    faded = 0
    passes = np.zeros(R)
    for t in range(len(rows.frames)):
        r = np.arange(rows.t_start[t], rows.t_start[t + 1])
        if on is not None:
            r = r[on[r]]
        if len(r) == 0:
            continue
        prev = rows.prev_row[r]
        if on is not None:  # a row whose predecessor is not run starts afresh
            prev = np.where((prev >= 0) & on[np.maximum(prev, 0)], prev, -1)
        new = prev < 0
        P_p = np.empty((len(r), n, n))  # this frame's rows' predictions
        if new.any():
            rn = r[new]
            x_p[rn] = init.x0[rn]
            P_p[new] = init.P0[rn]
        if (~new).any():
            old = np.flatnonzero(~new)
            ro, po = r[old], prev[old]
            F, Q = transition(frame_s[t] - frame_s[rows.row_t[po]], ro)
            x_p[ro], P_p[old] = predict_linear(x_f[po], P_f[po], F, Q)
            if fade:
                sc = prior_conflict(model, ro, x_p[ro], P_p[old])
                hit = np.any(sc > 1, axis=1)
                gap = []
                for g in np.flatnonzero(hit & ~measured[po]):
                    spread = spread_over_gap(int(ro[g]), sc[g])
                    if spread is not None:
                        P_p[old[g]] = spread
                        gap.append(g)
                if gap:  # what the spread noise does not explain fades the prediction as before
                    sc[gap] = prior_conflict(model, ro[gap], x_p[ro[gap]], P_p[old[gap]])
                if hit.any():
                    P_p[old[hit]] = sc[hit, :, None] * P_p[old[hit]] * sc[hit, None, :]
                    fade_s[ro[hit]] = sc[hit]
                    faded += int(hit.sum())
        xl, Pl = linearisation_point(model, r, x_p[r], P_p)
        x_f[r], P_f[r], inf = ukf_update_information(
            x_p[r], P_p, Measured(model.z[r], model.mask[r], model.var[r]), blocks, w, cfg.iterations,
            None if xl is None or Pl is None else (xl, Pl), weight0=model.weight0[r], columns=columns)
        if model.joint_info is not None:
            x_f[r], P_f[r] = add_joint_info(x_f[r], P_f[r], model.joint_info.rows(r), joint_dims)
        repaired += int(inf["repaired"])
        passes[r] = inf["passes_rows"]
        for k in per_row:
            per_row[k][r] = inf[k]
        for k in out:
            out[k][r] = inf[k]
    x_s, P_s = x_f, P_f  # smoothed in place, backwards (a row's filtered values are read first)
    if cfg.smooth:
        for t in range(len(rows.frames) - 2, -1, -1):
            r = np.arange(rows.t_start[t], rows.t_start[t + 1])
            nxt = rows.next_row[r]
            r = r[(nxt >= 0) & (True if on is None else on[r] & on[np.maximum(nxt, 0)])]
            if len(r) == 0:
                continue
            nr = rows.next_row[r]
            F, _ = transition(frame_s[rows.row_t[nr]] - frame_s[t], r)
            P_p = predicted_cov(r, nr)  # before row r's filtered covariance is smoothed in place
            x_s[r], P_s[r] = rts_step(x_f[r], P_f[r], x_p[nr], P_p, x_s[nr], P_s[nr], F)
    ran = passes > 0
    return FilterRun(x_s, P_s, per_row["nis_rows"], per_row["dof_rows"], per_row["loglik_rows"],
                     out.get("weights"), out.get("score2"), out.get("residual"), pd_repairs=repaired,
                     predictions_faded=faded, object_frames=R if on is None else int(on.sum()),
                     update_form="information, iterated and reweighted",
                     update_passes_mean=float(passes[ran].mean()) if ran.any() else 0.0)



#: The filters by loop order: the package's two and this reference.
BACKENDS = {"objects": run_boxes, "frames": run_frames, "joints": run_joints}

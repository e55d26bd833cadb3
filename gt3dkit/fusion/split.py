r"""The keypoint filter factorised by joint.

Nothing in a view couples two joints of a person: a joint's
projections depend on its own three coordinates, the motion model moves it by its own
velocity, and no initial covariance ties it to another joint or to the ellipsoid. The
covariance then stays block-diagonal, one (position, velocity) block per joint and one block
for the ellipsoid (centre, velocity, log semi-axes), and the filter over the stacked
``9 + 6J`` state is ``J + 1`` independent filters (exactly, but for when the iterated update
stops: each part on its own, within the update's convergence tolerance). :func:`split_joints` turns a
:class:`gt3dkit.fusion.measurement.Model` into ``(J + 1) R`` rows of a 15-entry state (the
ellipsoid and one joint: ``StateLayout(1)``), part 0 measured by the boxes, part ``j + 1`` by
joint ``j``'s keypoints; :meth:`JointSplit.merge` puts the results back. Per frame that is
``(J + 1) B`` rows of ``15 x 15`` algebra instead of ``B`` rows of ``(9 + 6J)^2``: for 19
joints, 123-state matrices (one inverse is 1.9 Mflop) become 20 of 15 states (3.4 kflop each).
Bones reach each part as information added after the views (:mod:`gt3dkit.fusion.bones`), so
the bone pass runs split too.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from gt3dkit.fusion.blockcov import BlockCov
from gt3dkit.fusion.filterrun import FilterRun
from gt3dkit.fusion.initial import InitialCov
from gt3dkit.fusion.measurement import Model
from gt3dkit.fusion.motion import StateLayout
from gt3dkit.fusion.rows import Rows
from gt3dkit.types import F64, I64

#: The state of one part: the ellipsoid entries and one joint with its velocity.
SUB = StateLayout(1)


def split_entries(n_joints: int) -> int:
    """Covariance entries per original row once split (``J + 1`` parts of ``SUB.n`` states)."""
    return (n_joints + 1) * SUB.n**2


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
        blocks, :class:`gt3dkit.fusion.blockcov.BlockCov`: 6 kB a row with 19 joints, the whole
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
    per row (see the module doc). The model's :class:`gt3dkit.fusion.bones.JointInfo` goes with
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
                    obs_row=rows.obs_row[src])
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

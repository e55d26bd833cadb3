r"""The process noise, found from the data: where a change to how the noise is chosen goes.

* :func:`moment_process_noise`: moment estimates from the per-frame fits alone (second
  differences of positions, first differences of log semi-axes; the motion model's moments,
  :mod:`gt3dkit.fusion.motion`);
* :func:`select_noise`: maximum likelihood of the UKF's forward pass (prediction-error
  decomposition), a bounded 1-D search on log scale per value (:func:`maximise_log`), after a
  provisional robust pass at the moment estimates fixes every measurement's weight; boxes alone
  price each value as a linear filter with the boxes' regression fixed per row
  (:class:`LinearisedSearch`); on at most :data:`SEARCH_OBJECT_FRAMES` object-frames
  (:func:`search_rows`);
* :func:`noise_by_likelihood`: the same for a preparation (what the GTSAM
  smoother's graph is tuned by too).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from functools import partial
from typing import Any

import numpy as np

from gt3dkit.arrays import contiguous
from gt3dkit.fusion.motion import lag_two_excess_var, second_difference_var, walk_var
from gt3dkit.fusion.preparation.prepare import Prepared
from gt3dkit.fusion.preparation.robust import chi2_median
from gt3dkit.fusion.preparation.rows import Rows, replicate_rows
from gt3dkit.fusion.ukf.boxupdate import (
    Start,
    applies_to_model,
    box_regressions,
    linear_forward,
    measured,
    motion_of,
    object_chains,
    regression_rows,
)
from gt3dkit.fusion.ukf.config import UKFConfig
from gt3dkit.fusion.ukf.filtering import backend_for, initial_states, run_filter, smoothed_weights
from gt3dkit.fusion.ukf.initial import Init, rows_of
from gt3dkit.fusion.ukf.jointupdate import run_joints
from gt3dkit.fusion.ukf.measurement import Model
from gt3dkit.threads import run_split
from gt3dkit.types import F64, I64, JsonDict

#: The provisional robust pass that fixes the noise search's weights runs at this multiple of
#: the moment estimates of the process noise.
PROVISIONAL_LOOSENESS = 3.0
#: ... and a shape noise of at least this (the moment estimate of a shape that the per-frame
#: noise hides is its floor, which would hold every box to a rigid shape).
PROVISIONAL_MIN_SHAPE_SD = 0.05
#: The noise search (and its provisional pass) runs on whole objects up to this many
#: object-frames: the likelihood of two or three noise levels needs no more.
SEARCH_OBJECT_FRAMES = 2500
#: Covariance bytes the values one pass of the noise search runs at once may hold (estimated).
SEARCH_PASS_BYTES = 1e9
#: Rounds of coordinate ascent between the centre's acceleration and position noise at most.
ASCENT_ROUNDS = 3
#: The fields :func:`select_noise` finds (the others are the caller's).
NOISE_FIELDS = ("accel_sd", "shape_sd", "joint_accel_sd", "position_sd")


@dataclass(frozen=True)
class ProcessNoise:
    accel_sd: float
    shape_sd: float
    joint_accel_sd: float
    source: str

    def as_dict(self) -> dict[str, float]:
        return {"accel_sd": self.accel_sd, "shape_sd": self.shape_sd,
                "joint_accel_sd": self.joint_accel_sd}


def _moment_q2(d2: F64, noise_var: F64, unit_var: F64, floor: float) -> float:
    r"""``q^2`` with ``d^2 ~ (q^2 u + n) chi^2_1`` from samples ``d2, noise_var n, unit_var u``:
    the value that puts the median of ``d^2 / (q^2 u + n)`` at the median of chi-square(1)
    (bisection on ``log q^2``), so that gross jumps (a swapped identity) do not count;
    ``floor`` when the noise explains it all. The median of a heavy-tailed motion (real
    joints jitter) is below what its mean would say: this is the process noise of the
    typical frame, which smooths more."""
    ok = np.isfinite(d2) & np.isfinite(noise_var) & (unit_var > 0)
    d2, nv, u = d2[ok], noise_var[ok], unit_var[ok]
    if d2.size < 3:
        return float("nan")
    target = chi2_median(1)

    def med(q2: float) -> float:
        return float(np.median(d2 / (q2 * u + nv)))

    lo, hi = np.log(floor), np.log(max(float(np.max(d2 / u)), floor) * 10)
    if med(float(np.exp(lo))) > target:
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if med(float(np.exp(mid))) > target:
                lo = mid
            else:
                hi = mid
    return max(float(np.exp(0.5 * (lo + hi))), floor)


def _shape_sd(la: F64, lv: F64, prev_row: I64, t_s: F64) -> float:
    """The log semi-axes' random walk from the first differences of the per-frame log semi-axes
    ``la (R, 3)`` (variances ``lv``) between each row and its object's previous row."""
    p = np.flatnonzero(prev_row >= 0)
    dtp = t_s[p] - t_s[prev_row[p]]
    d2 = ((la[p] - la[prev_row[p]]) ** 2).reshape(-1)
    nv = (lv[p] + lv[prev_row[p]]).reshape(-1)
    u = np.repeat(walk_var(dtp), 3)
    s2 = _moment_q2(d2, nv, u, 1e-10)
    return float(np.clip(np.sqrt(s2), 1e-5, 0.3)) if np.isfinite(s2) else 0.003


def moment_process_noise(pre: Prepared, x: F64, var: F64, fps: float,
                         accel_sd: float | None = None, shape_sd: float | None = None,
                         joint_accel_sd: float | None = None) -> ProcessNoise:
    r"""Process noise from the per-frame fits alone (independent of the UKF's likelihood).

    For a constant-velocity model under white acceleration ``q``, the second difference of
    positions three equally spaced frames apart has variance ``(2/3) q^2 dt^3`` plus the
    per-frame fits' own variance ``v_{k-1} + 4 v_k + v_{k+1}``; the first difference of
    the log semi-axes has ``s^2 dt + v_k + v_{k+1}``. ``q^2`` and ``s^2`` are the moment
    estimates over all objects (centre: horizontal axes; joints: all), with gross jumps
    trimmed. Values given are kept. ``x, var`` are :meth:`Prepared.frame_state`'s.
    """
    rows, lay = pre.rows, pre.layout
    t_s = rows.frames[rows.row_t] / fps
    a, b = rows.prev_row, rows.next_row
    r = np.flatnonzero((a >= 0) & (b >= 0))
    dt1 = t_s[r] - t_s[a[r]]
    dt2 = t_s[b[r]] - t_s[r]
    even = np.abs(dt1 - dt2) < 1e-9 * np.maximum(dt1, 1e-9)
    r, dt = r[even], dt1[even]
    src = []

    def second(block: slice, dims: np.ndarray) -> tuple[F64, F64, F64]:
        xs = x[:, block][:, dims]
        vs = var[:, block][:, dims]
        d = xs[b[r]] - 2 * xs[r] + xs[a[r]]
        nv = vs[b[r]] + 4 * vs[r] + vs[a[r]]
        u = np.broadcast_to(second_difference_var(dt)[:, None], d.shape)
        return (d**2).reshape(-1), nv.reshape(-1), u.reshape(-1)

    # five equally spaced frames: second differences at lags 1 and 2 (for the lag test)
    aa = np.where(a >= 0, a[np.maximum(a, 0)], -1)
    bb = np.where(b >= 0, b[np.maximum(b, 0)], -1)
    r5 = r[(aa[r] >= 0) & (bb[r] >= 0)]
    if r5.size:
        e1 = t_s[r5] - t_s[aa[r5]]
        e2 = t_s[bb[r5]] - t_s[r5]
        d1 = t_s[r5] - t_s[a[r5]]
        r5 = r5[(np.abs(e1 - e2) < 1e-9 * e1) & (np.abs(e1 - 2 * d1) < 1e-9 * e1)]

    def lagged(block: slice, dims: np.ndarray) -> float:
        r"""``q^2`` from the robust variances of second differences at lags 1 and 2,
        ``V_2 - V_1 = 7 (2/3) q^2 dt^3``: the per-frame fits' own noise (white in time) is
        the same ``6 v`` in both and cancels, however wrong their covariances are."""
        if r5.size < 10:
            return float("nan")
        xs = x[:, block][:, dims]
        dt1 = t_s[r5] - t_s[a[r5]]
        g1 = xs[b[r5]] - 2 * xs[r5] + xs[a[r5]]
        g2 = xs[bb[r5]] - 2 * xs[r5] + xs[aa[r5]]
        med = 0.4549364  # median of chi-square(1)
        s1, s2 = g1**2 / dt1[:, None] ** 3, g2**2 / dt1[:, None] ** 3

        def mean_var(v: F64) -> float:
            # a mean (heavy tails count: real motion turns, real joints jitter), without only
            # the gross jumps (beyond 24x the median's scale: the chi-square 1e-6 tail)
            scale = np.median(v) / med
            return float(np.mean(v[v < 23.9 * scale])) if scale > 0 else float(np.mean(v))

        return float((mean_var(s2) - mean_var(s1)) / lag_two_excess_var())

    def white_accel(block: slice, dims: np.ndarray, lo: float, default: float) -> float:
        """The lag test's ``q``, else the second differences' (clipped to ``[lo, 100]``)."""
        q2 = lagged(block, dims)
        if not (np.isfinite(q2) and q2 > 0):
            q2 = _moment_q2(*second(block, dims), 1e-4)
        return float(np.clip(np.sqrt(q2), lo, 100.0)) if np.isfinite(q2) else default

    accel, shape, joint = accel_sd, shape_sd, joint_accel_sd
    if pre.use_box and accel is None:
        accel = white_accel(lay.center, np.flatnonzero(np.abs(pre.cams.up) < 0.9)[:2], 0.01, 0.5)
        src.append("accel_sd: second differences of the per-frame centres")
    if pre.use_box and shape is None:
        shape = _shape_sd(x[:, lay.log_axes], var[:, lay.log_axes], a, t_s)
        src.append("shape_sd: first differences of the per-frame log semi-axes")
    if pre.use_kpt and joint is None:
        joint = white_accel(lay.joints, np.arange(3 * lay.n_joints), 0.03, 1.0)
        src.append("joint_accel_sd: second differences of the per-frame joints")
    return ProcessNoise(float(accel or joint or 0.5), float(shape or 0.003), float(joint or 1.0),
                        "; ".join(src) or "given")


class LinearisedSearch:
    """The likelihood of the box forward pass at many process-noise values, each the price of a
    linear Kalman filter: the boxes are regressed (:func:`box_regression`) once per row, about a
    smoothed estimate ``N(x_lin, P_lin)`` of the rows ``on`` (posterior linearisation:
    García-Fernández, Svensson & Särkkä, "Iterated posterior linearization smoother", IEEE TAC
    62, 2017), and every noise value reuses that regression. The full pass re-linearises at each
    prediction (:func:`forward`); for boxes, whose tangent box bends little over a prediction's
    spread, the two likelihoods' maxima are close (the tests compare the noise values found)."""

    def __init__(self, model: Model, init: Init, cfg: UKFConfig, fps: float, x_lin: F64, P_lin: F64,
                 weights: F64, on: np.ndarray | None) -> None:
        R = len(model.rows)
        m = model.z.shape[1]
        box = model.box_measurement(cfg.alpha, cfg.beta, cfg.kappa, None)
        self.chains, first, _ = object_chains(model, fps, on)
        self.lins = regression_rows(R, m, box.cols.dims.shape[1])
        box_regressions(np.flatnonzero(self.chains.run).astype(np.int64), contiguous(x_lin),
                        contiguous(P_lin),
                        measured(model.z, model.mask, model.var), box.sigma, box.rig, box.at, self.lins,
                        np.zeros(R, np.int64))
        self.first = first[first >= 0]
        self.start = Start(contiguous(init.x0), contiguous(init.P0))
        self.w0 = contiguous(np.broadcast_to(weights, (R, m)))
        self.model, self.cfg, self.cols = model, cfg, box.cols

    def logliks(self, settings: list[dict[str, float | None]]) -> list[float]:
        """The forward pass's log-likelihood at each setting (process-noise values by name, the
        others ``cfg``'s; the settings split over threads)."""
        out = [0.0] * len(settings)

        def part(a: int, b: int) -> None:
            for i in range(a, b):
                motion = motion_of(self.model, self.cfg, settings[i])
                out[i] = linear_forward(self.first, self.chains, self.start, motion, self.lins, self.w0,
                                        self.cols)

        run_split(part, len(out))
        return out


def maximise_log(f: Callable[[list[float]], list[float]], lo: float, hi: float, n_scan: int, rounds: int = 2
                 ) -> tuple[float, dict[float, float]]:
    """Maximiser of a smooth ``f`` over ``[lo, hi]`` on log scale, evaluated in batches:
    ``f(values) -> logliks`` takes a list. A log-spaced scan of ``n_scan`` values, then
    ``rounds`` of bisection (the log-midpoints to the best value's neighbours, two values per
    batch; the last batch adds the vertex of the parabola in ``log q`` through the best three).
    Returns the best value evaluated and every evaluation ``{value: f}``."""
    seen: dict[float, float] = {}

    def evaluate(values: list[float]) -> None:
        new = [v for v in values if v not in seen]
        if new:
            for v, ll in zip(new, f(new), strict=True):
                seen[v] = float(ll) if np.isfinite(ll) else -np.inf

    def vertex() -> list[float]:
        """The vertex of the parabola in log q through the best value and its neighbours."""
        vs = sorted(seen)
        ll = np.array([seen[v] for v in vs])
        k = int(np.argmax(ll))
        if k == 0 or k == len(vs) - 1 or not np.all(np.isfinite(ll[k - 1:k + 2])):
            return []
        u = np.log(vs[k - 1:k + 2])
        c2, c1, _ = np.polyfit(u, ll[k - 1:k + 2], 2)
        return [float(np.exp(np.clip(-c1 / (2 * c2), u[0], u[2])))] if c2 < 0 else []

    evaluate([float(v) for v in np.geomspace(lo, hi, n_scan)])
    for r in range(rounds):
        vs = sorted(seen)
        k = int(np.argmax([seen[v] for v in vs]))
        cand = [float(np.sqrt(vs[k] * vs[j])) for j in (k - 1, k + 1) if 0 <= j < len(vs)]
        evaluate(cand + (vertex() if r == rounds - 1 else []))
    best = max(seen, key=lambda v: seen[v])
    return best, seen


def _provisional(model: Model, init: Init, cfg: UKFConfig, pre: Prepared, fps: float,
                 curves: JsonDict
                 ) -> tuple[UKFConfig, F64, np.ndarray | None, LinearisedSearch | None]:
    """:func:`select_noise`'s start: the provisional values (the moment estimates, loosened), the
    measurements' weights a robust provisional pass at them gives, the rows the search runs on
    (None: all) and, for boxes alone, the linearised search about that pass; what it did is
    added to ``curves``."""
    use_box, use_kpt = pre.use_box, pre.use_kpt
    x_f, v_f, _ = pre.frame_state()
    prov = moment_process_noise(pre, x_f, v_f, fps, cfg.accel_sd, cfg.shape_sd,
                                cfg.joint_accel_sd)
    # looser than the moment estimates: the provisional pass is to catch what the other
    # views contradict, not to hold the data to a prior that may be too tight
    loose = PROVISIONAL_LOOSENESS
    start = replace(cfg, accel_sd=cfg.accel_sd or loose * prov.accel_sd,
                    shape_sd=cfg.shape_sd or max(loose * prov.shape_sd, PROVISIONAL_MIN_SHAPE_SD),
                    joint_accel_sd=cfg.joint_accel_sd or loose * prov.joint_accel_sd)
    weights = model.weight0
    on = search_rows(model.rows, SEARCH_OBJECT_FRAMES)
    if on is not None:
        curves["subsample"] = {
            "objects": int(len(np.unique(model.rows.row_o[on]))), "object_frames": int(on.sum()),
            "note": f"the search runs on whole objects drawn at random (seed 0) up to "
                    f"{SEARCH_OBJECT_FRAMES} object-frames: two noise levels need no more"}
    searching = (cfg.accel_sd is None or cfg.shape_sd is None or (use_kpt and cfg.joint_accel_sd is None))
    linear = searching and cfg.search_linearised and use_box and not use_kpt
    if linear:  # boxes only
        linear = applies_to_model(model)
    if searching and (cfg.robust or linear):
        # every point judged against the provisional *smoothed* estimate, as the second pass
        # judges them: a bad view in an object's first frames, which a forward pass cannot
        # tell yet, would otherwise bend the motion model's likelihood
        # the provisional pass's covariances are read by the linearised box search only
        prov_runner = partial(run_joints, covariances=False) if not linear and \
            backend_for(model) == "joints" else run_filter
        prov_run = prov_runner(model, init, start, fps, on=on)
        x_prov, P_prov = prov_run.x, prov_run.P
        if cfg.robust:
            weights = smoothed_weights(model, x_prov, start)
        curves["provisional"] = {**prov.as_dict(), "source": prov.source,
                                 "use": ("a robust pass at these values, smoothed, fixes the weights"
                                         if cfg.robust else "a pass at these values, smoothed")
                                 + (" and the boxes' linearisation" if linear else "")}
    lin = LinearisedSearch(model, init, start, fps, x_prov, np.asarray(P_prov), weights, on) \
        if linear else None  # (a boxes-only run's own array)
    return start, weights, on, lin


def select_noise(model: Model, init: Init, cfg: UKFConfig, pre: Prepared, fps: float
                 ) -> tuple[UKFConfig, JsonDict]:
    """Process noise by maximum likelihood of the forward pass (no smoothing, no bones).

    The likelihood must not be bent by outliers, and a single pass cannot reweight: so a
    first robust pass (forward and RTS), at provisional values (the moment estimates from the
    per-frame fits, :func:`gt3dkit.fusion.ukf.noise.moment_process_noise`), fixes every
    measurement's weight by its residual at that smoothed estimate, and the search's single
    passes use those weights. The search runs on at most ``SEARCH_OBJECT_FRAMES`` object-frames
    (:func:`search_rows`). Values set in
    ``cfg`` are kept; the others are found in turn (``accel_sd``, then ``shape_sd`` with boxes,
    then ``joint_accel_sd`` with keypoints) by :func:`maximise_log`. Returns the tuned config
    and, per searched parameter, the likelihood curve (``value, loglik``, sorted).
    """
    curves: JsonDict = {}
    use_box, use_kpt = pre.use_box, pre.use_kpt
    start, weights, on, lin = _provisional(model, init, cfg, pre, fps, curves)
    search_model = replace(model, weight0=weights)  # one pass each: no reweighting
    sel = np.flatnonzero(on) if on is not None else np.arange(len(model.rows))

    # several values in one pass (copies of the objects), as far as SEARCH_PASS_BYTES of the
    # whole state's covariances would allow. With joints their separate small filters hold
    # about a third of that, and only their likelihoods are read: the whole state's covariances
    # are not put back together (``covariances=False``), so the search stays well
    # inside the budget
    per_pass = max(1, int(SEARCH_PASS_BYTES // (6 * 8 * model.layout.n ** 2 * max(len(sel), 1))))
    runner = run_filter if backend_for(model) == "objects" else partial(run_joints, covariances=False)

    def search(name: str, c: UKFConfig, bounds: tuple[float, float], n_scan: int) -> UKFConfig:
        most = 0.0  # the most measurements any value's pass has used

        def logliks(values: list[float]) -> list[float]:
            nonlocal most
            if lin is not None:  # boxes: the regression fixed per row, a linear pass per value
                return lin.logliks([{"accel_sd": c.accel_sd, "shape_sd": c.shape_sd,
                                     "position_sd": c.position_sd or 0.0, name: v} for v in values])
            lls, used = [], []
            for i in range(0, len(values), per_pass):
                part = values[i:i + per_pass]
                rows_k, src, copy = replicate_rows(model.rows, sel, len(part))
                run = runner(search_model.take(rows_k, src), Init(init.x0[src], rows_of(init.P0, src)),
                             replace(c, smooth=False, iterations=1), fps, fade=False,
                             noise_rows={name: np.asarray(part)[copy]})
                lls += list(np.bincount(copy, weights=run.loglik_rows, minlength=len(part)))
                used += list(np.bincount(copy, weights=run.dof, minlength=len(part)))
            # the weights are fixed, so each value's pass should rest on the same measurements;
            # a prediction so uncertain that its sigma points leave a camera's view drops some,
            # and the likelihood of fewer measurements rises by dropping them (a clock-corrected
            # mouse's joints went to the bound, 100, on a fifth of its views): each value's is
            # taken over as many measurements as the most any pass used, at its own mean
            most = max([most, *used])
            return [float(v) * most / u if u > 0 else -np.inf for v, u in zip(lls, used, strict=True)]

        best, seen = maximise_log(logliks, *bounds, n_scan)
        curves[name] = [{"value": v, "loglik": ll if np.isfinite(ll) else None}  # None: the pass failed
                        for v, ll in sorted(seen.items())]
        chosen: dict[str, Any] = {name: best}  # the field searched, by name
        return replace(c, **chosen)

    given = cfg
    cfg = start
    if use_box and given.accel_sd is None:
        cfg = search("accel_sd", cfg, cfg.accel_bounds, 5)
    if use_box and given.position_sd is None:
        cfg = search("position_sd", cfg, cfg.position_bounds, 4)
        for _ in range(ASCENT_ROUNDS if given.accel_sd is None else 0):
            # the two trade off (a jittery label set is explained by either): coordinate ascent
            was = (cfg.accel_sd, cfg.position_sd)
            cfg = search("position_sd", search("accel_sd", cfg, cfg.accel_bounds, 5), cfg.position_bounds, 4)
            now = (cfg.accel_sd, cfg.position_sd)
            if None not in now + was and np.allclose(np.log(np.array(now, dtype=float)),
                                                     np.log(np.array(was, dtype=float)), atol=0.05):
                break
    if use_box and given.shape_sd is None:
        cfg = search("shape_sd", cfg, cfg.shape_bounds, 4)
    if use_kpt and given.joint_accel_sd is None:
        cfg = search("joint_accel_sd", cfg, cfg.joint_accel_bounds, 4)
    if not use_box and given.accel_sd is None:
        cfg = replace(cfg, accel_sd=cfg.joint_accel_sd)
    return cfg, curves


def noise_by_likelihood(pre: Prepared, fps: float, cfg: UKFConfig) -> tuple[UKFConfig, JsonDict]:
    """:func:`select_noise` of a preparation: the process noise (the values ``cfg`` leaves
    ``None``) that maximises the marginal likelihood of the state-space model, by the Kalman
    filter's prediction-error decomposition; what the GTSAM smoother's graph is tuned by too
    (the same model, solved another way). Computed each time it is asked: nothing is kept on the
    preparation, so that what an estimator is given never depends on what ran before it."""
    model = Model.of(pre)
    found, curves = select_noise(model, initial_states(model, cfg), cfg, pre, fps)
    return replace(found, **{k: v for k, v in asdict(cfg).items() if k not in NOISE_FIELDS}), curves


def search_rows(rows: Rows, budget: int, seed: int = 0) -> np.ndarray | None:
    """(R,) the rows of whole objects, drawn in a seeded random order until they hold
    ``budget`` object-frames (:func:`drawn_objects`); ``None`` (all rows) when the scene has no
    more than that. (Windows of the sequence with every object in them were tried: per pass they
    were no faster, the batches grew as the frames shrank, and a shape's random walk showed less.)"""
    if len(rows) <= budget:
        return None
    return drawn_objects(np.bincount(rows.row_o, minlength=len(rows.obj_ids)), budget, seed)[rows.row_o]


def drawn_objects(count: np.ndarray, budget: int, seed: int = 0) -> np.ndarray:
    """``(O,)`` which objects the noise search runs on, of objects with ``count (O,)``
    object-frames each: in a random order (``seed``) until they hold ``budget`` of them."""
    order = np.random.default_rng(seed).permutation(len(count))
    take = order[: int(np.searchsorted(np.cumsum(count[order]), budget)) + 1]
    obj = np.zeros(len(count), bool)
    obj[take] = True
    return obj

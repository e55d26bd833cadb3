r"""The tangent box of :mod:`gt3dkit.geom.conics` as one compiled loop (numba).

A whole-array numpy formulation of the same mathematics (``tests/oracles.py``) is the reference
the tests hold this kernel to. Written as array operations, one box call for 40 objects x 19
sigma points x 7 cameras makes ~100 temporaries of 21 000 elements and its two finite-
difference Newton steps for lens distortion evaluate ``cos``/``sin`` seven times per edge; the
profile of issue 13 found this to be 84 % of a box reconstruction. Here each (ellipsoid,
camera) pair is a few hundred flops in registers: the tangent angle is kept as the unit vector
``(cos θ, sin θ)`` (the closed-form start needs no ``atan2``), and the Newton steps use the
exact first and second derivatives along the outline (:func:`edge_slope`) instead of the
reference's central differences.

Per camera the work is chosen as in the reference: the closed form without distortion and skew,
the value at the tangent angle with skew only, Newton steps with distortion.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numba
import numpy as np

from gt3dkit.geom.kernel_cache import drop_stale
from gt3dkit.threads import run_split
from gt3dkit.types import F64

drop_stale()  # before any compiled function below is called (and its cache read)

#: Edges of a box: left, top, right, bottom.
EDGES = 4


@numba.njit(cache=True, nogil=True)
def edge_value(e: int, ct: float, st: float, m0: float, m1: float, l00: float, l10: float,
               l11: float, k: F64, K: F64) -> float:
    x = m0 + l00 * ct
    y = m1 + l10 * ct + l11 * st
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))
    xd = x * radial + 2.0 * k[2] * x * y + k[3] * (r2 + 2.0 * x * x)
    yd = y * radial + k[2] * (r2 + 2.0 * y * y) + 2.0 * k[3] * x * y
    if e == 0:
        return -(K[0, 0] * xd + K[0, 1] * yd + K[0, 2])
    if e == 1:
        return -(K[1, 1] * yd + K[1, 2])
    if e == 2:
        return K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    return K[1, 1] * yd + K[1, 2]

@numba.njit(cache=True, nogil=True)
def edge_slope(e: int, ct: float, st: float, m0: float, m1: float, l00: float, l10: float,
               l11: float, k: F64, K: F64) -> tuple[float, float]:
    """First and second derivative of :func:`edge_value` along the outline angle (exact)."""
    x = m0 + l00 * ct
    y = m1 + l10 * ct + l11 * st
    x1 = -l00 * st  # d/dθ
    y1 = -l10 * st + l11 * ct
    x2 = m0 - x  # d²/dθ²
    y2 = m1 - y
    r2 = x * x + y * y
    r2d = 2.0 * (x * x1 + y * y1)
    r2dd = 2.0 * (x1 * x1 + x * x2 + y1 * y1 + y * y2)
    radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))
    g = k[0] + r2 * (2.0 * k[1] + 3.0 * r2 * k[4])  # d radial / d r2
    rd = r2d * g
    rdd = r2dd * g + r2d * r2d * (2.0 * k[1] + 6.0 * r2 * k[4])
    xyd = x1 * y + x * y1
    xydd = x2 * y + 2.0 * x1 * y1 + x * y2
    xd1 = x1 * radial + x * rd + 2.0 * k[2] * xyd + k[3] * (r2d + 4.0 * x * x1)
    yd1 = y1 * radial + y * rd + k[2] * (r2d + 4.0 * y * y1) + 2.0 * k[3] * xyd
    xd2 = (x2 * radial + 2.0 * x1 * rd + x * rdd + 2.0 * k[2] * xydd
           + k[3] * (r2dd + 4.0 * (x1 * x1 + x * x2)))
    yd2 = (y2 * radial + 2.0 * y1 * rd + y * rdd + k[2] * (r2dd + 4.0 * (y1 * y1 + y * y2))
           + 2.0 * k[3] * xydd)
    if e == 0:
        return -(K[0, 0] * xd1 + K[0, 1] * yd1), -(K[0, 0] * xd2 + K[0, 1] * yd2)
    if e == 1:
        return -K[1, 1] * yd1, -K[1, 1] * yd2
    if e == 2:
        return K[0, 0] * xd1 + K[0, 1] * yd1, K[0, 0] * xd2 + K[0, 1] * yd2
    return K[1, 1] * yd1, K[1, 1] * yd2


class BoxCameras(NamedTuple):
    """The camera arrays the compiled tangent box needs (contiguous float64): ``world_from_body
    (3, 3)``, ``K (C, 3, 3)``, ``dist (C, 5)``, ``R (C, 3, 3)``, ``t (C, 3)``, ``depth_sign (C,)``."""

    world_from_body: F64
    K: F64
    dist: F64
    R: F64
    t: F64
    depth_sign: F64

    @classmethod
    def of(cls, cams: Any) -> BoxCameras:
        C = len(cams.K)
        return cls(contiguous(cams.world_from_body), contiguous(cams.K), contiguous(cams.dist),
                   contiguous(cams.R), contiguous(cams.t),
                   contiguous(np.broadcast_to(np.asarray(cams.depth_sign, dtype=np.float64), (C,))))


class BoxRig(NamedTuple):
    """:class:`BoxCameras` prepared for :func:`pair_box` (:func:`box_rig`): per camera ``Rc = R
    Rb (C, 3, 3)`` and the four edge directions ``A^T dir`` as ``gx, gy (C, 4)`` (``A = K[:2,
    :2]``), the cameras' ``K, dist, R, t, ds`` (depth sign) and the Newton ``steps`` along the
    outline with distortion."""

    Rc: F64
    gx: F64
    gy: F64
    K: F64
    dist: F64
    R: F64
    t: F64
    ds: F64
    steps: int


@numba.njit(cache=True, nogil=True)
def box_rig(cams: BoxCameras, steps: int) -> BoxRig:
    """The :class:`BoxRig` of ``cams``, shared by every pair of :func:`pair_box`."""
    K, R, Rb = cams.K, cams.R, cams.world_from_body
    C = K.shape[0]
    Rc = np.empty((C, 3, 3))
    for c in range(C):
        for i in range(3):
            for j in range(3):
                Rc[c, i, j] = R[c, i, 0] * Rb[0, j] + R[c, i, 1] * Rb[1, j] + R[c, i, 2] * Rb[2, j]
    gx = np.empty((C, 4))
    gy = np.empty((C, 4))
    for c in range(C):
        gx[c, 0], gy[c, 0] = -K[c, 0, 0], -K[c, 0, 1]
        gx[c, 1], gy[c, 1] = -K[c, 1, 0], -K[c, 1, 1]
        gx[c, 2], gy[c, 2] = K[c, 0, 0], K[c, 0, 1]
        gx[c, 3], gy[c, 3] = K[c, 1, 0], K[c, 1, 1]
    return BoxRig(Rc, gx, gy, K, cams.dist, R, cams.t, cams.depth_sign, steps)


@numba.njit(cache=True, nogil=True, inline="always")
def _in_camera(p: tuple[float, float, float], s: tuple[float, float, float], c: int, rig: BoxRig
               ) -> tuple[float, float, float, float, float, float, float, float, float]:
    """The centre ``p`` in camera ``c`` ``X`` and the shape matrix there ``M = Rc diag(s) Rc^T``
    of the ellipsoid with squared semi-axes ``s`` (its six entries): ``(X0, X1, X2, M00, M11,
    M22, M01, M02, M12)``."""
    p0, p1, p2 = p
    s0, s1, s2 = s
    R, t = rig.R, rig.t
    X0 = R[c, 0, 0] * p0 + R[c, 0, 1] * p1 + R[c, 0, 2] * p2 + t[c, 0]
    X1 = R[c, 1, 0] * p0 + R[c, 1, 1] * p1 + R[c, 1, 2] * p2 + t[c, 1]
    X2 = R[c, 2, 0] * p0 + R[c, 2, 1] * p1 + R[c, 2, 2] * p2 + t[c, 2]
    q = rig.Rc[c]
    M00 = q[0, 0] ** 2 * s0 + q[0, 1] ** 2 * s1 + q[0, 2] ** 2 * s2
    M11 = q[1, 0] ** 2 * s0 + q[1, 1] ** 2 * s1 + q[1, 2] ** 2 * s2
    M22 = q[2, 0] ** 2 * s0 + q[2, 1] ** 2 * s1 + q[2, 2] ** 2 * s2
    M01 = q[0, 0] * q[1, 0] * s0 + q[0, 1] * q[1, 1] * s1 + q[0, 2] * q[1, 2] * s2
    M02 = q[0, 0] * q[2, 0] * s0 + q[0, 1] * q[2, 1] * s1 + q[0, 2] * q[2, 2] * s2
    M12 = q[1, 0] * q[2, 0] * s0 + q[1, 1] * q[2, 1] * s1 + q[1, 2] * q[2, 2] * s2
    return X0, X1, X2, M00, M11, M22, M01, M02, M12


@numba.njit(cache=True, nogil=True, inline="always")
def _edge_angle(e: int, c: int, m: tuple[float, float], el: tuple[float, float, float], rig: BoxRig,
                has_dist: bool) -> tuple[float, float]:
    """The outline angle ``(cos θ, sin θ)`` where edge ``e`` of camera ``c`` touches the outline
    with centre ``m`` and Cholesky factor ``el = (l00, l10, l11)``: the closed form (no
    trigonometry), then with distortion Newton steps on the exact derivatives."""
    m0, m1 = m
    l00, l10, l11 = el
    gx, gy, k, Kc = rig.gx, rig.gy, rig.dist[c], rig.K[c]
    a = l00 * gx[c, e] + l10 * gy[c, e]
    b = l11 * gy[c, e]
    nrm = math.sqrt(a * a + b * b)
    ct, st = (a / nrm, b / nrm) if nrm > 0 else (1.0, 0.0)
    if has_dist:
        for _ in range(rig.steps):
            d1, d2 = edge_slope(e, ct, st, m0, m1, l00, l10, l11, k, Kc)
            step = -d1 / d2 if d2 < 0 else 0.0
            step = min(max(step, -0.5), 0.5)
            if step != 0.0:  # rotate (cos θ, sin θ) by the step
                qq = step * step
                if qq < 4e-4:  # Taylor, exact to 1e-13 below 0.02 rad
                    cs = 1.0 - qq * (0.5 - qq * (1.0 / 24.0 - qq / 720.0))
                    ss = step * (1.0 - qq * (1.0 / 6.0 - qq / 120.0))
                else:
                    cs, ss = math.cos(step), math.sin(step)
                ct, st = ct * cs - st * ss, st * cs + ct * ss
            # Newton converges quadratically: the next step would be ~step^2 and gain
            # ~|f''| step^4 / 2 px; below 1e-6 px it is not taken
            if abs(d2) * step**4 < 1e-6:
                break
    return ct, st


@numba.njit(cache=True, nogil=True, inline="always")
def _has_dist(dist: F64, c: int) -> bool:
    return (dist[c, 0] != 0 or dist[c, 1] != 0 or dist[c, 2] != 0 or dist[c, 3] != 0
            or dist[c, 4] != 0)


@numba.njit(cache=True, nogil=True, inline="always")  # ~20 % faster than a call
def pair_box(p: tuple[float, float, float], s: tuple[float, float, float], c: int, rig: BoxRig,
             want: bool, out: F64, n: int) -> float:
    """The box ``out[n, c] (4,)`` (``out (N, C, 4)``) of the ellipsoid with centre ``p`` and
    squared semi-axes ``s`` in camera ``c`` (NaN if behind it or not ``want``); returns the
    margin."""
    K, dist = rig.K, rig.dist
    X0, X1, X2, M00, M11, M22, M01, M02, M12 = _in_camera(p, s, c, rig)
    mg = rig.ds[c] * X2 - math.sqrt(max(M22, 0.0))
    if not mg > 0 or not want:
        for e in range(4):
            out[n, c, e] = np.nan
        return mg
    c33 = M22 - X2 * X2
    m0 = (M02 - X0 * X2) / c33
    m1 = (M12 - X1 * X2) / c33
    E00 = m0 * m0 - (M00 - X0 * X0) / c33
    E01 = m0 * m1 - (M01 - X0 * X1) / c33
    E11 = m1 * m1 - (M11 - X1 * X1) / c33
    has_dist = _has_dist(dist, c)
    if not has_dist and K[c, 0, 1] == 0:
        hx = math.sqrt(max(E00, 0.0))
        hy = math.sqrt(max(E11, 0.0))
        out[n, c, 0] = K[c, 0, 0] * (m0 - hx) + K[c, 0, 2]
        out[n, c, 1] = K[c, 1, 1] * (m1 - hy) + K[c, 1, 2]
        out[n, c, 2] = K[c, 0, 0] * (m0 + hx) + K[c, 0, 2]
        out[n, c, 3] = K[c, 1, 1] * (m1 + hy) + K[c, 1, 2]
        return mg
    l00 = math.sqrt(max(E00, 1e-300))
    l10 = E01 / l00
    l11 = math.sqrt(max(E11 - l10 * l10, 0.0))
    k = dist[c]
    Kc = K[c]
    for e in range(4):
        ct, st = _edge_angle(e, c, (m0, m1), (l00, l10, l11), rig, has_dist)
        v = edge_value(e, ct, st, m0, m1, l00, l10, l11, k, Kc)
        out[n, c, e] = -v if e < 2 else v
    return mg


@numba.njit(cache=True, nogil=True)
def pair_box_grad(p: tuple[float, float, float], la: tuple[float, float, float], c: int, rig: BoxRig,
                  box: F64, grad: F64) -> float:
    """The box ``box (4,)`` of the ellipsoid with centre ``p`` and log semi-axes ``la`` in camera
    ``c`` and its derivatives ``grad (4, 6)`` by (centre, log semi-axes); NaN if behind it.
    Returns the margin.

    Each edge is the outline's extreme along one image direction, at the angle θ* where it
    touches: by the envelope theorem its derivative is the partial one at fixed θ* (exact at
    the extreme; the Newton steps stop within 1e-6 px of it). The chain runs through the
    outline's centre ``m`` and the Cholesky factor ``L`` of its shape, forward mode, one
    parameter direction at a time."""
    s0, s1, s2 = math.exp(2.0 * la[0]), math.exp(2.0 * la[1]), math.exp(2.0 * la[2])
    K, dist, R = rig.K, rig.dist, rig.R
    X0, X1, X2, M00, M11, M22, M01, M02, M12 = _in_camera(p, (s0, s1, s2), c, rig)
    mg = rig.ds[c] * X2 - math.sqrt(max(M22, 0.0))
    if not mg > 0:
        box[:] = np.nan
        grad[:, :] = np.nan
        return mg
    c33 = M22 - X2 * X2
    m0 = (M02 - X0 * X2) / c33
    m1 = (M12 - X1 * X2) / c33
    b00, b01, b11 = (M00 - X0 * X0) / c33, (M01 - X0 * X1) / c33, (M11 - X1 * X1) / c33
    E00 = m0 * m0 - b00
    E01 = m0 * m1 - b01
    E11 = m1 * m1 - b11
    l00 = math.sqrt(max(E00, 1e-300))
    l10 = E01 / l00
    l11 = math.sqrt(max(E11 - l10 * l10, 1e-300))
    k = dist[c]
    Kc = K[c]
    has_dist = _has_dist(dist, c)
    q = rig.Rc[c]
    for e in range(4):
        ct, st = _edge_angle(e, c, (m0, m1), (l00, l10, l11), rig, has_dist)
        v = edge_value(e, ct, st, m0, m1, l00, l10, l11, k, Kc)
        box[e] = -v if e < 2 else v
        # the distorted point's derivative by the undistorted one, at θ*
        x = m0 + l00 * ct
        y = m1 + l10 * ct + l11 * st
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))
        g = k[0] + r2 * (2.0 * k[1] + 3.0 * r2 * k[4])
        dxx = radial + 2.0 * x * x * g + 2.0 * k[2] * y + 6.0 * k[3] * x
        dxy = 2.0 * x * y * g + 2.0 * k[2] * x + 2.0 * k[3] * y
        dyx = dxy
        dyy = radial + 2.0 * y * y * g + 6.0 * k[2] * y + 2.0 * k[3] * x
        for j in range(6):
            if j < 3:  # centre: X moves along R's column, M stays
                dX0, dX1, dX2 = R[c, 0, j], R[c, 1, j], R[c, 2, j]
                dM00 = dM11 = dM22 = dM01 = dM02 = dM12 = 0.0
            else:  # log semi-axis a: M moves by 2 s_a q_a q_a^T, X stays
                a = j - 3
                sa = 2.0 * (s0 if a == 0 else (s1 if a == 1 else s2))
                dX0 = dX1 = dX2 = 0.0
                dM00, dM11, dM22 = sa * q[0, a] * q[0, a], sa * q[1, a] * q[1, a], sa * q[2, a] * q[2, a]
                dM01, dM02, dM12 = sa * q[0, a] * q[1, a], sa * q[0, a] * q[2, a], sa * q[1, a] * q[2, a]
            dc33 = dM22 - 2.0 * X2 * dX2
            dm0 = (dM02 - dX0 * X2 - X0 * dX2 - m0 * dc33) / c33
            dm1 = (dM12 - dX1 * X2 - X1 * dX2 - m1 * dc33) / c33
            db00 = (dM00 - 2.0 * X0 * dX0 - b00 * dc33) / c33
            db01 = (dM01 - dX0 * X1 - X0 * dX1 - b01 * dc33) / c33
            db11 = (dM11 - 2.0 * X1 * dX1 - b11 * dc33) / c33
            dE00 = 2.0 * m0 * dm0 - db00
            dE01 = dm0 * m1 + m0 * dm1 - db01
            dE11 = 2.0 * m1 * dm1 - db11
            dl00 = dE00 / (2.0 * l00)
            dl10 = (dE01 - l10 * dl00) / l00
            dl11 = (dE11 - 2.0 * l10 * dl10) / (2.0 * l11)
            dx = dm0 + dl00 * ct
            dy = dm1 + dl10 * ct + dl11 * st
            dxd = dxx * dx + dxy * dy
            dyd = dyx * dx + dyy * dy
            grad[e, j] = Kc[0, 0] * dxd + Kc[0, 1] * dyd if e % 2 == 0 else Kc[1, 1] * dyd
    return mg


@numba.njit(cache=True, nogil=True)
def kernel(center: F64, axes: F64, cams: BoxCameras, steps: int, want: np.ndarray, box: F64,
           margin: F64) -> None:
    """Boxes ``box (N, C, 4)`` and margins ``margin (N, C)`` of N ellipsoids (``center, axes (N,
    3)``) in C cameras; ``want (N, C)`` (or ``(1, 1)``: every pair): pairs whose box is needed
    (the margin is computed for all; an unwanted box is NaN)."""
    N, C = center.shape[0], cams.K.shape[0]
    rig = box_rig(cams, steps)
    every = want.shape[0] == 1 and want.shape[1] == 1 and want[0, 0]
    for n in range(N):
        s = (axes[n, 0] ** 2, axes[n, 1] ** 2, axes[n, 2] ** 2)
        for c in range(C):
            margin[n, c] = pair_box((center[n, 0], center[n, 1], center[n, 2]), s, c, rig,
                                    every or want[n, c], box, n)


#: pairs per thread below which a call is not split (a thread hand-off costs ~20 us; a pair
#: ~0.3 us)
MIN_PAIRS_PER_THREAD = 256
EVERY_CAMERA = np.ones((1, 1), dtype=np.bool_)


def boxes_compiled(center_world: F64, semi_axes: F64, world_from_body: F64, K: F64, dist: F64,
                   R: F64, t: F64, depth_sign: F64 | float, newton_steps: int,
                   want: np.ndarray | None = None) -> tuple[F64, F64]:
    """:func:`gt3dkit.geom.conics.ellipsoid_boxes` for ``(..., 3)`` centres and semi-axes:
    ``(..., C, 4)`` boxes and ``(..., C)`` margins (numba compiles the kernel on first use and
    caches it on disk). ``want`` (broadcastable to ``(..., C)``): the pairs whose box is needed
    (the others are NaN; the margin is computed for every pair). Large calls are split over
    threads (:func:`gt3dkit.threads.run_split`)."""
    c, s = np.broadcast_arrays(np.asarray(center_world, dtype=np.float64),
                               np.asarray(semi_axes, dtype=np.float64))
    lead = c.shape[:-1]
    C = K.shape[0]

    def arr(a: Any, dtype: Any = np.float64) -> np.ndarray:  # one compiled signature: C order, writable
        if type(a) is np.ndarray and a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable:
            return a  # the common case, without np.require's ~4 us (GTSAM's factors call this 40 000 times)
        return np.require(a, dtype=dtype, requirements=["C", "W"])

    cf = arr(c.reshape(-1, 3))
    sf = arr(s.reshape(-1, 3))
    N = cf.shape[0]
    wf = EVERY_CAMERA if want is None else arr(np.broadcast_to(np.asarray(want, dtype=np.bool_),
                                                         lead + (C,)).reshape(N, C), np.bool_)
    box = np.empty((N, C, 4))
    margin = np.empty((N, C))
    ds = arr(np.broadcast_to(np.asarray(depth_sign, dtype=np.float64), (C,)))
    cam = BoxCameras(*(arr(a) for a in (world_from_body, K, dist, R, t)), ds)
    every = wf is EVERY_CAMERA

    def part(a: int, b: int) -> None:
        kernel(cf[a:b], sf[a:b], cam, int(newton_steps), wf if every else wf[a:b], box[a:b], margin[a:b])

    per = max(MIN_PAIRS_PER_THREAD // max(C, 1), 1)
    if N < 2 * per:
        part(0, N)  # too small to split: no thread policy to consult
    else:
        run_split(part, N, per)
    return box.reshape(lead + (C, 4)), margin.reshape(lead + (C,))


def contiguous(a: Any, dtype: Any = np.float64) -> np.ndarray:
    """``a`` as a C-contiguous, writable array of ``dtype``: numba compiles a function once per
    argument type, and a read-only array (a broadcast view) is another type."""
    return np.require(a, dtype=dtype, requirements=["C", "W"])

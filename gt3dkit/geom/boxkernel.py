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

The same state (centre, semi-axes along the body axes, body axis 2 up) has three box models
(:data:`BOX_MODELS`), for the three ways label sets draw a person's box:

* ``ellipsoid``: the tangent box of the ellipsoid (the paper's model; hand-drawn tight boxes);
* ``cylinder``: the box of the vertical cylinder with those radii and half-height, the union of
  its two end discs' tangent boxes (the cylinder is their convex hull);
* ``pom``: the rectangle of Fleuret et al.'s probabilistic occupancy map generator, with which
  WILDTRACK and MultiviewX made their boxes from the annotated ground positions: left, top and
  right are the extremes of the eight projected corners of the box-shaped person, the bottom the
  mean row of its four lowest corners.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from gt3dkit.geom.boxrig import (
    ROW_DIST as _DIST,
    ROW_DS as _DS,
    ROW_GX as _GX,
    ROW_GY as _GY,
    ROW_HASD as _HASD,
    ROW_K as _K,
    ROW_LENS as _LENS,
    ROW_R as _R,
    ROW_RC as _RC,
    ROW_T as _T,
    BoxCameras,
    BoxRig,
    box_rig,
)
from gt3dkit.geom.camera import FISHEYE
from gt3dkit.geom.kernel_cache import drop_stale
from gt3dkit.types import BOX_MODEL_REGISTRY, F64

drop_stale()  # before any compiled function below is called (and its cache read)

#: Edges of a box: left, top, right, bottom.
EDGES = 4
#: The most Newton steps along the outline through a fisheye lens (:func:`_edge_angle`).
FISHEYE_STEPS = 8
#: Angles around the outline a fisheye edge's Newton steps may start from (:func:`_edge_angle`).
FISHEYE_STARTS = 32
#: Indices of the box models of :data:`gt3dkit.types.BOX_MODELS` (module docstring).
ELLIPSOID, CYLINDER, POM = (BOX_MODEL_REGISTRY[m].index for m in ("ellipsoid", "cylinder", "pom"))


@numba.njit(cache=True, nogil=True, inline="always")
def _fisheye_h(rho: float, q: F64) -> tuple[float, float, float]:
    r"""OpenCV's fisheye map as :math:`(x', y') = h(\rho) (x, y)`, :math:`\rho = x^2 + y^2`:
    ``h = θ_d / r`` (``θ = atan r``, ``θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)``) and its first
    and second derivatives by ``ρ``. Near the axis (``r < 1e-3``) the derivatives are the series
    ``h = 1 + (k1 - 1/3) ρ + (k2 - k1 + 1/5) ρ² + O(ρ³)``."""
    k1, k2, k3, k4 = q[_DIST], q[_DIST + 1], q[_DIST + 2], q[_DIST + 3]
    r = math.sqrt(rho)
    th = math.atan(r)
    t2 = th * th
    td = th * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    h = td / r if r > 1e-8 else 1.0
    if r < 1e-3:
        a, b = k1 - 1.0 / 3.0, k2 - k1 + 0.2
        return h, a + 2.0 * b * rho, 2.0 * b
    s = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))  # dθ_d/dθ
    u = th * (6.0 * k1 + t2 * (20.0 * k2 + t2 * (42.0 * k3 + t2 * 72.0 * k4)))  # d²θ_d/dθ²
    w = 1.0 / (1.0 + rho)  # dθ/dr
    d1 = s * w  # dθ_d/dr
    d2 = (u - 2.0 * r * s) * w * w  # d²θ_d/dr²
    f1 = (d1 * r - td) / rho  # d(θ_d/r)/dr
    f2 = d2 / r - 2.0 * d1 / rho + 2.0 * td / (rho * r)
    return h, f1 / (2.0 * r), (f2 * r - f1) / (4.0 * rho * r)


@numba.njit(cache=True, nogil=True, inline="always")
def _lens_xy(x: float, y: float, q: F64) -> tuple[float, float]:
    """The lens model of camera row ``q`` at the undistorted normalised point ``(x, y)``."""
    r2 = x * x + y * y
    if q[_LENS] == FISHEYE:
        h = _fisheye_h(r2, q)[0]
        return h * x, h * y
    radial = 1.0 + r2 * (q[_DIST] + r2 * (q[_DIST + 1] + r2 * q[_DIST + 4]))
    xd = x * radial + 2.0 * q[_DIST + 2] * x * y + q[_DIST + 3] * (r2 + 2.0 * x * x)
    yd = y * radial + q[_DIST + 2] * (r2 + 2.0 * y * y) + 2.0 * q[_DIST + 3] * x * y
    return xd, yd


@numba.njit(cache=True, nogil=True, inline="always")
def _lens_jac(x: float, y: float, q: F64) -> tuple[float, float, float, float, float]:
    """The lens model of camera row ``q`` at ``(x, y)`` and its Jacobian: ``(xd, yd, dxd/dx,
    dxd/dy = dyd/dx, dyd/dy)`` (both models' Jacobians are symmetric)."""
    r2 = x * x + y * y
    if q[_LENS] == FISHEYE:
        h, h1, _ = _fisheye_h(r2, q)
        return h * x, h * y, h + 2.0 * h1 * x * x, 2.0 * h1 * x * y, h + 2.0 * h1 * y * y
    radial = 1.0 + r2 * (q[_DIST] + r2 * (q[_DIST + 1] + r2 * q[_DIST + 4]))
    xd = x * radial + 2.0 * q[_DIST + 2] * x * y + q[_DIST + 3] * (r2 + 2.0 * x * x)
    yd = y * radial + q[_DIST + 2] * (r2 + 2.0 * y * y) + 2.0 * q[_DIST + 3] * x * y
    g = q[_DIST] + r2 * (2.0 * q[_DIST + 1] + 3.0 * r2 * q[_DIST + 4])
    dxx = radial + 2.0 * x * x * g + 2.0 * q[_DIST + 2] * y + 6.0 * q[_DIST + 3] * x
    dxy = 2.0 * x * y * g + 2.0 * q[_DIST + 2] * x + 2.0 * q[_DIST + 3] * y
    dyy = radial + 2.0 * y * y * g + 6.0 * q[_DIST + 2] * y + 2.0 * q[_DIST + 3] * x
    return xd, yd, dxx, dxy, dyy


@numba.njit(cache=True, nogil=True)
def edge_value(e: int, ct: float, st: float, m0: float, m1: float, l00: float, l10: float,
               l11: float, q: F64) -> float:
    """Edge ``e``'s pixel coordinate (signed: maximised) at outline angle ``(ct, st)`` in the camera
    of row ``q`` (:class:`BoxRig`)."""
    x = m0 + l00 * ct
    y = m1 + l10 * ct + l11 * st
    xd, yd = _lens_xy(x, y, q)
    if e == 0:
        return -(q[_K] * xd + q[_K + 1] * yd + q[_K + 2])
    if e == 1:
        return -(q[_K + 4] * yd + q[_K + 5])
    if e == 2:
        return q[_K] * xd + q[_K + 1] * yd + q[_K + 2]
    return q[_K + 4] * yd + q[_K + 5]

@numba.njit(cache=True, nogil=True)
def edge_slope(e: int, ct: float, st: float, m0: float, m1: float, l00: float, l10: float,
               l11: float, q: F64) -> tuple[float, float]:
    """First and second derivative of :func:`edge_value` along the outline angle (exact)."""
    x = m0 + l00 * ct
    y = m1 + l10 * ct + l11 * st
    x1 = -l00 * st  # d/dθ
    y1 = -l10 * st + l11 * ct
    x2 = m0 - x  # d²/dθ²
    y2 = m1 - y
    if q[_LENS] == FISHEYE:
        xd1, yd1, xd2, yd2 = _fisheye_along(x, y, x1, y1, x2, y2, q)
        return _edge_pick(e, xd1, yd1, xd2, yd2, q)
    r2 = x * x + y * y
    r2d = 2.0 * (x * x1 + y * y1)
    r2dd = 2.0 * (x1 * x1 + x * x2 + y1 * y1 + y * y2)
    radial = 1.0 + r2 * (q[_DIST] + r2 * (q[_DIST + 1] + r2 * q[_DIST + 4]))
    g = q[_DIST] + r2 * (2.0 * q[_DIST + 1] + 3.0 * r2 * q[_DIST + 4])  # d radial / d r2
    rd = r2d * g
    rdd = r2dd * g + r2d * r2d * (2.0 * q[_DIST + 1] + 6.0 * r2 * q[_DIST + 4])
    xyd = x1 * y + x * y1
    xydd = x2 * y + 2.0 * x1 * y1 + x * y2
    xd1 = x1 * radial + x * rd + 2.0 * q[_DIST + 2] * xyd + q[_DIST + 3] * (r2d + 4.0 * x * x1)
    yd1 = y1 * radial + y * rd + q[_DIST + 2] * (r2d + 4.0 * y * y1) + 2.0 * q[_DIST + 3] * xyd
    xd2 = (x2 * radial + 2.0 * x1 * rd + x * rdd + 2.0 * q[_DIST + 2] * xydd
           + q[_DIST + 3] * (r2dd + 4.0 * (x1 * x1 + x * x2)))
    yd2 = (y2 * radial + 2.0 * y1 * rd + y * rdd + q[_DIST + 2] * (r2dd + 4.0 * (y1 * y1 + y * y2))
           + 2.0 * q[_DIST + 3] * xydd)
    return _edge_pick(e, xd1, yd1, xd2, yd2, q)


@numba.njit(cache=True, nogil=True, inline="always")
def _fisheye_along(x: float, y: float, x1: float, y1: float, x2: float, y2: float, q: F64
                   ) -> tuple[float, float, float, float]:
    """First and second derivatives along a curve ``p(θ) = (x, y)`` (``p' = (x1, y1)``, ``p'' =
    (x2, y2)``) of the fisheye map ``D(p) = h(ρ) p``:
    ``D' = h p' + 2 h_ρ (p·p') p`` and
    ``D'' = h p'' + 4 h_ρ (p·p') p' + (4 h_ρρ (p·p')² + 2 h_ρ (p'·p' + p·p'')) p``."""
    h, h1, h2 = _fisheye_h(x * x + y * y, q)
    pp1 = x * x1 + y * y1
    c = 4.0 * h2 * pp1 * pp1 + 2.0 * h1 * (x1 * x1 + y1 * y1 + x * x2 + y * y2)
    return (h * x1 + 2.0 * h1 * pp1 * x, h * y1 + 2.0 * h1 * pp1 * y,
            h * x2 + 4.0 * h1 * pp1 * x1 + c * x, h * y2 + 4.0 * h1 * pp1 * y1 + c * y)


@numba.njit(cache=True, nogil=True, inline="always")
def _edge_pick(e: int, xd1: float, yd1: float, xd2: float, yd2: float, q: F64) -> tuple[float, float]:
    """Edge ``e``'s first and second derivatives from the distorted point's (signed as
    :func:`edge_value`)."""
    if e == 0:
        return -(q[_K] * xd1 + q[_K + 1] * yd1), -(q[_K] * xd2 + q[_K + 1] * yd2)
    if e == 1:
        return -q[_K + 4] * yd1, -q[_K + 4] * yd2
    if e == 2:
        return q[_K] * xd1 + q[_K + 1] * yd1, q[_K] * xd2 + q[_K + 1] * yd2
    return q[_K + 4] * yd1, q[_K + 4] * yd2


@numba.njit(cache=True, nogil=True, inline="always")
def _in_camera(p: tuple[float, float, float], s: tuple[float, float, float], q: F64
               ) -> tuple[float, float, float, float, float, float, float, float, float]:
    """The centre ``p`` in camera row ``q`` ``X`` and the shape matrix there ``M = Rc diag(s) Rc^T``
    of the ellipsoid with squared semi-axes ``s`` (its six entries): ``(X0, X1, X2, M00, M11,
    M22, M01, M02, M12)``."""
    p0, p1, p2 = p
    s0, s1, s2 = s
    X0 = q[_R] * p0 + q[_R + 1] * p1 + q[_R + 2] * p2 + q[_T]
    X1 = q[_R + 3] * p0 + q[_R + 4] * p1 + q[_R + 5] * p2 + q[_T + 1]
    X2 = q[_R + 6] * p0 + q[_R + 7] * p1 + q[_R + 8] * p2 + q[_T + 2]
    r00, r01, r02 = q[_RC], q[_RC + 1], q[_RC + 2]
    r10, r11, r12 = q[_RC + 3], q[_RC + 4], q[_RC + 5]
    r20, r21, r22 = q[_RC + 6], q[_RC + 7], q[_RC + 8]
    M00 = r00 ** 2 * s0 + r01 ** 2 * s1 + r02 ** 2 * s2
    M11 = r10 ** 2 * s0 + r11 ** 2 * s1 + r12 ** 2 * s2
    M22 = r20 ** 2 * s0 + r21 ** 2 * s1 + r22 ** 2 * s2
    M01 = r00 * r10 * s0 + r01 * r11 * s1 + r02 * r12 * s2
    M02 = r00 * r20 * s0 + r01 * r21 * s1 + r02 * r22 * s2
    M12 = r10 * r20 * s0 + r11 * r21 * s1 + r12 * r22 * s2
    return X0, X1, X2, M00, M11, M22, M01, M02, M12


@numba.njit(cache=True, nogil=True, inline="always")
def _edge_angle(e: int, m: tuple[float, float], el: tuple[float, float, float], q: F64, steps: int
                ) -> tuple[float, float]:
    """The outline angle ``(cos θ, sin θ)`` where edge ``e`` of camera row ``q`` touches the outline
    with centre ``m`` and Cholesky factor ``el = (l00, l10, l11)``: the closed form (no
    trigonometry), then with distortion Newton steps on the exact derivatives.

    A fisheye lens bends the outline strongly, and an object that reaches far off the axis has an
    outline with several local extremes: its start is the best of the closed form through the
    lens's Jacobian at the outline's centre (the edge direction ``g`` pulled back as ``J^T g``) and
    :data:`FISHEYE_STARTS` angles around the outline, and it takes up to :data:`FISHEYE_STEPS`
    steps (each stops once within 1e-6 px, as the others)."""
    m0, m1 = m
    l00, l10, l11 = el
    gx, gy = q[_GX + e], q[_GY + e]
    n = steps
    if q[_LENS] == FISHEYE:
        _, _, jxx, jxy, jyy = _lens_jac(m0, m1, q)
        gx, gy = jxx * gx + jxy * gy, jxy * gx + jyy * gy
        n = max(steps, FISHEYE_STEPS)
    a = l00 * gx + l10 * gy
    b = l11 * gy
    nrm = math.sqrt(a * a + b * b)
    ct, st = (a / nrm, b / nrm) if nrm > 0 else (1.0, 0.0)
    if q[_LENS] == FISHEYE:
        best = edge_value(e, ct, st, m0, m1, l00, l10, l11, q)
        for k in range(FISHEYE_STARTS):
            ang = 2.0 * math.pi * k / FISHEYE_STARTS
            ck, sk = math.cos(ang), math.sin(ang)
            v = edge_value(e, ck, sk, m0, m1, l00, l10, l11, q)
            if v > best:
                best, ct, st = v, ck, sk
    if q[_HASD] != 0.0:
        for _ in range(n):
            d1, d2 = edge_slope(e, ct, st, m0, m1, l00, l10, l11, q)
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
def _quadric_box(p: tuple[float, float, float], s: tuple[float, float, float], q: F64, steps: int
                 ) -> tuple[float, float, float, float, float]:
    """Margin and box (left, top, right, bottom) of the ellipsoid (or flat disc: ``s[2] = 0``) with
    centre ``p`` and squared semi-axes ``s`` in camera row ``q``; NaN box if behind it."""
    X0, X1, X2, M00, M11, M22, M01, M02, M12 = _in_camera(p, s, q)
    mg = q[_DS] * X2 - math.sqrt(max(M22, 0.0))
    if not mg > 0:
        return mg, np.nan, np.nan, np.nan, np.nan
    c33 = M22 - X2 * X2
    m0 = (M02 - X0 * X2) / c33
    m1 = (M12 - X1 * X2) / c33
    E00 = m0 * m0 - (M00 - X0 * X0) / c33
    E01 = m0 * m1 - (M01 - X0 * X1) / c33
    E11 = m1 * m1 - (M11 - X1 * X1) / c33
    if q[_HASD] == 0.0 and q[_K + 1] == 0:
        hx = math.sqrt(max(E00, 0.0))
        hy = math.sqrt(max(E11, 0.0))
        return (mg, q[_K] * (m0 - hx) + q[_K + 2], q[_K + 4] * (m1 - hy) + q[_K + 5],
                q[_K] * (m0 + hx) + q[_K + 2], q[_K + 4] * (m1 + hy) + q[_K + 5])
    l00 = math.sqrt(max(E00, 1e-300))
    l10 = E01 / l00
    l11 = math.sqrt(max(E11 - l10 * l10, 0.0))
    el = (l00, l10, l11)
    c0, s0 = _edge_angle(0, (m0, m1), el, q, steps)
    c1, s1 = _edge_angle(1, (m0, m1), el, q, steps)
    c2, s2 = _edge_angle(2, (m0, m1), el, q, steps)
    c3, s3 = _edge_angle(3, (m0, m1), el, q, steps)
    return (mg, -edge_value(0, c0, s0, m0, m1, l00, l10, l11, q),
            -edge_value(1, c1, s1, m0, m1, l00, l10, l11, q),
            edge_value(2, c2, s2, m0, m1, l00, l10, l11, q), edge_value(3, c3, s3, m0, m1, l00, l10, l11, q))


@numba.njit(cache=True, nogil=True, inline="always")
def _up(q: F64) -> tuple[float, float, float]:
    """The body's axis 2 (up) in world coordinates, from camera row ``q``: ``R^T Rc[:, 2]``."""
    u0 = q[_R] * q[_RC + 2] + q[_R + 3] * q[_RC + 5] + q[_R + 6] * q[_RC + 8]
    u1 = q[_R + 1] * q[_RC + 2] + q[_R + 4] * q[_RC + 5] + q[_R + 7] * q[_RC + 8]
    u2 = q[_R + 2] * q[_RC + 2] + q[_R + 5] * q[_RC + 5] + q[_R + 8] * q[_RC + 8]
    return u0, u1, u2



@numba.njit(cache=True, nogil=True, inline="always")
def _point_px(X0: float, X1: float, X2: float, q: F64
              ) -> tuple[float, float, float, float, float, float, float, float]:
    """The pixel ``(u, v)`` of the camera-frame point ``X`` in camera row ``q`` (lens distortion
    included) and its derivatives ``du/dX (3)``, ``dv/dX (3)``."""
    x, y = X0 / X2, X1 / X2
    xd, yd, dxx, dxy, dyy = _lens_jac(x, y, q)
    u = q[_K] * xd + q[_K + 1] * yd + q[_K + 2]
    v = q[_K + 4] * yd + q[_K + 5]
    ux, uy = q[_K] * dxx + q[_K + 1] * dxy, q[_K] * dxy + q[_K + 1] * dyy  # du/dx, du/dy
    vx, vy = q[_K + 4] * dxy, q[_K + 4] * dyy
    iz = 1.0 / X2
    return (u, v, ux * iz, uy * iz, -(ux * x + uy * y) * iz, vx * iz, vy * iz, -(vx * x + vy * y) * iz)


@numba.njit(cache=True, nogil=True, inline="always")
def _pixel(X0: float, X1: float, X2: float, q: F64) -> tuple[float, float]:
    """The pixel ``(u, v)`` of the camera-frame point ``X`` in camera row ``q`` (:func:`_point_px`
    without the derivatives)."""
    x, y = X0 / X2, X1 / X2
    xd, yd = _lens_xy(x, y, q)
    return q[_K] * xd + q[_K + 1] * yd + q[_K + 2], q[_K + 4] * yd + q[_K + 5]


@numba.njit(cache=True, nogil=True, inline="always")
def world_pixel(p0: float, p1: float, p2: float, q: F64) -> tuple[float, float]:
    """The pixel ``(u, v)`` of the world point ``p`` in camera row ``q`` (lens distortion
    included); NaN where the point is not in front of the camera."""
    c0 = q[_R] * p0 + q[_R + 1] * p1 + q[_R + 2] * p2 + q[_T]
    c1 = q[_R + 3] * p0 + q[_R + 4] * p1 + q[_R + 5] * p2 + q[_T + 1]
    c2 = q[_R + 6] * p0 + q[_R + 7] * p1 + q[_R + 8] * p2 + q[_T + 2]
    if c2 * q[_DS] > 1e-9:
        return _pixel(c0, c1, c2, q)
    return np.nan, np.nan


@numba.njit(cache=True, nogil=True, inline="always")
def _pom_value(p: tuple[float, float, float], e: tuple[float, float, float], q: F64
               ) -> tuple[float, float, float, float, float]:
    """Margin and POM rectangle (left, top, right, bottom) of :func:`_pom_box` without its
    derivatives, in registers: the four lowest corners kept by insertion."""
    base0 = q[_R] * p[0] + q[_R + 1] * p[1] + q[_R + 2] * p[2] + q[_T]
    base1 = q[_R + 3] * p[0] + q[_R + 4] * p[1] + q[_R + 5] * p[2] + q[_T + 1]
    base2 = q[_R + 6] * p[0] + q[_R + 7] * p[1] + q[_R + 8] * p[2] + q[_T + 2]
    # the nearest corner's depth: the depth of the centre less the largest offset along the axis
    mg = q[_DS] * base2 - (abs(e[0] * q[_RC + 6]) + abs(e[1] * q[_RC + 7]) + abs(e[2] * q[_RC + 8]))
    if not mg > 0:
        return mg, np.nan, np.nan, np.nan, np.nan
    lo_u, lo_v, hi_u = np.inf, np.inf, -np.inf
    v1 = v2 = v3 = v4 = -np.inf  # the four largest rows, v1 the largest
    for k in range(8):
        a0 = e[0] if k & 1 else -e[0]
        a1 = e[1] if k & 2 else -e[1]
        a2 = e[2] if k & 4 else -e[2]
        X0 = base0 + a0 * q[_RC] + a1 * q[_RC + 1] + a2 * q[_RC + 2]
        X1 = base1 + a0 * q[_RC + 3] + a1 * q[_RC + 4] + a2 * q[_RC + 5]
        X2 = base2 + a0 * q[_RC + 6] + a1 * q[_RC + 7] + a2 * q[_RC + 8]
        u, v = _pixel(X0, X1, X2, q)
        lo_u, lo_v, hi_u = min(lo_u, u), min(lo_v, v), max(hi_u, u)
        if v > v4:
            if v > v1:
                v1, v2, v3, v4 = v, v1, v2, v3
            elif v > v2:
                v2, v3, v4 = v, v2, v3
            elif v > v3:
                v3, v4 = v, v3
            else:
                v4 = v
    return mg, lo_u, lo_v, hi_u, (v1 + v2 + v3 + v4) / 4.0


@numba.njit(cache=True, nogil=True)
def _pom_box(p: tuple[float, float, float], e: tuple[float, float, float], q: F64, box: F64,
             grad: F64, with_grad: bool) -> float:
    """The POM rectangle (Fleuret et al.'s occupancy-map rectangles, the WILDTRACK and MultiviewX
    labels) of the box-shaped person with centre ``p`` and half-extents ``e`` along the body axes
    in camera row ``q``: left, top and right are the extremes of its eight projected corners, the
    bottom the mean row of the four lowest. ``box (4,)``, with ``with_grad`` its derivatives ``grad
    (4, 6)`` by (centre, log half-extents). Returns the margin (the nearest corner's depth)."""
    X = np.empty((8, 3))
    u = np.empty(8)
    v = np.empty(8)
    gu = np.empty((8, 6))
    gv = np.empty((8, 6))
    base0 = q[_R] * p[0] + q[_R + 1] * p[1] + q[_R + 2] * p[2] + q[_T]
    base1 = q[_R + 3] * p[0] + q[_R + 4] * p[1] + q[_R + 5] * p[2] + q[_T + 1]
    base2 = q[_R + 6] * p[0] + q[_R + 7] * p[1] + q[_R + 8] * p[2] + q[_T + 2]
    mg = np.inf
    for k in range(8):
        sg0, sg1, sg2 = (1.0 if k & 1 else -1.0), (1.0 if k & 2 else -1.0), (1.0 if k & 4 else -1.0)
        a0, a1, a2 = sg0 * e[0], sg1 * e[1], sg2 * e[2]
        X[k, 0] = base0 + a0 * q[_RC] + a1 * q[_RC + 1] + a2 * q[_RC + 2]
        X[k, 1] = base1 + a0 * q[_RC + 3] + a1 * q[_RC + 4] + a2 * q[_RC + 5]
        X[k, 2] = base2 + a0 * q[_RC + 6] + a1 * q[_RC + 7] + a2 * q[_RC + 8]
        mg = min(mg, q[_DS] * X[k, 2])
    if not mg > 0:
        box[:] = np.nan
        if with_grad:
            grad[:, :] = np.nan
        return mg
    for k in range(8):
        uk, vk, u0, u1, u2, v0, v1, v2 = _point_px(X[k, 0], X[k, 1], X[k, 2], q)
        u[k], v[k] = uk, vk
        if with_grad:
            for j in range(3):  # centre: X moves along R's column j
                gu[k, j] = u0 * q[_R + j] + u1 * q[_R + 3 + j] + u2 * q[_R + 6 + j]
                gv[k, j] = v0 * q[_R + j] + v1 * q[_R + 3 + j] + v2 * q[_R + 6 + j]
            for a in range(3):  # log half-extent a: X moves by its offset along Rc's column a
                sa = (1.0 if k & (1 << a) else -1.0) * e[a]
                gu[k, 3 + a] = sa * (u0 * q[_RC + a] + u1 * q[_RC + 3 + a] + u2 * q[_RC + 6 + a])
                gv[k, 3 + a] = sa * (v0 * q[_RC + a] + v1 * q[_RC + 3 + a] + v2 * q[_RC + 6 + a])
    il, it, ir = np.argmin(u), np.argmin(v), np.argmax(u)
    low = np.argsort(v)[4:]
    box[0], box[1], box[2] = u[il], v[it], u[ir]
    box[3] = (v[low[0]] + v[low[1]] + v[low[2]] + v[low[3]]) / 4.0
    if with_grad:
        for j in range(6):
            grad[0, j], grad[1, j], grad[2, j] = gu[il, j], gv[it, j], gu[ir, j]
            grad[3, j] = (gv[low[0], j] + gv[low[1], j] + gv[low[2], j] + gv[low[3], j]) / 4.0
    return mg


# Each box model is one pair, its value (margin and box from the centre ``p`` and squared
# semi-axes ``s`` in camera row ``q``) and its gradient (box and derivatives by centre and log
# semi-axes ``la`` in camera ``c``), listed in :data:`BOX_KERNELS` under its name in
# :data:`gt3dkit.types.BOX_MODEL_REGISTRY`; :func:`pair_box` and :func:`pair_box_grad` pick the
# pair by the rig's ``box_model`` (the entry's index).
#
# The values and :func:`pair_box` are called, not inlined (numba's ``inline="always"``) into their
# callers: inlined, each of the three callers (the LM fit's residuals, the sigma points' boxes and
# :func:`kernel`) typed and compiled all three models' trees again: 129 s of the 207 s the box
# kernels took to compile (``make setup``). Called, they compile in 92 s in all, and a box
# estimate takes 3-6 % longer (the per-edge helpers within stay inlined); the same bytes.

@numba.njit(cache=True, nogil=True)
def ellipsoid_value(p: tuple[float, float, float], s: tuple[float, float, float], q: F64, steps: int
                    ) -> tuple[float, float, float, float, float]:
    """The ellipsoid's tangent box (:func:`_quadric_box`)."""
    return _quadric_box(p, s, q, steps)


@numba.njit(cache=True, nogil=True)
def ellipsoid_grad(p: tuple[float, float, float], la: tuple[float, float, float], c: int, rig: BoxRig,
                   box: F64, grad: F64) -> float:
    """The ellipsoid's tangent box and its derivatives (:func:`_quadric_box_grad`)."""
    return _quadric_box_grad(p, (math.exp(2.0 * la[0]), math.exp(2.0 * la[1]), math.exp(2.0 * la[2])),
                             c, rig, box, grad)


@numba.njit(cache=True, nogil=True)
def cylinder_value(p: tuple[float, float, float], s: tuple[float, float, float], q: F64, steps: int
                   ) -> tuple[float, float, float, float, float]:
    """The vertical cylinder's box: the union of its two end discs' tangent boxes (the cylinder
    is their convex hull), the discs ``sqrt(s[2])`` above and below the centre along up."""
    h = math.sqrt(s[2])
    u0, u1, u2 = _up(q)
    d = (s[0], s[1], 0.0)
    mg, b0, b1, b2, b3 = _quadric_box((p[0] + h * u0, p[1] + h * u1, p[2] + h * u2), d, q, steps)
    mg2, a0, a1, a2, a3 = _quadric_box((p[0] - h * u0, p[1] - h * u1, p[2] - h * u2), d, q, steps)
    return min(mg, mg2), min(a0, b0), min(a1, b1), max(a2, b2), max(a3, b3)


@numba.njit(cache=True, nogil=True)
def cylinder_grad(p: tuple[float, float, float], la: tuple[float, float, float], c: int, rig: BoxRig,
                  box: F64, grad: F64) -> float:
    """The cylinder's box and its derivatives: each edge is the end disc's that reaches further
    (the derivative of a maximum, exact away from ties); the half-height moves the discs along
    up."""
    q = rig.cam[c]
    h = math.exp(la[2])
    u0, u1, u2 = _up(q)
    d = (math.exp(2.0 * la[0]), math.exp(2.0 * la[1]), 0.0)
    b2 = np.empty(4)
    g2 = np.empty((4, 6))
    mg = _quadric_box_grad((p[0] + h * u0, p[1] + h * u1, p[2] + h * u2), d, c, rig, box, grad)
    mg2 = _quadric_box_grad((p[0] - h * u0, p[1] - h * u1, p[2] - h * u2), d, c, rig, b2, g2)
    if not (mg > 0 and mg2 > 0):
        box[:] = np.nan
        grad[:, :] = np.nan
        return min(mg, mg2)
    for e in range(4):
        top = grad[e, 0] * u0 + grad[e, 1] * u1 + grad[e, 2] * u2
        bot = g2[e, 0] * u0 + g2[e, 1] * u1 + g2[e, 2] * u2
        second = b2[e] < box[e] if e < 2 else b2[e] > box[e]
        if second:
            box[e] = b2[e]
            for j in range(5):
                grad[e, j] = g2[e, j]
            grad[e, 5] = -h * bot
        else:
            grad[e, 5] = h * top
    return min(mg, mg2)


@numba.njit(cache=True, nogil=True)
def pom_value(p: tuple[float, float, float], s: tuple[float, float, float], q: F64, steps: int
              ) -> tuple[float, float, float, float, float]:
    """The occupancy-map rectangle (:func:`_pom_value`) of half-extents ``sqrt(s)``."""
    return _pom_value(p, (math.sqrt(s[0]), math.sqrt(s[1]), math.sqrt(s[2])), q)


@numba.njit(cache=True, nogil=True)
def pom_grad(p: tuple[float, float, float], la: tuple[float, float, float], c: int, rig: BoxRig,
             box: F64, grad: F64) -> float:
    """The occupancy-map rectangle and its derivatives (:func:`_pom_box`)."""
    return _pom_box(p, (math.exp(la[0]), math.exp(la[1]), math.exp(la[2])), rig.cam[c], box, grad, True)


#: Every box model's (value, gradient) pair by its name in :data:`gt3dkit.types.BOX_MODEL_REGISTRY`.
BOX_KERNELS = {"ellipsoid": (ellipsoid_value, ellipsoid_grad), "cylinder": (cylinder_value, cylinder_grad),
               "pom": (pom_value, pom_grad)}


@numba.njit(cache=True, nogil=True)
def pair_box(p: tuple[float, float, float], s: tuple[float, float, float], c: int, rig: BoxRig,
             want: bool, out: F64, n: int) -> float:
    """The box ``out[n, c] (4,)`` (``out (N, C, 4)``) of the solid with centre ``p`` and
    squared semi-axes ``s`` in camera ``c`` (NaN if behind it or not ``want``), by the rig's box
    model's value (:data:`BOX_KERNELS`); returns the margin."""
    q = rig.cam[c]
    if rig.box_model == POM:
        mg, b0, b1, b2, b3 = pom_value(p, s, q, rig.steps)
    elif rig.box_model == CYLINDER:
        mg, b0, b1, b2, b3 = cylinder_value(p, s, q, rig.steps)
    else:
        mg, b0, b1, b2, b3 = ellipsoid_value(p, s, q, rig.steps)
    if not mg > 0 or not want:
        for e in range(4):
            out[n, c, e] = np.nan
        return mg
    out[n, c, 0], out[n, c, 1], out[n, c, 2], out[n, c, 3] = b0, b1, b2, b3
    return mg


@numba.njit(cache=True, nogil=True)
def pair_box_grad(p: tuple[float, float, float], la: tuple[float, float, float], c: int, rig: BoxRig,
                  box: F64, grad: F64) -> float:
    """The box ``box (4,)`` of the solid (:func:`pair_box`) with centre ``p`` and log semi-axes
    ``la`` in camera ``c`` and its derivatives ``grad (4, 6)`` by (centre, log semi-axes), by the
    rig's box model's gradient (:data:`BOX_KERNELS`); NaN if behind it. Returns the margin."""
    if rig.box_model == POM:
        return pom_grad(p, la, c, rig, box, grad)
    if rig.box_model == CYLINDER:
        return cylinder_grad(p, la, c, rig, box, grad)
    return ellipsoid_grad(p, la, c, rig, box, grad)


@numba.njit(cache=True, nogil=True)
def _quadric_box_grad(p: tuple[float, float, float], sq: tuple[float, float, float], c: int, rig: BoxRig,
                      box: F64, grad: F64) -> float:
    """The box ``box (4,)`` of the ellipsoid with centre ``p`` and log semi-axes ``la`` in camera
    ``c`` and its derivatives ``grad (4, 6)`` by (centre, log semi-axes); NaN if behind it.
    Returns the margin.

    Each edge is the outline's extreme along one image direction, at the angle θ* where it
    touches: by the envelope theorem its derivative is the partial one at fixed θ* (exact at
    the extreme; the Newton steps stop within 1e-6 px of it). The chain runs through the
    outline's centre ``m`` and the Cholesky factor ``L`` of its shape, forward mode, one
    parameter direction at a time."""
    s0, s1, s2 = sq
    q = rig.cam[c]
    X0, X1, X2, M00, M11, M22, M01, M02, M12 = _in_camera(p, (s0, s1, s2), q)
    mg = q[_DS] * X2 - math.sqrt(max(M22, 0.0))
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
    for e in range(4):
        ct, st = _edge_angle(e, (m0, m1), (l00, l10, l11), q, rig.steps)
        v = edge_value(e, ct, st, m0, m1, l00, l10, l11, q)
        box[e] = -v if e < 2 else v
        # the distorted point's derivative by the undistorted one, at θ*
        _, _, dxx, dxy, dyy = _lens_jac(m0 + l00 * ct, m1 + l10 * ct + l11 * st, q)
        dyx = dxy
        for j in range(6):
            if j < 3:  # centre: X moves along R's column, M stays
                dX0, dX1, dX2 = q[_R + j], q[_R + 3 + j], q[_R + 6 + j]
                dM00 = dM11 = dM22 = dM01 = dM02 = dM12 = 0.0
            else:  # log semi-axis a: M moves by 2 s_a q_a q_a^T, X stays
                a = j - 3
                sa = 2.0 * (s0 if a == 0 else (s1 if a == 1 else s2))
                dX0 = dX1 = dX2 = 0.0
                qa0, qa1, qa2 = q[_RC + a], q[_RC + 3 + a], q[_RC + 6 + a]
                dM00, dM11, dM22 = sa * qa0 * qa0, sa * qa1 * qa1, sa * qa2 * qa2
                dM01, dM02, dM12 = sa * qa0 * qa1, sa * qa0 * qa2, sa * qa1 * qa2
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
            grad[e, j] = q[_K] * dxd + q[_K + 1] * dyd if e % 2 == 0 else q[_K + 4] * dyd
    return mg


@numba.njit(cache=True, nogil=True)
def box_jacobian(p: F64, rig: BoxRig, box: F64, grad: F64) -> None:
    """The boxes ``box (C, 4)`` of the state ``p (6,)`` (centre, log semi-axes) in every camera of
    ``rig`` and their derivatives ``grad (C, 4, 6)`` (:func:`pair_box_grad`; NaN behind a camera):
    one call where central differences took thirteen box evaluations."""
    for c in range(rig.cam.shape[0]):
        pair_box_grad((p[0], p[1], p[2]), (p[3], p[4], p[5]), c, rig, box[c], grad[c])


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

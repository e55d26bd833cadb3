r"""The tangent box of a projected ellipsoid, batched, with lens distortion.

An ellipsoid with centre ``c``, body rotation ``R_b`` (``world_from_body``) and
semi-axes ``s`` has the dual quadric

.. math::
    Q^* = H \,\mathrm{diag}(s_1^2, s_2^2, s_3^2, -1)\, H^\top,
    \quad H = \begin{bmatrix} R_b & c \\ 0 & 1 \end{bmatrix}.

Through the normalised camera ``P = [R | t]`` its outline is the dual conic
``C* = P Q* P^T = M_c - X_c X_c^T`` with ``M_c = R R_b S^2 R_b^T R^T`` and
``X_c = R c + t`` (Hartley & Zisserman, 2nd ed., eq. 8.5, p. 201). A line ``l`` is
tangent to the outline iff ``l^T C* l = 0``; for the vertical line ``x = u`` this is
a quadratic in ``u`` whose two roots are the box's left and right edges (and the
same for ``y``).

Lens distortion bends the outline, so the extremes of the *distorted* outline are
not the distorted tangent points. We parametrise the outline ellipse as
``p(θ) = m + L [cos θ, sin θ]``, start at the closed-form tangent angle and take
two Newton steps on ``θ`` for the extreme of each distorted pixel coordinate. With
zero distortion the result is the closed form exactly.
"""

from __future__ import annotations

import numpy as np

from gt3dkit.arrays import compiled_arg
from gt3dkit.geom.boxkernel import kernel
from gt3dkit.geom.boxrig import EVERY_CAMERA, BoxCameras, box_cameras
from gt3dkit.geom.camera import Cams
from gt3dkit.threads import run_split
from gt3dkit.types import F64


def outline_ellipse(
    center_world: F64, semi_axes: F64, world_from_body: F64, R: F64, t: F64,
    depth_sign: F64 | float = 1.0,
) -> tuple[F64, F64, F64]:
    """The projected outline of ellipsoids in normalised image coordinates.

    Parameters
    ----------
    center_world : (..., 3) float64, metres
    semi_axes : (..., 3) float64, metres (> 0)
    world_from_body : (3, 3) float64, shared by all ellipsoids
    R, t : (C, 3, 3), (C, 3) ``cam_from_world``

    Returns
    -------
    m : (..., C, 2) float64
        Centre of the outline ellipse (not the projected 3D centre).
    E : (..., C, 2, 2) float64
        Shape matrix: outline = ``{m + E^{1/2} u : |u| = 1}``.
    margin : (..., C) float64
        ``z_c - sqrt(n^T M_c n)``: positive iff the whole ellipsoid is in front of
        the camera (metres). ``m`` and ``E`` are NaN where it is not.
    """
    Rc = R @ world_from_body  # (C,3,3) cam_from_body
    X_c = np.einsum("cij,...j->...ci", R, center_world) + t  # (...,C,3)
    s2 = semi_axes**2
    # M_c = Rc diag(s2) Rc^T, batched over (..., C)
    M_c = np.einsum("cik,...k,cjk->...cij", Rc, s2, Rc)
    Cs = M_c - X_c[..., :, None] * X_c[..., None, :]
    margin = depth_sign * X_c[..., 2] - np.sqrt(np.maximum(M_c[..., 2, 2], 0.0))
    ok = margin > 0
    c33 = np.where(ok, Cs[..., 2, 2], np.nan)
    m = Cs[..., :2, 2] / c33[..., None]
    E = m[..., :, None] * m[..., None, :] - Cs[..., :2, :2] / c33[..., None, None]
    return m, E, margin


def ellipsoid_boxes(
    center_world: F64,
    semi_axes: F64,
    world_from_body: F64,
    K: F64,
    dist: F64,
    R: F64,
    t: F64,
    depth_sign: F64 | float = 1.0,
    newton_steps: int = 2,
    want: np.ndarray | None = None,
) -> tuple[F64, F64]:
    """Tight boxes of ellipsoids in every camera's distorted image (compiled,
    :mod:`gt3dkit.geom.boxkernel`: one loop over (ellipsoid, camera) pairs).

    Parameters
    ----------
    center_world : (..., 3) float64, metres
    semi_axes : (..., 3) float64, metres
    world_from_body : (3, 3) float64
    K, dist, R, t : stacked arrays of ``C`` cameras
    depth_sign : (C,) see :class:`gt3dkit.types.Camera`
    newton_steps : refinement steps along the outline for distortion
    want : broadcastable to ``(..., C)``: compute only these pairs' boxes (the others are NaN;
        margins are computed for all)

    Returns
    -------
    box_xyxy_px : (..., C, 4) float64
        ``xmin, ymin, xmax, ymax``; NaN where the ellipsoid is not wholly in front.
    margin : (..., C) float64
        See :func:`outline_ellipse`.

    The tests hold it to a whole-array numpy formulation of the same mathematics
    (``tests/oracles.py``): boxes inside the image agree within 1e-9 px (the kernel's Newton
    steps use exact derivatives, the reference's central differences).
    """
    return boxes_compiled(center_world, semi_axes, box_cameras(world_from_body, K, dist, R, t, depth_sign),
                          newton_steps, want)


def model_boxes(center_world: F64, semi_axes: F64, cams: Cams, want: np.ndarray | None = None,
                newton_steps: int = 2) -> tuple[F64, F64]:
    """:func:`ellipsoid_boxes` under the cameras' box model (``cams.box_model``,
    :data:`gt3dkit.types.BOX_MODELS`): the same state's ellipsoid tangent box, cylinder box or
    occupancy-map rectangle. Returns ``(..., C, 4)`` boxes and ``(..., C)`` margins (the nearest
    point's depth)."""
    return boxes_compiled(center_world, semi_axes, BoxCameras.of(cams), newton_steps, want)


def covered_fraction(box: F64, depth: F64, depth_tol_m: float = 0.0) -> F64:
    """(N, C) fraction of each box covered by nearer boxes in the same camera: the sum over
    nearer boxes of their overlap (an upper bound of the union), capped at 1. box (N, C, 4)
    px of the N objects of one frame, depth (N, C) distance to the camera (m, NaN unknown);
    objects less than ``depth_tol_m`` farther count as nearer (estimated depths are uncertain
    and bodies have thickness)."""
    x0 = np.maximum(box[:, None, :, 0], box[None, :, :, 0])
    y0 = np.maximum(box[:, None, :, 1], box[None, :, :, 1])
    x1 = np.minimum(box[:, None, :, 2], box[None, :, :, 2])
    y1 = np.minimum(box[:, None, :, 3], box[None, :, :, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)  # (N, N, C)
    area = np.maximum((box[..., 2] - box[..., 0]) * (box[..., 3] - box[..., 1]), 1e-9)
    nearer = depth[None, :, :] < depth[:, None, :] + depth_tol_m  # [i, k]: k is nearer than i
    nearer &= ~np.eye(len(box), dtype=bool)[:, :, None]
    inter = np.where(nearer & np.isfinite(inter), inter, 0.0)
    return np.minimum(inter.sum(axis=1) / area, 1.0)


def cut_by(label: F64, box: F64, depth_label: F64, depth_box: F64, depth_tol_m: float = 0.3,
           margin_px: float = 2.0) -> np.ndarray:
    """Which edges of each label a nearer object could have cut, pair by pair (any broadcastable
    leading shape): the edge lies inside that object's box, more than ``margin_px`` from its sides
    (a negative margin widens the box), where the two boxes share at least half of the label's
    extent across the edge (half its height for a side edge, half its width for the top or
    bottom), and the object is at least ``depth_tol_m`` nearer the camera. ``label (..., C, 4)``
    labelled boxes (px, NaN none), ``box (..., C, 4)`` the other object's extent in each camera,
    ``depth_* (..., C)`` their distances to the camera (m). A person drawn as far as they are
    visible ends where the nearer one begins, so such an edge says where the occluder is, not
    where the person ends. Returns ``(..., C, 4)`` bool (xmin, ymin, xmax, ymax)."""
    with np.errstate(invalid="ignore"):
        over_x = np.minimum(label[..., 2], box[..., 2]) - np.maximum(label[..., 0], box[..., 0])
        over_y = np.minimum(label[..., 3], box[..., 3]) - np.maximum(label[..., 1], box[..., 1])
        tall = over_y >= 0.5 * (label[..., 3] - label[..., 1])
        wide = over_x >= 0.5 * (label[..., 2] - label[..., 0])
        lo, hi = box[..., :2] + margin_px, box[..., 2:] - margin_px  # (.., 2) x, y
        inside = [(lo[..., e % 2] < label[..., e]) & (label[..., e] < hi[..., e % 2]) for e in range(4)]
        nearer = depth_box <= depth_label - depth_tol_m
    cut = np.stack([inside[0] & tall, inside[1] & wide, inside[2] & tall, inside[3] & wide], -1)
    return cut & nearer[..., None]


def cut_edges(label: F64, box: F64, depth: F64, depth_tol_m: float = 0.3, margin_px: float = 2.0
              ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cut_by` among the N objects of one frame, each label against every other object:
    ``label``, ``box (N, C, 4)``, ``depth (N, C)``. Returns ``(N, C, 4)`` bool and ``(N, C)`` the
    nearer object that cuts the most edges of each label (-1: none)."""
    cut = cut_by(label[:, None], box[None, :], depth[:, None], depth[None, :], depth_tol_m, margin_px)
    cut &= ~np.eye(len(label), dtype=bool)[:, :, None, None]  # [i, k, c, e]: label i, object k
    n = cut.sum(axis=-1)  # (N, N, C) edges of label i inside object k's box
    who = np.where(n.max(axis=1) > 0, np.argmax(n, axis=1), -1)
    return np.asarray(cut.any(axis=1)), who


#: pairs per thread below which a call is not split (a thread hand-off costs ~20 us; a pair
#: ~0.3 us)
MIN_PAIRS_PER_THREAD = 256


def boxes_compiled(center_world: F64, semi_axes: F64, cams: BoxCameras, newton_steps: int,
                   want: np.ndarray | None = None) -> tuple[F64, F64]:
    """:func:`gt3dkit.geom.conics.ellipsoid_boxes` for ``(..., 3)`` centres and semi-axes in the
    cameras ``cams`` (:func:`box_cameras`; their box model): ``(..., C, 4)`` boxes and ``(..., C)``
    margins (numba compiles the kernel on first use and caches it on disk). ``want``
    (broadcastable to ``(..., C)``): the pairs whose box is needed (the others are NaN; the margin
    is computed for every pair). Large calls are split over threads
    (:func:`gt3dkit.threads.run_split`)."""
    c, s = np.broadcast_arrays(np.asarray(center_world, dtype=np.float64),
                               np.asarray(semi_axes, dtype=np.float64))
    lead = c.shape[:-1]
    C = cams.K.shape[0]
    cf = compiled_arg(c.reshape(-1, 3))
    sf = compiled_arg(s.reshape(-1, 3))
    N = cf.shape[0]
    wf = EVERY_CAMERA if want is None else compiled_arg(np.broadcast_to(np.asarray(want, dtype=np.bool_),
                                                          lead + (C,)).reshape(N, C), np.bool_)
    box = np.empty((N, C, 4))
    margin = np.empty((N, C))
    every = wf is EVERY_CAMERA

    def part(a: int, b: int) -> None:
        kernel(cf[a:b], sf[a:b], cams, int(newton_steps), wf if every else wf[a:b], box[a:b], margin[a:b])

    per = max(MIN_PAIRS_PER_THREAD // max(C, 1), 1)
    if N < 2 * per:
        part(0, N)  # too small to split: no thread policy to consult
    else:
        run_split(part, N, per)
    return box.reshape(lead + (C, 4)), margin.reshape(lead + (C,))

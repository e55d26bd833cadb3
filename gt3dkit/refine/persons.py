"""People's detections as the rig-from-people and clock searches read them: each detection's joints
as rays (normalised image coordinates), the candidate pairs of two cameras' detections in one
frame, and the epipolar distances between them (:mod:`gt3dkit.refine.people`,
:mod:`gt3dkit.refine.clocks`)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from gt3dkit.geom.triangulate import normalized_points
from gt3dkit.rig import Rig
from gt3dkit.types import F64, I64


@dataclass(frozen=True)
class PersonViews:
    """Every detection's joints, ``N`` detections of ``J`` joints: ``xy (N, J, 2)`` undistorted
    normalised coordinates, ``ok (N, J)`` used, ``cam``, ``frame`` (N,), ``uv (N, J, 2)`` px,
    ``mirror (J,)`` the joint index with left and right swapped, ``f_px (C,)`` focal lengths."""

    xy: F64
    ok: np.ndarray
    cam: I64
    frame: I64
    uv: F64
    mirror: I64
    f_px: F64


def normalised(pv: PersonViews, rig: Rig) -> F64:
    """(N, J, 2) the detections' joints through ``rig``'s intrinsics (NaN where not used)."""
    xy = normalized_points(pv.uv, rig.K[pv.cam][:, None], rig.dist[pv.cam][:, None])
    return np.where(pv.ok[..., None], xy, np.nan)


def sampson_px(E: F64, x1: F64, x2: F64, f_px: float) -> F64:
    """Sampson distances (px, through focal ``f_px``) of normalised pairs ``x1, x2 (..., 2)``
    under the essential matrix ``E (3, 3)`` (``x2^T E x1 = 0``)."""
    h1 = np.concatenate([x1, np.ones(x1.shape[:-1] + (1,))], -1)
    h2 = np.concatenate([x2, np.ones(x2.shape[:-1] + (1,))], -1)
    Ex1, Etx2 = h1 @ E.T, h2 @ E
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.abs(np.sum(h2 * Ex1, -1)) / np.sqrt(Ex1[..., 0] ** 2 + Ex1[..., 1] ** 2
                                                   + Etx2[..., 0] ** 2 + Etx2[..., 1] ** 2)
    return d * f_px


def candidates(pv: PersonViews, a: int, b: int) -> I64:
    """(P, 2) detection pairs of cameras ``a`` and ``b`` in one frame sharing 8 or more joints."""
    ia, ib = np.flatnonzero(pv.cam == a), np.flatnonzero(pv.cam == b)
    fa, fb = pv.frame[ia], pv.frame[ib]
    order = np.argsort(fb, kind="stable")
    lo, hi = np.searchsorted(fb[order], fa, "left"), np.searchsorted(fb[order], fa, "right")
    rows = [(i, ib[order[k]]) for i, s, e in zip(ia, lo, hi, strict=True) for k in range(s, e)]
    if not rows:
        return np.zeros((0, 2), np.int64)
    P = np.array(rows, dtype=np.int64)
    shared = np.maximum((pv.ok[P[:, 0]] & pv.ok[P[:, 1]]).sum(1),
                        (pv.ok[P[:, 0]] & pv.ok[P[:, 1]][:, pv.mirror]).sum(1))
    return P[shared >= 8]


def pair_errors(pv: PersonViews, E: F64, P: I64, f_px: float) -> tuple[F64, np.ndarray]:
    """Per candidate pair the median Sampson distance (px) in its better reading, and whether
    that reading swaps ``b``'s left and right."""
    x1, x2 = pv.xy[P[:, 0]], pv.xy[P[:, 1]]
    with np.errstate(all="ignore"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            e = np.nanmedian(sampson_px(E, x1, x2, f_px), axis=1)
            em = np.nanmedian(sampson_px(E, x1, x2[:, pv.mirror], f_px), axis=1)
    e, em = np.nan_to_num(e, nan=np.inf), np.nan_to_num(em, nan=np.inf)
    return np.minimum(e, em), em < e


def signed_px(E: F64, x1: F64, x2: F64, f_px: float) -> F64:
    """The signed Sampson distance (px) of normalised pairs ``x1, x2 (..., 2)`` (:func:`sampson_px`
    with the sign of ``x2^T E x1``)."""
    h1 = np.concatenate([x1, np.ones(x1.shape[:-1] + (1,))], -1)
    h2 = np.concatenate([x2, np.ones(x2.shape[:-1] + (1,))], -1)
    Ex1, Etx2 = h1 @ E.T, h2 @ E
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sum(h2 * Ex1, -1) / np.sqrt(Ex1[..., 0] ** 2 + Ex1[..., 1] ** 2 + Etx2[..., 0] ** 2
                                              + Etx2[..., 1] ** 2) * f_px




def essential(rig: Rig, a: int, b: int) -> F64:
    """(3, 3) the essential matrix of cameras ``a`` and ``b`` of ``rig`` (``x_b^T E x_a = 0`` for
    their normalised coordinates): ``[t]_x R`` of ``b``'s pose relative to ``a``'s."""
    R = rig.R[b] @ rig.R[a].T
    t = rig.t[b] - R @ rig.t[a]
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R

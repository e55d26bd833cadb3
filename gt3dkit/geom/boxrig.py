"""The cameras of the compiled box kernels (:mod:`gt3dkit.geom.boxkernel`): the stacked camera
arrays (:class:`BoxCameras`) and the rig a kernel reads them from, one row per camera
(:class:`BoxRig`, its offsets ``ROW_*``)."""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from gt3dkit.arrays import compiled_arg
from gt3dkit.geom.camera import FISHEYE, LENS_COL, Cams
from gt3dkit.geom.kernel_cache import drop_stale
from gt3dkit.types import F64

drop_stale()  # before any compiled function below is called (and its cache read)


class BoxCameras(NamedTuple):
    """The camera arrays the compiled tangent box needs (contiguous float64): ``world_from_body
    (3, 3)``, ``K (C, 3, 3)``, ``dist (C, 6)`` (the lens, :func:`gt3dkit.geom.camera.distort`),
    ``R (C, 3, 3)``, ``t (C, 3)``, ``depth_sign (C,)``."""

    world_from_body: F64
    K: F64
    dist: F64
    R: F64
    t: F64
    depth_sign: F64
    box_model: int = 0  # BoxModelEntry.index (gt3dkit.types.BOX_MODEL_REGISTRY)

    @classmethod
    def of(cls, cams: Cams) -> BoxCameras:
        """Of a :class:`gt3dkit.geom.camera.Cams` (its box model)."""
        return box_cameras(cams.world_from_body, cams.K, cams.dist, cams.R, cams.t, cams.depth_sign,
                           cams.box_model)


#: Offsets in a row of :attr:`BoxRig.cam` (one camera): ``R`` (9, row-major), ``t`` (3), ``Rc = R Rb``
#: (9), ``K``'s ``K00, K01, K02, K10, K11, K12``, the distortion ``k1, k2, p1, p2, k3`` (a fisheye's
#: ``k1, k2, k3, k4, 0``), the four edge directions ``A^T dir`` as ``gx`` (4) and ``gy`` (4) (``A =
#: K[:2, :2]``), the depth sign, whether the lens distorts (1.0 / 0.0), the lens model's code
#: (:data:`gt3dkit.geom.camera.FISHEYE` or pinhole).
ROW_R, ROW_T, ROW_RC, ROW_K, ROW_DIST, ROW_GX, ROW_GY, ROW_DS, ROW_HASD, ROW_LENS = (
    0, 9, 12, 21, 27, 32, 36, 40, 41, 42)
CAM_WIDTH = 43


class BoxRig(NamedTuple):
    """:class:`BoxCameras` prepared for :func:`gt3dkit.geom.boxkernel.pair_box` (:func:`box_rig`):
    one row per camera ``cam (C, CAM_WIDTH)`` (the offsets above: a pair reads its camera from
    one row), and the Newton ``steps`` along the outline with distortion."""

    cam: F64
    steps: int
    box_model: int  # BoxModelEntry.index (gt3dkit.types.BOX_MODEL_REGISTRY)


@numba.njit(cache=True, nogil=True)
def box_rig(cams: BoxCameras, steps: int) -> BoxRig:
    """The :class:`BoxRig` of ``cams``, shared by every pair of :func:`gt3dkit.geom.boxkernel.pair_box`."""
    K, R, Rb, dist = cams.K, cams.R, cams.world_from_body, cams.dist
    C = K.shape[0]
    out = np.zeros((C, CAM_WIDTH))
    for c in range(C):
        q = out[c]
        for i in range(3):
            q[ROW_T + i] = cams.t[c, i]
            for j in range(3):
                q[ROW_R + 3 * i + j] = R[c, i, j]
                q[ROW_RC + 3 * i + j] = R[c, i, 0] * Rb[0, j] + R[c, i, 1] * Rb[1, j] + R[c, i, 2] * Rb[2, j]
        q[ROW_K], q[ROW_K + 1], q[ROW_K + 2] = K[c, 0, 0], K[c, 0, 1], K[c, 0, 2]
        q[ROW_K + 3], q[ROW_K + 4], q[ROW_K + 5] = K[c, 1, 0], K[c, 1, 1], K[c, 1, 2]
        has = False
        for i in range(5):
            q[ROW_DIST + i] = dist[c, i]
            has = has or dist[c, i] != 0
        if dist.shape[1] > LENS_COL:
            q[ROW_LENS] = dist[c, LENS_COL]
            has = has or dist[c, LENS_COL] == FISHEYE  # an equidistant lens bends every ray
        q[ROW_GX], q[ROW_GY] = -K[c, 0, 0], -K[c, 0, 1]
        q[ROW_GX + 1], q[ROW_GY + 1] = -K[c, 1, 0], -K[c, 1, 1]
        q[ROW_GX + 2], q[ROW_GY + 2] = K[c, 0, 0], K[c, 0, 1]
        q[ROW_GX + 3], q[ROW_GY + 3] = K[c, 1, 0], K[c, 1, 1]
        q[ROW_DS] = cams.depth_sign[c]
        q[ROW_HASD] = 1.0 if has else 0.0
    return BoxRig(out, steps, cams.box_model)


EVERY_CAMERA = np.ones((1, 1), dtype=np.bool_)


def box_cameras(world_from_body: F64, K: F64, dist: F64, R: F64, t: F64, depth_sign: F64 | float,
                box_model: int = 0) -> BoxCameras:
    """:class:`BoxCameras` of stacked camera arrays (``depth_sign`` broadcast to ``(C,)``)."""
    ds = compiled_arg(np.broadcast_to(np.asarray(depth_sign, dtype=np.float64), (K.shape[0],)))
    return BoxCameras(compiled_arg(world_from_body), compiled_arg(K), compiled_arg(dist), compiled_arg(R),
                      compiled_arg(t), ds, int(box_model))

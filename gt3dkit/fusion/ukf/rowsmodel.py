"""What the compiled filters (:mod:`gt3dkit.fusion.ukf.boxupdate`, :mod:`gt3dkit.fusion.ukf.jointupdate`)
read of a model of the rows, and the box update's own bundle of it: the contract between the
model (:class:`gt3dkit.fusion.ukf.measurement.Model`, which builds on the filters) and them."""

from __future__ import annotations

from dataclasses import Field
from typing import Any, ClassVar, NamedTuple, Protocol

import numpy as np

from gt3dkit.fusion.motion import StateLayout
from gt3dkit.fusion.preparation.robust import RobustConfig
from gt3dkit.fusion.preparation.rows import Rows
from gt3dkit.fusion.ukf.bones import JointInfo
from gt3dkit.fusion.ukf.update import Columns
from gt3dkit.geom.boxrig import BoxRig
from gt3dkit.geom.camera import Cams
from gt3dkit.types import F64, I64

#: Newton steps along the outline with lens distortion (:func:`gt3dkit.geom.boxkernel.pair_box`).
OUTLINE_STEPS = 2


class BoxSigma(NamedTuple):
    """The sigma-point rule of the ellipsoid's marginal: its state entries ``dims (6,)`` (centre,
    log semi-axes; ``(9,)`` with the velocity between, for views off their rows' times), the
    weights ``Wm, Wc`` (without the centre point where the rule gives it no weight) and the
    points' ``scale``."""

    dims: I64
    Wm: F64
    Wc: F64
    scale: float


class BoxModel(NamedTuple):
    """Everything the box update needs besides the rows: the sigma rule, the cameras prepared,
    the measurement vector's :class:`gt3dkit.fusion.ukf.update.Columns`, the box's first column, the
    iterated update's passes (at most), whether it reweights, and when each row's views were taken
    ``seen_s (R, C)``, seconds after the row's time (``(0, C)``: at it)."""

    sigma: BoxSigma
    rig: BoxRig
    cols: Columns
    at: int
    iterations: int
    robust: bool
    seen_s: F64


class RowsModel(Protocol):
    """What the compiled filters read of a model of the rows: the fields and methods of
    :class:`gt3dkit.fusion.ukf.measurement.Model` (which builds on this module, so is named here by
    its shape), and of the boxes-only part of one (:func:`gt3dkit.fusion.ukf.jointupdate.boxes_part`)."""

    __dataclass_fields__: ClassVar[dict[str, Field[Any]]]  # a dataclass: dataclasses.replace works on it
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
    centre_determined: np.ndarray
    kpt_cov_frame: F64 | None
    joint_info: JointInfo | None

    @property
    def frame_centre_trace(self) -> F64: ...

    @property
    def box_rig(self) -> BoxRig: ...

    @property
    def n_box_columns(self) -> int: ...

    def box_measurement(self, alpha: float, beta: float, kappa: float,
                        robust: RobustConfig | None, seen_s: F64 | None = None) -> BoxModel: ...

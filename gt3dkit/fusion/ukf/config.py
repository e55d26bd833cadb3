"""The settings of the UKF (:class:`UKFConfig`): one frozen value, validated at construction,
read by the filter (:mod:`gt3dkit.fusion.ukf.filtering`), the noise search (:mod:`gt3dkit.fusion.ukf.noise`)
and the estimator (:mod:`gt3dkit.fusion.ukf.smoother`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import TypeAlias

import numpy as np

from gt3dkit.fusion.preparation.robust import RobustConfig
from gt3dkit.types import F64

#: Process noise given per row instead of ``UKFConfig``'s (the noise search's values): by the
#: config field's name, ``(R,)`` or one value for every row (None: the config's).
NoiseRows: TypeAlias = Mapping[str, F64 | float | None]


@dataclass(frozen=True)
class UKFConfig:
    """Settings of :class:`UKFSmoother` (units in the names). ``None`` = from the data.

    sigma_px : box-edge noise; ``None`` = robust residual level of the per-frame fits
    accel_sd : white-acceleration noise of the centre, m/s^2/sqrt(Hz); ``None`` = maximum
        likelihood of the forward pass within ``accel_bounds``
    position_sd : random walk of the centre's position on top of it, m/sqrt(s)
        (:mod:`gt3dkit.fusion.motion`: labels placed frame by frame depart from a smooth path);
        ``None`` = maximum likelihood within ``position_bounds`` (boxes; 0 without boxes)
    vertical_ratio : the vertical acceleration noise is this times ``accel_sd``
    shape_sd : random-walk noise of the log semi-axes, 1/sqrt(s); ``None`` = maximum
        likelihood within ``shape_bounds``
    kpt_sigma_px : keypoint noise (all joints); ``None`` = per joint, from the data
    joint_accel_sd : white-acceleration noise of the joints; ``None`` = maximum likelihood
        within ``joint_accel_bounds``
    robust : down-weight / reject measurements the other views disagree with
    huber_p, reject_p : tail probabilities where down-weighting starts / rejection is total
    cut_variance_ratio : boxes: a kind of edge cut by nearer objects is left out when it varies
        this many times as much as the kind's other edges (:mod:`gt3dkit.fusion.preparation.occlusion`)
    bones : tie each person's bone lengths together (messages from the first pass's joints to
        the final pass, :mod:`gt3dkit.fusion.ukf.bones`)
    bone_sd_m : sd of a bone's length about its fitted value; ``None`` = the spread of that
        bone's length over the first pass, at least ``bone_sd_floor_m``
    init_vel_sd_mps : initial velocity sd; init_canon_sd_m : initial sd of a joint placed
        from the canonical pose (no two views agree on it in the object's first frame): half a
        person's height, since the pose is scaled from the joints the frame did place (a knee
        placed from a head and shoulders was 0.85 m off; at 0.15 m its first views faded the
        prediction, velocity too, and the joint's filter diverged)
    clip_tol_px : edges this close to the image border count as clipped
    iterations : passes of the iterated, reweighted update
    inflate : inflate covariances by the NIS per degree of freedom when above 1
    smooth : run the backward RTS pass
    search_linearised : boxes only: the noise search's passes use the boxes' regression about the
        provisional smoothed estimate, fixed per row (:class:`gt3dkit.fusion.ukf.noise.LinearisedSearch`,
        a linear filter per value); ``False``: each pass re-linearises at every prediction
    """

    sigma_px: float | None = None
    accel_sd: float | None = None
    accel_bounds: tuple[float, float] = (0.01, 100.0)
    position_sd: float | None = None
    position_bounds: tuple[float, float] = (1e-3, 1.0)
    vertical_ratio: float = 0.1
    shape_sd: float | None = None
    shape_bounds: tuple[float, float] = (1e-5, 0.3)
    kpt_sigma_px: float | None = None
    joint_accel_sd: float | None = None
    joint_accel_bounds: tuple[float, float] = (0.03, 100.0)
    robust: bool = True
    huber_p: float = 1e-4
    reject_p: float = 1e-7
    cut_variance_ratio: float = 2.5
    bones: bool = True
    bone_sd_m: float | None = None
    bone_sd_floor_m: float = 0.001
    init_vel_sd_mps: float = 1.5
    init_canon_sd_m: float = 0.5
    alpha: float = 1.0
    beta: float = 0.0
    kappa: float = 0.0
    clip_tol_px: float = 1.0
    iterations: int = 4
    inflate: bool = True
    smooth: bool = True
    search_linearised: bool = True

    def chosen(self, name: str) -> float:
        """The noise level ``name`` (a field), once chosen (the noise search sets every one it
        searched: :func:`gt3dkit.fusion.ukf.noise.noise_by_likelihood`); ValueError while it
        is still ``None``."""
        v = getattr(self, name)
        if v is None:
            raise ValueError(f"{name} has not been chosen")
        return float(v)

    def __post_init__(self) -> None:
        for k, v in asdict(self).items():
            if isinstance(v, float) and not np.isfinite(v):
                raise ValueError(f"UKFConfig.{k} must be finite, got {v}")
        for k in ("sigma_px", "kpt_sigma_px", "bone_sd_m", "accel_sd", "shape_sd",
                  "joint_accel_sd", "position_sd"):
            v = getattr(self, k)
            if v is not None and v <= 0:
                raise ValueError(f"UKFConfig.{k} must be positive, got {v}")
        for k in ("accel_bounds", "shape_bounds", "joint_accel_bounds", "position_bounds"):
            lo, hi = getattr(self, k)
            if not 0 < lo < hi:
                raise ValueError(f"UKFConfig.{k} must be 0 < lo < hi, got {(lo, hi)}")
        if self.iterations < 1:
            raise ValueError("UKFConfig.iterations must be >= 1")
        RobustConfig(self.huber_p, self.reject_p, cut_variance_ratio=self.cut_variance_ratio)

    @property
    def robust_config(self) -> RobustConfig:
        return RobustConfig(self.huber_p, self.reject_p, enabled=self.robust,
                            cut_variance_ratio=self.cut_variance_ratio)

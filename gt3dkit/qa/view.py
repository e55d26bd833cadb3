"""What the annotation QA reads of a prepared scene: a small typed view, so that QA depends on
these names and types, not on the estimators' internals (``gt3dkit.fusion.preparation.prepare.Prepared`` and
``gt3dkit.fusion.preparation.rows.Rows`` are one, structurally; the layers keep QA independent of fusion)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from gt3dkit.geom.camera import Cams
from gt3dkit.skeletons import Skeleton
from gt3dkit.types import F64, I64


@runtime_checkable
class RowsView(Protocol):
    """The object-frames of a scene: ``R`` rows, each an object at a frame, ``C`` cameras."""

    def __len__(self) -> int: ...  # R

    @property
    def frames(self) -> I64: ...  # (T,) the frame numbers

    @property
    def row_t(self) -> I64: ...  # (R,) each row's index into ``frames``

    @property
    def row_o(self) -> I64: ...  # (R,) each row's index into ``obj_ids``

    @property
    def obj_ids(self) -> I64: ...  # (O,) the objects' ids

    @property
    def obs_row(self) -> I64: ...  # (R, C) the observation of each row and camera (-1: none)

    @property
    def n_views(self) -> I64: ...  # (R,) cameras with an annotation

    @property
    def box_z(self) -> F64: ...  # (R, C, 4) box edges, px (NaN: none)

    @property
    def box_mask(self) -> np.ndarray: ...  # (R, C, 4) edges that measure (not clipped)

    @property
    def kpt_z(self) -> F64: ...  # (R, C, J, 2) keypoints, px (NaN: none)


@runtime_checkable
class PreparedView(Protocol):
    """A prepared scene: its rows, cameras, which measurements it has and their noise levels."""

    @property
    def rows(self) -> RowsView: ...

    @property
    def cams(self) -> Cams: ...

    @property
    def use_box(self) -> bool: ...

    @property
    def use_kpt(self) -> bool: ...

    @property
    def sigma_box(self) -> F64: ...  # (4,) box-edge noise per edge kind, px

    @property
    def box_tail(self) -> float: ...  # the misfit tails' variance ratio of the box edges

    @property
    def kpt_var(self) -> F64: ...  # (R, C, J) each keypoint's variance, px^2

    @property
    def box_cut(self) -> np.ndarray | None: ...  # (R, C, 4) edges a nearer object cut, left out

    @property
    def box_cut_by(self) -> np.ndarray | None: ...  # (R, C, 4) the row of a nearer object each lies in

    @property
    def skeleton(self) -> Skeleton | None: ...  # the joints' skeleton (None without keypoints)


class SplitView(Protocol):
    """Where an id was split (``gt3dkit.fusion.preparation.identity.Split``): between frames
    ``frame_before`` and ``frame_after`` its views jump ``distance_m`` (``speed_mps``, more than
    ``limit_m``); ``segment``: the piece from there on; ``given``: a piece boundary the
    corrections file sets."""

    @property
    def track_id(self) -> int: ...

    @property
    def segment(self) -> int: ...

    @property
    def frame_before(self) -> int: ...

    @property
    def frame_after(self) -> int: ...

    @property
    def distance_m(self) -> float: ...

    @property
    def speed_mps(self) -> float: ...

    @property
    def views_before(self) -> int: ...

    @property
    def views_after(self) -> int: ...

    @property
    def limit_m(self) -> float: ...

    @property
    def given(self) -> bool: ...


class ExchangeView(Protocol):
    """Two ids whose labels were exchanged at ``frame`` (``gt3dkit.fusion.preparation.identity.Exchange``):
    each one's views ``distance_m`` from where it was, the other where it was."""

    @property
    def frame(self) -> int: ...

    @property
    def track_id(self) -> int: ...

    @property
    def other_id(self) -> int: ...

    @property
    def distance_m(self) -> tuple[float, float]: ...

    @property
    def views(self) -> tuple[int, int]: ...

"""What a preparation found, typed (:class:`PreparationSummary`, ``Prepared.info``): the noise levels
and what was left out, per measurement kind, as ``meta.json``'s ``preparation`` writes them."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from gt3dkit.types import JsonDict


@dataclass(frozen=True)
class BoxLevels:
    """What the boxes' preparation found (``meta.json``: ``preparation.boxes``): the box model and
    each model's median residual (px), the edges' noise (``sigma_px`` the whole level,
    ``sigma_px_core`` the typical edge's, their variance ratio, per edge kind) and its source, the
    edges rejected and usable, the cut edges (:class:`gt3dkit.fusion.preparation.occlusion.CutEdges`)
    and the shape prior."""

    box_model: str
    box_model_median_residual_px: dict[str, float]
    sigma_px: float
    sigma_px_core: float
    tail_variance_ratio: float
    sigma_px_per_edge_kind: dict[str, float]
    sigma_source: str
    edges_rejected_per_frame: int
    cut_edges: JsonDict | None
    edges_usable: int
    shape_prior: JsonDict
    crowd: JsonDict | None = None  # the crowding bands' levels (gt3dkit.fusion.preparation.crowd)


@dataclass(frozen=True)
class KeypointLevels:
    """What the keypoints' preparation found (``meta.json``: ``preparation.keypoints``): the
    noise (px: the whole level, per joint) and its source, the points seen and rejected, and the
    confidence curve (:class:`gt3dkit.fusion.preparation.confidence.ConfidenceCurve`)."""

    sigma_px: float
    sigma_px_per_joint: list[float]
    sigma_source: str
    points: int
    points_rejected_per_frame: int
    confidence: JsonDict | str


@dataclass(frozen=True)
class PreparationSummary:
    """What a preparation found, by measurement kind (None: the scene has none of it)."""

    boxes: BoxLevels | None = None
    keypoints: KeypointLevels | None = None

    def as_json(self) -> JsonDict:
        """``meta.json``'s ``preparation``: each kind the scene has, by its fields."""
        return {k: asdict(v) for k, v in (("boxes", self.boxes), ("keypoints", self.keypoints))
                if v is not None}

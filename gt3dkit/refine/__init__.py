"""Checks and refinement of a rig against the annotations (``gt3d calib show`` with an input,
``gt3d calib refine``, ``gt3d reconstruct --refine-calib``): keypoints by pycolmap bundle
adjustment (:mod:`.keypoints`), boxes through the tangent-box model (:mod:`.boxes`), both
validated on held-out time blocks (:mod:`.common`). Above :mod:`gt3dkit.fusion` (they use its
per-frame fits), apart from :mod:`gt3dkit.calib` (camera model and formats, below the readers)."""

from gt3dkit.refine.checks import scene_warnings
from gt3dkit.refine.common import RefineConfig, RefineResult, align_to, pose_change, rig_digest, transform_rig
from gt3dkit.refine.keypoints import refine

__all__ = ["RefineConfig", "RefineResult", "align_to", "pose_change", "refine", "rig_digest",
           "scene_warnings", "transform_rig"]

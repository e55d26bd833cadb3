"""Seeded synthetic scenes with known truth, written in any input layout.

People are vertical ellipsoids standing on the ground (centre height = vertical
semi-axis) walking smooth paths (a straight line plus a slow sinusoid) over a
rectangle seen by a ring of cameras with mild lens distortion. Each person is
annotated from a random first to a random last frame. Boxes are the exact
boxes of the people (:func:`gt3dkit.geom.conics.model_boxes`: tangent boxes of their ellipsoids),
plus Gaussian noise on every edge, clipped to the image and rounded to whole
pixels (truncated towards zero for the MultiviewX layout, as its generator does);
a view is dropped at random with probability ``Errors.dropped``.

Realistic annotation and detector errors (:class:`Errors`) are injected with a random
stream of their own, so a scene with errors has exactly the same noise as the same seed
without them: far-off keypoints, left/right swaps of single joints, glitches (a zero
coordinate with a high confidence), shifted boxes, a time gap with no annotation at all,
people seen by one camera only. Every injected error is listed (``injected.csv`` beside
``truth.csv``) so that tests check both the estimate and what was flagged.

``motion="walk"`` replaces the smooth paths by real-trajectory-like walking: speed and
heading wander (Ornstein-Uhlenbeck), people turn, slow down and keep inside the area.
"""

from gt3dkit.sim.boxes import make_rig, simulate, write_scene
from gt3dkit.sim.common import (
    DROPPED_KEYPOINTS,
    DROPPED_VIEWS,
    INJECTED_COLUMNS,
    POSITION_GRID_M,
    SIM_LAYOUTS,
    WRITE_LAYOUTS,
    Errors,
)
from gt3dkit.sim.skeletons import (
    Q_ZUP,
    detector_errors,
    make_dome,
    simulate_skeletons,
    skeleton_motion,
    to_z_up,
    write_coco,
    write_openpose,
    write_skeleton_scene,
)

__all__ = ["DROPPED_KEYPOINTS", "DROPPED_VIEWS", "INJECTED_COLUMNS", "POSITION_GRID_M", "Q_ZUP",
           "SIM_LAYOUTS", "WRITE_LAYOUTS", "Errors", "detector_errors", "make_dome", "make_rig", "simulate",
           "simulate_skeletons", "skeleton_motion", "to_z_up", "write_coco", "write_openpose",
           "write_scene", "write_skeleton_scene"]

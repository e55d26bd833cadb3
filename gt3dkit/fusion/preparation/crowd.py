"""Box-edge noise that grows with how crowded a view is.

A detector's box of a person among others is less sure of its edges than one of a person
standing alone: parts of the neighbours creep in, the person's own parts are hidden, and where
boxes merge an edge lands on a neighbour. :func:`crowd_levels` measures each label's crowding as
the share of its area that the other labels of its camera and frame cover (:func:`covered_share`),
and learns from the per-frame fits' residuals, per edge kind and crowding band
(:data:`CROWD_BANDS`), how much more the edges of crowded labels vary than those of the least
varying band, as the other noise levels are learned
(:func:`gt3dkit.fusion.preparation.confidence.group_variances`). The filters then weight each
edge by its band's level over the typical edge's. Where the labels are shapes placed in the
world (WILDTRACK's and MultiviewX's: their bands vary within 1.3x of each other) every edge keeps
the one level: the bands' levels are used only where one varies at least
:data:`CROWD_RATIO_NEEDED` times as much as the least varying band of its kind.

On CMC3's real detector boxes (up to 15 people, 4 cameras) the crowded bands vary 1.7-2.1x the
least crowded one and the UKF's ground error went from 144.3 to 138.7 mm (CMC1, 3 people: 71.2
mm, its p95 129.9 -> 129.8 mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gt3dkit.fusion.preparation.confidence import group_variances
from gt3dkit.fusion.preparation.occlusion import same_frame_pairs
from gt3dkit.fusion.preparation.rows import Rows
from gt3dkit.types import B8, BOX_EDGES, F64, I64, JsonDict

#: Lower bounds of the crowding bands: the share of a label's area the other labels cover.
CROWD_BANDS = (0.0, 0.25, 0.5, 0.75)
#: Edges a band and kind needs for a level of its own.
CROWD_MIN_EDGES = 100
#: A band varying this many times the least varying one of its kind makes the bands' levels used.
CROWD_RATIO_NEEDED = 1.5


def covered_share(rows: Rows) -> F64:
    """``(R, C)`` the share of each label's area (``rows.box_z``) that the other labels of its
    frame and camera cover (the sum of their overlaps, at most 1; NaN where no label)."""
    box = rows.box_z
    area = np.clip(box[..., 2] - box[..., 0], 0, None) * np.clip(box[..., 3] - box[..., 1], 0, None)
    covered = np.zeros(area.shape)
    a, b = same_frame_pairs(rows.row_t)
    if len(a):
        w = np.clip(np.minimum(box[a, :, 2], box[b, :, 2]) - np.maximum(box[a, :, 0], box[b, :, 0]), 0, None)
        h = np.clip(np.minimum(box[a, :, 3], box[b, :, 3]) - np.maximum(box[a, :, 1], box[b, :, 1]), 0, None)
        inter = np.nan_to_num(w * h)
        np.add.at(covered, a, inter)
        np.add.at(covered, b, inter)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.clip(covered / area, 0.0, 1.0)
    return np.where(np.isfinite(box).all(axis=-1) & (area > 0), share, np.nan)


def band_of(share: F64) -> I64:
    """Each ``share``'s crowding band (index into :data:`CROWD_BANDS`; 0 where NaN)."""
    return np.clip(np.searchsorted(np.asarray(CROWD_BANDS), np.nan_to_num(share), side="right") - 1,
                   0, len(CROWD_BANDS) - 1)


@dataclass(frozen=True)
class CrowdLevels:
    """Each edge kind's variance in each crowding band over the least varying band's,
    ``ratio (B, 4)`` (1 where a band has too few edges; never below a less crowded band's),
    whether they are used, and each label's band ``band (R, C)``."""

    ratio: F64
    used: bool
    band: I64

    def scale(self) -> F64 | None:
        """``(R, C, 4)`` each edge's variance over the typical edge's; None where not used."""
        return self.ratio[self.band] if self.used else None

    def as_json(self) -> JsonDict:
        return {"bands": list(CROWD_BANDS), "used": self.used,
                "variance_ratio": {k: [round(float(v), 3) for v in self.ratio[:, e]]
                                   for e, k in enumerate(BOX_EDGES)},
                "labels_per_band": np.bincount(self.band.reshape(-1), minlength=len(CROWD_BANDS)).tolist(),
                "rule": "a label's band is the share of its area the other labels of its view cover (from "
                        + ", ".join(f"{b:g}" for b in CROWD_BANDS) + "); an edge's variance is its band's "
                        f"over the least varying band's where a band varies {CROWD_RATIO_NEEDED:g}x as much "
                        f"or more ({CROWD_MIN_EDGES} edges at least)"}


def crowd_levels(rows: Rows, r2: F64, dof: F64, use: B8, reject_p: float) -> CrowdLevels:
    """The crowding bands' levels from the per-frame fits' squared edge residuals ``r2 (R, C,
    4)``, their degrees of freedom ``dof`` and the edges used ``use``."""
    band = band_of(covered_share(rows))
    B = len(CROWD_BANDS)
    group = band[..., None] * 4 + np.arange(4)  # (R, C, 4): band and edge kind
    _, per = group_variances(r2, dof, use, group, B * 4, reject_p, 1, min_points=CROWD_MIN_EDGES)
    counted = (np.bincount(group[use], minlength=B * 4) >= CROWD_MIN_EDGES).reshape(B, 4)
    level = np.where(counted & (per.reshape(B, 4) > 0), per.reshape(B, 4), np.nan)
    least = np.nanmin(np.where(np.isfinite(level), level, np.inf), axis=0)  # (4,)
    ratio = np.where(np.isfinite(level) & np.isfinite(least), level / least, 1.0)
    ratio = np.maximum.accumulate(np.maximum(ratio, 1.0), axis=0)  # crowding never sharpens an edge
    used = bool(np.any(np.isfinite(level)) and ratio.max() >= CROWD_RATIO_NEEDED)
    return CrowdLevels(ratio, used, band)

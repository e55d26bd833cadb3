"""What the simulators share: the layouts they write, the errors they inject (:class:`Errors`)
and their list (``injected.csv``), the rates of views left out, the cameras' aim."""

from __future__ import annotations

import csv
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from gt3dkit.io.datasets import LAYOUTS
from gt3dkit.types import F64, I64, LENSES, Rig

SIM_LAYOUTS = ("wildtrack", "multiviewx", "native")
WRITE_LAYOUTS = tuple(k for k, v in LAYOUTS.items() if v.write_boxes is not None)
INJECTED_COLUMNS = ("frame", "camera", "id", "joint", "kind", "detail")


#: Box views and keypoints left out at random unless :attr:`Errors.dropped` says otherwise.
DROPPED_VIEWS = 0.15
#: WILDTRACK's annotation tool places a person on a ground grid of this pitch (positionID).
POSITION_GRID_M = 0.025
DROPPED_KEYPOINTS = 0.05


@dataclass(frozen=True)
class Errors:
    """Errors real annotators and detectors make, as fractions.

    outliers : keypoints replaced by a point 100-300 px away (confidence 0.2-0.7)
    swaps : person-views in which one left/right joint pair is exchanged
    glitch : keypoints with a zero coordinate (x = 0, or both) at confidence 0.6-0.9
    shifted : boxes moved by 0.3-1.0 of their size (another person's box, a slip)
    gap : ``(a, b)`` frame *indices*: frames ``a..b-1`` carry no annotation at all
    single_view : people whose annotations are kept in one camera only (the one that sees
        them most)
    missing : boxes of people in plain sight (well inside the image, at most 10 % covered by
        people nearer or less than 0.5 m farther) left out, as an annotator who skipped them
        (boxes only)
    time_offset : ``(camera index, frames)``: that camera's boxes show each person ``frames``
        frame steps later than labelled (an unsynchronised camera; boxes only)
    hide_covered : boxes covered by nearer people's boxes by more than this fraction are left
        out, as annotators skip people hidden behind others (None: keep them; boxes only)
    dropped : views (boxes) or keypoints left out at random; None: the generator's default
        (:data:`DROPPED_VIEWS` of the box views, :data:`DROPPED_KEYPOINTS` of the keypoints)
    reused_ids : ids handed on: this many times a person's id goes, from some frame on, to
        another person (who is annotated under it from then on; the first person from then on
        not at all), as real label sets reuse the id of someone who left (boxes only)
    exchanged_ids : this many times two people's ids are exchanged for 1-4 consecutive frames,
        in every view (boxes only)
    occluded : keypoints hidden behind a nearer person in a view (inside the 2-D extent of the
        joints of a person at least 0.3 m nearer the camera) that the detector guesses: moved by
        8-25 px, confidence 0.1-0.5 (keypoints only)
    wrong_person : keypoints taken from another person in the view (the same joint of the
        nearest other person within 300 px), confidence 0.4-0.8 (keypoints only)
    over_one : confident keypoints (confidence above 0.9) whose confidence is 1.0-1.04, as
        OpenPose's heatmap peaks (keypoints only)
    cut_by_nearer : boxes drawn around the visible part of a person, as detectors and annotators
        draw them: where a nearer person's box (at least 0.3 m nearer the camera) covers the
        bottom of a box across most of its width, or one side across most of its height, that
        side ends where the nearer box begins (boxes only)
    noise_by_confidence : the pixel noise of a keypoint grows as its confidence falls, its
        variance ``noise_px^2 (0.92 / conf)^3`` below 0.92 (the law real OpenPose output on
        Shelf follows; keypoints only)

    Both id errors are in the truth as well (as in WILDTRACK, whose positions carry the labels'
    ids): the truth says where each annotated (frame, id) is, not who it is.
    """

    outliers: float = 0.0
    swaps: float = 0.0
    glitch: float = 0.0
    shifted: float = 0.0
    gap: tuple[int, int] | None = None
    single_view: float = 0.0
    missing: float = 0.0
    time_offset: tuple[int, int] | None = None
    hide_covered: float | None = None
    dropped: float | None = None
    reused_ids: int = 0
    exchanged_ids: int = 0
    occluded: float = 0.0
    wrong_person: float = 0.0
    over_one: float = 0.0
    noise_by_confidence: bool = False
    cut_by_nearer: bool = False

    def __post_init__(self) -> None:
        if self.reused_ids < 0 or self.exchanged_ids < 0:
            raise ValueError("reused_ids and exchanged_ids must be >= 0")
        for k in ("hide_covered", "dropped"):
            v = getattr(self, k)
            if v is not None and not 0 <= v < 1:
                raise ValueError(f"{k} must be a fraction in [0, 1), got {v}")
        for k in ("outliers", "swaps", "glitch", "shifted", "single_view", "missing", "occluded",
                  "wrong_person", "over_one"):
            v = getattr(self, k)
            if not 0 <= v <= 1:
                raise ValueError(f"{k} must be a fraction in [0, 1], got {v}")
        if self.gap is not None and not 0 <= self.gap[0] < self.gap[1]:
            raise ValueError(f"gap must be (first, end) frame indices with first < end, got {self.gap}")


def gap_mask(frames: I64, truth_frame: I64, gap: tuple[int, int] | None) -> np.ndarray:
    """(M,) truth rows inside the gap."""
    if gap is None:
        return np.zeros(len(truth_frame), bool)
    inside = frames[gap[0]:gap[1]]
    return np.isin(truth_frame, inside)


def keep_one_view(seen: np.ndarray, truth_id: I64, frac: float, rng: np.random.Generator
                   ) -> tuple[np.ndarray, list[int]]:
    """``seen (M, C)`` with a fraction of people restricted to their most-seen camera."""
    ids = np.unique(truth_id)
    k = int(round(frac * len(ids)))
    chosen = rng.choice(ids, size=k, replace=False) if k else np.zeros(0, dtype=np.int64)
    out = seen.copy()
    for pid in chosen:
        m = truth_id == pid
        best = int(np.argmax(seen[m].sum(axis=0)))
        keep = np.zeros(seen.shape[1], bool)
        keep[best] = True
        out[m] &= keep
    return out, [int(p) for p in chosen]


def write_injected(rows: tuple[tuple[int, str, int, str, str, str], ...], path: Path) -> None:
    """``injected.csv``: every error the simulator put in (``frame`` -1 and ``camera`` empty
    for a whole track)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(INJECTED_COLUMNS)
        w.writerows(rows)


# ---------------------------------------------------------------------------------------
# skeletons


def look_at(center: F64, target: F64) -> tuple[F64, F64]:
    """cam_from_world ``R, t`` of a camera at ``center`` looking at ``target`` (z up)."""
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ center


def with_lens(rig: Rig, lens: str, seed: int) -> Rig:
    """``rig`` with ``lens`` on every camera: ``"pinhole"`` leaves it as it is; ``"fisheye"`` fits
    each camera with a wide lens (OpenCV's fisheye model, 0.45 x its focal length: about 50 % more
    field of view, and equidistant coefficients as fisheye calibrations give), drawn from its own
    generator so that the rest of the scene stays the seed's."""
    if lens not in LENSES:
        raise ValueError(f"lens must be one of {', '.join(LENSES)}, got {lens!r}")
    if lens == "pinhole":
        return rig
    rng = np.random.default_rng([seed, 7])
    cams = []
    for c in rig.cameras:
        K = c.K.copy()
        K[:2, :2] *= 0.45
        k = np.array([rng.uniform(0.0, 0.06), rng.uniform(-0.03, 0.0), rng.uniform(0.0, 0.006), -0.001])
        cams.append(replace(c, K=K, dist=k, lens="fisheye"))
    return replace(rig, cameras=tuple(cams))

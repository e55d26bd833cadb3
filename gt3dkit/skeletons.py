"""Joint orders, bones and a canonical standing pose, named in one place.

* ``coco17``: COCO keypoints (nose, eyes, ears, shoulders, elbows, wrists, hips, knees, ankles).
* ``panoptic15``: CMU Panoptic's 15 body joints (the first 15 of ``coco19``).
* ``coco19``: CMU Panoptic's ``joints19`` order (``hdPose3d_stage1_coco19``).

The canonical pose is a person 1.7 m tall standing upright in the *body* frame
(x to the person's left, y forward, z up, metres, feet at z = 0); the UKF places
it at an ellipsoid's centre, scaled to the ellipsoid, for joints no two views see.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from gt3dkit.types import F64

_CANON = {  # body frame, metres
    "neck": (0.0, 0.0, 1.50), "nose": (0.0, 0.09, 1.62), "pelvis": (0.0, 0.0, 0.95),
    "l_shoulder": (0.18, 0.0, 1.45), "l_elbow": (0.22, 0.0, 1.17), "l_wrist": (0.24, 0.02, 0.92),
    "l_hip": (0.10, 0.0, 0.93), "l_knee": (0.11, 0.02, 0.50), "l_ankle": (0.11, 0.0, 0.08),
    "l_eye": (0.03, 0.08, 1.66), "l_ear": (0.07, 0.0, 1.64),
    "head_top": (0.0, 0.0, 1.74),
    "l_big_toe": (0.12, 0.18, 0.02), "l_small_toe": (0.16, 0.15, 0.02), "l_heel": (0.11, -0.06, 0.03),
}
for _k, (_x, _y, _z) in list(_CANON.items()):
    if _k.startswith("l_"):
        _CANON["r_" + _k[2:]] = (-_x, _y, _z)

_COCO19 = ("neck", "nose", "pelvis", "l_shoulder", "l_elbow", "l_wrist", "l_hip", "l_knee",
           "l_ankle", "r_shoulder", "r_elbow", "r_wrist", "r_hip", "r_knee", "r_ankle",
           "l_eye", "l_ear", "r_eye", "r_ear")
_COCO17 = ("nose", "l_eye", "r_eye", "l_ear", "r_ear", "l_shoulder", "r_shoulder", "l_elbow",
           "r_elbow", "l_wrist", "r_wrist", "l_hip", "r_hip", "l_knee", "r_knee", "l_ankle",
           "r_ankle")
_BONES_BODY = (("neck", "nose"), ("neck", "pelvis"), ("neck", "l_shoulder"),
               ("l_shoulder", "l_elbow"), ("l_elbow", "l_wrist"), ("pelvis", "l_hip"),
               ("l_hip", "l_knee"), ("l_knee", "l_ankle"), ("neck", "r_shoulder"),
               ("r_shoulder", "r_elbow"), ("r_elbow", "r_wrist"), ("pelvis", "r_hip"),
               ("r_hip", "r_knee"), ("r_knee", "r_ankle"))
_BONES_FACE = (("nose", "l_eye"), ("l_eye", "l_ear"), ("nose", "r_eye"), ("r_eye", "r_ear"))
_BONES_COCO17 = (("l_ankle", "l_knee"), ("l_knee", "l_hip"), ("r_ankle", "r_knee"),
                 ("r_knee", "r_hip"), ("l_hip", "r_hip"), ("l_shoulder", "l_hip"),
                 ("r_shoulder", "r_hip"), ("l_shoulder", "r_shoulder"),
                 ("l_shoulder", "l_elbow"), ("r_shoulder", "r_elbow"), ("l_elbow", "l_wrist"),
                 ("r_elbow", "r_wrist"), ("l_eye", "r_eye"), ("nose", "l_eye"),
                 ("nose", "r_eye"), ("l_eye", "l_ear"), ("r_eye", "r_ear"))


# OpenPose / AlphaPose / RTMPose orders (OpenPose's output docs; Pose2Sim's skeletons.py), as
# (our name, the detector's own name): every joint kept, feet and head included.
_OP_NAMES = {"nose": "Nose", "neck": "Neck", "pelvis": "MidHip", "head_top": "Head"}
for _side, _s in (("l", "L"), ("r", "R")):
    for _j, _n in (("shoulder", "Shoulder"), ("elbow", "Elbow"), ("wrist", "Wrist"), ("hip", "Hip"),
                   ("knee", "Knee"), ("ankle", "Ankle"), ("eye", "Eye"), ("ear", "Ear"),
                   ("big_toe", "BigToe"), ("small_toe", "SmallToe"), ("heel", "Heel")):
        _OP_NAMES[f"{_side}_{_j}"] = _s + _n
_BODY25 = ("nose", "neck", "r_shoulder", "r_elbow", "r_wrist", "l_shoulder", "l_elbow", "l_wrist",
           "pelvis", "r_hip", "r_knee", "r_ankle", "l_hip", "l_knee", "l_ankle", "r_eye", "l_eye",
           "r_ear", "l_ear", "l_big_toe", "l_small_toe", "l_heel", "r_big_toe", "r_small_toe", "r_heel")
_COCO18 = _BODY25[:8] + _BODY25[9:19]
_BODY25B = _COCO17 + ("neck", "head_top", "l_big_toe", "l_small_toe", "l_heel", "r_big_toe",
                      "r_small_toe", "r_heel")
_HALPE26 = _COCO17 + ("head_top", "neck", "pelvis", "l_big_toe", "r_big_toe", "l_small_toe",
                      "r_small_toe", "l_heel", "r_heel")
_COCO133_BODY = _COCO17 + ("l_big_toe", "l_small_toe", "l_heel", "r_big_toe", "r_small_toe", "r_heel")
_BONES_FEET = (("l_ankle", "l_big_toe"), ("l_big_toe", "l_small_toe"), ("l_ankle", "l_heel"),
               ("r_ankle", "r_big_toe"), ("r_big_toe", "r_small_toe"), ("r_ankle", "r_heel"))
_BONES_OP = _BONES_BODY + _BONES_FACE
_BONES_COCO18 = tuple(b for b in _BONES_OP if "pelvis" not in b) + (("neck", "l_hip"), ("neck", "r_hip"))
_BONES_25B = tuple(b for b in _BONES_COCO17 if b not in (("l_eye", "r_eye"),)) + (
    ("neck", "l_shoulder"), ("neck", "r_shoulder"), ("neck", "head_top"), ("neck", "nose")) + _BONES_FEET
_BONES_HALPE = _BONES_25B + (("pelvis", "l_hip"), ("pelvis", "r_hip"), ("neck", "pelvis"))


@dataclass(frozen=True)
class Skeleton:
    name: str
    joints: tuple[str, ...]
    bone_names: tuple[tuple[str, str], ...]
    labels: tuple[str, ...] = ()  # the detector's own joint names (marker names on export)
    #: points per person the detector writes when more than ``joints`` (the first
    #: ``n_joints`` are read: COCO-WholeBody's body and feet, not its face and hands); 0: as many
    detector_points: int = 0

    @property
    def marker_names(self) -> tuple[str, ...]:
        """Joint names for exports: the detector's own when it has them."""
        return self.labels or self.joints

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def bones(self) -> np.ndarray:
        """(K, 2) joint indices of the bones."""
        ix = {j: i for i, j in enumerate(self.joints)}
        return np.array([(ix[a], ix[b]) for a, b in self.bone_names], dtype=np.int64)

    def canonical(self) -> F64:
        """(J, 3) canonical standing pose in the body frame (metres, feet at z = 0)."""
        return np.array([_CANON[j] for j in self.joints], dtype=np.float64)


SKELETONS = {
    "coco17": Skeleton("coco17", _COCO17, _BONES_COCO17),
    "panoptic15": Skeleton("panoptic15", _COCO19[:15], _BONES_BODY),
    "coco19": Skeleton("coco19", _COCO19, _BONES_BODY + _BONES_FACE),
    "body25": Skeleton("body25", _BODY25, _BONES_OP + _BONES_FEET, tuple(_OP_NAMES[j] for j in _BODY25)),
    "body25b": Skeleton("body25b", _BODY25B, _BONES_25B,
                        tuple({"neck": "UpperNeck", "head_top": "HeadTop"}.get(j, _OP_NAMES[j])
                              for j in _BODY25B)),
    "coco18": Skeleton("coco18", _COCO18, _BONES_COCO18, tuple(_OP_NAMES[j] for j in _COCO18)),
    "halpe26": Skeleton("halpe26", _HALPE26, _BONES_HALPE,
                        tuple({"pelvis": "Hip"}.get(j, _OP_NAMES[j]) for j in _HALPE26)),
    # COCO-WholeBody (RTMPose's, Pose2Sim's COCO_133): 17 body + 6 feet points, then 68 face and
    # 2 x 21 hand points, 133 in all; the body and the feet are read
    "coco133": Skeleton("coco133", _COCO133_BODY, _BONES_COCO17 + _BONES_FEET,
                        tuple(_OP_NAMES[j] for j in _COCO133_BODY), detector_points=133),
}
#: 2D detector files (OpenPose JSON) name their skeleton by joint count; 25 is BODY_25 or BODY_25B
DETECTOR_SKELETONS = {25: ("body25", "body25b"), 26: ("halpe26",), 18: ("coco18",), 17: ("coco17",),
                      133: ("coco133",)}


def skeleton_for(n_joints_seen: int) -> Skeleton:
    """The smallest skeleton with at least ``n_joints_seen`` joints (max index + 1)."""
    for name in ("panoptic15", "coco17", "coco19"):
        if n_joints_seen <= SKELETONS[name].n_joints:
            return SKELETONS[name]
    raise ValueError(f"no skeleton has {n_joints_seen} joints (known: "
                     f"{', '.join(f'{k} ({v.n_joints})' for k, v in SKELETONS.items())})")


def _norm_joint(name: str) -> str:
    """A joint name in any common spelling (``LEye``, ``left_eye``, ``L_Eye``, ``left eye``) ->
    ours (``l_eye``)."""
    s = re.sub(r"^([LR])(?=[A-Z][a-z])", r"\1_", name.strip())  # OpenPose's LEye, RBigToe
    s = re.sub(r"(?<=[a-z])(?=[A-Z])", "_", s).lower().replace(" ", "_").replace("-", "_")
    s = re.sub(r"^left_?", "l_", re.sub(r"^right_?", "r_", s))
    return {"midhip": "pelvis", "mid_hip": "pelvis", "hip": "pelvis", "c_hip": "pelvis", "chip": "pelvis",
            "head": "head_top", "headtop": "head_top", "upper_neck": "neck", "l_bigtoe": "l_big_toe",
            "r_bigtoe": "r_big_toe", "l_smalltoe": "l_small_toe", "r_smalltoe": "r_small_toe"}.get(s, s)


def skeleton_for_names(names: list[str]) -> tuple[Skeleton, list[int]]:
    """The smallest known skeleton holding every joint named (any common spelling), and each
    name's index in it; ValueError naming what no skeleton has."""
    ours = [_norm_joint(n) for n in names]
    for sk in sorted(SKELETONS.values(), key=lambda s: s.n_joints):
        if set(ours) <= set(sk.joints):
            return sk, [sk.joints.index(j) for j in ours]
    best = max(SKELETONS.values(), key=lambda s: len(set(ours) & set(s.joints)))
    missing = [n for n, o in zip(names, ours, strict=True) if o not in best.joints]
    raise ValueError(f"no known skeleton has the joints {missing} (closest: {best.name})")

"""Skeletons: joint orders, bones and left/right pairs, described as data, and the standing
person's canonical pose.

The built-in human skeletons are files of the same form a user writes
(:func:`gt3dkit.io.skeletonfile.read_skeleton`), shipped in ``gt3dkit/data/skeletons/human/`` and
read here once, through the same checks (:func:`skeleton_from_doc`):

* ``coco17``: COCO keypoints (nose, eyes, ears, shoulders, elbows, wrists, hips, knees, ankles).
* ``panoptic15``: CMU Panoptic's 15 body joints (the first 15 of ``coco19``).
* ``coco19``: CMU Panoptic's ``joints19`` order (``hdPose3d_stage1_coco19``).
* ``body25``, ``body25b``, ``coco18``, ``halpe26``: OpenPose's, AlphaPose's and RTMPose's orders.
* ``coco133``: COCO-WholeBody's body and feet; ``wholebody133``: all of its 133 points (the face's
  68 and each hand's 21 too).

The canonical pose is a person 1.7 m tall standing upright in the *body* frame
(x to the person's left, y forward, z up, metres, feet at z = 0); the UKF places
it at an ellipsoid's centre, scaled to the ellipsoid, for joints no two views see. It is a model
of a person, by joint name (the simulator's walkers, calibration from people), not part of a
skeleton's description: a file's ``[pose]`` gives another body its own.
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib.resources import files

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.types import F64, JsonDict, JsonValue, Scene

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


@dataclass(frozen=True)
class Skeleton:
    """A skeleton: its joints (ours: ``l_``/``r_`` for the sides), bones, left/right ``pairs``
    (empty: the ``l_x``/``r_x`` names pair), the detector's own names (``labels``) and a
    canonical pose (``pose``, metres in the body frame, one row a joint; empty: the human one for
    the joints it names, the body's centre for the rest). A file describes one
    (:func:`read_skeleton`), as the built-ins are described here."""

    name: str
    joints: tuple[str, ...]
    bone_names: tuple[tuple[str, str], ...]
    labels: tuple[str, ...] = ()  # the detector's own joint names (marker names on export)
    #: points per person the detector writes when more than ``joints`` (the first
    #: ``n_joints`` are read: COCO-WholeBody's body and feet, not its face and hands); 0: as many
    detector_points: int = 0
    pairs: tuple[tuple[str, str], ...] = ()
    pose: tuple[tuple[float, float, float], ...] = ()
    #: joints that point up from ``floor`` when the body stands (the first seen is used: a
    #: person's neck, nose or head top); empty: the skeleton says nothing of up
    up: tuple[str, ...] = ()
    #: joints on or just above the floor when the body stands (a person's ankles); empty: none
    floor: tuple[str, ...] = ()
    #: groups of joints that move as one rigid body (a head's nose, ears and eyes): every two of
    #: a group keep their distance, as a bone does (:attr:`ties`)
    groups: tuple[tuple[str, ...], ...] = ()

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
        return np.array([(ix[a], ix[b]) for a, b in self.bone_names], dtype=np.int64).reshape(-1, 2)

    @property
    def tie_names(self) -> tuple[tuple[str, str], ...]:
        """The joint pairs held at a constant distance: the bones, then every two joints of a
        rigid group that no bone joins."""
        out = list(self.bone_names)
        have = {frozenset(b) for b in out}
        for g in self.groups:
            for i, a in enumerate(g):
                for b in g[i + 1:]:
                    if frozenset((a, b)) not in have:
                        have.add(frozenset((a, b)))
                        out.append((a, b))
        return tuple(out)

    @property
    def ties(self) -> np.ndarray:
        """(K', 2) joint indices of :attr:`tie_names` (the bones first, as :attr:`bones`)."""
        if not self.groups:
            return self.bones
        ix = {j: i for i, j in enumerate(self.joints)}
        return np.array([(ix[a], ix[b]) for a, b in self.tie_names], dtype=np.int64).reshape(-1, 2)

    @property
    def left_right(self) -> tuple[tuple[str, str], ...]:
        """The left/right pairs: ``pairs``, or where none are given the ``l_x``/``r_x`` joints."""
        if self.pairs:
            return self.pairs
        have = set(self.joints)
        return tuple((j, "r_" + j[2:]) for j in self.joints if j.startswith("l_") and "r_" + j[2:] in have)

    def mirror(self) -> np.ndarray:
        """(J,) each joint's left/right counterpart (itself where it has none)."""
        ix = {j: i for i, j in enumerate(self.joints)}
        out = np.arange(self.n_joints)
        for a, b in self.left_right:
            out[ix[a]], out[ix[b]] = ix[b], ix[a]
        return out

    def canonical(self) -> F64:
        """(J, 3) canonical pose in the body frame (metres): ``pose``, else the standing person's
        for the joints it names (feet at z = 0) and the body's centre for the others."""
        if self.pose:
            return np.array(self.pose, dtype=np.float64)
        centre = (0.0, 0.0, 0.95)
        return np.array([_CANON.get(j, centre) for j in self.joints], dtype=np.float64)

    def doc(self) -> JsonDict:
        """As a skeleton file holds it (:func:`skeleton_from_doc` reads it back)."""
        out: JsonDict = {"name": self.name, "joints": list(self.joints),
                         "bones": [list(b) for b in self.bone_names],
                         "pairs": [list(p) for p in self.left_right]}
        if self.labels:
            out["labels"] = list(self.labels)
        if self.detector_points:
            out["detector_points"] = self.detector_points
        if self.up:
            out["up"] = list(self.up)
        if self.floor:
            out["floor"] = list(self.floor)
        if self.groups:
            out["groups"] = [list(g) for g in self.groups]
        if self.pose:
            out["pose"] = {j: list(x) for j, x in zip(self.joints, self.pose, strict=True)}
        return out


#: the joints of the standing person's body (the face and hands below are carried by them)
BODY_JOINTS = frozenset(_CANON)


def _add_wholebody_pose() -> None:
    """The canonical places of COCO-WholeBody's face and hand points (its ``wholebody133`` file's
    names), added to the standing person's: a face looking forward, hands hanging at the sides,
    fingers down, palms in."""
    face = tuple(f"face_{k}" for k in range(68))
    # canonical places (body frame, m): the face ~14 cm wide on a plane 8 cm before the head's axis
    t = np.linspace(0.0, np.pi, 17)
    pts = [(-0.07 * np.cos(a), 0.05 + 0.03 * np.sin(a), 1.60 - 0.08 * np.sin(a)) for a in t]  # jaw
    pts += [(x, 0.085, 1.68) for x in np.linspace(-0.06, -0.015, 5)]  # the right brow
    pts += [(x, 0.085, 1.68) for x in np.linspace(0.015, 0.06, 5)]
    pts += [(0.0, 0.085 + 0.005 * k, 1.665 - 0.015 * k) for k in range(4)]  # the nose's bridge
    pts += [(x, 0.09, 1.60) for x in np.linspace(-0.02, 0.02, 5)]
    for cx in (-0.032, 0.032):  # the eyes
        pts += [(cx - 0.012 * np.cos(a), 0.08, 1.655 + 0.005 * np.sin(a))
                for a in np.linspace(0, 2 * np.pi, 7)[:6]]
    for rx, rz in ((0.025, 0.01), (0.015, 0.004)):  # the lips
        m = 12 if rx > 0.02 else 8
        ring = np.linspace(0, 2 * np.pi, m + 1)[:m]
        pts += [(-rx * np.cos(a), 0.085, 1.565 + rz * np.sin(a)) for a in ring]
    _CANON.update({j: (float(x), float(y), float(z)) for j, (x, y, z) in zip(face, pts, strict=True)})
    finger_y = {"thumb": 0.0, "forefinger": 0.03, "middle_finger": 0.01, "ring_finger": -0.01,
                "pinky_finger": -0.03}
    finger_len = {"forefinger": (0.04, 0.025, 0.02), "middle_finger": (0.045, 0.028, 0.02),
                  "ring_finger": (0.042, 0.026, 0.02), "pinky_finger": (0.032, 0.02, 0.018)}
    for side, sign in (("l", 1.0), ("r", -1.0)):
        wx, wy, wz = _CANON[f"{side}_wrist"]
        _CANON[f"{side}_hand_root"] = (wx, wy, wz - 0.01)
        thumb = ((-0.005, 0.025, -0.02), (-0.01, 0.045, -0.04), (-0.01, 0.06, -0.06), (-0.01, 0.07, -0.08))
        for k, (dx, dy, dz) in enumerate(thumb, 1):
            _CANON[f"{side}_thumb{k}"] = (wx + sign * dx, wy + dy, wz + dz)
        for f, lens in finger_len.items():
            z = wz - 0.09
            _CANON[f"{side}_{f}1"] = (wx, wy + finger_y[f], z)
            for k, d in enumerate(lens, 2):
                z -= d
                _CANON[f"{side}_{f}{k}"] = (wx, wy + finger_y[f], z)


_add_wholebody_pose()

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
    raise ValueError(f"no known skeleton has the joints {missing} (closest: {best.name}): describe yours in "
                     "a skeleton file and pass --skeleton FILE (gt3d skeleton NAME --write FILE starts one)")


def skeleton_of(scene: Scene) -> Skeleton | None:
    """The scene's skeleton: the one its input or a file described (``Scene.skeleton_doc``), else
    the built-in it names; None for a scene without keypoints."""
    if scene.skeleton is None:
        return None
    if scene.skeleton_doc is not None:
        return skeleton_from_doc(scene.skeleton_doc, f"skeleton {scene.skeleton}")
    return SKELETONS[scene.skeleton]


def skeleton_from_doc(doc: JsonValue, where: str) -> Skeleton:
    """The skeleton a document describes (:meth:`Skeleton.doc`, a skeleton file): InputError naming
    ``where`` and the entry for a joint named twice, a bone or pair to an unknown joint, a joint
    in two pairs, or a pair whose sides' bones do not mirror each other (a left shoulder paired
    with a right knee)."""
    if not isinstance(doc, Mapping):
        raise InputError(where, "a skeleton is a table (name, joints, bones, pairs)")

    def names(key: str, required: bool = True) -> list[str]:
        v = doc.get(key)
        if v is None and not required:
            return []
        if not isinstance(v, Sequence) or isinstance(v, str) or not all(isinstance(x, str) and x for x in v):
            raise InputError(f"{where}: {key}", "expected a list of names")
        return [str(x) for x in v]

    def links(key: str) -> list[tuple[str, str]]:
        v = doc.get(key, [])
        if not isinstance(v, Sequence) or isinstance(v, str):
            raise InputError(f"{where}: {key}", f"expected a list of [joint, joint] pairs, got {v!r}")
        out = []
        for k, x in enumerate(v):
            if not isinstance(x, Sequence) or isinstance(x, str) or len(x) != 2 or \
                    not all(isinstance(y, str) for y in x):
                raise InputError(f"{where}: {key}[{k}]", f"expected two joint names, got {x!r}")
            a, b = str(x[0]), str(x[1])
            for j in (a, b):
                if j not in joints:
                    raise InputError(f"{where}: {key}[{k}]", f"unknown joint {j!r}")
            if a == b:
                raise InputError(f"{where}: {key}[{k}]", f"joins {a!r} to itself")
            out.append((a, b))
        return out

    name = doc.get("name")
    if not isinstance(name, str) or not name:
        raise InputError(f"{where}: name", "expected a name")
    joint_list = names("joints")
    if not joint_list:
        raise InputError(f"{where}: joints", "no joints")
    twice = [j for k, j in enumerate(joint_list) if j in joint_list[:k]]
    if twice:
        raise InputError(f"{where}: joints", f"joint {twice[0]!r} named twice")
    joints = set(joint_list)
    bones = links("bones")
    pairs = links("pairs")
    labels = names("labels", required=False)
    up, floor = names("up", required=False), names("floor", required=False)
    for key, given in (("up", up), ("floor", floor)):
        for j in given:
            if j not in joints:
                raise InputError(f"{where}: {key}", f"unknown joint {j!r}")
    groups = _groups(where, doc.get("groups"), joints)
    both = sorted(set(up) & set(floor))
    if both:
        raise InputError(f"{where}: floor", f"joint {both[0]!r} is both up and on the floor")
    if labels and len(labels) != len(joint_list):
        raise InputError(f"{where}: labels", f"{len(labels)} names for {len(joint_list)} joints")
    paired = [j for a, b in pairs for j in (a, b)]
    again = [j for k, j in enumerate(paired) if j in paired[:k]]
    if again:
        raise InputError(f"{where}: pairs", f"joint {again[0]!r} is in two pairs")
    _check_mirrored(where, bones, pairs)
    points = doc.get("detector_points", 0)
    if not isinstance(points, int) or isinstance(points, bool) or (points and points < len(joint_list)):
        raise InputError(f"{where}: detector_points", "expected the points a detector writes per "
                                                      f"person, at least the {len(joint_list)} joints, "
                                                      f"got {points!r}")
    pose = doc.get("pose")
    pose_rows: tuple[tuple[float, float, float], ...] = ()
    if pose is not None:
        if not isinstance(pose, Mapping) or set(pose) != joints:
            raise InputError(f"{where}: pose", "expected one [x, y, z] (metres) for every joint")
        rows = []
        for j in joint_list:
            x = pose[j]
            items = list(x) if isinstance(x, Sequence) and not isinstance(x, str) else []
            xyz = [float(v) for v in items if isinstance(v, int | float) and not isinstance(v, bool)]
            if len(items) != 3 or len(xyz) != 3:
                raise InputError(f"{where}: pose: {j}", f"expected [x, y, z] in metres, got {x!r}")
            rows.append((xyz[0], xyz[1], xyz[2]))
        pose_rows = tuple(rows)
    return Skeleton(name, tuple(joint_list), tuple(bones), tuple(labels), points, tuple(pairs), pose_rows,
                    tuple(up), tuple(floor), groups)


def _groups(where: str, v: JsonValue, joints: set[str]) -> tuple[tuple[str, ...], ...]:
    """A skeleton document's rigid ``groups``: lists of two or more known joints, none twice."""
    if v is None:
        return ()
    if not isinstance(v, Sequence) or isinstance(v, str):
        raise InputError(f"{where}: groups", "expected a list of lists of joint names")
    out = []
    for k, g in enumerate(v):
        if not isinstance(g, Sequence) or isinstance(g, str) or not all(isinstance(x, str) for x in g):
            raise InputError(f"{where}: groups[{k}]", f"expected a list of joint names, got {g!r}")
        names = [str(x) for x in g]
        if len(names) < 2:
            raise InputError(f"{where}: groups[{k}]", "a rigid group needs two joints or more")
        for j in names:
            if j not in joints:
                raise InputError(f"{where}: groups[{k}]", f"unknown joint {j!r}")
        twice = [j for i, j in enumerate(names) if j in names[:i]]
        if twice:
            raise InputError(f"{where}: groups[{k}]", f"joint {twice[0]!r} named twice")
        out.append(tuple(names))
    return tuple(out)


def unmirrored(bones: Sequence[tuple[str, str]], pairs: Sequence[tuple[str, str]]) -> list[int]:
    """The indices of the left/right ``pairs`` whose two joints are not of one kind: mirrored
    through every pair, the bones of the one are not the bones of the other (a joint outside
    every pair is its own mirror)."""
    mirror = {a: b for a, b in pairs} | {b: a for a, b in pairs}
    bone_set = {frozenset(b) for b in bones}
    bad = []
    for k, (a, b) in enumerate(pairs):
        of_a = {frozenset((mirror.get(x, x), mirror.get(y, y))) for x, y in bones if a in (x, y)}
        of_b = {frozenset(bn) for bn in bones if b in bn}
        if of_a != of_b or not of_a <= bone_set:
            bad.append(k)
    return bad


def _check_mirrored(where: str, bones: list[tuple[str, str]], pairs: list[tuple[str, str]]) -> None:
    """InputError naming the first pair :func:`unmirrored` finds."""
    for k in unmirrored(bones, pairs)[:1]:
        a, b = pairs[k]
        raise InputError(f"{where}: pairs[{k}]", f"{a!r} and {b!r} are not a left/right pair: their "
                                                 "bones do not mirror each other")


def _builtin_skeletons() -> dict[str, Skeleton]:
    """The shipped human skeleton files (``gt3dkit/data/skeletons/human/*.toml``) by name, the
    smallest first, each read and checked as a user's file is (:func:`skeleton_from_doc`)."""
    out: dict[str, Skeleton] = {}
    folder = files("gt3dkit").joinpath("data", "skeletons", "human")
    for entry in sorted(folder.iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            where = f"gt3dkit/data/skeletons/human/{entry.name}"
            sk = skeleton_from_doc(tomllib.loads(entry.read_text(encoding="utf-8")), where)
            out[sk.name] = sk
    return dict(sorted(out.items(), key=lambda kv: (kv[1].n_joints, kv[0])))  # smallest first


#: the built-in skeletons by name (the human files shipped with the package)
SKELETONS = _builtin_skeletons()

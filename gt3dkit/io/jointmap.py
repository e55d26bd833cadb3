"""A user's mapping from the run's joints (the detector's skeleton) to another skeleton's.

A detector's joints are not a dataset's: OpenPose's hip is not a motion-capture hip joint
centre, Shelf's head is the top of the head. gt3dkit estimates the joints the detector gives
and writes them as they are (``keypoints.csv``); a mapping is applied only where the user asks
for it (``gt3d export --joint-map MAP``), from a file the user writes, so that who applies it is
explicit and nothing of it is fitted (least of all to a truth).

The file (JSON)::

    {"name": "shelf14", "from": "body25",
     "joints": {"r_ankle": {"RAnkle": 1},
                "head_top": {"Nose": 1.5, "Neck": -0.5},
                "pelvis": {"LHip": 0.5, "RHip": 0.5}}}

Each output joint is an affine combination of the run's joints (named as the run's markers are,
``RAnkle``, or as its joints, ``r_ankle``): the weights sum to 1, so the mapping does not depend
on where the world's origin is. Its sd is ``sqrt(sum w^2 sd^2)`` (the joints' errors taken as
independent). ``from`` must be the run's skeleton. Any mistake is an error naming the entry.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.parse import json_of, read_hashed
from gt3dkit.types import F64

#: The weights of an output joint sum to 1 within this.
WEIGHT_SUM_TOL = 1e-6


@dataclass(frozen=True)
class JointMap:
    """``names (K,)`` the output joints, ``weights (K, J)`` each one's combination of the run's
    ``J`` joints, the map's ``name`` and the file's ``sha256``."""

    name: str
    names: tuple[str, ...]
    weights: F64
    sha256: str

    def apply(self, kpt_world: F64, kpt_sd: F64) -> tuple[F64, F64]:
        """``(M, J, 3)`` joints (m) and ``(M, J)`` sds -> ``(M, K, 3)`` and ``(M, K)``; an output
        joint is NaN where a joint it uses is."""
        used = self.weights != 0
        X = np.einsum("kj,mjd->mkd", self.weights, np.where(np.isfinite(kpt_world), kpt_world, 0.0))
        gone = (~np.isfinite(kpt_world).all(axis=2)).astype(float)
        miss = np.einsum("kj,mj->mk", used.astype(float), gone) > 0
        X[miss] = np.nan
        sd2 = np.where(np.isfinite(kpt_sd), kpt_sd, 0.0) ** 2
        sd = np.sqrt(np.einsum("kj,mj->mk", self.weights ** 2, sd2))
        sd[miss] = np.nan
        return X, sd


def read_joint_map(path: Path, skeleton: str | None, joints: tuple[str, ...],
                   markers: tuple[str, ...]) -> JointMap:
    """The mapping in ``path`` for a run of ``skeleton`` whose joints are ``joints`` (our names)
    and ``markers`` (the detector's): :class:`InputError` naming the entry for every mistake."""
    where = str(path)
    raw, sha = read_hashed(Path(path))
    doc = json_of(Path(path), raw)
    if not isinstance(doc, dict):
        raise InputError(where, 'expected {"name": ..., "from": ..., "joints": {...}}')
    src = doc.get("from")
    if src != skeleton:
        raise InputError(f"{where}: from", f"the map is from {src!r}, the run's skeleton is {skeleton!r}")
    name = doc.get("name")
    if not isinstance(name, str) or not name.strip():
        raise InputError(f"{where}: name", "the output skeleton's name (a non-empty string) is missing")
    table = doc.get("joints")
    if not isinstance(table, dict) or not table:
        raise InputError(f"{where}: joints", "expected at least one output joint: {name: {joint: weight}}")
    index = {n: k for k, n in enumerate(joints)} | {n: k for k, n in enumerate(markers)}
    W = np.zeros((len(table), len(joints)))
    for k, (out, combo) in enumerate(table.items()):
        at = f"{where}: joints.{out}"
        if not isinstance(combo, dict) or not combo:
            raise InputError(at, "expected {joint: weight, ...} with at least one joint")
        for j, w in combo.items():
            if j not in index:
                raise InputError(f"{at}.{j}", f"the run has no joint {j!r} (its joints: "
                                              f"{', '.join(markers)})")
            if type(w) not in (int, float) or not np.isfinite(w):
                raise InputError(f"{at}.{j}", f"the weight must be a finite number, got {w!r}")
            W[k, index[j]] += float(w)
        if abs(W[k].sum() - 1.0) > WEIGHT_SUM_TOL:
            raise InputError(at, f"the weights sum to {W[k].sum():.6g}, not 1 (an affine combination "
                                 "does not depend on the world's origin)")
    return JointMap(name.strip(), tuple(str(n) for n in table), W, sha)

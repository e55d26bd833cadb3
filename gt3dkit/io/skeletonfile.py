"""Skeleton files (TOML): a skeleton described as data, read and checked
(:func:`gt3dkit.skeletons.skeleton_from_doc`), and ``--skeleton NAME|FILE``."""

from __future__ import annotations

import json
from importlib.resources import files
from pathlib import Path

from gt3dkit.errors import InputError
from gt3dkit.parse import load_toml
from gt3dkit.skeletons import SKELETONS, Skeleton, skeleton_from_doc
from gt3dkit.types import JsonDict


def shipped_skeletons() -> dict[str, Path]:
    """The skeleton files shipped with the package (``gt3dkit/data/skeletons/*.toml``), by name."""
    folder = Path(str(files("gt3dkit"))) / "data" / "skeletons"
    return {p.stem: p for p in sorted(folder.glob("*.toml"))}


def named_skeleton(name_or_file: str) -> Skeleton:
    """A built-in skeleton by name, a skeleton file shipped with the package by its name
    (:func:`shipped_skeletons`), or the one a skeleton file describes (:func:`read_skeleton`)."""
    if name_or_file in SKELETONS:
        return SKELETONS[name_or_file]
    shipped = shipped_skeletons()
    path = shipped.get(name_or_file, Path(name_or_file))
    if path.suffix.lower() == ".toml" and not path.is_file():  # meant as a file
        raise InputError(f"--skeleton: {name_or_file}", "no such file" if not path.exists() else "not a file")
    if path.suffix.lower() != ".toml" or not path.is_file():
        known = ", ".join([*SKELETONS, *shipped])
        raise InputError("--skeleton", f"unknown skeleton {name_or_file!r} (known: {known}; "
                                       "or a skeleton file, .toml)")
    return read_skeleton(path)


def given_skeleton(name_or_file: str) -> tuple[Skeleton, JsonDict | None]:
    """``--skeleton NAME|FILE`` for a reader (:func:`named_skeleton`), with the document a scene
    carries for it (``Scene.skeleton_doc``): None for a built-in, which its name is enough for."""
    sk = named_skeleton(name_or_file)
    return sk, (None if SKELETONS.get(sk.name) == sk else sk.doc())


def read_skeleton(path: Path) -> Skeleton:
    """A skeleton file (TOML)::

        name = "mouse"                          # default: the file's name
        joints = ["nose", "ear_l", "ear_r", "tail_base"]
        bones = [["nose", "ear_l"], ["nose", "ear_r"], ["nose", "tail_base"]]
        pairs = [["ear_l", "ear_r"]]            # left/right (default: l_x / r_x names)
        labels = ["Nose", "EarL", "EarR", "TTI"]  # the labelling tool's names (optional)
        detector_points = 0                     # points a detector writes per person when more
                                                # than the joints (the first are read; optional)
        groups = [["nose", "ear_l", "ear_r"]]   # joints that move as one rigid body (optional)
        up = ["nose"]                           # standing, these point up from the floor joints
        floor = ["ear_l"]                       # on the floor (both optional: a rig from people
                                                # needs them, gt3d calib people)
        [pose]                                  # canonical pose, m (optional): joint = [x, y, z]
        nose = [0.0, 0.05, 0.02]

    Every name and bone is checked (:func:`skeleton_from_doc`). The built-in skeletons are files
    of this form (``gt3dkit/data/skeletons/human/``), a starting point for one's own."""
    doc = load_toml(path)
    if "name" not in doc:
        doc = {**doc, "name": path.stem}
    return skeleton_from_doc(doc, str(path))


def write_skeleton(skel: Skeleton, path: Path) -> None:
    """``skel`` as a skeleton file (:func:`read_skeleton` reads it back)."""
    def names(xs: tuple[str, ...] | list[str]) -> str:
        return "[" + ", ".join(json.dumps(x) for x in xs) + "]"

    lines = [f"name = {json.dumps(skel.name)}", f"joints = {names(skel.joints)}",
             "bones = [" + ", ".join(names(b) for b in skel.bone_names) + "]",
             "pairs = [" + ", ".join(names(p) for p in skel.left_right) + "]"]
    if skel.labels:
        lines.append(f"labels = {names(skel.labels)}")
    if skel.detector_points:
        lines.append(f"detector_points = {skel.detector_points}")
    if skel.up:
        lines.append(f"up = {names(skel.up)}")
    if skel.floor:
        lines.append(f"floor = {names(skel.floor)}")
    if skel.groups:
        lines.append("groups = [" + ", ".join(names(g) for g in skel.groups) + "]")
    if skel.pose:
        lines.append("\n[pose]")
        lines += [f"{json.dumps(j)} = [{x!r}, {y!r}, {z!r}]" for j, (x, y, z) in zip(skel.joints, skel.pose,
                                                                                     strict=True)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")

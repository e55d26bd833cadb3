"""Dataset loaders. Every loader returns the same :class:`gt3dkit.types.Scene`."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from gt3dkit.calib.board import UNITS_M
from gt3dkit.calib.formats import detect_format, read_calibration
from gt3dkit.calib.formats.grid import LAYOUTS as GRID_LAYOUTS
from gt3dkit.calib.formats.native import FPS_RANGE
from gt3dkit.calib.show import far_apart
from gt3dkit.errors import InputError
from gt3dkit.io.datasets import anipose, dlc, mot, native, openpose, panoptic, sleap, tasks, wildtrack
from gt3dkit.rig import Rig
from gt3dkit.types import GroundTruth, JsonDict, JsonValue, ReadAhead, Scene, SimScene, SkeletonScene


class Calibration(NamedTuple):
    """A calibration to read: ``path`` (None: the one beside the annotations), whose lengths are in
    ``units`` (``m``, ``cm``, ``mm``: an anipose ``calibration.toml`` holds its board's units,
    millimetres where the board was measured so); the scene's world is made metres."""

    path: Path | str | None
    units: str = "m"


class ReadOptions(NamedTuple):
    """What :func:`read_scene` passes a layout's reader besides the folder."""

    skeleton: str | None
    calib: Path | str | None
    fps: float | None
    panoptic: JsonDict
    span: tuple[int, int] | None = None  # the frame numbers lo..hi only (Layout.index)
    ahead: ReadAhead | None = None  # what Layout.index read (FrameIndex.ahead): not read again


@dataclass(frozen=True)
class Layout:
    """One input layout: whether a folder holds it (``found``), its reader, and the simulator's
    writers of a box scene (``write_boxes(sim, folder, id_seed)``) and of a skeleton scene
    (``write_keypoints(sim, folder)``) into a folder (None: not written). ``associated``: its
    ids are per camera or absent (the cross-camera association makes people of them);
    ``skeletons``: ``--skeleton`` names its joint order; ``index``: the folder without its rows
    (:class:`gt3dkit.types.FrameIndex`) where its reader reads a span of frames on its own
    (``ReadOptions.span``: a long sequence's windows read their own frames), and ``truth`` the
    sequence's truth file, where one holds it (None: the frames' own, read with them; its
    ``files`` digest added to the dict given)."""

    name: str
    found: Callable[[Path], bool]
    read: Callable[[Path, ReadOptions], Scene]
    write_boxes: Callable[[SimScene, Path, int | None], None] | None = None
    write_keypoints: Callable[[SkeletonScene, Path], None] | None = None
    associated: bool = False
    skeletons: bool = False
    index: Callable[[Path], Scene] | None = None
    truth: Callable[[Path, dict[str, str]], GroundTruth | None] | None = None


def _grid(name: str) -> Layout:
    g = GRID_LAYOUTS[name]
    return Layout(name, lambda root: (root / "calibrations" / g.intrinsic_dir).is_dir(),
                  lambda root, o: wildtrack.load(root, g, o.span, o.ahead),
                  lambda sim, tmp, seed: wildtrack.write(sim, tmp, g),
                  index=lambda root: wildtrack.index(root, g), truth=wildtrack.truth_csv)


#: Every input layout, in the order a folder is tested for it (the first found is its layout).
LAYOUTS: dict[str, Layout] = {v.name: v for v in (
    Layout("mot", lambda root: (root / "mot").is_dir(), lambda root, o: mot.load(root, o.calib, o.fps),
           write_boxes=mot.write, associated=True),
    Layout("openpose", lambda root: any(p.is_dir() for p in root.glob("*_json"))
           or any(p.is_dir() for p in root.glob("pose/*_json")),
           lambda root, o: openpose.load(root, o.skeleton, o.calib, o.fps), associated=True, skeletons=True),
    Layout("cvat", lambda root: (root / "cvat").is_dir(),
           lambda root, o: tasks.load(root, "cvat", o.skeleton, o.calib, o.fps),
           write_boxes=tasks.write_cvat, associated=True, skeletons=True),
    Layout("coco", lambda root: (root / "coco").is_dir(),
           lambda root, o: tasks.load(root, "coco", o.skeleton, o.calib,
                                      o.fps), associated=True, skeletons=True),
    Layout("native", lambda root: (root / "cameras.json").exists(), lambda root, o: native.load(root,
                                                                                                o.skeleton),
           write_boxes=native.write_boxes, write_keypoints=native.write_keypoints, skeletons=True),
    _grid("wildtrack"),
    _grid("multiviewx"),
    Layout("panoptic", lambda root: any(root.glob("calibration_*.json")),
           lambda root, o: panoptic.load_with(root, o.panoptic), write_keypoints=panoptic.write),
    Layout("anipose", anipose.found, lambda root, o: anipose.load(root, o.skeleton, o.calib, o.fps),
           associated=True, skeletons=True),
    # last: DeepLabCut's test opens files (a CSV's first cell) that no layout above needs opened
    Layout("sleap", sleap.found, lambda root, o: sleap.load(root, o.calib, o.fps, o.skeleton),
           associated=True, skeletons=True),
    Layout("dlc", dlc.found, lambda root, o: dlc.load(root, o.skeleton, o.calib, o.fps), associated=True,
           skeletons=True),
)}
#: layouts whose ids are per camera or absent: association makes people of them
ASSOCIATED = tuple(k for k, v in LAYOUTS.items() if v.associated)


def detect_layout(root: Path) -> str:
    """Name the layout of an input folder from the files it holds."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(str(root), "not a directory")
    for name, layout in LAYOUTS.items():
        if layout.found(root):
            return name
    raise InputError(str(root), "unknown input layout: expected cameras.json (native), "
                                "calibrations/intrinsic_zero (WILDTRACK), "
                                "calibrations/intrinsic (MultiviewX) or "
                                "calibration_<seq>.json (CMU Panoptic), mot/<camera>.txt "
                                "(MOTChallenge per camera), <camera>_json/ (OpenPose), cvat/<camera>.xml, "
                                "coco/<camera>.json, <camera>/*.slp or *.analysis.h5 (SLEAP), pose-2d/ (an "
                                "anipose session) or DeepLabCut's .h5 or CSV per camera")


def with_calibration(scene: Scene, calib: Path | str) -> Scene:
    """``scene`` with its cameras replaced by those of a calibration file or folder in any
    format (:func:`gt3dkit.calib.formats.read_calibration`), matched by name."""
    rig = read_calibration(calib)
    have = {c.name: c for c in rig.cameras}
    used = sorted({scene.rig.cameras[int(c)].name for c in np.unique(scene.obs.cam)})
    missing = [n for n in used if n not in have]
    if missing:
        raise InputError(str(calib), f"camera {missing[0]} is referenced by the annotations but "
                                     f"absent from the calibration (it has {', '.join(rig.names)})")
    cams = tuple(have.get(c.name, c) for c in scene.rig.cameras)
    up = rig.up if detect_format(Path(calib)) == "native" else scene.rig.up  # only cameras.json has one
    new = Rig(cams, up=up, frame_name=f"{scene.rig.frame_name}, cameras from {calib}")
    files = {**scene.files, f"calibration:{calib}": _calib_digest(calib)}
    return dataclasses.replace(scene, rig=new, files=files)


def _calib_digest(calib: Path | str) -> str:
    """SHA-256 over the calibration's files (a folder: every file in it, sorted)."""
    import hashlib

    p = Path(calib)
    h = hashlib.sha256()
    for f in sorted(p.rglob("*")) if p.is_dir() else [p]:
        if f.is_file():
            h.update(f.name.encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def read_scene(root: Path | str, layout: str | None = None, skeleton: str | None = None,
               fps: float | None = None, calib: Path | str | Calibration | None = None,
               association: Path | str | None = None, span: tuple[int, int] | None = None,
               ahead: ReadAhead | None = None, **panoptic_options: JsonValue) -> Scene:
    """Read any supported input folder (layout detected when not given), as its files say: a
    layout with ids per camera or none (:data:`ASSOCIATED`) still has them (the cross-camera
    association is estimation, :func:`gt3dkit.api.load_scene`), and the scene is not checked
    yet (:func:`checks.check_scene`, after the association).

    ``skeleton`` names the joint order of native ``keypoints.csv`` (default: from the
    data); ``fps`` overrides the input's frame rate. ``panoptic_options`` go to
    :func:`gt3dkit.io.datasets.panoptic.load` (``cameras``, ``noise_px``, ``seed``,
    ``min_conf``). ``calib`` replaces the input's cameras by those of a calibration in any
    format (:func:`with_calibration`). ``span``: only the frames ``lo..hi`` (a layout with an
    ``index``; a span without an annotation is no error). ``ahead``: what :func:`index_scene`
    read of the folder (``FrameIndex.ahead``), not read again. A :class:`Calibration` says the
    calibration's units too (the world made metres, :func:`in_metres`).
    """
    path, units = (calib.path, calib.units) if isinstance(calib, Calibration) else (calib, "m")
    layout = _checked_layout(root, layout, skeleton, association, panoptic_options)
    scene = LAYOUTS[layout].read(Path(root), ReadOptions(skeleton, path, fps, panoptic_options, span, ahead))
    if len(scene.obs) == 0 and span is None:
        raise InputError(str(root), "no annotations in any frame")
    if path is None and layout in CALIBRATION_BESIDE:
        scene = _other_calibrations_said(scene, Path(root))
    scene = _as_asked(scene, root, layout, skeleton, fps, path, association, panoptic_options)
    return in_metres(scene, units)


#: the layouts whose calibration is found beside the annotations (:func:`mot.find_calibration`)
CALIBRATION_BESIDE = ("mot", "openpose", "cvat", "coco", "anipose", "sleap", "dlc")


def _other_calibrations_said(scene: Scene, root: Path) -> Scene:
    """``scene`` with a warning where more than one calibration lies beside its annotations (an
    older ``calibration_old.toml`` kept beside the new one): the first was read, silently."""
    found = mot.calibration_candidates(root)
    if len(found) < 2:
        return scene
    names = ", ".join(p.name for p in found)
    return dataclasses.replace(scene, warnings=(*scene.warnings, (
        f"{len(found)} calibrations beside the annotations ({names}): read {found[0].name} "
        "(--calib chooses one)")))


def index_scene(root: Path | str, layout: str | None = None, fps: float | None = None,
                calib: Path | str | Calibration | None = None) -> Scene | None:
    """:func:`read_scene` without the rows, where the layout reads a span of frames on its own
    (``Layout.index``; else None): the cameras, frames and each frame's objects
    (:class:`gt3dkit.types.FrameIndex`)."""
    path, units = (calib.path, calib.units) if isinstance(calib, Calibration) else (calib, "m")
    layout = _checked_layout(root, layout, None, None, {})
    index = LAYOUTS[layout].index
    if index is None:
        return None
    scene = index(Path(root))
    if scene.index is None or not len(scene.index.frames):
        raise InputError(str(root), "no annotations in any frame")
    return in_metres(_as_asked(scene, root, layout, None, fps, path, None, {}), units)


def in_metres(scene: Scene, units: str) -> Scene:
    """``scene`` read from a calibration whose lengths are in ``units`` (``m``, ``cm``, ``mm``),
    with its world in metres: the cameras' translations and any truth scaled
    (``load_options`` records the units, so a report reads it the same way)."""
    if units not in UNITS_M:
        raise InputError("--calib-units", f"unknown unit {units!r} (known: {', '.join(UNITS_M)})")
    if units == "m":
        return _far_apart_said(scene)
    s = UNITS_M[units]
    truth = scene.truth
    if truth is not None:
        truth = dataclasses.replace(truth, center_world=truth.center_world * s, semi_axes=truth.semi_axes * s,
                                    kpt_world=truth.kpt_world * s)
    return dataclasses.replace(scene, rig=scene.rig.in_metres(s), truth=truth,
                               load_options={**scene.load_options, "calib_units": units})


def _far_apart_said(scene: Scene) -> Scene:
    """``scene`` with a ``warning:`` where its cameras stand implausibly far apart for metres."""
    said = far_apart(scene.rig)
    return scene if said is None else dataclasses.replace(scene, warnings=(*scene.warnings, said))


def with_sequence_truth(head: Scene) -> Scene:
    """An :func:`index_scene`'s ``head`` with its sequence's truth file read, where its layout
    keeps one (``Layout.truth``)."""
    read = LAYOUTS[head.layout].truth
    files = dict(head.files)
    truth = read(Path(head.root), files) if read is not None else None
    return head if truth is None else dataclasses.replace(head, truth=truth, files=files)


def _checked_layout(root: Path | str, layout: str | None, skeleton: str | None,
                    association: Path | str | None, panoptic_options: JsonDict) -> str:
    """The input's layout (detected when not given), checked against the options given."""
    layout = layout or detect_layout(Path(root))
    if layout not in LAYOUTS:
        raise InputError(str(root), f"unknown layout {layout!r} (known: {', '.join(LAYOUTS)})")
    if skeleton is not None and not LAYOUTS[layout].skeletons:
        raise InputError("--skeleton", f"applies to native keypoints.csv inputs, not {layout}")
    if panoptic_options and layout != "panoptic":
        raise InputError(str(root), f"options {sorted(panoptic_options)} apply to the panoptic "
                                    "layout only")
    if association is not None and layout not in ASSOCIATED:
        raise InputError("--association", "applies to inputs with per-camera ids or none "
                                          f"({', '.join(ASSOCIATED)}), not {layout}")
    return layout


def _as_asked(scene: Scene, root: Path | str, layout: str, skeleton: str | None, fps: float | None,
              calib: Path | str | None, association: Path | str | None, panoptic_options: JsonDict
              ) -> Scene:
    """A layout's ``scene`` with :func:`read_scene`'s options: the calibration, the fps and
    the options it was read with (``load_options``)."""
    if calib is not None and layout not in ASSOCIATED:  # these read their calibration themselves
        scene = with_calibration(scene, calib)
    if fps is not None:
        if not (np.isfinite(fps) and FPS_RANGE[0] <= fps <= FPS_RANGE[1]):
            raise InputError("fps", f"must be in [{FPS_RANGE[0]:g}, {FPS_RANGE[1]:g}]"
                                    f", got {fps}")
        scene = dataclasses.replace(scene, fps=float(fps), fps_assumed="")
    opts = {"root": str(Path(root).resolve()), "layout": layout, "skeleton": skeleton, "fps": fps,
            "calib": None if calib is None else str(Path(calib).resolve()), **panoptic_options}
    if association is not None:
        opts["association"] = str(Path(association).resolve())
    scene = dataclasses.replace(scene, load_options=opts)
    return scene

"""The board views of a calibration: which files are which camera, their frames, the corners found.

Layouts read (:func:`find_cameras`):

* several paths, one per camera: a video, or a folder of images (``gt3d calib board
  back.mp4 mid.mp4 ...``);
* one folder whose entries are the cameras: videos (anipose's ``calibration/calib-cam1.mp4``), or
  folders of images or of one video each;
* Pose2Sim's calibration folder: ``intrinsics/int_<cam>_img/`` (each camera on its own, for its
  intrinsics) and ``extrinsics/ext_<cam>_img/`` (the cameras at once).

A camera is named by ``--cam-regex`` (its first group, searched in the path) or else by its file
or folder name without what every camera's name shares (``minimal_session-back-calibration.MOV``
-> ``back``; ``int_cam1_img`` -> ``cam1``). Frames of different cameras are simultaneous when
they have the same index (a video's frame number, an image's position in its sorted folder).
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gt3dkit.calib.board import Board, BoardDetector, Detection
from gt3dkit.errors import InputError

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".mpg", ".mpeg", ".wmv", ".webm")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class CameraSource:
    """Where one camera's board frames come from.

    ``synced``: its frames are simultaneous with the other cameras' frames of the same index
    (False for Pose2Sim's per-camera intrinsics folders).
    """

    name: str
    path: Path
    synced: bool = True


@dataclass(frozen=True)
class View:
    """The board as one camera saw it in one frame."""

    cam: int
    frame: int  # frame index (a video's frame number, an image's position)
    label: str  # "frame 12" or the image's file name
    synced: bool
    det: Detection


@dataclass(frozen=True)
class CameraFrames:
    """What reading one camera gave: its image size, its views, frames read and frames with no board."""

    size: tuple[int, int]  # (width, height) px
    views: tuple[View, ...]
    n_read: int
    n_empty: int


def _natural(p: Path) -> list[object]:
    return [int(s) if s.isdigit() else s for s in re.split(r"(\d+)", p.name)]


def _is_video(p: Path) -> bool:
    return p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES


def _images(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=_natural)


def _source_of(p: Path) -> Path | None:
    """A video, a folder of images, or a folder of exactly one video; else None."""
    if _is_video(p):
        return p
    if p.is_dir():
        if _images(p):
            return p
        vids = [q for q in p.iterdir() if _is_video(q)]
        if len(vids) == 1:
            return vids[0]
    return None


def _strip_shared(names: list[str]) -> list[str]:
    """The names without the prefix and suffix every one has (kept whole when that leaves two equal)."""
    if len(names) < 2:
        return names
    pre = os.path.commonprefix(names)
    suf = os.path.commonprefix([n[::-1] for n in names])[::-1]
    # only whole words: up to the last separator of the prefix, from the first of the suffix
    pre = pre[: max((pre.rfind(c) for c in "-_ ."), default=-1) + 1]
    cuts = [suf.find(c) for c in "-_ ." if c in suf]
    suf = suf[min(cuts) :] if cuts else ""
    cut = [n[len(pre) : len(n) - len(suf)] for n in names]
    cut = [c.strip("-_ .") for c in cut]
    if all(cut) and len(set(cut)) == len(cut):
        return cut
    return names


def camera_names(paths: Sequence[Path], cam_regex: str | None) -> list[str]:
    if cam_regex is not None:
        out = []
        for p in paths:
            m = re.search(cam_regex, str(p))
            if m is None:
                raise InputError(str(p), f"--cam-regex {cam_regex!r} does not match")
            out.append(m.group(1) if m.groups() else m.group(0))
    else:
        out = _strip_shared([p.stem if p.is_file() else p.name for p in paths])
    if len(set(out)) != len(out):
        raise InputError(
            str(paths[0].parent), f"two inputs have the same camera name ({', '.join(out)}): give --cam-regex"
        )
    return out


def find_cameras(
    inputs: Sequence[str | Path], cam_regex: str | None = None, intrinsics_only: bool = False
) -> list[CameraSource]:
    """The cameras of the input paths (see the module docstring)."""
    paths = [Path(p) for p in inputs]
    for p in paths:
        if not p.exists():
            raise InputError(str(p), "no such file or folder")
    if len(paths) == 1 and paths[0].is_dir() and _source_of(paths[0]) is None:
        root = paths[0]
        intr, extr = root / "intrinsics", root / "extrinsics"
        if intr.is_dir() or extr.is_dir():  # Pose2Sim
            out: list[CameraSource] = []
            for folder, synced in ((intr, False), (extr, True)):
                if not folder.is_dir() or (synced and intrinsics_only):
                    continue
                subs = sorted((q for q in folder.iterdir() if _source_of(q) is not None), key=_natural)
                names = camera_names(subs, cam_regex)
                out += [CameraSource(n, _source_of(q) or q, synced) for n, q in zip(names, subs, strict=True)]
            if not out:
                raise InputError(
                    str(root), "intrinsics/ and extrinsics/ hold no camera folders of images or videos"
                )
            return out
        paths = sorted((q for q in root.iterdir() if _source_of(q) is not None), key=_natural)
        if not paths:
            raise InputError(str(root), "no videos or folders of images (one per camera) in the folder")
    srcs = []
    for p in paths:
        s = _source_of(p)
        if s is None:
            raise InputError(str(p), "neither a video nor a folder of images")
        srcs.append(s)
    names = camera_names(paths, cam_regex)
    return [CameraSource(n, s, not intrinsics_only) for n, s in zip(names, srcs, strict=True)]


def _frames(src: CameraSource, step: int) -> Iterator[tuple[int, str, np.ndarray]]:
    """(index, label, grey image) of every ``step``-th frame."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # FFmpeg's own lines: the error says it once
    import cv2

    if src.path.is_dir():
        for i, p in enumerate(_images(src.path)):
            if i % step:
                continue
            im = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            if im is None:
                raise InputError(str(p), "cannot be decoded as an image")
            yield i, p.name, im
        return
    cap = cv2.VideoCapture(str(src.path))
    try:
        if not cap.isOpened():
            raise InputError(
                str(src.path), "cannot be opened as a video (not a video, or a codec OpenCV's FFmpeg lacks)"
            )
        i = 0
        while True:
            if i % step:
                if not cap.grab():
                    break
            else:
                ok, im = cap.read()
                if not ok:
                    break
                yield i, f"frame {i}", cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im
            i += 1
        if i == 0:
            raise InputError(str(src.path), "no frame could be decoded")
    finally:
        cap.release()


def read_camera(cam: int, src: CameraSource, board: Board, step: int) -> CameraFrames:
    """Every ``step``-th frame of one camera, the board found in each (in this thread)."""
    det = BoardDetector(board)
    size: tuple[int, int] | None = None
    views, n, empty = [], 0, 0
    first = ""
    for i, label, grey in _frames(src, step):
        wh = (int(grey.shape[1]), int(grey.shape[0]))
        if size is None:
            size, first = wh, label
        elif wh != size:
            raise InputError(
                str(src.path),
                f"{label}: image size {wh[0]}x{wh[1]} differs from {first}'s "
                f"{size[0]}x{size[1]}: one camera, one image size",
            )
        n += 1
        d = det.detect(grey)
        if d is None:
            empty += 1
            continue
        views.append(View(cam, i, label, src.synced, d))
    if size is None:
        raise InputError(str(src.path), "no images")
    return CameraFrames(size, tuple(views), n, empty)


def read_views(
    sources: Sequence[CameraSource], board: Board, step: int = 1, threads: int | None = None
) -> list[CameraFrames]:
    """:func:`read_camera` for every camera, cameras side by side in threads (OpenCV's decoding
    and detection let go of the GIL)."""
    if step < 1:
        raise InputError("--step", f"must be >= 1, got {step}")
    n = threads or min(len(sources), os.cpu_count() or 1)
    with ThreadPoolExecutor(max(1, n)) as pool:
        futs = [pool.submit(read_camera, i, s, board, step) for i, s in enumerate(sources)]
        return [f.result() for f in futs]


@dataclass(frozen=True)
class BoardViews:
    """Every camera's board views, the cameras named once (a Pose2Sim camera's intrinsics and
    extrinsics folders are one camera)."""

    names: tuple[str, ...]
    sizes: tuple[tuple[int, int], ...]
    views: tuple[View, ...]
    frames_read: tuple[int, ...]
    frames_empty: tuple[int, ...]
    sources: tuple[CameraSource, ...]


def board_views(sources: Sequence[CameraSource], board: Board, step: int = 1) -> BoardViews:
    """Read and detect every source (:func:`read_views`); a camera in which the board is never
    found, or whose folders disagree on the image size, is an :class:`InputError`."""
    names = list(dict.fromkeys(s.name for s in sources))
    got = read_views(sources, board, step)
    sizes: dict[str, tuple[int, int]] = {}
    read: dict[str, int] = dict.fromkeys(names, 0)
    empty: dict[str, int] = dict.fromkeys(names, 0)
    views: list[View] = []
    for s, cf in zip(sources, got, strict=True):
        if s.name in sizes and sizes[s.name] != cf.size:
            raise InputError(
                str(s.path),
                f"image size {cf.size[0]}x{cf.size[1]} differs from camera {s.name}'s "
                f"other board frames ({sizes[s.name][0]}x{sizes[s.name][1]})",
            )
        sizes[s.name] = cf.size
        read[s.name] += cf.n_read
        empty[s.name] += cf.n_empty
        c = names.index(s.name)
        views += [View(c, v.frame, v.label, v.synced, v.det) for v in cf.views]
    none = [n for n in names if read[n] == empty[n]]
    if none:
        where = ", ".join(str(s.path) for s in sources if s.name in none)
        raise InputError(
            where,
            f"the board ({board.describe()}) was found in none of the frames of camera "
            f"{', '.join(none)}: check its description (the ArUco dictionary, the number "
            "of squares along each side, the marker and square lengths; anipose's "
            "board.toml gives marker_bits and dict_size) and that the frames show the board",
        )
    return BoardViews(
        tuple(names),
        tuple(sizes[n] for n in names),
        tuple(views),
        tuple(read[n] for n in names),
        tuple(empty[n] for n in names),
        tuple(sources),
    )

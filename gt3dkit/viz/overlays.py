"""``gt3d report OUT --frames SOURCE``: the estimate drawn over the user's own frames, one H.264
video per camera (``report/overlays/<camera>.mp4``).

SOURCE holds each camera's frames as the layouts users have them, named by the camera:

    SOURCE/<camera>.mp4                    # a video per camera (.mp4, .avi, .mov, .mkv)
    SOURCE/<camera>/<anything>.mp4         # or one video in the camera's folder (SLEAP, anipose)
    SOURCE/<camera>/*.png|jpg              # or its frames as images, in natural order

Video frame ``f + offset`` shows the annotations' frame ``f`` (``--frame-offset``). Drawn per
frame, in colours that say which is which (the page's legend):

* the annotation as drawn: boxes and keypoints in green;
* the estimate's projection: the ellipsoid's outline, or the skeleton's bones and joints, in the
  track's colour (no green or red);
* its uncertainty, where it projects to more than :data:`SD_SHOWN_PX` pixels: around an
  object's centre the ellipse of its sd (1 sd, the centre's covariance projected), around a
  joint a circle of its sd (the run gives a joint's largest sd, one number);
* the QA flags of that frame and camera (``anomalies.csv``), in red, with their kind.

Frames are read, drawn and written one at a time (memory bounded by a frame), at most
``width`` pixels wide and every ``step``-th frame, with a progress bar. A video that cannot
be decoded, annotations beyond a video's last frame (by how many, and the option that aligns
them), or no camera with frames is one ``error:`` line; a camera without frames among others
that have them is a ``warning:``.
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from gt3dkit.errors import InputError

if TYPE_CHECKING:
    from distributed import Client
from gt3dkit.geom.camera import apply_K, distort, project_points
from gt3dkit.geom.conics import outline_ellipse
from gt3dkit.skeletons import skeleton_of
from gt3dkit.types import F64, Scene, TrackSet

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: BGR colours: the annotation, the QA flags, and the tracks' (no green, no red)
LABEL_BGR = (0, 200, 0)
FLAG_BGR = (0, 0, 255)
TRACK_BGR = ((255, 0, 255), (255, 128, 0), (0, 165, 255), (255, 255, 0), (128, 0, 255), (0, 255, 255),
             (255, 0, 128), (180, 105, 255))
#: an sd is drawn where it projects to more than this (px)
SD_SHOWN_PX = 3.0
#: points along an ellipsoid's outline
OUTLINE_POINTS = 48
#: stills of flagged frames at most (the highest scores first), each a JPEG of the overlay
MAX_STILLS = 200


@dataclass(frozen=True)
class FrameSource:
    """One camera's frames: a video or an image folder, its frame count, rate and size (px)."""

    camera: str
    path: Path
    images: tuple[Path, ...]  # an image folder's files in order; () for a video
    n_frames: int
    fps: float
    width: int
    height: int


def _natural(p: Path) -> list[object]:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


def _source_of(root: Path, camera: str) -> Path | None:
    """The camera's video file or image folder in ``root`` (None: none)."""
    for suffix in VIDEO_SUFFIXES:
        if (root / f"{camera}{suffix}").is_file():
            return root / f"{camera}{suffix}"
    folder = root / camera
    if not folder.is_dir():
        return None
    videos = sorted(p for p in folder.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES and p.is_file())
    if len(videos) > 1:
        raise InputError(str(folder), f"{len(videos)} videos ({', '.join(p.name for p in videos)}): "
                                      "one video per camera")
    if videos:
        return videos[0]
    return folder if any(p.suffix.lower() in IMAGE_SUFFIXES for p in folder.iterdir()) else None


@contextmanager
def _decoder_quiet() -> Iterator[None]:
    """The video decoder's own messages (FFmpeg's, written to the process's stderr by OpenCV)
    kept off the user's terminal: what fails is said once, as an ``error:`` line."""
    sys.stderr.flush()
    try:
        saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    except OSError:
        yield
        return
    os.dup2(devnull, 2)
    try:
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def open_source(path: Path, camera: str) -> FrameSource:
    """A camera's frames, checked: a video that cannot be decoded is an error naming it."""
    if path.is_dir():
        images = tuple(sorted((p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES),
                              key=_natural))
        first = cv2.imread(str(images[0]))
        if first is None:
            raise InputError(str(images[0]), "cannot be read as an image")
        return FrameSource(camera, path, images, len(images), 0.0, first.shape[1], first.shape[0])
    with _decoder_quiet():
        cap = cv2.VideoCapture(str(path))
        try:
            ok, first = cap.read() if cap.isOpened() else (False, None)
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        finally:
            cap.release()
    if not ok or first is None:
        raise InputError(str(path), "cannot be decoded as a video")
    return FrameSource(camera, path, (), n, fps, first.shape[1], first.shape[0])


def find_sources(root: Path, cameras: Sequence[str]) -> tuple[list[FrameSource], list[str]]:
    """Each camera's frames in ``root`` (in the rig's order) and the warnings (a camera without
    any); an error where no camera has frames."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(str(root), "--frames: not a folder")
    found, missing = [], []
    for cam in cameras:
        path = _source_of(root, cam)
        if path is None:
            missing.append(cam)
        else:
            found.append(open_source(path, cam))
    if not found:
        raise InputError(str(root), f"no camera's frames (expected <camera>.mp4, <camera>/<video> or "
                                    f"<camera>/*.png for the cameras {', '.join(cameras)})")
    warnings = [f"--frames: no video or images of camera {c} in {root}: its overlay is left out"
                for c in missing]
    return found, warnings


def check_aligned(src: FrameSource, frames: np.ndarray, offset: int) -> None:
    """An error naming the video where the annotations' frames ``frames`` (shifted by ``offset``)
    fall outside it: by how many frames, and the option that aligns them."""
    lo, hi = int(frames.min()) + offset, int(frames.max()) + offset
    if lo < 0:
        raise InputError(str(src.path), f"frames: the annotations start at frame {lo} of it ({-lo} before "
                                        "its first): --frame-offset N shows annotation frame f at its frame "
                                        f"f + N (now {offset})")
    if src.n_frames and hi >= src.n_frames:
        raise InputError(str(src.path), f"frames: it has {src.n_frames} frames, the annotations reach its "
                                        f"frame {hi} ({hi + 1 - src.n_frames} more): --frame-offset N shows "
                                        f"annotation frame f at its frame f + N (now {offset})")


def read_frames(src: FrameSource) -> Iterator[np.ndarray]:
    """The camera's frames (BGR), one at a time."""
    if src.images:
        for p in src.images:
            img = cv2.imread(str(p))
            if img is None:
                raise InputError(str(p), "cannot be read as an image")
            yield img
        return
    with _decoder_quiet():
        cap = cv2.VideoCapture(str(src.path))
    try:
        while True:
            with _decoder_quiet():
                ok, img = cap.read()
            if not ok:
                return
            yield img
    finally:
        cap.release()


@dataclass(frozen=True)
class Drawing:
    """What one camera's overlay draws, indexed by annotation frame: the labels (boxes ``(N, 4)``,
    keypoints ``(N, J, 2)``), the estimate's rows, the QA flags (frame, track id, kind)."""

    scene: Scene
    tracks: TrackSet
    cam: int
    flags: list[tuple[int, int, str]]
    bones: list[tuple[int, int]]


def _colour(track_id: int) -> tuple[int, int, int]:
    return TRACK_BGR[int(track_id) % len(TRACK_BGR)]


def _pt(xy: F64) -> tuple[int, int]:
    return int(round(float(xy[0]))), int(round(float(xy[1])))


def _project(X: F64, sc: Scene, c: int) -> tuple[F64, F64]:
    """``X (N, 3)`` world points into camera ``c``: ``(N, 2)`` px (NaN behind) and ``(N,)`` depth."""
    rig = sc.rig
    uv, depth = project_points(X, rig.K[c:c + 1], rig.dist[c:c + 1], rig.R[c:c + 1], rig.t[c:c + 1],
                               rig.depth_sign[c:c + 1])
    return uv[:, 0], depth[:, 0]


def draw_frame(img: np.ndarray, d: Drawing, frame: int) -> None:
    """Draw frame ``frame``'s estimate, uncertainty, flags and labels of camera ``d.cam`` on
    ``img`` (BGR, the camera's own size; in place), in that order: the labels stay on top."""
    sc, tr, c = d.scene, d.tracks, d.cam
    rows = np.flatnonzero(tr.frame == frame)
    f_px = float(np.mean(np.diag(sc.rig.cameras[c].K)[:2]))
    for r in rows:
        col = _colour(int(tr.track_id[r]))
        if tr.kpt_world.shape[1]:
            uv, depth = _project(tr.kpt_world[r], sc, c)
            ok = np.isfinite(uv).all(axis=1) & (depth > 0)
            for a, b in d.bones:
                if ok[a] and ok[b]:
                    cv2.line(img, _pt(uv[a]), _pt(uv[b]), col, 2, cv2.LINE_AA)
            for j in np.flatnonzero(ok):
                sd_px = f_px * float(tr.kpt_sd[r, j]) / float(depth[j])
                if sd_px > SD_SHOWN_PX:
                    cv2.circle(img, _pt(uv[j]), int(round(sd_px)), col, 1, cv2.LINE_AA)
                cv2.circle(img, _pt(uv[j]), 4, col, -1, cv2.LINE_AA)
        else:
            _draw_ellipsoid(img, d, int(r), col, f_px)
    for fr, oid, kind in d.flags:
        if fr != frame:
            continue
        at = rows[tr.track_id[rows] == oid] if oid >= 0 else np.zeros(0, np.int64)
        where = (20, 40)
        if at.size:
            uv, depth = _project(tr.center_world[at[:1]], sc, c)
            if np.isfinite(uv).all() and depth[0] > 0:
                where = _pt(uv[0])
        cv2.putText(img, kind, where, cv2.FONT_HERSHEY_SIMPLEX, 0.8, FLAG_BGR, 2, cv2.LINE_AA)
    obs = sc.obs
    for k in np.flatnonzero((obs.frame == frame) & (obs.cam == c)):
        box = obs.box_xyxy_px[k]
        if np.isfinite(box).all():
            cv2.rectangle(img, _pt(box[:2]), _pt(box[2:]), LABEL_BGR, 2)
        if obs.kpt_uv_px.shape[1]:
            for p in obs.kpt_uv_px[k][np.isfinite(obs.kpt_uv_px[k]).all(axis=1)]:
                x, y = _pt(p)
                cv2.line(img, (x - 3, y), (x + 3, y), LABEL_BGR, 2)
                cv2.line(img, (x, y - 3), (x, y + 3), LABEL_BGR, 2)


def _draw_ellipsoid(img: np.ndarray, d: Drawing, r: int, col: tuple[int, int, int], f_px: float) -> None:
    """Row ``r``'s ellipsoid outline (its projection's ellipse, through the lens) and its
    centre's sd."""
    sc, tr, c = d.scene, d.tracks, d.cam
    rig = sc.rig
    m, E, _ = outline_ellipse(tr.center_world[r], tr.semi_axes[r], rig.world_from_body(), rig.R[c:c + 1],
                              rig.t[c:c + 1], rig.depth_sign[c:c + 1])
    if not (np.isfinite(m).all() and np.isfinite(E).all()):
        return
    w, V = np.linalg.eigh(E[0])
    half = V * np.sqrt(np.maximum(w, 0.0))
    a = np.linspace(0, 2 * np.pi, OUTLINE_POINTS)
    xy = m[0][None] + (half @ np.stack([np.cos(a), np.sin(a)])).T  # (P, 2) normalised
    uv = apply_K(distort(xy[:, None], rig.dist[c:c + 1]), rig.K[c:c + 1])[:, 0]
    if np.isfinite(uv).all():
        cv2.polylines(img, [np.round(uv).astype(np.int32)], True, col, 2, cv2.LINE_AA)
    _draw_sd_ellipse(img, sc, c, tr.center_world[r], tr.center_sd[r], col)


def _draw_sd_ellipse(img: np.ndarray, sc: Scene, c: int, centre: F64, sd_xyz: F64,
                     col: tuple[int, int, int]) -> None:
    """The centre's sd (1 sd, the axes' sds ``sd_xyz (3,)``, m) projected into camera ``c``: the
    ellipse ``J diag(sd^2) J^T`` (``J`` the projection's Jacobian, by central differences of
    1 mm), drawn where its larger axis exceeds :data:`SD_SHOWN_PX`."""
    eps = 1e-3
    pts = np.concatenate([centre[None], centre + eps * np.eye(3), centre - eps * np.eye(3)])
    uv, depth = _project(pts, sc, c)
    if not (np.isfinite(uv).all() and (depth > 0).all()):
        return
    J = (uv[1:4] - uv[4:7]).T / (2 * eps)  # (2, 3)
    cov = J @ np.diag(np.asarray(sd_xyz, dtype=np.float64) ** 2) @ J.T
    w, V = np.linalg.eigh(cov)
    a, b = np.sqrt(np.maximum(w[::-1], 0.0))
    if not np.isfinite(a) or a <= SD_SHOWN_PX or a > 4 * max(img.shape):
        return
    angle = float(np.degrees(np.arctan2(V[1, 1], V[0, 1])))  # the larger axis' direction
    cv2.ellipse(img, _pt(uv[0]), (int(round(a)), max(int(round(b)), 1)), angle, 0, 360, col, 1, cv2.LINE_AA)


def drawing_of(scene: Scene, tracks: TrackSet, cam: int, anomalies: list[dict[str, str]]) -> Drawing:
    """What camera ``cam``'s overlay draws."""
    name = scene.rig.cameras[cam].name
    flags = [(int(a["frame"]), int(a["id"]) if a.get("id", "").lstrip("-").isdigit() else -1, a["kind"])
             for a in anomalies if a.get("camera") == name and a.get("frame", "").lstrip("-").isdigit()]
    skel = skeleton_of(scene) if tracks.kpt_world.shape[1] else None
    bones = [(int(a), int(b)) for a, b in skel.bones] if skel is not None else []
    return Drawing(scene, tracks, cam, flags, bones)


@dataclass(frozen=True)
class OverlayOptions:
    """``--frames SOURCE``, ``--frame-offset``, ``--overlay-step`` and ``--overlay-width``."""

    source: Path
    offset: int = 0
    step: int = 1
    width: int = 1280


@dataclass(frozen=True)
class Overlay:
    """One written overlay video: its camera, file (relative to the report), frames and size."""

    camera: str
    file: str
    frames: int
    width: int
    height: int
    fps: float
    source: str


def prepared_sources(scene: Scene, opts: OverlayOptions) -> tuple[list[FrameSource], list[str]]:
    """The cameras' frames for ``scene``, checked before anything is written: every camera with
    annotations has its frames aligned to them (an error otherwise), and the warnings."""
    if opts.step < 1 or opts.width < 16:
        raise InputError("--overlay-step/--overlay-width", "need a step >= 1 and a width >= 16 px")
    sources, warnings = find_sources(opts.source, scene.rig.names)
    for src in sources:
        c = scene.rig.index(src.camera)
        cam = scene.rig.cameras[c]
        if cam.width and cam.height and (src.width, src.height) != (cam.width, cam.height):
            raise InputError(str(src.path), f"its frames are {src.width} x {src.height} px, camera "
                                            f"{cam.name}'s calibration {cam.width} x {cam.height}: the "
                                            "overlays need the frames the calibration was made for")
        frames = scene.obs.frame[scene.obs.cam == c]
        if len(frames):
            check_aligned(src, frames, opts.offset)
    return sources, warnings


def _flagged(anomalies: list[dict[str, str]]) -> dict[str, set[int]]:
    """Camera -> the frames a QA row flags there, the :data:`MAX_STILLS` highest scores."""
    def score(a: dict[str, str]) -> float:
        try:
            return float(a.get("score", ""))
        except ValueError:
            return 0.0

    out: dict[str, set[int]] = {}
    n = 0
    for a in sorted(anomalies, key=lambda a: -score(a)):
        cam, fr = a.get("camera", ""), a.get("frame", "")
        if cam and fr.lstrip("-").isdigit() and int(fr) not in out.get(cam, set()) and n < MAX_STILLS:
            out.setdefault(cam, set()).add(int(fr))
            n += 1
    return out


def still_name(camera: str, frame: int) -> str:
    """A flagged frame's still, relative to the report."""
    return f"overlays/stills/{camera}_{frame:06d}.jpg"


def write_overlays(scene: Scene, tracks: TrackSet, anomalies: list[dict[str, str]],
                   sources: list[FrameSource], opts: OverlayOptions, folder: Path, progress: bool = True,
                   client: Client | None = None) -> tuple[list[Overlay], dict[tuple[int, str], str]]:
    """Each camera's overlay video into ``folder`` (H.264, ``<camera>.mp4``), frame by frame, and
    a still (JPEG) of each flagged frame (:func:`_flagged`); returns the videos and the stills
    by (frame, camera). ``client``: a Dask cluster's (``--scheduler``): each camera drawn by one of
    its workers (``folder`` on a file system they share), the progress by camera."""
    from tqdm import tqdm

    folder.mkdir(parents=True, exist_ok=True)
    flagged = _flagged(anomalies)
    stills: dict[tuple[int, str], str] = {}
    out = []
    if client is not None:
        from distributed import as_completed

        futures = [client.submit(camera_overlay, scene, tracks, anomalies, flagged, src, opts, folder,
                                 None, pure=False) for src in sources]
        with tqdm(total=len(futures), desc="overlays", unit="camera",
                  disable=None if progress else True, leave=False) as bar:
            for _ in as_completed(futures):
                bar.update(1)
        done = [f.result() for f in futures]
    else:
        total = sum(-(-s.n_frames // opts.step) for s in sources)
        with tqdm(total=total, desc="overlays", unit="frame", disable=None if progress else True,
                  leave=False) as bar:
            done = [camera_overlay(scene, tracks, anomalies, flagged, src, opts, folder, bar.update)
                    for src in sources]
    for video, camera_stills in done:
        out.append(video)
        stills.update(camera_stills)
    return out, stills


def camera_overlay(scene: Scene, tracks: TrackSet, anomalies: list[dict[str, str]],
                   flagged: dict[str, set[int]], src: FrameSource, opts: OverlayOptions, folder: Path,
                   tick: Callable[[int], object] | None) -> tuple[Overlay, dict[tuple[int, str], str]]:
    """One camera's overlay video and its flagged frames' stills (``tick(1)`` after each frame)."""
    import imageio_ffmpeg

    c = scene.rig.index(src.camera)
    d = drawing_of(scene, tracks, c, anomalies)
    scale = min(1.0, opts.width / src.width)
    w = 2 * max(int(round(src.width * scale / 2)), 1)
    h = 2 * max(int(round(src.height * scale / 2)), 1)
    fps = (src.fps or scene.fps or 30.0) / opts.step
    path = folder / f"{src.camera}.mp4"
    stills: dict[tuple[int, str], str] = {}
    writer = imageio_ffmpeg.write_frames(str(path), (w, h), fps=fps, codec="libx264",
                                         pix_fmt_in="bgr24", pix_fmt_out="yuv420p",
                                         macro_block_size=2, ffmpeg_log_level="error")
    writer.send(None)
    n = 0
    try:
        for v, img in enumerate(read_frames(src)):
            if v % opts.step:
                continue
            if img.shape[1] != src.width or img.shape[0] != src.height:
                raise InputError(str(src.path), f"frame {v} is {img.shape[1]} x {img.shape[0]} px, "
                                                f"its first {src.width} x {src.height}")
            draw_frame(img, d, v - opts.offset)
            if (w, h) != (src.width, src.height):
                img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
            if v - opts.offset in flagged.get(src.camera, ()):
                name = still_name(src.camera, v - opts.offset)
                (folder.parent / name).parent.mkdir(exist_ok=True)
                cv2.imwrite(str(folder.parent / name), img, [cv2.IMWRITE_JPEG_QUALITY, 85])
                stills[(v - opts.offset, src.camera)] = name
            writer.send(np.ascontiguousarray(img))
            n += 1
            if tick is not None:
                tick(1)
    finally:
        writer.close()
    return Overlay(src.camera, f"overlays/{path.name}", n, w, h, fps, str(src.path)), stills

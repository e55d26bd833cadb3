"""The 3D overview of a reconstruction: cameras as frusta with their names, the ground grid
(1 m cells), every object's ellipsoid (and skeleton) at one frame and every track's path,
rendered by open3d (:mod:`gt3dkit.viz.render3d`); names and the legend are drawn on top with
matplotlib at the pixels where the same pinhole projects them. Drawn to the objects' scale
(:func:`grid_cell_m`): a mouse's joints are not 5 cm balls on a grid of metres."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from gt3dkit.skeletons import skeleton_of
from gt3dkit.types import F64, Camera, Scene, TrackSet
from gt3dkit.viz.render3d import Drawing, Rendering, View, unit_sphere

GRID_COLOUR = (0.80, 0.80, 0.80)
CAMERA_COLOUR = (0.15, 0.15, 0.15)
#: Pixels a camera's centre keeps from the render's edges: any edge, the right (its name) and the
#: top (the caption), so that no frustum, name or caption is cut or covered.
CAMERA_ROOM_PX = (20, 90, 70)


def colour_of(i: int) -> tuple[float, float, float]:
    """The colour of object ``i`` in every picture of a report."""
    import matplotlib

    r, g, b = (float(v) for v in matplotlib.colormaps["tab10"](int(i) % 10)[:3])
    return r, g, b


def object_size_m(tracks: TrackSet) -> float:
    """The objects' typical size (m): the median over rows of a skeleton's extent (its joints'
    largest distance from their middle, twice), else of an ellipsoid's largest diameter; 1.7
    (a person) where there is none."""
    if tracks.kpt_world.shape[1]:
        ok = np.asarray(np.isfinite(tracks.kpt_world).all(axis=-1), dtype=bool)  # (R, J)
        rows = np.asarray(ok.sum(axis=1) >= 2, dtype=bool)
        X, ok = tracks.kpt_world[rows], ok[rows]
        mid = np.where(ok[..., None], X, 0.0).sum(axis=1) / ok.sum(axis=1)[:, None]
        ext = 2.0 * np.where(ok, np.linalg.norm(np.where(ok[..., None], X, 0.0) - mid[:, None], axis=-1),
                             0.0).max(axis=1)
    else:
        ext = 2.0 * np.max(tracks.semi_axes, axis=1) if len(tracks.semi_axes) else np.zeros(0)
    ext = ext[np.isfinite(ext) & (ext > 0)]
    return float(np.median(ext)) if len(ext) else 1.7


def grid_cell_m(size_m: float) -> float:
    """The floor grid's cell (m) for objects of ``size_m``: 1 m for people and anything larger,
    the power of ten at or below the size for smaller ones (0.1 m under a mouse)."""
    return float(min(1.0, 10.0 ** np.floor(np.log10(max(size_m, 1e-3)))))


def _frustum(cam: Camera, depth_m: float) -> tuple[F64, list[tuple[int, int]]]:
    Kinv = np.linalg.inv(cam.K)
    corners = [(0, 0), (cam.width, 0), (cam.width, cam.height), (0, cam.height)]
    rays = [Kinv @ np.array([u, v, 1.0]) for u, v in corners]
    P = [cam.center_world] + [cam.center_world + depth_m * cam.depth_sign * (cam.R.T @ r) for r in rays]
    return np.array(P), [(0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (2, 3), (3, 4), (4, 1)]


def overview_drawing(scene: Scene, tracks: TrackSet, frame: int, tracks_b: TrackSet | None = None,
                     close_up: bool = False) -> tuple[Drawing, View, F64]:
    """The drawing, a view that frames the cameras and the tracks from above and behind (or,
    ``close_up``, the objects at ``frame`` only), and the cameras' centres (C, 3).
    ``tracks_b``: a second estimate whose paths are drawn black (a comparison)."""
    rig = scene.rig
    up, wfb = rig.up, rig.world_from_body()
    cams = np.array([c.center_world for c in rig.cameras])
    fin = np.isfinite(tracks.center_world).all(axis=1)
    P = tracks.center_world[fin]
    lo_t, hi_t = (P.min(axis=0), P.max(axis=0)) if len(P) else (cams.min(axis=0), cams.max(axis=0))
    lo, hi = np.minimum(lo_t, cams.min(axis=0)), np.maximum(hi_t, cams.max(axis=0))
    centre_all = (lo + hi) / 2
    cell = grid_cell_m(object_size_m(tracks))
    size = max(float(np.linalg.norm(hi - lo)), cell)
    d = Drawing()
    # grid on the floor (height 0 along up) under the tracks, whole cells (1 m for people)
    x_ax, y_ax = wfb[:, 0], wfb[:, 1]
    ends = np.array([[lo_t @ x_ax, hi_t @ x_ax], [lo_t @ y_ax, hi_t @ y_ax]]) / cell  # in cells
    area_lo = (np.floor(ends.min(axis=1)) - 1) * cell
    area_hi = (np.ceil(ends.max(axis=1)) + 1) * cell
    pts, segs = [], []
    for a in np.arange(area_lo[0], area_hi[0] + cell / 2, cell):
        pts += [a * x_ax + area_lo[1] * y_ax, a * x_ax + area_hi[1] * y_ax]
        segs.append((len(pts) - 2, len(pts) - 1))
    for b in np.arange(area_lo[1], area_hi[1] + cell / 2, cell):
        pts += [area_lo[0] * x_ax + b * y_ax, area_hi[0] * x_ax + b * y_ax]
        segs.append((len(pts) - 2, len(pts) - 1))
    d.add_lines(np.array(pts), segs, GRID_COLOUR)
    for c in rig.cameras:
        Pc, S = _frustum(c, size / 20)
        d.add_lines(Pc, S, CAMERA_COLOUR)
    for tid in np.unique(tracks.track_id):
        m = (tracks.track_id == tid) & fin
        d.add_polyline(tracks.center_world[m], colour_of(tid))
        if tracks_b is not None:
            mb = (tracks_b.track_id == tid) & np.isfinite(tracks_b.center_world).all(axis=1)
            d.add_polyline(tracks_b.center_world[mb], (0.0, 0.0, 0.0))
    V, F = unit_sphere()
    skeleton = skeleton_of(scene) if tracks.kpt_world.shape[1] else None
    for k in np.flatnonzero((tracks.frame == frame) & fin):
        col = colour_of(tracks.track_id[k])
        if skeleton is not None and np.isfinite(tracks.kpt_world[k]).all(axis=1).sum() >= 2:
            X = tracks.kpt_world[k]
            bones = [(int(a), int(b)) for a, b in skeleton.bones
                     if np.isfinite(X[a]).all() and np.isfinite(X[b]).all()]
            d.add_lines(np.nan_to_num(X), bones, col)
            for x in X[np.isfinite(X).all(axis=1)]:  # joints as small balls
                d.add_mesh(V * 0.025 * cell + x, F, col)
            continue
        d.add_mesh((V * tracks.semi_axes[k]) @ wfb.T + tracks.center_world[k], F, col)
    # the eye: behind the scene's -y side (body frame), raised, looking at the tracks' middle
    centre = (lo_t + hi_t) / 2 if len(P) else centre_all
    span = max(float(np.linalg.norm(hi_t - lo_t)), cell) if len(P) else size
    if close_up:
        now = tracks.center_world[(tracks.frame == frame) & fin]
        if len(now):
            centre = now.mean(axis=0)
            span = max(float(np.linalg.norm(now.max(axis=0) - now.min(axis=0))), 2.0 * cell)
    back = centre - y_ax * (0.9 * span) + up * (0.6 * span)
    view = View(eye=back, centre=centre, up=up)
    # move back until every camera is in the picture with room for its name, and the top band
    # for the caption (or the distance has grown 1.6^8 = 43 times)
    for _ in range(0 if close_up else 8):
        uv = view.project(cams)
        edge, right, top = CAMERA_ROOM_PX
        if np.isfinite(uv).all() and (uv[:, 0] >= edge).all() and (uv[:, 0] < view.width - right).all() \
                and (uv[:, 1] >= top).all() and (uv[:, 1] < view.height - edge).all():
            break
        view = View(eye=centre + 1.6 * (view.eye - centre), centre=centre, up=up)
    return d, view, cams


def _content_box(img: np.ndarray, margin: int = 24) -> tuple[int, int, int, int]:
    """(u0, v0, u1, v1) of the non-white pixels of ``img`` with a margin."""
    ink = (img < 250).any(axis=2)
    if not ink.any():
        return 0, 0, img.shape[1], img.shape[0]
    v, u = np.nonzero(ink)
    return (max(int(u.min()) - margin, 0), max(int(v.min()) - margin - 40, 0),
            min(int(u.max()) + margin, img.shape[1]), min(int(v.max()) + margin, img.shape[0]))


def start_overviews(scene: Scene, tracks: TrackSet, frame: int, pictures: list[tuple[Path, bool]],
                    tracks_b: TrackSet | None = None, title: str = ""
                    ) -> tuple[Rendering, Callable[[], None]]:
    """Render the overview at ``frame`` into each PNG path of ``pictures`` (with its
    ``close_up``), cropped to what it shows, all in one open3d process, started here: it renders
    while the caller goes on (a report draws its panels meanwhile). The returned function waits
    for it and writes the pictures (:class:`RenderError` if open3d cannot render here); the
    :class:`Rendering`, closed first, gives them up."""
    drawn = [overview_drawing(scene, tracks, frame, tracks_b, close_up) for _, close_up in pictures]
    pending = Rendering([(d, view) for d, view, _ in drawn])

    def finish() -> None:
        imgs = pending.result()
        for (path, _), (_, view, cams), img in zip(pictures, drawn, imgs, strict=True):
            _captioned(img, view, cams, scene, tracks, frame, path, tracks_b, title)

    return pending, finish


def _captioned(img: np.ndarray, view: View, cams: F64, scene: Scene, tracks: TrackSet, frame: int,
               path: Path, tracks_b: TrackSet | None, title: str) -> None:
    """The render ``img`` cropped, with the cameras' names, the ids and a caption, into ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    u0, v0, u1, v1 = _content_box(img)
    u0, u1 = (0, view.width) if u1 - u0 < 900 else (u0, u1)  # room for the caption
    fig = plt.figure(figsize=((u1 - u0) / 100, (v1 - v0) / 100), dpi=100)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(img)
    ax.set_xlim(u0, u1)
    ax.set_ylim(v1, v0)
    ax.set_axis_off()
    for c, (u, v) in zip(scene.rig.cameras, view.project(cams), strict=True):
        if np.isfinite(u) and u0 <= u < u1 - 40 and v0 <= v < v1:
            ax.text(u + 6, v - 6, c.name, fontsize=11, color="black",
                    bbox={"facecolor": "white", "alpha": 0.75, "edgecolor": "none", "pad": 1})
    at = tracks.frame == frame
    cell = grid_cell_m(object_size_m(tracks))
    for k in np.flatnonzero(at & np.isfinite(tracks.center_world).all(axis=1)):
        top = tracks.center_world[k] + scene.rig.up * (tracks.semi_axes[k, 2] + 0.15 * cell)
        X = tracks.kpt_world[k] if tracks.kpt_world.shape[1] else np.zeros((0, 3))
        X = X[np.isfinite(X).all(axis=1)]
        if len(X):  # above the highest joint
            top = X[np.argmax(X @ scene.rig.up)] + 0.15 * cell * scene.rig.up
        (u, v), = view.project(top[None])
        if np.isfinite(u) and 0 <= u < view.width and 0 <= v < view.height:
            ax.text(u, v, str(int(tracks.track_id[k])), fontsize=9, ha="center", va="bottom",
                    color=colour_of(tracks.track_id[k]), fontweight="bold")
    what = "skeletons" if scene.skeleton and tracks.kpt_world.shape[1] else "ellipsoids"
    ax.text(u0 + 12, v0 + 8, (title + "\n" if title else "") +
            f"frame {frame}: {int(at.sum())} {what} (labels: ids); coloured lines: every track's path"
            + ("; black: the other estimator's" if tracks_b is not None else "")
            + f"; grid: {cell:g} m cells on the floor", fontsize=12, va="top",
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"})
    fig.savefig(path)
    plt.close(fig)

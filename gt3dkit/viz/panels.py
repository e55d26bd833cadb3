"""Matplotlib pictures of a reconstruction against its annotations, at each camera's pixels.

:func:`view_residuals` projects the estimate into every annotated view (the exact tangent box
of the ellipsoid, the keypoints); the pictures draw annotations solid / as dots and the
estimate dashed / as crosses, over the real image where the dataset has one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gt3dkit.geom.camera import project_points
from gt3dkit.geom.conics import model_boxes
from gt3dkit.qa.anomalies import track_row_of
from gt3dkit.qa.view import PreparedView
from gt3dkit.skeletons import skeleton_of
from gt3dkit.types import F64, I64, Scene, TrackSet
from gt3dkit.viz.overview import colour_of

if TYPE_CHECKING:
    from matplotlib.axes import Axes

ANNOTATION_NOTE = "annotation: solid box / dots; estimate: dashed box / crosses"


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


@dataclass(frozen=True)
class ViewResiduals:
    """The estimate projected into the views of the input rows it has (``n`` of them).

    rows : (n,) rows of ``pre.rows``; r_of : (n,) rows of the tracks
    frame, obj : (n,) frame number and object id
    box, box_z : (n, C, 4) projected tangent box and annotated box (px, NaN missing)
    box_err : (n, C, 4) absolute edge residuals of the usable edges (px, NaN otherwise)
    kpt, kpt_z : (n, C, J, 2) projected and annotated keypoints (px); kpt_err : (n, C, J) px
    view_err : (n, C) mean residual of each annotated view (px, NaN where not annotated)
    """

    rows: I64
    r_of: I64
    frame: I64
    obj: I64
    box: F64 | None
    box_z: F64 | None
    box_err: F64 | None
    kpt: F64 | None
    kpt_z: F64 | None
    kpt_err: F64 | None
    view_err: F64


def view_residuals(tracks: TrackSet, pre: PreparedView) -> ViewResiduals:
    rows, cams = pre.rows, pre.cams
    r_of = track_row_of(tracks, rows)
    idx = np.flatnonzero(r_of >= 0)
    r_of = r_of[idx]
    box = box_z = box_err = kpt = kpt_z = kpt_err = None
    parts = []
    if pre.use_box:
        box, _ = model_boxes(tracks.center_world[r_of], tracks.semi_axes[r_of], cams)
        box_z = rows.box_z[idx]
        box_err = np.where(rows.box_mask[idx], np.abs(box - box_z), np.nan)
        parts.append(box_err)
    if pre.use_kpt and tracks.kpt_world.shape[1]:
        uv, _ = project_points(tracks.kpt_world[r_of], cams.K, cams.dist, cams.R, cams.t, cams.depth_sign)
        kpt, kpt_z = np.swapaxes(uv, 1, 2), rows.kpt_z[idx]
        kpt_err = np.linalg.norm(kpt - kpt_z, axis=-1)
        parts.append(kpt_err)
    if parts:
        stacked = np.concatenate(parts, axis=2)
        n = np.isfinite(stacked).sum(axis=2)
        view_err = np.where(n > 0, np.nansum(np.nan_to_num(stacked, nan=0.0), axis=2) / np.maximum(n, 1),
                            np.nan)
    else:
        view_err = np.full((len(idx), len(pre.cams.K)), np.nan)
    return ViewResiduals(idx, r_of, rows.frames[rows.row_t[idx]], rows.obj_ids[rows.row_o[idx]],
                         box, box_z, box_err, kpt, kpt_z, kpt_err, view_err)


def camera_image(scene: Scene, cam: int, frame: int) -> np.ndarray | None:
    """The dataset's own image of camera ``cam`` at ``frame`` when it has one
    (``Image_subsets/C<n>/<frame>.png|jpg`` as WILDTRACK and MultiviewX ship them, or
    ``images/<camera>/<frame>.png|jpg``), else None."""
    root = Path(scene.root) if scene.root else None
    if root is None:
        return None
    name = scene.rig.cameras[cam].name
    folders = [root / "Image_subsets" / f"C{cam + 1}", root / "images" / name]
    for d in folders:
        for stem in (f"{frame:08d}", f"{frame:04d}", str(frame)):
            for ext in (".png", ".jpg", ".jpeg"):
                p = d / (stem + ext)
                if p.is_file():
                    try:
                        import matplotlib.image as mpimg

                        return mpimg.imread(p)
                    except (OSError, ValueError, SyntaxError):
                        return None
    return None


def _points(res: ViewResiduals, n: int, c: int, estimate: bool) -> F64:
    """(k, 2) pixels of residual row ``n`` in camera ``c``: the estimate's box corners and
    keypoints, or the annotation's."""
    pts = []
    box, kpt = (res.box, res.kpt) if estimate else (res.box_z, res.kpt_z)
    if box is not None and np.isfinite(box[n, c]).all():
        pts += [box[n, c, :2], box[n, c, 2:]]
    if kpt is not None:
        p = kpt[n, c]
        pts += list(p[np.isfinite(p).all(axis=1)])
    return np.array(pts).reshape(-1, 2)


def draw_view(ax: Axes, scene: Scene, res: ViewResiduals, cam: int, sel: np.ndarray,
              skeleton_bones: list[tuple[int, int]] | None = None, lw: float = 1.6,
              mark: tuple[int, int | None] | None = None, focus: int | None = None) -> None:
    """Draw the annotations and the projected estimate of the residual rows ``sel`` in camera
    ``cam`` onto ``ax`` (pixel axes); ``mark`` = (row, joint) circles that row's joint (or its
    box) in red; ``focus`` = a row drawn in full, the others faded (crowded anomaly pictures)."""
    plt = _plt()
    for n in sel:
        col: tuple[float, ...] = colour_of(res.obj[n])
        ink: tuple[float, ...] = (0.0, 0.0, 0.0)
        if focus is not None and n != focus:  # the others stay as context, faded
            col, ink = (*col, 0.25), (0.0, 0.0, 0.0, 0.25)
        if res.box_z is not None and res.box is not None and np.isfinite(res.box_z[n, cam]).all():
            for b, ls in ((res.box_z[n, cam], "-"), (res.box[n, cam], "--")):
                if np.isfinite(b).all():
                    ax.add_patch(plt.Rectangle((b[0], b[1]), b[2] - b[0], b[3] - b[1], fill=False,
                                               edgecolor=col, linestyle=ls, linewidth=lw))
            ax.text(res.box_z[n, cam, 0], res.box_z[n, cam, 1] - 4, str(int(res.obj[n])), color=col,
                    fontsize=8, fontweight="bold", clip_on=True)
            if mark is not None and mark[0] == n and mark[1] is None:
                b = res.box_z[n, cam]
                ax.add_patch(plt.Rectangle((b[0], b[1]), b[2] - b[0], b[3] - b[1], fill=False,
                                           edgecolor="red", linewidth=lw + 1.5, alpha=0.5))
        if res.kpt_z is not None and res.kpt is not None:
            z, p = res.kpt_z[n, cam], res.kpt[n, cam]
            seen = np.isfinite(z[:, 0])
            if not seen.any():
                continue
            for a, b in skeleton_bones or []:
                if seen[a] and seen[b]:
                    ax.plot(z[[a, b], 0], z[[a, b], 1], "-", color=col, lw=0.8, alpha=0.6)
            ax.plot(z[seen, 0], z[seen, 1], "o", ms=4, color=col)
            ax.plot(p[seen, 0], p[seen, 1], "x", ms=3.5, color=ink, mew=0.8)
            top = int(np.flatnonzero(seen)[np.argmin(z[seen, 1])])
            ax.text(z[top, 0], z[top, 1] - 8, str(int(res.obj[n])), color=col, fontsize=8, fontweight="bold",
                    clip_on=True)
            if mark is not None and mark[0] == n and mark[1] is not None and 0 <= mark[1] < len(z) \
                    and seen[mark[1]]:
                j = mark[1]
                ax.plot(*z[j], "o", ms=14, mfc="none", mec="red", mew=2)
                if np.isfinite(p[j]).all():
                    ax.annotate("", xy=z[j], xytext=p[j], arrowprops={"arrowstyle": "->", "color": "red"})


def _bones(scene: Scene) -> list[tuple[int, int]] | None:
    skel = skeleton_of(scene)
    return [(int(a), int(b)) for a, b in skel.bones] if skel is not None else None


def worst_frames(scene: Scene, res: ViewResiduals, folder: Path) -> list[tuple[str, str]]:
    """Per camera, the frame where its annotations disagree most with the estimate: one PNG
    at the camera's image size. Returns (file, caption) pairs."""
    plt = _plt()
    out = []
    bones = _bones(scene)
    for c, cam in enumerate(scene.rig.cameras):
        col = res.view_err[:, c]
        ok = np.isfinite(col)
        if not ok.any():
            continue
        worst = np.full(int(res.frame.max()) + 1 if len(res.frame) else 1, -1.0)
        np.maximum.at(worst, res.frame[ok], col[ok])
        f = int(np.argmax(worst))
        sel = np.flatnonzero(res.frame == f)
        aspect = cam.height / cam.width
        fig, ax = plt.subplots(figsize=(8, 8 * aspect + 0.6), dpi=100)
        img = camera_image(scene, c, f)
        if img is not None:
            ax.imshow(img, extent=(0, cam.width, cam.height, 0))
        else:
            ax.set_facecolor("#f2f2f2")
        ax.set_xlim(0, cam.width)
        ax.set_ylim(cam.height, 0)
        ax.set_aspect("equal")
        draw_view(ax, scene, res, c, sel, bones)
        ax.set_title(f"{cam.name}, frame {f}: its worst view has a mean residual of {worst[f]:.1f} px\n"
                     f"{ANNOTATION_NOTE}", fontsize=10)
        ax.tick_params(labelsize=7)
        fig.tight_layout()
        name = f"camera_{c:02d}.png"
        fig.savefig(folder / name)
        plt.close(fig)
        out.append((name, f"{cam.name}: frame {f} ({cam.width} x {cam.height} px"
                          f"{', over the dataset image' if img is not None else ''})"))
    return out


def residual_histograms(scene: Scene, res: ViewResiduals, folder: Path) -> str:
    """Per camera, the histogram of its reprojection residuals (box edges and keypoints, px)."""
    plt = _plt()
    C = len(scene.rig.cameras)
    cols = min(C, 4)
    nrow = int(np.ceil(C / cols))
    fig, axes = plt.subplots(nrow, cols, figsize=(3.4 * cols, 2.6 * nrow), dpi=100, squeeze=False)
    vals_all = [a[:, :].reshape(len(a), C, -1) for a in (res.box_err, res.kpt_err) if a is not None]
    allv = np.concatenate([v.ravel() for v in vals_all]) if vals_all else np.zeros(0)
    allv = allv[np.isfinite(allv)]
    top = max(float(np.percentile(allv, 99)), 1e-3) if allv.size else 1.0
    for c in range(nrow * cols):
        ax = axes.flat[c]
        if c >= C:
            ax.set_axis_off()
            continue
        v = np.concatenate([a[:, c].ravel() for a in vals_all]) if vals_all else np.zeros(0)
        v = v[np.isfinite(v)]
        if v.size:
            counts, edges = np.histogram(np.clip(v, 0, top), bins=40, range=(0, top))
            ax.stairs(counts, edges, fill=True, color="#4477aa")  # one artist, not 40 bars
            ax.set_title(f"{scene.rig.cameras[c].name}: median {np.median(v):.2f}, p95 "
                         f"{np.percentile(v, 95):.1f} px", fontsize=9)
        else:
            ax.set_title(f"{scene.rig.cameras[c].name}: no annotations", fontsize=9)
        ax.set_xlabel("reprojection residual (px; last bin: 99th percentile and beyond)", fontsize=7)
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(folder / "residuals.png")
    plt.close(fig)
    return "residuals.png"


def track_plots(tracks: TrackSet, res: ViewResiduals, folder: Path) -> str:
    """Per track over time: its mean reprojection residual (px) and its centre's sd (mm)."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(10, 6.4), dpi=100, sharex=True)
    ids = np.unique(tracks.track_id)
    for tid in ids:
        m = res.obj == tid
        if m.any():
            e = np.nanmean(np.where(np.isfinite(res.view_err[m]), res.view_err[m], np.nan), axis=1) \
                if np.isfinite(res.view_err[m]).any() else np.full(m.sum(), np.nan)
            o = np.argsort(res.frame[m])
            a1.plot(res.frame[m][o], e[o], color=colour_of(tid), lw=1.0, label=f"{tid}")
        mt = tracks.track_id == tid
        a2.plot(tracks.frame[mt], 1000 * tracks.center_sd[mt].max(axis=1), color=colour_of(tid), lw=1.0)
    a1.set_ylabel("mean residual of\nits views (px)")
    a1.set_title("each track (colour = id, as in every picture): reprojection residual and uncertainty")
    a2.set_yscale("log")
    from matplotlib.ticker import FormatStrFormatter

    a2.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    a2.yaxis.set_minor_formatter(FormatStrFormatter("%g"))
    a2.set_ylabel("centre sd,\nlargest axis (mm)")
    a2.set_xlabel("frame")
    if len(ids) <= 20:
        a1.legend(fontsize=7, ncol=10, title="id", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(folder / "tracks.png")
    plt.close(fig)
    return "tracks.png"


def anomaly_thumbnail(scene: Scene, res: ViewResiduals, frame: int, obj: int, camera: str,
                      joint: int | None, path: Path, max_views: int = 4, before: int | None = None) -> bool:
    """A small picture of the views involved in one anomaly: the flagged view (red title)
    and the object's other views at that frame, each cropped around the object. ``before``: a
    frame to show above it, each view cropped around the object there (an identity split: where
    the id was, and where its views put it now). False when there is nothing to draw."""
    plt = _plt()
    frames = [f for f in (before, frame) if f is not None]
    found = [_thumbnail_views(scene, res, f, obj, camera, max_views) for f in frames]
    if not found[-1]:
        return False
    picks = [p for p in found if p]
    width = max(len(p[1]) for p in picks)
    fig, axes = plt.subplots(len(picks), width, figsize=(2.4 * width, 2.6 * len(picks)), dpi=90,
                             squeeze=False)
    labels = ("before", "now") if len(picks) > 1 else ("",)
    bones = _bones(scene)
    for row, (n, cams), label in zip(axes, picks, labels, strict=True):
        for ax, c in zip(row, cams, strict=False):
            _thumbnail_view(ax, scene, res, (n, c), (camera, joint), bones,
                            f"{label} (frame {int(res.frame[n])}): " if label else "")
        for ax in row[len(cams):]:
            ax.set_axis_off()
    fig.subplots_adjust(left=0.01, right=0.99, top=0.86 if len(picks) == 1 else 0.93, bottom=0.02,
                        wspace=0.06, hspace=0.15)
    fig.savefig(path)
    plt.close(fig)
    return True


def _thumbnail_views(scene: Scene, res: ViewResiduals, frame: int, obj: int, camera: str,
                     max_views: int) -> tuple[int, list[int]] | None:
    """The residual row of ``obj`` at ``frame`` and the cameras to draw it in (the flagged
    camera first, then the worst-fitting views), or None."""
    names = scene.rig.names
    rows = np.flatnonzero((res.frame == frame) & (res.obj == obj))
    if not len(rows):
        return None
    n = int(rows[0])
    seen = np.isfinite(res.view_err[n])
    if res.box_z is not None:
        seen |= np.isfinite(res.box_z[n]).all(axis=1)
    if res.kpt_z is not None:
        seen |= np.isfinite(res.kpt_z[n][..., 0]).any(axis=1)
    cams = [names.index(camera)] if camera in names else []  # drawn even unannotated (missing_view)
    cams += [int(c) for c in np.argsort(-np.nan_to_num(res.view_err[n], nan=-1)) if seen[c] and c not in cams]
    cams = cams[:max_views]
    return (n, cams) if cams else None


def _thumbnail_view(ax: Axes, scene: Scene, res: ViewResiduals, row_cam: tuple[int, int],
                    flag: tuple[str, int | None], bones: list[tuple[int, int]] | None, prefix: str) -> None:
    """Camera ``c``'s view of residual row ``n`` (``row_cam``), cropped around the object; the
    flagged ``(camera, joint)`` marked."""
    (n, c), (camera, joint) = row_cam, flag
    names = scene.rig.names
    frame = int(res.frame[n])
    others = np.flatnonzero(res.frame == frame)
    core = _points(res, n, c, estimate=True)
    extra = _points(res, n, c, estimate=False)
    if not len(core):
        core, extra = extra, core
    if not len(core):
        ax.set_axis_off()
        return
    lo, hi = core.min(axis=0), core.max(axis=0)
    size = max(float((hi - lo).max()), 20.0)
    far = 0
    if len(extra):  # annotations near the estimate widen the crop; far-off ones are counted
        d = np.maximum(np.maximum(lo - extra, extra - hi), 0).max(axis=1)
        near = extra[d <= size]
        far = int((d > size).sum())
        if len(near):
            lo, hi = np.minimum(lo, near.min(axis=0)), np.maximum(hi, near.max(axis=0))
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    half = np.maximum(half, 0.75 * half.max())  # not a sliver: a tall person gets some width
    lo, hi = mid - half, mid + half
    pad = 0.3 * max(float((hi - lo).max()), 20.0)
    cam = scene.rig.cameras[c]
    img = camera_image(scene, c, frame)
    if img is not None:
        ax.imshow(img, extent=(0, cam.width, cam.height, 0))
    else:
        ax.set_facecolor("#f2f2f2")
    flagged = names[c] == camera
    draw_view(ax, scene, res, c, others, bones, lw=1.4, mark=(n, joint) if flagged else None, focus=n)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(hi[1] + pad, lo[1] - pad)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(prefix + names[c] + (f" ({far} point{'s' if far > 1 else ''} far off)" if far else ""),
                 fontsize=8, color="red" if flagged else "black")

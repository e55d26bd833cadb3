"""The board calibration's report: ``index.html`` with per camera the reprojection error (RMS, p95,
the worst views, the views left out and why), where the corners covered the image (where the
calibration can be trusted), the rig and the board poses in 3D. matplotlib, written to PNG beside
the page: the folder opens from disk and can be zipped and sent."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np

from gt3dkit.calib.boardcal import BoardCalibration


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def coverage_picture(cal: BoardCalibration, path: Path) -> None:
    """Per camera the image rectangle, every corner the fit used, the lens model's valid disc."""
    plt = _plt()
    C = len(cal.cameras)
    cols = min(C, 3)
    rows = (C + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), squeeze=False)
    for ax, rep, cam in zip(axes.flat, cal.cameras, cal.rig.cameras, strict=False):
        uv = rep.uv_used_px
        h, _, _ = np.histogram2d(uv[:, 0], uv[:, 1], bins=(8, 8), range=((0, cam.width), (0, cam.height)))
        covered = float((h > 0).mean())
        ax.imshow(
            (h.T > 0), extent=(0, cam.width, cam.height, 0), cmap="Greens", alpha=0.35, vmin=0, vmax=1.5
        )
        ax.scatter(uv[:, 0], uv[:, 1], s=1, c="tab:blue")
        if cam.valid_radius_px is not None:
            t = np.linspace(0, 2 * np.pi, 200)
            ax.plot(
                cam.K[0, 2] + cam.valid_radius_px * np.cos(t),
                cam.K[1, 2] + cam.valid_radius_px * np.sin(t),
                "r--",
                lw=1,
            )
        ax.set_xlim(0, cam.width)
        ax.set_ylim(cam.height, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{cam.name}: {covered:.0%} of the image's 8x8 cells", fontsize=9)
    for ax in list(axes.flat)[C:]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def rig_picture(cal: BoardCalibration, path: Path) -> None:
    """The cameras (as frusta of their images) and the board's outline at every pose, drawn with the
    rig's up vertical (``Rig.world_from_body``: in a camera's frame, up is its image's up)."""
    plt = _plt()
    fig = plt.figure(figsize=(7.5, 6.5))
    ax = fig.add_subplot(projection="3d")
    view = cal.rig.world_from_body()  # (3, 3): display = X_world @ view, z along up

    def show(X_world: np.ndarray) -> np.ndarray:
        return X_world @ view

    nx, ny = cal.board.inner
    outline = cal.board.corners_board()[[0, nx - 1, nx * ny - 1, nx * (ny - 1), 0]]
    pts = [show(np.array([c.center_world for c in cal.rig.cameras]))]
    for T in cal.frame_poses.values():
        Y = show(outline @ T[:3, :3].T + T[:3, 3])
        pts.append(Y)
        ax.plot(Y[:, 0], Y[:, 1], Y[:, 2], "-", lw=0.8, color="0.55")
    allp = np.concatenate(pts)
    depth = 0.12 * float(np.ptp(allp, axis=0).max())
    for c in cal.rig.cameras:
        wh = np.array([[0, 0], [c.width, 0], [c.width, c.height], [0, c.height]], dtype=np.float64)
        ray = np.c_[(wh - c.K[:2, 2]) / np.diag(c.K)[:2], np.ones(4)] * depth  # image corners, camera frame
        corners = show((ray - c.t) @ c.R)  # X_world = R^T (X_cam - t)
        o = show(c.center_world)
        for q in corners:
            ax.plot([o[0], q[0]], [o[1], q[1]], [o[2], q[2]], "-", lw=0.8, color="tab:red")
        loop = corners[[0, 1, 2, 3, 0]]
        ax.plot(loop[:, 0], loop[:, 1], loop[:, 2], "-", lw=1.2, color="tab:red")
        ax.text(o[0], o[1], o[2], f" {c.name}", fontsize=9)
    ax.set_xlabel("m")
    ax.set_ylabel("m")
    ax.set_zlabel("m (up)")
    mid, half = allp.mean(0), 0.55 * np.ptp(allp, axis=0).max()
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_title(f"{len(cal.rig.cameras)} cameras (red) and {len(cal.frame_poses)} board poses (grey)\n"
                 f"{cal.rig.frame_name}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def write_board_report(cal: BoardCalibration, folder: Path, command: str) -> None:
    """``folder/index.html`` and its pictures."""
    folder.mkdir(parents=True, exist_ok=True)
    coverage_picture(cal, folder / "coverage.png")
    rig_picture(cal, folder / "rig.png")
    e = html.escape
    rows = []
    for rep, cam in zip(cal.cameras, cal.rig.cameras, strict=True):
        worst = ", ".join(f"{e(v)} ({r:.2f} px)" for v, r in rep.worst)
        held = "" if rep.holdout_rms_px is None else f"{rep.holdout_rms_px:.3f}"
        rows.append(
            f"<tr><td>{e(rep.name)}</td><td>{rep.views_used}</td><td>{rep.rms_px:.3f}</td>"
            f"<td>{rep.p95_px:.3f}</td><td>{held}</td><td>{cam.K[0, 0]:.1f} &plusmn; {rep.focal_sd_px:.2f}"
            f"</td><td>{cam.K[1, 1]:.1f}</td><td>{cam.K[0, 2]:.1f}, {cam.K[1, 2]:.1f}</td>"
            f"<td>{e(cam.lens)} {e(str(np.round(cam.coefficients, 4).tolist()))}"
            f"</td><td>{rep.centre_sd_mm:.2f}</td>"
            f"<td>{rep.rotation_sd_deg:.3f}</td><td>{worst}</td></tr>"
        )
    dropped = [f"<li>{e(rep.name)}, {e(v)}: {e(w)}</li>" for rep in cal.cameras for v, w in rep.dropped]
    warn = [f"<li>{e(w)}</li>" for w in cal.warnings]
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>gt3dkit board calibration</title>
<style>body{{font-family:sans-serif;margin:2em}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:3px 6px;font-size:13px}}</style></head><body>
<h1>Board calibration</h1>
<p>{e(cal.board.describe())}; world frame: {e(cal.rig.frame_name)}.</p>
<p><code>{e(command)}</code></p>
<h2>Cameras</h2>
<table><tr><th>camera</th><th>views</th><th>RMS px</th><th>p95 px</th><th>held-out RMS px</th>
<th>fx px (&plusmn; sd)</th><th>fy px</th><th>principal point px</th><th>lens: pinhole k1 k2 p1 p2 k3,
fisheye k1 k2 k3 k4</th>
<th>centre sd mm</th><th>rotation sd &deg;</th><th>worst views</th></tr>
{"".join(rows)}</table>
<p>Held-out frames (left out of every fit, their board poses found with the rig held):
{", ".join(map(str, cal.holdout_frames)) or "none"}.</p>
<h2>Views left out</h2><ul>{"".join(dropped) or "<li>none</li>"}</ul>
<h2>Warnings</h2><ul>{"".join(warn) or "<li>none</li>"}</ul>
<h2>Where the corners covered the images</h2>
<p>The calibration is trusted where corners were seen (green cells); the red circle, where shown, is where
the lens model turns back.</p><img src="coverage.png" alt="coverage">
<h2>The rig and the board poses</h2><img src="rig.png" alt="rig">
</body></html>"""
    (folder / "index.html").write_text(page, encoding="utf-8")

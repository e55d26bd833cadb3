"""``report/scene.html``: the scene in 3D over time, to turn around and scrub through.

A self-contained page (it opens from disk with no server and no network): plotly's JavaScript
is written into it from the ``plotly`` package (a maintained library whose ``plotly.min.js``
ships inside its Python wheel; chosen over a vendored three.js viewer for its 3D camera controls,
sliders, animation and hover without code of ours to keep). It shows

* the cameras (their centres, named) and each object's path (its centres over the run);
* at the slider's frame, the estimate: skeletons (bones and joints) or ellipsoids (three
  principal outlines), each in its track's colour, hovering a joint or a centre shows the
  object's id and its sd (mm);
* a frame slider and a play button;
* beside it, where the report has overlays (``--frames``), each camera's overlay video held at
  the slider's frame.

At most :data:`MAX_FRAMES` frames are on the slider (every ``step``-th frame of the run, stated
on the page), so the page's size is bounded whatever the recording's length.
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from gt3dkit.skeletons import skeleton_of
from gt3dkit.types import F64, Scene, TrackSet
from gt3dkit.viz.overlays import TRACK_BGR, Overlay

#: frames on the slider at most (the page: ~5 MB of plotly, and each frame's traces, in mm)
MAX_FRAMES = 300
#: points along each of an ellipsoid's three principal outlines
RING_POINTS = 16


def _rgb(track_id: int) -> str:
    b, g, r = TRACK_BGR[int(track_id) % len(TRACK_BGR)]
    return f"rgb({r},{g},{b})"


def _mm(x: float) -> float:
    """A coordinate (m) to the millimetre: the page's numbers no longer than they mean."""
    return round(float(x), 3)


def _ellipsoid_rings(centre: F64, axes: F64, world_from_body: F64) -> F64:
    """``(3 * (RING_POINTS + 1), 3)`` the three principal outlines of an ellipsoid, NaN-separated."""
    a = np.linspace(0, 2 * np.pi, RING_POINTS)
    c, s = np.cos(a), np.sin(a)
    z = np.zeros_like(a)
    out = []
    for u, v in ((0, 1), (0, 2), (1, 2)):
        p = np.stack([z, z, z], axis=1)
        p[:, u], p[:, v] = axes[u] * c, axes[v] * s
        out += [centre + p @ world_from_body.T, np.full((1, 3), np.nan)]
    return np.concatenate(out)


def _frame_traces(scene: Scene, tracks: TrackSet, frame: int, bones: list[tuple[int, int]]
                  ) -> list[dict[str, object]]:
    """The estimate's traces at ``frame``: one lines trace (bones or outlines) and one markers
    trace (joints or centres, hovered for id and sd), each in every track's colour."""
    rows = np.flatnonzero(tracks.frame == frame)
    lx: list[float | None] = []
    ly: list[float | None] = []
    lz: list[float | None] = []
    lcol: list[str] = []
    mx, my, mz, mcol, text = [], [], [], [], []
    wfb = scene.rig.world_from_body()
    for r in rows:
        tid = int(tracks.track_id[r])
        col = _rgb(tid)
        if tracks.kpt_world.shape[1]:
            X = tracks.kpt_world[r]
            for a, b in bones:
                if np.isfinite(X[[a, b]]).all():
                    for p in (X[a], X[b]):
                        lx.append(_mm(p[0]))
                        ly.append(_mm(p[1]))
                        lz.append(_mm(p[2]))
                        lcol.append(col)
                    lx.append(None)
                    ly.append(None)
                    lz.append(None)
                    lcol.append(col)
            ok = np.isfinite(X).all(axis=1)
            for j in np.flatnonzero(ok):
                mx.append(_mm(X[j, 0]))
                my.append(_mm(X[j, 1]))
                mz.append(_mm(X[j, 2]))
                mcol.append(col)
                text.append(f"id {tid}, joint {j}<br>sd {1000 * float(tracks.kpt_sd[r, j]):.1f} mm")
        else:
            ring = _ellipsoid_rings(tracks.center_world[r], tracks.semi_axes[r], wfb)
            for p in ring:
                fin = np.isfinite(p).all()
                lx.append(_mm(p[0]) if fin else None)
                ly.append(_mm(p[1]) if fin else None)
                lz.append(_mm(p[2]) if fin else None)
                lcol.append(col)
            c = tracks.center_world[r]
            mx.append(_mm(c[0]))
            my.append(_mm(c[1]))
            mz.append(_mm(c[2]))
            mcol.append(col)
            text.append(f"id {tid}<br>sd {1000 * float(np.max(tracks.center_sd[r])):.0f} mm")
    lines = {"type": "scatter3d", "mode": "lines", "x": lx, "y": ly, "z": lz, "hoverinfo": "skip",
             "line": {"color": lcol, "width": 4}, "showlegend": False, "name": "estimate"}
    markers = {"type": "scatter3d", "mode": "markers", "x": mx, "y": my, "z": mz, "text": text,
               "hovertemplate": "%{text}<extra></extra>", "marker": {"color": mcol, "size": 4},
               "showlegend": False, "name": "objects"}
    return [lines, markers]


def scene_figure(scene: Scene, tracks: TrackSet) -> tuple[dict[str, object], list[int], int]:
    """The figure (plotly's JSON form), the slider's frames and the step between them."""
    frames = np.unique(tracks.frame)
    step = max(1, -(-len(frames) // MAX_FRAMES))
    shown = [int(f) for f in frames[::step]]
    skel = skeleton_of(scene) if tracks.kpt_world.shape[1] else None
    bones = [(int(a), int(b)) for a, b in skel.bones] if skel is not None else []
    centres = np.array([c.center_world for c in scene.rig.cameras])
    static: list[dict[str, object]] = [{
        "type": "scatter3d", "mode": "markers+text", "x": centres[:, 0].tolist(), "y": centres[:, 1].tolist(),
        "z": centres[:, 2].tolist(), "text": list(scene.rig.names), "marker": {"size": 5, "color": "black",
                                                                              "symbol": "diamond"},
        "hovertemplate": "camera %{text}<extra></extra>", "showlegend": False, "name": "cameras"}]
    for tid in np.unique(tracks.track_id):
        m = np.flatnonzero(tracks.track_id == tid)
        m = m[np.argsort(tracks.frame[m])]
        c = tracks.center_world[m]
        static.append({"type": "scatter3d", "mode": "lines", "x": c[:, 0].tolist(), "y": c[:, 1].tolist(),
                       "z": c[:, 2].tolist(), "line": {"color": _rgb(int(tid)), "width": 2, "dash": "dot"},
                       "hoverinfo": "skip", "showlegend": False, "name": f"path {int(tid)}"})
    n_static = len(static)
    first = _frame_traces(scene, tracks, shown[0], bones)
    anim = [{"name": str(f), "data": _frame_traces(scene, tracks, f, bones),
             "traces": [n_static, n_static + 1]} for f in shown]
    slider = {"active": 0, "currentvalue": {"prefix": "frame "}, "pad": {"t": 30},
              "steps": [{"label": str(f), "method": "animate",
                         "args": [[str(f)], {"mode": "immediate", "frame": {"duration": 0, "redraw": True},
                                             "transition": {"duration": 0}}]} for f in shown]}
    play = {"type": "buttons", "showactive": False, "x": 0.0, "y": 0.0, "xanchor": "left", "yanchor": "top",
            "buttons": [{"label": "play", "method": "animate",
                         "args": [None, {"frame": {"duration": 120, "redraw": True}, "fromcurrent": True,
                                         "transition": {"duration": 0}}]},
                        {"label": "pause", "method": "animate",
                         "args": [[None], {"mode": "immediate", "frame": {"duration": 0, "redraw": False}}]}]}
    layout = {"scene": {"aspectmode": "data", "xaxis": {"title": {"text": "x (m)"}},
                        "yaxis": {"title": {"text": "y (m)"}}, "zaxis": {"title": {"text": "z (m)"}}},
              "margin": {"l": 0, "r": 0, "t": 10, "b": 0}, "height": 640, "sliders": [slider],
              "updatemenus": [play], "uirevision": "keep"}
    return {"data": static + first, "layout": layout, "frames": anim}, shown, step


def write_scene_page(scene: Scene, tracks: TrackSet, folder: Path, overlays: list[Overlay],
                     frame_offset: int, overlay_step: int) -> str:
    """``folder/scene.html``; returns its name."""
    import plotly.offline

    fig, shown, step = scene_figure(scene, tracks)
    videos = "".join(
        f'<figure><video id="cam-{i}" muted preload="auto" src="{html.escape(v.file)}" '
        f'data-fps="{v.fps:.9g}" style="width:100%"></video><figcaption>{html.escape(v.camera)}</figcaption>'
        f'</figure>' for i, v in enumerate(overlays))
    note = (f"{len(shown)} frames on the slider (every {step}. of the run's {len(np.unique(tracks.frame))})"
            + (f"; beside it each camera's overlay at that frame (annotation frame f at its video's frame "
               f"f + {frame_offset}, every {overlay_step}. frame kept)" if overlays else
               "; the cameras' own frames are drawn with gt3d report --frames"))
    script = """
const fig = FIGURE;
const div = document.getElementById('scene');
const offset = OFFSET, vstep = VSTEP;
function showFrame(f) {
  document.querySelectorAll('video[data-fps]').forEach(v => {
    const t = (Math.floor((f + offset) / vstep)) / parseFloat(v.dataset.fps);
    if (isFinite(t) && t >= 0) { v.currentTime = t + 1e-3; }
  });
  document.getElementById('frame-shown').textContent = String(f);
}
Plotly.newPlot(div, fig.data, fig.layout).then(() => {
  Plotly.addFrames(div, fig.frames);
  div.on('plotly_sliderchange', e => showFrame(parseInt(e.step.label)));
  div.on('plotly_animatingframe', e => showFrame(parseInt(e.name)));
  showFrame(FIRST);
});
"""
    script = (script.replace("FIGURE", json.dumps(fig, allow_nan=False, default=float))
              .replace("OFFSET", str(int(frame_offset))).replace("VSTEP", str(int(overlay_step)))
              .replace("FIRST", str(shown[0])))
    page = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>gt3dkit: the scene in 3D</title>"
            "<style>body{font-family:sans-serif;margin:8px}#wrap{display:flex;gap:12px}#scene{flex:3}"
            "#cams{flex:2;display:grid;grid-template-columns:1fr 1fr;gap:6px}figure{margin:0}"
            "figcaption{font-size:13px}</style>"
            f"<script type='text/javascript'>{plotly.offline.get_plotlyjs()}</script></head><body>"
            f"<p><a href='index.html'>the report</a> &middot; frame <span id='frame-shown'></span> &middot; "
            f"{html.escape(note)}</p><div id='wrap'><div id='scene'></div><div id='cams'>{videos}</div></div>"
            f"<script type='text/javascript'>{script}</script></body></html>")
    (folder / "scene.html").write_text(page, encoding="utf-8")
    return "scene.html"

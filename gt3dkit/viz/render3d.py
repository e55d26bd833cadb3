"""Off-screen 3D renders with open3d (CPU: EGL on Mesa), always in a child process.

The scene to draw is plain numpy (:class:`Drawing`: line sets and triangle meshes in world
metres, a pinhole view); :func:`render` saves it to a temporary ``.npz``, runs
``python -m gt3dkit.viz.render3d JOB.npz OUT.png`` and reads the PNG back, so that an EGL or
driver failure (which can kill the interpreter) becomes a :class:`RenderError`, never a
crash of the caller. open3d is imported in the child only.

Why open3d's ``Visualizer`` (OpenGL through EGL) and not its Filament ``OffscreenRenderer``:
the open3d-cpu wheel's Filament is built for Vulkan only, and on Mesa's lavapipe one frame
with a lit mesh and a line set took 6 s to over 140 s depending on the mesh resolution
(measured here, open3d-cpu 0.20.0, Mesa 22.3.6), while the same frame through EGL/llvmpipe
takes well under a second.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gt3dkit.types import F64, I64

#: a render that has not finished after this long is given up (seconds)
RENDER_TIMEOUT_S = 300


class RenderError(RuntimeError):
    """The off-screen renderer failed (no EGL, driver crash, timeout)."""


@dataclass(frozen=True)
class View:
    """A pinhole looking from ``eye`` at ``centre``: ``width`` x ``height`` pixels, vertical
    field of view ``fov_deg``; world ``up`` is up in the picture."""

    eye: F64
    centre: F64
    up: F64
    width: int = 1280
    height: int = 800
    fov_deg: float = 50.0

    @property
    def focal_px(self) -> float:
        return (self.height / 2) / float(np.tan(np.radians(self.fov_deg) / 2))

    @property
    def intrinsic(self) -> F64:
        """(3, 3) K; open3d's view control needs the principal point at the image centre
        in its own convention (``width / 2 - 0.5``)."""
        f = self.focal_px
        return np.array([[f, 0, self.width / 2 - 0.5], [0, f, self.height / 2 - 0.5], [0, 0, 1.0]])

    @property
    def rotation(self) -> F64:
        """(3, 3) camera_from_world rotation: x right, y down, z forward (OpenCV)."""
        f = self.centre - self.eye
        f = f / np.linalg.norm(f)
        r = np.cross(f, self.up)
        if np.linalg.norm(r) < 1e-9:  # looking straight along up
            r = np.cross(f, np.roll(self.up, 1))
        r = r / np.linalg.norm(r)
        d = np.cross(f, r)
        return np.stack([r, d, f])

    @property
    def extrinsic(self) -> F64:
        """(4, 4) camera_from_world."""
        E = np.eye(4)
        E[:3, :3] = self.rotation
        E[:3, 3] = -self.rotation @ self.eye
        return E

    def project(self, X_world: F64) -> F64:
        """(N, 2) pixels of (N, 3) world points; NaN behind the eye."""
        Xc = (np.asarray(X_world, dtype=np.float64) - self.eye) @ self.rotation.T
        K = self.intrinsic
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = Xc[:, :2] / Xc[:, 2:3] * K[0, 0] + K[:2, 2]
        uv[Xc[:, 2] <= 1e-9] = np.nan
        return uv


@dataclass
class Drawing:
    """What to draw: line sets (points (N, 3) m, segments (M, 2) indices, one RGB colour)
    and triangle meshes (vertices (N, 3) m, triangles (M, 3), one RGB colour)."""

    lines: list[tuple[F64, I64, tuple[float, float, float]]] = field(default_factory=list)
    meshes: list[tuple[F64, I64, tuple[float, float, float]]] = field(default_factory=list)

    def add_lines(self, points: F64, segments: I64 | list[tuple[int, int]],
                  colour: tuple[float, float, float]) -> None:
        P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        S = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
        if len(S):
            self.lines.append((P, S, colour))

    def add_polyline(self, points: F64, colour: tuple[float, float, float]) -> None:
        P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(P) > 1:
            k = np.arange(len(P) - 1)
            self.add_lines(P, np.stack([k, k + 1], axis=1), colour)

    def add_mesh(self, vertices: F64, triangles: I64, colour: tuple[float, float, float]) -> None:
        self.meshes.append((np.asarray(vertices, dtype=np.float64), np.asarray(triangles, dtype=np.int64),
                            colour))


def unit_sphere(n_lat: int = 12, n_lon: int = 24) -> tuple[F64, I64]:
    """A UV sphere of radius 1: (V, 3) vertices, (F, 3) outward-facing triangles."""
    th = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack([np.sin(th)[:, None] * np.cos(ph), np.sin(th)[:, None] * np.sin(ph),
                     np.repeat(np.cos(th)[:, None], n_lon, axis=1)], axis=-1).reshape(-1, 3)
    V = np.concatenate([[[0, 0, 1.0]], ring, [[0, 0, -1.0]]])
    tris = []

    def idx(i: int, j: int) -> int:
        return 1 + i * n_lon + j % n_lon

    for j in range(n_lon):
        tris.append((0, idx(0, j), idx(0, j + 1)))
        tris.append((len(V) - 1, idx(n_lat - 2, j + 1), idx(n_lat - 2, j)))
    for i in range(n_lat - 2):
        for j in range(n_lon):
            a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1)
            tris += [(a, c, b), (b, c, d)]
    return V, np.array(tris, dtype=np.int64)


def render(drawing: Drawing, view: View, timeout_s: float = RENDER_TIMEOUT_S) -> np.ndarray:
    """(H, W, 3) uint8 picture of ``drawing`` seen through ``view``, on white, rendered by
    open3d in a child process; :class:`RenderError` when that fails."""
    return render_all([(drawing, view)], timeout_s)[0]


def render_all(jobs: list[tuple[Drawing, View]], timeout_s: float = RENDER_TIMEOUT_S) -> list[np.ndarray]:
    """:func:`render` of several drawings in one child process (open3d's import and window,
    ~1.5 s, paid once; ``timeout_s`` for each picture); :class:`RenderError` when it fails."""
    return Rendering(jobs, timeout_s).result()


class Rendering:
    """:func:`render_all` started: the child process renders while the caller goes on (a
    report draws its matplotlib panels meanwhile); :meth:`result` waits for the pictures
    (``timeout_s`` for each, from then), :meth:`close` gives them up. A context manager."""

    def __init__(self, jobs: list[tuple[Drawing, View]], timeout_s: float = RENDER_TIMEOUT_S) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="gt3d-render-")
        argv = []
        for n, (drawing, view) in enumerate(jobs):
            job, png = Path(self._tmp.name) / f"job{n}.npz", Path(self._tmp.name) / f"out{n}.png"
            arrays: dict[str, np.ndarray] = {
                "intrinsic": view.intrinsic, "extrinsic": view.extrinsic,
                "size": np.array([view.width, view.height])}
            for kind, items in (("line", drawing.lines), ("mesh", drawing.meshes)):
                for i, (P, S, col) in enumerate(items):
                    arrays[f"{kind}{i}_p"], arrays[f"{kind}{i}_s"] = P, S
                    arrays[f"{kind}{i}_c"] = np.asarray(col, dtype=np.float64)
            np.savez(job, allow_pickle=True, **arrays)  # (numpy's default, named: the arrays by name)
            argv += [str(job), str(png)]
        self._pngs = [Path(f) for f in argv[1::2]]
        self._timeout_s = timeout_s * len(jobs)
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
        try:
            self._proc: subprocess.Popen[str] | None = subprocess.Popen(  # noqa: S603
                [sys.executable, "-m", "gt3dkit.viz.render3d", *argv],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        except OSError as e:
            self._tmp.cleanup()
            raise RenderError(f"open3d's process did not start ({e})") from None

    def result(self) -> list[np.ndarray]:
        """The pictures, ``(H, W, 3) uint8`` each; :class:`RenderError` when the child failed."""
        p = self._proc
        if p is None:
            raise RenderError("the render was given up")
        try:
            out, err = p.communicate(timeout=self._timeout_s)
        except subprocess.TimeoutExpired:
            self.close()
            raise RenderError(f"open3d did not finish within {self._timeout_s / max(len(self._pngs), 1):g} s "
                              "a picture") from None
        try:
            if p.returncode != 0 or not all(f.is_file() for f in self._pngs):
                lines = [ln for ln in (err + out).splitlines() if ln.strip() and "INFO" not in ln]
                why = lines[-1].strip() if lines else f"exit status {p.returncode}"
                raise RenderError(f"open3d failed ({why})")
            import matplotlib.image as mpimg

            return [(np.clip(mpimg.imread(f)[..., :3], 0, 1) * 255).round().astype(np.uint8)
                    for f in self._pngs]
        finally:
            self._proc = None
            self._tmp.cleanup()

    def close(self) -> None:
        """Stop the child (if it still runs) and remove its files."""
        p, self._proc = self._proc, None
        if p is not None and p.poll() is None:
            p.kill()
            p.communicate()
        self._tmp.cleanup()

    def __enter__(self) -> Rendering:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _child(job: Path, png: Path) -> None:
    """Run in the child: build open3d geometries from ``job`` and render them to ``png``."""
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    a = np.load(job)
    W, H = (int(v) for v in a["size"])
    vis = o3d.visualization.Visualizer()
    if not vis.create_window(visible=False, width=W, height=H):
        raise SystemExit("error: open3d could not create an off-screen window (EGL)")
    k = 0
    while f"mesh{k}_p" in a:
        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(a[f"mesh{k}_p"]),
                                      o3d.utility.Vector3iVector(a[f"mesh{k}_s"].astype(np.int32)))
        m.compute_vertex_normals()
        m.paint_uniform_color(a[f"mesh{k}_c"])
        vis.add_geometry(m)
        k += 1
    k = 0
    while f"line{k}_p" in a:
        ls = o3d.geometry.LineSet(o3d.utility.Vector3dVector(a[f"line{k}_p"]),
                                  o3d.utility.Vector2iVector(a[f"line{k}_s"].astype(np.int32)))
        ls.paint_uniform_color(a[f"line{k}_c"])
        vis.add_geometry(ls)
        k += 1
    opt = vis.get_render_option()
    opt.background_color = np.array([1.0, 1.0, 1.0])
    opt.line_width = 2.0
    opt.mesh_show_back_face = True
    opt.light_on = True
    params = o3d.camera.PinholeCameraParameters()
    K = a["intrinsic"]
    params.intrinsic = o3d.camera.PinholeCameraIntrinsic(W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    params.extrinsic = a["extrinsic"]
    ctl = vis.get_view_control()
    if not ctl.convert_from_pinhole_camera_parameters(params, allow_arbitrary=True):
        raise SystemExit("error: open3d refused the view")
    ctl.set_constant_z_near(0.05)
    ctl.set_constant_z_far(1e4)
    vis.poll_events()
    vis.update_renderer()
    vis.capture_screen_image(png, do_render=True)
    vis.destroy_window()


if __name__ == "__main__":
    for _job, _png in zip(sys.argv[1::2], sys.argv[2::2], strict=True):
        _child(Path(_job), Path(_png))

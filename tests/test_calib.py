"""gt3dkit.calib: every format reads what it writes, and projects as OpenCV does."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gt3dkit.calib.formats import detect_format, read_calibration, write_calibration
from gt3dkit.calib.model import Camera, Rig
from gt3dkit.cli import bundled
from gt3dkit.errors import InputError
from gt3dkit.geom.camera import project_points
from gt3dkit.sim import simulate


def _rig() -> Rig:
    """Six cameras with distortion (k3 too) and a skewless K, from the simulator."""
    rig = simulate("native", seed=1, frames=2, people=1).rig
    cams = [Camera(c.name, c.width, c.height, c.K, np.array([-0.05, 0.01, 1e-3, -5e-4, 2e-3 * (i % 2)]),
                   c.R, c.t) for i, c in enumerate(rig.cameras)]
    return Rig(tuple(cams), up=rig.up)


def _same(a: Rig, b: Rig, tol: float = 1e-9) -> None:
    assert a.names == b.names
    for p, q in zip(a.cameras, b.cameras, strict=True):
        assert (p.width, p.height) == (q.width, q.height)
        for k in ("K", "dist", "R", "t"):
            np.testing.assert_allclose(getattr(p, k), getattr(q, k), atol=tol, rtol=0, err_msg=k)


def test_round_trip_through_every_writable_format(tmp_path) -> None:
    rig = _rig()
    chain = ["native", "colmap", "toml", "opencv", "native"]
    current = rig
    for i, fmt in enumerate(chain):
        where = write_calibration(current, tmp_path / f"{i}_{fmt}", fmt)
        assert detect_format(where) == ("native" if fmt == "native" else fmt)
        current = read_calibration(where)
        _same(rig, current)


@pytest.mark.parametrize("fmt", ["native", "colmap", "toml", "opencv"])
def test_projection_agrees_with_opencv(tmp_path, fmt) -> None:
    rig = read_calibration(write_calibration(_rig(), tmp_path, fmt))
    X = np.random.default_rng(0).uniform([-3, -3, 0], [3, 3, 2], size=(50, 3))
    uv, _ = project_points(X[:, None], rig.K, rig.dist, rig.R, rig.t, rig.depth_sign)  # (50,1,C,2)
    for c, cam in enumerate(rig.cameras):
        ref, _ = cv2.projectPoints(X, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.dist)
        np.testing.assert_allclose(uv[:, 0, c], ref[:, 0], atol=1e-6)


def test_bundled_calibrations_load() -> None:
    assert len(read_calibration(bundled("multiviewx")).cameras) == 6
    assert len(read_calibration(bundled("panoptic_160906_band1")).cameras) == 31


def test_grid_layout_round_trip(tmp_path) -> None:
    rig = read_calibration(bundled("multiviewx"))
    _same(rig, read_calibration(write_calibration(rig, tmp_path, "grid")), 1e-9)
    with pytest.raises(InputError, match="left-handed"):
        write_calibration(rig, tmp_path / "c", "colmap")


def test_bad_calibration_files(tmp_path) -> None:
    (tmp_path / "a.toml").write_text('[cam_0]\nname = "x"\nsize = [10, 10]\n')
    with pytest.raises(InputError, match=r"\[cam_0\].*missing matrix"):
        read_calibration(tmp_path / "a.toml")
    col = tmp_path / "col"
    write_calibration(_rig(), col, "colmap")
    for f in ("images.txt", "frames.txt"):
        lines = [x for x in (col / f).read_text().splitlines() if x.startswith("#")]
        (col / f).write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="no images"):
        read_calibration(col)

"""gt3dkit.calib: every format reads what it writes, and projects as OpenCV does."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from gt3dkit.calib.formats import detect_format, read_calibration, write_calibration
from gt3dkit.commands.common import bundled
from gt3dkit.errors import InputError
from gt3dkit.geom.camera import project_points
from gt3dkit.geom.triangulate import normalized_points
from gt3dkit.rig import Camera, Rig
from gt3dkit.sim import simulate


def _rig() -> Rig:
    """Six cameras with distortion (k3 too) and a skewless K, from the simulator."""
    rig = simulate("native", seed=1, frames=2, people=1).rig
    cams = [Camera(c.name, c.width, c.height, c.K, np.array([-0.05, 0.01, 1e-3, -5e-4, 2e-3 * (i % 2)]),
                   c.R, c.t) for i, c in enumerate(rig.cameras)]
    return Rig(tuple(cams), up=rig.up)


def _fisheye_rig() -> Rig:
    """The simulator's six cameras, every other one with a wide fisheye lens (focal 600 px)."""
    rig = _rig()
    cams = [replace(c, K=np.array([[600.0, 0, 955.5], [0, 601.0, 541.0], [0, 0, 1]]),
                    dist=np.array([0.04, -0.012, 0.003, -0.0004]), lens="fisheye") if i % 2 else c
            for i, c in enumerate(rig.cameras)]
    return Rig(tuple(cams), up=rig.up)


def _same(a: Rig, b: Rig, tol: float = 1e-9) -> None:
    assert a.names == b.names
    for p, q in zip(a.cameras, b.cameras, strict=True):
        assert (p.width, p.height, p.lens) == (q.width, q.height, q.lens)
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


def test_fisheye_round_trip_through_every_format_that_holds_it(tmp_path) -> None:
    rig = _fisheye_rig()
    current = rig
    for i, fmt in enumerate(["native", "colmap", "toml", "opencv", "native"]):
        current = read_calibration(write_calibration(current, tmp_path / f"{i}_{fmt}", fmt))
        _same(rig, current)
    with pytest.raises(InputError, match="pinhole lens only.*cam"):
        write_calibration(rig, tmp_path / "grid", "grid")


@pytest.mark.parametrize("fmt", ["native", "colmap", "toml", "opencv"])
def test_fisheye_projection_agrees_with_opencv(tmp_path, fmt) -> None:
    """Points 10-80 degrees off the axis, through each format, as ``cv2.fisheye.projectPoints``;
    and back through ``cv2.fisheye.undistortPoints``'s inverse."""
    rig = read_calibration(write_calibration(_fisheye_rig(), tmp_path, fmt))
    rng = np.random.default_rng(1)
    for c, cam in enumerate(rig.cameras):
        if cam.lens != "fisheye":
            continue
        ang, az = np.radians(rng.uniform(10, 80, 200)), rng.uniform(0, 2 * np.pi, 200)
        d_cam = np.stack([np.sin(ang) * np.cos(az), np.sin(ang) * np.sin(az), np.cos(ang)], -1)
        X = (d_cam * rng.uniform(0.5, 5, (200, 1)) - cam.t) @ cam.R  # world points
        uv, _ = project_points(X, rig.K[c : c + 1], rig.dist[c : c + 1], rig.R[c : c + 1], rig.t[c : c + 1])
        ref, _ = cv2.fisheye.projectPoints(X[None], cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.dist[:4])
        np.testing.assert_allclose(uv[:, 0], ref[0], atol=1e-6)
        xy = normalized_points(uv, rig.K[c : c + 1], rig.dist[c : c + 1])[:, 0]
        np.testing.assert_allclose(xy, d_cam[:, :2] / d_cam[:, 2:], rtol=1e-9, atol=1e-9)


def test_aniposelib_fisheye_calibration_reads(tmp_path) -> None:
    """aniposelib's FisheyeCamera writes ``fisheye = true`` and four distortions."""
    (tmp_path / "calibration.toml").write_text(
        '[cam_0]\nname = "A"\nsize = [ 1280, 1024,]\n'
        'matrix = [ [ 500.0, 0.0, 640.0,], [ 0.0, 500.0, 512.0,], [ 0.0, 0.0, 1.0,],]\n'
        'distortions = [ 0.05, -0.01, 0.002, 0.0,]\nrotation = [ 0.0, 0.0, 0.0,]\n'
        'translation = [ 0.0, 0.0, 0.0,]\nfisheye = true\n\n[metadata]\nadjusted = true\n')
    cam = read_calibration(tmp_path / "calibration.toml").cameras[0]
    assert cam.lens == "fisheye"
    np.testing.assert_array_equal(cam.dist, [0.05, -0.01, 0.002, 0.0, 0.0])
    (tmp_path / "calibration.toml").write_text(
        (tmp_path / "calibration.toml").read_text().replace("fisheye = true", 'fisheye = "yes"'))
    with pytest.raises(InputError, match=r"\[cam_0\].*fisheye must be true or false"):
        read_calibration(tmp_path / "calibration.toml")


@pytest.mark.parametrize("fmt", ["native", "colmap", "toml", "opencv"])
def test_projection_agrees_with_opencv(tmp_path, fmt) -> None:
    rig = read_calibration(write_calibration(_rig(), tmp_path, fmt))
    X = np.random.default_rng(0).uniform([-3, -3, 0], [3, 3, 2], size=(50, 3))
    uv, _ = project_points(X[:, None], rig.K, rig.dist, rig.R, rig.t, rig.depth_sign)  # (50,1,C,2)
    for c, cam in enumerate(rig.cameras):
        ref, _ = cv2.projectPoints(X, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.dist)
        np.testing.assert_allclose(uv[:, 0, c], ref[:, 0], atol=1e-6)


def test_opencv_loads_only_for_the_calibrations_that_need_it(tmp_path) -> None:
    """Reading a native or COLMAP calibration loads no OpenCV (26 MB, 30 ms: the Shelf run's peak
    memory 276 -> 247 MB); reading an OpenCV one loads it."""
    for fmt in ("native", "colmap", "opencv"):
        where = write_calibration(_rig(), tmp_path / fmt, fmt)
        probe = ("import sys; from gt3dkit.calib.formats import read_calibration; "
                 f"read_calibration({str(where)!r}); print('cv2' in sys.modules)")
        r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
        assert r.stdout.strip() == str(fmt == "opencv"), (fmt, r.stdout, r.stderr)


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


# ----------------------------------------------------------------------------- show


def _upside_down(rig: Rig) -> Rig:
    """The world turned upside down (what a mirrored board gives: cameras under the floor)."""
    from gt3dkit.refine import transform_rig

    return transform_rig(rig, 1.0, np.diag([1.0, -1.0, -1.0]), np.zeros(3))


def test_show_flags_nothing_on_the_bundled_calibrations() -> None:
    from gt3dkit.api import load_scene
    from gt3dkit.calib.show import rig_warnings
    from gt3dkit.refine import scene_warnings

    for name in ("multiviewx", "panoptic_160906_band1"):
        assert rig_warnings(read_calibration(bundled(name))) == []
    assert scene_warnings(load_scene(bundled("multiviewx"))) == []


def test_show_flags_an_upside_down_and_a_below_the_floor_rig() -> None:
    from gt3dkit.calib.show import rig_warnings

    rig = read_calibration(bundled("multiviewx"))
    w = " | ".join(rig_warnings(_upside_down(rig)))
    assert "below the floor" in w and "looks upwards" in w
    c = rig.cameras[2]
    C = c.center_world * np.array([1, 1, -1])
    low = Rig(tuple(x if i != 2 else Camera(c.name, c.width, c.height, c.K, c.dist, c.R, -c.R @ C,
                                            c.depth_sign) for i, x in enumerate(rig.cameras)), up=rig.up)
    w = rig_warnings(low)
    assert any("below the floor" in x and "Camera3" in x for x in w), w


def test_show_with_annotations_flags_people_under_the_floor(tmp_path, capsys) -> None:
    """A keypoint scene whose calibration was solved upside down: heads below the floor."""
    from gt3dkit.api import load_scene
    from gt3dkit.calib.formats.native import write
    from gt3dkit.refine import scene_warnings
    from gt3dkit.sim import simulate_skeletons, write_skeleton_scene

    write_skeleton_scene(simulate_skeletons("native", seed=1, frames=3, people=2, cameras=5), tmp_path / "s",
                         "native")
    scene = load_scene(tmp_path / "s")
    assert scene_warnings(scene) == []
    flipped = Rig(_upside_down(scene.rig).cameras, up=-scene.rig.up)  # y-down world: up is -y
    write(Rig(flipped.cameras, up=scene.rig.up), tmp_path / "s" / "cameras.json", fps=30.0,
          skeleton="coco19")
    w = " | ".join(scene_warnings(load_scene(tmp_path / "s")))
    assert "below the floor" in w, w


# ----------------------------------------------------------------------------- refine


def _perturbed(rig: Rig, deg: float, m: float, seed: int) -> Rig:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    cams = [rig.cameras[0]]
    for c in rig.cameras[1:]:
        ax = rng.normal(size=3)
        R = Rotation.from_rotvec(np.radians(deg) * ax / np.linalg.norm(ax)).as_matrix() @ c.R
        d = rng.normal(size=3)
        C = c.center_world + m * d / np.linalg.norm(d)
        cams.append(Camera(c.name, c.width, c.height, c.K, c.dist, R, -R @ C, c.depth_sign))
    return Rig(tuple(cams), up=rig.up)


@pytest.fixture(scope="module")
def skel_scene(tmp_path_factory):
    from gt3dkit.api import load_scene
    from gt3dkit.sim import simulate_skeletons, write_skeleton_scene

    root = tmp_path_factory.mktemp("calib") / "s"
    write_skeleton_scene(simulate_skeletons("native", seed=4, frames=24, people=2, cameras=6, noise_px=1.0),
                         root, "native")
    return load_scene(root)


def test_refine_recovers_a_perturbed_rig(skel_scene) -> None:
    import dataclasses

    from gt3dkit.refine import align_to, pose_change, refine

    truth = skel_scene.rig
    bad = _perturbed(truth, 1.0, 0.05, 3)
    res = refine(dataclasses.replace(skel_scene, rig=bad))
    assert len(res.report["refined_cameras"]) >= 5
    al, info = align_to(res.rig, truth)
    err = [pose_change(a, b) for a, b in zip(al.cameras, truth.cameras, strict=True)]
    assert max(e[0] for e in err) < 0.01 and max(e[1] for e in err) < 0.05
    assert abs(info["scale"] - 1) < 0.005
    before = [pose_change(a, b) for a, b in zip(align_to(bad, truth)[0].cameras, truth.cameras, strict=True)]
    assert max(e[1] for e in before) > 0.5  # it was off


def test_a_refinement_that_swings_a_camera_is_said(skel_scene) -> None:
    """A refined camera turned by more than a refinement does, or moved by a tenth of its distance
    to what it sees, is named (the shared mouse's back camera swung 41.5 degrees about the
    small animal); a camera moved a little, or kept, is not; the perturbed rig's refinement
    (1 degree, 5 cm at 3 m) says nothing."""
    import dataclasses

    from gt3dkit.refine import refine
    from gt3dkit.refine.common import large_moves

    truth = skel_scene.rig
    points = np.nan_to_num(skel_scene.truth.kpt_world.reshape(-1, 3), nan=np.inf)
    swung = _perturbed(truth, 8.0, 0.05, 1)
    nudged = _perturbed(truth, 1.0, 0.05, 1)
    shifted = _perturbed(truth, 0.5, 0.6, 1)
    every = np.ones(len(truth.cameras), bool)
    said = large_moves(truth, swung, every, points)
    assert len(said) == len(truth.cameras) - 1 and all("more than a refinement" in w for w in said)
    assert "turned it 8.0 degrees" in said[0] and "gt3d calib board" in said[0]
    assert large_moves(truth, nudged, every, points) == []
    assert len(large_moves(truth, shifted, every, points)) == len(truth.cameras) - 1
    assert large_moves(truth, swung, np.zeros_like(every), points) == []
    res = refine(dataclasses.replace(skel_scene, rig=nudged))
    assert res.report["refined_cameras"] and res.report["large_moves"] == []


def test_refine_keeps_a_good_rig(skel_scene) -> None:
    from gt3dkit.refine import refine

    res = refine(skel_scene)
    assert res.report["refined_cameras"] == []
    for a, b in zip(res.rig.cameras, skel_scene.rig.cameras, strict=True):
        np.testing.assert_array_equal(a.R, b.R)
        assert all("kept" in c["why"] for c in res.report["cameras"].values())


def test_calib_cli(skel_scene, tmp_path, capsys) -> None:
    from gt3dkit.cli import main

    root = Path(skel_scene.root)
    assert main(["calib", "refine", str(root), "--out", str(tmp_path / "r"), "--format", "toml"]) == 0
    assert (tmp_path / "r" / "calib_report.json").exists()
    assert (tmp_path / "r" / "calibration" / "calibration.toml").exists()
    assert main(["calib", "show", str(tmp_path / "r" / "cameras.json")]) == 0
    assert "0 calibration warnings" in capsys.readouterr().out
    assert main(["calib", "show", str(tmp_path / "r" / "calibration" / "calibration.toml")]) == 0
    assert "toml calibration" in capsys.readouterr().out
    # reconstruct with a calibration in another format: the same result as the input's own
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "a"), "--estimator", "triangulation"]) == 0
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "b"), "--estimator", "triangulation",
                 "--calib", str(tmp_path / "r" / "calibration" / "calibration.toml")]) == 0
    a = (tmp_path / "a" / "keypoints.csv").read_text()
    assert a == (tmp_path / "b" / "keypoints.csv").read_text()


def test_calib_commands_take_the_calibrations_units(skel_scene, tmp_path, capsys) -> None:
    """An anipose calibration in millimetres: gt3d calib show, refine and people take
    --calib-units as reconstruct does (they had no such option: refine worked in a world 1000x
    too large), and show says when a file's cameras stand too far apart for metres."""
    from gt3dkit.calib.formats import toml as toml_fmt
    from gt3dkit.cli import main

    toml_fmt.write(skel_scene.rig.in_metres(1000.0), tmp_path / "calibration.toml")  # the rig in mm
    capsys.readouterr()
    assert main(["calib", "show", str(tmp_path / "calibration.toml")]) == 0
    got = capsys.readouterr()
    assert "m apart (median over the pairs), the calibration read as metres" in got.err
    assert main(["calib", "show", str(tmp_path / "calibration.toml"), "--calib-units", "mm"]) == 0
    got = capsys.readouterr()
    assert "(in mm, shown in metres)" in got.out and "apart (median" not in got.err
    heights = [round(c.center_world[2], 3) for c in skel_scene.rig.cameras]
    assert all(f"{h:8.3f}" in got.out for h in heights)
    root = Path(skel_scene.root)
    assert main(["calib", "refine", str(root), "--out", str(tmp_path / "r"), "--calib",
                 str(tmp_path / "calibration.toml"), "--calib-units", "mm"]) == 0
    refined = read_calibration(tmp_path / "r" / "cameras.json")
    for a, b in zip(refined.cameras, skel_scene.rig.cameras, strict=True):
        np.testing.assert_allclose(a.center_world, b.center_world, atol=0.05)  # metres again


def test_camera_absent_from_the_calibration(skel_scene, tmp_path, capsys) -> None:
    from gt3dkit.cli import main

    rig = Rig(skel_scene.rig.cameras[:-1], up=skel_scene.rig.up)
    write_calibration(rig, tmp_path / "c", "toml")
    assert main(["reconstruct", skel_scene.root, "--out", str(tmp_path / "o"),
                 "--calib", str(tmp_path / "c" / "calibration.toml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "calibration.toml" in err and skel_scene.rig.cameras[-1].name in err

"""Skeletons as data (issue 66): skeleton files, ``--skeleton FILE``, SLEAP's analysis files and
DeepLabCut's CSVs per camera, a calibration in millimetres (``--calib-units``) and a camera whose
calibration fits no other's."""

from __future__ import annotations

import dataclasses
import json
from importlib.resources import files
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.api import load_run, load_scene, reconstruct
from gt3dkit.calib.formats import toml as toml_fmt
from gt3dkit.calib.formats.native import rig_of_doc
from gt3dkit.cli import main
from gt3dkit.errors import InputError
from gt3dkit.eval.pose import mpjpe_by_id
from gt3dkit.io.datasets import Calibration, read_scene
from gt3dkit.io.datasets.sleap import side_pairs
from gt3dkit.io.skeletonfile import named_skeleton, read_skeleton, write_skeleton
from gt3dkit.rig import Rig
from gt3dkit.sim import simulate_skeletons, write_skeleton_scene
from gt3dkit.skeletons import SKELETONS, skeleton_from_doc
from gt3dkit.types import SkeletonScene

h5py = pytest.importorskip("h5py")

COCO17 = SKELETONS["coco17"]


def _toml(path: Path, joints: list[str], bones: list[list[str]], pairs: list[list[str]] | None = None,
          name: str = "mine") -> Path:
    q = lambda xs: "[" + ", ".join(f'"{x}"' for x in xs) + "]"  # noqa: E731
    text = f'name = "{name}"\njoints = {q(joints)}\nbones = [' + ", ".join(q(b) for b in bones) + "]\n"
    if pairs is not None:
        text += "pairs = [" + ", ".join(q(p) for p in pairs) + "]\n"
    path.write_text(text)
    return path


def _run(*argv: str, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_every_built_in_skeleton_is_a_document_that_reads_back() -> None:
    for name, sk in SKELETONS.items():
        back = skeleton_from_doc(sk.doc(), name)
        assert back.joints == sk.joints and back.bone_names == sk.bone_names
        np.testing.assert_array_equal(back.mirror(), sk.mirror())
        np.testing.assert_array_equal(back.canonical(), sk.canonical())


def test_the_built_in_skeletons_are_the_files_shipped_with_the_package(tmp_path: Path) -> None:
    """Every built-in is a file of the form a user writes, read by the user's reader; HALPE-26
    and COCO-WholeBody among them; a copy written back reads as the same skeleton."""
    folder = Path(str(files("gt3dkit"))) / "data" / "skeletons" / "human"
    shipped = {p.stem: read_skeleton(p) for p in folder.glob("*.toml")}
    assert set(shipped) == set(SKELETONS) and {"halpe26", "wholebody133", "coco133"} <= set(shipped)
    for name, sk in SKELETONS.items():
        assert shipped[name] == sk, name
        write_skeleton(sk, tmp_path / f"{name}.toml")
        assert read_skeleton(tmp_path / f"{name}.toml").doc() == sk.doc(), name
    assert SKELETONS["wholebody133"].n_joints == 133 and SKELETONS["halpe26"].n_joints == 26
    assert SKELETONS["coco133"].detector_points == 133 and SKELETONS["coco133"].n_joints == 23
    bad = tmp_path / "few.toml"
    bad.write_text('name = "x"\njoints = ["a", "b"]\nbones = [["a", "b"]]\ndetector_points = 1\n')
    with pytest.raises(InputError, match="detector_points"):
        read_skeleton(bad)
    bad.write_text('name = "x"\njoints = ["a", "b"]\nbones = [["a", "b"]]\nup = ["c"]\n')
    with pytest.raises(InputError, match="up: unknown joint 'c'"):
        read_skeleton(bad)
    bad.write_text('name = "x"\njoints = ["a", "b"]\nbones = [["a", "b"]]\nup = ["a"]\nfloor = ["a"]\n')
    with pytest.raises(InputError, match="'a' is both up and on the floor"):
        read_skeleton(bad)
    for bones, problem in (('"a-b"', "bones: expected a list of \\[joint, joint\\] pairs, got 'a-b'"),
                           ('[["a", "b", "a"]]', r"bones\[0\]: expected two joint names")):
        bad.write_text(f'name = "x"\njoints = ["a", "b"]\nbones = {bones}\n')
        with pytest.raises(InputError, match=problem):
            read_skeleton(bad)
    for groups, problem in (('[["a", "c"]]', r"groups\[0\]: unknown joint 'c'"),
                            ('[["a"]]', "two joints or more"), ('[["a", "b", "a"]]', "'a' named twice")):
        bad.write_text(f'name = "x"\njoints = ["a", "b"]\nbones = [["a", "b"]]\ngroups = {groups}\n')
        with pytest.raises(InputError, match=problem):
            read_skeleton(bad)


@pytest.mark.parametrize("joints, bones, pairs, entry, problem", [
    (["a", "b", "a"], [["a", "b"]], None, "joints", "joint 'a' named twice"),
    (["a", "b"], [["a", "c"]], None, "bones[0]", "unknown joint 'c'"),
    (["a", "l", "r", "k"], [["a", "l"], ["a", "r"], ["r", "k"]], [["l", "r"]], "pairs[0]",
     "not a left/right pair"),
    (["a", "l", "r", "x"], [["a", "l"], ["a", "r"], ["a", "x"]], [["l", "r"], ["r", "x"]], "pairs",
     "'r' is in two pairs"),
])
def test_a_bad_skeleton_file_is_one_line_naming_the_entry(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                          joints: list[str], bones: list[list[str]],
                                                          pairs: list[list[str]] | None, entry: str,
                                                          problem: str) -> None:
    write_skeleton_scene(simulate_skeletons("native", seed=1, frames=3, people=1, cameras=3,
                                            skeleton="coco17"), tmp_path / "in", "native")
    bad = _toml(tmp_path / "bad.toml", joints, bones, pairs)
    code, _, err = _run("reconstruct", str(tmp_path / "in"), "--out", str(tmp_path / "out"),
                        "--skeleton", str(bad), capsys=capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"error: {bad}: {entry}: ") and problem in err, err
    assert not (tmp_path / "out").exists()


def test_a_skeleton_file_that_is_not_there_is_said_so(tmp_path: Path) -> None:
    """(Was 'unknown skeleton 'x.toml' (known: ...)', as if it were a name.)"""
    with pytest.raises(InputError, match=r"^--skeleton: .*nothere\.toml: no such file$"):
        named_skeleton(str(tmp_path / "nothere.toml"))
    with pytest.raises(InputError, match="unknown skeleton 'nosuch'"):
        named_skeleton("nosuch")


def test_a_skeleton_file_is_as_good_as_the_built_in_it_describes(tmp_path: Path) -> None:
    """The same joints and bones given as a file: the same estimate, and the file's skeleton
    written into meta.json."""
    write_skeleton_scene(simulate_skeletons("native", seed=2, frames=8, people=2, cameras=4, noise_px=1.0,
                                            skeleton="coco17"), tmp_path / "in", "native")
    mine = _toml(tmp_path / "mine.toml", list(COCO17.joints), [list(b) for b in COCO17.bone_names])
    assert read_skeleton(mine).left_right == COCO17.left_right  # l_/r_ names pair by default
    built_in = reconstruct(load_scene(tmp_path / "in", skeleton="coco17"), "ukf")
    scene = load_scene(tmp_path / "in", skeleton=str(mine))
    assert scene.skeleton == "mine" and scene.skeleton_doc is not None
    from_file = reconstruct(scene, "ukf", out=tmp_path / "out")
    np.testing.assert_array_equal(from_file.kpt_world, built_in.kpt_world)
    meta = (tmp_path / "out" / "meta.json").read_text()
    assert '"skeleton": "mine"' in meta and '"skeleton_doc"' in meta


def test_left_and_right_are_read_from_the_names_where_the_bones_agree() -> None:
    joints = ["Nose", "Ear_L", "Ear_R", "Head", "Shoulder_left", "Shoulder_right", "Tail", "LEye", "REye"]
    bones = [("Head", "Nose"), ("Head", "Ear_L"), ("Head", "Ear_R"), ("Head", "Shoulder_left"),
             ("Tail", "Shoulder_right"), ("Nose", "LEye"), ("Nose", "REye")]
    # the shoulders' bones do not mirror each other: no pair
    assert side_pairs(joints, bones) == [("Ear_L", "Ear_R"), ("LEye", "REye")]


def _write_sleap(sk: SkeletonScene, root: Path, names: list[str] | None = None) -> None:
    """A SLEAP + anipose folder of a simulated scene: ``calibration.toml`` and one analysis file per
    camera (as SLEAP writes it: tracks (n_tracks, 2, n_nodes, n_frames), every person a track)."""
    root.mkdir(parents=True)
    toml_fmt.write(sk.rig, root / "calibration.toml")
    skel = SKELETONS[sk.skeleton]
    nodes = names or list(skel.joints)
    ids = np.unique(sk.truth_id)
    F = len(sk.frames)
    for c, cam in enumerate(sk.rig.cameras):
        tracks = np.full((len(ids), 2, len(nodes), F), np.nan)
        for m in range(len(sk.truth_id)):
            k = int(np.searchsorted(ids, sk.truth_id[m]))
            f = int(np.searchsorted(sk.frames, sk.truth_frame[m]))
            tracks[k, :, :, f] = sk.uv[m, c].T
        (root / cam.name).mkdir()
        with h5py.File(root / cam.name / f"labels_{cam.name}.analysis.h5", "w") as h:
            h["tracks"] = tracks
            h["point_scores"] = np.full((len(ids), len(nodes), F), np.nan)
            h["track_names"] = np.array([f"track_{i}".encode() for i in range(len(ids))])
            h["node_names"] = np.array([n.encode() for n in nodes])
            h["edge_names"] = np.array([[nodes[a].encode(), nodes[b].encode()] for a, b in skel.bones])


def test_sleap_analysis_files_are_reconstructed_with_their_own_skeleton(tmp_path: Path) -> None:
    sk = simulate_skeletons("native", seed=3, frames=20, people=2, cameras=4, noise_px=1.0, skeleton="coco17")
    _write_sleap(sk, tmp_path / "sleap")
    scene = load_scene(tmp_path / "sleap")
    assert scene.layout == "sleap" and scene.skeleton == "sleap"
    assert scene.skeleton_doc is not None and scene.skeleton_doc["joints"] == list(COCO17.joints)
    tracks = reconstruct(scene, "ukf")
    assert len(np.unique(tracks.track_id)) == 2
    # each estimated person against the nearest true one, joint by joint
    err = []
    for f in np.unique(tracks.frame):
        est = tracks.kpt_world[tracks.frame == f]
        tru = sk.kpt_world[sk.truth_frame == sk.frames[f]]  # SLEAP's frames count from 0
        d = np.nanmean(np.linalg.norm(est[:, None] - tru[None], axis=-1), axis=2)
        err.append(d.min(axis=1))
    assert np.median(np.concatenate(err)) < 0.02


def _write_slp(sk: SkeletonScene, root: Path, tracked: bool = True, user: bool = False) -> None:
    """The same folder with SLEAP's own ``.slp`` per camera, written by sleap-io (SLEAP's reader
    and writer): every person a track (or none), predictions scored 0.9 (or a person's labels),
    the skeleton's left/right pairs as its symmetries."""
    sio = pytest.importorskip("sleap_io")
    skel = SKELETONS[sk.skeleton]
    nodes = list(skel.joints)
    sym = [list(p) for p in skel.left_right]
    s = sio.Skeleton(nodes=nodes, edges=[[nodes[a], nodes[b]] for a, b in skel.bones], symmetries=sym)
    ids = np.unique(sk.truth_id)
    tracks = [sio.Track(name=f"track_{i}") for i in range(len(ids))]
    for c, cam in enumerate(sk.rig.cameras):
        video = sio.Video(filename=f"{cam.name}.mp4", open_backend=False)
        frames = []
        for f, frame in enumerate(sk.frames):
            insts = []
            for m in np.flatnonzero(sk.truth_frame == frame):
                k = int(np.searchsorted(ids, sk.truth_id[m]))
                tr = tracks[k] if tracked else None
                uv = sk.uv[m, c].astype(np.float64)
                insts.append(sio.Instance.from_numpy(uv, skeleton=s, track=tr) if user else
                             sio.PredictedInstance.from_numpy(uv, skeleton=s, track=tr, score=1.0,
                                                              point_scores=np.full(len(nodes), 0.9)))
            frames.append(sio.LabeledFrame(video=video, frame_idx=f, instances=insts))
        (root / cam.name).mkdir(parents=True, exist_ok=True)
        sio.save_slp(sio.Labels(labeled_frames=frames, videos=[video], skeletons=[s],
                                tracks=tracks if tracked else []),
                     str(root / cam.name / f"labels_{cam.name}.slp"), verbose=False)


def test_sleap_slp_files_read_as_their_analysis_export(tmp_path: Path) -> None:
    sk = simulate_skeletons("native", seed=5, frames=12, people=2, cameras=4, noise_px=1.0, skeleton="coco17")
    _write_sleap(sk, tmp_path / "h5")
    _write_slp(sk, tmp_path / "slp")
    toml_fmt.write(sk.rig, tmp_path / "slp" / "calibration.toml")
    a, b = load_scene(tmp_path / "h5"), load_scene(tmp_path / "slp")
    assert sorted(b.files) == sorted(f"{c.name}/labels_{c.name}.slp" for c in sk.rig.cameras) + [
        "calibration:calibration.toml"]
    assert np.allclose(a.obs.kpt_uv_px, b.obs.kpt_uv_px, atol=1e-3, equal_nan=True)  # sleap-io: float32
    assert np.array_equal(a.obs.track_id, b.obs.track_id) and np.array_equal(a.obs.frame, b.obs.frame)
    assert np.allclose(b.obs.kpt_conf[np.isfinite(b.obs.kpt_uv_px[..., 0])], 0.9)  # the predictions' scores
    assert b.skeleton_doc is not None and sorted(map(sorted, b.skeleton_doc["pairs"])) == sorted(
        sorted(p) for p in COCO17.left_right)  # declared, not guessed: coco17's names say no _L/_R
    assert a.skeleton_doc is not None and a.skeleton_doc["pairs"] == []


def test_sleap_slp_files_without_tracks_and_of_a_persons_labels(tmp_path: Path) -> None:
    sk = simulate_skeletons("native", seed=6, frames=12, people=1, cameras=4, noise_px=1.0, skeleton="coco17")
    _write_slp(sk, tmp_path / "slp", tracked=False, user=True)
    toml_fmt.write(sk.rig, tmp_path / "slp" / "calibration.toml")
    scene = load_scene(tmp_path / "slp")
    seen = np.isfinite(scene.obs.kpt_uv_px[..., 0])
    assert seen.sum() == np.isfinite(sk.uv[..., 0]).sum() and np.all(scene.obs.kpt_conf[seen] == 1.0)
    tracks = reconstruct(scene, "ukf")
    est = tracks.kpt_world[np.argsort(tracks.frame)]
    assert len(np.unique(tracks.track_id)) == 1
    assert np.nanmedian(np.linalg.norm(est - sk.kpt_world, axis=-1)) < 0.02


def test_a_slp_without_sleap_io_reads_the_analysis_file_beside_it_or_says_what_to_install(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    from gt3dkit.io.datasets import sleap

    sk = simulate_skeletons("native", seed=7, frames=4, people=1, cameras=3, skeleton="coco17")
    _write_sleap(sk, tmp_path / "both")
    _write_slp(sk, tmp_path / "both")
    monkeypatch.setattr(sleap, "_have_sleap_io", lambda: False)
    scene = load_scene(tmp_path / "both")
    assert any("sleap-io is not installed" in w for w in scene.warnings)
    assert all(f.endswith(".analysis.h5") for f in scene.files if not f.startswith("calibration:"))
    alone = tmp_path / "both" / sk.rig.cameras[0].name / f"labels_{sk.rig.cameras[0].name}.analysis.h5"
    alone.unlink()
    code, _, err = _run("reconstruct", str(tmp_path / "both"), "--out", str(tmp_path / "out"), capsys=capsys)
    assert code == 2 and err.count("\n") == 1 and "pip install 'gt3dkit[sleap]'" in err, err
    slp = alone.with_suffix("").with_suffix(".slp")
    assert err.startswith(f"error: {slp}: ") and not (tmp_path / "out").exists()


def test_a_sleap_file_with_another_skeleton_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    sk = simulate_skeletons("native", seed=3, frames=4, people=1, cameras=3, skeleton="coco17")
    _write_sleap(sk, tmp_path / "sleap")
    other = tmp_path / "sleap" / sk.rig.cameras[1].name / f"labels_{sk.rig.cameras[1].name}.analysis.h5"
    with h5py.File(other, "a") as h:
        del h["node_names"]
        h["node_names"] = np.array([f"n{j}".encode() for j in range(COCO17.n_joints)])
    code, _, err = _run("reconstruct", str(tmp_path / "sleap"), "--out", str(tmp_path / "out"), capsys=capsys)
    assert code == 2 and err.count("\n") == 1 and err.startswith(f"error: {other}: "), err
    assert "skeleton differs" in err and not (tmp_path / "out").exists()


def test_a_calibration_in_millimetres_is_made_metres(tmp_path: Path) -> None:
    sk = simulate_skeletons("native", seed=4, frames=10, people=1, cameras=4, noise_px=0.5, skeleton="coco17")
    _write_sleap(sk, tmp_path / "m")
    mm = dataclasses.replace(sk, rig=sk.rig.in_metres(1000.0))  # the same cameras, translations in mm
    _write_sleap(mm, tmp_path / "mm")
    metres = load_scene(tmp_path / "m")
    scaled = load_scene(tmp_path / "mm", calib=Calibration(None, "mm"))
    np.testing.assert_allclose(scaled.rig.t, metres.rig.t, atol=1e-9)
    assert scaled.load_options["calib_units"] == "mm"
    a, b = reconstruct(metres, "ukf"), reconstruct(scaled, "ukf")
    np.testing.assert_allclose(a.kpt_world, b.kpt_world, atol=1e-6)
    far = [w for w in read_scene(tmp_path / "mm").warnings if "--calib-units" in w]
    assert len(far) == 1 and "m apart" in far[0]  # read as metres, the rig is kilometres wide: said
    assert not any("--calib-units" in w for s in (metres, scaled) for w in s.warnings)


def test_a_camera_whose_calibration_fits_no_other_is_named(tmp_path: Path) -> None:
    """One camera's calibration copied from another's (as in the shared anipose session): its
    detections agree with nobody's, and the warning says which camera."""
    sk = simulate_skeletons("native", seed=5, frames=30, people=1, cameras=4, noise_px=0.5, skeleton="coco17")
    cams = list(sk.rig.cameras)
    cams[2] = dataclasses.replace(cams[3], name=cams[2].name)  # camera 2 carries camera 3's pose
    _write_sleap(sk, tmp_path / "sleap")
    toml_fmt.write(Rig(tuple(cams), up=sk.rig.up), tmp_path / "sleap" / "calibration.toml")
    scene = load_scene(tmp_path / "sleap")
    named = [w for w in scene.warnings if "calibration does not fit" in w]
    assert len(named) == 1 and named[0].startswith(f"camera {cams[2].name}:"), scene.warnings
    assert not any("no annotation" in w for w in scene.warnings), scene.warnings  # said once


def test_refine_calib_poses_a_copied_camera_again(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--refine-calib`` on an input whose one camera carries another's pose: that camera posed
    again on the people the others place, its views kept, the rig the run used in meta.json."""
    sk = simulate_skeletons("native", seed=6, frames=40, people=1, cameras=4, noise_px=0.5, skeleton="coco17")
    cams = list(sk.rig.cameras)
    true = cams[2]
    cams[2] = dataclasses.replace(cams[3], name=true.name)
    _write_sleap(sk, tmp_path / "sleap")
    toml_fmt.write(Rig(tuple(cams), up=sk.rig.up), tmp_path / "sleap" / "calibration.toml")
    code, out, err = _run("reconstruct", str(tmp_path / "sleap"), "--out", str(tmp_path / "out"),
                          "--refine-calib", "--quiet", capsys=capsys)
    assert code == 0, err
    assert f"camera {true.name} posed again" in out
    meta = json.loads((tmp_path / "out" / "meta.json").read_text())
    rig = rig_of_doc(meta["calibration_refinement"]["refined_rig"], "meta.json")
    got = rig.cameras[rig.index(true.name)]
    assert np.linalg.norm(got.center_world - true.center_world) < 0.05  # metres
    assert abs(got.K[0, 0] / true.K[0, 0] - 1) < 0.05
    assert meta["calibration_refinement"]["reposed_cameras"][true.name]["median_px_after"] < 2.0
    # read back for a report: on the run's rig, the re-posed camera's views are there
    run = load_run(tmp_path / "out", "a test")
    assert np.any(run.scene.obs.cam == run.scene.rig.index(true.name))


def _write_dlc(sk: SkeletonScene, root: Path, multi: bool = True) -> list[Path]:
    """DeepLabCut CSVs of a simulated scene, one per camera (``video_<camera>DLC_<network>.csv``),
    with the calibration beside them: every person an individual (a multi-animal project)."""
    root.mkdir(parents=True)
    toml_fmt.write(sk.rig, root / "calibration.toml")
    parts = list(SKELETONS[sk.skeleton].joints)
    ids = np.unique(sk.truth_id) if multi else np.unique(sk.truth_id)[:1]
    out = []
    for c, cam in enumerate(sk.rig.cameras):
        path = root / f"video_{cam.name}DLC_resnet50_mouseJan1shuffle1_1000.csv"
        rows = [["scorer"] + ["DLC_resnet50"] * (3 * len(parts) * len(ids))]
        if multi:
            rows.append(["individuals"] + [f"animal{i}" for i in range(len(ids)) for _ in parts
                                           for _ in range(3)])
        rows += [["bodyparts"] + [p for _ in ids for p in parts for _ in range(3)],
                 ["coords"] + ["x", "y", "likelihood"] * (len(parts) * len(ids))]
        for k, fr in enumerate(sk.frames):
            row: list[object] = [k]
            for i in ids:
                m = np.flatnonzero((sk.truth_frame == fr) & (sk.truth_id == i))
                for j in range(len(parts)):
                    ok = len(m) and np.isfinite(sk.uv[m[0], c, j, 0])
                    row += [f"{sk.uv[m[0], c, j, 0]:.3f}", f"{sk.uv[m[0], c, j, 1]:.3f}", "0.95"] if ok else \
                        ["", "", ""]
            rows.append(row)
        path.write_text("\n".join(",".join(str(x) for x in r) for r in rows) + "\n")
        out.append(path)
    return out


def _mpjpe_m(tracks: object, sk: SkeletonScene, frames_from_zero: bool) -> float:
    """Median over the estimated people-frames of the mean joint distance to the nearest true
    person (m)."""
    err = []
    for f in np.unique(tracks.frame):  # type: ignore[attr-defined]
        est = tracks.kpt_world[tracks.frame == f]  # type: ignore[attr-defined]
        tru = sk.kpt_world[sk.truth_frame == (sk.frames[f] if frames_from_zero else f)]
        err.append(np.nanmean(np.linalg.norm(est[:, None] - tru[None], axis=-1), axis=2).min(axis=1))
    return float(np.median(np.concatenate(err)))


def test_deeplabcut_multi_animal_csvs_are_as_good_as_native_keypoints(tmp_path: Path) -> None:
    sk = simulate_skeletons("native", seed=3, frames=20, people=3, cameras=4, noise_px=2.0, skeleton="coco17")
    _write_dlc(sk, tmp_path / "dlc")
    scene = load_scene(tmp_path / "dlc")
    assert scene.layout == "dlc" and any("no bones" in w for w in scene.warnings)
    dlc = reconstruct(scene, "ukf")
    assert len(np.unique(dlc.track_id)) == 3
    write_skeleton_scene(sk, tmp_path / "native", "native")
    native = reconstruct(load_scene(tmp_path / "native"), "ukf")
    # the native run ties the bones; DeepLabCut's CSV has none (its skeleton file gives them)
    mine = _toml(tmp_path / "coco.toml", list(COCO17.joints), [list(b) for b in COCO17.bone_names])
    with_bones = reconstruct(load_scene(tmp_path / "dlc", skeleton=str(mine)), "ukf")
    assert _mpjpe_m(with_bones, sk, True) <= 1.1 * _mpjpe_m(native, sk, False)
    assert _mpjpe_m(dlc, sk, True) < 0.01


def _as_dlc_h5(csv_path: Path, h5_path: Path) -> None:
    """A DeepLabCut CSV as DeepLabCut's own ``.h5`` (its conversion: pandas reads the CSV's header
    rows as the columns, then ``to_hdf(key="df_with_missing", format="table")``)."""
    pd = pytest.importorskip("pandas")
    pytest.importorskip("tables")
    levels = 4 if csv_path.read_text().splitlines()[1].startswith("individuals") else 3
    df = pd.read_csv(csv_path, header=list(range(levels)), index_col=0)
    df.to_hdf(h5_path, key="df_with_missing", format="table", mode="w")


def test_deeplabcut_h5_files_read_as_their_csvs(tmp_path: Path) -> None:
    sk = simulate_skeletons("native", seed=8, frames=10, people=2, cameras=4, noise_px=1.0, skeleton="coco17")
    csvs = _write_dlc(sk, tmp_path / "csv")
    (tmp_path / "h5").mkdir()
    toml_fmt.write(sk.rig, tmp_path / "h5" / "calibration.toml")
    for p in csvs:
        _as_dlc_h5(p, tmp_path / "h5" / p.with_suffix(".h5").name)
        _as_dlc_h5(p, p.with_suffix(".h5"))  # beside its CSV, as DeepLabCut writes both: the .h5 is read
    b, both = load_scene(tmp_path / "h5"), load_scene(tmp_path / "csv")
    assert b.layout == "dlc" and all(f.endswith(".h5") for f in both.files if not f.startswith("calibration"))
    for p in csvs:
        p.with_suffix(".h5").unlink()
    a = load_scene(tmp_path / "csv")
    for x in (b, both):
        assert np.array_equal(a.obs.kpt_uv_px, x.obs.kpt_uv_px, equal_nan=True)
        assert np.array_equal(a.obs.track_id, x.obs.track_id) and np.array_equal(a.obs.frame, x.obs.frame)


def _anipose_session(sk: SkeletonScene, project: Path, scheme: list[list[str]]) -> Path:
    """An anipose project of one session: ``config.toml`` (a ``cam_regex`` for the simulated
    cameras' names, the labeling scheme), ``session1/calibration/calibration.toml`` and
    ``session1/pose-2d/<video>-cam<name>.h5``, DeepLabCut's output per camera."""
    session = project / "session1"
    csvs = _write_dlc(sk, project / "dlc")
    (session / "pose-2d").mkdir(parents=True)
    (session / "calibration").mkdir()
    toml_fmt.write(sk.rig, session / "calibration" / "calibration.toml")
    for p, cam in zip(csvs, sk.rig.cameras, strict=True):
        _as_dlc_h5(p, session / "pose-2d" / f"trial1-cam{cam.name}.h5")
    q = lambda xs: "[" + ", ".join(f'"{x}"' for x in xs) + "]"  # noqa: E731
    (project / "config.toml").write_text(
        "project = 'sim'\n[triangulation]\ncam_regex = '-cam([0-9_]+)$'\n"
        "[labeling]\nscheme = [" + ", ".join(q(c) for c in scheme) + "]\n")
    return session


def test_an_anipose_session_is_read_with_its_cameras_and_scheme(tmp_path: Path) -> None:
    sk = simulate_skeletons("native", seed=9, frames=16, people=2, cameras=4, noise_px=2.0, skeleton="coco17")
    chains = [["l_ankle", "l_knee", "l_hip", "r_hip", "r_knee", "r_ankle"],
              ["l_wrist", "l_elbow", "l_shoulder", "r_shoulder", "r_elbow", "r_wrist"],
              ["l_hip", "l_shoulder"],
              ["r_hip", "r_shoulder"], ["l_ear", "l_eye", "nose", "r_eye", "r_ear"]]
    session = _anipose_session(sk, tmp_path / "proj", chains)
    scene = load_scene(session)
    assert scene.layout == "anipose" and scene.skeleton_doc is not None
    bones = {frozenset(b) for b in scene.skeleton_doc["bones"]}  # type: ignore[union-attr]
    assert bones == {frozenset(p) for c in chains for p in zip(c, c[1:], strict=False)}
    assert ["l_knee", "r_knee"] in scene.skeleton_doc["pairs"]  # type: ignore[operator]
    tracks = reconstruct(scene, "ukf")
    assert len(np.unique(tracks.track_id)) == 2 and _mpjpe_m(tracks, sk, True) < 0.01
    assert not any(session.rglob("*.csv")) and not (session / "out").exists()  # nothing written there


def test_an_anipose_file_whose_camera_the_calibration_lacks_is_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sk = simulate_skeletons("native", seed=9, frames=4, people=1, cameras=3, skeleton="coco17")
    session = _anipose_session(sk, tmp_path / "proj", [["l_hip", "r_hip"]])
    stray = session / "pose-2d" / "trial1-cam99.h5"
    (session / "pose-2d" / f"trial1-cam{sk.rig.cameras[0].name}.h5").rename(stray)
    code, _, err = _run("reconstruct", str(session), "--out", str(tmp_path / "out"), capsys=capsys)
    assert code == 2 and err.count("\n") == 1 and err.startswith(f"error: {stray}: "), err
    assert "'99'" in err and not (tmp_path / "out").exists()


def test_a_deeplabcut_file_of_two_scorers_or_other_parts_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sk = simulate_skeletons("native", seed=3, frames=4, people=1, cameras=3, skeleton="coco17")
    files = _write_dlc(sk, tmp_path / "dlc", multi=False)
    text = files[1].read_text().splitlines()
    text[0] = text[0].replace("DLC_resnet50", "DLC_mobnet", 3)
    files[1].write_text("\n".join(text) + "\n")
    code, _, err = _run("reconstruct", str(tmp_path / "dlc"), "--out", str(tmp_path / "out"), capsys=capsys)
    assert code == 2 and err.startswith(f"error: {files[1]}: scorer: ") and err.count("\n") == 1, err
    other = _toml(tmp_path / "other.toml", ["a", "b"], [["a", "b"]])
    files[1].write_text("\n".join(text).replace("DLC_mobnet", "DLC_resnet50") + "\n")
    code, _, err = _run("reconstruct", str(tmp_path / "dlc"), "--out", str(tmp_path / "out"), "--skeleton",
                        str(other), capsys=capsys)
    assert code == 2 and err.startswith("error: --skeleton: ") and "body parts" in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("how, entry, problem", [
    ("empty", "", "empty: a DeepLabCut CSV starts with its header rows"),
    ("latin-1", "", "not UTF-8 text"),
    ("a frame twice", "line 6", "frame 0 again (first at line 4)"),
    ("a negative frame", "line 4", "negative frame index '-3'"),
    ("an infinite x", "line 5", "an infinite value (column x of "),
])
def test_a_broken_deeplabcut_file_is_one_line_naming_it(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                        how: str, entry: str, problem: str) -> None:
    """A file named as DeepLabCut names its output that is empty or not UTF-8 was passed over (its
    camera then had no annotation); a repeated or negative frame index named no line (line 0)
    or read -3 as frame 3."""
    sk = simulate_skeletons("native", seed=3, frames=4, people=1, cameras=3, skeleton="coco17")
    files = _write_dlc(sk, tmp_path / "dlc", multi=False)
    lines = files[1].read_text().splitlines()  # 3 header rows, then frames 0, 1, ...
    if how == "empty":
        files[1].write_bytes(b"")
    elif how == "latin-1":
        files[1].write_bytes(files[1].read_bytes().replace(b"scorer", b"sc\xf6rer", 1))
    elif how == "a frame twice":
        files[1].write_text("\n".join(lines[:5] + [lines[3]] + lines[5:]) + "\n")
    elif how == "a negative frame":
        files[1].write_text("\n".join(lines[:3] + ["-3" + lines[3][lines[3].index(","):]] + lines[4:]) + "\n")
    else:  # DeepLabCut writes an empty cell where a part is not found, never infinity
        cells = lines[4].split(",")
        bad = ",".join([cells[0], "inf", *cells[2:]])
        files[1].write_text("\n".join(lines[:4] + [bad] + lines[5:]) + "\n")
    code, _, err = _run("reconstruct", str(tmp_path / "dlc"), "--out", str(tmp_path / "out"), capsys=capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"error: {files[1]}: {entry + ': ' if entry else ''}") and problem in err, err
    assert not (tmp_path / "out").exists()


MOUSE = (files("gt3dkit") / "data" / "skeletons" / "mouse.toml").read_text()


def test_labels_projected_from_a_run_of_a_skeleton_file_are_read_back(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """gt3d project of a run whose skeleton is a file (an animal's, joints spelt as its labelling
    tool spells them) writes that file beside the labels, and gt3d reconstruct reads them back
    (it said that no known skeleton had those joints); a CVAT folder read with --skeleton FILE
    matches a label's name as the file spells it (it matched only the normalised spelling)."""
    (tmp_path / "mouse.toml").write_text(MOUSE)
    doc = read_skeleton(tmp_path / "mouse.toml").doc()
    spelt = {j: j.capitalize().replace("_l", "_L").replace("_r", "_R") for j in doc["joints"]}  # Ear_L

    def renamed(x: object) -> object:
        if isinstance(x, str):
            return spelt.get(x, x)
        if isinstance(x, list):
            return [renamed(v) for v in x]
        return {spelt.get(k, k): v for k, v in x.items()} if isinstance(x, dict) else x

    path = tmp_path / "Mouse.toml"
    write_skeleton(skeleton_from_doc({**{k: renamed(v) for k, v in doc.items()}, "name": "Mouse"}, "Mouse"),
                   path)
    assert "Ear_L" in read_skeleton(path).joints
    sk = simulate_skeletons("native", seed=4, frames=10, people=1, cameras=4, noise_px=1.0,
                            skeleton=str(path))
    write_skeleton_scene(sk, tmp_path / "in", "native")
    reconstruct(load_scene(tmp_path / "in"), "ukf", out=tmp_path / "out")
    code, _, err = _run("project", str(tmp_path / "out"), "--format", "cvat", "--to", str(tmp_path / "cvat"),
                        capsys=capsys)
    assert code == 0 and (tmp_path / "cvat" / "skeleton.toml").is_file(), err
    ids = str(tmp_path / "cvat" / "association.csv")
    back = load_scene(tmp_path / "cvat", association=ids)
    assert back.skeleton == "Mouse" and back.skeleton_doc is not None
    assert np.isfinite(reconstruct(back, "ukf").kpt_world).all()
    (tmp_path / "cvat" / "skeleton.toml").rename(tmp_path / "elsewhere.toml")
    with pytest.raises(InputError, match="pass --skeleton FILE"):
        load_scene(tmp_path / "cvat", association=ids)
    assert load_scene(tmp_path / "cvat", skeleton=str(tmp_path / "elsewhere.toml"),
                      association=ids).skeleton == "Mouse"


def test_a_skeleton_file_is_simulated_and_reconstructed(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    """Mice from a skeleton file with a pose: simulated (the bones swinging, their lengths exact),
    written as a native folder that names its skeleton file, reconstructed within millimetres."""
    path = tmp_path / "mouse.toml"
    path.write_text(MOUSE)
    sk = simulate_skeletons("native", seed=2, frames=20, people=2, cameras=5, noise_px=1.0,
                            skeleton=str(path))
    assert sk.skeleton == "mouse" and sk.skeleton_doc is not None
    bones = read_skeleton(path).bones
    lengths = np.linalg.norm(sk.kpt_world[:, bones[:, 0]] - sk.kpt_world[:, bones[:, 1]], axis=-1)
    per_mouse = [lengths[sk.truth_id == i] for i in np.unique(sk.truth_id)]
    assert max(float(np.ptp(v, axis=0).max()) for v in per_mouse) < 1e-9  # each bone one length
    write_skeleton_scene(sk, tmp_path / "in", "native")
    assert (tmp_path / "in" / "skeleton.toml").is_file()
    scene = load_scene(tmp_path / "in")
    assert scene.skeleton == "mouse" and scene.truth is not None
    tracks = reconstruct(scene, "ukf")
    assert mpjpe_by_id(tracks, scene.truth)[0] < 3.0  # mm
    bad = tmp_path / "posed_not.toml"
    bad.write_text(MOUSE.split("[pose]")[0])
    code, _, err = _run("simulate", "--kind", "skeleton", "--skeleton", str(bad), "--out",
                        str(tmp_path / "x"), capsys=capsys)
    assert code == 2 and "[pose]" in err and err.count("\n") == 1, err


def test_a_sleap_input_takes_a_skeleton_file_of_its_nodes(tmp_path: Path) -> None:
    """SLEAP's file says nodes, edges and symmetries only; a skeleton file of the same nodes (any
    order) adds up, the floor and rigid groups (a SLEAP input refused --skeleton, so gt3d calib
    people could never find its up and floor). The order is the files' and nothing is lost in it
    (DeepLabCut's reorder dropped up, floor and groups)."""
    sk = simulate_skeletons("native", seed=7, frames=6, people=1, cameras=4, noise_px=1.0, skeleton="coco17")
    _write_sleap(sk, tmp_path / "sleap")
    mine = COCO17.doc()
    doc = {**mine, "name": "mine", "joints": list(reversed(mine["joints"])), "up": ["nose"],
           "floor": ["l_ankle", "r_ankle"], "groups": [["nose", "l_eye", "r_eye"]]}
    write_skeleton(skeleton_from_doc(doc, "mine"), tmp_path / "mine.toml")
    scene = load_scene(tmp_path / "sleap", skeleton=str(tmp_path / "mine.toml"))
    assert scene.skeleton == "mine" and scene.skeleton_doc is not None
    got = skeleton_from_doc(scene.skeleton_doc, "mine")
    assert list(got.joints) == list(COCO17.joints)  # the files' order
    assert got.up == ("nose",) and got.floor == ("l_ankle", "r_ankle")
    assert got.groups == (("nose", "l_eye", "r_eye"),)
    plain = reconstruct(load_scene(tmp_path / "sleap"), "ukf")
    tied = reconstruct(scene, "ukf")
    assert np.isfinite(tied.kpt_world).all() and tied.kpt_world.shape == plain.kpt_world.shape
    with pytest.raises(InputError, match="are not the SLEAP files' nodes"):
        load_scene(tmp_path / "sleap", skeleton="mouse")
    from gt3dkit.io.datasets.dlc import body_skeleton

    as_dlc = body_skeleton(list(COCO17.joints), str(tmp_path / "mine.toml"))  # DeepLabCut's reorder too
    assert (as_dlc.joints, as_dlc.up, as_dlc.floor) == (got.joints, got.up, got.floor)
    assert as_dlc.groups == got.groups


def test_an_infinite_pixel_in_a_sleap_analysis_file_is_one_line(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    """SLEAP writes NaN where a node is not labelled; an infinite pixel was left out in silence."""
    h5py = pytest.importorskip("h5py")
    sk = simulate_skeletons("native", seed=6, frames=4, people=1, cameras=3, skeleton="coco17")
    _write_sleap(sk, tmp_path / "sleap")
    path = next((tmp_path / "sleap").rglob("*.h5"))
    with h5py.File(path, "r+") as f:
        tracks = f["tracks"][()]
        tracks[0, 0, 2, 1] = np.inf
        f["tracks"][...] = tracks
    code, _, err = _run("reconstruct", str(tmp_path / "sleap"), "--out", str(tmp_path / "out"), capsys=capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"error: {path}: tracks: an infinite pixel (track 0, node "), err
    assert "frame 1)" in err, err
    assert not (tmp_path / "out").exists()


def test_a_second_calibration_beside_the_labels_is_said_and_a_board_file_is_none(tmp_path: Path) -> None:
    """anipose keeps its board in a ``board.toml`` (keys, no table): not a calibration. A second
    calibration beside the first (an older one kept) was passed over in silence."""
    sk = simulate_skeletons("native", seed=5, frames=4, people=1, cameras=3, skeleton="coco17")
    _write_sleap(sk, tmp_path / "sleap")
    (tmp_path / "sleap" / "board.toml").write_text("board_x = 8\nboard_y = 11\nsquare_length = 24.0\n")
    assert not [w for w in load_scene(tmp_path / "sleap").warnings if "calibrations" in w]
    folder = tmp_path / "sleap"
    (folder / "calibration_old.toml").write_bytes((folder / "calibration.toml").read_bytes())
    said = [w for w in load_scene(tmp_path / "sleap").warnings if "calibrations" in w]
    assert said == ["2 calibrations beside the annotations (calibration.toml, calibration_old.toml): read "
                    "calibration.toml (--calib chooses one)"]
    (tmp_path / "sleap" / "calibration.toml").unlink()
    (tmp_path / "sleap" / "calibration_old.toml").unlink()
    with pytest.raises(InputError, match="no calibration beside the annotations"):
        load_scene(tmp_path / "sleap")  # the board is not read as the cameras


def test_anipose_points3d_export_is_in_the_units_of_the_calibration_read(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]
                                                                        ) -> None:
    """An anipose calibration in millimetres, read with --calib-units mm: the export writes the
    joints in millimetres, as anipose's own points3d beside that calibration (it wrote metres)."""
    pd = pytest.importorskip("pandas")
    sk = simulate_skeletons("native", seed=4, frames=6, people=1, cameras=4, noise_px=1.0, skeleton="coco17")
    _write_sleap(sk, tmp_path / "sleap")
    toml_fmt.write(sk.rig.in_metres(1000.0), tmp_path / "sleap" / "calibration.toml")  # the rig in mm
    code, _, err = _run("reconstruct", str(tmp_path / "sleap"), "--out", str(tmp_path / "out"),
                        "--calib-units", "mm", "--quiet", capsys=capsys)
    assert code == 0, err
    code, out, err = _run("export", str(tmp_path / "out"), "--format", "anipose", capsys=capsys)
    assert code == 0 and "(mm; " in out and "--calib-units mm" in out, out + err
    df = pd.read_csv(tmp_path / "out" / "export_anipose" / "points3d.csv")
    row = pd.read_csv(tmp_path / "out" / "keypoints.csv").query("joint == 5").iloc[0]  # metres
    got = df[df.fnum == row.frame].iloc[0]
    np.testing.assert_allclose([got.l_shoulder_x, got.l_shoulder_y, got.l_shoulder_z],
                               1000.0 * np.array([row.x, row.y, row.z]), atol=1e-3)


def test_anipose_points3d_export_holds_the_joints_as_anipose_names_them(tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture[str]
                                                                          ) -> None:
    pd = pytest.importorskip("pandas")
    sk = simulate_skeletons("native", seed=3, frames=8, people=1, cameras=4, noise_px=1.0, skeleton="coco17")
    _write_sleap(sk, tmp_path / "sleap")
    reconstruct(load_scene(tmp_path / "sleap"), "ukf", out=tmp_path / "out")
    code, _, err = _run("export", str(tmp_path / "out"), "--format", "anipose", capsys=capsys)
    assert code == 0, err
    df = pd.read_csv(tmp_path / "out" / "export_anipose" / "points3d.csv")
    kp = pd.read_csv(tmp_path / "out" / "keypoints.csv")
    assert list(df.columns[:6]) == ["nose_x", "nose_y", "nose_z", "nose_error", "nose_ncams", "nose_score"]
    assert list(df.columns[-4:]) == ["center_0", "center_1", "center_2", "fnum"]
    row = kp[(kp.joint == 5)].iloc[0]
    got = df[df.fnum == row.frame].iloc[0]
    np.testing.assert_allclose([got.l_shoulder_x, got.l_shoulder_y, got.l_shoulder_z], [row.x, row.y, row.z],
                               atol=1e-6)
    assert got.l_shoulder_score == 1 and np.isnan(got.l_shoulder_ncams)  # n_views: --every-frame only


def test_coco_wholebody_hands_are_reconstructed_and_the_body_as_well_as_alone(tmp_path: Path) -> None:
    """COCO-WholeBody's 133 points (the simulator's hands go with their wrists, fingers curling):
    the hands within 3 mm at 2 px noise with 8 cameras, and the body no worse than the same
    scene's 17 body points given alone."""
    sk = simulate_skeletons("native", seed=11, frames=20, people=2, cameras=8, noise_px=2.0,
                            skeleton="wholebody133")
    joints = SKELETONS["wholebody133"].joints
    assert len(joints) == 133 and SKELETONS["wholebody133"].marker_names[91] == "left_hand_root"
    # the hands move with the wrists: a finger tip keeps its distance to its hand's root
    tip, root = joints.index("l_middle_finger4"), joints.index("l_hand_root")
    reach = np.linalg.norm(sk.kpt_world[:, tip] - sk.kpt_world[:, root], axis=-1)
    assert np.ptp(reach) > 0.005 and reach.max() < 0.2  # curling, never torn off
    body = dataclasses.replace(sk, skeleton="coco17", kpt_world=sk.kpt_world[:, :17], uv=sk.uv[:, :, :17])
    err = {}
    for name, scene in (("whole", sk), ("body", body)):
        write_skeleton_scene(scene, tmp_path / name, "native")
        tracks = reconstruct(load_scene(tmp_path / name), "ukf")
        assert len(np.unique(tracks.track_id)) == 2
        per = []
        for f in np.unique(scene.truth_frame):
            tru, est = scene.kpt_world[scene.truth_frame == f], tracks.kpt_world[tracks.frame == f]
            d = np.nanmean(np.linalg.norm(est[:, None] - tru[None], axis=-1), axis=2)
            per += [np.linalg.norm(e - tru[np.argmin(d[i])], axis=-1) for i, e in enumerate(est)]
        err[name] = np.array(per)
    hands = [k for k, j in enumerate(joints) if "hand" in j or "finger" in j or "thumb" in j]
    assert len(hands) == 42 and np.nanmean(err["whole"][:, hands]) < 0.003
    assert np.nanmean(err["whole"][:, :17]) <= 1.1 * np.nanmean(err["body"])


def test_a_rigid_group_holds_its_joints_distances(tmp_path: Path) -> None:
    """A skeleton file's ``groups``: the simulator moves a group as one body; the estimate ties every
    two of its joints as a bone (the ears, which no bone joins, too): their distances vary less than
    with the same skeleton without the group, and the joints are no worse."""
    rigid = MOUSE.replace('pairs = [', 'groups = [["head", "nose", "ear_l", "ear_r"]]\npairs = [', 1)
    (tmp_path / "rigid.toml").write_text(rigid)
    (tmp_path / "plain.toml").write_text(MOUSE)
    sk = read_skeleton(tmp_path / "rigid.toml")
    assert ("ear_l", "ear_r") in sk.tie_names and ("ear_l", "ear_r") not in sk.bone_names
    sim = simulate_skeletons("native", seed=3, frames=40, people=2, cameras=4, noise_px=2.0,
                             skeleton=str(tmp_path / "rigid.toml"))
    ix = {j: k for k, j in enumerate(sk.joints)}
    pairs = [(ix[a], ix[b]) for a, b in sk.tie_names[len(sk.bone_names):]]

    def spread_mm(kpt: np.ndarray, ids: np.ndarray) -> float:
        d = np.stack([np.linalg.norm(kpt[:, a] - kpt[:, b], axis=-1) for a, b in pairs], axis=1)
        return float(np.mean([np.nanstd(d[ids == i], axis=0).mean() for i in np.unique(ids)]) * 1000)

    assert spread_mm(sim.kpt_world, sim.truth_id) < 1e-6  # the group moved as one
    write_skeleton_scene(sim, tmp_path / "in", "native")
    runs = {}
    for name in ("rigid", "plain"):
        scene = load_scene(tmp_path / "in", skeleton=str(tmp_path / f"{name}.toml"))
        runs[name] = reconstruct(scene, "ukf", out=tmp_path / name)
    truth = load_scene(tmp_path / "in").truth
    assert truth is not None
    held, free = (spread_mm(runs[n].kpt_world, runs[n].track_id) for n in ("rigid", "plain"))
    assert held < 0.7 * free, (held, free)
    err = {n: mpjpe_by_id(runs[n], truth)[0] for n in runs}
    assert err["rigid"] <= 1.02 * err["plain"], err
    meta = json.loads((tmp_path / "rigid" / "meta.json").read_text())
    assert "ear_l-ear_r" in meta["estimator"]["bones"]["per_person"][str(int(runs["rigid"].track_id[0]))]


def test_gt3d_skeleton_lists_describes_checks_and_writes(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    """``gt3d skeleton`` lists every built-in and shipped skeleton; with a name or file it describes
    and checks it; ``--write`` copies it to a new file that reads back the same, never over one."""
    code, out, _ = _run("skeleton", capsys=capsys)
    assert code == 0 and all(f"\n{name} " in out for name in [*SKELETONS, "mouse"]), out
    rigid = tmp_path / "rigid.toml"
    rigid.write_text(MOUSE.replace('pairs = [', 'groups = [["head", "ear_l", "ear_r"]]\npairs = [', 1))
    code, out, _ = _run("skeleton", str(rigid), capsys=capsys)
    assert code == 0 and "1 rigid groups (11 distances held)" in out and "group 0: head, ear_l, ear_r" in out
    mine = tmp_path / "mine.toml"
    code, out, _ = _run("skeleton", "halpe26", "--write", str(mine), capsys=capsys)
    assert code == 0 and read_skeleton(mine).doc() == SKELETONS["halpe26"].doc()
    before = mine.read_bytes()
    code, out, err = _run("skeleton", "coco17", "--write", str(mine), capsys=capsys)
    assert code == 2 and err == f"error: {mine}: exists: not overwritten\n" and not out
    assert mine.read_bytes() == before
    bad = _toml(tmp_path / "bad.toml", ["a", "b"], [["a", "c"]])
    code, out, err = _run("skeleton", str(bad), capsys=capsys)
    assert code == 2 and err.startswith(f"error: {bad}: bones[0]: ") and err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml", "mine.toml", "rigid.toml"]

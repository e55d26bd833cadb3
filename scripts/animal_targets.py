"""Issue 66's targets on the shared mouse, printed (what exists of them so far):

    make bench-env   # .venv-bench: aniposelib 0.8.0, for section 2
    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/animal_targets.py [--data ../shared/data]

The shared anipose + SLEAP session (``sleap_minimal_session``, its PROVENANCE.md: one mouse, 15
body parts, 4 cameras, 120 frames of proofread labels; anipose's ``calibration.toml`` in
millimetres, its ``side`` camera a copy of ``top``):

1. ``gt3d reconstruct`` of a folder holding SLEAP's ``.slp`` labels per camera and anipose's
   calibration as given (``--calib-units mm``), then with ``--refine-calib``: what it says of the
   cameras, each camera's median reprojection of the estimate through the calibration it used
   (px; the labels of a camera whose views were left out are compared too), each bone's length
   sd over the frames (mm), the time. 1b: both rigs against ``gt3d calib board`` on the session's
   own ChArUco videos (each camera's rotation and centre off the board's).
2. aniposelib ``triangulate`` + ``optim_points`` (``scripts/peer_aniposelib.py``: anipose's
   defaults, the SLEAP skeleton's edges as constraints) on the same labels and the refined
   calibration, scored the same way; gt3dkit's time over its. 2b: each camera left out in turn,
   both estimates from the other three drawn into it (:func:`held_out`); 2c: the same, and both
   from all four cameras, on the rig ``gt3d calib board`` made in 1b (a rig neither estimate
   made: the refined one was fitted to gt3dkit's own estimate).
3. anipose's published ``points3d.h5`` against gt3dkit's: the median distance per joint (mm),
   and its own reprojection per camera.
4. COCO-WholeBody (simulated, no data needed): 133 joints, 8 cameras, 2 px noise, three people,
   written as native keypoints and reconstructed: the hands', the face's and the body's MPJPE
   (mm), against the same scene's 17 body joints given as a COCO-17 scene; three seeds.
5. DeepLabCut multi-animal files written by ``movement`` (``make movement-env``;
   ``scripts/peer_movement.py``) from a simulated scene of the shipped ``mouse`` skeleton: 3 animals,
   4 cameras, 2 px noise, read back with ``--skeleton mouse``: MPJPE against the same scene given
   as native keypoints (target: within 1.1x); three seeds.

Exit status 0 always: it prints what it measured.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gt3dkit.calib.formats import read_calibration  # noqa: E402
from gt3dkit.calib.formats.native import rig_of_doc  # noqa: E402
from gt3dkit.geom.camera import project_points  # noqa: E402
from gt3dkit.io.datasets.native import write_cameras  # noqa: E402
from gt3dkit.io.datasets.sleap import _read  # noqa: E402
from gt3dkit.rig import Camera, Rig  # noqa: E402

GT3D = str(Path(sys.executable).with_name("gt3d"))
CAMS = ("back", "mid", "side", "top")


def labels(root: Path) -> tuple[np.ndarray, list[str], list[tuple[str, str]]]:
    """``(F, J, C, 2)`` the proofread labels of the ``.slp`` files (NaN: none), the node names and
    the edges; each checked against SLEAP's analysis export beside it (the same numbers)."""
    uv, nodes, edges = [], [], []
    for c in CAMS:
        got = _read(next((root / c).glob("*.slp")))
        other = _read(next((root / c).glob("*.analysis.h5")))
        same = np.array_equal(got.tracks, other.tracks, equal_nan=True) and got.nodes == other.nodes
        print(f"   {c}: .slp read with sleap-io {'equals' if same else 'DIFFERS FROM'} its analysis .h5 "
              f"({int(np.isfinite(got.tracks[..., 0, :, :]).sum())} labelled points)")
        nodes, edges = got.nodes, got.edges
        uv.append(np.transpose(got.tracks[0], (2, 1, 0)))  # (F, J, 2), the one animal
    return np.stack(uv, axis=2), nodes, edges


def reprojection(X: np.ndarray, uv: np.ndarray, rig: Rig) -> dict[str, float]:
    """Median px per camera of ``X (F, J, 3)`` (m) against the labels ``uv (F, J, C, 2)``."""
    order = [rig.index(c) for c in CAMS]
    p, _ = project_points(X.reshape(-1, 3), rig.K[order], rig.dist[order], rig.R[order], rig.t[order])
    d = np.linalg.norm(p.reshape(uv.shape) - uv, axis=-1)  # (F, J, C)
    return {c: float(np.nanmedian(d[..., k])) for k, c in enumerate(CAMS)}


def bone_sd_mm(X: np.ndarray, nodes: list[str], edges: list[tuple[str, str]]) -> dict[str, float]:
    ix = {n: i for i, n in enumerate(nodes)}
    out = {}
    for a, b in edges:
        ln = np.linalg.norm(X[:, ix[a]] - X[:, ix[b]], axis=-1)
        out[f"{a}-{b}"] = float(np.nanstd(ln) * 1000)
    return out


def joints_of(csv_path: Path, F: int, J: int) -> np.ndarray:
    """``(F, J, 3)`` of a ``frame,id,joint,x,y,z[,sd]`` file (the one animal; NaN: none)."""
    X = np.full((F, J, 3), np.nan)
    with open(csv_path) as f:
        for r in csv.DictReader(f):
            X[int(r["frame"]), int(r["joint"])] = [float(r["x"]), float(r["y"]), float(r["z"])]
    return X


def summary(name: str, X: np.ndarray, uv: np.ndarray, rig: Rig, nodes: list[str],
            edges: list[tuple[str, str]], sec: float | None) -> dict[str, float]:
    rep = reprojection(X, uv, rig)
    sd = bone_sd_mm(X, nodes, edges)
    print(f"   {name:<28} reprojection px: " + ", ".join(f"{c} {v:.2f}" for c, v in rep.items())
          + f"; bone length sd mm: median {np.nanmedian(list(sd.values())):.2f}, worst "
          + f"{max(sd, key=lambda k: sd[k])} {max(sd.values()):.2f}"
          + (f"; {sec:.2f} s" if sec is not None else ""))
    return rep


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--peer", default=str(REPO / ".venv-bench" / "bin" / "python"))
    args = ap.parse_args()
    data = args.data / "sleap_minimal_session"
    if not data.is_dir():
        print(f"1-3 skipped: {data} absent")
    else:
        mouse(data, args.peer)
    wholebody()
    written_by_movement(REPO / ".venv-movement" / "bin" / "python")
    return 0


def _mpjpe_rows(tracks: object, sk: object) -> np.ndarray:
    """(rows, J) each estimated person's joint errors (m) against the nearest true person of its
    frame."""
    from gt3dkit.types import SkeletonScene, TrackSet

    assert isinstance(tracks, TrackSet) and isinstance(sk, SkeletonScene)
    rows = []
    for f in np.unique(sk.truth_frame):
        tru, est = sk.kpt_world[sk.truth_frame == f], tracks.kpt_world[tracks.frame == f]
        if len(est):
            d = np.nanmean(np.linalg.norm(est[:, None] - tru[None], axis=-1), axis=2)
            rows += [np.linalg.norm(e - tru[np.argmin(d[i])], axis=-1) for i, e in enumerate(est)]
    return np.array(rows)


def wholebody() -> None:
    import dataclasses

    from gt3dkit.api import load_scene, reconstruct
    from gt3dkit.sim import simulate_skeletons, write_skeleton_scene
    from gt3dkit.skeletons import SKELETONS

    print("\n4. COCO-WholeBody, simulated: 133 joints, 8 cameras, 2 px noise, 3 people, 60 frames "
          "(target: hands <= 3 mm, body as the COCO-17 run of the same scene)")
    joints = SKELETONS["wholebody133"].joints
    hand = [k for k, j in enumerate(joints) if "hand" in j or "finger" in j or "thumb" in j]
    face = [k for k, j in enumerate(joints) if j.startswith("face_")]
    for seed in (1, 2, 3):
        sk = simulate_skeletons("native", seed=seed, frames=60, people=3, cameras=8, noise_px=2.0,
                                skeleton="wholebody133")
        body = dataclasses.replace(sk, skeleton="coco17", kpt_world=sk.kpt_world[:, :17], uv=sk.uv[:, :, :17])
        with tempfile.TemporaryDirectory() as tmp_s:
            errs = []
            for name, scene in (("wholebody133", sk), ("coco17", body)):
                write_skeleton_scene(scene, Path(tmp_s) / name, "native")
                t0 = time.perf_counter()
                tracks = reconstruct(load_scene(Path(tmp_s) / name), "ukf")
                errs.append((_mpjpe_rows(tracks, scene) * 1000, time.perf_counter() - t0))
        (e, sec), (e17, sec17) = errs
        print(f"   seed {seed}: hands {np.nanmean(e[:, hand]):.2f} mm (worst joint "
              f"{np.nanmax(np.nanmean(e[:, hand], axis=0)):.2f}), face {np.nanmean(e[:, face]):.2f}, "
              f"body {np.nanmean(e[:, :17]):.2f} against the COCO-17 run's {np.nanmean(e17):.2f}; "
              f"{sec:.1f} s against {sec17:.1f} s")


def written_by_movement(python: Path) -> None:
    import dataclasses

    from gt3dkit.api import load_scene, reconstruct
    from gt3dkit.sim import simulate_skeletons, write_skeleton_scene

    print("\n5. DeepLabCut multi-animal .h5 written by movement, 3 mice, 4 cameras, 2 px noise, 40 frames "
          "(target: MPJPE within 1.1x of the same scene as native keypoints)")
    if not python.exists():
        print(f"   skipped: {python} absent (make movement-env)")
        return
    for seed in (1, 2, 3):
        sk = simulate_skeletons("native", seed=seed, frames=40, people=3, cameras=4, noise_px=2.0,
                                skeleton="mouse")
        with tempfile.TemporaryDirectory() as tmp_s:
            tmp = Path(tmp_s)
            write_skeleton_scene(sk, tmp / "native", "native")
            native = reconstruct(load_scene(tmp / "native"), "ukf")
            ids, F = np.unique(sk.truth_id), len(sk.frames)
            joints = sk.skeleton_doc["joints"] if sk.skeleton_doc else []
            arrays: dict[str, np.ndarray] = {"cameras": np.array(sk.rig.names), "keypoints": np.array(joints),
                                             "individuals": np.array([f"mouse{i}" for i in ids])}
            for c, cam in enumerate(sk.rig.cameras):
                pos = np.full((F, 2, sk.uv.shape[2], len(ids)), np.nan)
                for m in range(len(sk.truth_id)):
                    pos[int(np.searchsorted(sk.frames, sk.truth_frame[m])), :, :, int(np.searchsorted(
                        ids, sk.truth_id[m]))] = sk.uv[m, c].T
                arrays[f"{cam.name}_position"] = pos
                arrays[f"{cam.name}_confidence"] = np.where(np.isfinite(pos[:, 0]), 0.95, np.nan)
            np.savez(tmp / "poses.npz", **arrays)
            dlc = tmp / "dlc"
            q = subprocess.run([str(python), str(REPO / "scripts" / "peer_movement.py"),
                                str(tmp / "poses.npz"), str(dlc)], capture_output=True, text=True)
            if q.returncode != 0:
                print(f"   movement failed: {q.stderr.strip()[-300:]}")
                return
            from gt3dkit.calib.formats import toml as toml_fmt

            toml_fmt.write(sk.rig, dlc / "calibration.toml")
            scene = load_scene(dlc, skeleton="mouse")
            ours = reconstruct(scene, "ukf")
            # movement counts the frames from 0: the truth on that clock, matched person by person
            from_zero = dataclasses.replace(sk, truth_frame=np.searchsorted(sk.frames, sk.truth_frame))
            a, b = np.nanmean(_mpjpe_rows(ours, from_zero)) * 1000, np.nanmean(_mpjpe_rows(native, sk)) * 1000
            print(f"   seed {seed}: {scene.layout} layout, {len(np.unique(ours.track_id))} mice; "
                  f"MPJPE {a:.2f} mm against the native keypoints' {b:.2f} mm: {a / b:.2f}x")

def against_board(data: Path, tmp: Path, rigs: dict[str, Rig]) -> Rig | None:
    """Section 1b: ``gt3d calib board`` on the session's own ChArUco videos, and each of ``rigs``
    against it: per camera, its rotation (degrees) and centre (mm) off the board's, after the
    similarity that maps the board rig's ``mid`` and ``top`` onto the rig's (the mean of their
    rotations, the scale and shift of their centres). Returns the board's rig (None: not made)."""
    from scipy.spatial.transform import Rotation

    videos = [next(iter(sorted((data / c / "calibration_images").glob(f"*.{ext}"))), None)
              for c in CAMS for ext in (("mp4",) if c != "side" else ("MOV",))]
    if any(v is None for v in videos):
        print("   1b. skipped: the calibration videos are absent")
        return None
    out = tmp / "board"
    p = subprocess.run([GT3D, "calib", "board", *map(str, videos), "--board", str(data / "board.toml"),
                        "--out", str(out)], capture_output=True, text=True)
    if p.returncode != 0:
        print(f"   1b. gt3d calib board failed: {p.stderr.strip()[-200:]}")
        return None
    board = read_calibration(out / "cameras.json")  # its cameras named from the videos: back, mid, ...

    def cam(r: Rig, c: str) -> Camera:
        return r.cameras[r.index(c)]

    print("   1b. against gt3d calib board on the session's ChArUco videos (rotation deg / centre mm off "
          "its cameras, after the similarity that maps its mid and top)")
    for label, r in rigs.items():
        ref = ("mid", "top")
        Q = Rotation.from_matrix(np.array([cam(r, c).R.T @ cam(board, c).R for c in ref])).mean().as_matrix()
        A = np.array([cam(r, c).center_world for c in ref])
        B = np.array([cam(board, c).center_world for c in ref])
        s = np.linalg.norm(A[0] - A[1]) / np.linalg.norm(B[0] - B[1])
        d = A.mean(0) - s * (Q @ B.mean(0))
        cells = []
        for c in CAMS:
            ang = np.degrees(Rotation.from_matrix((cam(r, c).R @ Q).T @ cam(board, c).R).magnitude())
            off = np.linalg.norm(cam(r, c).center_world - (s * (Q @ cam(board, c).center_world) + d))
            cells.append(f"{c} {ang:.1f} / {1000 * off:.0f}")
        print(f"      {label:<24} " + ", ".join(cells) + "; focal " +
              ", ".join(f"{c} {cam(r, c).K[0, 0]:.0f} (board {cam(board, c).K[0, 0]:.0f})" for c in CAMS))
    return board


def native_folder(folder: Path, uv: np.ndarray, rig: Rig, cams: tuple[str, ...] | list[str]) -> Path:
    """``folder`` made: the rig's ``cameras.json`` and the labels ``uv (F, J, C, 2)`` of the
    cameras ``cams`` only as a native ``keypoints.csv`` (no scores: the labels alone)."""
    folder.mkdir(parents=True)
    write_cameras(rig, 30.0, folder)
    with open(folder / "keypoints.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "camera", "id", "joint", "u", "v"])
        for fr, j, c in zip(*np.nonzero(np.isfinite(uv[..., 0])), strict=True):
            if CAMS[c] in cams:
                w.writerow([fr, CAMS[c], 0, j, f"{uv[fr, j, c, 0]:.4f}", f"{uv[fr, j, c, 1]:.4f}"])
    return folder


def run_peer(peer_python: str, native: Path, bones: str, out: Path) -> subprocess.CompletedProcess[str]:
    """``scripts/peer_aniposelib.py`` on a :func:`native_folder`, its joints to ``out``."""
    return subprocess.run([peer_python, str(REPO / "scripts" / "peer_aniposelib.py"), str(native), "--bones",
                           bones, "--out", str(out)], capture_output=True, text=True)


def held_out(section: str, data: Path, tmp: Path, uv: np.ndarray, rig: Rig, bones: str, peer_python: str,
             label: str, nodes: list[str], edges: list[tuple[str, str]], all_four: bool) -> None:
    """Each camera left out in turn. gt3dkit (the other three cameras' ``.slp`` files) and
    aniposelib (their labels) estimate on ``rig``; each estimate drawn into the camera it did not
    see, the median px against that camera's labels: how well each predicts a view it was not
    fitted to (its reprojection in the cameras it saw can be lowered by fitting their labels' own
    disagreements). ``all_four``: first both estimates from all four cameras, scored as in
    section 2."""
    F, J = uv.shape[:2]
    key = label.split()[0].strip("'")
    (tmp / f"held_{key}").mkdir()
    write_cameras(rig, 30.0, tmp / f"held_{key}")
    calib = str(tmp / f"held_{key}" / "cameras.json")

    def both(seen: list[str], tag: str) -> tuple[np.ndarray, np.ndarray] | None:
        slp = tmp / f"held_slp_{key}_{tag}"
        for c in seen:
            (slp / c).mkdir(parents=True)
            (slp / c / f"{c}.slp").symlink_to(next((data / c).glob("*.slp")))
        out = tmp / f"held_out_{key}_{tag}"
        p = subprocess.run([GT3D, "reconstruct", str(slp), "--out", str(out), "--calib", calib, "--quiet"],
                           capture_output=True, text=True)
        q = run_peer(peer_python, native_folder(tmp / f"held_native_{key}_{tag}", uv, rig, seen), bones,
                     tmp / f"held_peer_{key}_{tag}.csv")
        if p.returncode != 0 or q.returncode != 0:
            print(f"      {tag}: failed: {(p.stderr + q.stderr).strip()[-300:]}")
            return None
        return joints_of(out / "keypoints.csv", F, J), joints_of(tmp / f"held_peer_{key}_{tag}.csv", F, J)

    if all_four:
        got = both(list(CAMS), "all")
        if got is not None:
            print(f"   {section} all four cameras on {label}:")
            summary("gt3dkit UKF", got[0], uv, rig, nodes, edges, None)
            summary("aniposelib optim_points", got[1], uv, rig, nodes, edges, None)
    print(f"   {section} each camera left out in turn, on {label}: the estimate from the other three drawn "
          "into the one left out (median px against its labels; in brackets, the three it saw)")
    lower = []
    for held in CAMS:
        seen = [c for c in CAMS if c != held]
        got = both(seen, held)
        if got is None:
            continue
        px = {}
        for name, X in zip(("gt3dkit", "aniposelib"), got, strict=True):
            rep = reprojection(X, uv, rig)
            px[name] = rep[held]
            print(f"      {held:<5} left out, {name:<11} {rep[held]:6.2f} px  ("
                  + ", ".join(f"{c} {rep[c]:.2f}" for c in seen) + ")")
        if px["gt3dkit"] < px["aniposelib"]:
            lower.append(held)
    print(f"   gt3dkit's prediction of the camera left out lower in {len(lower)} of 4 ({', '.join(lower)})")


def mouse(data: Path, peer_python: str) -> None:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    print("0. the labels: SLEAP's .slp files through sleap-io, against its analysis export")
    uv, nodes, edges = labels(data)
    F, J = uv.shape[:2]
    rig = read_calibration(data / "calibration.toml").in_metres(1e-3)
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        folder = tmp / "mouse"
        for c in CAMS:
            (folder / c).mkdir(parents=True)
            (folder / c / f"{c}.slp").symlink_to(next((data / c).glob("*.slp")))
        (folder / "calibration.toml").symlink_to(data / "calibration.toml")
        print("1. gt3d reconstruct of the SLEAP .slp files, anipose's calibration as given "
              "(--calib-units mm), then with --refine-calib")
        runs = {}
        for name, extra in (("as given", []), ("--refine-calib", ["--refine-calib"])):
            out = tmp / name.strip("-").replace(" ", "_")
            t0 = time.perf_counter()
            p = subprocess.run([GT3D, "reconstruct", str(folder), "--out", str(out), "--calib-units", "mm",
                                "--quiet", *extra], capture_output=True, text=True)
            sec = time.perf_counter() - t0
            if p.returncode != 0:
                print(f"   {name}: failed: {p.stderr.strip()}")
                return
            for w in (p.stdout + p.stderr).splitlines():
                if any(f"camera {c}" in w for c in CAMS):
                    print(f"   {w[:170]}")
            meta = json.loads((out / "meta.json").read_text())
            used = rig_of_doc(meta["calibration_refinement"]["refined_rig"], "meta.json") if extra else rig
            runs[name] = (joints_of(out / "keypoints.csv", F, J), used, sec)
            summary(f"gt3dkit UKF, {name}", runs[name][0], uv, used, nodes, edges, sec)
        ours, refined, _ = runs["--refine-calib"]
        board = against_board(data, tmp, {"anipose's, as given": rig, "gt3dkit --refine-calib": refined})
        # the estimate alone on the refined rig (what aniposelib is given below), timed
        write_cameras(refined, 30.0, tmp)
        t0 = time.perf_counter()
        p = subprocess.run([GT3D, "reconstruct", str(folder), "--out", str(tmp / "on_refined"), "--calib",
                            str(tmp / "cameras.json"), "--quiet"], capture_output=True, text=True)
        sec = time.perf_counter() - t0
        if p.returncode == 0:
            ours = joints_of(tmp / "on_refined" / "keypoints.csv", F, J)
            summary("gt3dkit UKF, the refined rig", ours, uv, refined, nodes, edges, sec)

        print("\n2. aniposelib triangulate + optim_points on the same labels and the refined calibration")
        if Path(peer_python).exists():
            native = native_folder(tmp / "native", uv, refined, CAMS)
            bones = ",".join(f"{nodes.index(a)}-{nodes.index(b)}" for a, b in edges)
            t0 = time.perf_counter()
            q = run_peer(peer_python, native, bones, tmp / "peer.csv")
            peer_sec = time.perf_counter() - t0
            if q.returncode == 0:
                peer = joints_of(tmp / "peer.csv", F, J)
                theirs_px = summary("aniposelib optim_points", peer, uv, refined, nodes, edges, peer_sec)
                ours_px = reprojection(ours, uv, refined)
                lower = [c for c in CAMS if ours_px[c] < theirs_px[c]]
                ratio = sec / peer_sec
                print(f"   gt3dkit's median reprojection lower in {len(lower)} of 4 cameras "
                      f"({', '.join(lower)}); its time over aniposelib's: {ratio:.2f}x (target 0.3x)")
            else:
                print(f"   aniposelib failed: {q.stderr.strip()[-300:]}")
            held_out("2b.", data, tmp, uv, refined, bones, peer_python, "the refined rig", nodes, edges,
                     False)
            if board is not None:  # a rig neither estimator's refinement made
                held_out("2c.", data, tmp, uv, board, bones, peer_python, "gt3d calib board's rig (1b)",
                         nodes, edges, True)
        else:
            print(f"   skipped: {peer_python} absent (make bench-env)")

        print("\n3. anipose's published points3d.h5 beside gt3dkit's estimate")
        import h5py

        with h5py.File(data / "points3d.h5") as h:
            theirs = np.asarray(h["tracks"][()], dtype=np.float64)[:, 0] * 1e-3  # (F, J, 3) mm -> m
        summary("anipose points3d.h5", theirs, uv, rig, nodes, edges, None)
        d = np.linalg.norm(theirs - ours, axis=-1) * 1000
        print("   median distance to gt3dkit's per joint, mm: "
              + ", ".join(f"{n} {np.nanmedian(d[:, j]):.1f}" for j, n in enumerate(nodes)))


if __name__ == "__main__":
    sys.exit(main())

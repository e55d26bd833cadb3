"""What gt3dkit guarantees about its outputs: one run's files or the previous ones, never a
mix, never a half; interruptions and closed pipes end in one line; odd input is said.

The cases the hostile-input suite (tests/hostile.py) cannot express as one command: two
runs into one folder, signals, killed runs, closed pipes, and results checked for being
right, not only for running.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.cli import main
from gt3dkit.commands.printing import pose_table
from gt3dkit.eval.pose import PoseScores
from gt3dkit.io.atomic import MARKER, clean_stale
from gt3dkit.sim import Errors, simulate, simulate_skeletons, write_scene, write_skeleton_scene

GT3D = [sys.executable, "-m", "gt3dkit.cli"]


def _dead_pid() -> int:
    p = subprocess.Popen(["true"])
    p.wait()
    return p.pid


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".gt3d-" in p.name)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = Path(tmp_path_factory.mktemp("scenes"))
    write_scene(simulate("native", seed=2, frames=6, people=3, errors=Errors(dropped=0.0)), root / "boxes",
                "native")
    write_skeleton_scene(simulate_skeletons("native", seed=2, frames=4, people=2, cameras=4),
                         root / "kpts", "native")
    write_scene(simulate("native", seed=4, frames=240, people=10, noise_px=1.0), root / "long", "native")
    return {p.name: p for p in root.iterdir()}


def test_a_new_result_replaces_the_whole_folder(scenes, tmp_path, capsys) -> None:
    """No stale keypoints.csv of a keypoint run beside the box results of the next run."""
    out = tmp_path / "out"
    assert main(["reconstruct", str(scenes["kpts"]), "--out", str(out), "--estimator",
                 "triangulation"]) == 0
    assert (out / "keypoints.csv").exists()
    assert main(["reconstruct", str(scenes["boxes"]), "--out", str(out), "--estimator",
                 "triangulation"]) == 0
    assert not (out / "keypoints.csv").exists() and (out / MARKER).exists()
    assert json.loads((out / "meta.json").read_text())["input"]["root"] == str(scenes["boxes"])
    assert _leftovers(tmp_path) == []


def test_simulate_replaces_an_earlier_scene_whole(tmp_path, capsys) -> None:
    out = tmp_path / "scene"
    assert main(["simulate", "--kind", "skeleton", "--out", str(out), "--frames", "3",
                 "--people", "1"]) == 0
    assert (out / "keypoints.csv").exists()
    assert main(["simulate", "--out", str(out), "--frames", "3", "--people", "1"]) == 0
    assert not (out / "keypoints.csv").exists() and (out / "boxes.csv").exists()
    assert main(["reconstruct", str(out), "--out", str(tmp_path / "r"), "--estimator",
                 "triangulation"]) == 0


def test_stale_temp_folders_of_dead_runs_are_removed(scenes, tmp_path, capsys) -> None:
    out = tmp_path / "out"
    dead = tmp_path / f".out.gt3d-tmp-{_dead_pid()}-abc"
    alive = tmp_path / f".out.gt3d-tmp-{os.getpid()}-def"  # a run still going: keep
    other = tmp_path / f".other.gt3d-tmp-{_dead_pid()}-ghi"  # another output's: not ours to judge
    for d in (dead, alive, other):
        d.mkdir()
        (d / "tracks.csv").write_text("half")
    assert main(["reconstruct", str(scenes["boxes"]), "--out", str(out), "--estimator",
                 "triangulation"]) == 0
    assert not dead.exists() and alive.exists() and other.exists()
    assert clean_stale(tmp_path / "other") == [other]


def test_interrupted_write_leaves_the_previous_result(scenes, tmp_path, capsys, monkeypatch) -> None:
    """Ctrl-C while the files are written: the previous result whole, no temp folder."""
    out = tmp_path / "out"
    assert main(["reconstruct", str(scenes["boxes"]), "--out", str(out), "--estimator",
                 "triangulation"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr("gt3dkit.io.writers.write_downweighted_csv", interrupted)
    monkeypatch.setattr("gt3dkit.io.writers.write_keypoints_csv", interrupted)
    assert main(["reconstruct", str(scenes["kpts"]), "--out", str(out), "--estimator", "ukf"]) == 130
    err = capsys.readouterr().err
    assert err.startswith("error: interrupted") and err.count("\n") == 1
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert _leftovers(tmp_path) == []


def test_a_bug_is_one_line_and_exit_1(scenes, tmp_path, capsys, monkeypatch) -> None:
    def broken(*a, **k):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr("gt3dkit.io.writers.write_tracks_csv", broken)
    assert main(["reconstruct", str(scenes["boxes"]), "--out", str(tmp_path / "o"), "--estimator",
                 "triangulation"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: internal error, ZeroDivisionError: a bug") and err.count("\n") == 1
    assert "--debug" in err and not (tmp_path / "o").exists() and _leftovers(tmp_path) == []
    assert main(["reconstruct", str(scenes["boxes"]), "--out", str(tmp_path / "o"), "--estimator",
                 "triangulation", "--debug"]) == 1
    assert "Traceback" in capsys.readouterr().err  # --debug shows it


def test_output_checks_come_before_the_work(scenes, tmp_path, capsys, monkeypatch) -> None:
    def never(*a, **k):
        raise AssertionError("the estimation ran")

    monkeypatch.setattr("gt3dkit.fusion.preparation.prepare.prepare", never)
    f = tmp_path / "file"
    f.write_text("x")
    for cmd in ("reconstruct", "compare"):
        assert main([cmd, str(scenes["boxes"]), "--out", str(f)]) == 2
        assert "not a folder" in capsys.readouterr().err
    assert f.read_text() == "x"


@pytest.mark.parametrize("sig,code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_during_a_run(scenes, tmp_path, sig, code) -> None:
    out = tmp_path / "out"
    shutil.copytree(scenes["boxes"], tmp_path / "prev_in")
    subprocess.run([*GT3D, "reconstruct", str(scenes["boxes"]), "--out", str(out), "--estimator",
                    "triangulation"], check=True, capture_output=True)
    before = _snapshot(out)
    for wait in (2.0, 1.2, 3.0, 0.8, 6.0):  # imports done, estimating (compare runs a few seconds)
        # a background job's children start with SIGINT ignored (POSIX shells do that): restore it
        p = subprocess.Popen([*GT3D, "compare", str(scenes["long"]), "--out", str(out), "--no-progress"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             preexec_fn=lambda: signal.signal(sig, signal.SIG_DFL))  # noqa: PLW1509
        time.sleep(wait)
        p.send_signal(sig)
        _, err = p.communicate(timeout=300)
        # -sig: it came before Python had even started gt3d (a loaded machine), 0: after the run
        # had finished (a fast one): either way the signal met no work of ours; try another moment
        if p.returncode not in (-sig, 0):
            break
        before = _snapshot(out)  # a finished run's is the result now (compare's: a folder per estimator)
    assert p.returncode == code, err
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    assert _snapshot(out) == before
    assert _leftovers(tmp_path) == []


def _snapshot(out: Path) -> dict[str, bytes]:
    """Every file below ``out`` (its path relative to ``out``) with its bytes."""
    return {str(q.relative_to(out)): q.read_bytes() for q in sorted(out.rglob("*")) if q.is_file()}


# an object a signal leaves half-built (numba's compiler, interrupted inside llvmlite) fails in
# its finaliser as the process ends: that must not add a traceback under the one error line
HALF_BUILT = """
import os, signal, sys, time
from gt3dkit.commands.common import signals_handled, unexpected_error
class HalfBuilt:
    def __del__(self):
        raise AttributeError("no attribute '_as_parameter_'")
kept = []
try:
    with signals_handled():
        kept.append(HalfBuilt())
        os.kill(os.getpid(), signal.{sig})
        time.sleep(30)
except BaseException as e:
    code = unexpected_error(e, False) if not isinstance(e, KeyboardInterrupt) else 130
    if isinstance(e, KeyboardInterrupt):
        print("error: interrupted (Ctrl-C): no output written or changed", file=sys.stderr)
    sys.exit(code)
"""


@pytest.mark.parametrize("sig,code", [("SIGTERM", 143), ("SIGINT", 130)])
def test_finalisers_after_a_signal_add_nothing(sig, code) -> None:
    p = subprocess.run([sys.executable, "-c", HALF_BUILT.format(sig=sig)], capture_output=True,
                       text=True, timeout=60, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert p.returncode == code, p.stderr
    assert p.stderr.startswith("error: ") and p.stderr.count("\n") == 1, p.stderr


def test_killed_run_then_rerun(scenes, tmp_path) -> None:
    """SIGKILL at any moment: the folder holds the old or the new result, and the next run
    removes what the killed one left."""
    out = tmp_path / "out"
    cmd = [*GT3D, "reconstruct", str(scenes["boxes"]), "--out", str(out), "--estimator", "triangulation"]
    rng = np.random.default_rng(0)
    for _ in range(3):
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(float(rng.uniform(0.2, 1.5)))
        p.kill()
        p.wait()
        if out.exists():
            assert {"tracks.csv", "meta.json", MARKER} <= {q.name for q in out.iterdir()}
    subprocess.run(cmd, check=True, capture_output=True)
    assert _leftovers(tmp_path) == []
    assert (out / MARKER).exists()


def test_concurrent_runs_into_one_folder_do_not_mix(scenes, tmp_path) -> None:
    out = tmp_path / "out"
    runs = [[*GT3D, "reconstruct", str(scenes["kpts"]), "--out", str(out), "--estimator", "triangulation"],
            [*GT3D, "reconstruct", str(scenes["boxes"]), "--out", str(out), "--estimator", "triangulation"]]
    for _ in range(3):
        ps = [subprocess.Popen(c, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
              for c in runs]
        for p in ps:
            _, err = p.communicate(timeout=120)
            assert p.returncode == 0, err
        root = json.loads((out / "meta.json").read_text())["input"]["root"]
        assert (out / "keypoints.csv").exists() == (root == str(scenes["kpts"]))
        n_rows = len((out / "tracks.csv").read_text().splitlines()) - 1
        assert n_rows == json.loads((out / "meta.json").read_text())["counts"]["rows"]
        assert _leftovers(tmp_path) == []


def test_closed_pipe_is_quiet(scenes, tmp_path) -> None:
    """``gt3d ... | head``: the reader went away; the result is written, nothing is said."""
    p = subprocess.Popen([*GT3D, "reconstruct", str(scenes["boxes"]), "--out", str(tmp_path / "o"),
                          "--estimator", "triangulation"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert p.stdout is not None and p.stderr is not None
    p.stdout.close()
    with p.stderr:
        err = p.stderr.read().decode()
    assert p.wait() == 141 and err == "", err
    assert (tmp_path / "o" / MARKER).exists()


# the program's own end (gt3dkit.cli.finish) after a command that left work behind it: a thread
# pool's task still running, an atexit handler, stdout buffered in a pipe
LEFT_BEHIND = """
import atexit, sys, time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from gt3dkit import cli
out = Path(sys.argv[1])
ThreadPoolExecutor(1).submit(lambda: (time.sleep(0.3), (out / "pool").write_text("done")))
atexit.register(lambda: (out / "atexit").write_text("ran"))
print("x" * 100_000, end="")  # more than a pipe's buffer holds
cli.finish(3)
"""


def test_the_programs_own_end_leaves_nothing_undone(tmp_path) -> None:
    """``gt3d`` ends its process without the interpreter's teardown (:func:`gt3dkit.cli.finish`):
    a pool thread's work still finishes, atexit handlers still run, what is buffered for stdout
    still arrives, and the exit status is kept."""
    p = subprocess.run([sys.executable, "-c", LEFT_BEHIND, str(tmp_path)], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 3, p.stderr
    assert p.stdout == "x" * 100_000 and p.stderr == ""
    assert (tmp_path / "pool").read_text() == "done" and (tmp_path / "atexit").read_text() == "ran"


# the same after a signal: a thread blocked on a lock the interrupted code held (llvmlite's, as
# numba compiled a kernel for a pool thread, when `gt3d compare` was stopped by SIGTERM)
BLOCKED = """
import atexit, sys, threading
from pathlib import Path
from gt3dkit import cli
out = Path(sys.argv[1])
held = threading.Lock()
held.acquire()
threading.Thread(target=held.acquire).start()  # never gets it
atexit.register(lambda: (out / "atexit").write_text("ran"))
print("stopped", file=sys.stderr)
cli.finish(143)
"""


def test_the_program_ends_after_a_signal_whatever_a_thread_waits_for(tmp_path) -> None:
    """After a signal (status 143), the program ends although a thread waits for ever on a lock
    the signal left held (it waited for it, and ``gt3d compare`` hung): the atexit handlers
    still run, what was said arrives, the status is kept."""
    p = subprocess.run([sys.executable, "-c", BLOCKED, str(tmp_path)], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 143 and p.stderr == "stopped\n", p.stderr
    assert (tmp_path / "atexit").read_text() == "ran"


def test_the_program_gives_mains_status(tmp_path) -> None:
    """``python -m gt3dkit.cli`` (as the ``gt3d`` script): the error line and status 2 of bad input,
    0 and the whole help text through a pipe."""
    p = subprocess.run([*GT3D, "reconstruct", str(tmp_path / "absent"), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and p.stderr.startswith("error: ") and p.stderr.count("\n") == 1, p.stderr
    assert not (tmp_path / "o").exists()
    h = subprocess.run([*GT3D, "reconstruct", "--help"], capture_output=True, text=True, timeout=120)
    assert h.returncode == 0 and h.stdout.startswith("usage: gt3d reconstruct") and h.stdout.endswith("\n")


def test_off_image_boxes_are_ignored_with_a_warning(tmp_path, capsys) -> None:
    """Boxes entirely outside the image (negative coordinates) must not pull the estimate away."""
    root = tmp_path / "in"
    write_scene(simulate("native", seed=5, frames=8, people=4, errors=Errors(dropped=0.0)), root, "native")
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "clean")]) == 0
    clean = capsys.readouterr().out
    lines = (root / "boxes.csv").read_text().splitlines()
    rng = np.random.default_rng(5)
    for i in rng.choice(np.arange(1, len(lines)), size=len(lines) // 5, replace=False):
        f = lines[i].split(",")
        f[3:] = ["-300", "-200", "-120", "-20"]
        lines[i] = ",".join(f)
    (root / "boxes.csv").write_text("\n".join(lines) + "\n")
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "odd")]) == 0
    cap = capsys.readouterr()
    assert cap.err.count("warning:") == 1 and f"{len(lines) // 5} boxes lie entirely outside" in cap.err
    mota = [line for line in clean.splitlines() if line.startswith("ground plane")][0]
    assert mota.split("MOTA ")[1].split()[0] == "100.0"
    odd = [line for line in cap.out.splitlines() if line.startswith("ground plane")][0]
    assert odd.split("MOTA ")[1].split()[0] == "100.0"


def test_evaluate_uses_max_dist(scenes, tmp_path, capsys) -> None:
    out = tmp_path / "out"
    assert main(["reconstruct", str(scenes["boxes"]), "--out", str(out), "--estimator", "triangulation"]) == 0
    t = (out / "tracks.csv").read_text().splitlines()
    shifted = [t[0]] + [",".join([*r.split(",")[:2], f"{float(r.split(',')[2]) + 0.3:.6f}",
                                  *r.split(",")[3:]]) for r in t[1:]]
    (out / "tracks.csv").write_text("\n".join(shifted) + "\n")
    capsys.readouterr()
    motas = []
    for d in ("0.1", "1"):
        assert main(["evaluate", str(out), "--truth", str(scenes["boxes"]), "--max-dist-m", d]) == 0
        line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("ground plane")][0]
        assert f"ground plane, {d} m" in line
        motas.append(float(line.split("MOTA ")[1].split()[0]))
    assert motas[1] == 100.0 and motas[0] < 0  # 0.3 m off: a miss and a false positive at 0.1 m


def test_tables_print_a_dash_for_no_value() -> None:
    p = PoseScores(ap={25: 0.5, 50: 0.6, 100: 0.7, 150: 0.8}, recall_500=1.0, mpjpe_mm=float("nan"),
                   poses_truth=3, poses_predicted=0)
    text = pose_table([("triangulation", p, float("nan"))])
    assert "nan" not in text and text.splitlines()[-1].rstrip().endswith("-")


def test_distortion_fold_agrees_with_opencv_round_trips() -> None:
    """Where distortion_fold finds no fold, OpenCV undistorts every pixel and distorts it back
    to itself; where it finds one, some pixel does not come back (two undistorted points)."""
    import cv2

    from gt3dkit.types import distortion_fold

    K = np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]])
    u, v = np.meshgrid(np.linspace(0, 1919, 41), np.linspace(0, 1079, 23))
    px = np.stack([u.ravel(), v.ravel()], 1)[:, None, :]

    def round_trip_px(dist: np.ndarray) -> float:
        n = cv2.undistortPoints(px, K, dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                                       200, 1e-12))
        xyz = np.concatenate([n[:, 0], np.ones((len(n), 1))], 1)
        back, _ = cv2.projectPoints(xyz, np.zeros(3), np.zeros(3), K, dist)
        return float(np.nanmax(np.linalg.norm(back[:, 0] - px[:, 0], axis=1)))

    for d in ([-0.06, 0.01, -0.001, -0.0007, 0.0], [-0.2, 0.1, 0.0, 0.0, 0.0], [0.3, 0.0, 0.0, 0.0, 0.0],
              [-0.1, 0.02, 0.002, -0.001, 0.001]):
        dist = np.array(d)
        assert distortion_fold(K, dist, 1920, 1080) is None
        assert round_trip_px(dist) < 0.01, d
    for d in ([-1.0, 0, 0, 0, 0], [-0.3, 0, 0, 0, 0], [0, 0, -1.0, 0, 0]):
        dist = np.array(d)
        assert distortion_fold(K, dist, 1920, 1080) is not None
        assert round_trip_px(dist) > 1.0, d

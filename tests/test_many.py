"""gt3d reconstruct-many: a local process pool and a Dask LocalCluster on loopback."""

from __future__ import annotations

import contextlib
import csv
import io
import os
import subprocess
import sys
from pathlib import Path

import pytest

from gt3dkit.cli import main
from gt3dkit.many import Job, _ran, run_job
from gt3dkit.sim import Errors, simulate, write_scene


@pytest.fixture(scope="module")
def manifest(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = Path(tmp_path_factory.mktemp("many"))
    for i in (1, 2, 3):
        sim = simulate("native", seed=i, frames=6, people=2, errors=Errors(dropped=0.0))
        write_scene(sim, root / "seqs" / f"s{i}", "native")
    bad = root / "seqs" / "s4"
    bad.mkdir()
    (bad / "cameras.json").write_text("{")  # malformed
    (root / "m.txt").write_text("# all of them\nseqs/s*\n")
    return root / "m.txt"


def _run(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(argv))
    return code, out.getvalue(), err.getvalue()


def _summary(out: Path) -> dict[str, dict[str, str]]:
    with open(out / "summary.csv", newline="") as f:
        return {Path(r["input"]).name: r for r in csv.DictReader(f)}


def test_dask_local_cluster(manifest: Path, tmp_path: Path) -> None:
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=":0") as cluster:
        code, so, se = _run("reconstruct-many", str(manifest), "--out", str(tmp_path / "o"), "--scheduler",
                            cluster.scheduler_address, "--quiet", "--estimator", "triangulation")
        assert code == 1 and "1 sequence failed: s4" in se, se
        s = _summary(tmp_path / "o")
        assert [s[k]["status"] for k in ("s1", "s2", "s3", "s4")] == ["done", "done", "done", "failed"]
        assert "cameras.json" in s["s4"]["error"]
        for k in ("s1", "s2", "s3"):
            assert (tmp_path / "o" / k / "tracks.csv").is_file()
        # a rerun skips what is complete and current, and redoes a sequence whose input changed
        p = manifest.parent / "seqs" / "s2" / "boxes.csv"
        p.write_text(p.read_text() + "")
        lines = p.read_text().splitlines()
        p.write_text("\n".join(lines[:-1]) + "\n")
        code, so, se = _run("reconstruct-many", str(manifest), "--out", str(tmp_path / "o"), "--scheduler",
                            cluster.scheduler_address, "--quiet", "--estimator", "triangulation")
        s = _summary(tmp_path / "o")
        assert [s[k]["status"] for k in ("s1", "s2", "s3")] == ["up to date", "done", "up to date"]


def test_local_pool_and_misuse(manifest: Path, tmp_path: Path) -> None:
    code, so, se = _run("reconstruct-many", str(manifest), "--out", str(tmp_path / "o"), "--jobs", "2",
                        "--quiet", "--estimator", "triangulation", "--report")
    assert code == 1
    assert (tmp_path / "o" / "index.html").is_file()
    assert (tmp_path / "o" / "s1" / "report" / "index.html").is_file()
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "x.txt").write_text("x")
    code, _, se = _run("reconstruct-many", str(manifest), "--out", str(tmp_path / "mine"))
    assert code == 2 and "gt3dkit did not write" in se
    bad = tmp_path / "bad.txt"
    bad.write_text("nowhere/*\n")
    code, _, se = _run("reconstruct-many", str(bad), "--out", str(tmp_path / "o2"))
    assert code == 2 and "bad.txt: line 1" in se and "matches no folder" in se


def _gt3d_on_scheduler(command: str, address: str, tmp_path: Path
                       ) -> tuple[subprocess.CompletedProcess, Path]:
    """``gt3d COMMAND`` of the bundled MultiviewX (a one-line manifest of it for ``reconstruct-many``)
    on the scheduler at ``address``, Dask's connect timeout 1 s: the process and its ``--out``."""
    src = Path(__file__).parents[1] / "gt3dkit" / "data" / "multiviewx"
    arg = str(src)
    if command == "reconstruct-many":
        arg = str(tmp_path / "m.txt")
        Path(arg).write_text(f"{src}\n")
    out = tmp_path / "o"
    env = {**os.environ, "DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT": "1s"}
    argv = [sys.executable, "-m", "gt3dkit.cli", command, arg, "--out", str(out), "--scheduler", address,
            "--quiet"]
    return subprocess.run(argv, capture_output=True, text=True, env=env, cwd=tmp_path), out


@pytest.mark.parametrize("command", ["reconstruct", "reconstruct-many"])
def test_an_unreachable_scheduler_is_one_error_line_and_nothing_written(command: str, tmp_path: Path) -> None:
    """Nothing listens on port 9 of loopback: after Dask's own connect timeout (1 s here, by its
    configuration's environment variable) one ``error:`` line naming ``--scheduler``, exit 2, no
    output folder (``reconstruct-many`` used to make it, and its marker, before connecting)."""
    pytest.importorskip("distributed")
    r, out = _gt3d_on_scheduler(command, "tcp://127.0.0.1:9", tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and r.stderr.startswith(
        "error: --scheduler: cannot reach the Dask scheduler at tcp://127.0.0.1:9 ("), r.stderr
    assert "Traceback" not in r.stderr and not out.exists()


@pytest.mark.parametrize("command", ["reconstruct", "reconstruct-many"])
def test_a_scheduler_without_workers_is_one_error_line_and_nothing_written(command: str, tmp_path: Path
                                                                           ) -> None:
    """A scheduler no worker joins within Dask's connect timeout: one ``error:`` line, exit 2, no
    output (``reconstruct-many`` waited for ever, ``reconstruct`` failed inside Dask's scatter)."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=0, processes=True, host="127.0.0.1", dashboard_address=":0") as c:
        r, out = _gt3d_on_scheduler(command, c.scheduler_address, tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr == (f"error: --scheduler: the Dask scheduler at {c.scheduler_address} has no worker "
                        "(none joined in 1 s)\n"), r.stderr
    assert not out.exists()


def _dies_on_s2(job: Job) -> dict[str, object]:
    """:func:`run_job`, but the process running sequence ``s2`` dies (as the out-of-memory killer
    ends it)."""
    if Path(job.input).name == "s2":
        os._exit(1)
    return run_job(job)


@pytest.mark.parametrize("where", ["dask", "processes"])
def test_a_sequence_whose_process_dies_is_a_failed_row(manifest: Path, where: str, tmp_path: Path) -> None:
    """The summary still comes: on Dask (which tries it on 4 workers first) the dead sequence alone
    fails, with why; in local processes its pool breaks, so the sequences not done by then fail too, and say
    that a rerun does them."""
    todo = [Job(str(p), str(tmp_path / p.name), "triangulation", False)
            for p in sorted((manifest.parent / "seqs").glob("s[123]"))]
    if where == "dask":
        distributed = pytest.importorskip("distributed")
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                      dashboard_address=":0") as cluster:
            with distributed.Client(cluster) as client:
                rows = {Path(r["input"]).name: r for r in _ran(todo, client, None, False, _dies_on_s2)}
        # a sequence done on a worker that then died is done again, and found up to date
        assert [rows[k]["status"] for k in ("s1", "s3")] in (["done"] * 2, ["up to date", "done"],
                                                             ["done", "up to date"], ["up to date"] * 2), rows
        assert rows["s2"]["status"] == "failed", rows
    else:
        rows = {Path(r["input"]).name: r for r in _ran(todo, None, 1, False, _dies_on_s2)}
        assert rows["s1"]["status"] == "done" and rows["s2"]["status"] == "failed", rows
        assert "run again" in rows["s2"]["error"]
    assert "out of memory?" in rows["s2"]["error"]


def test_a_worker_with_another_gt3dkit_is_one_error_line(monkeypatch: pytest.MonkeyPatch) -> None:
    """The workers have gt3dkit 0.1.0 (this checkout); this process says it has another: the
    connection is refused before anything runs, naming a worker and both versions."""
    distributed = pytest.importorskip("distributed")
    import gt3dkit.windows.cluster as windows
    from gt3dkit.errors import InputError

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=":0") as cluster:
        windows.connect_scheduler(cluster.scheduler_address).close()  # the same gt3dkit: connected
        monkeypatch.setattr(windows, "__version__", "0.0.0-other")
        said = (r"^--scheduler: the Dask worker tcp://127\.0\.0\.1:\d+ has gt3dkit \S+, this process "
                r"0\.0\.0-other \(2 worker\(s\) differ\)")
        with pytest.raises(InputError, match=said):
            windows.connect_scheduler(cluster.scheduler_address)


def test_every_sequence_is_read_as_the_options_say(tmp_path: Path) -> None:
    """--calib-units, --skeleton and --fps reach every sequence (reconstruct-many had none: a lab's
    sessions calibrated in millimetres could not be run), and a rerun read another way is no
    longer up to date."""
    import json

    import numpy as np

    sim = simulate("native", seed=5, frames=6, people=2, errors=Errors(dropped=0.0))
    for name in ("a", "b"):
        write_scene(sim, tmp_path / "seqs" / name, "native")
        cams = tmp_path / "seqs" / name / "cameras.json"
        doc = json.loads(cams.read_text())
        for c in doc["cameras"]:
            c["t"] = [1000.0 * v for v in c["t"]]  # the same rig in millimetres
        cams.write_text(json.dumps(doc))
        for f in (tmp_path / "seqs" / name).glob("truth*"):
            f.unlink()
    (tmp_path / "m.txt").write_text("seqs/*\n")

    def centres() -> np.ndarray:
        return np.loadtxt(tmp_path / "o" / "a" / "tracks.csv", delimiter=",", skiprows=1, usecols=(2, 3))

    code, so, se = _run("reconstruct-many", str(tmp_path / "m.txt"), "--out", str(tmp_path / "o"), "--jobs",
                        "1", "--quiet", "--estimator", "triangulation", "--calib-units", "mm")
    assert code == 0, se
    assert np.abs(centres()).max() < 50  # metres
    meta = json.loads((tmp_path / "o" / "a" / "meta.json").read_text())
    assert meta["input"]["load"]["calib_units"] == "mm"
    same = ("reconstruct-many", str(tmp_path / "m.txt"), "--out", str(tmp_path / "o"), "--jobs", "1",
            "--quiet", "--estimator", "triangulation")
    code, so, _ = _run(*same, "--calib-units", "mm")
    assert code == 0 and "2 up to date" in so
    code, so, _ = _run(*same)
    assert code == 0 and "2 reconstructed" in so and np.abs(centres()).max() > 500  # read as metres
    code, _, se = _run("reconstruct-many", str(tmp_path / "m.txt"), "--out", str(tmp_path / "o3"),
                       "--skeleton", str(tmp_path / "none.toml"))
    assert code == 2 and se.count("\n") == 1 and "none.toml: no such file" in se
    assert not (tmp_path / "o3").exists()

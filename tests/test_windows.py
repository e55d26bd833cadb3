"""Long sequences in overlapping time windows (gt3dkit.windows): the stitched result against the
whole-sequence smoother, the same output from one process, two processes and a Dask cluster on
loopback, and misuse."""

from __future__ import annotations

import contextlib
import gc
import io
import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from gt3dkit import cli
from gt3dkit.api import (
    load_head,
    load_scene,
    process_noise_prepared,
    reconstruct,
    scene_kind,
    take_rows,
    tiny_scene,
)
from gt3dkit.cli import main
from gt3dkit.commands.common import Stages, clock
from gt3dkit.early import WARM_KINDS, Early
from gt3dkit.errors import InputError
from gt3dkit.fusion.base import make_estimator
from gt3dkit.sim import Errors, simulate_skeletons, write_skeleton_scene
from gt3dkit.windows import (
    Cluster,
    Plan,
    Window,
    _run_windows,
    _window_scenes,
    noise,
    reconstruct_windowed,
    reconstruct_windows,
)
from gt3dkit.windows.cluster import connect_scheduler, process_pool
from gt3dkit.windows.noise import noise_sample
from gt3dkit.windows.plan import balanced_size, plan_windows
from gt3dkit.windows.stitch import WindowJob, run_window
from tests.scenes import written_scene


def _run(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(argv))
    return code, out.getvalue(), err.getvalue()


def test_windows_cover_every_frame_once() -> None:
    frames = np.arange(0, 500, 5)
    ws = plan_windows(frames, 30, 7)
    cores = np.concatenate([frames[(frames >= w.first) & (frames <= w.last)] for w in ws])
    np.testing.assert_array_equal(cores, frames)
    for w in ws:
        inside = frames[(frames >= w.lo) & (frames <= w.hi)]
        assert w.lo <= w.first <= w.last <= w.hi
        assert (np.sum(inside < w.first) == 7 or w.lo == frames[0]) and (np.sum(inside > w.last) == 7
                                                                        or w.hi == frames[-1])


@pytest.mark.parametrize(("n", "size", "workers"), [(4000, 1639, 2), (4000, 1639, 1), (4000, 0, 3), (7, 2, 2),
                                                   (100, 1000, 4)])
def test_balanced_windows_are_a_multiple_of_the_workers(n: int, size: int, workers: int) -> None:
    """The windows the tool chooses for ``workers``: a multiple of them (no worker runs the last one
    alone), of lengths differing by at most one window's rounding, none longer than asked."""
    ws = plan_windows(np.arange(n), balanced_size(n, size, workers), 5)
    lengths = np.array([w.last - w.first + 1 for w in ws])
    assert len(ws) % workers == 0 or len(ws) == n, lengths
    assert lengths.sum() == n and lengths.max() <= (size or n)
    assert lengths.max() - lengths.min() <= max(len(ws), 1), lengths


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_windows_by_work_hold_equal_object_frames(seed: int) -> None:
    """Cut by each frame's objects, the windows are as many as by frames, cover every frame once,
    and hold equal object-frames to within a frame's; a stretch with nobody in it adds none."""
    rng = np.random.default_rng(seed)
    n = 997
    work = rng.integers(0, 40, n).astype(float) * (np.arange(n) // 100 % 3 > 0)  # empty stretches
    frames = np.arange(n) * 2
    ws = plan_windows(frames, 120, 9, work)
    assert len(ws) == len(plan_windows(frames, 120, 9)) == 9
    cores = np.concatenate([frames[(frames >= w.first) & (frames <= w.last)] for w in ws])
    np.testing.assert_array_equal(cores, frames)
    held = np.array([work[(frames >= w.first) & (frames <= w.last)].sum() for w in ws])
    assert np.ptp(held) <= 2 * work.max(), held
    assert np.array_equal(plan_windows(frames, 120, 9, np.zeros(n)), plan_windows(frames, 120, 9))


def test_noise_sample_is_the_busiest_stretch_cut_to_the_limit(boxes: object) -> None:
    """The process noise is chosen on the busiest window, cut around its middle to at most the
    given number of object-frames."""
    scene = boxes
    f = np.asarray(scene.frames)  # type: ignore[attr-defined]
    keys = np.unique(np.c_[scene.obs.frame, scene.obs.track_id], axis=0)  # type: ignore[attr-defined]
    windows = [Window(int(f[0]), int(f[0]), int(f[59]), int(f[69])),
               Window(int(f[50]), int(f[60]), int(f[-1]), int(f[-1]))]
    per = [np.sum((keys[:, 0] >= w.lo) & (keys[:, 0] <= w.hi)) for w in windows]
    busy = windows[int(np.argmax(per))]
    assert noise_sample(scene, windows, 10**9) == (busy.lo, busy.hi)  # type: ignore[arg-type]
    lo, hi = noise_sample(scene, windows, 100)  # type: ignore[arg-type]
    inside = np.sum((keys[:, 0] >= lo) & (keys[:, 0] <= hi))
    assert busy.lo <= lo <= hi <= busy.hi and 80 <= inside <= 100, (lo, hi, inside)
    mid = (busy.lo + busy.hi) / 2
    assert abs((lo + hi) / 2 - mid) < 0.25 * (busy.hi - busy.lo)


@pytest.fixture(scope="module")
def boxes(tmp_path_factory: pytest.TempPathFactory) -> object:
    return written_scene(tmp_path_factory.mktemp("win"), "native", seed=1, frames=120, people=5, noise_px=1.0,
                         motion="walk", errors=Errors(dropped=0.1))[0]


def test_windowed_boxes_equal_the_whole_sequence(boxes: object) -> None:
    """Windows of 30 frames with 20 of context, the process noise the whole run chose: every
    centre within 0.1 of its sd of the whole-sequence smoother's."""
    whole = reconstruct(boxes, "ukf")
    p = whole.info.params
    fixed = {k: p[k] for k in ("accel_sd", "position_sd", "shape_sd")}
    part, qa, _ = reconstruct_windowed(boxes, "ukf", Plan(30, overlap=20), **fixed)
    np.testing.assert_array_equal(part.frame, whole.frame)
    np.testing.assert_array_equal(part.track_id, whole.track_id)
    z = np.abs(part.center_world - whole.center_world) / whole.center_sd
    assert z.max() < 0.1, z.max()
    assert part.info.windows is not None and part.info.windows.count == 4
    assert part.info.windows.process_noise["accel_sd"] == pytest.approx(p["accel_sd"])


def test_a_gap_longer_than_a_window_runs(boxes: object) -> None:
    """A stretch of frames without annotations longer than a window and its context: the
    windows that hold nothing are left out, the others give the rows of the whole run (a window
    of nothing to estimate was an internal error)."""
    import dataclasses

    scene = boxes
    frames = np.asarray(scene.frames)  # type: ignore[attr-defined]
    gap = (scene.obs.frame > frames[20]) & (scene.obs.frame < frames[60])  # type: ignore[attr-defined]
    holed = dataclasses.replace(scene, obs=scene.obs.select(~gap), truth=None)  # type: ignore[call-overload]
    whole = reconstruct(holed, "ukf")
    p = whole.info.params
    part, _, _ = reconstruct_windowed(holed, "ukf", Plan(8, overlap=5),
                                   **{k: p[k] for k in ("accel_sd", "position_sd", "shape_sd")})
    assert part.info.windows is not None and part.info.windows.count < len(plan_windows(frames, 8, 5))
    np.testing.assert_array_equal(part.frame, whole.frame)
    np.testing.assert_array_equal(part.track_id, whole.track_id)


def test_bridge_rows_hand_worked() -> None:
    """Id 7 at frames 0-4 and 20-24, id 9 at 10-30: a window's objects bring their own
    annotated frames nearest its frames, two a side, where they span them; windows past every
    annotation bring none (frames beyond the last annotation once read the next id's rows)."""
    from types import SimpleNamespace

    from gt3dkit.windows.plan import Bridge

    fr = np.r_[np.arange(5), np.arange(20, 25), np.arange(10, 31)]
    tid = np.r_[np.full(10, 7), np.full(21, 9)]
    scene = SimpleNamespace(obs=SimpleNamespace(frame=fr, track_id=tid))

    def rows(w: Window) -> list[tuple[int, int]]:
        m = Bridge.of(scene, 2).rows(w)  # type: ignore[arg-type]
        return sorted(zip(tid[m].tolist(), fr[m].tolist(), strict=True))

    assert rows(Window(8, 10, 12, 14)) == [(7, 3), (7, 4), (7, 20), (7, 21), (9, 13), (9, 14)]
    assert rows(Window(26, 28, 40, 45)) == [(9, 26), (9, 27)]  # id 7 ended before: not its window
    assert rows(Window(90, 100, 120, 130)) == []
    assert rows(Window(40, 44, 46, 50)) == []  # past both ids' last annotations


@pytest.mark.parametrize("who", ["everyone", "one person"])
def test_dense_rows_across_a_gap_longer_than_a_window(boxes: object, who: str) -> None:
    """``--every-frame`` in windows where nobody, or one person, goes unannotated for longer than
    a window and its context: each object's windows bring its own annotations beyond the stretch
    (``Bridge.rows``), so every row between annotations is there, near the whole run's (within
    0.1 of their sd inside the stretch). Without that they were missing, or 6.7 sd off where a
    window held one annotated frame of one side."""
    import dataclasses

    scene = boxes
    frames = np.asarray(scene.frames)  # type: ignore[attr-defined]
    obs = scene.obs  # type: ignore[attr-defined]
    gap = (obs.frame > frames[10]) & (obs.frame < frames[75])  # longer than 8 + 2 x 20 frames
    if who == "one person":  # the one seen longest
        ids, n = np.unique(obs.track_id, return_counts=True)
        gap &= obs.track_id == ids[np.argmax(n)]
    holed = dataclasses.replace(scene, obs=obs.select(~gap), truth=None)  # type: ignore[call-overload]
    whole = reconstruct(holed, "ukf", every_frame=0)
    p = whole.info.params
    part, _, _ = reconstruct_windowed(holed, "ukf", Plan(8, overlap=20), every_frame=0,
                                   **{k: p[k] for k in ("accel_sd", "position_sd", "shape_sd")})
    np.testing.assert_array_equal(part.frame, whole.frame)
    np.testing.assert_array_equal(part.track_id, whole.track_id)
    inside = (whole.frame > frames[10]) & (whole.frame < frames[75]) & (whole.n_views == 0)
    assert inside.sum() >= 50  # rows between annotations (no view) across the stretch
    z = np.abs(part.center_world - whole.center_world) / whole.center_sd
    assert z[inside].max() < 0.1, z[inside].max()  # measured: 0.06
    assert z.max() < 0.15, z.max()  # 8-frame windows, 20 of context: 0.11 without the stretch too


def test_windowed_skeletons_near_the_whole_sequence(tmp_path: Path) -> None:
    """Keypoints with bones, the process noise fixed: every person's bones pooled over the
    windows are the whole run's (within 0.1 mm: each window's first pass, with its own keypoint
    noise, is a hair from the whole's), and the joints near the
    whole-sequence smoother's (median 0.05 of their sd, 99 % within 0.2), all rows present. Each
    window measures its own keypoint noise per joint (on 30 frames here), which moves them a
    little; with each window's own bone lengths the median was 0.05 and the 99th percentile 0.5."""
    sk = simulate_skeletons("native", seed=3, frames=90, people=2, cameras=5, noise_px=1.0)
    write_skeleton_scene(sk, tmp_path / "sk", "native")
    scene = load_scene(tmp_path / "sk")
    whole = reconstruct(scene, "ukf")
    p = whole.info.params
    fixed = {k: p[k] for k in ("accel_sd", "shape_sd", "joint_accel_sd")}
    part, _, _ = reconstruct_windowed(scene, "ukf", Plan(30, overlap=30), **fixed)
    np.testing.assert_array_equal(part.frame, whole.frame)
    bones = [b["per_person"] for b in (whole.info.bones, part.info.bones)]
    assert set(bones[1]) == set(bones[0])
    for person, got in bones[1].items():
        for bone, v in got.items():
            assert abs(v["length"] - bones[0][person][bone]["length"]) <= 1e-4, (person, bone)
    z = np.linalg.norm(part.kpt_world - whole.kpt_world, axis=-1) / whole.kpt_sd
    z = z[np.isfinite(z)]
    assert np.median(z) < 0.05 and np.percentile(z, 99) < 0.2, (np.median(z), np.percentile(z, 99))


def test_jobs_and_dask_give_the_one_process_output(boxes: object, tmp_path: Path) -> None:
    root = Path(boxes.root)  # type: ignore[attr-defined]
    outs = {}
    for name, extra in (("one", ()), ("two", ("--jobs", "2"))):
        code, so, se = _run("reconstruct", str(root), "--out", str(tmp_path / name), "--window", "40",
                            "--quiet", *extra)
        assert code == 0, se
        outs[name] = (tmp_path / name / "tracks.csv").read_bytes()
    assert outs["one"] == outs["two"]
    code, so, se = _run("reconstruct", str(root), "--out", str(tmp_path / "spread"), "--quiet", "--jobs", "2")
    assert code == 0 and "in 2 windows of about 56 frames with 20 of context (one per worker" in so, so
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=":0") as cluster:
        code, so, se = _run("reconstruct", str(root), "--out", str(tmp_path / "dask"), "--window", "40",
                            "--quiet", "--scheduler", cluster.scheduler_address)
        # the library's own connection (no Cluster given: made in the run, the first worker unwarmed)
        reconstruct_windows(load_scene(root), "ukf", Plan(40, scheduler=cluster.scheduler_address),
                            str(tmp_path / "library"))
    assert code == 0, se
    assert (tmp_path / "dask" / "tracks.csv").read_bytes() == outs["one"]
    assert (tmp_path / "library" / "tracks.csv").read_bytes() == outs["one"]


def test_the_search_runs_where_its_first_worker_is_gone(boxes: object,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """The noise search prefers the first worker (warmed for it) but does not wait for one that
    is gone: given the address of a worker that left the cluster, it runs on the others, its
    sample scattered to them or read there (it waited for ever, or failed scattering)."""
    distributed = pytest.importorskip("distributed")
    scene = load_scene(Path(boxes.root))  # type: ignore[attr-defined]
    with (distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                                   dashboard_address=":0") as cluster,
          distributed.Client(cluster) as client):
        monkeypatch.setattr(noise, "worker_addresses", lambda c: ["tcp://127.0.0.1:9"])
        for sample in (scene, lambda: scene):  # scattered, read where it runs
            found: list[object] = []
            searching = threading.Thread(target=lambda s=sample, into=found: into.append(
                noise.chosen_noise(scene, s, "ukf", {}, client)()), daemon=True)
            searching.start()
            searching.join(120)
            assert found and isinstance(found[0], noise.Chosen), "the search waited for a worker that is gone"


@pytest.mark.parametrize("read", [False, True], ids=["scattered", "read"])
def test_a_window_whose_dask_worker_dies_runs_again_on_the_others(read: bool, request: pytest.FixtureRequest,
                                                                   tmp_path: Path) -> None:
    """The first window to run kills its worker (``os._exit``, as a machine lost or the kernel's
    out-of-memory killer would). Scattered: the scenes scattered to it are lost (Dask cannot
    recompute scattered data) and the windows that needed them were cancelled (the run failed
    with ``FutureCancelledError``); they are scattered and run again. Read: a window that reads
    its own frames (nothing scattered) runs again on the other worker. Either way every window's
    part, and what it read, are the ones the same windows give in this process."""
    import os

    distributed = pytest.importorskip("distributed")
    scene = load_head(request.getfixturevalue("grid")) if read else request.getfixturevalue("boxes")
    assert scene is not None
    windows = plan_windows(np.asarray(scene.frames, dtype=np.int64), 20 if read else 30, 10 if read else 20)
    like = WindowJob(windows[0], "ukf", {"accel_sd": 0.5, "shape_sd": 0.01}, None)
    marker = tmp_path / "died"

    def dies_once(job: WindowJob, s: object) -> object:
        if not marker.exists():
            marker.write_text("a worker died here")
            os._exit(1)
        return run_window(job, s)

    reads: list[object] | None = [] if read else None
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=":0") as cluster, distributed.Client(cluster) as client:
        parts = _run_windows(_window_scenes(scene, windows, client), windows, like, client, lambda k, n: None,
                             dies_once, reads=reads)  # type: ignore[arg-type]
    assert marker.exists()
    alone_reads: list[object] | None = [] if read else None
    alone = _run_windows(_window_scenes(scene, windows, None), windows, like, None, lambda k, n: None,
                         reads=alone_reads)  # type: ignore[arg-type]
    if read:
        assert len(reads) == len(windows)  # type: ignore[arg-type]
        assert [r.rows for r in reads] == [r.rows for r in alone_reads]  # type: ignore[attr-defined, union-attr]
    for k in range(len(windows)):
        for name in ("frame", "track_id", "center_world", "center_sd"):
            np.testing.assert_array_equal(getattr(parts[k][0], name), getattr(alone[k][0], name), name)


def _dies(job: WindowJob, scene: object) -> object:
    """A window whose process dies (as the out-of-memory killer ends it)."""
    import os

    os._exit(1)


def test_a_dead_pool_process_is_an_error_naming_the_window(boxes: object) -> None:
    """``--jobs``: a pool process that dies is an EstimationError (``error: --jobs: ...``, exit 1),
    not an internal error asking for a bug report."""
    from gt3dkit.errors import EstimationError

    windows = plan_windows(np.asarray(boxes.frames, dtype=np.int64), 30, 20)  # type: ignore[attr-defined]
    like = WindowJob(windows[0], "ukf", {"accel_sd": 0.5, "shape_sd": 0.01}, None)
    said = r"^--jobs: a worker process died \(out of memory\? .*\) with window \d+ \(frames \d+-\d+\)"
    with process_pool(2) as pool, pytest.raises(EstimationError, match=said):
        _run_windows(_window_scenes(boxes, windows, None), windows, like, pool, lambda k, n: None, _dies)


def _tiny_scenes_made() -> int:
    """1 where this process made the tiny scenes (a warm-up), else 0."""
    api = sys.modules.get("gt3dkit.api")
    return 0 if api is None else int(api.tiny_scene.cache_info().currsize > 0)


def test_a_cluster_warms_the_first_worker_while_the_caller_goes_on() -> None:
    """``Cluster`` with ``loading`` (``gt3d reconstruct --scheduler``, while the input loads) has
    the first worker, the one the noise search runs on, estimate the tiny scenes; the others are
    left alone (they warm during the search, on the sequence's frames), and so is every worker
    without ``loading``."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=":0") as cluster:
        with Cluster(cluster.scheduler_address, "ukf", {}) as c:
            client = c.client
            first, other = sorted(client.scheduler_info()["workers"])
            for _ in range(600):  # until the warm-up is done (seconds)
                made = client.run(_tiny_scenes_made)
                if made[first]:
                    break
                time.sleep(0.1)
            assert made == {first: 1, other: 0}, made
        with Cluster(cluster.scheduler_address, "ukf", {}, loading=False) as c:
            time.sleep(1.0)
            assert c.client.run(_tiny_scenes_made)[other] == 0


def test_gt3d_connects_and_warms_the_first_worker_before_its_own_imports() -> None:
    """``gt3d reconstruct --scheduler`` connects before it loads the commands: the entry point
    imports nothing heavy, and the early connection warms the first worker only; the run's
    ``Cluster`` takes that client and warm-up over (no second connection, no second warm-up of
    the first worker) and warms the others at once."""
    probe = ("import sys, gt3dkit.cli; print(sorted(m for m in ('numba', 'scipy', 'gt3dkit.api', "
             "'gt3dkit.commands.main', 'distributed') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert r.stdout.strip() == "[]", r.stdout
    assert cli.early_start(["simulate", "--scheduler", "tcp://127.0.0.1:9"]) is None
    assert cli.early_start(["reconstruct", "in", "--out", "o"]) is None
    assert cli._value(["reconstruct", "--scheduler=a", "--scheduler", "b", "--", "--scheduler", "c"],
                      "--scheduler") == "b"
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=":0") as cluster:
        early = cli.early_start(["reconstruct", "in", f"--scheduler={cluster.scheduler_address}"])
        assert early is not None and early.error is None
        try:
            first, other = sorted(early.client.scheduler_info()["workers"])
            assert list(early.warming) == [(first, "boxes"), (first, "joints")]
            sent = dict(early.warming)
            with Cluster(cluster.scheduler_address, "ukf", {}, early=early) as c:
                assert c.client is early.client and c.warmed == {first, other}
                assert early.warming == {}  # taken over: the run alone holds them
                assert all(c._warming[k] is f for k, f in sent.items())
                assert c._warming[(other, "boxes")].key.startswith("warm_first")
                for _ in range(600):  # until the warm-ups are done (seconds)
                    made = c.client.run(_tiny_scenes_made)
                    if made[first] and made[other]:
                        break
                    time.sleep(0.1)
                assert made == {first: 1, other: 1}, made
        finally:
            early.close()  # after the run closed it: nothing left to do, no error


def test_the_run_lets_go_of_the_warm_ups_its_input_does_not_use() -> None:
    """The first worker is sent a warm-up for each kind of tiny scene; once the input is loaded
    the run keeps those of its kind only (``Cluster.warm_only``, :func:`gt3dkit.api.scene_kind`),
    and the others' futures are let go (Dask cancels a task no client wants): the noise search,
    sent next to that worker, does not wait for the joints' warm-up of a box sequence."""
    distributed = pytest.importorskip("distributed")
    assert [scene_kind(tiny_scene(kind)) for kind in WARM_KINDS] == list(WARM_KINDS)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=":0") as cluster:
        with Cluster(cluster.scheduler_address, "ukf", {}) as c:
            (w,) = c.warmed
            keys = {kind: f.key for (_, kind), f in c._warming.items()}
            assert set(keys) == {"boxes", "joints"}
            c.warm_only("boxes")
            assert list(c._warming) == [(w, "boxes")] and c.warmed == {w}
            gc.collect()
            for _ in range(200):  # the client lets a future go on its event loop's thread
                if keys["joints"] not in c.client.futures:
                    break
                time.sleep(0.05)
            assert keys["joints"] not in c.client.futures and keys["boxes"] in c.client.futures


def test_the_early_warm_up_is_sealed_and_opened_where_it_runs() -> None:
    """The early warm-up is sent by name (``cli.Named``) and sealed (:mod:`gt3dkit.sealed`):
    sealing it imports nothing of gt3dkit's windows here; unpickling the sealed call, as the
    scheduler and the worker's message reader do, imports none either; opening it, where the
    task runs, imports the function."""
    probe = ("import pickle, sys; from gt3dkit.cli import Named; from gt3dkit.sealed import Sealed; "
             "b = pickle.dumps(Sealed.of(Named('gt3dkit.windows.cluster', 'warm_first'))); "
             "print('gt3dkit.windows' in sys.modules); s = pickle.loads(b); "
             "print('gt3dkit.windows' in sys.modules); f = s.opened(); "
             "print(f.__module__, f.__name__, 'gt3dkit.windows' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert r.stdout.split("\n")[:3] == ["False", "False", "gt3dkit.windows.cluster warm_first True"], r.stdout
    assert cli.Named("gt3dkit.windows.plan", "balanced_size")(100, 10, 2) == balanced_size(100, 10, 2)


#: A Dask scheduler in a process of its own: it prints its address, and when its input closes,
#: which of gt3dkit's heavy modules it imported.
_SCHEDULER = """
import asyncio, sys
from distributed import Scheduler
async def main():
    async with Scheduler(host="127.0.0.1", port=0, dashboard_address=":0") as s:
        print(s.address, flush=True)
        await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
        print(sorted(m for m in ("gt3dkit.api", "gt3dkit.windows", "numba", "scipy") if m in sys.modules))
asyncio.run(main())
"""


def test_the_scheduler_imports_nothing_of_gt3dkit(boxes: object, tmp_path: Path) -> None:
    """Every task and scattered scene a run sends is sealed: the scheduler, which unpickles each
    task, imports none of gt3dkit's estimators, numba or SciPy (0.9 s of its CPU at the start
    of a run, taken from the workers on a small machine), for the warm-ups, the noise search, the
    windows, scattered or read where they run, and the bones' two rounds; the output is the one
    process's."""
    pytest.importorskip("distributed")
    sched = subprocess.Popen([sys.executable, "-c", _SCHEDULER], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    worker = None
    try:
        address = sched.stdout.readline().strip()  # type: ignore[union-attr]
        worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address,
                                   "--nthreads", "1", "--no-dashboard"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        root = str(boxes.root)  # type: ignore[attr-defined]
        for name, extra in (("one", ()), ("read", ("--scheduler", address)),
                            ("scattered", ("--scheduler", address, "--every-frame", "1"))):
            code, _, se = _run("reconstruct", root, "--out", str(tmp_path / name), "--window", "40",
                               "--quiet", *extra)
            assert code == 0, se
        skel = tmp_path / "skel"
        write_skeleton_scene(simulate_skeletons("native", seed=2, frames=60, people=1, cameras=3), skel,
                             "native")
        code, _, se = _run("reconstruct", str(skel), "--out", str(tmp_path / "bones"), "--window", "30",
                           "--quiet", "--scheduler", address)
        assert code == 0, se
        out, _ = sched.communicate("", timeout=60)
    finally:
        for p in (worker, sched):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
    assert out.split("\n")[0] == "[]", out
    assert (tmp_path / "read" / "tracks.csv").read_bytes() == (tmp_path / "one" / "tracks.csv").read_bytes()


def test_an_early_connection_error_is_said_where_the_run_connects() -> None:
    """What went wrong connecting early is raised as the run's own connection says it, with no
    second attempt (which would wait Dask's connect timeout again)."""
    early = Early("tcp://127.0.0.1:9", error=OSError("Timed out trying to connect"))
    with pytest.raises(InputError, match=r"^--scheduler: cannot reach the Dask scheduler at "
                                         r"tcp://127\.0\.0\.1:9 \(Timed out trying to connect\)$"):
        connect_scheduler("tcp://127.0.0.1:9", early)
    with pytest.raises(InputError, match="is not a Dask scheduler address"):
        connect_scheduler("not-an-address", Early("not-an-address", error=ValueError("never raised")))


def test_skeleton_windows_give_the_one_process_output_in_processes_and_on_dask(tmp_path: Path) -> None:
    """Keypoints with bones run in two rounds (the bones pooled, then the windows): two local
    processes and a Dask cluster on loopback write the one-process ``keypoints.csv`` byte for byte,
    and ``meta.json`` lists every person's pooled bones."""
    sk = simulate_skeletons("native", seed=5, frames=60, people=2, cameras=4, noise_px=1.0)
    write_skeleton_scene(sk, tmp_path / "sk", "native")
    args = (str(tmp_path / "sk"), "--window", "20", "--quiet")
    outs = {}
    for name, extra in (("one", ()), ("two", ("--jobs", "2"))):
        code, so, se = _run("reconstruct", *args, "--out", str(tmp_path / name), *extra)
        assert code == 0, se
        outs[name] = (tmp_path / name / "keypoints.csv").read_bytes()
    assert outs["one"] == outs["two"]
    meta = json.loads((tmp_path / "one" / "meta.json").read_text())["estimator"]
    assert sorted(meta["bones"]["per_person"]) == ["0", "1"] and "pooled" in meta["bones"]
    assert 0 < meta["windows"]["bones_round_seconds"] < meta["seconds"]
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=":0") as cluster:
        code, so, se = _run("reconstruct", *args, "--out", str(tmp_path / "dask"), "--scheduler",
                            cluster.scheduler_address)
        with distributed.Client(cluster) as client:  # each worker's kept preparations went at the end
            left = client.run(_kept_runs)
    assert code == 0, se
    assert (tmp_path / "dask" / "keypoints.csv").read_bytes() == outs["one"]
    assert len(left) == 2 and set(left.values()) == {0}


def _kept_runs() -> int:
    """The runs whose preparations this process keeps (gt3dkit.windows.stitch.Keep)."""
    from gt3dkit.windows.stitch import _KEPT

    return len(_KEPT)


def test_the_second_round_takes_each_windows_preparation_from_the_first(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Keypoints with bones in one process: the bones' round keeps each window's preparation (on
    disk) and the second round takes it, so every window is prepared once, not twice, with the
    same rows; where it cannot be written (a full disk), each is made again, the same rows."""
    import errno
    import pickle

    from gt3dkit.fusion.ukf.smoother import UKFSmoother

    sk = simulate_skeletons("native", seed=5, frames=60, people=2, cameras=4, noise_px=1.0)
    write_skeleton_scene(sk, tmp_path / "sk", "native")
    scene = load_scene(tmp_path / "sk")
    fixed = {"accel_sd": 1.0, "shape_sd": 0.01, "joint_accel_sd": 2.0}
    made: list[int] = []
    real = UKFSmoother.prepare

    def counted(self: UKFSmoother, sc: object) -> object:
        made.append(1)
        return real(self, sc)

    monkeypatch.setattr(UKFSmoother, "prepare", counted)
    kept, _, _ = reconstruct_windowed(scene, "ukf", Plan(20, overlap=10), **fixed)
    assert kept.info.windows is not None
    n, once = kept.info.windows.count, len(made)  # the windows' and the noise sample's
    assert n == 3 and _kept_runs() == 0  # dropped at the end of the run

    def full(*args: object, **kw: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    made.clear()
    monkeypatch.setattr(pickle, "dump", full)
    again, _, _ = reconstruct_windowed(scene, "ukf", Plan(20, overlap=10), **fixed)
    assert len(made) == once + n  # the second round prepared each window again
    for k in ("frame", "track_id", "kpt_world", "kpt_sd", "center_world", "center_sd"):
        np.testing.assert_array_equal(getattr(again, k), getattr(kept, k))


def test_window_misuse(boxes: object, tmp_path: Path) -> None:
    root = str(boxes.root)  # type: ignore[attr-defined]
    code, so, se = _run("reconstruct", root, "--out", str(tmp_path / "a"), "--jobs", "2", "--window", "0")
    assert code == 2 and se.startswith("error: --jobs: ") and len(se.strip().splitlines()) == 1
    code, so, se = _run("reconstruct", root, "--out", str(tmp_path / "b"), "--window", "30", "--estimator",
                        "triangulation")
    assert code == 2 and se.startswith("error: --window: ") and len(se.strip().splitlines()) == 1
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_process_noise_is_what_the_estimate_chooses(boxes: object) -> None:
    """The windows' process noise, found by the UKF's search alone, is what a whole estimate of
    the same scene runs with; the progress line's time left follows the pace of the parts."""
    est = make_estimator("ukf")
    found = process_noise_prepared(boxes, est)[0]  # type: ignore[arg-type]
    params = reconstruct(boxes, "ukf").info.params  # type: ignore[arg-type]
    assert found is not None and {"accel_sd", "shape_sd"} <= set(found)
    for k, v in found.items():
        assert v == pytest.approx(params[k], rel=1e-12), k
    assert process_noise_prepared(boxes, make_estimator("triangulation"))[0] is None  # type: ignore[arg-type]
    st = Stages(3, quiet=True)
    st("windows")
    st._stage_t0 -= 30.0  # the first of four windows took 30 s
    st.part("windows", 1, 4)
    assert st.name == "windows 1/4 done, about 01:30 left"
    st.part("windows", 4, 4)
    assert st.name == "windows 4/4 done" and clock(3725) == "1:02:05"


@pytest.mark.parametrize(("accel_sd", "sd_m", "fps"),
                         [(3.4, 0.001, 30.0), (1.0, 0.01, 30.0), (0.5, 0.05, 10.0), (0.1, 0.05, 30.0)])
def test_context_steps_bound_the_smoothers_weight(accel_sd: float, sd_m: float, fps: float) -> None:
    """The context :func:`context_steps` gives against the smoother solved as one least-squares
    problem (the batch MAP estimate of the constant-velocity model, which RTS equals): a position
    measurement ``n`` steps away weighs at most ~CONTEXT_WEIGHT of the frame's own in the middle
    of a long sequence, and more than that at half the distance (the context is not oversized)."""
    from gt3dkit.windows.noise import CONTEXT_WEIGHT, context_steps

    dt, N, k = 1.0 / fps, 400, 200
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Qi = np.linalg.inv(accel_sd**2 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]))
    L = np.eye(2 * N) * 1e-9
    for i in range(N - 1):
        A = np.zeros((2, 2 * N))
        A[:, 2 * i:2 * i + 2], A[:, 2 * i + 2:2 * i + 4] = -F, np.eye(2)
        L += A.T @ Qi @ A
    H = np.zeros((N, 2 * N))
    H[np.arange(N), 2 * np.arange(N)] = 1.0
    L += H.T @ H / sd_m**2
    w = np.abs(np.linalg.solve(L, H.T / sd_m**2)[2 * k])  # position at k <- each measurement
    n = context_steps(accel_sd, sd_m, dt)
    assert w[k + n] / w[k] < 1.5 * CONTEXT_WEIGHT and w[k - n] / w[k] < 1.5 * CONTEXT_WEIGHT
    assert w[k + n // 2] / w[k] > CONTEXT_WEIGHT


def test_pooled_bones_leave_out_ids_a_window_splits() -> None:
    """An id one window splits into pieces (which may be different people) gets no pooled bones:
    every window keeps its own pieces' lengths; the other ids pool all their windows' rows."""
    from gt3dkit.fusion.ukf.bones import BoneSamples
    from gt3dkit.skeletons import SKELETONS
    from gt3dkit.windows.stitch import pooled_bones

    skel = SKELETONS["coco17"]
    K = len(skel.bones)
    rng = np.random.default_rng(2)

    def part(ids: list[int], frames: np.ndarray) -> BoneSamples:
        obj = np.repeat(ids, len(frames))
        R = len(obj)
        return BoneSamples(skel, obj, np.tile(frames, len(ids)), 0.3 + obj[:, None] * 0.01 + rng.normal(
            scale=1e-3, size=(R, K)), np.full((R, K), 1e-7), np.ones((R, K), bool))

    a, b = part([1, 2], np.arange(0, 50)), part([1, 2, 3], np.arange(50, 100))
    none = np.zeros(0, np.int64)
    pooled = pooled_bones([(a, none, 1.0), (b, np.array([2]), 1.0), (None, none, 0.1)], {})
    assert pooled is not None
    np.testing.assert_array_equal(pooled.ids, [1, 3])
    both = BoneSamples.joined([a, b])
    one = both.length[both.obj == 1]
    np.testing.assert_allclose(pooled.lengths.length[0], np.median(one, axis=0), rtol=0, atol=1e-15)
    assert pooled_bones([(None, none, 0.1)], {}) is None


def _without_seconds(x: object) -> object:
    """A ``meta.json`` with its clock readings (``seconds``, ``created_utc``) left out."""
    if isinstance(x, dict):
        return {k: _without_seconds(v) for k, v in x.items() if "seconds" not in k and k != "created_utc"}
    if isinstance(x, list):
        return [_without_seconds(v) for v in x]
    return x


@pytest.mark.parametrize("kind", ["boxes", "joints"])
def test_rows_written_as_the_windows_finish_equal_the_whole_written_at_the_end(
        boxes: object, tmp_path: Path, kind: str) -> None:
    """``reconstruct_windows`` writes each window's rows as it finishes (``StreamedRows``): the
    folder holds the files ``write_outputs`` writes of the stitched result, byte for byte but for
    the clock readings in ``meta.json``; parts that come out of order wait for the earlier ones,
    and a part that never comes is an error, not a file with a hole. The windows make their rows'
    text where they run (``PartText``); a part given none has it made by the writer: the same."""
    from gt3dkit.io.writers import PartText, StreamedRows, write_outputs

    if kind == "boxes":
        scene = load_scene(Path(boxes.root))  # type: ignore[attr-defined]
    else:
        sk = simulate_skeletons("native", seed=5, frames=60, people=2, cameras=4, noise_px=1.0)
        write_skeleton_scene(sk, tmp_path / "sk", "native")
        scene = load_scene(tmp_path / "sk")
    plan = Plan(20)
    tracks, qa, _ = reconstruct_windowed(scene, "ukf", plan)
    write_outputs(tmp_path / "whole", scene, tracks, anomalies=qa)
    reconstruct_windows(scene, "ukf", plan, str(tmp_path / "streamed"))
    names = sorted(p.name for p in (tmp_path / "whole").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "streamed").iterdir())
    assert {"tracks.csv", "anomalies.csv"} <= set(names) and ("keypoints.csv" in names) == (kind == "joints")
    for name in names:
        a, b = (tmp_path / d / name for d in ("whole", "streamed"))
        if name == ".gt3dkit-output":  # the marker: when it was written
            continue
        if name == "meta.json":
            assert _without_seconds(json.loads(a.read_text())) == _without_seconds(json.loads(b.read_text()))
        else:
            assert a.read_bytes() == b.read_bytes(), name
    if kind == "boxes":
        assert len((tmp_path / "whole" / "anomalies.csv").read_text().splitlines()) > 10  # views left out
    # out of order: the same files; a part missing: an error
    f = np.unique(tracks.frame)
    spans = [(f[0], f[len(f) // 3]), (f[len(f) // 3], f[2 * len(f) // 3]), (f[2 * len(f) // 3], f[-1] + 1)]
    parts = [take_rows(tracks, (tracks.frame >= a) & (tracks.frame < b)) for a, b in spans]
    found = [[r for r in qa.rows if a <= r[0] < b] for a, b in spans]
    (tmp_path / "reversed").mkdir()
    with StreamedRows(tmp_path / "reversed") as rows:  # the text made with the part, or by the writer
        for k in (2, 1, 0):
            rows.add(k, parts[k], found[k], PartText.of(parts[k], found[k]) if k != 1 else None)
    for name in ("tracks.csv", "anomalies.csv"):
        assert (tmp_path / "reversed" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes()
    (tmp_path / "gap").mkdir()
    with pytest.raises(RuntimeError, match="without part 0"), StreamedRows(tmp_path / "gap") as rows:
        rows.add(1, parts[1], found[1])


@pytest.fixture(scope="module")
def grid(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A WILDTRACK-layout folder (one JSON a frame): its windows read their own frames."""
    root = tmp_path_factory.mktemp("grid") / "wildtrack"
    written_scene(root, "wildtrack", seed=2, frames=60, people=4, noise_px=1.0, motion="walk",
                  errors=Errors(dropped=0.1))
    return root


def test_windows_that_read_their_own_frames_give_the_whole_read_output(grid: Path, tmp_path: Path) -> None:
    """An input indexed without its rows (``load_head``: cameras, frames, each frame's objects),
    each window reading its own frames where it runs, gives the tracks and QA findings of the
    same windows cut from the whole input read at once, and the scene it returns says what the
    whole read says: its annotation rows, every file's digest, the truth (the simulator's
    ``truth.csv``, or without it the positionID grid's, gathered from the windows) and the box
    model."""
    whole = load_scene(grid)
    head = load_head(grid)
    assert head is not None and head.index is not None and len(head.obs) == 0
    f, n = np.unique(whole.obs.frame, return_counts=True)
    assert np.isin(f, head.index.frames).all()
    for name, root in (("truth.csv", grid), ("positionID", tmp_path / "no_truth")):
        if root != grid:
            shutil.copytree(grid, root)
            (root / "truth.csv").unlink()
            whole, head = load_scene(root), load_head(root)
        a, qa_a, read = reconstruct_windowed(head, "ukf", Plan(20, overlap=10))  # type: ignore[arg-type]
        b, qa_b, _ = reconstruct_windowed(whole, "ukf", Plan(20, overlap=10))
        for k in ("frame", "track_id", "center_world", "semi_axes", "n_views"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=f"{name}: {k}")
        assert qa_a.rows == qa_b.rows
        assert read.n_annotations == len(whole.obs) and read.has_boxes
        assert read.files == whole.files and read.box_model == whole.box_model
        assert read.truth is not None and whole.truth is not None and read.truth.source == whole.truth.source
        for k in ("frame", "track_id", "center_world", "semi_axes"):
            np.testing.assert_array_equal(getattr(read.truth, k), getattr(whole.truth, k), err_msg=name)


def test_jobs_and_dask_read_their_own_frames_to_the_one_process_output(grid: Path, tmp_path: Path) -> None:
    """``gt3d reconstruct`` of a WILDTRACK-layout folder in windows: the same bytes in one process
    and on two Dask workers, each reading its windows' frames (a local pool's processes read
    theirs as a worker does: the bad-frame test below), and the same as the library's windows cut
    from the whole input read at once; ``meta.json`` counts every annotation row and lists every
    file."""
    outs = {}
    code, so, se = _run("reconstruct", str(grid), "--out", str(tmp_path / "one"), "--window", "20", "--quiet")
    assert code == 0, se
    outs["one"] = (tmp_path / "one" / "tracks.csv").read_bytes()
    whole = load_scene(grid)
    reconstruct_windows(whole, "ukf", Plan(20), str(tmp_path / "library"))
    assert (tmp_path / "library" / "tracks.csv").read_bytes() == outs["one"]
    meta = json.loads((tmp_path / "one" / "meta.json").read_text())
    assert meta["counts"]["annotations"] == len(whole.obs)
    assert meta["input"]["files_sha256"] == whole.files
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=":0") as cluster:
        code, so, se = _run("reconstruct", str(grid), "--out", str(tmp_path / "dask"), "--window", "20",
                            "--quiet", "--scheduler", cluster.scheduler_address)
    assert code == 0, se
    assert (tmp_path / "dask" / "tracks.csv").read_bytes() == outs["one"]


@pytest.mark.parametrize("jobs", [(), ("--jobs", "2")])
def test_a_bad_frame_a_window_reads_is_one_error_line_and_nothing_written(grid: Path, tmp_path: Path,
                                                                           jobs: tuple[str, ...]) -> None:
    """A frame file that only the last window reads (a box with ``xmin > xmax``) is found where
    that window runs: one ``error:`` line naming the file and the entry, exit 2, nothing written;
    a box wholly outside its image in another frame is a ``warning:`` naming the frames of the
    window that read it, and the run goes on."""
    root = tmp_path / "in"
    shutil.copytree(grid, root)
    files = [p for p in sorted((root / "annotations_positions").glob("*.json")) if json.loads(p.read_text())]
    odd = json.loads(files[0].read_text())
    odd[0]["views"][0].update(xmin=-500, xmax=-400)
    files[0].write_text(json.dumps(odd))
    code, so, se = _run("reconstruct", str(root), "--out", str(tmp_path / "ok"), "--window", "20", *jobs)
    assert code == 0, se
    assert se.count("warning: frames ") == se.count("boxes lie entirely outside") == 1, se
    assert "1 boxes lie entirely outside their camera's image" in se, se
    bad = json.loads(files[-1].read_text())
    bad[0]["views"][0].update(xmin=900, xmax=800)
    files[-1].write_text(json.dumps(bad))
    code, so, se = _run("reconstruct", str(root), "--out", str(tmp_path / "out"), "--window", "20", "--quiet",
                        *jobs)
    assert code == 2 and se.count("\n") == 1 and se.startswith(f"error: {files[-1]}: personID"), se
    assert not (tmp_path / "out").exists()


def test_the_truth_report_counted_as_the_windows_finish_is_the_whole_ones(
        grid: Path, boxes: object, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The truth report of a windowed run, counted window by window as the rows are written
    (``TruthTally``), prints what the report computed on the whole tracks prints: a folder whose
    windows read their own frames (its truth file read meanwhile) and one read whole. ``gt3d
    reconstruct`` uses it: with the whole computation made to fail, the report still comes."""
    from gt3dkit.commands import printing
    from gt3dkit.commands.printing import TruthTally, report_truth

    def printed(scene: object, tracks: object, tally: TruthTally | None) -> str:
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            report_truth(scene, tracks, "ukf", tally=tally)  # type: ignore[arg-type]
        return out.getvalue()

    for name, scene in (("index", load_head(grid)), ("whole", load_scene(Path(boxes.root)))):  # type: ignore[attr-defined]
        tally = TruthTally(scene.rig.up)  # type: ignore[union-attr]
        tracks, read = reconstruct_windows(scene, "ukf", Plan(20), str(tmp_path / name), tally=tally)  # type: ignore[arg-type]
        assert tally.counted(read, tracks) is not None, name
        whole = printed(read, tracks, None)
        assert "MOTA" in whole and printed(read, tracks, tally) == whole, name
    monkeypatch.setattr(printing, "tracking_scores", lambda *a, **k: pytest.fail("computed whole"))
    code, so, se = _run("reconstruct", str(grid), "--out", str(tmp_path / "cli"), "--window", "20", "--quiet")
    assert code == 0, se
    assert "MOTA" in so

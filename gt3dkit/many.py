"""``gt3d reconstruct-many MANIFEST --out OUT``: many sequences in parallel.

The manifest is a text file: one input folder per line (relative paths from the manifest's
folder), or a glob (``sequences/*``), ``#`` comments. Each sequence is reconstructed into
``OUT/<input folder name>/`` (atomically, as ``gt3d reconstruct`` writes), by a local process
pool (``--jobs``, default: the machine's cores) or, with ``--scheduler ADDRESS``, on a running
Dask distributed cluster (a ``dask-scheduler`` you started, or a ``LocalCluster``'s address).
A sequence that fails is reported with its one-line error and does not stop the others (exit
status 1 at the end, naming them). A rerun skips every sequence whose output is complete and
current: its ``meta.json`` has the same input checksums, estimator and gt3dkit version.
``OUT/summary.csv`` lists every sequence; ``--report`` also writes each sequence's report and
``OUT/index.html`` over all of them.
"""

from __future__ import annotations

import csv
import glob
import html
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from gt3dkit.api import load_scene, reconstruct
from gt3dkit.errors import EstimationError, InputError
from gt3dkit.io.atomic import MARKER
from gt3dkit.io.datasets import Calibration
from gt3dkit.sealed import submit
from gt3dkit.threads import small_matrix_blas
from gt3dkit.types import JsonDict, JsonValue, Scene
from gt3dkit.version import __version__
from gt3dkit.viz.report import write_report
from gt3dkit.windows import connect_scheduler

if TYPE_CHECKING:
    from distributed import Client

SUMMARY_COLUMNS = ("input", "output", "status", "seconds", "objects", "object_frames", "anomalies",
                   "error")


def read_manifest(path: Path) -> list[Path]:
    """The input folders a manifest names (globs expanded, sorted), each once."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(str(path), f"cannot read the manifest ({e})") from None
    base = path.parent
    out: list[Path] = []
    for k, raw in enumerate(lines, 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        p = Path(line) if Path(line).is_absolute() else base / line
        if any(ch in line for ch in "*?["):
            found = sorted(Path(x) for x in glob.glob(str(p)) if Path(x).is_dir())
            if not found:
                raise InputError(f"{path}: line {k}", f"{line!r} matches no folder")
            out += found
        else:
            if not p.is_dir():
                raise InputError(f"{path}: line {k}", f"{line!r}: not a folder")
            out.append(p)
    uniq = list(dict.fromkeys(q.resolve() for q in out))
    if not uniq:
        raise InputError(str(path), "names no input folder")
    names: dict[str, Path] = {}
    for q in uniq:
        if q.name in names:
            raise InputError(str(path), f"two inputs share the folder name {q.name!r} ({names[q.name]} and "
                                        f"{q}): their outputs would collide")
        names[q.name] = q
    return uniq


@dataclass(frozen=True)
class ReadAs:
    """How every sequence is read, as ``gt3d reconstruct``'s options say it of one: ``skeleton``
    (a name or a skeleton file's path), ``fps``, the calibration's ``calib_units`` (None: each
    input's own)."""

    skeleton: str | None = None
    fps: float | None = None
    calib_units: str | None = None

    def scene(self, root: Path) -> Scene:
        units = self.calib_units or "m"
        return load_scene(root, skeleton=self.skeleton, fps=self.fps,
                          calib=Calibration(None, units) if units != "m" else None)

    def same_as(self, load: object) -> bool:
        """Whether a run's ``meta.json`` ``input.load`` was read this way."""
        if not isinstance(load, dict):
            return False
        return (load.get("skeleton") == self.skeleton and load.get("fps") == self.fps
                and (load.get("calib_units") or "m") == (self.calib_units or "m"))


@dataclass(frozen=True)
class Job:
    input: str
    output: str
    estimator: str
    report: bool
    read: ReadAs = ReadAs()


def _current(out: Path, scene: Scene, estimator: str, read: ReadAs = ReadAs()) -> bool:
    """``out`` holds a complete output of this input (same checksums, read the same way),
    estimator and version."""
    try:
        meta = json.loads((out / "meta.json").read_text())
    except (OSError, ValueError):
        return False
    given = meta.get("input") or {}
    return ((out / MARKER).is_file() and (out / "tracks.csv").is_file()
            and meta.get("gt3dkit_version") == __version__
            and (meta.get("estimator") or {}).get("estimator") == estimator
            and given.get("files_sha256") == scene.files and read.same_as(given.get("load")))


def run_job(job: Job) -> JsonDict:
    """Reconstruct one sequence (in a worker process): a summary row, never an exception."""
    import warnings


    row = _row(job, seconds=0.0)
    t0 = time.perf_counter()
    os.environ.setdefault("GT3D_BLAS_THREADS", "1")  # the workers are the parallelism
    try:
        with warnings.catch_warnings(), small_matrix_blas():
            warnings.simplefilter("ignore", RuntimeWarning)

            scene = job.read.scene(Path(job.input))
            out = Path(job.output)
            if _current(out, scene, job.estimator, job.read):
                row["status"] = "up to date"
            else:
                tracks = reconstruct(scene, job.estimator, out=out)
                row["status"] = "done"
                row["objects"] = len(set(tracks.track_id.tolist()))
                row["object_frames"] = len(tracks)
                qa = tracks.info.qa.anomalies if tracks.info.qa is not None else {}
                row["anomalies"] = sum(qa.values())
            if job.report and (row["status"] == "done" or not (out / "report" / "index.html").is_file()):
                write_report(out)
    except (InputError, EstimationError) as e:
        row["status"], row["error"] = "failed", f"error: {e}"
    except Exception as e:  # one sequence's bug must not stop the others
        row["status"], row["error"] = "failed", f"error: internal error, {type(e).__name__}: {e}"
    row["seconds"] = round(time.perf_counter() - t0, 2)
    return row


def run_many(inputs: list[Path], out: Path, estimator: str = "ukf", jobs: int | None = None,
             scheduler: str | None = None, report: bool = False,
             progress: bool = True, read: ReadAs = ReadAs()) -> list[JsonDict]:
    """Run every input, each read as ``read`` says; returns the summary rows (also
    ``OUT/summary.csv``)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("--out", f"{out} is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / MARKER).is_file():
        raise InputError("--out", f"{out} holds files gt3dkit did not write")
    for i in inputs:
        o, r = out.resolve(), i.resolve()
        if o == r or r in o.parents or o in r.parents:
            raise InputError("--out", f"{out} is, contains or lies inside the input folder {i}")
    client = connect_scheduler(scheduler) if scheduler else None  # an unreachable one: nothing written
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / MARKER).write_text(json.dumps({"writer": "gt3d reconstruct-many"}))
        todo = [Job(str(i), str(out / i.name), estimator, report, read) for i in inputs]
        rows = _ran(todo, client, jobs, progress)
    finally:
        if client is not None:
            client.close()
    order = {j.input: k for k, j in enumerate(todo)}
    rows.sort(key=lambda r: order[str(r["input"])])
    with open(out / "summary.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=SUMMARY_COLUMNS)
        w.writeheader()
        w.writerows(rows)
    if report:
        _index(out, rows)
    return rows


def _ran(todo: list[Job], client: Client | None, jobs: int | None, progress: bool,
         fn: Callable[[Job], JsonDict] = run_job) -> list[JsonDict]:
    """Every job's summary row (``fn``, :func:`run_job`), in the order they finish: on the Dask
    ``client``'s workers, or in ``jobs`` local processes (spawned). A sequence whose process died
    (the out-of-memory killer, a crash in a library) is a failed row, not the end of the run: Dask
    retries it on another worker first and gives up with ``KilledWorker``; a dead local process
    breaks its pool, and the sequences not yet done are failed rows too (a rerun does them)."""
    from tqdm import tqdm

    rows: list[JsonDict] = []
    bar = tqdm(total=len(todo), desc="sequences", unit="seq", disable=not progress)
    if client is not None:
        from distributed import as_completed
        from distributed.scheduler import KilledWorker

        futures = {submit(client, fn, j): j for j in todo}
        for f in as_completed(futures):
            try:
                rows.append(f.result())
            except KilledWorker:
                rows.append(_died(futures[f], "it killed the Dask workers that ran it (out of memory?)"))
            bar.update()
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed as done
        from concurrent.futures.process import BrokenProcessPool

        n = max(1, min(jobs or os.cpu_count() or 1, len(todo)))
        with ProcessPoolExecutor(max_workers=n, mp_context=mp.get_context("spawn")) as pool:
            submitted = {pool.submit(fn, j): j for j in todo}
            for f in done(submitted):
                try:
                    rows.append(f.result())
                except BrokenProcessPool:
                    rows.append(_died(submitted[f], "a worker process died (out of memory?) before it "
                                                    "was done: run again to do it"))
                bar.update()
    bar.close()
    return rows


def _row(job: Job, **fields: JsonValue) -> JsonDict:
    """``job``'s summary row (:data:`SUMMARY_COLUMNS`), empty but for ``fields``."""
    return {"input": job.input, "output": job.output, **dict.fromkeys(SUMMARY_COLUMNS[2:], ""), **fields}


def _died(job: Job, why: str) -> JsonDict:
    """The summary row of ``job``, failed because its process died (``why``)."""
    return _row(job, status="failed", error=f"error: {why}")


def _index(out: Path, rows: list[JsonDict]) -> None:
    """``OUT/index.html``: every sequence with its status, counts and a link to its report."""
    body = []
    for r in rows:
        name = Path(str(r["output"])).name
        link = (f'<a href="{html.escape(name)}/report/index.html">report</a>'
                if (out / name / "report" / "index.html").is_file() else "")
        body.append("<tr>" + "".join(f"<td>{html.escape(str(r[k]))}</td>" for k in
                                     ("input", "status", "seconds", "objects", "object_frames", "anomalies",
                                      "error")) + f"<td>{link}</td></tr>")
    head = "".join(f"<th>{k}</th>" for k in ("input", "status", "seconds", "objects", "object-frames",
                                              "anomalies", "error", "report"))
    n_fail = sum(r["status"] == "failed" for r in rows)
    (out / "index.html").write_text(
        "<!doctype html><html><head><meta charset='utf-8'><title>gt3dkit: many sequences</title><style>"
        "body{font-family:sans-serif;max-width:1400px;margin:auto}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:3px 7px}</style></head><body>"
        f"<h1>{len(rows)} sequences, {n_fail} failed</h1><table><tr>{head}</tr>{''.join(body)}</table>"
        "</body></html>", encoding="utf-8")

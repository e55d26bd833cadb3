"""Issue 64's measurable targets, printed:

    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/prepare_targets.py [--data ../shared/data] [--runs 5]

1. **Files opened per run**: ``gt3d reconstruct`` of each input under ``strace -f -e trace=openat``
   (every process it starts), each file of the input folder counted by the successful opens of
   its path: the simulated 400-frame, 40-person WILDTRACK-rig scene (``gt3d simulate --layout
   wildtrack --frames 400 --people 40 --noise-px 1``), a simulated native skeleton scene and every
   real dataset in ``--data``. An
   annotation file is the input's frame files, ``keypoints.csv``, ``boxes.csv`` or OpenPose's JSON
   (target: each opened once); the calibration and truth files are listed beside them.
2. **Whole-process time** of ``gt3d reconstruct`` on that 400-frame scene: the minimum and median
   of ``--runs`` runs (target 3.5 s).
3. **Process-wide state**: every assignment at module level of gt3dkit to a mutable container
   (``{}``, ``[]``, ``dict()``, ``set()``, ...) that a function of the module then changes
   (``X[k] = ``, ``X.update``, ``X.append``, ``X.add``, ``X.pop``, ``X.clear``, ``X.setdefault``),
   found with :mod:`ast`; and any field of ``Prepared`` typed as a dict (a memo).
4. The parameters typed ``Any``, the functions over 80 lines (``scripts/structure_targets.py``'s
   counts) and the modules in each folder of ``gt3dkit/fusion`` (target: at most 20 in any).
5. **The input's entries into each module**, followed call by call (``sys.setprofile``) through
   ``gt3d reconstruct`` of the first three inputs of 1: a call into a module of gt3dkit from
   another one with the ``Scene`` or the ``Prepared`` among its arguments is one entry (the data's
   own methods and constructors left out). Target: no module more than twice.
6. **The type checker**: mypy as ``pyproject.toml`` configures it (strict on the package).

Exit status 0 always: it prints what it measured, each target's ok or MISSED.
"""

from __future__ import annotations

import argparse
import ast
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))

from structure_targets import any_parameters, long_functions, modules  # noqa: E402

GT3D = str(Path(sys.executable).with_name("gt3d"))
OPEN_RE = re.compile(r'openat\([^,]+, "([^"]+)", ([^)]*)\) = (-?\d+)')
ANNOTATION = re.compile(r"(annotations_positions/.*\.json|_json/.*\.json|(?:^|/)(?:keypoints|boxes)\.csv|"
                        r"mot/.*\.txt|hdPose3d_stage1_coco19/.*\.json|coco/.*\.json|cvat/.*\.xml)$")
#: Why each module-level container that remains cannot change a result (printed beside it).
WHY_KEPT = {
    "RECEIVED_SIGNALS": "the signals the CLI process received, for its exit status: the process's own",
    "_STEPS": "the compiled filter steps registered once as their modules load (a registry, as the "
              "layouts' and formats' are); never changed after",
    "_POOL": "the thread pool the compiled loops run on, made once a process; a resource, not a result",
    "_KEPT": "a window's preparation kept in the worker process between the bones' round and the run "
             "(a Dask worker holds it); a miss makes the same preparation again",
}
MUTATORS = {"update", "append", "add", "pop", "clear", "setdefault", "extend", "insert", "remove",
            "popitem", "discard"}


def opens(root: Path, extra: list[str], out: Path) -> tuple[int, Counter[str]]:
    """``gt3d reconstruct root extra`` under strace: its exit status and how many times each file
    below ``root`` was opened (successfully, not as a folder)."""
    trace = out.with_suffix(".strace")
    p = subprocess.run(["strace", "-f", "-qq", "-e", "trace=openat", "-o", str(trace), GT3D, "reconstruct",
                        str(root), "--out", str(out), *extra], capture_output=True, text=True)
    count: Counter[str] = Counter()
    for line in trace.read_text().splitlines():
        m = OPEN_RE.search(line)
        if m and int(m.group(3)) >= 0 and "O_DIRECTORY" not in m.group(2):
            path = Path(m.group(1))
            if path.is_relative_to(root) and path.is_file():
                count[str(path.relative_to(root))] += 1
    return p.returncode, count


def print_opens(name: str, rc: int, count: Counter[str]) -> bool:
    ann = {k: v for k, v in count.items() if ANNOTATION.search(k)}
    other = {k: v for k, v in count.items() if k not in ann}
    times = Counter(ann.values())
    worst = max(ann.values(), default=0)
    ok = rc == 0 and worst == 1
    print(f"   {name:<34} annotation files: {len(ann):>5}, opened "
          + ", ".join(f"{n}x: {k}" for n, k in sorted(times.items()))
          + f"  {'ok' if ok else 'MISSED'}" + ("" if rc == 0 else f" (exit {rc})"))
    if other:
        print("   " + " " * 34 + " others: " + ", ".join(f"{k} {v}x" for k, v in sorted(other.items())))
    return ok


def module_state() -> list[str]:
    """``module:line name`` of each module-level mutable container a function of its module changes."""
    found = []
    for mod, path in modules().items():
        tree = ast.parse(path.read_text())
        names: dict[str, int] = {}
        for node in tree.body:
            targets = (node.targets if isinstance(node, ast.Assign) else [node.target]
                       if isinstance(node, ast.AnnAssign) and node.value is not None else [])
            value = getattr(node, "value", None)
            mutable = isinstance(value, (ast.Dict, ast.List, ast.Set)) or (
                isinstance(value, ast.Call) and isinstance(value.func, ast.Name)
                and value.func.id in {"dict", "list", "set", "defaultdict", "OrderedDict"})
            for t in targets:
                if mutable and isinstance(t, ast.Name):
                    names[t.id] = node.lineno
        changed = set()
        for fn in ast.walk(tree):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for n in ast.walk(fn):
                if isinstance(n, ast.Subscript) and isinstance(n.ctx, (ast.Store, ast.Del)) \
                        and isinstance(n.value, ast.Name) and n.value.id in names:
                    changed.add(n.value.id)
                if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) \
                        and n.func.attr in MUTATORS and isinstance(n.func.value, ast.Name) \
                        and n.func.value.id in names:
                    changed.add(n.func.value.id)
        found += [f"{mod}:{names[k]} {k}" for k in sorted(changed)]
    return found


def prepared_dicts() -> list[str]:
    """The fields of ``fusion.preparation.prepare.Prepared`` annotated as a ``dict``, and its
    cached properties (a memo written on first use)."""
    tree = ast.parse((REPO / "gt3dkit" / "fusion" / "preparation" / "prepare.py").read_text())
    cls = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == "Prepared")
    return [f"{n.target.id}: {ast.unparse(n.annotation)}" for n in cls.body  # type: ignore[union-attr]
            if isinstance(n, ast.AnnAssign) and "dict" in ast.unparse(n.annotation).lower()] + [
        f"{n.name}: a cached property" for n in cls.body if isinstance(n, ast.FunctionDef)
        and any("cache" in ast.unparse(d) for d in n.decorator_list)]


#: The tracer of section 5, run in a process of its own (``python -c``) with the CLI's arguments.
ENTRIES = """
import collections, sys
from gt3dkit.types import Scene
from gt3dkit.fusion.preparation.prepare import Prepared
from gt3dkit import cli
entries = collections.Counter()
def on_call(frame, event, arg):
    if event != "call":
        return
    mod = frame.f_globals.get("__name__", "")
    caller = frame.f_back
    if not mod.startswith("gt3dkit") or caller is None or caller.f_globals.get("__name__") == mod:
        return
    code = frame.f_code
    loc = frame.f_locals
    args = code.co_varnames[:code.co_argcount + code.co_kwonlyargcount]
    own = args and args[0] == "self" and isinstance(loc.get("self"), (Scene, Prepared))
    if code.co_name == "__init__" or own:
        return  # the data's own constructor and methods
    if any(isinstance(loc.get(a), (Scene, Prepared)) for a in args):
        entries[mod] += 1
sys.setprofile(on_call)
try:
    cli.main(sys.argv[1:])
finally:
    sys.setprofile(None)
    print("ENTRIES", dict(entries))
"""


def entries(argv: list[str]) -> dict[str, int]:
    """Section 5: how many times ``gt3d reconstruct ARGV``'s input (its ``Scene``, or the
    ``Prepared`` made of it) enters each module of gt3dkit: a call into the module from another
    one with the scene or the preparation among its arguments (the data's own methods and
    constructors left out)."""
    p = subprocess.run([sys.executable, "-c", ENTRIES, *argv], capture_output=True, text=True, check=True)
    line = next(x for x in p.stdout.splitlines() if x.startswith("ENTRIES "))
    return dict(ast.literal_eval(line[len("ENTRIES "):]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        scene = tmp / "wildtrack400"
        subprocess.run([GT3D, "simulate", "--layout", "wildtrack", "--frames", "400", "--people", "40",
                        "--noise-px", "1", "--out", str(scene)], check=True, capture_output=True)
        skel = tmp / "skeleton"
        subprocess.run([GT3D, "simulate", "--kind", "skeleton", "--seed", "1", "--frames", "60", "--out",
                        str(skel)], check=True, capture_output=True)
        print("1. files opened by one gt3d reconstruct (strace -f -e trace=openat)")
        inputs = [("simulated WILDTRACK rig, 400 frames", scene, []),
                  ("simulated skeletons (native keypoints)", skel, [])]
        for name, sub, extra in (("wildtrack_first_half", "", []), ("multiviewx", "", []),
                                 ("panoptic_160906_band1", "", ["--noise-px", "2"]),
                                 ("cmc1_detector_boxes", "", []), ("cmc3_detector_boxes", "", []),
                                 ("shelf_first_half", "pose", ["--calib", "CAL"])):
            root = args.data / name / sub if sub else args.data / name
            if root.is_dir():
                inputs.append((name, root, [str(args.data / name / "cameras.json") if e == "CAL" else e
                                            for e in extra]))
            else:
                print(f"   {name}: not in {args.data}, skipped")
        for k, (name, root, extra) in enumerate(inputs):
            rc, count = opens(root.resolve(), extra, tmp / f"out{k}")
            print_opens(name, rc, count)

        print(f"\n2. whole-process time of gt3d reconstruct on the 400-frame scene, {args.runs} runs")
        took = []
        for k in range(args.runs):
            t0 = time.perf_counter()
            subprocess.run([GT3D, "reconstruct", str(scene), "--out", str(tmp / f"time{k}")], check=True,
                           capture_output=True)
            took.append(time.perf_counter() - t0)
        print(f"   min {min(took):.2f} s, median {statistics.median(took):.2f} s: "
              f"{'ok' if statistics.median(took) <= 3.5 else 'MISSED'} (target 3.5 s)")

        print("\n5. the input's entries into each module, call by call (a call from another module with "
              "the Scene or the Prepared)")
        for name, root, extra in inputs[:3]:
            got = entries(["reconstruct", str(root), *extra, "--out", str(tmp / f"entries_{name[:8]}"),
                           "--quiet"])
            over = {m: n for m, n in sorted(got.items(), key=lambda kv: -kv[1]) if n > 2}
            key = {m: got.get(m, 0) for m in ("gt3dkit.api", "gt3dkit.fusion.preparation.prepare")}
            print(f"   {name:<34} api.py {key['gt3dkit.api']}, prepare.py "
                  f"{key['gt3dkit.fusion.preparation.prepare']}; over twice: "
                  + (", ".join(f"{m} {n}" for m, n in over.items()) or "none")
                  + f" ({'ok' if not over else 'MISSED'}, target: no module more than twice)")

    state, memo = module_state(), prepared_dicts()
    print("\n3. process-wide state: module-level containers a function changes "
          f"({len(state)}); Prepared's dict fields ({len(memo)})")
    for s in state:
        print(f"   {s}: {WHY_KEPT.get(s.split()[-1], 'NOT JUSTIFIED')}")
    for s in memo:
        print(f"   Prepared.{s}")
    mods = modules()
    rooms = {str(d.relative_to(REPO)): len(list(d.glob("*.py")))
             for d in [REPO / "gt3dkit" / "fusion", *(REPO / "gt3dkit" / "fusion").rglob("*/")]
             if d.is_dir() and d.name != "__pycache__"}
    big = max(rooms, key=rooms.__getitem__)
    anys, longs = any_parameters(mods), long_functions(mods)
    print(f"\n4. parameters typed Any: {len(anys)} ({'ok' if not anys else 'MISSED'}, target 0); "
          f"functions over 80 lines: {len(longs)} ({'ok' if not longs else 'MISSED'}); "
          f"gt3dkit/fusion's largest folder: {big}, {rooms[big]} modules "
          f"({'ok' if rooms[big] <= 20 else 'MISSED'}, target 20)")
    mypy = subprocess.run([sys.executable, "-m", "mypy"], cwd=REPO, capture_output=True, text=True)
    last = (mypy.stdout.strip().splitlines() or ["(no output)"])[-1]
    print(f"\n6. the type checker (mypy, strict on the package as pyproject.toml sets it): {last} "
          f"({'ok' if mypy.returncode == 0 else 'MISSED'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

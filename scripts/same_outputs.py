"""No behaviour change, measured: the output files of a fixed set of runs, hashed, saved and compared.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/same_outputs.py --save before.json
    ... change the code ...
    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/same_outputs.py --against before.json

Each run is ``gt3d reconstruct`` as a user runs it (a subprocess); its ``tracks.csv``,
``keypoints.csv``, ``anomalies.csv`` and ``downweighted.csv`` are hashed (sha256). Where a file
differs from the saved run, the largest difference of any number in it is printed (the files
are read as CSV, cell by cell), so that a change of the last bits shows as such. Runs:

* bundled MultiviewX (UKF and GTSAM);
* ``../shared/data/wildtrack_first_half`` (and with ``--every-frame`` and ``--window 100``);
* CMU Panoptic 160906_band1 with ``--noise-px 2 --seed 0``;
* a 300-frame simulated skeleton (``gt3d simulate --kind skeleton --seed 1 --frames 300``), also
  with ``--window 100``;
* ``../shared/data/cmc1_detector_boxes``.

A run whose data is absent (no ``../shared``) is skipped and said so. Exit status 1 when a file
differs from the saved run (``--against``).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
GT3D = str(Path(sys.executable).with_name("gt3d"))
FILES = ("tracks.csv", "keypoints.csv", "anomalies.csv", "downweighted.csv")


def runs(data: Path, sim: Path) -> dict[str, tuple[Path, list[str]]]:
    mvx = REPO / "gt3dkit" / "data" / "multiviewx"
    wt = data / "wildtrack_first_half"
    pan = data / "panoptic_160906_band1"
    return {
        "multiviewx": (mvx, []),
        "multiviewx-gtsam": (mvx, ["--estimator", "gtsam"]),
        "wildtrack": (wt, []),
        "wildtrack-every-frame": (wt, ["--every-frame"]),
        "wildtrack-window100": (wt, ["--window", "100"]),
        "panoptic-noise2": (pan, ["--noise-px", "2", "--seed", "0"]),
        "skeleton300": (sim, []),
        "skeleton300-window100": (sim, ["--window", "100"]),
        "cmc1": (data / "cmc1_detector_boxes", []),
    }


def digest(out: Path) -> dict[str, str]:
    return {f: hashlib.sha256((out / f).read_bytes()).hexdigest() for f in FILES if (out / f).exists()}


def largest_gap(a: Path, b: Path) -> str:
    """The largest absolute difference between numeric cells of two CSV files (or why none)."""
    ra = list(csv.reader(a.open()))
    rb = list(csv.reader(b.open()))
    if len(ra) != len(rb):
        return f"{len(ra)} rows against {len(rb)}"
    gap, text = 0.0, 0
    for x, y in zip(ra, rb, strict=True):
        if len(x) != len(y):
            return "rows of different lengths"
        for u, v in zip(x, y, strict=True):
            if u == v:
                continue
            try:
                gap = max(gap, abs(float(u) - float(v)))
            except ValueError:
                text += 1
    return f"largest numeric difference {gap:.3g}" + (f", {text} text cells differ" if text else "")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--save", type=Path, help="write the hashes (and keep the outputs beside, in FILE.d/)")
    ap.add_argument("--against", type=Path, help="compare with a saved run")
    ap.add_argument("--only", help="comma-separated run names")
    args = ap.parse_args(argv)
    env = dict(os.environ, OPENBLAS_NUM_THREADS=os.environ.get("OPENBLAS_NUM_THREADS", "1"))
    saved = json.loads(args.against.read_text()) if args.against else {}
    keep = (args.save.with_suffix(".d") if args.save else Path(tempfile.mkdtemp(prefix="same_outputs_")))
    keep.mkdir(parents=True, exist_ok=True)
    sim = keep / "sim_skeleton300"
    if not (sim / "cameras.json").exists():
        subprocess.run([GT3D, "simulate", "--kind", "skeleton", "--seed", "1", "--frames", "300",
                        "--out", str(sim)], check=True, env=env, capture_output=True)
    hashes: dict[str, dict[str, str]] = {}
    bad = 0
    only = set(args.only.split(",")) if args.only else None
    for name, (inp, extra) in runs(args.data, sim).items():
        if only and name not in only:
            continue
        if not inp.exists():
            print(f"{name:<24} skipped: {inp} absent")
            continue
        out = keep / name
        p = subprocess.run([GT3D, "reconstruct", str(inp), "--out", str(out), "--quiet", *extra],
                           env=env, capture_output=True, text=True)
        if p.returncode:
            print(f"{name:<24} FAILED ({p.returncode}): {p.stderr.strip().splitlines()[-1:]}")
            bad += 1
            continue
        hashes[name] = digest(out)
        if not args.against:
            print(f"{name:<24} {', '.join(f'{f} {h[:10]}' for f, h in hashes[name].items())}")
            continue
        was = saved.get(name, {})
        for f in sorted(set(was) | set(hashes[name])):
            same = was.get(f) == hashes[name].get(f)
            detail = "identical" if same else "DIFFERS"
            if not same and f in hashes[name] and f in was:
                ref = args.against.with_suffix(".d") / name / f
                if ref.exists():
                    detail += f": {largest_gap(ref, out / f)}"
            bad += not same
            print(f"{name:<24} {f:<18} {detail}")
    if args.save:
        args.save.write_text(json.dumps(hashes, indent=1))
        print(f"saved {args.save} (outputs in {keep})")
    if args.against:
        print(f"{'all files identical' if not bad else f'{bad} file(s) differ'}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

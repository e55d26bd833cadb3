"""Issue 23 benchmark (part): long recordings, whole-process time and peak RSS of ``gt3d
reconstruct`` on the whole sequence (``--window 0``) and in the windows it chooses by itself,
with the MPJPE each gets against the simulator's truth.

    .venv/bin/python scripts/bench_long.py [--frames 1000,3000] [--people 3] [--cameras 8]
                                           [--modes whole,auto] [--box-frames 0]

* skeletons: ``gt3d simulate --kind skeleton --layout native --cameras C --frames F --people P
  --noise-px 1 --seed 1`` (19 joints, 30 fps), one scene per ``--frames`` value;
* boxes (``--box-frames N``): a WILDTRACK-rig scene of ``--box-people`` walkers, 7 cameras.

Every run is its own process, measured by ``/usr/bin/time`` (``%e`` wall seconds, ``%M`` peak
RSS of the process and its workers); OPENBLAS_NUM_THREADS=1 unless set. Not yet here: aniposelib
beside it (issue 23 asks for it in a ``bench`` extra).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

GT3D = str(Path(sys.executable).with_name("gt3d"))


def timed(cmd: list[str]) -> tuple[float, float, str]:
    """Wall seconds, peak RSS (GB) and stdout of ``cmd`` as a process."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1")}
    r = subprocess.run(["/usr/bin/time", "-f", "TIME %e %M", *cmd], capture_output=True, text=True, env=env)
    m = re.search(r"TIME ([\d.]+) (\d+)", r.stderr)
    if r.returncode != 0 or m is None:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{r.stderr[-2000:]}")
    return float(m.group(1)), int(m.group(2)) / 1e6, r.stdout


def mpjpe(out: str) -> str:
    m = re.search(r"ukf, all joints .* ([\d.]+)\s+[\d.]+\s*$", out, re.M)
    return m.group(1) if m else "-"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", default="1000,3000")
    ap.add_argument("--people", type=int, default=3)
    ap.add_argument("--cameras", type=int, default=8)
    ap.add_argument("--modes", default="whole,auto")
    ap.add_argument("--box-frames", type=int, default=0)
    ap.add_argument("--box-people", type=int, default=40)
    args = ap.parse_args()
    modes = {"whole": ["--window", "0"], "auto": []}
    print(f"{'scene':<34}{'run':<8}{'seconds':>9}{'peak GB':>9}{'ms/object-frame':>17}{'MPJPE mm':>10}"
          f"{'windows':>9}")
    with tempfile.TemporaryDirectory() as d:
        scenes = [(f"skeleton {f} fr x {args.people} x {args.cameras} cams",
                   ["--kind", "skeleton", "--layout", "native", "--cameras", str(args.cameras), "--frames", f,
                    "--people", str(args.people), "--noise-px", "1", "--seed", "1"])
                  for f in args.frames.split(",") if f]
        if args.box_frames:
            scenes.append((f"boxes {args.box_frames} fr x {args.box_people} x 7 cams",
                           ["--layout", "wildtrack", "--frames", str(args.box_frames), "--people",
                            str(args.box_people), "--noise-px", "1", "--seed", "1"]))
        for k, (name, sim) in enumerate(scenes):
            src = Path(d) / f"s{k}"
            subprocess.run([GT3D, "simulate", *sim, "--out", str(src)], check=True, capture_output=True)
            for mode in args.modes.split(","):
                out = Path(d) / f"o{k}{mode}"
                sec, gb, so = timed([GT3D, "reconstruct", str(src), "--out", str(out), *modes[mode]])
                found = re.search(r"-> (\d+) object-frames", so)
                rows = int(found.group(1)) if found else 1
                win = re.search(r"in (\d+) windows of (\d+) frames", so)
                print(f"{name:<34}{mode:<8}{sec:>9.1f}{gb:>9.2f}{1e3 * sec / rows:>17.2f}{mpjpe(so):>10}"
                      f"{(win.group(1) + 'x' + win.group(2)) if win else '-':>9}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

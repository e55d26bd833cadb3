"""``gt3d demo`` as a newcomer runs it: both datasets reconstructed and scored, both reports
written (the MultiviewX one drawn in a second process while Panoptic runs)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def test_the_demo_writes_its_runs_and_both_reports(tmp_path: Path) -> None:
    gt3d = str(Path(sys.executable).with_name("gt3d"))
    r = subprocess.run([gt3d, "demo", "--out", str(tmp_path / "demo")], capture_output=True, text=True,
                       check=False)
    assert r.returncode == 0, r.stderr[-2000:]
    for name in ("ukf", "gtsam", "triangulation", "panoptic_noise0px", "panoptic_noise2px"):
        assert (tmp_path / "demo" / name / "tracks.csv").is_file(), name
    for name in ("ukf", "panoptic_noise2px"):
        index = tmp_path / "demo" / name / "report" / "index.html"
        assert index.is_file() and f"  {index}" in r.stdout.splitlines()
        assert "each camera's worst frame" in index.read_text()
    assert "paper (Ma et al.)" in r.stdout and "ukf 2px, 19 joints" in r.stdout

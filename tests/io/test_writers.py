"""The CSV writers' bytes against the standard library's ``csv.writer``."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from gt3dkit.io.writers import KPT_COLUMNS, write_keypoints_csv
from gt3dkit.types import TrackSet


def test_keypoints_csv_is_what_csv_writer_writes(tmp_path: Path) -> None:
    """``keypoints.csv`` (one ``%``-template a row) holds the bytes ``csv.writer`` writes of each
    finite joint's row formatted field by field: negative zeros, values that round to zero or
    carry at the sixth decimal, large ids; joints with any NaN left out."""
    rng = np.random.default_rng(3)
    m, j = 400, 5
    kpt = rng.normal(size=(m, j, 3)) * rng.choice([1e-7, 1.0, 1e3], size=(m, j, 1))
    kpt[rng.random((m, j)) < 0.1, rng.integers(0, 3)] = np.nan
    kpt[0, 0] = [-0.0, 4e-7, -4e-7]
    kpt[0, 1] = [1234.5678905, -0.0000005, 2.5e-6]
    sd = np.abs(rng.normal(size=(m, j))) * 1e-2
    tracks = TrackSet(frame=np.arange(m) // 2, track_id=np.where(np.arange(m) % 2, 2**40, -3),
                      center_world=np.zeros((m, 3)), semi_axes=np.ones((m, 3)), center_sd=np.ones((m, 3)),
                      n_views=np.ones(m, np.int64), kpt_world=kpt, kpt_sd=sd)
    write_keypoints_csv(tmp_path / "k.csv", tracks)
    with open(tmp_path / "ref.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(KPT_COLUMNS)
        for r in range(m):
            for k in range(j):
                x = kpt[r, k]
                if np.isfinite(x).all():
                    w.writerow([int(tracks.frame[r]), int(tracks.track_id[r]), k,
                                f"{x[0]:.6f}", f"{x[1]:.6f}", f"{x[2]:.6f}", f"{sd[r, k]:.6f}"])
    got = (tmp_path / "k.csv").read_bytes()
    assert got == (tmp_path / "ref.csv").read_bytes()
    assert b"-0.000000" in got and got.count(b"\r\n") == 1 + int(np.isfinite(kpt).all(axis=-1).sum())

"""Issue 63: the UKF taking each view at its own camera's time, on the simulator's unsynchronised
cameras (the scenes of ``tests/fusion/test_timed_views.py``, whose tests assert the ordering; this
prints the figures).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/clock_filter_targets.py

1. Keypoints: 3 people, 6 cameras, 1.5 px, cameras late by 2.4, -1.3, 0.5, 3.7, -0.25 frames (the
   people's exact motion at each camera's time): MPJPE with each view at its own time, with the
   offsets rounded to whole frames, ignored, and the same people filmed in step.
2. The same with one camera at 25 fps and two drifting by 0.2 %: with the rates given, without.
3. Boxes: people simulated at 100 fps, each camera keeping every tenth frame from its own start (late
   by 2.4, -1.3, 0.5, 1.7, -0.6 frames at 10 fps): centre error the same four ways.
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gt3dkit.api import load_scene, reconstruct  # noqa: E402
from gt3dkit.eval.metrics import box_errors  # noqa: E402
from gt3dkit.eval.pose import mpjpe_by_id  # noqa: E402
from gt3dkit.io.clocks import CameraClocks, on_one_clock  # noqa: E402
from gt3dkit.sim import simulate, simulate_skeletons, write_scene, write_skeleton_scene  # noqa: E402
from gt3dkit.types import GroundTruth, Scene  # noqa: E402

LATE = np.array([0.0, 2.4, -1.3, 0.5, 3.7, -0.25])
FPS = np.array([30.0, 30.0, 25.0, 30.0, 30.06, 29.94])
LATE_BOXES = np.array([0.0, 2.4, -1.3, 0.5, 1.7, -0.6])


def skeletons(tmp: Path) -> None:
    def scene(name: str, **clock: np.ndarray) -> Scene:
        sim = simulate_skeletons("native", seed=2, frames=60, people=3, noise_px=1.5, cameras=6, **clock)
        write_skeleton_scene(sim, tmp / name, "native")
        return load_scene(tmp / name)

    def mm(s: Scene) -> float:
        assert s.truth is not None
        return mpjpe_by_id(reconstruct(s, "ukf"), s.truth)[0]

    sync, late = scene("sync"), scene("late", late_frames=LATE)
    rates = scene("rates", late_frames=LATE, camera_fps=FPS)
    names = late.rig.names
    own = mm(on_one_clock(late, CameraClocks.of(names, LATE)))
    whole = mm(on_one_clock(late, CameraClocks.of(names, np.floor(LATE + 0.5))))
    print(f"1. keypoints, MPJPE mm: in step {mm(sync):.2f}; each view at its own time {own:.2f}; whole "
          f"frames {whole:.2f}; offsets ignored {mm(late):.2f}")
    given = mm(on_one_clock(rates, CameraClocks(names, LATE, np.full(6, np.nan), FPS)))
    only = mm(on_one_clock(rates, CameraClocks.of(names, LATE)))
    print(f"2. one camera at 25 fps, two drifting 0.2 %: rates given {given:.2f}; offsets only {only:.2f}")


def boxes(tmp: Path) -> None:
    sim = simulate("native", seed=0, frames=300, people=6, noise_px=1.0, fps=100.0)
    write_scene(sim, tmp / "fine", "native")
    fine = load_scene(tmp / "fine")
    step, o, tr = 10, fine.obs, fine.truth
    assert tr is not None

    def coarse(frame: np.ndarray) -> Scene:
        on = frame % step == 0
        kept = dataclasses.replace(o, frame=frame // step).select(on)
        t = tr.frame % step == 0
        truth = GroundTruth(tr.frame[t] // step, tr.track_id[t], tr.center_world[t], tr.semi_axes[t],
                            tr.kpt_world[t], tr.source)
        return dataclasses.replace(fine, obs=kept, fps=fine.fps / step, frames=np.unique(kept.frame),
                                   truth=truth)

    def mm(s: Scene) -> float:
        assert s.truth is not None
        return 1000 * box_errors(reconstruct(s, "ukf"), s.truth, s.rig.up).centre_mean_m

    sync = coarse(o.frame)
    shifted = coarse(o.frame + np.round(LATE_BOXES * step).astype(np.int64)[o.cam])
    names = fine.rig.names
    own = mm(on_one_clock(shifted, CameraClocks.of(names, LATE_BOXES)))
    whole = mm(on_one_clock(shifted, CameraClocks.of(names, np.floor(LATE_BOXES + 0.5))))
    print(f"3. boxes, centre error mm: in step {mm(sync):.1f}; each view at its own time {own:.1f}; whole "
          f"frames {whole:.1f}; offsets ignored {mm(shifted):.1f}")


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        skeletons(Path(tmp))
        boxes(Path(tmp))
    return 0


if __name__ == "__main__":
    sys.exit(main())

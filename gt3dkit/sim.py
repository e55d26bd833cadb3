"""Seeded synthetic scenes with known truth, written in any input layout.

People are vertical ellipsoids standing on the ground (centre height = vertical
semi-axis) walking smooth paths (a straight line plus a slow sinusoid) over a
rectangle seen by a ring of cameras with mild lens distortion. Each person is
annotated from a random first to a random last frame. Boxes are the exact
boxes of the people (:func:`gt3dkit.geom.conics.model_boxes`: tangent boxes of their ellipsoids),
plus Gaussian noise on every edge, clipped to the image and rounded to whole
pixels (truncated towards zero for the MultiviewX layout, as its generator does);
a view is dropped at random with probability ``Errors.dropped``.

Realistic annotation and detector errors (:class:`Errors`) are injected with a random
stream of their own, so a scene with errors has exactly the same noise as the same seed
without them: far-off keypoints, left/right swaps of single joints, glitches (a zero
coordinate with a high confidence), shifted boxes, a time gap with no annotation at all,
people seen by one camera only. Every injected error is listed (``injected.csv`` beside
``truth.csv``) so that tests check both the estimate and what was flagged.

``motion="walk"`` replaces the smooth paths by real-trajectory-like walking: speed and
heading wander (Ornstein-Uhlenbeck), people turn, slow down and keep inside the area.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from gt3dkit.calib.formats.grid import LAYOUTS as GRID_LAYOUTS
from gt3dkit.geom.camera import Cams, project_points
from gt3dkit.geom.conics import covered_fraction, model_boxes
from gt3dkit.io.atomic import write_dir_atomically
from gt3dkit.io.datasets import LAYOUTS, openpose, tasks
from gt3dkit.io.datasets.wildtrack import write_truth_csv
from gt3dkit.skeletons import SKELETONS
from gt3dkit.types import BOX_MODELS, F64, I64, Camera, Rig, SimScene, SkeletonScene

SIM_LAYOUTS = ("wildtrack", "multiviewx", "native")
WRITE_LAYOUTS = tuple(k for k, v in LAYOUTS.items() if v.write_boxes is not None)
INJECTED_COLUMNS = ("frame", "camera", "id", "joint", "kind", "detail")


#: Box views and keypoints left out at random unless :attr:`Errors.dropped` says otherwise.
DROPPED_VIEWS = 0.15
#: WILDTRACK's annotation tool places a person on a ground grid of this pitch (positionID).
POSITION_GRID_M = 0.025
DROPPED_KEYPOINTS = 0.05


@dataclass(frozen=True)
class Errors:
    """Errors real annotators and detectors make, as fractions.

    outliers : keypoints replaced by a point 100-300 px away (confidence 0.2-0.7)
    swaps : person-views in which one left/right joint pair is exchanged
    glitch : keypoints with a zero coordinate (x = 0, or both) at confidence 0.6-0.9
    shifted : boxes moved by 0.3-1.0 of their size (another person's box, a slip)
    gap : ``(a, b)`` frame *indices*: frames ``a..b-1`` carry no annotation at all
    single_view : people whose annotations are kept in one camera only (the one that sees
        them most)
    missing : boxes of people in plain sight (well inside the image, at most 10 % covered by
        people nearer or less than 0.5 m farther) left out, as an annotator who skipped them
        (boxes only)
    time_offset : ``(camera index, frames)``: that camera's boxes show each person ``frames``
        frame steps later than labelled (an unsynchronised camera; boxes only)
    hide_covered : boxes covered by nearer people's boxes by more than this fraction are left
        out, as annotators skip people hidden behind others (None: keep them; boxes only)
    dropped : views (boxes) or keypoints left out at random; None: the generator's default
        (:data:`DROPPED_VIEWS` of the box views, :data:`DROPPED_KEYPOINTS` of the keypoints)
    reused_ids : ids handed on: this many times a person's id goes, from some frame on, to
        another person (who is annotated under it from then on; the first person from then on
        not at all), as real label sets reuse the id of someone who left (boxes only)
    exchanged_ids : this many times two people's ids are exchanged for 1-4 consecutive frames,
        in every view (boxes only)

    Both id errors are in the truth as well (as in WILDTRACK, whose positions carry the labels'
    ids): the truth says where each annotated (frame, id) is, not who it is.
    """

    outliers: float = 0.0
    swaps: float = 0.0
    glitch: float = 0.0
    shifted: float = 0.0
    gap: tuple[int, int] | None = None
    single_view: float = 0.0
    missing: float = 0.0
    time_offset: tuple[int, int] | None = None
    hide_covered: float | None = None
    dropped: float | None = None
    reused_ids: int = 0
    exchanged_ids: int = 0

    def __post_init__(self) -> None:
        if self.reused_ids < 0 or self.exchanged_ids < 0:
            raise ValueError("reused_ids and exchanged_ids must be >= 0")
        for k in ("hide_covered", "dropped"):
            v = getattr(self, k)
            if v is not None and not 0 <= v < 1:
                raise ValueError(f"{k} must be a fraction in [0, 1), got {v}")
        for k in ("outliers", "swaps", "glitch", "shifted", "single_view", "missing"):
            v = getattr(self, k)
            if not 0 <= v <= 1:
                raise ValueError(f"{k} must be a fraction in [0, 1], got {v}")
        if self.gap is not None and not 0 <= self.gap[0] < self.gap[1]:
            raise ValueError(f"gap must be (first, end) frame indices with first < end, got {self.gap}")


def _gap_mask(frames: I64, truth_frame: I64, gap: tuple[int, int] | None) -> np.ndarray:
    """(M,) truth rows inside the gap."""
    if gap is None:
        return np.zeros(len(truth_frame), bool)
    inside = frames[gap[0]:gap[1]]
    return np.isin(truth_frame, inside)


def _keep_one_view(seen: np.ndarray, truth_id: I64, frac: float, rng: np.random.Generator
                   ) -> tuple[np.ndarray, list[int]]:
    """``seen (M, C)`` with a fraction of people restricted to their most-seen camera."""
    ids = np.unique(truth_id)
    k = int(round(frac * len(ids)))
    chosen = rng.choice(ids, size=k, replace=False) if k else np.zeros(0, dtype=np.int64)
    out = seen.copy()
    for pid in chosen:
        m = truth_id == pid
        best = int(np.argmax(seen[m].sum(axis=0)))
        keep = np.zeros(seen.shape[1], bool)
        keep[best] = True
        out[m] &= keep
    return out, [int(p) for p in chosen]


def _look_at(center: F64, target: F64) -> tuple[F64, F64]:
    """cam_from_world ``R, t`` of a camera at ``center`` looking at ``target`` (z up)."""
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ center


def make_rig(n_cams: int, area_lo: F64, area_hi: F64, names: list[str],
             rng: np.random.Generator) -> Rig:
    """A ring of ``n_cams`` 1920x1080 cameras around the area, 2.5-6 m high, mild distortion."""
    mid = (area_lo + area_hi) / 2
    half = (area_hi - area_lo) / 2
    cams = []
    for i in range(n_cams):
        ang = 2 * np.pi * (i + rng.uniform(-0.15, 0.15)) / n_cams
        pos = np.r_[mid + (half + 5.0) * np.array([np.cos(ang), np.sin(ang)]), rng.uniform(2.5, 6)]
        target = np.r_[mid + rng.uniform(-0.2, 0.2, 2) * half, 0.8]
        R, t = _look_at(pos, target)
        f = rng.uniform(900, 1200)
        K = np.array([[f, 0, 960 + rng.uniform(-20, 20)], [0, f, 540 + rng.uniform(-20, 20)],
                      [0, 0, 1]])
        dist = np.array([rng.uniform(-0.08, -0.02), rng.uniform(0.0, 0.03),
                         rng.uniform(-1e-3, 1e-3), rng.uniform(-1e-3, 1e-3), 0.0])
        cams.append(Camera(names[i], 1920, 1080, K, dist, R, t))
    return Rig(tuple(cams), up=np.array([0.0, 0.0, 1.0]), frame_name="synthetic world (z up)")


def _walk(rng: np.random.Generator, t_s: F64, lo: F64, hi: F64) -> F64:
    """(T, 2) a walking path: speed and turn rate wander (Ornstein-Uhlenbeck, 1-3 s), the
    walker steers back when near the area's border. Integrated at 50 Hz, sampled at t_s."""
    dt = 0.02
    tt = np.arange(t_s[0], t_s[-1] + dt, dt)
    v0 = rng.uniform(0.6, 1.6)
    p = rng.uniform(lo + 1, hi - 1)
    head = rng.uniform(0, 2 * np.pi)
    v, w = v0, 0.0
    out = np.zeros((len(tt), 2))
    mid = (lo + hi) / 2
    for k in range(len(tt)):
        out[k] = p
        v += (v0 - v) * dt / 2.0 + 0.35 * np.sqrt(dt) * rng.normal()
        v = max(v, 0.0)
        w += -w * dt / 1.0 + 1.2 * np.sqrt(dt) * rng.normal()
        if np.any(p < lo + 1) or np.any(p > hi - 1):  # steer back towards the middle
            want = np.arctan2(*(mid - p)[::-1])
            w += 2.0 * np.angle(np.exp(1j * (want - head))) * dt
        head += w * dt
        p = p + v * dt * np.array([np.cos(head), np.sin(head)])
    return np.stack([np.interp(t_s, tt, out[:, 0]), np.interp(t_s, tt, out[:, 1])], -1)


def _stop_and_turn(rng: np.random.Generator, t_s: F64, lo: F64, hi: F64) -> F64:
    """(T, 2) a walker who stops and turns as people do between two annotations at 2 fps: walks
    at 0.8-1.6 m/s, every 2-6 s either stands still for 0.5-2.5 s or turns by 45-150 degrees within
    half a second (2.5-6 m/s^2 of the labels' own second differences), steers back near the
    area's border. Integrated at 50 Hz, sampled at ``t_s``."""
    dt = 0.02
    tt = np.arange(t_s[0], t_s[-1] + dt, dt)
    v0 = rng.uniform(0.8, 1.6)
    p = rng.uniform(lo + 1, hi - 1)
    head = rng.uniform(0, 2 * np.pi)
    mid = (lo + hi) / 2
    out = np.zeros((len(tt), 2))
    next_event, stop_until, turn_left, turn_rate = rng.uniform(1, 4), -1.0, 0.0, 0.0
    for k, now in enumerate(tt):
        out[k] = p
        if now >= next_event:
            if rng.uniform() < 0.5:
                stop_until = now + rng.uniform(0.5, 2.5)
            else:
                turn_left = 0.5
                turn_rate = np.deg2rad(rng.uniform(45, 150)) * rng.choice([-1, 1]) / 0.5
            next_event = now + rng.uniform(2, 6)
        if turn_left > 0:
            head += turn_rate * dt
            turn_left -= dt
        if np.any(p < lo + 1) or np.any(p > hi - 1):  # steer back towards the middle
            want = np.arctan2(*(mid - p)[::-1])
            head += 2.0 * np.angle(np.exp(1j * (want - head))) * dt
        v = 0.0 if now < stop_until else v0
        p = p + v * dt * np.array([np.cos(head), np.sin(head)])
    return np.stack([np.interp(t_s, tt, out[:, 0]), np.interp(t_s, tt, out[:, 1])], -1)


def simulate(layout: str = "native", seed: int = 0, frames: int = 40, people: int = 10,
             noise_px: float = 0.0, errors: Errors | None = None, motion: str = "smooth",
             cameras: int | None = None, fps: float | None = None, labels: str = "ellipsoid") -> SimScene:
    """Generate a seeded scene. See the module docstring.

    ``motion``: ``smooth`` paths, ``walk`` (speed and turn rate wander) or ``stop-and-turn``
    (:func:`_stop_and_turn`). ``labels``: the box model that draws the boxes
    (:data:`gt3dkit.types.BOX_MODELS`): ``ellipsoid`` (each box the tangent box of the person's
    ellipsoid, clipped at the image border), or an annotation tool's: ``cylinder`` (an upright
    cylinder's box) or ``pom`` (the occupancy-map rectangle of WILDTRACK's and MultiviewX's labels),
    one radius, placed on a 2.5 cm ground grid and drawn whole, partly outside the image where the
    person is; the truth is the centre on the grid.


    ``cameras`` and ``fps`` set the native layout's camera count (default 6) and frame rate
    (default 10); the WILDTRACK and MultiviewX layouts have their own.
    """
    if layout not in SIM_LAYOUTS:
        raise ValueError(f"unknown layout {layout!r} (known: {', '.join(SIM_LAYOUTS)})")
    errors = errors or Errors()
    dropout = DROPPED_VIEWS if errors.dropped is None else errors.dropped
    if frames < 2 or people < 1 or not noise_px >= 0:
        raise ValueError("need frames >= 2, people >= 1, noise_px >= 0")
    if motion not in ("smooth", "walk", "stop-and-turn"):
        raise ValueError(f"motion must be smooth, walk or stop-and-turn, got {motion!r}")
    if labels not in BOX_MODELS:
        raise ValueError(f"labels must be one of {', '.join(BOX_MODELS)}, got {labels!r}")
    if layout not in ("native", "mot") and (cameras is not None or fps is not None):
        raise ValueError("cameras and fps apply to the native layout (the others have theirs)")
    if cameras is not None and not 1 <= cameras <= 64:
        raise ValueError(f"cameras must be 1..64, got {cameras}")
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    errors = errors or Errors()
    rng = np.random.default_rng(seed)
    err_rng = np.random.default_rng([seed, 1])
    if layout == "wildtrack":
        g = GRID_LAYOUTS["wildtrack"]
        lo, hi = np.array([-1.0, -6.0]), np.array([7.0, 14.0])
        names, step, fps = list(g.cameras), 5, g.fps
    elif layout == "multiviewx":
        g = GRID_LAYOUTS["multiviewx"]
        lo, hi = np.array([3.0, 2.0]), np.array([22.0, 14.0])
        names, step, fps = list(g.cameras), 1, g.fps
    else:
        lo, hi = np.array([-6.0, -4.0]), np.array([6.0, 4.0])
        names, step = [f"cam{i}" for i in range(cameras or 6)], 1
        fps = float(fps or 10.0)
    rig = make_rig(len(names), lo, hi, names, rng)
    frame_numbers = np.arange(frames, dtype=np.int64) * step + (1 if layout == "multiviewx" else 0)
    t_s = frame_numbers / fps
    T = t_s[-1] - t_s[0]
    rows_f, rows_id, centers, axes = [], [], [], []
    for pid in range(people):
        ab = rng.uniform(0.2, 0.3, 2)
        c = rng.uniform(0.8, 0.95)
        p0 = rng.uniform(lo + 1, hi - 1)
        p1 = rng.uniform(lo + 1, hi - 1)
        amp = rng.uniform(0.2, 0.6) * rng.normal(size=2) / np.sqrt(2)
        period = rng.uniform(8, 16)
        phase = rng.uniform(0, 2 * np.pi)
        first = int(rng.integers(0, max(frames // 3, 1)))
        last = int(rng.integers(2 * frames // 3, frames))
        walk = _walk(np.random.default_rng([seed, 2, pid]), t_s, lo, hi) if motion == "walk" \
            else _stop_and_turn(np.random.default_rng([seed, 3, pid]), t_s, lo, hi) \
            if motion == "stop-and-turn" else None
        for k in range(first, last + 1):
            s = (t_s[k] - t_s[0]) / max(T, 1e-9)
            xy = p0 + (p1 - p0) * s + amp * np.sin(2 * np.pi * (t_s[k] - t_s[0]) / period + phase)
            if walk is not None:
                xy = walk[k]
            rows_f.append(frame_numbers[k])
            rows_id.append(pid)
            centers.append([xy[0], xy[1], c])
            axes.append([ab[0], ab[1], c])
    center = np.array(centers)
    semi = np.array(axes)
    cams = Cams.of(rig, labels)
    tool = labels != "ellipsoid"  # an annotation tool's solid: one radius, on its 2.5 cm grid
    if tool:
        semi[:, :2] = semi[:, :2].mean(axis=1, keepdims=True)
        center[:, :2] = np.round(center[:, :2] / POSITION_GRID_M) * POSITION_GRID_M
    box, margin = model_boxes(center, semi, cams)
    box = box + rng.normal(scale=noise_px, size=box.shape) if noise_px > 0 else box
    W, H = cams.wh[:, 0], cams.wh[:, 1]
    inside = (margin > 0) & (box[..., 2] > 0) & (box[..., 0] < W - 1) & (box[..., 3] > 0) \
        & (box[..., 1] < H - 1)
    if not tool:  # an annotation tool's solid is drawn past the border whole
        box = np.stack([np.clip(box[..., 0], 0, W - 1), np.clip(box[..., 1], 0, H - 1),
                        np.clip(box[..., 2], 0, W - 1), np.clip(box[..., 3], 0, H - 1)], -1)
    box = np.trunc(box) if layout == "multiviewx" else np.rint(box)
    seen = inside & (rng.uniform(size=inside.shape) >= dropout)
    seen &= (box[..., 2] > box[..., 0]) & (box[..., 3] > box[..., 1])
    truth_frame, truth_id = np.array(rows_f), np.array(rows_id)
    injected: list[tuple[int, str, int, str, str, str]] = []
    if errors.time_offset is not None:
        c, k = errors.time_offset
        if not 0 <= c < len(rig.cameras):
            raise ValueError(f"time_offset camera {c} not in 0..{len(rig.cameras) - 1}")
        at = {(int(f), int(i)): m for m, (f, i) in enumerate(zip(truth_frame, truth_id, strict=True))}
        step = int(frame_numbers[1] - frame_numbers[0])
        src = np.array([at.get((int(f) + k * step, int(i)), -1) for f, i in
                        zip(truth_frame, truth_id, strict=True)])
        box[:, c] = np.where((src >= 0)[:, None], box[np.maximum(src, 0), c], np.nan)
        seen[:, c] &= (src >= 0) & inside[np.maximum(src, 0), c]
        injected.append((int(frame_numbers[0]), rig.cameras[c].name, -1, "", "time_offset",
                         f"{k:+d} frames"))
    centres = np.stack([c.center_world for c in rig.cameras])
    depth = np.linalg.norm(center[:, None, :] - centres[None], axis=-1)  # (M, C)
    hide_covered = errors.hide_covered
    if hide_covered is not None or errors.missing:  # everyone in the picture hides, annotated or not
        cov = np.zeros(seen.shape)
        for f in np.unique(truth_frame):
            m = np.flatnonzero(truth_frame == f)
            cov[m] = covered_fraction(np.where(inside[m][..., None], box[m], np.nan), depth[m])
        if hide_covered is not None:
            seen &= cov <= hide_covered
        if errors.missing:  # plain sight: not covered by anyone nearer or within half a metre
            for f in np.unique(truth_frame):
                m = np.flatnonzero(truth_frame == f)
                cov[m] = covered_fraction(np.where(inside[m][..., None], box[m], np.nan), depth[m], 0.5)
            margin_px = 0.05 * np.maximum(W, H)
            plain = seen & (cov <= 0.1) & (box[..., 0] > margin_px) & (box[..., 1] > margin_px) \
                & (box[..., 2] < W - margin_px) & (box[..., 3] < H - margin_px)
            plain &= seen.sum(axis=1, keepdims=True) >= 3  # the others still see them twice
            hit = plain & (err_rng.uniform(size=seen.shape) < errors.missing)
            seen &= ~hit
            for m, c in zip(*np.nonzero(hit), strict=True):
                injected.append((int(truth_frame[m]), rig.cameras[c].name, int(truth_id[m]), "",
                                 "missing_view", f"{100 * cov[m, c]:.0f}% covered"))
    seen &= ~_gap_mask(frame_numbers, truth_frame, errors.gap)[:, None]
    if errors.single_view:
        seen, chosen = _keep_one_view(seen, truth_id, errors.single_view, err_rng)
        injected += [(-1, "", p, "", "single_view", "annotated in one camera only")
                     for p in chosen]
    if errors.shifted:
        hit = seen & (err_rng.uniform(size=seen.shape) < errors.shifted)
        size = np.stack([box[..., 2] - box[..., 0], box[..., 3] - box[..., 1]], -1)
        frac = err_rng.uniform(0.3, 1.0, size=seen.shape) * err_rng.choice([-1, 1], size=seen.shape)
        horiz = err_rng.uniform(size=seen.shape) < 0.7
        d = np.where(horiz[..., None], [1.0, 0.0], [0.0, 1.0]) * (frac[..., None] * size)
        moved = box + np.concatenate([d, d], -1)
        W, H = cams.wh[:, 0], cams.wh[:, 1]
        ok = (moved[..., 0] >= 0) & (moved[..., 2] <= W - 1) & (moved[..., 1] >= 0) \
            & (moved[..., 3] <= H - 1)
        hit &= ok
        box = np.where(hit[..., None], moved, box)
        for m, c in zip(*np.nonzero(hit), strict=True):
            injected.append((int(truth_frame[m]), rig.cameras[c].name, int(truth_id[m]), "",
                             "shifted_box", f"moved {float(np.abs(d[m, c]).max()):.0f} px"))
    box = np.where(seen[..., None], box, np.nan)
    if errors.reused_ids or errors.exchanged_ids:
        keep, truth_id, more = _id_errors(truth_frame, truth_id, seen, errors, err_rng)
        injected += more
        truth_frame, truth_id = truth_frame[keep], truth_id[keep]
        center, semi, box = center[keep], semi[keep], box[keep]
    return SimScene(rig=rig, frames=frame_numbers, fps=fps, truth_frame=truth_frame,
                    truth_id=truth_id, center_world=center, semi_axes=semi, boxes=box,
                    injected=tuple(injected))


def _id_errors(frame: I64, ids: I64, seen: np.ndarray, errors: Errors, rng: np.random.Generator
               ) -> tuple[np.ndarray, I64, list[tuple[int, str, int, str, str, str]]]:
    """The id errors of ``errors`` on truth rows ``frame, ids (M,)`` whose views are ``seen (M,
    C)``: the rows kept ``(M,)``, the ids they carry ``(M,)`` and the injected-error rows."""
    keep = np.ones(len(frame), bool)
    ids = ids.copy()
    out: list[tuple[int, str, int, str, str, str]] = []
    two = seen.sum(axis=1) >= 2

    def frames_of(i: int) -> I64:
        return np.unique(frame[keep & (ids == i) & two])

    used: set[int] = set()  # each person in one id error at most (each error stays as listed)
    for _ in range(errors.reused_ids):  # id a goes to person b from frame k on
        people = [int(i) for i in np.unique(ids[keep]) if int(i) not in used]
        pairs = [(a, b) for a in people for b in people if a != b]
        rng.shuffle(pairs)
        for a, b in pairs:
            fa, fb = frames_of(int(a)), frames_of(int(b))
            both = np.intersect1d(fa, fb)
            if len(both) < 6:
                continue
            k = int(both[rng.integers(2, len(both) - 2)])
            keep &= ~(((ids == a) & (frame >= k)) | ((ids == b) & (frame < k)))
            ids[(ids == b) & (frame >= k)] = a
            used |= {a, b}
            out.append((k, "", int(a), "", "reused_id", f"person {int(b)} from here"))
            break
    for _ in range(errors.exchanged_ids):  # ids a and b exchanged for 1-4 frames
        people = [int(i) for i in np.unique(ids[keep]) if int(i) not in used]
        pairs = [(a, b) for a in people for b in people if a < b]
        rng.shuffle(pairs)
        for a, b in pairs:
            both = np.intersect1d(frames_of(int(a)), frames_of(int(b)))
            n = int(rng.integers(1, 5))
            if len(both) < n + 4:
                continue
            i0 = int(rng.integers(2, len(both) - n - 1))
            span = both[i0:i0 + n]
            ra = keep & (ids == a) & np.isin(frame, span)
            rb = keep & (ids == b) & np.isin(frame, span)
            ids[ra], ids[rb] = b, a
            used |= {a, b}
            out.append((int(span[0]), "", int(a), "", "exchanged_ids",
                        f"with {int(b)} for {n} frame{'s' if n > 1 else ''}"))
            break
    return keep, ids, out


def write_scene(sim: SimScene, out: Path, layout: str, id_seed: int | None = 0) -> None:
    """Write ``sim`` as an input folder of ``layout`` (atomically, by the layout's writer in
    :data:`gt3dkit.io.datasets.LAYOUTS`), with ``truth.csv`` and ``injected.csv``.

    ``mot``, ``cvat``: each camera's ids a random permutation of the people (``id_seed``; None
    keeps the global ids), as separate per-camera annotation tasks number them."""
    if layout not in WRITE_LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}")
    writer = LAYOUTS[layout].write_boxes
    assert writer is not None

    def write(tmp: Path) -> None:
        write_truth_csv(sim, tmp / "truth.csv")
        _write_injected(sim.injected, tmp / "injected.csv")
        writer(sim, tmp, id_seed)

    write_dir_atomically(Path(out), write)


def _write_injected(rows: tuple[tuple[int, str, int, str, str, str], ...], path: Path) -> None:
    """``injected.csv``: every error the simulator put in (``frame`` -1 and ``camera`` empty
    for a whole track)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(INJECTED_COLUMNS)
        w.writerows(rows)


# ---------------------------------------------------------------------------------------
# skeletons


def make_dome(n_cams: int, rng: np.random.Generator, up: F64, names: list[str]) -> Rig:
    """HD cameras (1920x1080, Panoptic-like focal length and distortion) on a dome of radius
    ~2.9 m (CMU Panoptic's HD cameras: f ~ 1600 px, k1 ~ -0.22)."""
    up = up / np.linalg.norm(up)
    ref = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = ref - up * (ref @ up)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    cams = []
    for i in range(n_cams):
        ang = 2 * np.pi * (i + rng.uniform(-0.2, 0.2)) / n_cams
        h = rng.uniform(0.8, 2.8)
        r = rng.uniform(2.6, 3.1)
        pos = r * (np.cos(ang) * e1 + np.sin(ang) * e2) + h * up
        target = 0.9 * up + rng.uniform(-0.2, 0.2) * e1
        z = target - pos
        z /= np.linalg.norm(z)
        x = np.cross(z, up)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        f = rng.uniform(1400, 1700)
        K = np.array([[f, 0, 960 + rng.uniform(-15, 15)], [0, f, 540 + rng.uniform(-15, 15)],
                      [0, 0, 1]])
        dist = np.array([rng.uniform(-0.25, -0.15), rng.uniform(0.05, 0.2),
                         rng.uniform(-1e-3, 1e-3), rng.uniform(-1e-3, 1e-3), rng.uniform(0, 0.03)])
        cams.append(Camera(names[i], 1920, 1080, K, dist, R, -R @ pos))
    return Rig(tuple(cams), up=up, frame_name="synthetic world")


def _rot(axis: F64, ang: F64) -> F64:
    """Rotations (..., 3, 3) about unit ``axis`` (3,) by angles ``ang`` (...,) (Rodrigues)."""
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.asarray(ang)[..., None, None]
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * (K @ K)


def skeleton_motion(skel_name: str, t_s: F64, rng: np.random.Generator) -> F64:
    """(T, J, 3) body-frame joints of one person: canonical pose scaled, limbs swinging
    about their parent joints (bone lengths exact), turning and walking slowly."""
    skel = SKELETONS[skel_name]
    names = skel.joints
    ix = {n: i for i, n in enumerate(names)}
    base = skel.canonical() * rng.uniform(0.9, 1.1)
    T = len(t_s)
    P = np.repeat(base[None], T, axis=0)
    lat = np.array([1.0, 0.0, 0.0])
    chains = [("l_shoulder", ("l_elbow", "l_wrist")), ("r_shoulder", ("r_elbow", "r_wrist")),
              ("l_hip", ("l_knee", "l_ankle")), ("r_hip", ("r_knee", "r_ankle"))]
    w = rng.uniform(2.0, 4.0)
    for k, (root, kids) in enumerate(chains):
        amp = rng.uniform(0.2, 0.5) * (1 if k % 2 == 0 else -1)
        Rt = _rot(lat, amp * np.sin(w * t_s + rng.uniform(0, 0.3)))  # (T,3,3)
        o = base[ix[root]]
        for kid in kids:
            if kid in ix:
                P[:, ix[kid]] = o + np.einsum("tij,j->ti", Rt, base[ix[kid]] - o)
        # the lower link bends further about the middle joint
        if len(kids) == 2 and all(c in ix for c in kids):
            mid, end = ix[kids[0]], ix[kids[1]]
            R2 = _rot(lat, 0.3 * amp * (1 + np.sin(1.3 * w * t_s)))
            P[:, end] = P[:, mid] + np.einsum("tij,tj->ti", R2, P[:, end] - P[:, mid])
    yaw = rng.uniform(0, 2 * np.pi) + rng.uniform(-0.4, 0.4) * np.sin(0.5 * t_s)
    Rz = _rot(np.array([0.0, 0.0, 1.0]), yaw)
    root_xy = rng.uniform(-0.8, 0.8, 2) + np.stack([0.3 * np.sin(0.4 * t_s + rng.uniform(0, 6)),
                                                     0.3 * np.cos(0.3 * t_s)], -1)
    P = np.einsum("tij,tkj->tki", Rz, P)
    P[..., :2] += root_xy[:, None, :]
    return P


def simulate_skeletons(layout: str = "native", seed: int = 0, frames: int = 30, people: int = 3,
                       noise_px: float = 0.0, cameras: int = 10,
                       skeleton: str = "coco19", fps: float = 30.0, errors: Errors | None = None,
                       confidences: bool = False) -> SkeletonScene:
    """People as moving skeletons seen by a dome of HD cameras, in a y-down world.

    2D points are exact projections (with distortion) plus ``noise_px`` Gaussian noise;
    points behind a camera or outside its image are dropped, and a fraction
    ``Errors.dropped`` of the rest at random. ``errors`` (native layout) adds detector errors;
    ``confidences`` writes a detector-like confidence per point (lower for worse points).
    """
    if layout not in ("native", "panoptic"):
        raise ValueError(f"skeleton scenes are written as native or panoptic, not {layout!r}")
    errors = errors or Errors()
    missing = DROPPED_KEYPOINTS if errors.dropped is None else errors.dropped
    if layout == "panoptic" and replace(errors, dropped=None) != Errors():
        raise ValueError("detector errors are written in the native layout (the Panoptic "
                         "layout's loader makes its own 2D points)")
    if frames < 2 or people < 1 or cameras < 2 or not noise_px >= 0:
        raise ValueError("need frames >= 2, people >= 1, cameras >= 2, noise_px >= 0")
    rng = np.random.default_rng(seed)
    up = np.array([0.0, -1.0, 0.0])
    names = [f"00_{i:02d}" for i in range(cameras)]
    rig = make_dome(cameras, rng, up, names)
    t_s = np.arange(frames) / fps
    frame_numbers = np.arange(frames, dtype=np.int64) + 100
    wfb = rig.world_from_body()
    kpts, fr, ids = [], [], []
    for pid in range(people):
        body = skeleton_motion(skeleton, t_s, rng)
        body[..., :2] += np.array([1.2 * np.cos(2 * np.pi * pid / people),
                                   1.2 * np.sin(2 * np.pi * pid / people)]) * (people > 1)
        kpts.append(np.einsum("ij,tkj->tki", wfb, body))
        fr.append(frame_numbers)
        ids.append(np.full(frames, pid))
    X = np.concatenate(kpts)
    uv, depth = project_points(X, rig.K, rig.dist, rig.R, rig.t)  # (M,J,C,2)
    if noise_px > 0:
        uv = uv + rng.normal(scale=noise_px, size=uv.shape)
    ok = (depth > 0) & np.all((uv >= 0) & (uv <= rig.wh - 1), axis=-1)
    ok &= rng.uniform(size=ok.shape) >= missing
    uv = np.swapaxes(np.where(ok[..., None], uv, np.nan), 1, 2)  # (M, C, J, 2)
    truth_frame, truth_id = np.concatenate(fr), np.concatenate(ids)
    uv, conf, injected = _detector_errors(uv, rig, skeleton, truth_frame, truth_id, frame_numbers,
                                          errors, np.random.default_rng([seed, 1]))
    return SkeletonScene(rig=rig, frames=frame_numbers, fps=fps, skeleton=skeleton,
                         truth_frame=truth_frame, truth_id=truth_id, kpt_world=X, uv=uv,
                         conf=conf if confidences else None, injected=tuple(injected))


def _detector_errors(uv: F64, rig: Rig, skeleton: str, truth_frame: I64, truth_id: I64,
                     frames: I64, errors: Errors, rng: np.random.Generator
                     ) -> tuple[F64, F64, list[tuple[int, str, int, str, str, str]]]:
    """Inject ``errors`` into keypoints ``uv (M, C, J, 2)``; confidences ``(M, C, J)``."""
    M, C, J = uv.shape[:3]
    uv = uv.copy()
    seen = np.isfinite(uv[..., 0])
    # a clean point's confidence: high, lower for the noisier ones
    conf = np.clip(0.92 - 0.08 * rng.standard_normal((M, C, J)) ** 2
                   + 0.04 * rng.standard_normal((M, C, J)), 0.3, 1.0)
    injected: list[tuple[int, str, int, str, str, str]] = []
    names = rig.names

    def note(m: int, c: int, j: int | str, kind: str, detail: str) -> None:
        injected.append((int(truth_frame[m]), names[c], int(truth_id[m]), str(j), kind, detail))

    gap = _gap_mask(frames, truth_frame, errors.gap)
    seen &= ~gap[:, None, None]
    if errors.single_view:
        sv, chosen = _keep_one_view(seen.any(axis=2), truth_id, errors.single_view, rng)
        seen &= sv[..., None]
        injected += [(-1, "", p, "", "single_view", "detected in one camera only") for p in chosen]
    if errors.swaps:
        joints = SKELETONS[skeleton].joints
        pairs = [(joints.index(a), joints.index("r_" + a[2:])) for a in joints
                 if a.startswith("l_") and "r_" + a[2:] in joints]
        hit = np.argwhere(seen.any(axis=2) & (rng.uniform(size=(M, C)) < errors.swaps))
        for m, c in hit:
            a, b = pairs[int(rng.integers(len(pairs)))]
            if seen[m, c, a] and seen[m, c, b]:
                d = float(np.linalg.norm(uv[m, c, a] - uv[m, c, b]))
                uv[m, c, [a, b]] = uv[m, c, [b, a]]
                note(m, c, f"{a}+{b}", "swapped_joints", f"{joints[a]}<->{joints[b]} {d:.0f} px")
    if errors.outliers:
        hit = seen & (rng.uniform(size=seen.shape) < errors.outliers)
        for m, c, j in np.argwhere(hit):
            W, H = rig.wh[c]
            for _ in range(20):
                ang, r = rng.uniform(0, 2 * np.pi), rng.uniform(100, 300)
                p = uv[m, c, j] + r * np.array([np.cos(ang), np.sin(ang)])
                if 0 <= p[0] <= W - 1 and 0 <= p[1] <= H - 1:
                    uv[m, c, j] = p
                    conf[m, c, j] = rng.uniform(0.2, 0.7)
                    note(m, c, j, "keypoint_outlier", f"{r:.0f} px away")
                    break
    if errors.glitch:
        hit = seen & (rng.uniform(size=seen.shape) < errors.glitch)
        for m, c, j in np.argwhere(hit):
            both = rng.uniform() < 0.3
            uv[m, c, j] = [0.0, 0.0] if both else [0.0, uv[m, c, j, 1]]
            conf[m, c, j] = rng.uniform(0.6, 0.9)
            note(m, c, j, "glitch", "u = v = 0" if both else "u = 0")
    uv = np.where(seen[..., None], uv, np.nan)
    return uv, np.where(seen, conf, np.nan), injected


#: y-down (the skeleton simulator's world) -> z-up (Pose2Sim's): X_zup = Q_ZUP @ X_ydown
Q_ZUP = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])


def to_z_up(sim: SkeletonScene) -> SkeletonScene:
    """The same scene in a z-up world (cameras and truth rotated; images unchanged)."""
    import dataclasses as _dc

    cams = tuple(_dc.replace(c, R=c.R @ Q_ZUP.T) for c in sim.rig.cameras)
    rig = Rig(cams, up=np.array([0.0, 0.0, 1.0]), frame_name="synthetic z-up world")
    return _dc.replace(sim, rig=rig, kpt_world=sim.kpt_world @ Q_ZUP.T)


def write_skeleton_scene(sim: SkeletonScene, out: Path, layout: str) -> None:
    """Write as an input folder of ``layout`` (atomically, by the layout's writer in
    :data:`gt3dkit.io.datasets.LAYOUTS`: native ``cameras.json``, ``keypoints.csv``,
    ``truth_keypoints.csv``; or a CMU Panoptic sequence, whose loader makes the 2D points), with
    ``injected.csv`` (native)."""
    writer = LAYOUTS[layout].write_keypoints if layout in LAYOUTS else None
    if writer is None:
        raise ValueError(f"unknown layout {layout!r}")

    def write(tmp: Path) -> None:
        writer(sim, tmp)
        if layout == "native":
            _write_injected(sim.injected, tmp / "injected.csv")

    write_dir_atomically(Path(out), write)


def write_openpose(sim: SkeletonScene, out: Path, seed: int = 0,
                   folder_names: list[str] | None = None) -> None:
    """Write as a Pose2Sim/OpenPose trial (atomically; :func:`gt3dkit.io.datasets.openpose.write`)
    with ``injected.csv``. ``sim`` must be in a z-up world (:func:`to_z_up`) and a detector
    skeleton (body25, ...)."""

    def write(tmp: Path) -> None:
        openpose.write(sim, tmp, seed, folder_names)
        _write_injected(sim.injected, tmp / "injected.csv")

    write_dir_atomically(Path(out), write)


def write_coco(sim: SkeletonScene, out: Path, track_ids: bool = True, seed: int = 0) -> None:
    """Write as ``coco/<camera>.json`` + ``cameras.json`` + ``truth_keypoints.csv`` (atomically;
    :func:`gt3dkit.io.datasets.tasks.write_coco`)."""
    write_dir_atomically(Path(out), lambda tmp: tasks.write_coco(sim, tmp, track_ids, seed))

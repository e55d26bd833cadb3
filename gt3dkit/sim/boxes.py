"""Scenes of people as ellipsoids annotated by boxes (:func:`simulate`), their paths and id
errors, written in any box layout (:func:`write_scene`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gt3dkit.calib.formats.grid import LAYOUTS as GRID_LAYOUTS
from gt3dkit.geom.camera import Cams
from gt3dkit.geom.conics import covered_fraction, model_boxes
from gt3dkit.io.atomic import write_dir_atomically
from gt3dkit.io.datasets import LAYOUTS
from gt3dkit.io.datasets.wildtrack import write_truth_csv
from gt3dkit.sim.common import (
    DROPPED_VIEWS,
    POSITION_GRID_M,
    SIM_LAYOUTS,
    WRITE_LAYOUTS,
    Errors,
    gap_mask,
    keep_one_view,
    look_at,
    with_lens,
    write_injected,
)
from gt3dkit.types import BOX_EDGES, BOX_MODELS, F64, I64, Camera, Rig, SimScene


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
        R, t = look_at(pos, target)
        f = rng.uniform(900, 1200)
        K = np.array([[f, 0, 960 + rng.uniform(-20, 20)], [0, f, 540 + rng.uniform(-20, 20)],
                      [0, 0, 1]])
        dist = np.array([rng.uniform(-0.08, -0.02), rng.uniform(0.0, 0.03),
                         rng.uniform(-1e-3, 1e-3), rng.uniform(-1e-3, 1e-3), 0.0])
        cams.append(Camera(names[i], 1920, 1080, K, dist, R, t))
    return Rig(tuple(cams), up=np.array([0.0, 0.0, 1.0]), frame_name="synthetic world (z up)")


#: The room rig (``rig="room"``): a room of this floor (m), its cameras in its top corners at this
#: height (m), looking down at its middle, as the CMC dataset's four cameras do
ROOM_M = (7.7, 3.4)
ROOM_CAMERA_HEIGHT_M = 2.6
ROOM_FPS = 4.0


def make_room_rig(names: list[str], rng: np.random.Generator) -> Rig:
    """Cameras in the top corners of a :data:`ROOM_M` room (the first four corners, then on the
    walls between), each looking down at the room's middle at 0.8 m: people stand in front of
    people in every view. 1920x1080, wide (f 700-800 px), mild distortion."""
    w, d = ROOM_M
    spots = [(0.0, 0.0), (w, 0.0), (w, d), (0.0, d), (w / 2, 0.0), (w / 2, d), (0.0, d / 2), (w, d / 2)]
    cams = []
    for i, name in enumerate(names):
        x, y = spots[i % len(spots)]
        pos = np.array([x, y, ROOM_CAMERA_HEIGHT_M]) + rng.uniform(-0.05, 0.05, 3)
        R, t = look_at(pos, np.array([w / 2, d / 2, 0.8]) + np.r_[rng.uniform(-0.3, 0.3, 2), 0.0])
        f = rng.uniform(700, 800)
        K = np.array([[f, 0, 960 + rng.uniform(-20, 20)], [0, f, 540 + rng.uniform(-20, 20)], [0, 0, 1]])
        dist = np.array([rng.uniform(-0.08, -0.02), rng.uniform(0.0, 0.03), 0.0, 0.0, 0.0])
        cams.append(Camera(name, 1920, 1080, K, dist, R, t))
    return Rig(tuple(cams), up=np.array([0.0, 0.0, 1.0]), frame_name="synthetic room (z up)")


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


def _layout_area(layout: str, cameras: int | None, fps: float | None
                 ) -> tuple[F64, F64, list[str], int, float]:
    """The walking area's corners (m), the cameras' names, the frame step and the frame rate of a
    simulated layout (the native one: ``cameras`` cameras, default 6, at ``fps``, default 10)."""
    if layout == "wildtrack":
        g = GRID_LAYOUTS["wildtrack"]
        return np.array([-1.0, -6.0]), np.array([7.0, 14.0]), list(g.cameras), 5, g.fps
    if layout == "multiviewx":
        g = GRID_LAYOUTS["multiviewx"]
        return np.array([3.0, 2.0]), np.array([22.0, 14.0]), list(g.cameras), 1, g.fps
    return (np.array([-6.0, -4.0]), np.array([6.0, 4.0]), [f"cam{i}" for i in range(cameras or 6)], 1,
            float(fps or 10.0))


def _paths(rng: np.random.Generator, seed: int, people: int, t_s: F64, frame_numbers: I64,
           area: tuple[F64, F64], motion: str) -> tuple[I64, I64, F64, F64]:
    """Every person's frames, id, centre and semi-axes ``(M, 3)`` (m): a random first to last
    frame along a smooth path (or ``walk`` / ``stop-and-turn``), one size each."""
    lo, hi = area
    frames = len(frame_numbers)
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
    return np.array(rows_f), np.array(rows_id), np.array(centers), np.array(axes)


def simulate(layout: str = "native", seed: int = 0, frames: int = 40, people: int = 10,
             noise_px: float = 0.0, errors: Errors | None = None, motion: str = "smooth",
             cameras: int | None = None, fps: float | None = None, labels: str = "ellipsoid",
             lens: str = "pinhole", rig: str = "ring") -> SimScene:
    """Generate a seeded scene. See the module docstring.

    ``motion``: ``smooth`` paths, ``walk`` (speed and turn rate wander) or ``stop-and-turn``
    (:func:`_stop_and_turn`). ``labels``: the box model that draws the boxes
    (:data:`gt3dkit.types.BOX_MODELS`): ``ellipsoid`` (each box the tangent box of the person's
    ellipsoid, clipped at the image border), or an annotation tool's: ``cylinder`` (an upright
    cylinder's box) or ``pom`` (the occupancy-map rectangle of WILDTRACK's and MultiviewX's labels),
    one radius, placed on a 2.5 cm ground grid and drawn whole, partly outside the image where the
    person is; the truth is the centre on the grid.


    ``cameras`` and ``fps`` set the native layout's camera count (default 6) and frame rate
    (default 10); the WILDTRACK and MultiviewX layouts have their own. ``lens="fisheye"``: wide
    lenses on the same cameras (:func:`gt3dkit.sim.common.with_lens`). ``rig="room"`` (the native
    layout): a crowd in a :data:`ROOM_M` room seen from its top corners (:func:`make_room_rig`; 4
    cameras and :data:`ROOM_FPS` frames per second unless given), where people hide each other.
    """
    _check_arguments(layout, frames, people, noise_px, motion, cameras, fps, labels)
    if rig not in ("ring", "room") or (rig == "room" and layout != "native"):
        raise ValueError(f"rig must be ring, or room with the native layout; got {rig!r} with {layout!r}")
    errors = errors or Errors()
    dropout = DROPPED_VIEWS if errors.dropped is None else errors.dropped
    rng = np.random.default_rng(seed)
    err_rng = np.random.default_rng([seed, 1])
    if rig == "room":
        lo, hi = np.full(2, 0.3), np.array(ROOM_M) - 0.3  # the walls kept off
        names, step, fps = [f"cam{i + 1}" for i in range(cameras or 4)], 1, float(fps or ROOM_FPS)
        cams_rig = make_room_rig(names, rng)
    else:
        lo, hi, names, step, fps = _layout_area(layout, cameras, fps)
        cams_rig = make_rig(len(names), lo, hi, names, rng)
    the_rig = with_lens(cams_rig, lens, seed)
    frame_numbers = np.arange(frames, dtype=np.int64) * step + (1 if layout == "multiviewx" else 0)
    truth_frame, truth_id, center, semi = _paths(rng, seed, people, frame_numbers / fps, frame_numbers,
                                                 (lo, hi), motion)
    if rig == "room":  # no one walks through a wall
        center[:, :2] = np.clip(center[:, :2], lo, hi)
    cams = Cams.of(the_rig, labels)
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
    injected: list[tuple[int, str, int, str, str, str]] = []
    if errors.time_offset is not None:
        injected.append(_time_offset(errors.time_offset, box, seen, inside, (truth_frame, truth_id),
                                     frame_numbers, the_rig))
    if errors.hide_covered is not None or errors.missing:  # everyone in the picture hides, annotated or not
        injected += _hidden(errors, seen, box, inside, center, (truth_frame, truth_id), cams, the_rig,
                            err_rng)
    seen &= ~gap_mask(frame_numbers, truth_frame, errors.gap)[:, None]
    if errors.single_view:
        seen, chosen = keep_one_view(seen, truth_id, errors.single_view, err_rng)
        injected += [(-1, "", p, "", "single_view", "annotated in one camera only")
                     for p in chosen]
    if errors.cut_by_nearer:
        box, more = _cut_by_nearer(box, seen, center, (truth_frame, truth_id), the_rig)
        injected += more
    if errors.shifted:
        box, more = _shifted(errors.shifted, seen, box, cams, (truth_frame, truth_id), the_rig, err_rng)
        injected += more
    box = np.where(seen[..., None], box, np.nan)
    if errors.reused_ids or errors.exchanged_ids:
        keep, truth_id, more = _id_errors(truth_frame, truth_id, seen, errors, err_rng)
        injected += more
        truth_frame, truth_id = truth_frame[keep], truth_id[keep]
        center, semi, box = center[keep], semi[keep], box[keep]
    return SimScene(rig=the_rig, frames=frame_numbers, fps=fps, truth_frame=truth_frame,
                    truth_id=truth_id, center_world=center, semi_axes=semi, boxes=box,
                    injected=tuple(injected))


def _check_arguments(layout: str, frames: int, people: int, noise_px: float, motion: str,
                     cameras: int | None, fps: float | None, labels: str) -> None:
    """ValueError naming the first of :func:`simulate`'s arguments out of its range."""
    if layout not in SIM_LAYOUTS:
        raise ValueError(f"unknown layout {layout!r} (known: {', '.join(SIM_LAYOUTS)})")
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


def _time_offset(offset: tuple[int, int], box: F64, seen: np.ndarray, inside: np.ndarray,
                 truth: tuple[I64, I64], frame_numbers: I64, rig: Rig) -> tuple[int, str, int, str, str, str]:
    """Camera ``offset[0]``'s boxes ``box (M, C, 4)`` show each person ``offset[1]`` frame steps
    later than labelled (``box`` and ``seen (M, C)`` changed in place); the injected-error row."""
    truth_frame, truth_id = truth
    c, k = offset
    if not 0 <= c < len(rig.cameras):
        raise ValueError(f"time_offset camera {c} not in 0..{len(rig.cameras) - 1}")
    at = {(int(f), int(i)): m for m, (f, i) in enumerate(zip(truth_frame, truth_id, strict=True))}
    step = int(frame_numbers[1] - frame_numbers[0])
    src = np.array([at.get((int(f) + k * step, int(i)), -1) for f, i in
                    zip(truth_frame, truth_id, strict=True)])
    box[:, c] = np.where((src >= 0)[:, None], box[np.maximum(src, 0), c], np.nan)
    seen[:, c] &= (src >= 0) & inside[np.maximum(src, 0), c]
    return (int(frame_numbers[0]), rig.cameras[c].name, -1, "", "time_offset", f"{k:+d} frames")


def _hidden(errors: Errors, seen: np.ndarray, box: F64, inside: np.ndarray, center: F64,
            truth: tuple[I64, I64], cams: Cams, rig: Rig, err_rng: np.random.Generator
            ) -> list[tuple[int, str, int, str, str, str]]:
    """Boxes covered by nearer people's beyond ``errors.hide_covered`` left out, and a fraction
    ``errors.missing`` of those in plain sight (``seen (M, C)`` changed in place); the
    injected-error rows of the latter."""
    truth_frame, truth_id = truth
    W, H = cams.wh[:, 0], cams.wh[:, 1]
    injected: list[tuple[int, str, int, str, str, str]] = []
    centres = np.stack([c.center_world for c in rig.cameras])
    depth = np.linalg.norm(center[:, None, :] - centres[None], axis=-1)  # (M, C)
    hide_covered = errors.hide_covered
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
    return injected


#: A nearer box cuts a side it covers across this share of the side's length (the bottom across
#: the box's width, a side across its height), and the box keeps at least this share of its size.
CUT_COVER, CUT_KEEP = 0.6, 0.3


def _cut_by_nearer(box: F64, seen: np.ndarray, center: F64, truth: tuple[I64, I64], rig: Rig,
                   nearer_m: float = 0.3) -> tuple[F64, list[tuple[int, str, int, str, str, str]]]:
    """Each seen box ``box (M, C, 4)`` drawn around the visible part of its person: a side a
    nearer person's box covers (the bottom across :data:`CUT_COVER` of the width, the left or right
    side across that share of the height) ends where the nearer box begins; a box cut to less
    than :data:`CUT_KEEP` of its width or height (hidden from both sides) is drawn whole. People
    hidden by others count whether annotated or not. Returns the boxes and an injected-error row
    per cut box."""
    truth_frame, truth_id = truth
    out = box.copy()
    injected: list[tuple[int, str, int, str, str, str]] = []
    centres = np.stack([c.center_world for c in rig.cameras])
    depth = np.linalg.norm(center[:, None, :] - centres[None], axis=-1)  # (M, C)
    order = np.argsort(truth_frame, kind="stable")
    bounds = np.flatnonzero(np.r_[True, np.diff(truth_frame[order]) != 0, True])
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        m = np.sort(order[lo:hi])
        bm = box[m]  # (n, C, 4)
        b, o = bm[:, None], bm[None, :]  # [i, k, c, 4]: person i's box, nearer k's
        w, h = b[..., 2] - b[..., 0], b[..., 3] - b[..., 1]
        with np.errstate(invalid="ignore"):
            near = (depth[m][None, :] <= depth[m][:, None] - nearer_m) & np.isfinite(o).all(axis=-1)
            near &= ~np.eye(len(m), dtype=bool)[..., None]
            over_x = np.minimum(b[..., 2], o[..., 2]) - np.maximum(b[..., 0], o[..., 0])
            over_y = np.minimum(b[..., 3], o[..., 3]) - np.maximum(b[..., 1], o[..., 1])
            legs = near & (over_x >= CUT_COVER * w) & (b[..., 1] + CUT_KEEP * h < o[..., 1]) \
                & (o[..., 1] < b[..., 3])  # the legs behind the nearer one
            side = near & (over_y >= CUT_COVER * h)
            left = side & (o[..., 0] <= b[..., 0]) & (b[..., 0] < o[..., 2]) \
                & (o[..., 2] < b[..., 2] - CUT_KEEP * w)  # the left side behind it
            right = side & (b[..., 0] + CUT_KEEP * w < o[..., 0]) & (o[..., 0] < b[..., 2]) \
                & (b[..., 2] <= o[..., 2])  # the right side behind it
        new = bm.copy()
        new[..., 3] = np.minimum(new[..., 3], np.where(legs, o[..., 1], np.inf).min(axis=1))
        new[..., 0] = np.maximum(new[..., 0], np.where(left, o[..., 2], -np.inf).max(axis=1))
        new[..., 2] = np.minimum(new[..., 2], np.where(right, o[..., 0], np.inf).min(axis=1))
        with np.errstate(invalid="ignore"):
            ok = (new[..., 2] - new[..., 0] >= CUT_KEEP * (bm[..., 2] - bm[..., 0])) \
                & (new[..., 3] - new[..., 1] >= CUT_KEEP * (bm[..., 3] - bm[..., 1]))
        changed = seen[m] & ok & (new != bm).any(axis=-1) & np.isfinite(bm).all(axis=-1)
        for i, c in zip(*np.nonzero(changed), strict=True):
            out[m[i], c] = new[i, c]
            sides = ", ".join(n for n, a, z in zip(BOX_EDGES, bm[i, c], new[i, c], strict=True) if a != z)
            injected.append((int(truth_frame[m[i]]), rig.cameras[c].name, int(truth_id[m[i]]), "",
                             "cut_box", f"{sides} cut by a nearer person"))
    return out, injected


def _shifted(fraction: float, seen: np.ndarray, box: F64, cams: Cams, truth: tuple[I64, I64], rig: Rig,
             err_rng: np.random.Generator) -> tuple[F64, list[tuple[int, str, int, str, str, str]]]:
    """A ``fraction`` of the seen boxes moved by 0.3-1.0 of their size (mostly sideways) where
    they stay inside the image; the boxes and the injected-error rows."""
    truth_frame, truth_id = truth
    injected: list[tuple[int, str, int, str, str, str]] = []
    hit = seen & (err_rng.uniform(size=seen.shape) < fraction)
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
    return box, injected


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
    if writer is None:
        raise ValueError(f"the {layout} layout has no writer of box scenes")

    def write(tmp: Path) -> None:
        write_truth_csv(sim, tmp / "truth.csv")
        write_injected(sim.injected, tmp / "injected.csv")
        writer(sim, tmp, id_seed)

    write_dir_atomically(Path(out), write)

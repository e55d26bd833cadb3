"""Scenes of people as skeletons seen by a dome of cameras (:func:`simulate_skeletons`), with a
detector's errors, written as keypoint files (:func:`write_skeleton_scene`, OpenPose, COCO)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from gt3dkit.geom.camera import project_points
from gt3dkit.io.atomic import write_dir_atomically
from gt3dkit.io.datasets import LAYOUTS, openpose, tasks
from gt3dkit.io.skeletonfile import named_skeleton
from gt3dkit.sim.common import DROPPED_KEYPOINTS, Errors, gap_mask, keep_one_view, with_lens, write_injected
from gt3dkit.skeletons import BODY_JOINTS, SKELETONS, Skeleton
from gt3dkit.types import F64, I64, Camera, Rig, SkeletonScene


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


def skeleton_motion(skeleton: str | Skeleton, t_s: F64, rng: np.random.Generator) -> F64:
    """(T, J, 3) body-frame joints of one person: canonical pose scaled, limbs swinging
    about their parent joints (bone lengths exact), turning and walking slowly. A skeleton a file
    describes (:func:`gt3dkit.io.skeletonfile.read_skeleton`, its ``[pose]`` given) moves as
    :func:`any_motion` moves it."""
    skel = skeleton if isinstance(skeleton, Skeleton) else SKELETONS[skeleton]
    if SKELETONS.get(skel.name) != skel:
        return any_motion(skel, t_s, rng)
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
            hand = _carried(skel, kids[1])
            if hand:  # a hand's points go with its wrist (both turns), each finger curling
                local = _curled(skel, hand, base, t_s, rng)  # (T, K, 3) at rest
                moved = o + np.einsum("tij,tkj->tki", Rt, local - o)
                P[:, hand] = P[:, mid, None] + np.einsum("tij,tkj->tki", R2, moved - P[:, mid, None])
    yaw = rng.uniform(0, 2 * np.pi) + rng.uniform(-0.4, 0.4) * np.sin(0.5 * t_s)
    Rz = _rot(np.array([0.0, 0.0, 1.0]), yaw)
    root_xy = rng.uniform(-0.8, 0.8, 2) + np.stack([0.3 * np.sin(0.4 * t_s + rng.uniform(0, 6)),
                                                     0.3 * np.cos(0.3 * t_s)], -1)
    P = np.einsum("tij,tkj->tki", Rz, P)
    P[..., :2] += root_xy[:, None, :]
    return P


def _carried(skel: Skeleton, end: str) -> list[int]:
    """The joints a chain's ``end`` carries: those its bones reach without passing a joint of the
    standing body (a hand's points from its wrist; none for the body skeletons)."""
    ix = {n: i for i, n in enumerate(skel.joints)}
    if end not in ix:
        return []
    out, todo = [], [ix[end]]
    while todo:
        j = todo.pop()
        for a, b in skel.bones:
            k = b if a == j else a if b == j else -1
            if k >= 0 and k not in out and skel.joints[k] not in BODY_JOINTS:
                out.append(int(k))
                todo.append(int(k))
    return out


def _curled(skel: Skeleton, hand: list[int], base: F64, t_s: F64, rng: np.random.Generator) -> F64:
    """(T, K, 3) the ``hand`` joints at rest, each finger's outer joints curling about its first
    (the bone tree from the hand's root: every joint turns the joints beyond it)."""
    T = len(t_s)
    P = np.repeat(base[None, hand], T, axis=0)
    pos = {j: k for k, j in enumerate(hand)}
    parent: dict[int, int] = {}
    for a, b in skel.bones:
        if a in pos and b in pos:
            parent.setdefault(b, a)
    lat = np.array([0.0, 1.0, 0.0])
    w, phase = rng.uniform(1.0, 2.5), rng.uniform(0, 2 * np.pi)
    for j in hand:  # the bones in the file's order: outwards along each finger
        p = parent.get(j)
        if p is None or parent.get(p) is None:
            continue
        beyond = [pos[j]] + [pos[k] for k in hand if _above(parent, k, j)]
        R = _rot(lat, 0.25 * (1 + np.sin(w * t_s + phase)))
        o = P[:, pos[p], None]
        P[:, beyond] = o + np.einsum("tij,tkj->tki", R, P[:, beyond] - o)
    return P


def _above(parent: dict[int, int], k: int, j: int) -> bool:
    """Whether ``j`` is among ``k``'s ancestors."""
    while k in parent:
        k = parent[k]
        if k == j:
            return True
    return False


def any_motion(skel: Skeleton, t_s: F64, rng: np.random.Generator) -> F64:
    """(T, J, 3) body-frame joints of any skeleton with a canonical ``pose`` (an animal, a hand):
    the pose scaled, every bone swinging about its parent joint (the bones from the first joint
    outwards, each turning its part of the skeleton: bone lengths exact) but within a rigid group
    (``Skeleton.groups``: held rigid where its joints hang together in the bone tree), the body
    turning and moving slowly over the floor."""
    if not skel.pose:
        raise ValueError(f"skeleton {skel.name}: a [pose] (each joint's place, m) is needed to simulate it")
    base = skel.canonical() * rng.uniform(0.9, 1.1)
    T, J = len(t_s), skel.n_joints
    P = np.repeat(base[None], T, axis=0)
    parent = np.full(J, -1)
    order, seen = [0], {0}
    for j in order:  # breadth first over the bones
        for a, b in skel.bones:
            k = b if a == j else a if b == j else -1
            if k >= 0 and k not in seen:
                parent[k] = j
                seen.add(k)
                order.append(int(k))
    child_of = {j: [k for k in range(J) if parent[k] == j] for j in range(J)}

    def part(j: int) -> list[int]:
        out, todo = [], [j]
        while todo:
            k = todo.pop()
            out.append(k)
            todo += child_of[k]
        return out

    size = float(np.ptp(base, axis=0).max()) or 1.0
    group_of = {j: k for k, g in enumerate(skel.groups) for j in g}
    for j in order[1:]:
        p = parent[j]
        if skel.joints[j] in group_of and group_of.get(skel.joints[j]) == group_of.get(skel.joints[p]):
            continue  # a rigid group's joints do not turn about each other
        bone = base[j] - base[p]
        axis = np.cross(bone, rng.normal(size=3))
        axis /= np.linalg.norm(axis) or 1.0
        swing = rng.uniform(0.1, 0.3) * np.sin(rng.uniform(1.0, 3.0) * t_s + rng.uniform(0, 2 * np.pi))
        R = _rot(axis, swing)
        sub = part(j)
        P[:, sub] = P[:, p, None] + np.einsum("tij,tkj->tki", R, P[:, sub] - P[:, p, None])
    yaw = rng.uniform(0, 2 * np.pi) + rng.uniform(-0.4, 0.4) * np.sin(0.5 * t_s)
    P = np.einsum("tij,tkj->tki", _rot(np.array([0.0, 0.0, 1.0]), yaw), P)
    P[..., :2] += 2 * size * np.stack([np.sin(0.4 * t_s + rng.uniform(0, 6)), np.cos(0.3 * t_s)], -1)[:, None]
    return P


def simulate_skeletons(layout: str = "native", seed: int = 0, frames: int = 30, people: int = 3,
                       noise_px: float = 0.0, cameras: int = 10,
                       skeleton: str = "coco19", fps: float = 30.0, errors: Errors | None = None,
                       confidences: bool = False, lens: str = "pinhole", late_frames: F64 | None = None,
                       camera_fps: F64 | None = None) -> SkeletonScene:
    """People as moving skeletons seen by a dome of HD cameras, in a y-down world.

    2D points are exact projections (with distortion) plus ``noise_px`` Gaussian noise;
    points behind a camera or outside its image are dropped, and a fraction
    ``Errors.dropped`` of the rest at random. ``errors`` (native layout) adds detector errors;
    ``confidences`` writes a detector-like confidence per point (lower for worse points).
    ``lens="fisheye"``: wide lenses on the same cameras (:func:`gt3dkit.sim.common.with_lens`).
    Unsynchronised cameras (:mod:`gt3dkit.io.clocks`): camera ``c`` late by ``late_frames[c]``
    frames and recording at ``camera_fps[c]`` frames per second (a rate a little off ``fps`` is a
    clock's drift) shows at its frame ``g`` the people at the scene's frame ``g fps / fps_c -
    late_c`` (their exact motion then, not an interpolation); the truth is on the scene's clock.
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
    skel = named_skeleton(skeleton)  # a built-in, or a skeleton file (with its [pose])
    custom = SKELETONS.get(skel.name) != skel
    rng = np.random.default_rng(seed)
    up = np.array([0.0, -1.0, 0.0])
    names = [f"00_{i:02d}" for i in range(cameras)]
    rig = with_lens(make_dome(cameras, rng, up, names), lens, seed)
    frame_numbers = np.arange(frames, dtype=np.int64) + 100
    late = np.zeros(cameras) if late_frames is None else np.asarray(late_frames, dtype=np.float64)
    rate = np.full(cameras, fps) if camera_fps is None else np.asarray(camera_fps, dtype=np.float64)
    if late.shape != (cameras,) or rate.shape != (cameras,) or not np.all(rate > 0):
        raise ValueError(f"late_frames and camera_fps need one value per camera ({cameras}), fps > 0")
    # the scene's clock, then each camera's: seconds since the first frame
    t_s = np.concatenate([np.arange(frames) / fps] + [
        (frame_numbers * (fps / r) - frame_numbers[0] - late[c]) / fps for c, r in enumerate(rate)])
    wfb = rig.world_from_body()
    kpts, fr, ids = [], [], []
    for pid in range(people):
        body = skeleton_motion(skel, t_s, rng)
        body[..., :2] += np.array([1.2 * np.cos(2 * np.pi * pid / people),
                                   1.2 * np.sin(2 * np.pi * pid / people)]) * (people > 1)
        kpts.append(np.einsum("ij,tkj->tki", wfb, body).reshape(cameras + 1, frames, -1, 3))
        fr.append(frame_numbers)
        ids.append(np.full(frames, pid))
    both = np.concatenate(kpts, axis=1)  # (1 + C, M, J, 3): the truth, then as each camera sees it
    X = both[0]
    seen = [project_points(both[1 + c], rig.K[c:c + 1], rig.dist[c:c + 1], rig.R[c:c + 1], rig.t[c:c + 1])
            for c in range(cameras)]
    uv = np.concatenate([u for u, _ in seen], axis=2)  # (M, J, C, 2)
    depth = np.concatenate([d for _, d in seen], axis=2)
    if noise_px > 0:
        uv = uv + rng.normal(scale=noise_px, size=uv.shape)
    ok = (depth > 0) & np.all((uv >= 0) & (uv <= rig.wh - 1), axis=-1)
    ok &= rng.uniform(size=ok.shape) >= missing
    uv = np.swapaxes(np.where(ok[..., None], uv, np.nan), 1, 2)  # (M, C, J, 2)
    truth_frame, truth_id = np.concatenate(fr), np.concatenate(ids)
    uv, conf, injected = detector_errors(uv, rig, skel, truth_frame, truth_id, frame_numbers,
                                          errors, np.random.default_rng([seed, 1]),
                                          np.swapaxes(depth, 1, 2), noise_px)
    return SkeletonScene(rig=rig, frames=frame_numbers, fps=fps, skeleton=skel.name,
                         skeleton_doc=skel.doc() if custom else None,
                         truth_frame=truth_frame, truth_id=truth_id, kpt_world=X, uv=uv,
                         conf=conf if confidences else None, injected=tuple(injected))


def detector_errors(uv: F64, rig: Rig, skeleton: str | Skeleton, truth_frame: I64, truth_id: I64,
                     frames: I64, errors: Errors, rng: np.random.Generator,
                     depth_m: F64 | None = None, noise_px: float = 0.0
                     ) -> tuple[F64, F64, list[tuple[int, str, int, str, str, str]]]:
    """Inject ``errors`` into keypoints ``uv (M, C, J, 2)``; confidences ``(M, C, J)``.
    ``depth_m (M, C, J)``: each point's depth in its camera (occlusion needs it); ``noise_px``:
    the pixel noise already in ``uv`` (scaled by confidence with ``noise_by_confidence``)."""
    M, C, J = uv.shape[:3]
    uv = uv.copy()
    seen = np.isfinite(uv[..., 0])
    # a clean point's confidence: high, lower for the noisier ones
    conf = np.clip(0.92 - 0.08 * rng.standard_normal((M, C, J)) ** 2
                   + 0.04 * rng.standard_normal((M, C, J)), 0.3, 1.0)
    injected: list[tuple[int, str, int, str, str, str]] = []
    names = rig.names

    def note(m: int, c: int, j: int | np.integer | str, kind: str, detail: str) -> None:
        injected.append((int(truth_frame[m]), names[c], int(truth_id[m]), str(j), kind, detail))

    gap = gap_mask(frames, truth_frame, errors.gap)
    seen &= ~gap[:, None, None]
    if errors.single_view:
        sv, chosen = keep_one_view(np.asarray(seen.any(axis=2)), truth_id, errors.single_view, rng)
        seen &= sv[..., None]
        injected += [(-1, "", p, "", "single_view", "detected in one camera only") for p in chosen]
    if errors.swaps:
        skel = skeleton if isinstance(skeleton, Skeleton) else SKELETONS[skeleton]
        joints = skel.joints
        pairs = [(joints.index(a), joints.index(b)) for a, b in skel.left_right]
        swapped = np.argwhere(seen.any(axis=2) & (rng.uniform(size=(M, C)) < errors.swaps))
        for m, c in swapped:
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
    if errors.occluded or errors.wrong_person or errors.over_one or errors.noise_by_confidence:
        _view_errors(uv, conf, seen, truth_frame, errors, rng, depth_m, noise_px, note)
    uv = np.where(seen[..., None], uv, np.nan)
    return uv, np.where(seen, conf, np.nan), injected


def _view_errors(uv: F64, conf: F64, seen: np.ndarray, truth_frame: I64, errors: Errors,
                 rng: np.random.Generator, depth_m: F64 | None, noise_px: float,
                 note: Callable[[int, int, int | np.integer | str, str, str], None]) -> None:
    """The errors of a detector that sees several people in a view (in place): joints hidden
    behind a nearer person guessed, joints taken from another person, confidences above 1, noise
    that grows as the confidence falls (:class:`Errors`)."""
    M, C, J = seen.shape
    clean = seen & (conf >= 0.3)
    if errors.noise_by_confidence and noise_px > 0:
        extra = noise_px * np.sqrt(np.maximum((0.92 / conf) ** 3 - 1.0, 0.0))
        uv += rng.standard_normal(uv.shape) * np.where(clean, extra, 0.0)[..., None]
    if errors.occluded or errors.wrong_person:
        if errors.occluded and depth_m is None:
            raise ValueError("occluded needs each point's depth")
        for f in np.unique(truth_frame):
            rows = np.flatnonzero(truth_frame == f)
            for c in range(C):
                _frame_view(uv, conf, seen, rows, c, errors, rng, depth_m, note)
    if errors.over_one:
        hit = seen & (conf > 0.9) & (rng.uniform(size=seen.shape) < errors.over_one)
        conf[hit] = rng.uniform(1.0, 1.04, size=int(hit.sum()))
        for m, c, j in np.argwhere(hit):
            note(m, c, j, "confidence_above_1", f"{conf[m, c, j]:.3f}")


def _frame_view(uv: F64, conf: F64, seen: np.ndarray, rows: I64, c: int, errors: Errors,
                rng: np.random.Generator, depth_m: F64 | None,
                note: Callable[[int, int, int | np.integer | str, str, str], None]) -> None:
    """:func:`_view_errors`' occlusion and wrong-person joints of one frame's ``rows`` in camera ``c``."""
    here = [m for m in rows if seen[m, c].sum() >= 3]
    for m in here:
        for n in here:
            if n == m:
                continue
            pts = uv[n, c][seen[n, c]]
            lo, hi = pts.min(axis=0) - 10.0, pts.max(axis=0) + 10.0
            if errors.occluded and depth_m is not None and (
                    np.nanmedian(depth_m[n, c]) < np.nanmedian(depth_m[m, c]) - 0.3):
                inside = seen[m, c] & np.all((uv[m, c] >= lo) & (uv[m, c] <= hi), axis=1)
                for j in np.flatnonzero(inside & (rng.uniform(size=len(inside)) < errors.occluded)):
                    r, ang = rng.uniform(8.0, 25.0), rng.uniform(0, 2 * np.pi)
                    uv[m, c, j] += r * np.array([np.cos(ang), np.sin(ang)])
                    conf[m, c, j] = rng.uniform(0.1, 0.5)
                    note(m, c, j, "occluded_joint", f"behind a nearer person: moved {r:.0f} px")
        if errors.wrong_person:
            others = [n for n in here if n != m]
            for j in np.flatnonzero(seen[m, c] & (rng.uniform(size=seen.shape[2]) < errors.wrong_person)):
                cand = [(float(np.linalg.norm(uv[n, c, j] - uv[m, c, j])), n) for n in others
                        if seen[n, c, j]]
                cand = [(d, n) for d, n in cand if d <= 300.0]
                if cand:
                    d, n = min(cand)
                    uv[m, c, j] = uv[n, c, j] + rng.normal(scale=1.0, size=2)
                    conf[m, c, j] = rng.uniform(0.4, 0.8)
                    note(m, c, j, "wrong_person_joint", f"another person's, {d:.0f} px away")


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
            write_injected(sim.injected, tmp / "injected.csv")

    write_dir_atomically(Path(out), write)


def write_openpose(sim: SkeletonScene, out: Path, seed: int = 0,
                   folder_names: list[str] | None = None) -> None:
    """Write as a Pose2Sim/OpenPose trial (atomically; :func:`gt3dkit.io.datasets.openpose.write`)
    with ``injected.csv``. ``sim`` must be in a z-up world (:func:`to_z_up`) and a detector
    skeleton (body25, ...)."""

    def write(tmp: Path) -> None:
        openpose.write(sim, tmp, seed, folder_names)
        write_injected(sim.injected, tmp / "injected.csv")

    write_dir_atomically(Path(out), write)


def write_coco(sim: SkeletonScene, out: Path, track_ids: bool = True, seed: int = 0) -> None:
    """Write as ``coco/<camera>.json`` + ``cameras.json`` + ``truth_keypoints.csv`` (atomically;
    :func:`gt3dkit.io.datasets.tasks.write_coco`)."""
    write_dir_atomically(Path(out), lambda tmp: tasks.write_coco(sim, tmp, track_ids, seed))

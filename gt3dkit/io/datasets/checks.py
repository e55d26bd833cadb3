"""Checks every loaded scene goes through, whatever its layout (:func:`gt3dkit.api.load_scene` runs them).

Errors (:class:`InputError`, naming the file and entry): coordinates no image can hold.
Odd but valid input is kept or dropped as said here, with one ``warning:`` line per kind
(with counts) in ``Scene.warnings``:

* a box entirely outside its camera's image cannot have been drawn on it: dropped;
* a keypoint further than :data:`KPT_OFF_IMAGE` image sizes outside the image: dropped;
* a keypoint, or a box with an edge, beyond where its camera's lens model turns back
  (:attr:`~gt3dkit.rig.Camera.valid_radius_px`): dropped, counted per camera;
* objects only ever seen by one camera: kept (their distance comes from the size prior
  alone, so expect errors of metres; their standard deviations say so);
* a rig of one camera: every object is such an object;
* gaps longer than :data:`GAP_S` seconds (and than one step of the scene's annotated frames)
  in an object's annotations: kept (no rows there; ``--every-frame`` writes the motion
  model's interpolation, with a growing standard deviation).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gt3dkit.arrays import unique_rows
from gt3dkit.errors import InputError
from gt3dkit.types import Camera, Observations, Scene

#: A coordinate more than this many image sizes outside the image is an error, not a label.
FAR_IMAGES = 10.0
#: Keypoints further outside the image than this fraction of its size are dropped.
KPT_OFF_IMAGE = 0.1
#: Annotation gaps (seconds) longer than this are reported.
GAP_S = 1.0


def check_pixels(where: str, cam: Camera, xy: list[float], what: str) -> None:
    """Raise :class:`InputError` for pixel coordinates (x, y, x, y, ...) no image of ``cam``
    can hold: more than :data:`FAR_IMAGES` image sizes outside it."""
    for i, v in enumerate(xy):
        size = cam.width if i % 2 == 0 else cam.height
        if not -FAR_IMAGES * size <= v <= (1 + FAR_IMAGES) * size:
            raise InputError(where, f"{what} coordinate {v:g} far outside the {cam.width}x"
                                    f"{cam.height} image of camera {cam.name} (more than "
                                    f"{FAR_IMAGES:g} image sizes)")


def _ids(ids: np.ndarray, n: int = 5) -> str:
    s = ", ".join(str(int(i)) for i in ids[:n])
    return s + (f", ... ({len(ids)} in all)" if len(ids) > n else "")


def _cameras_per_object(track_id: np.ndarray, cam: np.ndarray) -> dict[int, int]:
    pairs = unique_rows(np.stack([track_id, cam], 1))
    ids, n = np.unique(pairs[:, 0], return_counts=True)
    return dict(zip(ids.tolist(), n.tolist(), strict=True))


def _redundancy(scene: Scene, obs: Observations, explained: tuple[str, ...] = ()) -> list[str]:
    """Warnings where the views cannot check each other: calibrated cameras without a single
    annotation (an empty camera folder), and keypoints no more than two views ever see at once
    (two views determine a point, none is left over to tell a wrong one from a right one)."""
    out = []
    names = scene.rig.names
    empty = [names[c] for c in range(len(names)) if not np.any(obs.cam == c) and names[c] not in explained]
    if empty and len(empty) < len(names):
        out.append(f"camera{'s' if len(empty) > 1 else ''} {', '.join(empty[:5])}"
                   f"{' ...' if len(empty) > 5 else ''} ha{'ve' if len(empty) > 1 else 's'} no annotation "
                   f"(of {len(names)} calibrated): the estimate comes from the other "
                   f"{len(names) - len(empty)}")
    kpt = np.isfinite(obs.kpt_uv_px[..., 0]).any(axis=1)
    if len(names) > 1 and kpt.any():
        views = unique_rows(np.stack([obs.frame[kpt], obs.track_id[kpt]], 1), return_counts=True)[1]
        if views.max() <= 2:
            out.append("no object is seen by more than two cameras at once: nothing is redundant (a wrong "
                       "keypoint cannot be told from a right one, and a joint only one view shows is left "
                       "out); the sds assume every view is right")
    return out


def _gaps(scene: Scene, obs: Observations) -> list[str]:
    """A warning where an object is unannotated for longer than GAP_S and than one step of the
    scene's frames."""
    pairs = unique_rows(np.stack([obs.track_id, obs.frame], 1))  # sorted by id, frame
    same = pairs[1:, 0] == pairs[:-1, 0]
    steps = np.diff(np.unique(obs.frame))
    step = float(np.median(steps)) if steps.size else 1.0
    gap = np.where(same, np.diff(pairs[:, 1]), 0).astype(np.float64)
    long = (gap / scene.fps > GAP_S) & (gap > 1.5 * step)
    if not long.any():
        return []
    who = np.unique(pairs[1:, 0][long])
    worst = int(np.argmax(np.where(long, gap, 0)))
    return [f"{int(long.sum())} gaps of more than {GAP_S:g} s in the annotations of "
            f"{who.size} objects (ids {_ids(who)}; longest {gap[worst] / scene.fps:.3g} s "
            f"= {int(gap[worst])} frames, object {int(pairs[worst + 1, 0])} after frame "
            f"{int(pairs[worst, 1])}): no rows there (--every-frame interpolates them)"]


def _beyond_lens_model(scene: Scene, obs: Observations) -> tuple[Observations, list[str]]:
    """Keypoints, and boxes with an edge's middle, further from the principal point than the
    camera's lens model is one-to-one (:attr:`Camera.valid_radius_px`): left out and counted."""
    radius = np.array([np.inf if c.valid_radius_px is None else c.valid_radius_px
                       for c in scene.rig.cameras])
    if not np.isfinite(radius).any() or len(obs) == 0:
        return obs, []
    pp = scene.rig.K[obs.cam][:, :2, 2]  # (N, 2)
    lim = radius[obs.cam]
    kpt = obs.kpt_uv_px
    kbad = np.isfinite(kpt[..., 0]) & (np.hypot(kpt[..., 0] - pp[:, None, 0], kpt[..., 1] - pp[:, None, 1])
                                       > lim[:, None])
    box = obs.box_xyxy_px
    mid = np.stack([np.stack([box[:, 0], (box[:, 1] + box[:, 3]) / 2], -1),
                    np.stack([box[:, 2], (box[:, 1] + box[:, 3]) / 2], -1),
                    np.stack([(box[:, 0] + box[:, 2]) / 2, box[:, 1]], -1),
                    np.stack([(box[:, 0] + box[:, 2]) / 2, box[:, 3]], -1)], axis=1)  # (N, 4, 2)
    with np.errstate(invalid="ignore"):
        bbad = obs.has_box & np.any(np.hypot(mid[..., 0] - pp[:, None, 0], mid[..., 1] - pp[:, None, 1])
                                    > lim[:, None], axis=1)
    if not kbad.any() and not bbad.any():
        return obs, []
    out = []
    for c, cam in enumerate(scene.rig.cameras):
        n_k, n_b = int(kbad[obs.cam == c].sum()), int(bbad[obs.cam == c].sum())
        if n_k or n_b:
            parts = (f"{n_k} keypoints" if n_k else "", f"{n_b} boxes" if n_b else "")
            what = " and ".join(x for x in parts if x)
            out.append(f"camera {cam.name}: {what} lie beyond {cam.valid_radius_px:.0f} px from its "
                       "principal "
                       "point, where its lens model turns back: left out")
    box = np.where(bbad[:, None], np.nan, box)
    kpt = np.where(kbad[..., None], np.nan, kpt)
    conf = None if obs.kpt_conf is None else np.where(kbad, np.nan, obs.kpt_conf)
    keep = np.all(np.isfinite(box), axis=1) | np.isfinite(kpt[..., 0]).any(axis=1)
    return dataclasses.replace(obs, box_xyxy_px=box, kpt_uv_px=kpt, kpt_conf=conf).select(keep), out


def check_scene(scene: Scene, whole: bool = True, identities: bool = True,
                explained: tuple[str, ...] = ()) -> Scene:
    """``scene`` with off-image annotations dropped and its odd-input warnings added; ``whole``:
    the scene is the whole input (else some of its frames: none left is no error); ``identities``:
    its ids name objects across cameras and frames (False: they do not yet, so nothing is dropped
    or warned of by them: objects seen by one camera, gaps, redundancy); ``explained``: cameras
    whose views a warning already says were left out (not said again)."""
    obs, warnings = scene.obs, list(scene.warnings)
    wh = scene.rig.wh[obs.cam]  # (N, 2)

    box = obs.box_xyxy_px
    has_box = obs.has_box
    lo, hi = -FAR_IMAGES * wh, (1 + FAR_IMAGES) * wh
    far = has_box & np.any((box[:, :2] < lo) | (box[:, 2:] > hi), axis=1)
    kpt = obs.kpt_uv_px
    kfar = np.isfinite(kpt[..., 0]) & np.any((kpt < lo[:, None]) | (kpt > hi[:, None]), axis=-1)
    for bad, what in ((far, "box"), (kfar.any(axis=1), "keypoint")):
        if bad.any():
            r = int(np.flatnonzero(bad)[0])
            cam = scene.rig.cameras[int(obs.cam[r])]
            raise InputError(obs.origin[r], f"{what} coordinate far outside the {cam.width}x"
                                            f"{cam.height} image of camera {cam.name} "
                                            f"(more than {FAR_IMAGES:g} image sizes)")

    outside = has_box & ((box[:, 2] < 0) | (box[:, 3] < 0) | (box[:, 0] > wh[:, 0] - 1)
                         | (box[:, 1] > wh[:, 1] - 1))
    margin = KPT_OFF_IMAGE * wh[:, None]
    koff = np.isfinite(kpt[..., 0]) & np.any((kpt < -margin) | (kpt > wh[:, None] - 1 + margin),
                                             axis=-1)
    if outside.any() or koff.any():
        box = np.where(outside[:, None], np.nan, box)
        kpt = np.where(koff[..., None], np.nan, kpt)
        conf = None if obs.kpt_conf is None else np.where(koff, np.nan, obs.kpt_conf)
        if outside.any():
            warnings.append(f"{int(outside.sum())} boxes lie entirely outside their camera's image"
                            f" (first: {obs.origin[int(np.flatnonzero(outside)[0])]}): ignored")
        if koff.any():
            warnings.append(f"{int(koff.sum())} keypoints lie more than {KPT_OFF_IMAGE:.0%} of the "
                            f"image size outside their camera's image (first: "
                            f"{obs.origin[int(np.flatnonzero(koff.any(axis=1))[0])]}): ignored")
        keep = np.all(np.isfinite(box), axis=1) | np.isfinite(kpt[..., 0]).any(axis=1)
        obs = dataclasses.replace(obs, box_xyxy_px=box, kpt_uv_px=kpt, kpt_conf=conf).select(keep)
        if len(obs) == 0 and whole:
            raise InputError(scene.root or "input", "no annotation lies inside its camera's image")

    obs, w = _beyond_lens_model(scene, obs)
    warnings += w
    if len(obs) == 0 and whole:
        raise InputError(scene.root or "input", "no annotation lies where its camera's lens model is valid")
    if not identities:
        return dataclasses.replace(scene, obs=obs, warnings=tuple(warnings))

    n_cams = _cameras_per_object(obs.track_id, obs.cam)
    boxed = set(obs.track_id[obs.has_box].tolist())
    lone_kpt = np.array([i for i, n in n_cams.items() if n == 1 and i not in boxed], dtype=np.int64)
    if lone_kpt.size:
        obs = obs.select(~np.isin(obs.track_id, lone_kpt))
        if len(obs) == 0 and whole:
            seen = sorted({scene.rig.names[int(c)] for c in np.unique(scene.obs.cam)})
            raise InputError(scene.root or "input",
                             f"no object is seen by two cameras (annotations only in camera "
                             f"{', '.join(seen)} of {len(scene.rig.cameras)}): keypoints alone give no "
                             "3D position")
        warnings.append(f"{lone_kpt.size} objects with keypoints only are only ever seen by one "
                        f"camera (ids {_ids(lone_kpt)}): left out, one view gives them no 3D "
                        "position")
    if len(scene.rig.cameras) == 1:
        warnings.append(f"one camera only ({scene.rig.cameras[0].name}): every distance comes from "
                        "the object size prior alone; expect errors of metres")
    else:
        n_cams = _cameras_per_object(obs.track_id, obs.cam)
        lone = np.array([i for i, n in n_cams.items() if n == 1], dtype=np.int64)
        if lone.size:
            warnings.append(f"{lone.size} objects are only ever seen by one camera (ids "
                            f"{_ids(lone)}): their distance comes from the size prior alone "
                            "(expect errors of metres; their sd says so)")

    warnings += _redundancy(scene, obs, explained) + _gaps(scene, obs)
    return dataclasses.replace(scene, obs=obs, warnings=tuple(warnings))

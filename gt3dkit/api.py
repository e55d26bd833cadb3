"""The library entry points the CLI is a thin layer over: loading an input (reading it, the
cross-camera association where its ids are per camera, the checks), reconstructing, reading a
run back with its scene."""

from __future__ import annotations

import dataclasses
import functools
import json
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from gt3dkit.arrays import frame_grid, lookup_rows, unique_rows
from gt3dkit.calib.formats.native import rig_of_doc
from gt3dkit.errors import InputError
from gt3dkit.fusion.base import ESTIMATORS, Estimator, make_estimator, over_time
from gt3dkit.fusion.preparation.associate import Association, apply_association, associate, read_overrides
from gt3dkit.fusion.preparation.boxfit import choose_box_model
from gt3dkit.fusion.preparation.detections import SECOND_DETECTION, associate_detections
from gt3dkit.fusion.preparation.identity import Segments, identity_segments
from gt3dkit.fusion.preparation.pieces import pieces_prepared
from gt3dkit.fusion.preparation.prepare import Prepared, prepare, undetermined_objects
from gt3dkit.fusion.preparation.rows import Rows, build_rows
from gt3dkit.fusion.ukf.bones import BoneSamples
from gt3dkit.geom.camera import Cams
from gt3dkit.io.clocks import CameraClocks, on_one_clock
from gt3dkit.io.datasets import ASSOCIATED, Calibration, checks, index_scene, read_scene
from gt3dkit.io.results import read_result
from gt3dkit.io.writers import ANOMALY_COLUMNS, read_keypoints_csv, read_segments_csv, write_outputs
from gt3dkit.jsondoc import json_at, json_num, json_obj, json_str
from gt3dkit.parse import read_csv_rows
from gt3dkit.qa.anomalies import Anomalies, find_anomalies
from gt3dkit.sim import simulate, simulate_skeletons, write_scene, write_skeleton_scene
from gt3dkit.threads import small_matrix_blas
from gt3dkit.types import (
    BOX_MODELS,
    I64,
    DenseSummary,
    IdentitySummary,
    JsonDict,
    JsonValue,
    OptionValue,
    QASummary,
    Scene,
    TrackSet,
)

__all__ = ["ESTIMATORS", "annotation_qa", "load_run", "load_scene", "make_estimator", "reconstruct"]


def tiny_scenes() -> tuple[Scene, Scene]:
    """The two small scenes of :func:`tiny_scene`: boxes, then joints."""
    return tiny_scene("boxes"), tiny_scene("joints")


@functools.cache
def tiny_scene(kind: str) -> Scene:
    """A small simulated scene, written and read back as any input is: ``"boxes"``, 4 frames of 2
    people boxed by the WILDTRACK rig's 7 cameras (1 px of noise), or ``"joints"``, 3 frames of
    one COCO-19 skeleton seen by 3 cameras. Estimating it compiles, or loads from numba's cache,
    the kernels a run of that kind uses (:mod:`gt3dkit.commands.warmup`, where each kind's
    process makes only its own: simulating the boxes compiles the box models' kernels, 13 s the
    joints' process spent again; :func:`gt3dkit.windows.warm_worker`, a Dask worker's while the
    sequence loads)."""
    with tempfile.TemporaryDirectory() as tmp:
        if kind == "boxes":
            write_scene(simulate("wildtrack", seed=0, frames=4, people=2, noise_px=1.0), Path(tmp) / kind,
                        "wildtrack")
        else:
            write_skeleton_scene(simulate_skeletons("native", seed=0, frames=3, people=1, cameras=3),
                                 Path(tmp) / kind, "native")
        return load_scene(Path(tmp) / kind)


def scene_kind(scene: Scene) -> str:
    """The kind of :func:`tiny_scene` whose kernels a run of ``scene`` uses: ``"joints"`` where it
    has keypoints, else ``"boxes"``."""
    return "joints" if scene.obs.n_joints > 0 else "boxes"


def load_scene(root: Path | str | Scene, layout: str | None = None, skeleton: str | None = None,
               fps: float | None = None, calib: Path | str | Calibration | None = None,
               association: Path | str | None = None, segments: Path | str | None = None,
               box_model: str = "auto", clocks: CameraClocks | JsonDict | None = None,
               **panoptic_options: JsonValue) -> Scene:
    """Load any supported input folder (layout detected when not given): read it
    (:func:`gt3dkit.io.datasets.read_scene`, whose arguments these are), give ids per camera or
    none global identities (:mod:`gt3dkit.fusion.preparation.associate`, with the overrides of the file
    ``association``), then check it (:func:`gt3dkit.io.datasets.checks.check_scene`).
    ``segments``: an edited ``segments.csv`` whose pieces replace the automatic identity splits
    of the ids it lists (:func:`gt3dkit.fusion.preparation.identity.identity_segments`). ``box_model``: how
    the boxes are drawn (:data:`gt3dkit.types.BOX_MODELS`), or ``"auto"``: chosen from them
    (:func:`with_box_model`). ``clocks``: each camera's clock (:mod:`gt3dkit.io.clocks`, or its
    ``doc()``): every view moved onto one clock before the association. ``root`` may be the
    :func:`load_head` of the folder: what it read (``FrameIndex.ahead``) is not read again."""
    ahead = None
    explained: tuple[str, ...] = ()  # cameras a warning names as left out by the association
    if isinstance(root, Scene):
        ahead = root.index.ahead if root.index is not None else None
        root = root.root
    scene = read_scene(root, layout, skeleton, fps, calib, association, span=None, ahead=ahead,
                       **panoptic_options)
    if clocks is not None:
        if not isinstance(clocks, CameraClocks):
            clocks = CameraClocks.from_doc(clocks, "time offsets")
        scene = on_one_clock(scene, clocks)
        scene = dataclasses.replace(scene, load_options={**scene.load_options, "clocks": clocks.doc()})
    if scene.layout in ASSOCIATED:  # ids per camera or none -> global identities, before the checks
        over = read_overrides(Path(association), scene.rig.names) if association is not None else None
        if over:  # a row whose camera has no such id (a track deleted, a drawn shape left out): unused
            pairs = unique_rows(np.c_[scene.obs.cam, scene.obs.track_id])
            have = {(scene.rig.names[int(c)], int(i)) for c, i in pairs}
            unused = [k for k in over if (k[0], k[1]) not in have and k[2] is None]
            if unused:
                over = {k: v for k, v in over.items() if k not in unused}
                scene = dataclasses.replace(scene, warnings=(*scene.warnings, (
                    f"{association}: {len(unused)} rows name an id their camera does not have (first: "
                    f"camera {unused[0][0]}, local id {unused[0][1]}): unused")))
        per_frame = scene.layout == "openpose" or scene.association == "detections"
        assoc = (associate_detections if per_frame else associate)(scene, overrides=over)
        scene = dataclasses.replace(apply_association(scene, assoc), association=assoc)
        twice = sum(1 for r in assoc.rows if r[3] < 0 and r[7] == SECOND_DETECTION)
        out = sum(1 for r in assoc.rows if r[3] < 0) - twice
        if out:
            scene = dataclasses.replace(scene, warnings=(*scene.warnings, f"{out} detections no second view "
                                                         "confirms left out (association.csv, global id -1)"))
        if twice:
            scene = dataclasses.replace(scene, warnings=(*scene.warnings, (
                f"{twice} detections of a person a camera had already detected in that frame left out "
                "(association.csv, global id -1)")))
        named = disagreeing_cameras(assoc)
        explained = tuple(c for c, _ in named)
        scene = dataclasses.replace(scene, warnings=(*scene.warnings, *(w for _, w in named)))
        if not len(scene.obs):
            raise InputError(str(root), "no person is seen by two cameras at once (nothing to reconstruct)")
        scene = without_undetermined(scene)
    scene = checks.check_scene(scene, explained=explained)
    if segments is not None:
        scene = with_pieces(scene, Path(segments))
    return with_box_model(scene, box_model)


def load_detections(root: Path | str, layout: str | None = None, skeleton: str | None = None,
                    fps: float | None = None, calib: Path | str | Calibration | None = None,
                    **panoptic_options: JsonValue) -> Scene:
    """Each camera's detections as read and checked, with no identities made across cameras (the
    association needs the rig's poses, which :mod:`gt3dkit.refine.people` is to find)."""
    return checks.check_scene(read_scene(root, layout, skeleton, fps, calib, None, span=None, ahead=None,
                                         **panoptic_options),
                              identities=False)


def load_head(root: Path | str, layout: str | None = None, fps: float | None = None,
              calib: Path | str | Calibration | None = None, box_model: str = "auto") -> Scene | None:
    """:func:`load_scene` without the rows, for a sequence whose windows read their own frames
    (:func:`read_frames`; :mod:`gt3dkit.windows`): the cameras, the frames and each frame's
    objects (:class:`gt3dkit.types.FrameIndex`), where the layout reads a span of frames on its
    own and nothing about the whole sequence is needed to read one (no cross-camera association);
    else None. ``box_model`` ``"auto"`` is chosen later, on the frames the process noise is
    chosen on (:class:`gt3dkit.windows.frames.SampleRead`)."""
    head = index_scene(root, layout, fps, calib)
    if head is None:
        return None
    if box_model in BOX_MODELS:
        head = dataclasses.replace(head, box_model=box_model)
    return dataclasses.replace(head, load_options={**head.load_options, "box_model": box_model})


def read_frames(head: Scene, lo: int, hi: int, check: bool = True) -> Scene:
    """The frames ``lo..hi`` of the sequence :func:`load_head` indexed, read and (``check``)
    checked as :func:`load_scene` reads and checks the whole (a window's: its rows those the
    whole would have; the warnings of :func:`gt3dkit.io.datasets.checks.check_scene` are the
    frames' own), with the head's box model."""
    o = head.load_options
    calib = o.get("calib")
    scene = read_scene(head.root, head.layout, fps=json_num(o, "fps"), span=(lo, hi),
                       calib=Calibration(calib if isinstance(calib, str) else None,
                                         json_str(o, "calib_units") or "m"))
    scene = dataclasses.replace(scene, box_model=head.box_model, box_model_px=head.box_model_px,
                                load_options=o)
    return checks.check_scene(scene, whole=False) if check else scene


def without_undetermined(scene: Scene) -> Scene:
    """A keypoints-only scene whose people the association made: those that no two views ever
    agree on (:func:`gt3dkit.fusion.preparation.prepare.undetermined_objects`) left out, with a warning, and
    listed in ``Scene.left_out`` (the anomalies name them): one such person must not cost the
    others their estimate."""
    ids = undetermined_objects(scene)
    if not ids.size:
        return scene
    obs = scene.obs
    out = np.isin(obs.track_id, ids)
    left = []
    for i in ids:
        m = obs.track_id == i
        cams = ", ".join(sorted({scene.rig.names[int(c)] for c in np.unique(obs.cam[m])}))
        left.append((int(i), int(obs.frame[m].min()), int(obs.frame[m].max()), int(m.sum()), cams))
    if out.all():
        raise InputError(str(scene.root), "no person the association made is ever seen by two cameras at "
                                          "once that agree (nothing to reconstruct)")
    shown = ", ".join(str(i) for i in ids[:5]) + (" ..." if len(ids) > 5 else "")
    warn = (f"{len(ids)} person(s) no two views ever agree on left out (id {shown}: "
            f"{int(out.sum())} detections; anomalies.csv lists them as undetermined_person)")
    return dataclasses.replace(scene, obs=obs.select(~out), warnings=(*scene.warnings, warn),
                               left_out=tuple(left))


def disagreeing_cameras(assoc: Association, share: float = 0.9, min_rows: int = 10) -> list[tuple[str, str]]:
    """Each camera whose detections (at least ``min_rows``) the others confirm in under
    ``1 - share`` of the frames while the rest confirm most of theirs, and a warning saying so:
    its calibration does not fit theirs (a copied or stale camera), whatever its labels say
    (``--refine-calib`` poses it again: :mod:`gt3dkit.refine.repose`)."""
    kept: dict[str, list[bool]] = {}
    for r in assoc.rows:
        if r[7] != SECOND_DETECTION:
            kept.setdefault(r[0], []).append(r[3] >= 0)
    out = []
    for cam, k in kept.items():
        rest = [x for c, v in kept.items() if c != cam for x in v]
        lost = len(k) - sum(k)
        if len(k) >= min_rows and lost >= share * len(k) and rest and sum(rest) > 0.5 * len(rest):
            out.append((cam, f"camera {cam}: {lost} of its {len(k)} detections agree with no other camera's, "
                       f"while the others agree on {100 * sum(rest) / len(rest):.0f} % of theirs: its "
                       "calibration does not fit the others' (a copied or outdated camera?); its views are "
                       "left out (--refine-calib poses it again on the people the others place)"))
    return out


def with_box_model(scene: Scene, box_model: str = "auto") -> Scene:
    """``scene`` with the box model that draws its boxes: ``box_model`` when one of
    :data:`gt3dkit.types.BOX_MODELS`, else the one its boxes' per-frame fits choose
    (:func:`gt3dkit.fusion.preparation.boxfit.choose_box_model`). The choice is kept in ``load_options``, so a
    report's reload draws the same boxes without choosing again."""
    px: dict[str, float] = {}
    if box_model not in BOX_MODELS:
        rows = build_rows(scene)
        box_model, px = ("ellipsoid", {}) if not np.isfinite(rows.box_z).any() else \
            choose_box_model(rows.box_z, rows.box_mask, Cams.of(scene.rig))
    opts = {**scene.load_options, "box_model": box_model}
    return dataclasses.replace(scene, box_model=box_model, box_model_px=px, load_options=opts)


def with_pieces(scene: Scene, path: Path) -> Scene:
    """``scene`` with the pieces of an edited ``segments.csv``: every annotated frame of an id the
    file lists must lie in one of its pieces."""
    pieces = read_segments_csv(path)
    for i in sorted({p[0] for p in pieces}):
        f = np.unique(scene.obs.frame[scene.obs.track_id == i])
        if not len(f):
            raise InputError(str(path), f"id {i}: the input has no such id")
        mine = [p for p in pieces if p[0] == i]
        inside = np.zeros(len(f), bool)
        for _, _, a, b in mine:
            inside |= (f >= a) & (f <= b)
        if not inside.all():
            raise InputError(str(path), f"id {i}: annotated frame {int(f[~inside][0])} is in none of its "
                                        "pieces")
    opts = {**scene.load_options, "segments": str(path.resolve())}
    return dataclasses.replace(scene, identity_pieces=pieces, load_options=opts)


def reconstruct(scene: Scene | str | Path, estimator: str | Estimator = "ukf",
                out: str | Path | None = None, extra_meta: JsonDict | None = None,
                on_stage: Callable[[str], None] | None = None, every_frame: int | None = None,
                **config: OptionValue) -> TrackSet:
    """Estimate tracks for a scene (or an input folder); write ``out`` if given (with
    ``extra_meta`` added to its meta.json). ``on_stage(name)`` is called as each stage starts
    (a progress display). ``every_frame``: None = a row for every annotated object-frame (one
    camera or more); 0 = a row for every frame of the input's frame grid from each object's
    first to its last annotation (interpolated where no camera sees it: ``n_views`` 0); ``k >
    0`` = every ``k`` frame numbers (and every annotated frame)."""
    with small_matrix_blas():  # one BLAS thread for our small matrices (gt3dkit.threads)
        sc = scene if isinstance(scene, Scene) else load_scene(Path(scene))
        est = make_estimator(estimator, **config) if isinstance(estimator, str) else estimator
        tracks, qa = estimate_checked(sc, est, every_frame, out is not None, on_stage)
        if out is not None:
            write_outputs(Path(out), sc, tracks, extra_meta, anomalies=qa)
    return tracks


def estimate_checked(scene: Scene, est: Estimator, every_frame: int | None = None, qa: bool = True,
                     on_stage: Callable[[str], None] | None = None, pre: Prepared | None = None
                     ) -> tuple[TrackSet, Anomalies | None]:
    """:func:`reconstruct`'s pipeline on a loaded scene without the writing: per-frame fits,
    identity segments, the estimator (``every_frame`` as there), and with ``qa`` the annotation
    QA (:func:`gt3dkit.qa.anomalies.find_anomalies`; else None). ``pre``: the estimator's own
    preparation of the scene it runs on (after ``every_frame``'s grid), made before (None: made
    here)."""
    stage = on_stage or (lambda name: None)
    sc = scene
    if every_frame is not None:
        if not over_time(est.name):
            raise InputError("--every-frame", f"the {est.name} estimator fits each frame on its own: "
                                              "it has no estimate between annotations (use ukf or gtsam)")
        sc = dense_frames(sc, every_frame or None)
    stage("per-frame fits")
    if pre is None:
        pre = est.prepare(sc)
    segs = identity_segments(pre, sc.fps, pieces=sc.identity_pieces)
    stage(est.name)
    tracks = estimate_scene(sc, est, pre, segs, dense=every_frame is not None)
    if not qa:
        return tracks, None
    stage("annotation QA, writing")
    found = find_anomalies(sc, tracks, pre, splits=segs.splits, exchanges=segs.exchanges)
    return tracks.with_info(replace(tracks.info, qa=QASummary(found.counts()))), found


def process_noise_prepared(scene: Scene, est: Estimator) -> tuple[dict[str, float] | None, Prepared | None]:
    """The process noise ``est`` would choose for ``scene`` as :func:`estimate_checked` runs it
    (on the pieces of split ids), by the estimator's own ``process_noise`` without the rest of the
    estimate, and the preparation (per-frame fits) it was found on (None, None
    when the estimator has no ``process_noise``)."""
    if not est.capabilities.process_noise:
        return None, None
    pre = est.prepare(scene)
    segs = identity_segments(pre, scene.fps, pieces=scene.identity_pieces)
    if segs.splits:
        scene, _ = split_ids(scene, pre.rows, segs)
        pre = est.prepare(scene)
    found = est.process_noise(scene, pre)
    return found, pre


def bone_samples_checked(scene: Scene, est: Estimator, pre: Prepared | None = None
                         ) -> tuple[BoneSamples | None, I64]:
    """The first pass's bones (:class:`gt3dkit.fusion.ukf.bones.BoneSamples`, ``obj``: the input's
    ids) that :func:`estimate_checked` would tie ``scene``'s joints with, by the estimator's own
    ``bone_samples`` without the rest of the estimate (None when it ties no bones), and the ids
    it splits ``(S,)`` (an id's pieces may be different people: the caller leaves them out; the
    rows of the pieces after an id's first, whose ids are this run's own, are left out here).
    ``pre``: the estimator's preparation of ``scene``, made before (None: made here)."""
    if not est.capabilities.bone_samples:
        return None, np.zeros(0, np.int64)
    pre = pre if pre is not None else est.prepare(scene)
    segs = identity_segments(pre, scene.fps, pieces=scene.identity_pieces)
    if not segs.splits:
        return est.bone_samples(scene, pre), np.zeros(0, np.int64)
    split = np.unique(pre.rows.obj_ids[pre.rows.row_o[segs.segment > 0]]).astype(np.int64)
    pieces, back = split_ids(scene, pre.rows, segs)
    s = est.bone_samples(pieces)
    if s is None:
        return None, split
    return s.take(~np.isin(s.obj, np.fromiter(back, np.int64))), split


def dense_frames(scene: Scene, step: int | None) -> Scene:
    """``scene`` whose frame grid is every frame number from its first to its last annotated
    frame at ``step`` (None: the input's own step, :func:`gt3dkit.arrays.frame_grid`), its
    annotated frames included: the estimators then give every object a row on that grid from
    its first to its last annotation."""
    grid, _ = frame_grid(scene.frames, step)
    return dataclasses.replace(scene, frames=np.union1d(grid, np.asarray(scene.frames, dtype=np.int64)))


def take_rows(tracks: TrackSet, keep: np.ndarray) -> TrackSet:
    """The rows ``keep (M,)`` of ``tracks`` (bool or indices)."""
    return dataclasses.replace(
        tracks, frame=tracks.frame[keep], track_id=tracks.track_id[keep],
        center_world=tracks.center_world[keep], semi_axes=tracks.semi_axes[keep],
        center_sd=tracks.center_sd[keep], n_views=tracks.n_views[keep],
        kpt_world=tracks.kpt_world[keep], kpt_sd=tracks.kpt_sd[keep])


def estimate_scene(scene: Scene, est: Estimator, pre: Prepared | None, segs: Segments,
                   dense: bool = False, split: SplitScene | None = None
                   ) -> TrackSet:
    """``est``'s tracks of ``scene``, each piece of a split id (:mod:`gt3dkit.fusion.preparation.identity`)
    estimated as an object of its own; the tracks carry the input's ids, ``info.identity``
    the pieces. ``pre``: the estimator's own preparation of ``scene`` (None: it prepares).
    A row for each annotated object-frame; ``dense``: also the rows of frames no camera saw
    the object in (the estimator's interpolation, ``n_views`` 0). ``split``: :func:`split_scene`'s
    result, shared by several estimators (``gt3d compare``)."""
    tracks = _estimate_pieces(scene, est, pre, segs, split)
    if dense:
        tracks = tracks.with_info(replace(tracks.info, every_frame=DenseSummary(
            int(len(scene.frames)), int(np.sum(tracks.n_views == 0)),
            "a row for every frame of the grid from each object's first to its last annotation; "
            "n_views 0 = no camera saw it there (interpolated by the motion model, its sd grows "
            "with the distance to the nearest view)")))
    elif np.any(tracks.n_views == 0):
        keep = tracks.n_views > 0
        if follows_visibility(pre):  # a short gap no camera saw the object in is bridged
            keep |= bridged(tracks.frame, tracks.track_id, keep, BRIDGE_S * scene.fps)
        tracks = take_rows(tracks, keep)  # info and downweighted carried over
    return tracks


#: The longest time (s) between two views of an object that its rows bridge where the labels follow
#: what the cameras see (:func:`follows_visibility`); ``--every-frame`` bridges every gap.
BRIDGE_S = 1.0


def follows_visibility(pre: Prepared | None) -> bool:
    """Whether the scene's boxes are drawn around what each camera sees: their edges cut by a
    nearer object vary more than the others (a kind of them left out by the preparation,
    :mod:`gt3dkit.fusion.preparation.occlusion`), as a detector's and most people's do. Such
    labels leave a person out where no camera sees them (hidden behind others, or missed by
    the detector), not where they are absent: a short gap in them is bridged (rows of ``n_views``
    0, their sd grown with the gap). Labels of a shape placed in the world (WILDTRACK's,
    MultiviewX's: their cut edges vary as the others) leave a person out where the labeller
    says they are not there: their gaps keep no rows."""
    return pre is not None and pre.box_cut is not None and bool(np.any(pre.box_cut))


def bridged(frame: I64, obj: I64, seen: np.ndarray, max_frames: float) -> np.ndarray:
    """``(N,)`` the unseen rows between two seen rows of their object at most ``max_frames`` frame
    numbers apart (``frame``, ``obj``, ``seen``: ``(N,)`` each)."""
    out = np.zeros(len(frame), bool)
    order = np.lexsort((frame, obj))
    f, o, s = frame[order], obj[order], seen[order]
    idx = np.arange(len(f))
    last = np.maximum.accumulate(np.where(s, idx, -1))  # the seen row at or before each row
    nxt = np.minimum.accumulate(np.where(s, idx, len(f))[::-1])[::-1]  # ... at or after it
    ok = (~s) & (last >= 0) & (nxt < len(f))
    lo, hi = np.clip(last, 0, len(f) - 1), np.clip(nxt, 0, len(f) - 1)
    ok &= (o[lo] == o) & (o[hi] == o) & (f[hi] - f[lo] <= max_frames)
    out[order] = ok
    return out


#: The scene of an input's split ids' pieces, its preparation (None: the estimator makes its own) and
#: each piece's id and segment by its own id (:func:`split_scene`).
SplitScene = tuple[Scene, Prepared | None, dict[int, tuple[int, int]]]


def split_scene(scene: Scene, pre: Prepared, segs: Segments) -> SplitScene:
    """The scene of the pieces (:func:`split_ids`), its preparation (:func:`prepare`'s defaults,
    as ``gt3d compare`` shares one) and the map back to the input's ids."""
    pieces, back = split_ids(scene, pre.rows, segs)
    return pieces, pieces_prepared(pre, pieces, back), back


def _estimate_pieces(scene: Scene, est: Estimator, pre: Prepared | None, segs: Segments,
                     shared: SplitScene | None) -> TrackSet:
    """:func:`estimate_scene` with every row the estimator gives."""
    if not segs.splits:
        tracks = est.estimate(scene, pre)
    else:
        if shared is None:  # the pieces' preparation is the whole's (one preparation a run)
            whole = pre if pre is not None else est.prepare(scene)
            pieces, back = split_ids(scene, whole.rows, segs)
            shared = (pieces, pieces_prepared(whole, pieces, back), back)
        tracks = restored_ids(est.estimate(shared[0], shared[1]), shared[2])
    return tracks.with_info(replace(tracks.info, identity=IdentitySummary(
        len(segs.splits), len(segs.exchanges), round(segs.speed_limit_mps, 3),
        "an id is split between two consecutive frames its views place farther apart than "
        "the scene's objects move (2x the 95th percentile of the ids' median speeds, at least "
        "3 m/s, plus 4 sd); "
        "each piece is estimated on its own (segments.csv, identity_split in anomalies.csv)")))


def split_ids(scene: Scene, rows: Rows, segs: Segments) -> tuple[Scene, dict[int, tuple[int, int]]]:
    """``scene`` with the annotations of every piece after an id's first given an id of its own,
    and the map back: new id -> (input id, piece)."""
    frame_of = rows.frames[rows.row_t]
    id_of = rows.obj_ids[rows.row_o]
    later = np.flatnonzero(segs.segment > 0)
    pairs = np.unique(np.c_[id_of[later], segs.segment[later]], axis=0)
    fresh = int(max(int(scene.obs.track_id.max()), int(rows.obj_ids.max()))) + 1 + np.arange(len(pairs))
    back = {int(n): (int(i), int(s)) for n, (i, s) in zip(fresh, pairs, strict=True)}
    new_of_row = np.full(len(rows), -1, np.int64)
    new_of_row[later] = fresh[lookup_rows(pairs, np.c_[id_of[later], segs.segment[later]])]
    hit = lookup_rows(np.c_[frame_of, id_of], np.c_[scene.obs.frame, scene.obs.track_id])
    ids = np.where((hit >= 0) & (new_of_row[np.maximum(hit, 0)] >= 0), new_of_row[np.maximum(hit, 0)],
                   scene.obs.track_id)
    obs = dataclasses.replace(scene.obs, track_id=ids.astype(np.int64))
    return dataclasses.replace(scene, obs=obs), back


def restored_ids(tracks: TrackSet, back: dict[int, tuple[int, int]]) -> TrackSet:
    """``tracks`` of a scene made by :func:`split_ids` with the input's ids again (rows sorted as
    before: by frame, then id), and the pieces in ``info.segments``."""
    new = np.array(sorted(back), dtype=np.int64)
    to = np.array([back[int(k)] for k in new], dtype=np.int64).reshape(-1, 2)  # (input id, piece)

    def input_ids(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k = np.minimum(np.searchsorted(new, ids), len(new) - 1)
        hit = new[k] == ids
        return np.where(hit, to[k, 0], ids), np.where(hit, to[k, 1], 0)

    orig, piece = input_ids(tracks.track_id)
    order = np.lexsort((orig, tracks.frame))
    d = tracks.downweighted
    if d is not None:
        d = dataclasses.replace(d, track_id=input_ids(d.track_id)[0])
    out = take_rows(dataclasses.replace(tracks, track_id=orig, downweighted=d), order)
    pieces, inv = np.unique(np.c_[orig, piece], axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    first = np.full(len(pieces), np.iinfo(np.int64).max)
    last = np.full(len(pieces), np.iinfo(np.int64).min)
    np.minimum.at(first, inv, tracks.frame)
    np.maximum.at(last, inv, tracks.frame)
    count = np.bincount(inv, minlength=len(pieces))
    return out.with_info(replace(out.info, segments=[
        {"id": int(i), "segment": int(s), "first_frame": int(a), "last_frame": int(b), "rows": int(n)}
        for (i, s), a, b, n in zip(pieces, first, last, count, strict=True)]))


def annotation_qa(scene: Scene, tracks: TrackSet) -> Anomalies:
    """Every input annotation scored against ``tracks``, and every split id
    (:mod:`gt3dkit.fusion.preparation.identity`): :class:`gt3dkit.qa.anomalies.Anomalies`."""
    pre = prepare(scene)
    segs = identity_segments(pre, scene.fps, pieces=scene.identity_pieces)
    return find_anomalies(scene, tracks, pre, splits=segs.splits, exchanges=segs.exchanges)


@dataclass
class Run:
    """A reconstruct output read back, with the scene it was made from."""

    out: Path
    meta: JsonDict
    scene: Scene
    tracks: TrackSet
    anomalies: list[dict[str, str]]
    notes: list[str]


def _load_scene(out: Path, meta: JsonDict, why: str) -> tuple[Scene, list[str]]:
    where = str(out / "meta.json")
    inp = meta.get("input")
    if not isinstance(inp, dict) or not isinstance(inp.get("load", inp), dict):
        raise InputError(where, "input: missing (not a gt3d reconstruct output?)")
    load = dict(inp.get("load") or {"root": inp.get("root"), "layout": inp.get("layout")})
    root = load.pop("root", None)
    if not isinstance(root, str) or not root:
        raise InputError(where, "input: no input folder recorded")
    if not Path(root).is_dir():
        raise InputError(where, f"input: the input folder {root} is not there any more ({why})")
    if load.get("calib") and not Path(load["calib"]).exists():
        raise InputError(where, f"input: the calibration {load['calib']} is not there any more")
    if "calib_units" in load:  # the calibration's own units (read_scene makes them metres)
        load["calib"] = Calibration(load.get("calib"), str(load.pop("calib_units")))
    known = {"layout", "skeleton", "fps", "calib", "cameras", "noise_px", "seed", "min_conf", "association",
             "segments", "box_model", "clocks"}
    refined = json_at(meta, "calibration_refinement", "refined_rig")
    with tempfile.TemporaryDirectory() as tmp:
        if refined and json_obj(meta, "calibration_refinement", "reposed_cameras"):
            # a camera the run posed again: the input read on the run's rig, as the run read it
            # (through the input's own calibration its views agree with no other camera's)
            (Path(tmp) / "cameras.json").write_text(json.dumps(refined))
            load["calib"] = Calibration(str(Path(tmp) / "cameras.json"), "m")
        scene = load_scene(Path(root), **{k: v for k, v in load.items() if k in known})
    notes = []
    old = inp.get("files_sha256") or {}
    changed = sorted(k for k, v in scene.files.items() if old.get(k) not in (None, v))
    if changed:
        notes.append(f"input files changed since the run: {', '.join(changed[:5])}"
                     + (" ..." if len(changed) > 5 else "") + " (today's annotations beside the run's "
                     "estimate: run gt3d reconstruct again to bring them together)")
    people = json_at(meta, "calibration_from_people", "rig")
    if people:
        scene = dataclasses.replace(scene, rig=rig_of_doc(people, f"{where}: calibration_from_people"))
        notes.append("cameras: the rig found from the people (meta.json calibration_from_people)")
    if refined:
        scene = dataclasses.replace(scene, rig=rig_of_doc(refined, f"{where}: calibration_refinement"))
        notes.append("cameras: the refined calibration the run used (meta.json calibration_refinement)")
    return scene, notes


def load_run(out: Path, why: str) -> Run:
    """:func:`read_result` plus the scene it was made from and its anomalies; ``why`` the caller
    needs the scene (said where the input folder is gone). ``Run.notes``: what the user should
    know (input files changed since the run, a refined calibration)."""
    res = read_result(out)
    out = res.out
    scene, notes = _load_scene(out, res.meta, why)
    tracks = res.tracks
    if (out / "keypoints.csv").is_file() and scene.obs.n_joints \
            and tracks.kpt_world.shape[1] != scene.obs.n_joints:
        tracks = read_keypoints_csv(out / "keypoints.csv", tracks, scene.obs.n_joints)
    anomalies = []
    if (out / "anomalies.csv").is_file():
        anomalies = [dict(r) for _, r in read_csv_rows(out / "anomalies.csv", ANOMALY_COLUMNS)]
    return Run(out, res.meta, scene, tracks, anomalies, notes)

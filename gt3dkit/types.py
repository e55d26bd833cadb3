"""Typed containers at the edges of the package.

Everything inside ``geom/`` and ``fusion/`` works on plain batched numpy arrays;
these frozen dataclasses carry those arrays between the loaders, the estimators
and the writers, and validate them once, at construction.

Conventions
-----------
* Cameras are ``cam_from_world``: ``X_cam = R @ X_world + t`` (OpenCV), metres.
* Pixels are OpenCV pixels of the *distorted* image (pixel centres at integers).
* Missing data is NaN (a box of four NaNs, a keypoint of two NaNs).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, is_dataclass, replace
from typing import Any, TypeAlias, overload

import numpy as np
import numpy.typing as npt

from gt3dkit.rig import (  # the camera model lives in gt3dkit.rig; re-exported here
    LENS_CODES as LENS_CODES,
    LENSES as LENSES,
    MAX_DIST_COEF as MAX_DIST_COEF,
    MAX_PIXELS as MAX_PIXELS,
    MAX_WORLD_M as MAX_WORLD_M,
    R_STORAGE_TOL as R_STORAGE_TOL,
    Camera as Camera,
    Rig as Rig,
    as_array as as_array,
    distortion_fold as distortion_fold,
)

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
B8 = npt.NDArray[np.bool_]

#: Rows of a batch as numpy indexes them: one, a slice, integer indices or a mask.
RowIndex: TypeAlias = "int | slice | np.ndarray"
#: A value a JSON file holds (``meta.json``, a summary, a report's numbers), nested; numpy's
#: scalars count as the Python numbers they subclass or convert to when written.
#: Containers as read-only ``Sequence``/``Mapping``: a ``dict[str, float]`` or a ``list`` of
#: objects is then a value as it is (``list``/``dict`` are invariant in what they hold).
JsonValue: TypeAlias = ("str | int | float | bool | None | Sequence[JsonValue]"
                        " | Mapping[str, JsonValue]")
#: A JSON object by its keys.
JsonDict: TypeAlias = "dict[str, JsonValue]"

#: An estimator option: a field of its config set by keyword (a number, a switch, bounds).
OptionValue: TypeAlias = float | int | bool | str | tuple[float, float] | None
#: Estimator options by config field (``gt3d``'s ``--sigma-px`` and the like, or the API's keywords).
Options: TypeAlias = dict[str, OptionValue]

#: How a state (centre, semi-axes along the body axes) draws a person's box in a camera
#: (:mod:`gt3dkit.geom.boxkernel`): the ellipsoid's tangent box (the paper's), the vertical
#: cylinder's box, or the rectangle of the probabilistic-occupancy-map generator (WILDTRACK's and
#: MultiviewX's labels). A scene's is chosen from its boxes
#: (:func:`gt3dkit.fusion.preparation.boxfit.choose_box_model`).
@dataclass(frozen=True)
class BoxModelEntry:
    """One way boxes are drawn: its ``name`` (the option value), what it draws (``summary``, how
    a run's summary line and the command line's help name it) and ``index``, how the compiled
    kernels of :mod:`gt3dkit.geom.boxkernel` select it (its value and gradient there)."""

    name: str
    index: int
    summary: str


#: Every box model, registered once: the command line's choices and help, the summary line, the
#: chooser (:func:`gt3dkit.fusion.preparation.boxfit.choose_box_model`), the simulator and the
#: kernels read it.
BOX_MODEL_REGISTRY: dict[str, BoxModelEntry] = {e.name: e for e in (
    BoxModelEntry("ellipsoid", 0, "ellipsoid tangent boxes"),
    BoxModelEntry("cylinder", 1, "cylinder boxes"),
    BoxModelEntry("pom", 2, "occupancy-map rectangles"),
)}
BOX_MODELS = tuple(BOX_MODEL_REGISTRY)
#: The four edges of a box, in the order of ``Observations.box_xyxy_px``'s columns.
BOX_EDGES = ("xmin", "ymin", "xmax", "ymax")


@dataclass(frozen=True, eq=False)
class Origins(Sequence[str]):
    """Where each observation row came from (``"file: line 12"``, ``"file: personID 3, viewNum
    2"``), for error messages; written out when read: row ``i`` is
    ``templates[kind[i]].format(*args[i])``. A reader's rows share a few templates, so a long
    recording holds three integers per row, not a string (whose objects, interleaved with the
    reader's freed ones, also kept the reader's whole heap resident).

    templates : tuple[str, ...] ``str.format`` templates of two positional fields at most;
    kind : (N,) int64 index into ``templates``; args : (N, 2) int64 their fields.
    """

    templates: tuple[str, ...]
    kind: I64
    args: I64

    @staticmethod
    def literal(text: str) -> str:
        """``text`` as a template that formats to itself."""
        return text.replace("{", "{{").replace("}", "}}")

    @classmethod
    def of(cls, texts: Iterable[str]) -> Origins:
        """Rows given as text, one string each."""
        texts = list(texts)
        index = {t: k for k, t in enumerate(dict.fromkeys(texts))}
        return cls(tuple(cls.literal(t) for t in index), np.array([index[t] for t in texts], dtype=np.int64),
                   np.zeros((len(texts), 2), dtype=np.int64))

    @classmethod
    def formatted(cls, template: str, *args: npt.ArrayLike) -> Origins:
        """Rows of one ``template`` whose fields are ``args`` (one or two ``(N,)`` int arrays)."""
        cols = [np.asarray(a, dtype=np.int64).reshape(-1) for a in args]
        n = len(cols[0]) if cols else 0
        a = np.zeros((n, 2), dtype=np.int64)
        for k, c in enumerate(cols):
            a[:, k] = c
        return cls((template,), np.zeros(n, dtype=np.int64), a)

    @classmethod
    def concat(cls, parts: Sequence[Origins]) -> Origins:
        """The rows of ``parts`` one after another."""
        offsets = np.cumsum([0] + [len(p.templates) for p in parts])
        return cls(tuple(t for p in parts for t in p.templates),
                   np.concatenate([np.zeros(0, np.int64)]
                                  + [p.kind + o for p, o in zip(parts, offsets, strict=False)]),
                   np.concatenate([np.zeros((0, 2), np.int64)] + [p.args for p in parts]))

    def take(self, idx: npt.ArrayLike) -> Origins:
        """The rows ``idx`` (indices or a boolean mask)."""
        i = np.asarray(idx)
        i = np.flatnonzero(i) if i.dtype == bool else i.astype(np.int64).reshape(-1)
        return Origins(self.templates, self.kind[i], self.args[i])

    def __len__(self) -> int:
        return len(self.kind)

    @overload
    def __getitem__(self, i: int) -> str: ...

    @overload
    def __getitem__(self, i: slice) -> list[str]: ...

    def __getitem__(self, i: int | slice) -> str | list[str]:
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        k = int(i)
        if not -len(self) <= k < len(self):
            raise IndexError(f"row {k} of {len(self)}")
        return self.templates[int(self.kind[k])].format(*self.args[k].tolist())

    def __iter__(self) -> Iterator[str]:
        return (self[k] for k in range(len(self)))

    def __eq__(self, other: object) -> bool:
        return (isinstance(other, Sequence) and not isinstance(other, str) and len(self) == len(other)
                and all(a == b for a, b in zip(self, other, strict=True)))

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True)
class Observations:
    """2D annotations, one row per (frame, camera, object).

    Attributes
    ----------
    frame : (N,) int64
    cam : (N,) int64
        Index into ``Rig.cameras``.
    track_id : (N,) int64
    box_xyxy_px : (N, 4) float64
        ``xmin, ymin, xmax, ymax`` in distorted pixels; NaN = no box in this row.
    kpt_uv_px : (N, J, 2) float64
        Keypoints in distorted pixels; NaN = not seen. ``J`` may be 0.
    origin : Origins
        For each row, where it came from (``"file: entry"``), for error messages (any sequence
        of strings is taken, and held as :class:`Origins`).
    kpt_conf : (N, J) float64 or None
        Detector confidence of each keypoint in ``(0, 1]`` (NaN where not seen); ``None``
        = no confidences given (every point counts fully).
    frame_offset : (N,) float64 or None
        When each row was seen, in frames after ``frame`` on the scene's clock (a camera whose
        clock runs late or at its own rate: :func:`gt3dkit.io.clocks.on_one_clock`); ``None`` = every
        row at its frame.
    """

    frame: I64
    cam: I64
    track_id: I64
    box_xyxy_px: F64
    kpt_uv_px: F64
    origin: Origins
    kpt_conf: F64 | None = None
    frame_offset: F64 | None = None

    def __post_init__(self) -> None:
        n = len(self.frame)
        for name in ("frame", "cam", "track_id"):
            a = np.asarray(getattr(self, name), dtype=np.int64).reshape(-1)
            if a.shape != (n,):
                raise ValueError(f"expected {name} of shape ({n},), got {a.shape}")
            object.__setattr__(self, name, a)
        object.__setattr__(self, "box_xyxy_px", as_array(self.box_xyxy_px, (n, 4), "box_xyxy_px",
                                                     finite=False))
        k = np.asarray(self.kpt_uv_px, dtype=np.float64)
        if k.ndim != 3 or k.shape[0] != n or k.shape[2] != 2:
            raise ValueError(f"expected kpt_uv_px of shape ({n}, J, 2), got {k.shape}")
        object.__setattr__(self, "kpt_uv_px", k)
        if self.kpt_conf is not None:
            c = np.asarray(self.kpt_conf, dtype=np.float64)
            if c.shape != k.shape[:2]:
                raise ValueError(f"expected kpt_conf of shape {k.shape[:2]}, got {c.shape}")
            seen = np.isfinite(k[..., 0])
            if np.any(seen & ~((c > 0) & (c <= 1))):
                raise ValueError("kpt_conf must be in (0, 1] for every seen keypoint")
            object.__setattr__(self, "kpt_conf", c)
        if self.frame_offset is not None:
            object.__setattr__(self, "frame_offset", as_array(self.frame_offset, (n,), "frame_offset"))
        if not isinstance(self.origin, Origins):
            object.__setattr__(self, "origin", Origins.of(self.origin))
        if len(self.origin) != n:
            raise ValueError(f"expected {n} origins, got {len(self.origin)}")

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def n_joints(self) -> int:
        return int(self.kpt_uv_px.shape[1])

    @property
    def has_box(self) -> B8:
        """(N,) rows that carry a box."""
        return np.all(np.isfinite(self.box_xyxy_px), axis=1)

    def select(self, rows: npt.NDArray[Any]) -> Observations:
        rows = np.asarray(rows)
        idx = np.flatnonzero(rows) if rows.dtype == bool else rows
        return Observations(self.frame[idx], self.cam[idx], self.track_id[idx],
                            self.box_xyxy_px[idx], self.kpt_uv_px[idx],
                            self.origin.take(idx),
                            None if self.kpt_conf is None else self.kpt_conf[idx],
                            None if self.frame_offset is None else self.frame_offset[idx])


@dataclass(frozen=True)
class GroundTruth:
    """What an input says the 3D truth is. NaN = not given.

    Attributes
    ----------
    frame, track_id : (M,) int64
    center_world : (M, 3) float64
        Ellipsoid centre (metres). For WILDTRACK/MultiviewX only the ground position
        is known: its two horizontal coordinates are set and the vertical one is NaN.
    semi_axes : (M, 3) float64
        Along body x, y, up (metres).
    kpt_world : (M, J, 3) float64
        3D joints (metres).
    """

    frame: I64
    track_id: I64
    center_world: F64
    semi_axes: F64
    kpt_world: F64
    source: str = ""

    def select(self, rows: npt.NDArray[Any]) -> GroundTruth:
        """The rows ``rows`` (a mask or indices)."""
        return GroundTruth(self.frame[rows], self.track_id[rows], self.center_world[rows],
                           self.semi_axes[rows], self.kpt_world[rows], self.source)

    @staticmethod
    def concat(parts: Sequence[GroundTruth]) -> GroundTruth:
        """``parts`` (at least one, one source) one after another."""
        def cat(key: str) -> npt.NDArray[Any]:
            return np.concatenate([getattr(t, key) for t in parts])

        return GroundTruth(cat("frame"), cat("track_id"), cat("center_world"), cat("semi_axes"),
                           cat("kpt_world"), parts[0].source)


@dataclass(frozen=True)
class FrameIndex:
    """What a long input's frame files say without being read whole (a :class:`Scene` whose
    windows read their own frames, :mod:`gt3dkit.windows`): ``frames (F,)`` the annotated frame
    numbers, sorted, and ``objects (F,)`` how many objects each holds; ``rows`` and ``boxes``: the
    annotation rows and whether one has a box, once the windows have read them (0 before)."""

    frames: I64
    objects: I64
    rows: int = 0
    boxes: bool = False  # whether a row read has a box
    ahead: ReadAhead | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True)
class ReadAhead:
    """What indexing a folder read that its whole reading needs again, so that each file is
    opened once a run: ``frame_bytes`` each frame file's bytes by its path (``str``), and the
    layout's ``cameras`` (None: a camera without a calibration) with ``files`` their files'
    digests. Kept only while a run may still read the folder whole (:func:`gt3dkit.api.load_head`);
    a run in windows drops it (each window reads its own frames)."""

    frame_bytes: dict[str, bytes]
    cameras: tuple[Camera | None, ...]
    files: dict[str, str]


@dataclass(frozen=True)
class Scene:
    """A loaded input: rig, annotations, optional truth, and where they came from. A scene with
    an ``index`` holds no rows (``obs`` is empty): its windows read their own frames
    (:func:`gt3dkit.api.load_head`, :func:`gt3dkit.api.read_frames`)."""

    rig: Rig
    obs: Observations
    layout: str
    fps: float
    frames: I64
    truth: GroundTruth | None = None
    skeleton: str | None = None
    #: the skeleton as its input or a file describes it (``gt3dkit.skeletons.Skeleton.doc``: joints,
    #: bones, left/right pairs); None: the built-in ``skeleton`` names
    skeleton_doc: JsonDict | None = None
    files: dict[str, str] = field(default_factory=dict)  # relative path -> sha256
    root: str = ""
    warnings: tuple[str, ...] = ()  # odd but valid input: printed as ``warning:`` lines
    fps_assumed: str = ""  # why ``fps`` is a default, not the input's ("" = the input gives it)
    load_options: JsonDict = field(default_factory=dict)  # load_scene's arguments (JSON-able)
    association: Any = None  # fusion.preparation.associate.Association when ids were per camera
    # (id, segment, first frame, last frame) pieces an edited segments.csv gives (fusion.preparation.identity)
    identity_pieces: tuple[tuple[int, int, int, int], ...] = ()
    # how the boxes are drawn (BOX_MODELS) and the evidence that chose it (median edge residual,
    # px, of per-frame fits under each model; empty when given, not chosen)
    box_model: str = "ellipsoid"
    box_model_px: dict[str, float] = field(default_factory=dict)
    # people the association made that no two views ever agree on, left out of the estimate:
    # (id, first frame, last frame, detections, cameras that saw it) each (gt3dkit.api)
    left_out: tuple[tuple[int, int, int, int, str], ...] = ()
    index: FrameIndex | None = None

    @property
    def n_annotations(self) -> int:
        """The annotation rows: the scene's own, or those its windows read (``index``)."""
        return len(self.obs) if self.index is None else self.index.rows

    @property
    def has_boxes(self) -> bool:
        """Whether an annotation row has a box: the scene's own, or those its windows read."""
        return bool(self.obs.has_box.any()) if self.index is None else self.index.boxes

    @property
    def all_warnings(self) -> tuple[str, ...]:
        """The loader's warnings plus what the scene assumes (fps, re-orthonormalised R)."""
        out = list(self.warnings)
        if self.fps_assumed:
            out.append(f"{self.fps_assumed}: assuming {self.fps:g} frames per second (set it, or "
                       "pass --fps: velocities and the motion model depend on it)")
        fixed = [c for c in self.rig.cameras if c.r_deviation > 0]
        if fixed:
            names = ", ".join(c.name for c in fixed[:4]) + (", ..." if len(fixed) > 4 else "")
            out.append(f"camera{'s' if len(fixed) > 1 else ''} {names}: R re-orthonormalised "
                       f"({len(fixed)} camera{'s' if len(fixed) > 1 else ''}, max |R R^T - I| "
                       f"was {max(c.r_deviation for c in fixed):.2g}: storage precision; see "
                       "meta.json calibration_notes)")
        return tuple(out)

    @property
    def calibration_notes(self) -> dict[str, str]:
        """Per camera, what was done to its calibration on loading (for ``meta.json``)."""
        return {c.name: f"R re-orthonormalised (max |R R^T - I| was {c.r_deviation:.2g})"
                for c in self.rig.cameras if c.r_deviation > 0}


@dataclass(frozen=True)
class RobustSummary:
    """What the robust update did: whether it ran, the measurements it down-weighted and rejected,
    and its rule (``meta.json``'s ``robust``)."""

    enabled: bool
    downweighted: int
    rejected: int
    rule: str


@dataclass(frozen=True)
class QASummary:
    """The annotation QA's findings (``meta.json``'s ``qa``): each kind's count, by kind's name, and
    the file that lists them."""

    anomalies: dict[str, int]
    file: str = "anomalies.csv"


@dataclass(frozen=True)
class IdentitySummary:
    """The identity check (``meta.json``'s ``identity``): the ids split and exchanged, the speed
    past which a jump splits an id (m/s), and the rule."""

    splits: int
    exchanges: int
    speed_limit_mps: float
    rule: str


@dataclass(frozen=True)
class DenseSummary:
    """A run with a row for every frame (``meta.json``'s ``every_frame``): the frame grid's frames,
    the rows no camera saw (interpolated), and what that means."""

    frames: int
    rows_interpolated: int
    note: str


@dataclass(frozen=True)
class WindowsSummary:
    """How a long sequence ran in windows (``meta.json``'s ``windows``): their count, frames each,
    the context around them, why they were sized so (None: given), how they were cut, each
    window's span, the process noise chosen once, a note, and the bones' first round's time (None:
    no such round)."""

    count: int
    frames: int
    overlap_frames: int
    why: str | None
    cut: str
    windows: list[JsonDict]
    process_noise: dict[str, float]
    note: str
    bones_round_seconds: float | None = None

    def as_json(self) -> JsonDict:
        out: JsonDict = {"count": self.count, "frames": self.frames, "overlap_frames": self.overlap_frames,
                         "why": self.why, "cut": self.cut, "windows": self.windows,
                         "process_noise": self.process_noise, "note": self.note}
        if self.bones_round_seconds is not None:
            out["bones_round_seconds"] = self.bones_round_seconds
        return out


@dataclass(frozen=True)
class RunInfo:
    """What a run used and found (``meta.json``'s ``estimator`` object, :meth:`as_json`): the
    fields other modules read, typed; each estimator's own diagnostics in ``details``.

    estimator : the estimator's name (:data:`gt3dkit.fusion.base.REGISTRY`)
    params : the settings used after any automatic tuning (the chosen process noise included)
    seconds : the estimator's time
    object_frames : rows estimated; skipped_lt2_views : rows a per-frame fit left out
    robust : the robust update's rule and counts; bones : the persons' bone lengths
    every_frame, identity, segments, qa, windows : what the run added around the estimator
        (dense rows, the identity check, its split ids' pieces, the anomaly counts, the time
        windows of a long sequence)
    details : everything else the estimator reports, as it reports it
    """

    estimator: str = ""
    params: JsonDict = field(default_factory=dict)
    seconds: float = 0.0
    object_frames: int | None = None
    skipped_lt2_views: int | None = None
    robust: RobustSummary | None = None
    bones: JsonDict | None = None
    every_frame: DenseSummary | None = None
    identity: IdentitySummary | None = None
    segments: list[JsonDict] = field(default_factory=list)
    qa: QASummary | None = None
    windows: WindowsSummary | None = None
    details: JsonDict = field(default_factory=dict)

    def as_json(self) -> JsonDict:
        """The fields as ``meta.json`` writes them (unset ones left out, ``details`` inline)."""
        out: JsonDict = {"estimator": self.estimator, "params": self.params, **self.details}
        for key in ("robust", "bones", "every_frame", "identity", "qa", "windows", "object_frames",
                    "skipped_lt2_views"):
            v = getattr(self, key)
            if v is not None:
                # the flat summaries as their fields (meta.json's keys are the fields' names)
                flat = is_dataclass(v) and not isinstance(v, WindowsSummary)
                out[key] = v.as_json() if isinstance(v, WindowsSummary) else asdict(v) if flat else v
        if self.segments:
            out["segments"] = self.segments
        out["seconds"] = self.seconds
        return out


@dataclass(frozen=True)
class TrackSet:
    """Estimator output: one row per (frame, object).

    Attributes
    ----------
    frame, track_id : (M,) int64
    center_world : (M, 3) float64, metres
    semi_axes : (M, 3) float64, metres, along body x, y, up
    center_sd : (M, 3) float64, metres, marginal standard deviation of the centre
    n_views : (M,) int64, cameras with an annotation of this object in this frame
    kpt_world : (M, J, 3) float64, metres (J may be 0)
    kpt_sd : (M, J) float64, metres: the largest standard deviation over all directions
        (square root of the largest eigenvalue of the joint's 3x3 covariance), so that the
        error along any axis is within ``k * sd`` at least as often as a 1-D Gaussian says
    info : RunInfo
        Estimator name, parameters and diagnostics for ``meta.json``.
    downweighted : Downweighted or None
        Every measurement the robust update down-weighted or rejected.
    """

    frame: I64
    track_id: I64
    center_world: F64
    semi_axes: F64
    center_sd: F64
    n_views: I64
    kpt_world: F64
    kpt_sd: F64
    info: RunInfo = field(default_factory=RunInfo)
    downweighted: Downweighted | None = None

    def __len__(self) -> int:
        return len(self.frame)

    def with_info(self, info: RunInfo) -> TrackSet:
        """These tracks with ``info`` (a :class:`RunInfo` is replaced, never edited in place:
        ``tracks.with_info(dataclasses.replace(tracks.info, qa=...))``)."""
        return replace(self, info=info)


@dataclass(frozen=True)
class Downweighted:
    """Measurements a robust estimator down-weighted (``0 < weight < 1``) or rejected (0).

    frame, cam, track_id : (K,) int64 (``cam`` indexes ``Rig.cameras``)
    joint : (K,) int64, -1 for a box edge
    edge : (K,) int64, 0..3 = xmin, ymin, xmax, ymax for a box edge, -1 for a keypoint
    weight : (K,) float64 in [0, 1)
    residual_px : (K,) float64, distance between the annotation and the estimate's
        projection (keypoint) or the edge's offset (box), pixels
    score : (K,) float64, the residual in standard deviations, judged against the other
        views (leave-one-out, see :mod:`gt3dkit.fusion.preparation.robust`)
    """

    frame: I64
    cam: I64
    track_id: I64
    joint: I64
    edge: I64
    weight: F64
    residual_px: F64
    score: F64

    def __len__(self) -> int:
        return len(self.frame)


@dataclass(frozen=True)
class SimScene:
    """A synthetic scene.

    frames : (T,) frame numbers; fps : frame-number rate
    truth_frame, truth_id : (M,); center_world (M, 3), semi_axes (M, 3), metres
    boxes : (M, C, 4) annotated boxes in pixels (NaN = not seen)
    """

    rig: Rig
    frames: I64
    fps: float
    truth_frame: I64
    truth_id: I64
    center_world: F64
    semi_axes: F64
    boxes: F64
    injected: tuple[tuple[int, str, int, str, str, str], ...] = ()


@dataclass(frozen=True)
class SkeletonScene:
    """A synthetic multi-person skeleton sequence.

    truth_frame, truth_id : (M,); kpt_world : (M, J, 3) metres
    uv : (M, C, J, 2) observed keypoints (NaN = not seen)
    """

    rig: Rig
    frames: I64
    fps: float
    skeleton: str
    truth_frame: I64
    truth_id: I64
    kpt_world: F64
    uv: F64
    conf: F64 | None = None  # (M, C, J) detector confidence, None = not written
    #: a skeleton a file describes (``Skeleton.doc``), None: the built-in ``skeleton`` names
    skeleton_doc: JsonDict | None = None
    injected: tuple[tuple[int, str, int, str, str, str], ...] = ()

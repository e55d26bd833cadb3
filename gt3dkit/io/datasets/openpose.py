"""OpenPose JSON per camera, as OpenPose and Pose2Sim write it.

Folders ``<camera>_json/`` in the input folder or in ``pose/``, one file per frame
(``<anything>_<frame>_keypoints.json``: the last number in the name is the frame) holding
``{"people": [{"person_id": [-1], "pose_keypoints_2d": [x0, y0, c0, x1, ...]}, ...]}``.
Skeletons by joint count: BODY_25 or BODY_25B (25, told apart by where joint 1 lies: the neck
between the shoulders, or the left eye), HALPE_26 (26), COCO-18 (18), COCO-17 (17); every
joint kept with the detector's own names on export; ``--skeleton`` overrides. A confidence of 0
is "not detected"; the others are passed on (a point's variance is sigma^2 / confidence).

Detections carry no identity: :func:`gt3dkit.fusion.preparation.detections.associate_detections` groups them
across views per frame and links the groups over time into people. Calibration as for
:mod:`gt3dkit.io.datasets.mot` (plus Pose2Sim's ``Calib*.toml``); the frame rate from the
calibration, ``--fps``, or a Pose2Sim ``Config.toml`` (``frame_rate``), else 30 assumed.
"""

from __future__ import annotations

import dataclasses
import json
import re
import tomllib
from pathlib import Path

import numpy as np

from gt3dkit.calib.formats import toml as toml_fmt
from gt3dkit.errors import InputError
from gt3dkit.io.datasets.checks import FAR_IMAGES, check_pixels
from gt3dkit.io.datasets.common import JointRows, RowBuilder
from gt3dkit.io.datasets.mot import calibration_beside, match_cameras, natural_key
from gt3dkit.io.datasets.native import read_kpt_truth_hashed, write_kpt_truth
from gt3dkit.io.skeletonfile import given_skeleton
from gt3dkit.parse import load_json, sha256
from gt3dkit.skeletons import DETECTOR_SKELETONS, SKELETONS, Skeleton
from gt3dkit.types import Camera, Origins, Rig, Scene, SkeletonScene

DEFAULT_FPS = 30.0


def camera_folders(root: Path) -> list[Path]:
    for base in (root, root / "pose"):
        found = sorted((p for p in base.glob("*_json") if p.is_dir()), key=lambda p: natural_key(p.name))
        if found:
            return found
    return []


def _frame_of(path: Path) -> int:
    nums = re.findall(r"\d+", path.name.replace("_keypoints", ""))
    if not nums:
        raise InputError(str(path), "no frame number in the file name")
    v = int(nums[-1])
    if v > 2**31 - 1:
        raise InputError(str(path), f"frame number {v} out of range")
    return v


def _config_fps(root: Path) -> float | None:
    for p in (root / "Config.toml", root.parent / "Config.toml"):
        if p.is_file():
            try:
                doc = tomllib.loads(p.read_text(encoding="utf-8"))
            except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError):
                return None
            fr = (doc.get("project") or {}).get("frame_rate")
            if isinstance(fr, int | float) and fr > 0:
                return float(fr)
    return None


def _which_25(sample: list[np.ndarray]) -> str:
    """BODY_25 (joint 1 = the neck, below the nose 0 by about the nose's distance from a shoulder
    5) or BODY_25B (joint 1 = the left eye, beside the nose): the distance of joint 1 from joint 0
    in units of joint 0's from joint 5, median over the detections that show all three (every
    view of a head and shoulders keeps the two apart: the real Shelf BODY_25 files give 0.92,
    BODY_25B about 0.2). The earlier test, joint 1 at the shoulders' midpoint, read a neck drawn
    above the shoulder line, or shoulders seen edge-on, as BODY_25B."""
    d = []
    for k in sample:
        if (k[[0, 1, 5], 2] > 0).all():
            w = np.linalg.norm(k[0, :2] - k[5, :2]) + 1e-9
            d.append(np.linalg.norm(k[1, :2] - k[0, :2]) / w)
    return "body25" if not d or float(np.median(d)) > BODY_25B_BELOW else "body25b"


#: :func:`_which_25`'s boundary: BODY_25's neck-nose distance is 0.6-1.3 nose-shoulder
#: distances (10th-90th percentile of real and simulated files), BODY_25B's eye-nose 0.15-0.27.
BODY_25B_BELOW = 0.4


#: Frame files of one camera gathered into one block of rows (:class:`_Detections`).
CHUNK_FILES = 2048


@dataclasses.dataclass
class _Detections:
    """One camera's detections of a run of frame files, gathered as arrays and added to a
    :class:`RowBuilder` at once (a row per detection: the frame, the camera, its index in its file),
    with :meth:`RowBuilder.add_joint` 's checks made on the arrays: a long recording is held as
    arrays, not a Python object per detection."""

    camera: Camera
    cam: int
    frame: list[int] = dataclasses.field(default_factory=list)
    index: list[int] = dataclasses.field(default_factory=list)
    kp: list[np.ndarray] = dataclasses.field(default_factory=list)
    file_of: list[int] = dataclasses.field(default_factory=list)  # each detection's file
    paths: list[str] = dataclasses.field(default_factory=list)

    @property
    def files(self) -> int:
        return len(self.paths)

    def add(self, frame: int, i: int, a: np.ndarray, path: Path) -> None:
        """Detection ``i`` of the frame file ``path``: ``a (J, 3)`` x, y, confidence."""
        if not self.paths or self.paths[-1] != str(path):
            self.paths.append(str(path))
        self.file_of.append(len(self.paths) - 1)
        self.frame.append(frame)
        self.index.append(i)
        self.kp.append(a)

    def flush_into(self, rb: RowBuilder | None, J: int | None) -> RowBuilder | None:
        """The detections gathered so far added to ``rb`` (made with ``J`` joints when None);
        :class:`InputError` at the first point (in reading order) no image could hold."""
        if not self.frame or J is None:
            return rb
        kp = np.stack(self.kp)  # (D, J, 3)
        index = np.asarray(self.index, dtype=np.int64)
        origin = Origins(tuple(Origins.literal(p) + ": people[{0}]" for p in self.paths),
                         np.asarray(self.file_of, dtype=np.int64), np.stack([index, np.zeros_like(index)], 1))
        seen = kp[..., 2] > 0  # a confidence of 0: not detected
        size = np.array([self.camera.width, self.camera.height], dtype=np.float64)
        inside = (kp[..., :2] >= -FAR_IMAGES * size) & (kp[..., :2] <= (1 + FAR_IMAGES) * size)
        far = seen & ~np.all(inside, axis=-1)
        if far.any():
            d, j = np.argwhere(far)[0]
            check_pixels(origin[int(d)], self.camera, list(kp[d, j, :2]), "keypoint")
        D = len(kp)
        keys = np.stack([np.asarray(self.frame), np.full(D, self.cam), index], 1).astype(np.int64)
        line = np.where(seen, np.arange(D)[:, None], -1)
        rows = JointRows(keys, np.arange(J), np.where(seen[..., None], kp[..., :2], np.nan),
                         np.where(seen, kp[..., 2], np.nan), line, origin)
        rb = rb if rb is not None else RowBuilder(n_joints=J)
        rb.add_joint_rows(rows)
        self.frame, self.index, self.kp, self.file_of, self.paths = [], [], [], [], []
        return rb


def _points_read(given: Skeleton | None, J: int) -> int:
    """Of detections of ``J`` points, how many are joints of the skeleton (given, or the one
    ``J`` names): all, or the first ones of a whole-body detector (``Skeleton.detector_points``)."""
    sk = [given] if given is not None else [SKELETONS[n] for n in DETECTOR_SKELETONS.get(J, ())]
    return sk[0].n_joints if sk and sk[0].detector_points == J else J


def _skeleton_of(given: Skeleton | None, J: int, sample: list[np.ndarray]) -> str:
    """The detector skeleton of ``J``-point detections (``sample``: some of them), or the given
    skeleton's name, checked against ``J``."""
    if given is None:
        opts = DETECTOR_SKELETONS[J]
        return opts[0] if len(opts) == 1 else _which_25(sample)
    if J not in (given.n_joints, given.detector_points):
        raise InputError("--skeleton", f"{given.name} has {given.n_joints} joints, the files {J}")
    return given.name


def _keypoints(where: str, person: object) -> np.ndarray:
    """One detection's ``pose_keypoints_2d`` as ``(J, 3)`` x, y, confidence (finite, confidence >=
    0); an error naming ``where`` otherwise. JSON's true/false are refused, not read as 1/0."""
    kp = person.get("pose_keypoints_2d") if isinstance(person, dict) else None
    if not isinstance(kp, list) or not all(type(v) in (int, float) for v in kp) or len(kp) % 3:
        raise InputError(where, "pose_keypoints_2d must be numbers x, y, confidence per joint")
    a = np.asarray(kp, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(a).all() or (a[:, 2] < 0).any():
        raise InputError(where, "a non-finite value or a negative confidence")
    return a


@dataclasses.dataclass
class _Reading:
    """What reading the files has found so far: the joints per detection ``J``, the first
    detections (to tell BODY_25 from BODY_25B), the largest confidence of each detection with
    one above 1, the files read and those whose people list is empty."""

    skeleton: Skeleton | None  # the one given (--skeleton), or None: the files' joint count names it
    J: int | None = None  # points per detection in the files
    kept: int | None = None  # of them read (COCO-WholeBody: its body and feet)
    sample: list[np.ndarray] = dataclasses.field(default_factory=list)
    above: list[float] = dataclasses.field(default_factory=list)
    n_files: int = 0
    empty: int = 0

    def read(self, p: Path, f: int, chunk: _Detections) -> None:
        """The detections of file ``p`` (frame ``f``) into ``chunk``."""
        doc = load_json(p)
        people = doc.get("people") if isinstance(doc, dict) else None
        if not isinstance(people, list):
            raise InputError(str(p), 'expected {"people": [...]}')
        self.n_files += 1
        self.empty += not people
        for i, person in enumerate(people):
            where = f"{p}: people[{i}]"
            a = _keypoints(where, person)
            if self.J is None:
                self.J = len(a)
                if self.skeleton is None and self.J not in DETECTOR_SKELETONS:
                    raise InputError(where, f"{self.J} joints: no known detector skeleton has that many "
                                            f"({', '.join(f'{k}' for k in DETECTOR_SKELETONS)})")
                self.kept = _points_read(self.skeleton, self.J)
            if len(a) != self.J:
                raise InputError(where, f"{len(a)} joints, the other detections have {self.J}")
            a = a[:self.kept]
            if (a[:, 2] > 1).any():  # a heatmap's peak, not a probability: OpenPose writes up to ~1.04
                self.above.append(float(a[:, 2].max()))
                a[:, 2] = np.minimum(a[:, 2], 1.0)
            if len(self.sample) < 500:
                self.sample.append(a)
            chunk.add(f, i, a, p)

    def warnings(self) -> list[str]:
        """The warnings of odd but valid files: confidences above 1, empty people lists, points
        not read (a whole-body detector's face and hands)."""
        out = []
        if self.J is not None and self.kept is not None and self.kept < self.J:
            whole = [k for k, v in SKELETONS.items() if v.n_joints == self.J and not v.detector_points]
            out.append(f"{self.J} points per detection: the first {self.kept} (body and feet) read, the "
                       f"other {self.J - self.kept} (face and hands) not"
                       + (f" (--skeleton {whole[0]} reads them all)" if whole else ""))
        if self.above:
            out.append(f"{len(self.above)} detection(s) with a confidence above 1 (up to "
                       f"{max(self.above):.4g}; OpenPose's confidences are heatmap peaks): read as 1")
        if self.empty:
            out.append(f"{self.empty} of {self.n_files} files list no person (frames where the detector "
                       "found no one in that camera)")
        return out


def load(
    root: Path, skeleton: str | None = None, calib: Path | str | None = None, fps: float | None = None
) -> Scene:
    """The detections as a scene whose ``track_id`` is the detection's index in its file
    (association makes people of them)."""
    root = Path(root)
    folders = camera_folders(root)
    if not folders:
        raise InputError(str(root), "no <camera>_json folders (in the folder or in pose/)")
    rig, fps_doc, cal = calibration_beside(root, calib)
    warnings: list[str] = []
    names = [p.name[: -len("_json")] for p in folders]
    cam_of = match_cameras(names, rig, str(root), warnings)
    files: dict[str, str] = {}
    given, doc = given_skeleton(skeleton) if skeleton is not None else (None, None)
    reading = _Reading(given)
    rb: RowBuilder | None = None
    for folder, name in zip(folders, names, strict=True):
        seen_frames: dict[int, Path] = {}
        chunk = _Detections(rig.cameras[cam_of[name]], cam_of[name])
        for p in sorted(folder.glob("*.json"), key=lambda q: natural_key(q.name)):
            f = _frame_of(p)
            if f in seen_frames:
                raise InputError(str(p), f"frame {f} again (also {seen_frames[f].name})")
            seen_frames[f] = p
            reading.read(p, f, chunk)
            if chunk.files >= CHUNK_FILES:  # held as arrays, not an object per detection
                rb = chunk.flush_into(rb, reading.kept)
        rb = chunk.flush_into(rb, reading.kept)
        files[f"{folder.name}/"] = f"{len(seen_frames)} files"
    J = reading.kept
    if rb is None or J is None or reading.J is None:
        raise InputError(str(root), "no annotations in any frame (no people in the JSON files)")
    warnings += reading.warnings()
    skeleton = _skeleton_of(given, reading.J, reading.sample)
    obs = rb.build()
    files[f"calibration:{cal.name}"] = sha256(cal) if cal.is_file() else "folder"
    truth = None
    if (root / "truth_keypoints.csv").exists():
        truth, files["truth_keypoints.csv"] = read_kpt_truth_hashed(root / "truth_keypoints.csv", J)
    cfg_fps = _config_fps(root)
    rate = fps or fps_doc or cfg_fps
    return Scene(
        truth=truth,
        rig=rig,
        obs=obs,
        layout="openpose",
        fps=float(rate or DEFAULT_FPS),
        frames=np.unique(obs.frame),
        skeleton=skeleton,
        skeleton_doc=doc,
        files=files,
        root=str(root),
        warnings=tuple(warnings),
        fps_assumed="" if rate else f"{cal} and Config.toml give no frame rate",
    )


def write(sim: SkeletonScene, tmp: Path, seed: int = 0, folder_names: list[str] | None = None) -> None:
    """A simulated skeleton scene as a Pose2Sim/OpenPose trial in ``tmp``, read by :func:`load`:
    ``calibration/Calib_scene.toml``
    (cameras ``cam_01``...), ``Config.toml`` with the frame rate, ``pose/<name>_json/`` with
    one OpenPose file per frame per camera, people in a random order without ids (undetected
    joints 0, 0, 0), and ``truth_keypoints.csv`` in the same z-up world. ``sim`` must be in a
    z-up world (:func:`gt3dkit.sim.to_z_up`) and a detector skeleton (body25, ...)."""
    rng = np.random.default_rng([seed, 7])
    names = folder_names or [f"cam{k + 1}" for k in range(len(sim.rig.cameras))]
    rig = Rig(tuple(dataclasses.replace(c, name=f"cam_{k + 1:02d}") for k, c in enumerate(sim.rig.cameras)),
              up=sim.rig.up, frame_name=sim.rig.frame_name)

    (tmp / "calibration").mkdir()
    toml_fmt.write(rig, tmp / "calibration" / "Calib_scene.toml")
    (tmp / "Config.toml").write_text(f"[project]\nframe_rate = {sim.fps:g}\n")
    J = SKELETONS[sim.skeleton].n_joints
    pad = [0.0] * 3 * max(SKELETONS[sim.skeleton].detector_points - J, 0)  # face and hands: not detected
    for c, name in enumerate(names):
        d = tmp / "pose" / f"{name}_json"
        d.mkdir(parents=True)
        for f in sim.frames:
            people = []
            for a in rng.permutation(np.flatnonzero(sim.truth_frame == f)):
                uv = sim.uv[a, c]
                if not np.isfinite(uv[:, 0]).any():
                    continue
                cf = sim.conf[a, c] if sim.conf is not None else np.full(J, 0.9)
                trip = np.where(np.isfinite(uv).all(axis=1)[:, None],
                                np.column_stack([uv, cf]), 0.0).ravel()
                people.append({"person_id": [-1],
                               "pose_keypoints_2d": [round(float(v), 3) for v in trip] + pad,
                               "face_keypoints_2d": [], "hand_left_keypoints_2d": [],
                               "hand_right_keypoints_2d": []})
            doc = {"version": 1.3, "people": people}
            (d / f"trial_{int(f):012d}_keypoints.json").write_text(json.dumps(doc))
    write_kpt_truth(sim, tmp / "truth_keypoints.csv")

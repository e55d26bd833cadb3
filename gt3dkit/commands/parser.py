"""``gt3d``'s command line: its options, one function a sub-command (``gt3d --help``)."""

from __future__ import annotations

import argparse

from gt3dkit.api import ESTIMATORS
from gt3dkit.calib.board import UNITS_M
from gt3dkit.calib.formats import WRITABLE
from gt3dkit.commands.calib import cmd_calib_board, cmd_calib_people, cmd_calib_refine, cmd_calib_show
from gt3dkit.commands.common import (
    ACCEL,
    FPS,
    FRACTION,
    PIXELS,
    SEED,
    SIGMA_PX,
    Parser,
    number_type,
    scheduler_address,
)
from gt3dkit.commands.demo import cmd_demo
from gt3dkit.commands.run import (
    cmd_associate,
    cmd_compare,
    cmd_evaluate,
    cmd_export,
    cmd_project,
    cmd_reconstruct,
    cmd_reconstruct_many,
    cmd_report,
)
from gt3dkit.commands.simulate import cmd_simulate
from gt3dkit.commands.skeleton import cmd_skeleton
from gt3dkit.early import DEFAULT_ESTIMATOR
from gt3dkit.export import FORMATS as EXPORT_FORMATS
from gt3dkit.io.datasets import LAYOUTS
from gt3dkit.io.labels import LABEL_FORMATS
from gt3dkit.io.skeletonfile import shipped_skeletons
from gt3dkit.sim import SIM_LAYOUTS
from gt3dkit.skeletons import SKELETONS
from gt3dkit.types import BOX_MODEL_REGISTRY, BOX_MODELS, LENSES

#: What ``gt3d --help`` says first.
DESCRIPTION = ("gt3d: 3D ground truth from 2D annotations and detections in calibrated cameras: "
               "an ellipsoid per object and frame, joints per person, each with its sd")


def _panoptic_options(p: argparse.ArgumentParser) -> None:
    """The options of a CMU Panoptic input (its 3D joints projected into the chosen cameras)."""
    p.add_argument("--cameras", help="CMU Panoptic: comma-separated HD cameras (default all)")
    p.add_argument("--noise-px", type=PIXELS, default=0.0, help="CMU Panoptic: noise added to the 2D joints")
    p.add_argument("--seed", type=SEED, help="CMU Panoptic: seed of that noise (default 0)")


def _scene_options(p: argparse.ArgumentParser) -> None:
    """How an input folder is read into a scene (``reconstruct`` and ``compare``)."""
    p.add_argument("--layout", choices=tuple(LAYOUTS), help="input layout (default: detected)")
    p.add_argument("--skeleton", metavar="NAME|FILE",
                   help="joint order of keypoints.csv: a built-in skeleton (" + ", ".join(sorted(SKELETONS))
                        + "), one shipped as a file (" + ", ".join(shipped_skeletons())
                        + ") or a skeleton file (.toml: joints, bones, left/right pairs)")
    _panoptic_options(p)
    p.add_argument("--fps", type=FPS, help="frame-number rate (default: the layout's)")
    p.add_argument("--calib", help="calibration file or folder in any format (cameras.json, WILDTRACK/"
                   "MultiviewX calibrations/, OpenCV .yml/.xml, Anipose .toml, COLMAP) for the input's own; "
                   "reconstruct: 'people' finds the poses from the people first (see gt3d calib people)")
    _calib_units(p)
    p.add_argument("--time-offsets", metavar="auto|FILE", help="cameras whose clocks disagree: each "
                   "camera's frames late (and frame rate) from a time_offsets.csv (as gt3d calib people "
                   "--clocks writes), or auto: found from the people; the UKF takes each view at its "
                   "own time")
    p.add_argument("--association", metavar="FILE", help="per-camera ids (mot): an edited association.csv "
                   "whose rows override the automatic cross-view association")
    p.add_argument("--segments", metavar="FILE", help="an edited segments.csv: its pieces replace the "
                                                      "automatic identity splits of the ids it lists")
    p.add_argument("--box-model", choices=("auto", *BOX_MODELS), default="auto", help="how boxes are "
                   "drawn: " + ", ".join(f"{e.name} ({e.summary})" for e in BOX_MODEL_REGISTRY.values())
                   + "; auto: chosen from the boxes")


def _estimating(sub: argparse._SubParsersAction[Parser], common: Parser, name: str, about: str,
                what: tuple[str, str], out: str) -> Parser:
    """Command ``name`` that estimates: its positional argument ``what`` (name, help), ``--out``
    and ``--estimator``."""
    p = sub.add_parser(name, parents=[common], help=about)
    p.add_argument(what[0], help=what[1])
    p.add_argument("--out", required=True, help=out)
    p.add_argument("--estimator", choices=ESTIMATORS, default=DEFAULT_ESTIMATOR)
    return p


def _add_reconstruct(sub: argparse._SubParsersAction[Parser], common: Parser) -> None:
    """``gt3d reconstruct``'s options."""
    r = _estimating(sub, common, "reconstruct", "2D boxes or keypoints from calibrated cameras -> 3D tracks",
                    ("input", "input folder (any layout)"), "output folder (tracks.csv, meta.json)")
    r.add_argument("--sigma-px", type=SIGMA_PX, help="box-edge noise (default: from the data)")
    r.add_argument("--accel-sd", type=ACCEL,
                   help="acceleration noise, m/s^2/sqrt(Hz) (default: max likelihood)")
    r.add_argument("--refine-calib", action="store_true",
                   help="refine the cameras from the annotations first (see gt3d calib refine)")
    r.add_argument("--no-smooth", action="store_true", help="forward filter only (no RTS)")
    r.add_argument("--every-frame", nargs="?", const=0, type=number_type(int, 1, 10**9), metavar="STEP",
                   help="a row for every frame of the input's grid (or every STEP frame numbers) from each "
                        "object's first to last annotation; tracks.csv gets n_views (0 = interpolated)")
    r.add_argument("--window", type=number_type(int, 0, 10**9), metavar="FRAMES", help="long recordings: "
                   "overlapping windows of FRAMES frames (default: when too long for memory; 0: never)")
    r.add_argument("--jobs", type=number_type(int, 1, 4096), help="--window: windows in N local processes")
    r.add_argument("--scheduler", metavar="ADDRESS", type=scheduler_address,
                   help="--window: windows on a running Dask scheduler")
    r.add_argument("--quiet", action="store_true", help="no progress display")
    r.add_argument("--no-bones", action="store_true", help="do not tie bone lengths")
    _scene_options(r)
    r.set_defaults(func=cmd_reconstruct, early=None)


def _add_simulate(sub: argparse._SubParsersAction[Parser], common: Parser) -> None:
    """``gt3d simulate``'s options."""
    s = sub.add_parser("simulate", parents=[common],
                       help="write a seeded synthetic scene with its truth")
    s.add_argument("--kind", choices=("boxes", "skeleton"), default="boxes")
    s.add_argument("--layout", choices=(*SIM_LAYOUTS, "panoptic"), default="native",
                   help="boxes: native|wildtrack|multiviewx; skeleton: native|panoptic")
    s.add_argument("--cameras", type=number_type(int, 1, 1000),
                   help="cameras (skeleton scenes: HD cameras, default 10; native boxes: 6)")
    s.add_argument("--fps", type=FPS, help="frame rate (skeletons: 30; native boxes: 10)")
    s.add_argument("--motion", choices=("smooth", "walk", "stop-and-turn"),
                   help="box scenes: smooth paths (default), walking, or walkers who stop and turn")
    s.add_argument("--labels", choices=BOX_MODELS, default="ellipsoid", help="box scenes: an ellipsoid's "
                   "tangent box, or a grid-placed cylinder's or occupancy-map rectangle (WILDTRACK's)")
    for flag, what in (("--outliers", "skeletons: fraction of keypoints replaced by far-off points"),
                       ("--swaps", "skeletons: fraction of person-views with one left/right pair swapped"),
                       ("--glitch", "skeletons: fraction of keypoints at x = 0 with a high confidence"),
                       ("--shifted", "boxes: fraction of boxes moved by 0.3-1 of their size")):
        s.add_argument(flag, type=FRACTION, default=0.0, help=what)
    s.add_argument("--cut-by-nearer", action="store_true",
                   help="boxes: drawn around the visible part of each person (a side a nearer "
                        "person's box covers ends where it begins), as detectors draw them")
    s.add_argument("--gap", help="FIRST:END frame indices with no annotation at all")
    s.add_argument("--single-view", type=FRACTION, default=0.0,
                   help="fraction of people annotated in one camera only")
    s.add_argument("--conf", action="store_true",
                   help="skeletons: write a detector confidence per keypoint")
    s.add_argument("--missing", type=number_type(float, 0, 1, hi_open=True),
                   help="skeleton scenes: fraction of 2D points dropped at random (default 0.05)")
    s.add_argument("--skeleton", metavar="NAME|FILE",
                   help="skeleton scenes: a built-in (default coco19) or a skeleton file with a [pose] (an "
                        "animal, a hand; native layout)")
    s.add_argument("--lens", choices=LENSES, default="pinhole",
                   help="the cameras' lenses: pinhole, or fisheye (wide, OpenCV's fisheye model; native "
                        "layout)")
    s.add_argument("--late-frames", metavar="D1,D2,...", help="skeleton scenes: each camera late by this "
                   "many frames (fractions too; its people's motion at its own time; written to "
                   "true_time_offsets.csv)")
    s.add_argument("--camera-fps", metavar="F1,F2,...", help="skeleton scenes: each camera's frame rate "
                   "(a little off --fps: a clock that drifts)")
    s.add_argument("--out", required=True)
    s.add_argument("--seed", type=SEED, default=0)
    s.add_argument("--frames", type=number_type(int, 1, 10**7), default=40)
    s.add_argument("--people", type=number_type(int, 1, 10**5), default=10)
    s.add_argument("--noise-px", type=PIXELS, default=0.0)
    s.add_argument("--dropout", type=number_type(float, 0, 1, hi_open=True),
                   help="box scenes: fraction of boxes dropped (default 0.15)")
    s.add_argument("--format", choices=("mot", "cvat", "coco", "openpose"),
                   help="write the annotations as users' tools do: boxes as mot/<camera>.txt "
                        "(MOTChallenge) or cvat/<camera>.xml (CVAT for video 1.1), each camera "
                        "numbering its people itself; skeletons as coco/<camera>.json (COCO "
                        "keypoints) or a Pose2Sim/OpenPose trial (z-up world, TOML calibration, "
                        "no ids)")
    s.add_argument("--global-ids", action="store_true",
                   help="with --format mot or cvat: keep one id per person across cameras")
    s.add_argument("--no-track-ids", action="store_true",
                   help="with --format coco: no track ids (detections per frame)")
    s.set_defaults(func=cmd_simulate)


def _add_compare(sub: argparse._SubParsersAction[Parser], common: Parser) -> None:
    """``gt3d compare``'s options."""
    c = sub.add_parser("compare", parents=[common],
                       help="UKF, GTSAM smoother and triangulation side by side")
    c.add_argument("input", help="input folder (any layout)")
    c.add_argument("--out", required=True, help="output folder (<estimator>/, comparison.csv)")
    _scene_options(c)
    c.add_argument("--no-progress", "--quiet", dest="no_progress", action="store_true",
                   help="no progress bar")
    c.set_defaults(func=cmd_compare)


def _add_evaluate(sub: argparse._SubParsersAction[Parser], common: Parser) -> None:
    """``gt3d evaluate``'s options."""
    e = sub.add_parser("evaluate", parents=[common],
                       help="score OUT/tracks.csv against an input's truth")
    e.add_argument("out", help="a reconstruct output folder")
    e.add_argument("--truth", required=True, help="the input folder that carries the truth")
    e.add_argument("--layout", choices=tuple(LAYOUTS))
    e.add_argument("--max-dist-m", type=number_type(float, 1e-6, 1e6), default=1.0,
                   help="ground-plane distance within which an estimate matches a true object "
                        "(MOTA, IDF1, HOTA, OSPA cut-off)")
    e.set_defaults(func=cmd_evaluate)


def _calib_units(p: argparse.ArgumentParser) -> None:
    p.add_argument("--calib-units", choices=("m", "cm", "mm"),
                   help="the calibration's unit of length where its format does not say it (Anipose's "
                        "calibration.toml holds its board's units; default m): the world is made metres")


def _rig_output_options(p: argparse.ArgumentParser) -> None:
    """How a rig found from the annotations is written (``--format``) and its input read."""
    p.add_argument("--format", choices=WRITABLE, default=None,
                   help="also write the rig in this format (into OUT/calibration/)")
    p.add_argument("--layout", choices=tuple(LAYOUTS))
    p.add_argument("--skeleton", metavar="NAME|FILE",
                   help="a built-in skeleton, one shipped as a file, or a skeleton file (.toml); a rig "
                        "from people reads up and the floor from its up and floor joints")
    p.add_argument("--fps", type=FPS)
    _calib_units(p)
    _panoptic_options(p)


def _add_calib(sub: argparse._SubParsersAction[Parser], common: Parser) -> None:
    """``gt3d calib``'s options."""
    k = sub.add_parser("calib", parents=[common], help="show, check and refine calibrations")
    ksub = k.add_subparsers(dest="calib_command", required=True, parser_class=Parser)
    ks = ksub.add_parser("show", parents=[common],
                         help="a table per camera and warnings for common calibration mistakes")
    ks.add_argument("input", help="an input folder (checked with its annotations) or a calibration "
                                  "file or folder in any format")
    _calib_units(ks)
    ks.set_defaults(func=cmd_calib_show)
    kr = ksub.add_parser("refine", parents=[common],
                         help="refine the rig from the annotations (validated on held-out frames)")
    kr.add_argument("input", help="input folder (any layout)")
    kr.add_argument("--out", required=True, help="output folder (cameras.json, calib_report.json)")
    kr.add_argument("--calib", help="start from this calibration instead of the input's own")
    kr.add_argument("--refine-intrinsics", action="store_true",
                    help="refine focal length and distortion too (keypoints only)")
    _rig_output_options(kr)
    kr.set_defaults(func=cmd_calib_refine)
    kp = ksub.add_parser("people", parents=[common],
                         help="the cameras' poses from the people in the scene: their keypoints (no board, "
                              "no identities), or their boxes (ids across cameras); intrinsics given")
    kp.add_argument("input", help="input folder with keypoints or boxes (any layout); its calibration's "
                                  "intrinsics are used, its poses are not")
    kp.add_argument("--out", required=True, help="output folder (cameras.json, calib_report.json)")
    kp.add_argument("--intrinsics", help="a calibration (any format) whose intrinsics are used instead of "
                                         "the input's")
    kp.add_argument("--focal-unknown", action="store_true",
                    help="the intrinsics are not known either: each camera's focal length is found too, "
                         "from 1.2 x its image's longer side, its principal point at the image's centre")
    kp.add_argument("--clocks", action="store_true",
                    help="find each camera's clock too (how many frames late, to a fraction; "
                         "OUT/time_offsets.csv), and the rig on the people moved onto one clock")
    kp.add_argument("--height", type=number_type(float, 0.5, 2.5),
                    help="the people's median standing height, m (default: the scale from typical adult "
                         "bone lengths, about 5 %% uncertain; from boxes, 1.7 m)")
    _rig_output_options(kp)
    kp.set_defaults(func=cmd_calib_people)
    kb = ksub.add_parser("board", parents=[common],
                         help="calibrate a rig from views of a ChArUco board or a checkerboard "
                              "(videos or images)")
    kb.add_argument("input", nargs="+",
                    help="one video or image folder per camera; or one folder of those; or Pose2Sim's "
                         "calibration folder (intrinsics/int_<cam>_img, extrinsics/ext_<cam>_img)")
    kb.add_argument("--board", required=True,
                    help="anipose's board.toml or config.toml, Pose2Sim's Config.toml, or a spec "
                         "charuco:8x11:24:18.75:DICT_4X4_1000 / checkerboard:9x6:25 (squares, lengths)")
    kb.add_argument("--board-units", choices=tuple(UNITS_M), default="mm",
                    help="the unit of the board's lengths (default mm)")
    kb.add_argument("--out", required=True, help="output folder (cameras.json, board_report.json, report/)")
    kb.add_argument("--format", choices=WRITABLE, default=None,
                    help="also write the rig in this format (into OUT/calibration/)")
    kb.add_argument("--step", type=number_type(int, 1, 1_000_000), default=1,
                    help="read every STEP-th frame of a video or image folder (default 1)")
    kb.add_argument("--cam-regex", help="camera name: the first group of this regular expression in each "
                                        "path (default: the names without what they all share)")
    kb.add_argument("--intrinsics", help="a calibration (any format) whose intrinsics are kept: only the "
                                         "poses are found")
    kb.add_argument("--intrinsics-only", action="store_true",
                    help="each camera saw the board on its own: intrinsics only, no poses")
    kb.add_argument("--origin", choices=("camera", "floor"), default="camera",
                    help="world frame: the first camera's, or the board as the floor (z up) (default camera)")
    kb.add_argument("--floor-frame", type=number_type(int, 0, 10**9),
                    help="with --origin floor: the frame whose board is the floor (default: the one most "
                         "cameras saw)")
    kb.add_argument("--holdout", type=number_type(int, 0, 10**6), default=0,
                    help="leave every K-th frame out of the fit and report its reprojection error "
                         "(default 0: none)")
    kb.add_argument("--lens", default="auto",
                    help="each camera's lens model: pinhole (OpenCV's k1 k2 p1 p2 k3), fisheye (OpenCV's "
                         "fisheye k1..k4) or auto (by the data: fisheye where it fits clearly better); "
                         "one for all, and/or CAM=MODEL pairs, comma-separated (default auto)")
    kb.set_defaults(func=cmd_calib_board)


def _add_reconstruct_many(sub: argparse._SubParsersAction[Parser], common: Parser) -> None:
    """``gt3d reconstruct-many``'s options."""
    m = _estimating(sub, common, "reconstruct-many",
                    "many input folders in parallel (local processes or a Dask cluster)",
                    ("manifest", "a text file: one input folder (or a glob) per line"),
                    "output folder: OUT/<input folder name>/ per sequence")
    m.add_argument("--jobs", type=number_type(int, 1, 4096), help="local worker processes (default: cores)")
    m.add_argument("--scheduler", metavar="ADDRESS", type=scheduler_address,
                   help="a running Dask distributed scheduler (tcp://host:8786) instead of local processes")
    m.add_argument("--report", action="store_true", help="also each sequence's report and OUT/index.html")
    m.add_argument("--quiet", action="store_true", help="no progress bar")
    m.add_argument("--skeleton", metavar="NAME|FILE", help="every sequence's skeleton, as gt3d reconstruct "
                                                          "takes it (a built-in name or a skeleton file)")
    m.add_argument("--fps", type=FPS, help="every sequence's frame-number rate (default: each layout's)")
    _calib_units(m)
    m.set_defaults(func=cmd_reconstruct_many)


def _add_associate(sub: argparse._SubParsersAction[Parser], common: Parser) -> None:
    """``gt3d associate``'s options."""
    a = sub.add_parser("associate", parents=[common],
                       help="per-camera ids (MOT files) -> global identities: OUT/association.csv")
    a.add_argument("input", help="input folder with per-camera ids (mot/<camera>.txt + calibration)")
    a.add_argument("--out", required=True, help="output folder (association.csv)")
    a.add_argument("--calib", help="calibration file or folder in any format")
    a.add_argument("--fps", type=FPS)
    a.add_argument("--association", metavar="FILE", help="an edited association.csv to apply")
    a.set_defaults(func=cmd_associate, layout=None, skeleton=None, cameras=None, noise_px=0.0, seed=None)


def _add_report(sub: argparse._SubParsersAction[Parser], common: Parser) -> None:
    """``gt3d report``'s options."""
    rp = sub.add_parser("report", parents=[common],
                        help="OUT/report/index.html for a reconstruct or compare output: 3D renders, "
                             "per-camera pictures, residuals, anomalies with pictures")
    rp.add_argument("out", metavar="OUT", help="a gt3d reconstruct or gt3d compare output folder")
    rp.add_argument("--frames", metavar="SOURCE", help="the cameras' own frames, to draw the estimate "
                    "over: SOURCE/<camera>.mp4, SOURCE/<camera>/<video> or SOURCE/<camera>/*.png "
                    "(report/overlays/, an H.264 video per camera)")
    rp.add_argument("--frame-offset", type=number_type(int, -10**9, 10**9), default=0, metavar="N",
                    help="--frames: annotation frame f is the video's frame f + N (default 0)")
    rp.add_argument("--overlay-step", type=number_type(int, 1, 10**6), default=1, metavar="K",
                    help="--frames: every K-th frame of the video (default 1)")
    rp.add_argument("--overlay-width", type=number_type(int, 16, 10**5), default=1280, metavar="PX",
                    help="--frames: the overlays at most PX wide (default 1280)")
    rp.add_argument("--scheduler", metavar="ADDRESS", type=scheduler_address,
                    help="--frames: a running Dask scheduler whose workers draw the overlays, a camera each "
                         "(the report's folder on a file system they share)")
    rp.add_argument("--quiet", action="store_true", help="no progress display")
    rp.set_defaults(func=cmd_report)


def _add_export(sub: argparse._SubParsersAction[Parser], common: Parser) -> None:
    """``gt3d export``'s options."""
    ex = sub.add_parser("export", parents=[common],
                        help="a reconstruct output as C3D, TRC (OpenSim), JSON or a Rerun recording")
    ex.add_argument("out", metavar="OUT", help="a gt3d reconstruct output folder")
    ex.add_argument("--format", required=True, choices=EXPORT_FORMATS)
    ex.add_argument("--to", metavar="DIR", help="folder to write (default OUT/export_FORMAT)")
    ex.add_argument("--joint-map", metavar="MAP.json", help="your mapping from the run's joints to another "
                    "skeleton's (each output joint a weighted sum of the run's, weights summing to 1; "
                    "docs/outputs.md): the export's joints are those; keypoints.csv keeps the detector's")
    ex.set_defaults(func=cmd_export)


def _add_project(sub: argparse._SubParsersAction[Parser], common: Parser) -> None:
    """``gt3d project``'s options."""
    pj = sub.add_parser("project", parents=[common],
                        help="a reconstruct output drawn back into every camera as CVAT, MOTChallenge or "
                             "COCO labels for review: the labels, proposals for views without one, "
                             "interpolations, each with its anomalies, sd and occlusion")
    pj.add_argument("out", metavar="OUT", help="a gt3d reconstruct output folder (or one estimator's "
                                               "folder of a gt3d compare output)")
    pj.add_argument("--format", required=True, choices=LABEL_FORMATS)
    pj.add_argument("--to", metavar="DIR", required=True,
                    help="folder to write: <format>/<camera>.*, cameras.json, projection.json "
                         "(gt3d reconstruct DIR reads it back)")
    pj.add_argument("--every-frame", metavar="STEP", nargs="?", const=1, default=None,
                    type=number_type(int, 1, 1_000_000),
                    help="also every STEP-th frame (default 1) between an object's labelled frames, "
                         "interpolated")
    pj.add_argument("--cameras", help="comma-separated camera names (default: all)")
    pj.add_argument("--only-flagged", action="store_true",
                    help="only what needs a person: labels with anomalies, proposals, interpolations")
    pj.set_defaults(func=cmd_project)


def _add_demo(sub: argparse._SubParsersAction[Parser], common: Parser) -> None:
    """``gt3d demo``'s options."""
    d = sub.add_parser("demo", parents=[common],
                       help="reconstruct the bundled MultiviewX and Panoptic data, print errors")
    d.add_argument("--out", default="out/demo", help="where to write (default out/demo)")
    d.set_defaults(func=cmd_demo)


def _add_skeleton(sub: argparse._SubParsersAction[Parser], common: Parser) -> None:
    """``gt3d skeleton``'s options."""
    k = sub.add_parser("skeleton", parents=[common],
                       help="the skeletons gt3dkit knows; one described and checked, or written to a "
                            "file to start your own")
    k.add_argument("skeleton", nargs="?", metavar="NAME|FILE",
                   help="a built-in, a shipped skeleton or a skeleton file (.toml); none: list them")
    k.add_argument("--write", metavar="FILE", help="write it as a skeleton file (.toml; never overwritten)")
    k.set_defaults(func=cmd_skeleton)


def build_parser() -> argparse.ArgumentParser:
    """The ``gt3d`` command line: one sub-command per function below."""
    common = Parser(add_help=False)
    common.add_argument("--debug", action="store_true",
                        help="show the Python traceback of an unexpected error")
    p = Parser(prog="gt3d", description=DESCRIPTION, parents=[common])
    sub = p.add_subparsers(dest="command", required=True, parser_class=Parser)

    for add in (_add_reconstruct, _add_simulate, _add_compare,
                _add_evaluate, _add_calib, _add_reconstruct_many, _add_associate,
                _add_report, _add_export, _add_project, _add_skeleton, _add_demo):
        add(sub, common)
    return p

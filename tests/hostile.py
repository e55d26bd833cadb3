"""A seeded hostile-input suite for the ``gt3d`` command line.

:func:`cases` makes, from a seed, malformed variants of every file of every input layout
(native boxes, native keypoints with confidences, WILDTRACK, MultiviewX, CMU Panoptic, a
result folder for ``gt3d evaluate``) and of every option of every command, plus odd but
valid inputs and misuses of the output folder. :func:`run_case` runs one (in this process
or as a real subprocess) and :func:`judge` checks the promise:

* bad input: exit status 2 and one line ``error: <file>: <entry>: <problem>`` naming what
  the case broke; no traceback; the output folder as it was (absent, or the earlier result
  intact); nothing left beside it; the input unchanged;
* odd but valid input: exit status 0, one ``warning:`` line per kind (naming it), a complete
  result, the input unchanged.

``tests/test_hostile.py`` runs it; ``scripts/reliability_targets.py`` runs more seeds and
counts tracebacks, wrong exit codes, leftovers and silent acceptances.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import random
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from gt3dkit.sim import Errors

ERROR, WARN, OK, EITHER = "error", "warn", "ok", "either"
MARKER = ".gt3dkit-output"

Mutation = Callable[[Path], None]


@dataclass(frozen=True)
class Case:
    """One run of ``gt3d``: a base input copied to ``{in}`` and changed by ``mutate``."""

    name: str
    base: str | None  # a folder made by make_bases, copied to {in}; None = no input
    argv: tuple[str, ...]  # placeholders: {in} {out} {bases} {work}
    expect: str  # ERROR, WARN, OK or EITHER (exit 0 or a clean error)
    needles: tuple[str, ...] = ()  # in the error line / each in exactly one warning line
    mutate: Mutation | None = None
    prev: bool = True  # {out} holds an earlier result, which a failure must leave intact
    writes: bool = True  # the command writes {out} when it succeeds


@dataclass
class Outcome:
    case: Case
    code: int
    stdout: str
    stderr: str
    problems: list[str] = field(default_factory=list)


# ----------------------------------------------------------------------------- bases


def make_bases(root: Path) -> Path:
    """Small simulated inputs of every layout, and a result folder, under ``root``."""
    from gt3dkit.cli import main
    from gt3dkit.sim import simulate, simulate_skeletons, write_scene, write_skeleton_scene

    root.mkdir(parents=True, exist_ok=True)
    write_scene(simulate("native", seed=1, frames=5, people=3, errors=Errors(dropped=0.0)), root / "boxes",
                "native")
    write_scene(simulate("wildtrack", seed=1, frames=3, people=2, errors=Errors(dropped=0.0)),
                root / "wildtrack",
                "wildtrack")
    write_scene(simulate("multiviewx", seed=1, frames=3, people=2, errors=Errors(dropped=0.0)),
                root / "multiviewx", "multiviewx")
    write_skeleton_scene(simulate_skeletons("native", seed=1, frames=4, people=2, cameras=4,
                                            skeleton="coco17", confidences=True, noise_px=1.0),
                         root / "kpts", "native")
    write_skeleton_scene(simulate_skeletons("panoptic", seed=1, frames=3, people=2, cameras=3),
                         root / "panoptic", "panoptic")
    from gt3dkit.sim import to_z_up, write_coco, write_openpose

    write_scene(simulate("wildtrack", seed=1, frames=4, people=3, errors=Errors(dropped=0.0)), root / "mot",
                "mot")
    write_scene(simulate("wildtrack", seed=1, frames=4, people=3, errors=Errors(dropped=0.0)),
                root / "cvat", "cvat")
    sk = simulate_skeletons("native", seed=1, frames=4, people=2, cameras=4, noise_px=1.0, skeleton="body25",
                            confidences=True)
    write_openpose(to_z_up(sk), root / "openpose")
    sk = simulate_skeletons("native", seed=1, frames=4, people=2, cameras=4, noise_px=1.0)
    write_coco(sk, root / "coco")
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        code = main(["reconstruct", str(root / "boxes"), "--out", str(root / "result"),
                     "--estimator", "triangulation"])
    assert code == 0, f"the base result could not be made: {err.getvalue()}"
    for p in root.rglob(MARKER):
        p.unlink()  # bases are inputs, not gt3dkit outputs of a test
    (root / "result" / MARKER).write_text("{}\n")
    return root


# ----------------------------------------------------------------------------- mutations


def _lines(p: Path) -> list[str]:
    return p.read_text().splitlines()


def _write_lines(p: Path, lines: list[str]) -> None:
    p.write_text("\n".join(lines) + "\n")


def csv_set(rel: str, line: int, col: int, value: str) -> Mutation:
    """Field ``col`` of data line ``line`` (1 = first after the header) set to ``value``."""
    def m(root: Path) -> None:
        lines = _lines(root / rel)
        f = lines[line].split(",")
        f[col] = value
        lines[line] = ",".join(f)
        _write_lines(root / rel, lines)
    return m


def csv_edit(rel: str, edit: Callable[[list[str]], list[str]]) -> Mutation:
    def m(root: Path) -> None:
        _write_lines(root / rel, edit(_lines(root / rel)))
    return m


def raw(rel: str, edit: Callable[[bytes], bytes]) -> Mutation:
    def m(root: Path) -> None:
        p = root / rel
        p.write_bytes(edit(p.read_bytes()))
    return m


def json_edit(rel: str, edit: Callable[[object], object]) -> Mutation:
    def m(root: Path) -> None:
        p = root / rel
        p.write_text(json.dumps(edit(json.loads(p.read_text()))))
    return m


def remove(rel: str) -> Mutation:
    def m(root: Path) -> None:
        p = root / rel
        shutil.rmtree(p) if p.is_dir() else p.unlink()
    return m


def chain(*ms: Mutation) -> Mutation:
    def m(root: Path) -> None:
        for f in ms:
            f(root)
    return m


def _leaves(doc: object, path: tuple = ()) -> list[tuple]:
    if isinstance(doc, dict):
        return [p for k, v in doc.items() for p in _leaves(v, (*path, k))] or [path]
    if isinstance(doc, list):
        return [p for i, v in enumerate(doc) for p in _leaves(v, (*path, i))] or [path]
    return [path]


def _set_at(doc: object, path: tuple, value: object, delete: bool = False) -> object:
    if not path:
        return value
    parent = doc
    for k in path[:-1]:
        parent = parent[k]  # type: ignore[index]
    if delete:
        del parent[path[-1]]  # type: ignore[union-attr]
    else:
        parent[path[-1]] = value  # type: ignore[index]
    return doc


# ----------------------------------------------------------------------------- the cases

#: What each CSV column holds: int (non-negative), id, cam, coord, conf, real.
CSV_KINDS = {
    "boxes.csv": ("frame", "id_", "cam", "coord", "coord", "coord", "coord"),
    "keypoints.csv": ("frame", "cam", "id_", "joint", "coord", "coord", "conf"),
    "truth.csv": ("frame", "id_", "real", "real", "real", "pos", "pos", "pos"),
    "truth_keypoints.csv": ("frame", "id_", "joint", "real", "real", "real"),
    "tracks.csv": ("frame", "id_", "real", "real", "real", "pos", "pos", "pos", "pos", "pos", "pos"),
}
NOT_A_NUMBER = ("", "abc", "nan", "inf", "-inf", "0x1f", "1,,2", " - ")
NOT_AN_INT = (*NOT_A_NUMBER, "1.5", "1e23", "99999999999999999999999")
BAD_COORD = (*NOT_A_NUMBER, "1e308", "-1e308", "1e23")
ODD_COORD = ("-5", "0", "1e4", "1919.9")


def _bad_values(kind: str) -> tuple[tuple[str, str], ...]:
    """(value, expectation) for a CSV column of ``kind``."""
    ints = tuple((v, ERROR) for v in NOT_AN_INT if v != "1,,2")
    if kind == "frame":
        return (*ints, ("-1", ERROR), ("3000000000", ERROR))
    if kind == "id_":
        return (*ints, ("-1", EITHER), ("123456789012", EITHER))
    if kind == "joint":
        return (*ints, ("-1", ERROR), ("17", ERROR), ("400", ERROR))
    if kind == "cam":
        return (("", ERROR), ("ghost", ERROR), ("CAM0", ERROR))
    if kind == "coord":
        return (*((v, ERROR) for v in BAD_COORD if v != "1,,2"), *((v, EITHER) for v in ODD_COORD))
    if kind == "conf":
        return (("-0.1", ERROR), ("1.5", WARN), ("2.5", ERROR), ("nan", ERROR), ("abc", ERROR), ("0", WARN),
                ("1e-9", EITHER))
    if kind == "pos":
        return (("nan", ERROR), ("abc", ERROR), ("inf", ERROR), ("-1", ERROR), ("", ERROR))
    return (("nan", ERROR), ("abc", ERROR), ("inf", ERROR), ("", ERROR), ("1e300", EITHER))


def _recon(est: str = "triangulation") -> tuple[str, ...]:
    return ("reconstruct", "{in}", "--out", "{out}", "--estimator", est)


def _csv_cases(rng: random.Random, base: str, rel: str, argv: tuple[str, ...],
               n_rows: int) -> list[Case]:
    kinds = CSV_KINDS[Path(rel).name]
    out = []
    name = f"{base}/{rel}"
    for col, kind in enumerate(kinds):
        values = _bad_values(kind)
        for value, expect in rng.sample(values, min(3, len(values))):
            line = rng.randrange(1, n_rows + 1)
            needles = (rel.split("/")[-1], f"line {line + 1}") if expect == ERROR else ()
            if kind == "conf" and value == "0":
                needles = ("confidence 0",)
            out.append(Case(f"{name}: line {line + 1} col {col} = {value!r}", base, argv, expect,
                            needles, csv_set(rel, line, col, value)))
    line = rng.randrange(1, n_rows + 1)
    structural: list[tuple[str, str, tuple[str, ...], Mutation]] = [
        ("extra field", ERROR, (f"line {line + 1}", "fields"),
         csv_edit(rel, lambda ls: [*ls[:line], ls[line] + ",7", *ls[line + 1:]])),
        ("missing field", ERROR, (f"line {line + 1}", "fields"),
         csv_edit(rel, lambda ls: [*ls[:line], ls[line].rsplit(",", 1)[0], *ls[line + 1:]])),
        ("duplicated row", ERROR, ("second",),
         csv_edit(rel, lambda ls: [*ls, ls[line]])),
        ("empty file", ERROR, (rel.split("/")[-1],), raw(rel, lambda b: b"")),
        ("no header", ERROR, ("header",), csv_edit(rel, lambda ls: ls[1:])),
        ("renamed header", ERROR, ("header",),
         csv_edit(rel, lambda ls: [ls[0].replace("frame", "Frame"), *ls[1:]])),
        ("truncated header", ERROR, ("header",), raw(rel, lambda b: b[:5])),
        ("truncated inside the data", EITHER, (),
         raw(rel, lambda b: b[:len(b) // 2 + rng.randrange(-20, 20)])),
        ("NUL byte", ERROR, (f"line {line + 1}",),
         csv_edit(rel, lambda ls: [*ls[:line], ls[line][:3] + "\0" + ls[line][3:], *ls[line + 1:]])),
        ("latin-1 byte", ERROR, (rel.split("/")[-1], "UTF-8"),
         raw(rel, lambda b: b.replace(b",", b",\xe9", 1))),
        ("binary garbage", ERROR, (rel.split("/")[-1],),
         raw(rel, lambda b: bytes(rng.randrange(256) for _ in range(300)))),
        ("200000-character field", ERROR, (f"line {line + 1}",),
         csv_edit(rel, lambda ls: [*ls[:line], ls[line] + "x" * 200_000, *ls[line + 1:]])),
        ("UTF-8 byte-order mark (Excel)", OK, (), raw(rel, lambda b: b"\xef\xbb\xbf" + b)),
        ("CRLF line ends", OK, (), raw(rel, lambda b: b.replace(b"\n", b"\r\n"))),
        ("blank lines", OK, (), csv_edit(rel, lambda ls: [ls[0], "", *ls[1:], "", " "])),
        # our own formats (truth*.csv, tracks.csv) are exact; annotations may carry more columns
        ("extra column", WARN if rel in ("boxes.csv", "keypoints.csv") else ERROR,
         ("ignored",) if rel in ("boxes.csv", "keypoints.csv") else ("unexpected columns",),
         csv_edit(rel, lambda ls: [ls[0] + ",note", *(x + ",hello" for x in ls[1:])])),
    ]
    for label, expect, needles, m in structural:
        out.append(Case(f"{name}: {label}", base, argv, expect, needles, m))
    return out


def _json_cases(rng: random.Random, base: str, rel: str, argv: tuple[str, ...]) -> list[Case]:
    name = f"{base}/{rel}"
    fname = Path(rel).name
    out = [
        Case(f"{name}: truncated", base, argv, ERROR, (fname, "JSON"),
             raw(rel, lambda b: b[: max(1, int(len(b) * rng.uniform(0.05, 0.95)))])),
        Case(f"{name}: 100000 nested [", base, argv, ERROR, (fname, "nested"),
             raw(rel, lambda b: b"[" * 100_000 + b"]" * 100_000)),
        Case(f"{name}: empty", base, argv, ERROR, (fname,), raw(rel, lambda b: b"")),
        Case(f"{name}: not UTF-8", base, argv, ERROR, (fname, "UTF-8"),
             raw(rel, lambda b: b"\xff\xfe" + b)),
        Case(f"{name}: byte-order mark", base, argv, OK, (), raw(rel, lambda b: b"\xef\xbb\xbf" + b)),
    ]
    for doc in ([], 42, "x", None, {}):
        empty_frame = doc == [] and "annotations_positions" in rel  # a frame with nobody: valid
        out.append(Case(f"{name}: document {json.dumps(doc)}", base, argv,
                        OK if empty_frame else ERROR, () if empty_frame else (fname,),
                        json_edit(rel, lambda d, doc=doc: doc)))
    values = ("x", None, [], {}, -1, 0, 1e308, float("nan"), True, 10**23, [[[]]])
    for _ in range(6):
        value = rng.choice(values)

        def pick(d: object, value: object = value, r: int = rng.randrange(10**9)) -> object:
            leaves = _leaves(d)
            return _set_at(d, leaves[r % len(leaves)], value)
        out.append(Case(f"{name}: a leaf = {value!r}", base, argv, EITHER, (),
                        json_edit(rel, pick)))

    def drop(d: object, r: int = rng.randrange(10**9)) -> object:
        leaves = [p for p in _leaves(d) if p]
        return _set_at(d, leaves[r % len(leaves)], None, delete=True) if leaves else d
    out.append(Case(f"{name}: a key or item deleted", base, argv, EITHER, (), json_edit(rel, drop)))
    return out


def _xml_cases(rng: random.Random, base: str, rel: str, argv: tuple[str, ...]) -> list[Case]:
    name = f"{base}/{rel}"
    fname = Path(rel).name
    return [
        Case(f"{name}: truncated", base, argv, ERROR, (fname,),
             raw(rel, lambda b: b[: max(1, int(len(b) * rng.uniform(0.1, 0.9)))])),
        Case(f"{name}: empty", base, argv, ERROR, (fname,), raw(rel, lambda b: b"")),
        Case(f"{name}: a number is nan", base, argv, ERROR, (fname,),
             raw(rel, lambda b: re.sub(rb"(<data>\s*)[-0-9.eE+]+", rb"\1nan", b, count=1)
                 if b"<data>" in b else re.sub(rb"(<rvec>\s*)[-0-9.eE+]+", rb"\1nan", b, count=1))),
        Case(f"{name}: missing", base, argv, ERROR, (fname,), remove(rel)),
        Case(f"{name}: a matrix removed", base, argv, ERROR, (fname, "missing"),
             raw(rel, lambda b: re.sub(rb"<(camera_matrix|tvec)[ >].*?</\1>", b"", b, flags=re.S))),
    ]


def _cam(d: dict, i: int = 0) -> dict:
    return d["cameras"][i]  # type: ignore[no-any-return]


def _camera_cases(argv: tuple[str, ...]) -> list[Case]:
    """Targeted cameras.json errors: each must be named."""
    def edit(f: Callable[[dict], None]) -> Mutation:
        def g(d: object) -> object:
            f(d)  # type: ignore[arg-type]
            return d
        return json_edit("cameras.json", g)

    c = "cameras.json"
    return [
        Case("cameras.json: fps 'ten'", "boxes", argv, ERROR, (c, "fps"),
             edit(lambda d: d.update(fps="ten"))),
        Case("cameras.json: fps 1e-300", "boxes", argv, ERROR, (c, "fps"),
             edit(lambda d: d.update(fps=1e-300))),
        Case("cameras.json: fps -10", "boxes", argv, ERROR, (c, "fps"), edit(lambda d: d.update(fps=-10))),
        Case("cameras.json: no fps", "boxes", argv, WARN, ("no \"fps\"",), edit(lambda d: d.pop("fps"))),
        Case("cameras.json: dist of 3 coefficients", "boxes", argv, ERROR, (c, "cam1", "dist"),
             edit(lambda d: _cam(d, 1).update(dist=[0.1, 0.0, 0.0]))),
        Case("cameras.json: dist of 8 with k4..k6", "boxes", argv, ERROR, (c, "dist"),
             edit(lambda d: _cam(d).update(dist=[0, 0, 0, 0, 0, 0.1, 0, 0]))),
        Case("cameras.json: K with a string", "boxes", argv, ERROR, (c, "cam0"),
             edit(lambda d: _cam(d)["K"][0].__setitem__(0, "f"))),
        Case("cameras.json: dist k1 = -1 (folds the image)", "boxes", argv, ERROR, (c, "cam1", "folds"),
             edit(lambda d: _cam(d, 1).update(dist=[-1.0, 0, 0, 0, 0]))),
        Case("cameras.json: dist p1 = -1 (folds the image)", "kpts", argv, ERROR, (c, "folds"),
             edit(lambda d: _cam(d, 1).update(dist=[0, 0, -1.0, 0, 0]))),
        Case("cameras.json: dist k3 = 1e308", "boxes", argv, ERROR, (c, "dist"),
             edit(lambda d: _cam(d).update(dist=[0, 0, 0, 0, 1e308]))),
        Case("cameras.json: K[2][0] = 1e308", "boxes", argv, ERROR, (c, "cam0", "upper triangular"),
             edit(lambda d: _cam(d)["K"][2].__setitem__(0, 1e308))),
        Case("cameras.json: R entry 1e308", "boxes", argv, ERROR, (c, "cam0", "rotation"),
             edit(lambda d: _cam(d)["R"][2].__setitem__(1, 1e308))),
        Case("cameras.json: K 2x2", "boxes", argv, ERROR, (c, "cam0", "K"),
             edit(lambda d: _cam(d).update(K=[[1, 0], [0, 1]]))),
        Case("cameras.json: negative focal length", "boxes", argv, ERROR, (c, "cam0", "focal"),
             edit(lambda d: _cam(d)["K"][0].__setitem__(0, -1000.0))),
        Case("cameras.json: width 0", "boxes", argv, ERROR, (c, "cam0", "width"),
             edit(lambda d: _cam(d).update(width=0))),
        Case("cameras.json: width 1e23", "boxes", argv, ERROR, (c, "cam0", "width"),
             edit(lambda d: _cam(d).update(width=1e23))),
        Case("cameras.json: height 'tall'", "boxes", argv, ERROR, (c, "cam0", "height"),
             edit(lambda d: _cam(d).update(height="tall"))),
        Case("cameras.json: R not a rotation", "boxes", argv, ERROR, (c, "cam0", "rotation"),
             edit(lambda d: _cam(d).update(R=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]))),
        Case("cameras.json: R stored to 5 digits", "boxes", argv, WARN, ("re-orthonormalised",),
             edit(lambda d: _cam(d).update(R=[[round(v, 5) for v in r] for r in _cam(d)["R"]]))),
        Case("cameras.json: t of 2", "boxes", argv, ERROR, (c, "cam0", "t"),
             edit(lambda d: _cam(d).update(t=[0, 1]))),
        Case("cameras.json: t with null", "boxes", argv, ERROR, (c, "cam0", "t"),
             edit(lambda d: _cam(d).update(t=[0, None, 1]))),
        Case("cameras.json: duplicate camera", "boxes", argv, ERROR, (c, "duplicate"),
             edit(lambda d: d["cameras"].append(dict(_cam(d))))),
        Case("cameras.json: up zero", "boxes", argv, ERROR, (c, "up"),
             edit(lambda d: d.update(up=[0, 0, 0]))),
        Case("cameras.json: no cameras", "boxes", argv, ERROR, (c,), edit(lambda d: d.update(cameras=[]))),
        Case("cameras.json: camera without name", "boxes", argv, ERROR, (c, "name"),
             edit(lambda d: _cam(d).pop("name"))),
        Case("cameras.json: unknown skeleton", "kpts", argv, ERROR, (c, "skeleton"),
             edit(lambda d: d.update(skeleton="octopus"))),
        Case("cameras.json: skeleton [1]", "kpts", argv, ERROR, (c, "skeleton"),
             edit(lambda d: d.update(skeleton=[1]))),
        Case("cameras.json: camera turned around", "boxes", argv, ERROR, ("boxes.csv", "behind"),
             edit(lambda d: _cam(d).update(R=[[-v for v in r] if i != 1 else r
                                               for i, r in enumerate(_cam(d)["R"])],
                                            t=[-_cam(d)["t"][0], _cam(d)["t"][1], -_cam(d)["t"][2]]))),
    ]


def _odd_cases() -> list[Case]:
    """Odd but valid inputs: the run succeeds and says so, once per kind."""
    r = ("reconstruct", "{in}", "--out", "{out}")

    def boxes_of(ids: set[str], keep_cam: str) -> Mutation:
        return csv_edit("boxes.csv", lambda ls: [ls[0], *(x for x in ls[1:] if x.split(",")[2] not in ids
                                                          or x.split(",")[1] == keep_cam)])

    def one_camera(root: Path) -> None:
        d = json.loads((root / "cameras.json").read_text())
        d["cameras"] = d["cameras"][:1]
        (root / "cameras.json").write_text(json.dumps(d))
        _write_lines(root / "boxes.csv", [x for x in _lines(root / "boxes.csv")
                                         if x.startswith("frame") or x.split(",")[1] == "cam0"])

    def gap(root: Path) -> None:  # object 0 unseen in frames 1..3 (0.3 s at 10 fps) -> 4 frames at 1 fps
        d = json.loads((root / "cameras.json").read_text())
        d["fps"] = 1.0
        (root / "cameras.json").write_text(json.dumps(d))
        _write_lines(root / "boxes.csv", [x for x in _lines(root / "boxes.csv") if x.startswith("frame")
                                         or not (x.split(",")[2] == "0" and x.split(",")[0] in "123")])

    def off_image(root: Path) -> None:  # two boxes of cam2 moved entirely left of the image
        ls = _lines(root / "boxes.csv")
        n = 0
        for i, x in enumerate(ls[1:], 1):
            f = x.split(",")
            if f[1] == "cam2" and n < 2:
                w = float(f[5]) - float(f[3])
                f[3], f[5] = f"{-w - 40:.1f}", "-40"
                ls[i] = ",".join(f)
                n += 1
        _write_lines(root / "boxes.csv", ls)

    def minus_ones(root: Path) -> None:
        _write_lines(root / "boxes.csv", [*_lines(root / "boxes.csv"), "2,cam3,1,-1,-1,-1,-1"])

    def kpt_lone(root: Path) -> None:
        _write_lines(root / "keypoints.csv", [*_lines(root / "keypoints.csv"), "100,00_01,42,3,900,500,0.9"])

    return [
        Case("odd: object seen by one camera only (ukf)", "boxes", (*r, "--estimator", "ukf"), WARN,
             ("only ever seen by one camera",), boxes_of({"1"}, "cam2")),
        Case("odd: object seen by one camera only (gtsam)", "boxes", (*r, "--estimator", "gtsam"), WARN,
             ("only ever seen by one camera",), boxes_of({"1"}, "cam2")),
        Case("odd: a one-camera rig", "boxes", (*r, "--estimator", "ukf"), WARN, ("one camera only",),
             one_camera),
        Case("odd: a gap of 4 s", "boxes", (*r, "--estimator", "ukf"), WARN, ("gaps of more than",), gap),
        Case("odd: boxes entirely outside the image", "boxes", (*r, "--estimator", "ukf"), WARN,
             ("2 boxes lie entirely outside",), off_image),
        Case("odd: a box of -1s in boxes.csv", "boxes", (*r, "--estimator", "triangulation"), WARN,
             ("boxes of -1s",), minus_ones),
        Case("odd: keypoint object in one view", "kpts", (*r, "--estimator", "ukf"), WARN,
             ("keypoints only are only ever seen by one camera",), kpt_lone),
        Case("odd: compare with one-view object", "boxes", ("compare", "{in}", "--out", "{out}",
                                                             "--no-progress"), WARN,
             ("only ever seen by one camera",), boxes_of({"2"}, "cam4")),
    ]


def _someones_folder(root: Path) -> None:
    (root.parent / "mine").mkdir()
    (root.parent / "mine" / "notes.txt").write_text("keep me")


def _panoptic_conf_zero(root: Path) -> None:
    for p in (root / "hdPose3d_stage1_coco19").glob("*.json"):
        d = json.loads(p.read_text())
        for b in d["bodies"]:
            b["joints19"][3::4] = [0.0] * len(b["joints19"][3::4])
        p.write_text(json.dumps(d))


def _colmap_without_images(root: Path) -> None:
    from gt3dkit.calib.formats import write_calibration

    col = root.parent / "col"
    write_calibration(_any_rig(), col, "colmap")
    for f in ("images.txt", "frames.txt"):
        (col / f).write_text("".join(x + "\n" for x in (col / f).read_text().splitlines()
                                     if x.startswith("#")))


def _any_rig():  # a small rig, independent of the bases
    from gt3dkit.sim import simulate

    return simulate("native", seed=0, frames=3, people=1).rig


def _calib_without_last_camera(root: Path) -> None:
    from gt3dkit.calib.formats import read_calibration, write_calibration
    from gt3dkit.rig import Rig

    rig = read_calibration(root)
    write_calibration(Rig(rig.cameras[:-1], up=rig.up), root.parent / "c", "toml")


def _option_cases() -> list[Case]:
    """Every numeric option of every command with values it must refuse, and misuses."""
    out = []
    bad_real = ("nan", "inf", "-inf", "-1", "abc", "", "1e300", "1e-300")
    bad_count = ("nan", "0", "-3", "1.5", "abc", "1e9")
    rec = ("reconstruct", "{in}", "--out", "{out}")
    sim = ("simulate", "--out", "{out}")
    options = [
        (rec, "--fps", bad_real + ("0",)), (rec, "--sigma-px", bad_real + ("0",)),
        (rec, "--accel-sd", bad_real + ("0",)), (rec, "--noise-px", ("nan", "inf", "-1", "abc")),
        (rec, "--seed", ("-1", "1.5", "abc", "1e30")),
        (("compare", "{in}", "--out", "{out}"), "--fps", ("nan", "inf", "0", "1e-300")),
        (("evaluate", "{bases}/result", "--truth", "{in}"), "--max-dist-m", bad_real + ("0",)),
        (sim, "--noise-px", ("nan", "inf", "-1")), (sim, "--fps", ("nan", "0", "inf", "1e-300")),
        (sim, "--frames", bad_count + ("100000000",)), (sim, "--people", bad_count),
        (sim, "--cameras", bad_count), (sim, "--dropout", ("nan", "1", "-0.1", "2")),
        (sim, "--outliers", ("nan", "2", "-1")), (sim, "--single-view", ("nan", "1.5")),
        (sim, "--missing", ("nan", "1")), (sim, "--seed", ("-1", "x")),
        (sim, "--gap", ("x", "5", "3:2", "-1:2", "0:1000", "a:b")),
    ]
    for argv, opt, values in options:
        for v in values:
            writes = argv[0] != "evaluate"
            out.append(Case(f"option {argv[0]} {opt} {v!r}", "boxes", (*argv, f"{opt}={v}"), ERROR,
                            (opt.split("=")[0] if v not in ("100000000",) else "--frames",),
                            writes=writes))
    g = ("reconstruct", "{in}", "--out")
    out += [
        Case("--out is the input folder", "boxes", (*g, "{in}"), ERROR, ("--out", "input folder"),
             prev=False),
        Case("--out inside the input folder", "boxes", (*g, "{in}/res"), ERROR, ("--out",), prev=False),
        Case("--out contains the input folder", "boxes", (*g, "{work}"), ERROR, ("--out", "input folder"),
             prev=False),
        Case("--out is a file", "boxes", (*g, "{in}/../file.txt"), ERROR, ("--out", "not a folder"),
             mutate=lambda root: (root.parent / "file.txt").write_text("x"), prev=False),
        Case("--out holds someone's files", "boxes", (*g, "{work}/mine"), ERROR, ("gt3dkit did not write",),
             mutate=_someones_folder, prev=False),
        Case("--out under a file", "boxes", (*g, "{in}/../file.txt/out"), ERROR, ("--out",),
             mutate=lambda root: (root.parent / "file.txt").write_text("x"), prev=False),
        Case("input does not exist", None, ("reconstruct", "{work}/nothing", "--out", "{out}"), ERROR,
             ("nothing", "not a directory")),
        Case("input is a file", "boxes", ("reconstruct", "{in}/boxes.csv", "--out", "{out}"), ERROR,
             ("boxes.csv",)),
        Case("input of no known layout", "boxes", (*rec,), ERROR, ("unknown input layout",),
             mutate=remove("cameras.json")),
        Case("no annotations", "boxes", (*rec,), ERROR, ("no annotations",),
             mutate=chain(remove("boxes.csv"))),
        Case("boxes.csv with a header only", "boxes", (*rec,), ERROR, ("no annotations",),
             mutate=csv_edit("boxes.csv", lambda ls: ls[:1])),
        Case("--layout wildtrack on a native folder", "boxes", (*rec, "--layout", "wildtrack"), ERROR,
             ("annotations_positions",)),
        Case("--skeleton coco17 on coco19 joints", "panoptic", (*rec, "--skeleton", "coco17"), EITHER, ()),
        Case("--cameras on a native folder", "boxes", (*rec, "--cameras", "cam0"), ERROR, ("--cameras",)),
        Case("--cameras empty", "panoptic", (*rec, "--cameras", ","), ERROR, ("--cameras",)),
        Case("--cameras unknown", "panoptic", (*rec, "--cameras", "00_00,99_99"), ERROR, ("99_99",)),
        Case("--accel-sd with triangulation", "boxes", (*rec, "--estimator", "triangulation",
                                                       "--accel-sd", "1"), ERROR, ("--accel-sd",)),
        Case("--no-bones with gtsam", "kpts", (*rec, "--estimator", "gtsam", "--no-bones"), ERROR,
             ("--no-bones",)),
        Case("unknown estimator", "boxes", (*rec, "--estimator", "kalman"), ERROR, ("--estimator",)),
        Case("unknown command", None, ("reconstrut",), ERROR, ("invalid choice",), writes=False),
        Case("no --out", "boxes", ("reconstruct", "{in}"), ERROR, ("--out",)),
        Case("evaluate a folder with no tracks.csv", "boxes", ("evaluate", "{in}", "--truth", "{in}"),
             ERROR, ("tracks.csv",), writes=False),
        Case("evaluate against an input with no truth", "boxes",
             ("evaluate", "{bases}/result", "--truth", "{in}"), ERROR, ("no truth",),
             mutate=remove("truth.csv"), writes=False),
        Case("evaluate a file", "boxes", ("evaluate", "{in}/boxes.csv", "--truth", "{in}"), ERROR,
             ("boxes.csv",), writes=False),
        Case("simulate into someone's folder", None, ("simulate", "--out", "{work}/mine"), ERROR,
             ("gt3dkit did not write",), mutate=_someones_folder, prev=False),
        Case("simulate --shifted on a skeleton", None, ("simulate", "--out", "{out}", "--kind", "skeleton",
                                                        "--shifted", "0.1"), ERROR, ("--shifted",)),
        Case("simulate --frames 2 --people 1", None, ("simulate", "--out", "{out}", "--frames", "2",
                                                      "--people", "1"), OK, ()),
        Case("simulate --cameras 65", None, ("simulate", "--out", "{out}", "--cameras", "65"), ERROR,
             ("cameras",)),
        Case("--skeleton on a boxes-only input", "boxes", (*rec, "--skeleton", "coco17"), ERROR,
             ("--skeleton", "no keypoints")),
        Case("--skeleton on a WILDTRACK input", "wildtrack", (*rec, "--skeleton", "coco17"), ERROR,
             ("--skeleton",)),
        Case("--seed on a native input", "boxes", (*rec, "--seed", "3"), ERROR, ("--seed",)),
        Case("simulate --skeleton for boxes", None, ("simulate", "--out", "{out}", "--skeleton", "coco17"),
             ERROR, ("--skeleton",)),
        Case("simulate --dropout for a skeleton", None, ("simulate", "--out", "{out}", "--kind", "skeleton",
                                                         "--dropout", "0.1"), ERROR, ("--dropout",)),
        Case("simulate --conf for boxes", None, ("simulate", "--out", "{out}", "--conf"), ERROR, ("--conf",)),
        Case("wildtrack: every frame empty", "wildtrack", rec, ERROR, ("no annotations",),
             mutate=lambda root: [p.write_text("[]") for p in (root / "annotations_positions").glob("*")]),
        Case("boxes.csv is a folder", "boxes", rec, ERROR, ("boxes.csv", "cannot read"),
             mutate=chain(remove("boxes.csv"), lambda root: (root / "boxes.csv").mkdir())),
        Case("cameras.json is a folder", "boxes", rec, ERROR, ("cameras.json", "cannot read"),
             mutate=chain(remove("cameras.json"), lambda root: (root / "cameras.json").mkdir())),
        Case("calib show: a folder with no calibration", None, ("calib", "show", "{work}"), ERROR,
             ("no calibration",), writes=False, prev=False),
        Case("calib show: a TOML without matrix", None, ("calib", "show", "{work}/c.toml"), ERROR,
             ("c.toml", "[cam_0]", "missing matrix"), writes=False, prev=False,
             mutate=lambda root: (root.parent / "c.toml").write_text(
                 '[cam_0]\nname = "a"\nsize = [10, 10]\nrotation = [0, 0, 0]\ntranslation = [0, 0, 1]\n'
                 'distortions = [0, 0, 0, 0]\n')),
        Case("calib show: a COLMAP model without images", None, ("calib", "show", "{work}/col"), ERROR,
             ("col", "no images"), writes=False, prev=False, mutate=_colmap_without_images),
        Case("calib refine: --out is the input", "kpts", ("calib", "refine", "{in}", "--out", "{in}"), ERROR,
             ("--out",), prev=False),
        Case("calib refine: too few correspondences", "kpts", ("calib", "refine", "{in}", "--out", "{out}"),
             ERROR, ("too few correspondences", "00_00"),
             mutate=csv_edit("keypoints.csv", lambda ls: [ls[0], *(
                 x for x in ls[1:] if x.startswith("100,") and x.split(",")[2] == "0")])),
        Case("calib refine of a good rig", "kpts", ("calib", "refine", "{in}", "--out", "{out}"), OK, ()),
        Case("calib refine of a box scene", "boxes", ("calib", "refine", "{in}", "--out", "{out}"), EITHER,
             ()),
        Case("--calib that does not exist", "boxes", (*rec, "--calib", "{work}/nothing.toml"), ERROR,
             ("nothing.toml",)),
        Case("--calib without a camera the annotations use", "boxes", (*rec, "--calib", "{work}/c"), ERROR,
             ("cam5", "absent from the calibration"), mutate=_calib_without_last_camera),
        Case("panoptic: every confidence 0", "panoptic", rec, ERROR, ("confidence",),
             mutate=_panoptic_conf_zero),
        Case("panoptic: a body id of 1e23", "panoptic", rec, ERROR, ("id",),
             mutate=lambda root: [p.write_text(p.read_text().replace('"id": 0', '"id": ' + "1" * 24))
                                  for p in (root / "hdPose3d_stage1_coco19").glob("*.json")]),
        Case("panoptic: frame file name of 10^23", "panoptic", rec, ERROR, ("frame",),
             mutate=lambda root: next((root / "hdPose3d_stage1_coco19").glob("*.json")).rename(
                 root / "hdPose3d_stage1_coco19" / ("body3DScene_" + "1" * 24 + ".json"))),
        Case("wildtrack: an annotation file not named by a frame", "wildtrack", rec, ERROR,
             ("frame number",),
             mutate=lambda root: (root / "annotations_positions" / "x.json").write_text("[]")),
        Case("wildtrack: positionID outside the grid", "wildtrack", rec, ERROR, ("positionID",),
             mutate=json_edit("annotations_positions/00000000.json",
                              lambda d: [{**d[0], "positionID": 10**9}, *d[1:]])),
        Case("wildtrack: person listed twice", "wildtrack", rec, ERROR, ("second entry",),
             mutate=json_edit("annotations_positions/00000000.json", lambda d: [*d, d[0]])),
        Case("wildtrack: box of -1s", "wildtrack", rec, OK, (),
             mutate=json_edit("annotations_positions/00000000.json",
                              lambda d: [{**d[0], "views": [*d[0]["views"][:-1],
                                                           {**d[0]["views"][-1], "xmin": -1, "ymin": -1,
                                                            "xmax": -1, "ymax": -1}]}, *d[1:]])),
    ]
    return out


def cases(seed: int = 0) -> list[Case]:
    """The suite for one seed: every layout's files, the options, odd inputs and misuses."""
    rng = random.Random(seed)
    est = ("triangulation", "ukf", "gtsam")
    out: list[Case] = []

    def rec() -> tuple[str, ...]:
        return _recon(rng.choices(est, weights=(5, 4, 1))[0])
    out += _csv_cases(rng, "boxes", "boxes.csv", rec(), 20)
    out += _csv_cases(rng, "boxes", "truth.csv", rec(), 10)
    out += _csv_cases(rng, "kpts", "keypoints.csv", rec(), 200)
    out += _csv_cases(rng, "kpts", "truth_keypoints.csv", rec(), 100)
    out += _csv_cases(rng, "result", "tracks.csv", ("evaluate", "{in}", "--truth", "{bases}/boxes"), 10)
    out = [c if c.base != "result" else Case(c.name, c.base, c.argv, c.expect, c.needles, c.mutate,
                                             prev=False, writes=False) for c in out]
    out += _json_cases(rng, "boxes", "cameras.json", rec())
    out += _json_cases(rng, "kpts", "cameras.json", rec())
    out += _json_cases(rng, "wildtrack", "annotations_positions/00000005.json", rec())
    out += _json_cases(rng, "multiviewx", "annotations_positions/00001.json", rec())
    out += _json_cases(rng, "panoptic", "calibration_sim.json", rec())
    out += _json_cases(rng, "panoptic", "hdPose3d_stage1_coco19/body3DScene_00000100.json", rec())
    cam = rng.choice(("CVLab1", "CVLab2", "IDIAP1", "IDIAP3"))
    out += _xml_cases(rng, "wildtrack", f"calibrations/intrinsic_zero/intr_{cam}.xml", rec())
    out += _xml_cases(rng, "wildtrack", f"calibrations/extrinsic/extr_{cam}.xml", rec())
    cam = rng.choice(("Camera1", "Camera3", "Camera6"))
    out += _xml_cases(rng, "multiviewx", f"calibrations/intrinsic/intr_{cam}.xml", rec())
    out += _xml_cases(rng, "multiviewx", f"calibrations/extrinsic/extr_{cam}.xml", rec())
    out += _camera_cases(rec())
    out += _odd_cases()
    out += _option_cases()
    out += _report_cases()
    out += _format_cases()
    out += newer_command_cases()
    return out


# ----------------------------------------------------------------------------- running


def tree(p: Path) -> dict[str, str]:
    """relative path -> sha256 of every file under ``p`` ({} if absent)."""
    if not p.exists():
        return {}
    if p.is_file():
        return {".": hashlib.sha256(p.read_bytes()).hexdigest()}
    return {str(f.relative_to(p)): hashlib.sha256(f.read_bytes()).hexdigest()
            for f in sorted(p.rglob("*")) if f.is_file()}


def _call(argv: list[str], subprocess_mode: bool) -> tuple[int, str, str]:
    if subprocess_mode:
        r = subprocess.run([sys.executable, "-m", "gt3dkit.cli", *argv], capture_output=True,
                           text=True, timeout=600)
        return r.returncode, r.stdout, r.stderr
    from gt3dkit.cli import main

    so, se = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(so), contextlib.redirect_stderr(se):
        try:
            code = main(argv)
        except BaseException as e:  # noqa: BLE001 - anything escaping main is a traceback
            import traceback

            traceback.print_exc(file=se)
            code = -1 if not isinstance(e, SystemExit) else int(e.code or 0)
    return code, so.getvalue(), se.getvalue()


def run_case(case: Case, bases: Path, work: Path, subprocess_mode: bool = False) -> Outcome:
    """Run ``case`` in the empty folder ``work`` and judge it."""
    work.mkdir(parents=True)
    inp, out = work / "in", work / "out"
    if case.base:
        shutil.copytree(bases / case.base, inp)
    if case.mutate:
        case.mutate(inp)
    if case.prev:
        shutil.copytree(bases / "result", out)
    entries = {p.name for p in work.iterdir()}
    before_in, before_out = tree(inp), tree(out)
    argv = [a.format(**{"in": inp, "out": out, "bases": bases, "work": work}) for a in case.argv]
    code, so, se = _call(argv, subprocess_mode)
    o = Outcome(case, code, so, se)
    judge(o, work, entries, before_in, before_out)
    return o


def judge(o: Outcome, work: Path, entries: set[str], before_in: dict[str, str],
          before_out: dict[str, str]) -> None:
    c, p = o.case, o.problems
    lines = [x for x in o.stderr.splitlines() if x.strip()]
    if "Traceback" in o.stderr or o.code == -1:
        p.append("traceback")
    if "internal error" in o.stderr:
        p.append("internal error")
    failed = o.code != 0
    if c.expect == ERROR and o.code == 0:
        p.append("silently accepted")
    elif c.expect in (WARN, OK) and failed:
        p.append(f"rejected valid input (exit {o.code})")
    if o.code not in (0, 2):
        p.append(f"wrong exit code {o.code}")
    if failed:
        if len(lines) != 1 or not lines[0].startswith("error: "):
            p.append(f"not one error line: {lines[:3]}")
        elif c.expect == ERROR:
            missing = [n for n in c.needles if n not in lines[0]]
            if missing:
                p.append(f"error line does not name {missing}")
        if tree(work / "out") != before_out:
            p.append("output changed by a failed run")
    else:
        bad = [x for x in lines if not x.startswith("warning: ")]
        if bad:
            p.append(f"stderr of a successful run: {bad[:2]}")
        if c.expect == WARN:
            for n in c.needles:
                k = sum(n in x for x in lines)
                if k != 1:
                    p.append(f"{k} warning lines mention {n!r}")
        if c.expect == OK and lines:
            p.append(f"warnings on clean input: {lines[:2]}")
        if c.writes and "--out" in c.argv:
            out = Path(c.argv[c.argv.index("--out") + 1].format(
                **{"in": work / "in", "out": work / "out", "bases": "", "work": work}))
            if not (out / MARKER).is_file():
                p.append("no complete output")
    if tree(work / "in") != before_in:
        p.append("input changed")
    left = sorted(x.name for x in work.iterdir() if x.name not in entries | {"out", "mine"}
                  and not (x.name == "file.txt"))
    stray = [x for x in left if "gt3d-" in x or x.startswith(".")]
    if stray:
        p.append(f"left behind: {stray}")


def _format_cases() -> list[Case]:
    """The per-camera task formats (MOT, CVAT, COCO, OpenPose) and the commands around them."""
    rec = _recon("triangulation")
    paired = "paired by sorted order"  # the OpenPose base's folders are named unlike its TOML

    def op_file(root: Path) -> Path:
        return sorted((root / "pose" / "cam2_json").glob("*.json"))[1]

    def op_doc(doc: object) -> Mutation:
        return lambda root: op_file(root).write_text(json.dumps(doc))

    def coco_edit(edit: Callable[[dict], None]) -> Mutation:
        def m(root: Path) -> None:
            p = sorted((root / "coco").glob("*.json"))[0]
            d = json.loads(p.read_text())
            edit(d)
            p.write_text(json.dumps(d))
        return m

    def cvat_edit(edit: Callable[[str], str]) -> Mutation:
        def m(root: Path) -> None:
            p = root / "cvat" / "CVLab1.xml"
            p.write_text(edit(p.read_text()))
        return m

    def mot_append(line: str) -> Mutation:
        def m(root: Path) -> None:
            p = root / "mot" / "CVLab2.txt"
            p.write_text(p.read_text() + line + "\n")
        return m

    return [
        Case("mot: a row of 5 fields", "mot", rec, ERROR, ("CVLab2.txt", "line", "fields"),
             mot_append("1,2,3,4,5")),
        Case("mot: an id of -1", "mot", rec, ERROR, ("CVLab2.txt", "without a track id"),
             mot_append("5,-1,100,100,40,90,1,-1,-1,-1")),
        Case("mot: width 0", "mot", rec, ERROR, ("CVLab2.txt", "degenerate"),
             mot_append("5,3,100,100,0,90,1,-1,-1,-1")),
        Case("mot: a box of nan", "mot", rec, ERROR, ("CVLab2.txt", "non-finite"),
             mot_append("5,3,nan,100,40,90,1,-1,-1,-1")),
        Case("mot: an ignored box (conf 0)", "mot", rec, WARN, ("conf 0",),
             mot_append("5,3,100,100,40,90,0,-1,-1,-1")),
        Case("mot: no calibration", "mot", rec, ERROR, ("no calibration",), remove("cameras.json")),
        Case("mot: --association on a native input", "boxes", (*rec, "--association", "{work}/a.csv"),
             ERROR, ("--association",)),
        Case("mot: an association file naming an unknown camera", "mot",
             (*rec, "--association", "{work}/a.csv"), ERROR, ("a.csv", "unknown camera"),
             mutate=lambda root: (root.parent / "a.csv").write_text(
                 "camera,local_id,frame,global_id\nzz,1,,2\n")),
        Case("associate an input whose ids are global", "boxes", ("associate", "{in}", "--out", "{out}"),
             ERROR, ("already global",)),
        Case("openpose: people is not a list", "openpose", rec, ERROR, ("cam2_json", "people"),
             op_doc({"people": 3})),
        Case("openpose: a confidence of 2 (a heatmap peak: read as 1, warned)", "openpose", rec, WARN,
             ("confidence above 1",), op_doc({"people": [{"pose_keypoints_2d": [10, 10, 2] * 25}]})),
        Case("openpose: a negative confidence", "openpose", rec, ERROR, ("cam2_json", "negative confidence"),
             op_doc({"people": [{"pose_keypoints_2d": [10, 10, -0.5] * 25}]})),
        Case("openpose: pose_keypoints_2d holding true", "openpose", rec, ERROR, ("cam2_json", "numbers"),
             op_doc({"people": [{"pose_keypoints_2d": [10, 10, True] * 25}]})),
        Case("openpose: 24 joints", "openpose", rec, ERROR, ("cam2_json", "24 joints"),
             op_doc({"people": [{"pose_keypoints_2d": [10, 10, 0.5] * 24}]})),
        Case("openpose: a truncated file", "openpose", rec, ERROR, ("cam2_json",),
             lambda root: op_file(root).write_text(op_file(root).read_text()[:50])),
        Case("openpose: camera folders named unlike the calibration", "openpose", rec, WARN, (paired,)),
        Case("cvat: truncated XML", "cvat", rec, ERROR, ("CVLab1.xml", "line"), cvat_edit(lambda t: t[:400])),
        Case("cvat: a box corner of 1e308", "cvat", rec, ERROR, ("CVLab1.xml", "far outside"),
             cvat_edit(lambda t: re.sub(r'xbr="[^"]+"', 'xbr="1e308"', t, count=1))),
        Case("coco: keypoints of the wrong length", "coco", rec, ERROR, ("annotations[0]", "keypoint values"),
             coco_edit(lambda d: d["annotations"][0].update(keypoints=[1, 2, 2]))),
        Case("coco: an unknown image_id", "coco", rec, ERROR, ("annotations[0]", "image_id"),
             coco_edit(lambda d: d["annotations"][0].update(image_id=99999))),
        Case("export of an input folder", "boxes", ("export", "{in}", "--format", "c3d", "--to", "{out}"),
             ERROR, ("tracks.csv",)),
    ]


def _report_cases() -> list[Case]:
    """``gt3d report`` on outputs that are not, or no longer, what it needs."""
    rep = ("report", "{in}")

    def meta_root(root: Path) -> None:
        m = json.loads((root / "meta.json").read_text())
        m["input"]["load"]["root"] = str(root.parent / "gone")
        (root / "meta.json").write_text(json.dumps(m))

    def anomalies_extra(root: Path) -> None:
        (root / "anomalies.csv").write_text("frame,camera,id,joint,kind,score,detail\n"
                                            "0,cam1,0,,shifted_box,9,x,y\n")

    return [Case(n, b, a, ERROR, needles, mutate=m, prev=False, writes=False) for n, b, a, needles, m in (
        ("report of an input folder", "boxes", rep, ("tracks.csv",), None),
        ("report of a file", "result", ("report", "{in}/tracks.csv"), ("not a folder",), None),
        ("report: meta.json truncated", "result", rep, ("meta.json",), raw("meta.json", lambda b: b[:40])),
        ("report: the input has moved", "result", rep, ("not there any more",), meta_root),
        ("report: anomalies.csv with an extra field", "result", rep, ("anomalies.csv", "fields"),
         anomalies_extra),
        ("report: tracks.csv with NaN rows", "result", rep, ("tracks.csv",),
         csv_edit("tracks.csv", lambda ls: [ls[0], ",".join([*ls[1].split(",")[:2], *["nan"] * 9]),
                                            *ls[2:]])),
    )]


def _as_compare_output(root: Path) -> None:
    """A reconstruct output moved into ``ukf/`` beside a ``comparison.csv``: what gt3d compare writes."""
    (root / "ukf").mkdir()
    for p in list(root.iterdir()):
        if p.name != "ukf":
            p.rename(root / "ukf" / p.name)
    (root / "comparison.csv").write_text("estimator\nukf\n")


def _keypoints_in_one_camera(root: Path) -> None:
    lines = _lines(root / "keypoints.csv")
    cam = lines[1].split(",")[1]
    _write_lines(root / "keypoints.csv", [lines[0], *(x for x in lines[1:] if x.split(",")[1] == cam)])


def newer_command_cases() -> list[Case]:
    """Issue 49: the newer commands used as a hostile or careless user would (each failed on the
    main before it: an internal error, a wrong option named, a silent acceptance)."""
    rec = ("reconstruct", "{in}", "--out", "{out}")
    many = ("reconstruct-many", "{work}/m.txt", "--out", "{out}")

    def manifest(root: Path) -> None:
        (root.parent / "m.txt").write_text(f"{root}\n")

    def user_file(root: Path) -> None:
        (root.parent / "mine").mkdir()
        (root.parent / "mine" / "notes.txt").write_text("mine\n")

    proj = ("project", "{in}", "--format", "mot", "--to", "{work}/mine")
    return [
        Case("--scheduler not-an-address", "boxes", (*rec, "--scheduler", "not-an-address"), ERROR,
             ("--scheduler", "not-an-address")),
        Case("--scheduler with an unknown scheme", "boxes", (*rec, "--scheduler", "foo://127.0.0.1:8786"),
             ERROR, ("--scheduler", "foo")),
        Case("reconstruct-many --scheduler not-an-address", "boxes", (*many, "--scheduler", "not-an-address"),
             ERROR, ("--scheduler",), manifest),
        Case("--scheduler '' (an unset variable)", "boxes", (*rec, "--scheduler", ""), ERROR,
             ("--scheduler", "empty")),
        Case("project --to a folder of the user's", "result", proj, ERROR, ("--to", "notes.txt"), user_file,
             prev=False, writes=False),
        Case("export --to a folder of the user's", "result",
             ("export", "{in}", "--format", "json", "--to", "{work}/mine"), ERROR, ("--to",), user_file,
             prev=False, writes=False),
        Case("project a gt3d compare output", "result",
             ("project", "{in}", "--format", "mot", "--to", "{work}/p"), ERROR, ("ukf", "compare"),
             _as_compare_output, prev=False, writes=False),
        Case("--box-model cylinder on keypoints", "kpts", (*rec, "--box-model", "cylinder"), ERROR,
             ("--box-model", "keypoints only")),
        Case("keypoints seen by one camera only", "kpts", rec, ERROR, ("only in camera",),
             _keypoints_in_one_camera),
        Case("panoptic --cameras naming one camera", "panoptic", (*rec, "--cameras", "00_01"), ERROR,
             ("--cameras", "one camera")),
        Case("panoptic: every joint below the confidence kept", "panoptic", rec, ERROR,
             ("joints19", "confidence"), _panoptic_conf_zero),
    ]


def issue_cases() -> list[Case]:
    """The cases issue 9 lists that are one command each (the others, signals, concurrent runs,
    closed pipes, are tests/test_reliability.py)."""
    rec = ("reconstruct", "{in}", "--out", "{out}")
    row = "0,cam1,0,100,200,300,400"

    def append(line: str) -> Mutation:
        return csv_edit("boxes.csv", lambda ls: [*ls, line])

    def tracks_nan(ls: list[str]) -> list[str]:
        return [ls[0], ",".join([*ls[1].split(",")[:2], *["nan"] * 9]), *ls[2:]]

    one_view = [c for c in _odd_cases() if "one camera" in c.name or "one-camera" in c.name]
    off = [c for c in _odd_cases() if "outside the image" in c.name]
    return [
        Case("--out is the input folder (holding keypoints.csv)", "kpts", (*rec[:3], "{in}"), ERROR,
             ("--out", "input folder"), prev=False),
        Case("100 000 nested [ in cameras.json", "boxes", rec, ERROR, ("cameras.json", "nested"),
             raw("cameras.json", lambda b: b"[" * 100_000)),
        Case("a frame of 10^23", "boxes", rec, ERROR, ("boxes.csv", "frame"),
             append("100000000000000000000000,cam1,0,100,200,300,400")),
        Case("an id of 10^23", "boxes", rec, ERROR, ("boxes.csv", "id"),
             append("0,cam1,100000000000000000000000,100,200,300,400")),
        Case("a CSV field of 200 000 characters", "boxes", rec, ERROR, ("boxes.csv", "line"),
             append(row + "x" * 200_000)),
        Case("--estimator gtsam --sigma-px nan", "boxes", (*rec, "--estimator", "gtsam", "--sigma-px", "nan"),
             ERROR, ("--sigma-px",)),
        Case("simulate --frames 100000000", None, ("simulate", "--out", "{out}", "--frames", "100000000"),
             ERROR, ("--frames",)),
        Case("--fps 1e-300", "boxes", (*rec, "--fps", "1e-300"), ERROR, ("--fps",)),
        Case("--fps inf", "boxes", (*rec, "--fps", "inf"), ERROR, ("--fps",)),
        Case('"fps": "ten" in cameras.json', "boxes", rec, ERROR, ("cameras.json", "fps"),
             json_edit("cameras.json", lambda d: {**d, "fps": "ten"})),  # type: ignore[dict-item]
        Case("Panoptic input with every joint confidence 0", "panoptic", rec, ERROR,
             ("hdPose3d_stage1_coco19", "confidence"), _panoptic_conf_zero),
        Case("Panoptic --noise-px inf", "panoptic", (*rec, "--noise-px", "inf"), ERROR, ("--noise-px",)),
        Case("evaluate a tracks.csv with NaN rows", "result",
             ("evaluate", "{in}", "--truth", "{bases}/boxes"), ERROR,
             ("tracks.csv", "line 2"), csv_edit("tracks.csv", tracks_nan), prev=False, writes=False),
        *_report_cases(),
        Case("--out that is a file", "boxes", (*rec[:3], "{work}/f"), ERROR, ("--out", "not a folder"),
             lambda root: (root.parent / "f").write_text("x"), prev=False),
        *off,
        Case("xmax = 1e308", "boxes", rec, ERROR, ("boxes.csv", "far outside"),
             append("0,cam1,7,100,200,1e308,400")),
        Case("an extra field in one CSV row", "boxes", rec, ERROR, ("boxes.csv", "fields"),
             append(row + ",9")),
        Case("dist of 3 coefficients", "boxes", rec, ERROR, ("cameras.json", "dist"),
             json_edit("cameras.json", lambda d: {**d, "cameras": [  # type: ignore[dict-item]
                 {**d["cameras"][0], "dist": [0.01, 0.0, 0.0]}, *d["cameras"][1:]]})),  # type: ignore[index]
        Case("triangulation --sigma-px -1", "boxes",
             (*rec, "--estimator", "triangulation", "--sigma-px", "-1"), ERROR, ("--sigma-px",)),
        Case("simulate --noise-px nan", None, ("simulate", "--out", "{out}", "--noise-px", "nan"), ERROR,
             ("--noise-px",)),
        Case("evaluate a tracks.csv with every row duplicated", "result",
             ("evaluate", "{in}", "--truth", "{bases}/boxes"), ERROR, ("tracks.csv", "second row"),
             csv_edit("tracks.csv", lambda ls: [ls[0], *ls[1:], *ls[1:]]), prev=False, writes=False),
        *one_view,
        Case("a box of -1s in native boxes.csv (the README's 'not seen')", "boxes", rec, WARN,
             ("boxes of -1s",), append("0,cam1,0,-1,-1,-1,-1")),
        Case("boxes.csv saved by Excel with a UTF-8 BOM", "boxes", rec, OK, (),
             raw("boxes.csv", lambda b: b"\xef\xbb\xbf" + b)),
        Case("simulate into a folder holding someone's files", None, ("simulate", "--out", "{work}/mine"),
             ERROR, ("gt3dkit did not write",), _someones_folder, prev=False),
    ]

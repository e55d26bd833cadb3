"""OpenCV FileStorage calibrations (YAML or XML), one file per camera (read and write).

A file holds the intrinsics ``camera_matrix`` (or ``K``), ``distortion_coefficients`` (or
``dist``, ``D``) and the pose ``R`` (3x3) or ``rvec`` (Rodrigues), and ``tvec`` (or ``t``,
``T``), ``cam_from_world`` in metres, and optionally ``image_width``/``image_height`` (else
``--`` the size must come from elsewhere: the annotations' layout). The camera is named by
the file's stem (``cam0.yml`` -> ``cam0``; ``intr_``/``extr_`` prefixes dropped). A fisheye
camera (OpenCV's ``cv::fisheye``) says so in ``distortion_model`` (``fisheye`` or ROS's
``equidistant``) with four coefficients; without it the lens is OpenCV's pinhole.
WILDTRACK/MultiviewX keep intrinsics and extrinsics in two files
(:mod:`gt3dkit.io.datasets.wildtrack` reads those with :func:`read_storage`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.rig import Camera, Rig

# cv2 is imported in the functions that use it: 26 MB and 30 ms that a run whose calibration is
# not OpenCV's, WILDTRACK's or Pose2Sim's never needs
if TYPE_CHECKING:
    import cv2

SUFFIXES = (".yml", ".yaml", ".xml")
_K = ("camera_matrix", "K")
_D = ("distortion_coefficients", "dist", "D")
_T = ("tvec", "t", "T")
#: ``distortion_model`` values (lower case) of each lens: ours and ROS's ``camera_info`` names.
FISHEYE_MODELS = ("fisheye", "equidistant")
PINHOLE_MODELS = ("", "pinhole", "plumb_bob", "radtan", "radial-tangential")


def read_storage(path: Path, keys: tuple[str, ...], raw: bytes | None = None) -> list[np.ndarray]:
    """The matrices ``keys`` of an OpenCV FileStorage file (``raw``: its bytes, read already:
    parsed from memory, the file not opened again)."""
    import cv2
    try:
        fs = (cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ) if raw is None else
              cv2.FileStorage(raw.decode("utf-8", errors="replace"),
                              cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY))
    except (cv2.error, SystemError) as e:
        # OpenCV raises cv2.error, or a SystemError wrapping it, for a parse failure
        cause = e.__cause__ or e.__context__ or e
        lines = str(cause).strip().splitlines()
        msg = lines[-1].strip() if lines else "unreadable"
        raise InputError(str(path), f"malformed OpenCV XML ({msg})") from None
    if not fs.isOpened():
        raise InputError(str(path), "cannot open OpenCV XML file")
    out = []
    try:
        for k in keys:
            node = fs.getNode(k)
            if node.empty():
                raise InputError(str(path), f"missing matrix '{k}'")
            # opencv-matrix nodes (MultiviewX, WILDTRACK intrinsics) or plain number
            # sequences (WILDTRACK's extrinsics: <rvec>1.88 0.46 -0.21</rvec>)
            try:
                m = (np.array([node.at(i).real() for i in range(node.size())])
                     if node.isSeq() else node.mat())
            except (cv2.error, SystemError) as e:
                lines = str(e).strip().splitlines()
                raise InputError(str(path), f"'{k}' is malformed ({lines[-1].strip() if lines else e})"
                                 ) from None
            if m is None or m.size == 0:
                raise InputError(str(path), f"'{k}' is not a matrix or a list of numbers")
            if not np.all(np.isfinite(m)):
                raise InputError(str(path), f"'{k}' has non-finite values")
            out.append(np.asarray(m, dtype=np.float64))
    finally:
        fs.release()
    return out




def _first(path: Path, fs: cv2.FileStorage, names: tuple[str, ...], required: bool = True
           ) -> np.ndarray | None:
    for n in names:
        node = fs.getNode(n)
        if not node.empty():
            return read_storage(path, (n,))[0]
    if required:
        raise InputError(str(path), f"missing matrix {' or '.join(repr(n) for n in names)}")
    return None


def _size(fs: cv2.FileStorage, key: str) -> int | None:
    node = fs.getNode(key)
    return None if node.empty() else int(node.real())


def read_camera(path: Path, width: int | None = None, height: int | None = None,
                name: str | None = None) -> Camera:
    """One camera from a FileStorage file (size from the file, else ``width``/``height``)."""
    import cv2
    path = Path(path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):
        read_storage(path, ())  # raises the named error
        raise
    try:
        K = _first(path, fs, _K)
        D = _first(path, fs, _D, required=False)
        R = _first(path, fs, ("R",), required=False)
        rvec = None if R is not None else _first(path, fs, ("rvec",))
        t = _first(path, fs, _T)
        w, h = _size(fs, "image_width") or width, _size(fs, "image_height") or height
        model = fs.getNode("distortion_model")
        model_name = "" if model.empty() or not model.isString() else model.string().strip().lower()
    finally:
        fs.release()
    if w is None or h is None:
        raise InputError(str(path), "no image_width/image_height (and none given)")
    if R is None:
        if rvec is None or rvec.size != 3:
            raise InputError(str(path), "rvec must have 3 values")
        R, _ = cv2.Rodrigues(rvec.reshape(3, 1).astype(np.float64))
    cam = name or path.stem.removeprefix("intr_").removeprefix("extr_")
    if model_name not in FISHEYE_MODELS + PINHOLE_MODELS:
        raise InputError(str(path), f"distortion_model {model_name!r} is not one of OpenCV's "
                                    f"(pinhole: {', '.join(PINHOLE_MODELS[1:])}; fisheye: "
                                    f"{', '.join(FISHEYE_MODELS)})")
    try:
        return Camera(name=cam, width=w, height=h, K=np.asarray(K, float).reshape(3, 3),
                      dist=np.zeros(5) if D is None else np.asarray(D, float).reshape(-1),
                      R=np.asarray(R, float).reshape(3, 3), t=np.asarray(t, float).reshape(-1),
                      lens="fisheye" if model_name in FISHEYE_MODELS else "pinhole")
    except ValueError as e:
        raise InputError(str(path), str(e)) from None


def read(path: Path) -> Rig:
    """A folder of per-camera files (``*.yml``, ``*.yaml``, ``*.xml``), or one such file."""
    path = Path(path)
    files = [path] if path.is_file() else sorted(p for p in path.iterdir() if p.suffix in SUFFIXES)
    if not files:
        raise InputError(str(path), "no OpenCV calibration files (*.yml, *.yaml, *.xml)")
    cams = [read_camera(p) for p in files]
    try:
        return Rig(tuple(cams), frame_name=f"world frame of {path.name}")
    except ValueError as e:
        raise InputError(str(path), str(e)) from None


def write_camera(cam: Camera, path: Path) -> None:
    """One camera as FileStorage (YAML or XML by suffix), with R and rvec both written."""
    import cv2
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(cam.width))
        fs.write("image_height", int(cam.height))
        fs.write("camera_matrix", cam.K)
        if cam.lens == "fisheye":
            fs.write("distortion_model", "fisheye")
            fs.write("distortion_coefficients", cam.coefficients.reshape(1, -1))
        else:
            fs.write("distortion_coefficients", cam.dist.reshape(1, -1))
        fs.write("R", cam.R)
        fs.write("rvec", cv2.Rodrigues(cam.R)[0])
        fs.write("tvec", cam.t.reshape(3, 1))
    finally:
        fs.release()


def write(rig: Rig, folder: Path, suffix: str = ".yml") -> None:
    """Every camera of ``rig`` as ``folder/<name><suffix>``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for c in rig.cameras:
        write_camera(c, folder / f"{c.name}{suffix}")

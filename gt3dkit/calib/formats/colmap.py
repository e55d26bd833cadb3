"""A COLMAP sparse model (``cameras``/``images``[/``rigs``/``frames``] ``.bin`` or ``.txt``),
read and written with pycolmap (the only module that imports it, lazily).

One COLMAP image per camera of the rig, named ``<camera>.<ext>`` (the camera is the image
name's stem); its ``cam_from_world`` is our ``R``, ``t`` (COLMAP's world units are taken as
metres; its principal point is OpenCV's + 0.5 px: COLMAP puts pixel centres at +0.5).
Camera models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV and
FULL_OPENCV (with k4 = k5 = k6 = 0) map to our pinhole lens; OPENCV_FISHEYE,
SIMPLE_RADIAL_FISHEYE and RADIAL_FISHEYE (COLMAP's equidistant models, ``θ_d = θ (1 + k1 θ² +
...)``) to OpenCV's fisheye; any other is named in the error. A fisheye camera is written as
OPENCV_FISHEYE.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.rig import Camera, Rig

SUPPORTED = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
             "OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE")


def model_folder(path: Path) -> Path | None:
    """The folder holding ``cameras.bin``/``cameras.txt`` (``path``, or ``sparse/0`` in it)."""
    path = Path(path)
    if path.is_file():
        path = path.parent
    for d in (path, path / "sparse" / "0", path / "sparse", path / "0"):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return d
    return None


def intrinsics_of(model: str, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """(K, dist, lens) of a COLMAP camera's model name and params: ``dist`` is ``k1 k2 p1 p2 k3``
    for a pinhole lens, ``k1 k2 k3 k4`` for a fisheye (:class:`gt3dkit.rig.Camera`)."""
    z = 0.0
    lens = "pinhole"
    if model == "SIMPLE_RADIAL_FISHEYE":
        f, cx, cy, k = p
        fx = fy = f
        d, lens = [k, z, z, z], "fisheye"
    elif model == "RADIAL_FISHEYE":
        f, cx, cy, k1, k2 = p
        fx = fy = f
        d, lens = [k1, k2, z, z], "fisheye"
    elif model == "OPENCV_FISHEYE":
        fx, fy, cx, cy, k1, k2, k3, k4 = p
        d, lens = [k1, k2, k3, k4], "fisheye"
    elif model == "SIMPLE_PINHOLE":
        (f, cx, cy), d = p, [z] * 5
        fx = fy = f
    elif model == "PINHOLE":
        (fx, fy, cx, cy), d = p, [z] * 5
    elif model == "SIMPLE_RADIAL":
        f, cx, cy, k = p
        fx = fy = f
        d = [k, z, z, z, z]
    elif model == "RADIAL":
        f, cx, cy, k1, k2 = p
        fx = fy = f
        d = [k1, k2, z, z, z]
    elif model == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = p
        d = [k1, k2, p1, p2, z]
    elif model == "FULL_OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = p
        if k4 or k5 or k6:
            raise ValueError("FULL_OPENCV with rational terms k4..k6 is not supported")
        d = [k1, k2, p1, p2, k3]
    else:
        raise ValueError(f"camera model {model} is not supported (supported: {', '.join(SUPPORTED)})")
    # COLMAP's pixel centres are at +0.5 (the image's corner is 0), OpenCV's at integers
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return K, np.asarray(d, dtype=np.float64), lens


def read(path: Path) -> Rig:
    import pycolmap

    folder = model_folder(path)
    if folder is None:
        raise InputError(str(path), "no COLMAP model (cameras.bin or cameras.txt)")
    try:
        rec = pycolmap.Reconstruction(str(folder))
    except Exception as e:  # noqa: BLE001 - pycolmap raises bare RuntimeErrors/ValueErrors
        raise InputError(str(folder), f"unreadable COLMAP model ({str(e).strip().splitlines()[-1]})"
                         ) from None
    if rec.num_images() == 0:
        raise InputError(str(folder), "the COLMAP model has no images (one image per camera)")
    cams = []
    for image_id in sorted(rec.images):
        im = rec.image(image_id)
        name = Path(im.name).stem
        where = f"{folder}: image {im.name!r}"
        if not im.has_pose:
            raise InputError(where, "not registered (no pose)")
        c = rec.camera(im.camera_id)
        try:
            K, d, lens = intrinsics_of(c.model_name, np.asarray(c.params, dtype=np.float64))
            m = im.cam_from_world().matrix()
            cams.append(Camera(name=name, width=int(c.width), height=int(c.height), K=K, dist=d,
                               R=m[:, :3], t=m[:, 3], lens=lens))
        except ValueError as e:
            raise InputError(f"{where}, camera {im.camera_id}", str(e)) from None
    try:
        return Rig(tuple(cams), frame_name=f"COLMAP world of {folder.name}")
    except ValueError as e:
        raise InputError(str(folder), str(e)) from None


def to_reconstruction(rig: Rig, image_ext: str = ".png",
                      keypoints: list[np.ndarray] | None = None) -> Any:
    """A pycolmap Reconstruction with one camera and one registered image per camera;
    ``keypoints[c]`` (m, 2), OpenCV pixels, become image c's 2D points (COLMAP pixels)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    for i, c in enumerate(rig.cameras, start=1):
        k1, k2, p1, p2, k3 = c.dist
        fx, fy, cx, cy = c.K[0, 0], c.K[1, 1], c.K[0, 2] + 0.5, c.K[1, 2] + 0.5  # COLMAP pixels
        if c.lens == "fisheye":
            model, params = "OPENCV_FISHEYE", [fx, fy, cx, cy, *c.dist[:4]]
        elif k3 == 0:
            model, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
        else:
            model, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
        cam = pycolmap.Camera(model=model, width=int(c.width), height=int(c.height),
                              params=np.asarray(params, dtype=np.float64), camera_id=i)
        rec.add_camera_with_trivial_rig(cam)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(c.R), c.t.astype(np.float64))
        kp = np.zeros((0, 2)) if keypoints is None else np.asarray(keypoints[i - 1], np.float64) + 0.5
        rec.add_image_with_trivial_frame(pycolmap.Image(name=f"{c.name}{image_ext}", keypoints=kp,
                                                        camera_id=i, image_id=i), pose)
    return rec


def write(rig: Rig, folder: Path, binary: bool = False) -> None:
    """``rig`` as a COLMAP model in ``folder`` (text by default)."""
    if rig.cameras and any(abs(c.K[0, 1]) > 0 for c in rig.cameras):
        raise ValueError("COLMAP's camera models have no skew: K[0, 1] must be 0")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rec = to_reconstruction(rig)
    (rec.write_binary if binary else rec.write_text)(str(folder))

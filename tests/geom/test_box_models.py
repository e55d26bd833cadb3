"""The cylinder and occupancy-map (POM) box models of the compiled kernel against OpenCV's
projection of the solids' points, their derivatives against central differences, and the choice
of a scene's box model from its boxes."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from gt3dkit.api import reconstruct
from gt3dkit.eval.metrics import match_rows
from gt3dkit.geom import boxkernel as bk
from gt3dkit.geom.boxrig import box_cameras
from gt3dkit.geom.conics import boxes_compiled
from gt3dkit.sim import Errors
from gt3dkit.types import BOX_MODELS
from tests.geom.test_boxkernel import random_cameras, rotation
from tests.scenes import written_scene


def solid_points(c: np.ndarray, s: np.ndarray, Rb: np.ndarray, model: str, n: int = 4000) -> np.ndarray:
    """World points whose image extent is the model's box: the cylinder's two end circles
    (``n`` each), or the POM solid's eight corners."""
    if model == "cylinder":
        a = np.linspace(0, 2 * np.pi, n, endpoint=False)
        body = np.concatenate([np.c_[s[0] * np.cos(a), s[1] * np.sin(a), np.full(n, z * s[2])]
                               for z in (-1, 1)])
    else:
        body = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)]) * s
    return c + body @ Rb.T


def opencv_box(P: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray, dist: np.ndarray, model: str
               ) -> np.ndarray:
    uv = cv2.projectPoints(P, cv2.Rodrigues(R)[0], t, K, dist)[0][:, 0]
    bottom = np.sort(uv[:, 1])[-4:].mean() if model == "pom" else uv[:, 1].max()  # POM: 4 lowest corners
    return np.array([uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), bottom])


@pytest.mark.parametrize("model", ["cylinder", "pom"])
@pytest.mark.parametrize("kind", ["distorted", "pinhole"])
def test_box_models_equal_opencv_projection_of_the_solid(model: str, kind: str) -> None:
    rng = np.random.default_rng([BOX_MODELS.index(model), kind == "pinhole"])
    C, N = 4, 40
    R, t, K, dist = random_cameras(rng, C, kind)
    Rb = rotation(rng)
    c = rng.normal(size=(N, 3)) * 1.5
    s = np.exp(rng.normal(size=(N, 3)) * 0.3) * 0.4
    cams = box_cameras(Rb, K, dist, R, t, np.ones(C), BOX_MODELS.index(model))
    box, margin = boxes_compiled(c, s, cams, 2)
    checked = 0
    for n in range(N):
        for k in range(C):
            depth = (solid_points(c[n], s[n], Rb, model) @ R[k].T + t[k])[:, 2]
            assert (margin[n, k] > 0) == (depth.min() > 0)
            if depth.min() <= 0.5:
                assert depth.min() > 0 or np.isnan(box[n, k]).all()
                continue
            ref = opencv_box(solid_points(c[n], s[n], Rb, model), R[k], t[k], K[k], dist[k], model)
            if not np.all((ref > -500) & (ref < 2500)):  # far outside: distortion models diverge
                continue
            tol = 0.05 if model == "cylinder" else 1e-6  # 4000 points per circle against the exact extent
            np.testing.assert_allclose(box[n, k], ref, atol=tol)
            checked += 1
    assert checked > 40


@pytest.mark.parametrize("model", BOX_MODELS)
def test_box_model_gradients_equal_finite_differences(model: str) -> None:
    """Each box model's gradient (what the compiled fits use) is its value's derivative, and
    its box the value's, the pair looked up in ``BOX_KERNELS`` by the registry's name."""
    rng = np.random.default_rng(10 + BOX_MODELS.index(model))
    C = 4
    R, t, K, dist = random_cameras(rng, C, "distorted")
    Rb = rotation(rng)
    rig = bk.box_rig(bk.BoxCameras(Rb, K, dist, R, t, np.ones(C), BOX_MODELS.index(model)), 2)
    assert set(bk.BOX_KERNELS) == set(BOX_MODELS)  # every registered model has its pair
    value = bk.BOX_KERNELS[model][0]
    box, grad = np.empty(4), np.empty((4, 6))
    checked = 0
    for _ in range(40):
        p = np.r_[rng.normal(size=3) * 1.5, np.log(np.exp(rng.normal(size=3) * 0.3) * 0.4)]
        for c in range(C):
            if not bk.pair_box_grad(tuple(p[:3]), tuple(p[3:]), c, rig, box, grad) > 0.5:
                continue
            if not np.all((box > 0) & (box < 1920)):
                continue
            # the model's own value function (its pair's other half), differenced
            fd = np.empty((4, 6))
            for j in range(6):
                e = np.zeros(6)
                e[j] = 1e-6
                hi, lo = (np.array(value(tuple(x[:3]), tuple(np.exp(2 * x[3:])), rig.cam[c], rig.steps)[1:])
                          for x in (p + e, p - e))
                fd[:, j] = (hi - lo) / 2e-6
            np.testing.assert_allclose(box, value(tuple(p[:3]), tuple(np.exp(2 * p[3:])), rig.cam[c],
                                                  rig.steps)[1:], atol=1e-9)
            np.testing.assert_allclose(grad, fd, rtol=1e-4, atol=1e-3 * np.abs(fd).max())
            checked += 1
    assert checked > 40


@pytest.mark.parametrize("labels", BOX_MODELS)
def test_a_scene_box_model_is_chosen_from_its_boxes(tmp_path: Path, labels: str) -> None:
    """Boxes drawn by each model (1 px noise): the choice finds it, and reconstructing under the
    chosen model beats the paper's ellipsoid on the tool's labels."""
    sc, _ = written_scene(tmp_path, "wildtrack", seed=2, frames=8, people=12, noise_px=1.0, labels=labels,
                          errors=Errors(dropped=0.0))
    assert sc.box_model == labels, sc.box_model_px
    assert sc.load_options["box_model"] == labels
    best = min(sc.box_model_px, key=lambda m: sc.box_model_px[m])
    assert best == labels


def test_the_right_box_model_is_more_accurate(tmp_path: Path) -> None:
    sc, _ = written_scene(tmp_path, "wildtrack", seed=5, frames=6, people=12, labels="pom",
                          errors=Errors(dropped=0.0))
    err = {}
    for model in ("pom", "ellipsoid"):
        t = reconstruct(dataclasses.replace(sc, box_model=model), "triangulation")
        it, ig = match_rows(t, sc.truth)
        d = t.center_world[it, :2] - sc.truth.center_world[ig, :2]
        err[model] = float(np.linalg.norm(d, axis=1).mean())
    assert err["pom"] < 0.01 and err["ellipsoid"] > 2 * err["pom"], err

"""The compiled tangent box (gt3dkit.geom.boxkernel) against the whole-array numpy reference
(tests/oracles.py) and its analytic derivatives against central differences."""

from __future__ import annotations

import numpy as np
import pytest

from gt3dkit.geom import boxkernel as bk
from gt3dkit.geom.boxrig import EVERY_CAMERA
from gt3dkit.geom.camera import FISHEYE, apply_K, distort
from gt3dkit.geom.conics import ellipsoid_boxes, outline_ellipse
from tests.oracles import ellipsoid_boxes_numpy


def rotation(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def random_cameras(rng: np.random.Generator, C: int, kind: str) -> tuple[np.ndarray, ...]:
    """``R, t, K, dist`` of ``C`` cameras ~8 m from the origin: ``kind`` distorted, pinhole,
    skewed or fisheye (a wide lens: focal 350 px, OpenCV's fisheye model)."""
    R = np.stack([rotation(rng) for _ in range(C)])
    t = rng.normal(size=(C, 3)) + [0, 0, 8.0]
    K = np.tile(np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]]), (C, 1, 1))
    if kind == "skewed":
        K[:, 0, 1] = 3.0
    dist = np.zeros((C, 5))
    if kind == "distorted":
        dist[:] = rng.normal(size=(C, 5)) * [0.05, 0.01, 0.001, 0.001, 0.001]
    if kind == "fisheye":
        t = rng.normal(size=(C, 3)) * 0.5 + [0, 0, 3.0]
        K[:, :2, :2] = np.diag([350.0, 350.0])
        dist = np.zeros((C, 6))
        dist[:, :4] = rng.normal(size=(C, 4)) * [0.05, 0.02, 0.005, 0.001]
        dist[:, 5] = FISHEYE
    return R, t, K, dist


@pytest.mark.parametrize("kind", ["distorted", "pinhole", "skewed"])
def test_compiled_tangent_box_equals_the_numpy_reference(kind: str) -> None:
    rng = np.random.default_rng({"distorted": 0, "pinhole": 1, "skewed": 2}[kind])
    C, N = 5, 400
    R, t, K, dist = random_cameras(rng, C, kind)
    c = rng.normal(size=(N, 3)) * 2.0
    s = np.exp(rng.normal(size=(N, 3)) * 0.3) * 0.4
    args = (rotation(rng), K, dist, R, t, np.ones(C))
    b1, m1 = ellipsoid_boxes(c, s, *args)
    b2, m2 = ellipsoid_boxes_numpy(c, s, *args)
    np.testing.assert_allclose(m1, m2, atol=1e-12)
    np.testing.assert_array_equal(np.isnan(b1), np.isnan(b2))
    inside = np.all((b2 > 0) & (b2 < 1920), axis=-1)
    assert inside.sum() > 100
    np.testing.assert_allclose(b1[inside], b2[inside], atol=1e-6)


def test_fisheye_tangent_box_equals_the_extremes_of_the_outline() -> None:
    """Through OpenCV's fisheye model the box is the extremes of the ellipsoid's outline, sampled
    densely (20 001 points) and pushed through the lens: brute force, no Newton steps."""
    rng = np.random.default_rng(8)
    C, N = 4, 150
    R, t, K, dist = random_cameras(rng, C, "fisheye")
    c = rng.normal(size=(N, 3))
    s = np.exp(rng.normal(size=(N, 3)) * 0.3) * 0.3
    Rb = rotation(rng)
    box, _ = ellipsoid_boxes(c, s, Rb, K, dist, R, t, np.ones(C))
    m, E, _ = outline_ellipse(c, s, Rb, R, t, np.ones(C))
    th = np.linspace(0, 2 * np.pi, 20001)
    unit = np.stack([np.cos(th), np.sin(th)], -1)  # (T, 2)
    checked = 0
    for n, k in zip(*np.nonzero(np.isfinite(box).all(-1)), strict=True):
        xy = m[n, k] + unit @ np.linalg.cholesky(E[n, k]).T  # (T, 2) the outline, normalised
        uv = apply_K(distort(xy[:, None], dist[k : k + 1]), K[k : k + 1])[:, 0]
        np.testing.assert_allclose(box[n, k], np.r_[uv.min(0), uv.max(0)], atol=1e-5)
        checked += 1
    assert checked > 400


def test_split_and_masked_tangent_box_equal_the_whole_call(monkeypatch) -> None:
    rng = np.random.default_rng(3)
    C, N = 6, 3000  # large enough to be split over threads
    R, t, K, dist = random_cameras(rng, C, "distorted")
    c = rng.normal(size=(N, 3)) * 2.0
    s = np.exp(rng.normal(size=(N, 3)) * 0.3) * 0.4
    Rb = rotation(rng)
    want = rng.uniform(size=(N, C)) < 0.7
    box, margin = np.empty((N, C, 4)), np.empty((N, C))
    cams = bk.BoxCameras(Rb, K, dist, R, t, np.ones(C))
    bk.kernel(c, s, cams, 2, EVERY_CAMERA, box, margin)  # one call, one thread
    monkeypatch.setenv("GT3D_THREADS", "3")
    b3, m3 = ellipsoid_boxes(c, s, Rb, K, dist, R, t, np.ones(C))
    np.testing.assert_array_equal(b3, box)
    np.testing.assert_array_equal(m3, margin)
    bw, mw = ellipsoid_boxes(c, s, Rb, K, dist, R, t, np.ones(C), want=want)
    np.testing.assert_array_equal(mw, margin)  # margins of every pair
    np.testing.assert_array_equal(bw[want], box[want])
    assert np.isnan(bw[~want]).all()


@pytest.mark.parametrize("kind", ["distorted", "pinhole", "skewed", "fisheye"])
def test_tangent_box_gradient_equals_finite_differences(kind: str) -> None:
    """The tangent box's analytic derivatives (envelope theorem, forward mode) against central
    differences of the numpy reference; through a fisheye, whose outline may have several local
    extremes the reference's local steps stop at, of the compiled box's values (held to brute force
    by the test above)."""
    rng = np.random.default_rng({"distorted": 5, "pinhole": 6, "skewed": 7, "fisheye": 9}[kind])
    oracle = ellipsoid_boxes if kind == "fisheye" else ellipsoid_boxes_numpy
    C, N = 4, 60
    R, t, K, dist = random_cameras(rng, C, kind)
    Rb = rotation(rng)
    ds = np.ones(C)
    rig = bk.box_rig(bk.BoxCameras(Rb, K, dist, R, t, ds), 2)
    eps = np.r_[[1e-6] * 3, [1e-7] * 3]
    checked = 0
    for _ in range(N):
        p = np.r_[rng.normal(size=3) * 2.0, np.log(np.exp(rng.normal(size=3) * 0.3) * 0.4)]
        steps = np.concatenate([np.diag(eps), -np.diag(eps)])
        P = p[None] + steps
        ref, _ = oracle(P[:, :3], np.exp(P[:, 3:]), Rb, K, dist, R, t, ds)  # (12, C, 4)
        fd = np.moveaxis((ref[:6] - ref[6:]) / (2 * eps[:, None, None]), 0, -1)  # (C, 4, 6)
        b0, _ = oracle(p[None, :3], np.exp(p[None, 3:]), Rb, K, dist, R, t, ds)
        for c in range(C):
            box, grad = np.empty(4), np.empty((4, 6))
            bk.pair_box_grad((p[0], p[1], p[2]), (p[3], p[4], p[5]), c, rig, box, grad)
            inside = np.all((b0[0, c] > 0) & (b0[0, c] < 1920)) and np.isfinite(fd[c]).all()
            if not inside:
                continue
            np.testing.assert_allclose(box, b0[0, c], atol=1e-6)
            np.testing.assert_allclose(grad, fd[c], rtol=2e-4, atol=2e-3 * np.abs(fd[c]).max())
            checked += 1
    assert checked > 40

"""Projection and tangent boxes against OpenCV and a brute-force silhouette."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from gt3dkit.geom.camera import distort, pixel_rays, project_points, undistort
from gt3dkit.geom.conics import ellipsoid_boxes, outline_ellipse


def _camera(rng: np.random.Generator, strong: bool = True):
    K = np.array([[rng.uniform(800, 1500), 0, rng.uniform(900, 1000)],
                  [0, rng.uniform(800, 1500), rng.uniform(500, 580)], [0, 0, 1.0]])
    dist = np.array([-0.2, 0.05, 1e-3, -2e-3, 0.01]) if strong else np.zeros(5)
    rvec = rng.normal(size=3)
    R, _ = cv2.Rodrigues(rvec)
    return K, dist, R, rvec


def _silhouette_box(c, s, Rb, K, dist, rvec, t, n=300_000, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    X = c + (u * s) @ Rb.T
    uv, _ = cv2.projectPoints(X, rvec, t, K, dist)
    uv = uv[:, 0]
    return np.r_[uv.min(0), uv.max(0)]


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("strong", [True, False])
def test_tangent_box_matches_brute_force_silhouette(seed: int, strong: bool) -> None:
    rng = np.random.default_rng(seed)
    K, dist, R, rvec = _camera(rng, strong)
    c_cam = np.array([rng.uniform(-1.5, 1.5), rng.uniform(-1, 1), rng.uniform(5, 12)])
    t = c_cam - R @ np.zeros(3)  # ellipsoid at world origin + offset below
    center = rng.normal(size=3) * 0.3
    t = c_cam - R @ center
    semi = rng.uniform(0.15, 1.0, 3)
    Rb, _ = cv2.Rodrigues(rng.normal(size=3))
    box, margin = ellipsoid_boxes(center, semi, Rb, K[None], dist[None], R[None], t[None])
    ref = _silhouette_box(center, semi, Rb, K, dist, rvec, t)
    assert margin[0] > 0
    # brute force sampling under-reaches the true extreme by at most ~1e-3 px here
    np.testing.assert_allclose(box[0], ref, atol=5e-3)


def test_tangent_box_closed_form_hz_without_distortion() -> None:
    """Zero distortion: the box is the H&Z p.201 closed form of C* = P Q* P^T."""
    rng = np.random.default_rng(1)
    K, _, R, _ = _camera(rng, strong=False)
    t = np.array([0.2, -0.1, 8.0])
    center, semi, Rb = np.array([0.1, 0.2, 0.3]), np.array([0.3, 0.4, 0.9]), np.eye(3)
    P = K @ np.c_[R, t]
    H = np.eye(4)
    H[:3, :3], H[:3, 3] = Rb, center
    Qs = H @ np.diag(np.r_[semi**2, -1]) @ H.T
    Cs = P @ Qs @ P.T
    xs = np.roots([Cs[2, 2], -2 * Cs[0, 2], Cs[0, 0]])
    ys = np.roots([Cs[2, 2], -2 * Cs[1, 2], Cs[1, 1]])
    box, _ = ellipsoid_boxes(center, semi, Rb, K[None], np.zeros((1, 5)), R[None], t[None])
    np.testing.assert_allclose(box[0], [xs.min(), ys.min(), xs.max(), ys.max()], atol=1e-8)


def test_behind_camera_gives_nan_and_negative_margin() -> None:
    K = np.array([[1000.0, 0, 960], [0, 1000, 540], [0, 0, 1]])
    R, t = np.eye(3), np.zeros(3)
    box, margin = ellipsoid_boxes(np.array([[0, 0, -5.0], [0, 0, 0.2]]), np.full((2, 3), 0.5),
                                  np.eye(3), K[None], np.zeros((1, 5)), R[None], t[None])
    assert np.all(np.isnan(box)) and np.all(margin <= 0)
    # depth_sign -1 (left-handed calibration): the first one is now "in front"
    m2 = outline_ellipse(np.array([0, 0, -5.0]), np.full(3, 0.5), np.eye(3), R[None], t[None],
                         np.array([-1.0]))[2]
    assert m2[0] > 0


@pytest.mark.parametrize("seed", range(4))
def test_project_points_matches_opencv(seed: int) -> None:
    rng = np.random.default_rng(seed)
    K, dist, R, rvec = _camera(rng)
    t = np.array([0.1, 0.2, 6.0])
    X = rng.uniform(-1.5, 1.5, size=(50, 3))
    uv, depth = project_points(X, K[None], dist[None], R[None], t[None])
    ref, _ = cv2.projectPoints(X, rvec, t, K, dist)
    np.testing.assert_allclose(uv[:, 0], ref[:, 0], atol=1e-9)
    np.testing.assert_allclose(depth[:, 0], (X @ R.T + t)[:, 2])


@settings(max_examples=50, deadline=None)
@given(st.floats(-0.4, 0.4), st.floats(-0.3, 0.3))
def test_undistort_inverts_distort(x: float, y: float) -> None:
    dist = np.array([[-0.2, 0.05, 1e-3, -2e-3, 0.01]])
    xy = np.array([[x, y]])
    np.testing.assert_allclose(undistort(distort(xy, dist), dist), xy, atol=1e-10)


def test_pixel_rays_hit_the_projected_point() -> None:
    rng = np.random.default_rng(5)
    K, dist, R, _ = _camera(rng)
    t = np.array([0.0, 0.0, 7.0])
    X = rng.uniform(-1, 1, size=(20, 3))
    uv, _ = project_points(X, K[None], dist[None], R[None], t[None])
    o, d = pixel_rays(uv, K[None], dist[None], R[None], t[None])
    v = X - o[0]
    cross = np.linalg.norm(np.cross(v, d[:, 0]), axis=1) / np.linalg.norm(v, axis=1)
    assert cross.max() < 1e-9
    assert np.all(np.einsum("ni,ni->n", v, d[:, 0]) > 0)

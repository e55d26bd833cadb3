"""fusion.ukf.measurement: the stacked measurement function of a row against OpenCV's projection,
and its block decomposition (what the filter's regression uses) against the whole function."""

from __future__ import annotations

import cv2
import numpy as np

from gt3dkit.fusion.motion import SPACE


def _states(pre, model, rng: np.random.Generator, n: int = 3) -> np.ndarray:
    """(1, n, state) states around ``n`` rows' per-frame joints (rows where every joint and the
    centre are finite), each moved by 2 cm."""
    lay = model.layout
    ok = np.flatnonzero(np.isfinite(model.x_frame).all(axis=1))
    assert len(ok) >= n
    x = model.x_frame[ok[:n]].copy()
    x[:, lay.joints] += rng.normal(scale=0.02, size=x[:, lay.joints].shape)
    return x[None]


def test_keypoint_columns_are_opencvs_projection(skeleton_prepared) -> None:
    """Each joint's columns of ``Model.h`` (camera-major, then joint, then u, v) equal
    ``cv2.projectPoints`` of that joint with the camera's lens distortion."""
    _, pre, model, _ = skeleton_prepared
    cams, J = model.cams, model.layout.n_joints
    C = len(cams.K)
    X = _states(pre, model, np.random.default_rng(0))
    got = model.h(X)[0].reshape(X.shape[1], C, J, 2)
    joints = X[0][:, model.layout.joints].reshape(-1, J, SPACE)
    for c in range(C):
        rvec, _ = cv2.Rodrigues(cams.R[c])
        for s in range(X.shape[1]):
            ref, _ = cv2.projectPoints(joints[s], rvec, cams.t[c], cams.K[c], cams.dist[c, :5])
            np.testing.assert_allclose(got[s, c], ref.reshape(J, 2), rtol=0, atol=1e-6)


def test_blocks_are_the_whole_function_in_pieces(skeleton_prepared) -> None:
    """Every keypoint block's ``h`` on its own state entries gives the columns ``cols`` of the
    whole ``Model.h``: the filter's per-block regressions see the same measurement function."""
    _, pre, model, _ = skeleton_prepared
    X = _states(pre, model, np.random.default_rng(1))
    whole = model.h(X)[0]  # (S, m)
    blocks = [b for b in model.blocks() if b.h is not None]
    assert blocks, "the skeleton scene has keypoint blocks"
    for b in blocks:
        sub = X[0][:, b.dims]  # (S, G, d)
        part = b.h(np.moveaxis(sub, 0, 1)[None])[0]  # (G, S, k)
        for g in range(len(b.dims)):
            np.testing.assert_allclose(part[g], whole[:, b.cols[g]], rtol=0, atol=1e-9)
    covered = np.concatenate([b.cols.ravel() for b in model.blocks()])
    assert np.array_equal(np.sort(covered), np.arange(model.z.shape[1]))  # each column once

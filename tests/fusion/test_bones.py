"""Bones as messages to each joint (gt3dkit.fusion.ukf.bones) against computations written out plainly:
the iterated update against the MAP of the same Gaussian problem found by scipy, the messages'
information added to a state against the information form inverted by numpy, and the split
filter with the messages against the whole-state filter with them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.optimize import least_squares

from gt3dkit.fusion.preparation.robust import RobustConfig
from gt3dkit.fusion.ukf import smoother as us
from gt3dkit.fusion.ukf.bones import JointInfo, bone_messages
from tests.oracles_frames import add_joint_info, run_frames

BONES = np.array([[0, 1], [1, 2], [1, 3]])


def _problem(seed: int) -> tuple[np.ndarray, ...]:
    """Four joints of a small tree, their independent priors (anisotropic), bone lengths a few cm
    off the prior's, one bone's variance large."""
    rng = np.random.default_rng(seed)
    m0 = np.array([[0.0, 0.0, 1.7], [0.0, 0.0, 1.4], [0.25, 0.0, 1.3], [-0.2, 0.05, 1.35]])
    m0 = m0 + rng.normal(scale=0.02, size=m0.shape)
    A = rng.normal(size=(4, 3, 3)) * 0.03
    C = A @ np.swapaxes(A, 1, 2) + 1e-4 * np.eye(3)
    length = np.linalg.norm(m0[BONES[:, 0]] - m0[BONES[:, 1]], axis=1) + rng.normal(scale=0.03, size=3)
    var = np.array([1e-4, 4e-4, 1e-2])
    return m0, C, length, var


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bone_update_is_the_map_of_the_gaussian_problem(seed: int) -> None:
    """The posterior mean behind the messages (prior times message, per joint) equals the
    minimiser of ``|p - m0|^2_C^-1 + sum_b (|p_a - p_b| - L_b)^2 / s_b^2`` (scipy), and no bone
    is down-weighted when none is off."""
    m0, C, length, var = _problem(seed)
    ji = bone_messages(m0[None], C[None], BONES, length[None], var[None], np.ones((1, 3), bool),
                       RobustConfig(), iterations=20)
    Ci = np.linalg.inv(C)
    post_info = Ci + ji.info[0]
    mean = np.linalg.solve(post_info, (np.einsum("jab,jb->ja", Ci, m0) + ji.eta[0])[..., None])[..., 0]
    Lc = np.linalg.cholesky(Ci)  # whitening of the prior: |L^T (p - m0)|^2

    def resid(p: np.ndarray) -> np.ndarray:
        q = p.reshape(4, 3)
        prior = np.einsum("jba,jb->ja", Lc, q - m0).ravel()
        bones = (np.linalg.norm(q[BONES[:, 0]] - q[BONES[:, 1]], axis=1) - length) / np.sqrt(var)
        return np.r_[prior, bones]

    ref = least_squares(resid, m0.ravel(), xtol=1e-14, ftol=1e-14, gtol=1e-14).x.reshape(4, 3)
    np.testing.assert_allclose(mean, ref, atol=2e-6)
    got = np.linalg.norm(mean[BONES[:, 0]] - mean[BONES[:, 1]], axis=1)
    prior_len = np.linalg.norm(m0[BONES[:, 0]] - m0[BONES[:, 1]], axis=1)
    assert np.all(np.abs(got - length)[:2] < np.abs(prior_len - length)[:2])  # tight bones pulled in
    # information only where a bone reaches, positive semi-definite
    assert np.all(np.linalg.eigvalsh(ji.info[0]) > -1e-9 * np.abs(ji.info[0]).max())


def test_a_bone_the_views_contradict_gives_way() -> None:
    """A bone 30 cm off a tight prior is rejected (no message from it); unmasked, without the
    robust rule, it pulls."""
    m0, C, length, _ = _problem(0)
    C = np.broadcast_to(1e-6 * np.eye(3), C.shape).copy()
    var = np.full(3, 1e-4)
    length = np.linalg.norm(m0[BONES[:, 0]] - m0[BONES[:, 1]], axis=1)
    length[2] += 0.3
    on = np.ones((1, 3), bool)
    robust = bone_messages(m0[None], C[None], BONES, length[None], var[None], on, RobustConfig())
    plain = bone_messages(m0[None], C[None], BONES, length[None], var[None], on, None)
    assert np.all(robust.info[0, 3] == 0.0)  # joint 3 is reached by the rejected bone only
    assert np.abs(plain.info[0, 3]).max() > 0.0
    none = bone_messages(m0[None], C[None], BONES, length[None], var[None], np.zeros((1, 3), bool), None)
    assert not none.info.any() and not none.eta.any()


def test_added_information_equals_the_information_form() -> None:
    """``add_joint_info`` against ``(P^-1 + E^T Lam E)^-1`` and ``P^+ (P^-1 x + E^T eta)`` inverted
    by numpy, with two joints of a 12-entry state, one row without information."""
    rng = np.random.default_rng(3)
    B, n = 3, 12
    A = rng.normal(size=(B, n, n))
    P = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(n)
    x = rng.normal(size=(B, n))
    dims = np.array([[3, 4, 5], [6, 7, 8]])
    L = rng.normal(size=(B, 2, 3, 2))
    info = L @ np.swapaxes(L, -1, -2)  # rank 2: as from two bones
    info[1] = 0.0
    eta = rng.normal(size=(B, 2, 3))
    eta[1] = 0.0
    x1, P1 = add_joint_info(x, P, JointInfo(info, eta), dims)
    for b in range(B):
        Ji = np.linalg.inv(P[b])
        g = Ji @ x[b]
        for j in range(2):
            Ji[np.ix_(dims[j], dims[j])] += info[b, j]
            g[dims[j]] += eta[b, j]
        np.testing.assert_allclose(P1[b], np.linalg.inv(Ji), rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(x1[b], np.linalg.solve(Ji, g), rtol=1e-9, atol=1e-10)
    np.testing.assert_array_equal(x1[1], x[1])


def test_split_filter_with_bone_messages_equals_the_whole_state_filter(skeleton_prepared) -> None:
    """The messages added to the joints' separate filters and to the whole state's: the same
    filter (one update pass: equal to rounding), and the bones tie the lengths tighter than the
    first pass."""
    scene, pre, model, cfg = skeleton_prepared
    cfg = replace(cfg, iterations=1)
    init = us.initial_states(model, cfg)
    first = run_frames(model, init, cfg, scene.fps, collect=True)
    msgs, lengths = us.bone_messages_of(model, cfg, first, pre.skeleton)
    assert msgs.info.any()
    bm = replace(model, joint_info=msgs)
    a = run_frames(bm, init, cfg, scene.fps, collect=True, split=False)
    b = run_frames(bm, init, cfg, scene.fps, collect=True, split=True)
    sd = np.sqrt(np.einsum("rii->ri", a.P))
    assert np.max(np.abs(b.x - a.x) / sd) < 1e-7
    np.testing.assert_allclose(b.P, a.P, rtol=1e-7, atol=1e-12)
    lay, R, J = model.layout, len(model.rows), model.layout.n_joints
    bones = pre.skeleton.bones

    def spread(x: np.ndarray) -> float:
        q = x[:, lay.joints].reshape(R, J, 3)
        ln = np.linalg.norm(q[:, bones[:, 0]] - q[:, bones[:, 1]], axis=-1)
        return float(np.mean(np.abs(ln - lengths.length[model.rows.row_o])))

    assert spread(b.x) < 0.5 * spread(first.x)


def test_pooled_bones_are_each_persons_over_all_its_rows() -> None:
    """Bones pooled from parts (the windows of a sequence, rows of several persons in any order)
    are each person's as found from all its rows at once; a run given them takes them for the
    persons they hold and keeps its own for the others."""
    from gt3dkit.fusion.ukf.bones import BoneSamples, PersonBones, bone_samples, lengths_of
    from gt3dkit.skeletons import SKELETONS

    skel = SKELETONS["coco17"]
    rng = np.random.default_rng(5)
    R, J = 400, skel.n_joints
    row_o = rng.integers(0, 3, R)
    joints = rng.normal(size=(J, 3))[None] * 0.3 + rng.normal(scale=0.01, size=(R, J, 3))
    joints = joints + row_o[:, None, None]
    A = rng.normal(scale=0.003, size=(R, J, 3, 3))
    cov = A @ np.swapaxes(A, -1, -2)
    seen2 = rng.random((R, J)) > 0.2
    s = bone_samples(row_o, np.arange(R), seen2, joints, cov, skel)
    whole = lengths_of(s, np.arange(3), 0.001)
    ids = np.array([70, 12, 40])
    named = BoneSamples(skel, ids[row_o], s.frame, s.length, s.var, s.both)
    cut = rng.permutation(R)
    parts = [named.take(np.sort(cut[:150])), named.take(np.sort(cut[150:]))]
    pooled = PersonBones.pooled(BoneSamples.joined(parts), 0.001)
    np.testing.assert_array_equal(pooled.ids, np.sort(ids))
    order = np.argsort(ids)
    np.testing.assert_allclose(pooled.lengths.length, whole.length[order], rtol=0, atol=1e-15)
    np.testing.assert_allclose(pooled.lengths.sd, whole.sd[order], rtol=1e-9)
    own = lengths_of(s, np.arange(2), 0.001)
    other = PersonBones(pooled.ids, replace(pooled.lengths, length=pooled.lengths.length + 1.0))
    applied = other.of(np.array([12, 99])).applied(own, np.array([12, 5]))
    np.testing.assert_array_equal(applied.length[0], other.lengths.length[0])  # id 12 (sorted first)
    np.testing.assert_array_equal(applied.length[1], own.length[1])  # id 5: not pooled

"""fusion.preparation.confidence: the keypoint noise as a function of the detector's confidence, learnt
from residuals, against residuals drawn with a known law."""

from __future__ import annotations

import numpy as np
import pytest

from gt3dkit.fusion.preparation.confidence import INVERSE, learn_curve


def _residuals(rng: np.random.Generator, law, n: int = 40_000, J: int = 5):
    """Squared 2-D residuals of ``n`` points with joint levels 1..J px and variance factor
    ``law(conf)``, 1 % of them gross (30x the sd)."""
    conf = rng.uniform(0.2, 1.0, n)
    joint = rng.integers(0, J, n)
    level = (1.0 + joint) ** 2
    r2 = level * law(conf) * rng.chisquare(2, n)
    gross = rng.random(n) < 0.01
    r2[gross] *= 900.0
    return r2, np.full(n, 2.0), np.ones(n, bool), conf, joint, level


@pytest.mark.parametrize("power", [1.0, 3.0])
def test_the_curve_is_the_law_that_drew_the_residuals(power: float) -> None:
    """Variance ``conf^-power`` (1: the old assumed rule; 3: close to what Shelf's OpenPose
    output shows): the learnt factors follow it (relative to the most confident bin) within
    10 %, and the joints' levels are recovered within 5 % at that bin's confidence."""
    rng = np.random.default_rng(int(power))
    r2, dof, use, conf, joint, level = _residuals(rng, lambda c: c ** -power)
    curve, var_j = learn_curve(r2, dof, use, conf, joint, 5, 1e-7)
    assert len(curve.knots) == 8 and np.all(np.diff(curve.factors) <= 0)
    want = (curve.knots / curve.knots[-1]) ** -power
    np.testing.assert_allclose(curve.factors, want, rtol=0.10)
    top = curve.knots[-1] ** -power
    np.testing.assert_allclose(var_j, np.unique(level) * top, rtol=0.05)
    np.testing.assert_allclose(curve(curve.knots), curve.factors)
    # below the least confident bin's median the law goes on (not flat at that bin's factor)
    np.testing.assert_allclose(curve(np.array([0.2])), (0.2 / curve.knots[-1]) ** -power, rtol=0.25)


def test_without_confidences_the_rule_stays_the_assumed_one() -> None:
    """All confidences 1 (the input gives none), or too few points to bin: ``1/conf``."""
    rng = np.random.default_rng(3)
    r2, dof, use, conf, joint, _ = _residuals(rng, lambda c: np.ones_like(c), n=5000)
    curve, _ = learn_curve(r2, dof, use, np.ones_like(conf), joint, 5, 1e-7)
    assert curve is INVERSE and curve(np.array([0.5]))[0] == 2.0
    curve, _ = learn_curve(r2[:500], dof[:500], use[:500], conf[:500], joint[:500], 5, 1e-7)
    assert curve is INVERSE

"""Posterior predictive intervals of held-out photos, and the misspecification flags
(:mod:`jaxrefl.svbrdf._predictive`), on small synthetic flash captures."""

from __future__ import annotations

import numpy as np
import pytest

from jaxrefl.demo import demo_scene, photograph_maps
from jaxrefl.svbrdf import (
    Discrepancy,
    FitJob,
    ModelCheck,
    estimate_discrepancy,
    fit_capture,
    predictive,
)

SIZE = 16
SIGMA = 0.004
HELD = 8
# Columns 0-11 a dielectric inside the model's range (grey F0 0.04); columns 12-15 a
# surface whose grey F0 (0.6) the ``ggx`` model cannot reach (its cap is 0.25).
F0_IN, F0_OUT, SPLIT = 0.04, 0.6, 12


def _capture(seed: int = 0):
    """(capture, truth): GGX + Lambert, albedo in [0.1, 0.6], alpha in [0.1, 0.3], grey F0
    as above; linear photos with Gaussian noise of std SIGMA (the fit's noise model)."""
    scene = demo_scene(size=SIZE)
    rng = np.random.default_rng(seed)
    f0 = np.where(np.arange(SIZE)[None, :] < SPLIT, F0_IN, F0_OUT) * np.ones((SIZE, SIZE))
    truth = {
        "albedo": rng.uniform(0.1, 0.6, (SIZE, SIZE, 3)),
        "specular": np.repeat(f0[..., None], 3, -1),
        "alpha": rng.uniform(0.1, 0.3, (SIZE, SIZE)),
    }
    return photograph_maps(scene, truth, SIGMA, rng), truth


@pytest.fixture(scope="module")
def fitted():
    cap, _truth = _capture()
    # One tile for the whole capture: the discrepancy's 8 stacked folds are 8 calls.
    job = FitJob(model="ggx", holdout=(HELD,), tile_pixels=SIZE * SIZE)
    cf = fit_capture(cap, job)
    disc = estimate_discrepancy(cap, cf)
    return cap, cf, disc, predictive(cap, cf, disc)


def test_out_of_range_f0_is_flagged_and_in_range_is_not(fitted):
    _cap, _cf, _disc, pred = fitted
    flag = pred.check.reshape(SIZE, SIZE)
    out, inside = flag[:, SPLIT:], flag[:, :SPLIT]
    assert np.mean(out != 0) > 0.9, pred.check_counts()
    assert np.mean((out & ModelCheck.AT_MODEL_BOUND) != 0) > 0.9
    assert np.mean(inside != 0) < 0.02, pred.check_counts()
    # the fit's own map (checked against the noise alone) agrees, and the report counts it
    _cap, cf, _disc, _pred = fitted
    m = cf.maps["misspecified"]
    assert m.dtype == np.uint32
    assert np.mean(m[:, SPLIT:] != 0) > 0.9 and np.mean(m[:, :SPLIT] != 0) < 0.02
    assert cf.report["misspecified_counts"]["misspecified"] == int(np.sum(m != 0))


def test_held_out_intervals_cover_at_the_nominal_rate(fitted):
    _cap, _cf, disc, pred = fitted
    ok = ~pred.misspecified
    # the training photos of a well-specified capture ask for no discrepancy below the
    # out-of-range highlights (the brightest bin)
    assert np.sqrt(np.max(disc.var[:-1])) < SIGMA, disc.as_dict()
    for level in (0.5, 0.9):
        cov, n = pred.coverage(HELD, level, ok)
        assert n > 400
        assert abs(cov - level) < 0.05, (level, cov)
    # without the noise term the intervals are far too narrow: the test can fail
    cov, _ = pred.coverage(HELD, 0.9, ok, terms=("param",))
    assert cov < 0.75, cov


def test_discrepancy_term_and_bad_arguments(fitted):
    cap, cf, _disc, pred = fitted
    d = Discrepancy(np.array([0.1, 0.3]), np.array([1e-4, 4e-4]))
    np.testing.assert_allclose(d(np.array([0.0, 0.2, 1.0])), [1e-4, 2.5e-4, 4e-4])
    wider = predictive(cap, cf, d)
    want = pred.std(("param", "noise")) ** 2 + d(pred.mean)
    np.testing.assert_allclose(wider.std() ** 2, want, rtol=1e-6)
    with pytest.raises(ValueError, match="level"):
        pred.interval(1.5)
    with pytest.raises(ValueError, match="terms"):
        pred.std(("noise", "bias"))
    with pytest.raises(ValueError, match="pixels"):
        predictive(cap.crop(0, 8, 0, SIZE), cf)

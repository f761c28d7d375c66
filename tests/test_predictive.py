"""Posterior predictive intervals of held-out photos, and the misspecification flags
(:mod:`jaxrefl.svbrdf._predictive`), on small synthetic flash captures."""

from __future__ import annotations

from dataclasses import replace

import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl.demo import demo_scene, photograph_maps
from jaxrefl.svbrdf import (
    Discrepancy,
    DiscrepancyOptions,
    FitJob,
    ModelCheck,
    capture_model,
    estimate_discrepancy,
    fit_capture,
    predictive,
)
from jaxrefl.svbrdf._check import bound_bits

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


def test_alpha_at_its_floor_is_a_bit_of_its_own():
    """ALPHA_AT_FLOOR: a lobe whose width piles against the floor (the mode there, or near
    it with the Laplace interval reaching it), always with AT_MODEL_BOUND; not the ceiling,
    not a width inside the range, not a pixel without a lobe (F0 at 0: alpha says nothing)."""
    _model, space = capture_model("ggx_rgb", channels=3, alpha_min=0.05)
    f0 = np.array([0.2, 0.0, 0.2, 0.2, 0.2])
    alpha = np.array([0.05, 0.05, 1.0, 0.2, 0.052])
    theta = np.asarray(
        space.from_natural(
            {
                "albedo": np.full((5, 3), 0.3),
                "specular": np.repeat(f0[:, None], 3, 1),
                "alpha": alpha,
            }
        )
    )
    std = np.full_like(theta, 0.05)
    std[:, space.labels.index("alpha")] = [0.05, 0.05, 0.05, 0.05, 1.0]
    both = int(ModelCheck.AT_MODEL_BOUND | ModelCheck.ALPHA_AT_FLOOR)
    at = int(ModelCheck.AT_MODEL_BOUND)
    assert bound_bits(space, theta, std).tolist() == [both, 0, at, 0, both]
    assert bound_bits(space, theta).tolist() == [both, 0, at, 0, 0]  # the mode alone
    nan = theta.copy()
    nan[0, 0] = np.nan
    assert bound_bits(space, nan, std)[0] == 0  # no estimate, no flag


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


def test_one_capture_noise_scale_is_replaced_by_a_variance_function(fitted):
    """``pooled`` has one known noise scale for the capture: by default the discrepancy
    estimate replaces it with a variance function of the radiance; the per-pixel ``ggx``
    keeps its per-pixel noise (the module fixture's estimate)."""
    cap, _cf, disc_ggx, _pred = fitted
    assert not disc_ggx.replaces_noise
    cf = fit_capture(cap, FitJob(model="pooled", holdout=(HELD,), tile_pixels=SIZE * SIZE))
    disc = estimate_discrepancy(cap, cf)
    assert disc.replaces_noise and np.all(disc.var > 0), disc.as_dict()
    pred = predictive(cap, cf, disc)
    np.testing.assert_allclose(pred.noise_var, disc(pred.mean), rtol=1e-12)
    assert np.all(pred.disc_var == 0)
    # its noise variance is known: normal Laplace marginals
    from jaxrefl.svbrdf._uncertainty import laplace_dof

    dof = laplace_dof(cf)
    assert np.all(np.isinf(dof[~np.isnan(dof)])) and np.mean(~np.isnan(dof)) > 0.9
    kept = estimate_discrepancy(cap, cf, DiscrepancyOptions(replace_noise=False))
    assert not kept.replaces_noise
    known = float(cf.pooled.sigma) ** 2
    np.testing.assert_allclose(predictive(cap, cf, kept).noise_var, known, rtol=1e-5)


def test_variance_function_rescales_the_parameter_term_to_the_pixels_own_noise():
    """Noise that grows with the radiance (std 3% of it) over albedos spread across two
    decades, under ``pooled``'s one noise scale: its Laplace covariance takes every pixel as
    noisy as the capture's median, so a dark pixel's parameter term alone is wider than its
    errors. The variance function rescales it by f = 1 / mean(v_fit / e^2(mu)) over the
    pixel's training observations (checked against that formula), which brings the dark
    fifth of the held-out photo down towards its nominal 50% (e^2 includes the parameter
    term, so the rescaled intervals stay a little wide)."""
    scene = demo_scene(size=SIZE)
    rng = np.random.default_rng(7)
    albedo = np.exp(rng.uniform(np.log(0.005), np.log(0.8), (SIZE, SIZE, 1)))
    truth = {
        "albedo": albedo * np.ones(3),
        "specular": np.full((SIZE, SIZE, 3), F0_IN),
        "alpha": np.full((SIZE, SIZE), 0.2),
    }
    clean = photograph_maps(scene, truth)
    noisy = clean.images * (1.0 + 0.03 * rng.standard_normal(clean.images.shape))
    cap = replace(clean, images=noisy.astype(np.float32))
    cf = fit_capture(cap, FitJob(model="pooled", holdout=(HELD,), tile_pixels=SIZE * SIZE))
    disc = estimate_discrepancy(cap, cf)
    assert disc.error_var is not None and np.all(disc.var <= disc.error_var), disc.as_dict()
    pred = predictive(cap, cf, disc)
    plain = predictive(cap, cf, Discrepancy(disc.radiance, disc.var, replaces_noise=True))
    known = float(cf.pooled.sigma) ** 2
    err = np.interp(pred.mean, disc.radiance, disc.error_var)
    train = np.arange(cap.n_photos) != HELD
    f = 1.0 / np.mean((known / err)[:, train], axis=(1, 2))
    ok = ~pred.no_covariance
    np.testing.assert_allclose(pred.param_var[ok], (plain.param_var * f[:, None, None])[ok])
    lum = pred.mean[:, HELD].mean(-1)
    dark = lum <= np.quantile(lum, 0.2)
    rescaled, _ = pred.coverage(HELD, 0.5, dark)
    unscaled, _ = plain.coverage(HELD, 0.5, dark)
    assert unscaled > 0.7 and rescaled < unscaled - 0.12, (rescaled, unscaled)
    assert abs(pred.coverage(HELD, 0.5)[0] - 0.5) < 0.05


def test_laplace_intervals_are_student_t_where_the_noise_was_estimated(fitted):
    """``ggx`` estimates each pixel's noise scale: its Laplace marginals are Student t with
    n_used - P degrees of freedom (8 photos x 3 channels - 5 parameters = 19 here), in the
    unconstrained space, mapped through the bijection; a known noise scale gives the normal
    quantile."""
    from scipy import stats

    from jaxrefl.svbrdf._uncertainty import laplace_dof, laplace_interval, laplace_theta_std

    _cap, cf, _disc, _pred = fitted
    _model, space = cf.model()
    dof = laplace_dof(cf)
    p = len(space.labels)
    ok = np.isfinite(dof)
    assert ok.mean() > 0.9
    np.testing.assert_array_equal(dof[ok], cf.maps["n_used"].reshape(-1)[ok] - p)
    assert np.median(dof[ok]) == 8 * 3 - p
    box = laplace_interval(cf, 0.9)
    j = space.labels.index("alpha")
    lo, hi = box["alpha"]
    theta = np.asarray(cf.theta, np.float64)
    s_t = laplace_theta_std(cf, space)[:, j]
    use = ok & np.isfinite(s_t) & np.isfinite(lo)
    assert use.mean() > 0.9
    q = stats.t.ppf(0.95, dof[use])
    t_lo, t_hi = theta.copy(), theta.copy()
    t_lo[use, j] -= q * s_t[use]
    t_hi[use, j] += q * s_t[use]
    nat_lo = np.asarray(space.natural_vector(jnp.asarray(np.nan_to_num(t_lo))))[:, j]
    nat_hi = np.asarray(space.natural_vector(jnp.asarray(np.nan_to_num(t_hi))))[:, j]
    np.testing.assert_allclose(lo[use], nat_lo[use], rtol=1e-9)
    np.testing.assert_allclose(hi[use], nat_hi[use], rtol=1e-9)
    # 19 degrees of freedom: 4.6% wider than the normal interval in theta
    z = stats.norm.ppf(0.95)
    assert np.all(q / z > 1.04)
    a = cf.maps["alpha"].reshape(-1)[use]
    assert np.all((lo[use] <= a) & (a <= hi[use]))
    with pytest.raises(ValueError, match="level"):
        laplace_interval(cf, 1.0)


def test_discrepancy_options_are_checked():
    for bad, match in (
        (dict(max_pixels=0), "integer max_pixels >= 1"),
        (dict(bins=0), "integer bins >= 1"),
        (dict(seed=-2), "integer seed >= 0"),
        (dict(replace_noise="yes"), "replace_noise True, False or None"),
    ):
        with pytest.raises(ValueError, match=match):
            DiscrepancyOptions(**bad)
    assert DiscrepancyOptions().to_json() == {
        "type": "discrepancy",
        "max_pixels": 4096,
        "bins": 8,
        "seed": 0,
        "replace_noise": None,
    }

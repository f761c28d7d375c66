"""Exact Gibbs sampling of linear-Gaussian pixel posteriors (:mod:`jaxrefl.posterior._gibbs`):
known answers, agreement with HMC, and which posteriors take that path."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxrefl import fit, svbrdf
from jaxrefl import posterior as jp
from jaxrefl.demo import demo_scene, photograph_maps
from jaxrefl.posterior._gibbs import linear_terms, qualifies, sample_gibbs, truncated_normal

SIZE = 8


def _capture(albedo_scale: float = 1.0, f0: float = 0.5, sigma: float = 0.004, seed: int = 0):
    """A co-located flash capture of GGX + Lambert pixels (alpha 0.2, F0 ``f0`` grey)."""
    scene = demo_scene(size=SIZE)
    rng = np.random.default_rng(seed)
    truth = {
        "albedo": albedo_scale * rng.uniform(0.0, 0.4, (SIZE, SIZE, 3)),
        "specular": np.full((SIZE, SIZE, 3), f0),
        "alpha": np.full((SIZE, SIZE), 0.2),
    }
    return photograph_maps(scene, truth, sigma, rng)


def test_lambert_with_known_noise_is_the_exact_truncated_normal():
    """Lambert albedo with a known noise sigma: per channel the posterior is N(r/Q, s^2/Q)
    truncated to [0, 1]. Pixels whose albedo is 0 have half their mass cut at the bound."""
    sigma = 0.02
    cap = _capture(albedo_scale=0.0, f0=0.0, sigma=sigma)  # every albedo 0: a bound
    model, space = svbrdf.capture_model("lambert", channels=3)
    lp = jp.log_posterior(model, space, fit.GaussianNoise(sigma=sigma))
    assert lp.noise_scale is None
    data = svbrdf.pixel_block(cap, 0, 4, dtype=np.float64)
    assert qualifies(lp, data) == (True, "")
    theta0 = jnp.zeros((4, lp.size))
    s = sample_gibbs(
        lp, data, theta0, num_chains=4, num_warmup=50, num_samples=2000, sweeps=1, seed=3
    )
    assert s.method == "gibbs" and s.theta.shape == (4, 4, 2000, 3)
    a, b, ok = linear_terms(lp, data)
    assert np.all(np.asarray(ok))
    for i in range(4):
        for c in range(3):
            rows = slice(c, None, 3)  # observations of channel c (K x C, row-major)
            ai = np.asarray(a[i, rows, c]) / sigma
            yi = (np.asarray(data.obs[i, :, c]) - np.asarray(b[i, rows])) / sigma
            q, r = ai @ ai, ai @ yi
            m, sd = r / q, 1.0 / np.sqrt(q)
            exact = stats.truncnorm((0.0 - m) / sd, (1.0 - m) / sd, loc=m, scale=sd)
            draws = s.natural[i, :, :, c].reshape(-1)
            se = exact.std() / np.sqrt(draws.size)  # draws are independent (one direction)
            assert abs(draws.mean() - exact.mean()) < 5 * se, (i, c)
            assert draws.std() == pytest.approx(exact.std(), rel=0.05)
            for qq in (0.05, 0.5, 0.95):
                assert np.quantile(draws, qq) == pytest.approx(exact.ppf(qq), abs=0.1 * sd)


@pytest.fixture(scope="module")
def pooled_posterior():
    cap = _capture()
    job = svbrdf.FitJob(
        model="pooled", config=fit.FitConfig(dtype=np.float64), tile_pixels=SIZE * SIZE
    )
    cf = svbrdf.fit_capture(cap, job)
    model, space = cf.model()
    lp = jp.log_posterior(model, space, fit.GaussianNoise(None))
    data = svbrdf.pixel_block(cap, 0, SIZE * SIZE, dtype=np.float64)
    keep = np.flatnonzero(~np.any(np.asarray(data.censored) != 0, axis=(1, 2)))[:6]
    sub = jax.tree.map(lambda x: x[keep], data)
    noise0 = np.nan_to_num(cf.maps["noise_std"].reshape(-1)[keep], nan=1e-2)
    theta0 = lp.init_theta(jnp.asarray(cf.theta[keep]), noise_scale=np.maximum(noise0, 1e-3))
    return lp, sub, theta0


def test_gibbs_agrees_with_hmc_on_the_pooled_posterior(pooled_posterior):
    """``pooled`` (shared alpha, coloured F0 up to 1), unknown noise scale (Jeffreys): the
    same posterior sampled by HMC and by exact Gibbs, means within 5 Monte Carlo standard
    errors and stds within 10%."""
    lp, sub, theta0 = pooled_posterior
    assert qualifies(lp, sub) == (True, "")
    assert lp.labels[-1] == "noise_scale"
    g = jp.sample_pixels(
        lp,
        sub,
        theta0,
        options=jp.HMCOptions(num_warmup=100, num_samples=1000, num_chains=4),
        gibbs=jp.GibbsOptions(sweeps=2),
        seed=1,
    )
    assert g.method == "gibbs"
    h = jp.sample_pixels(
        lp, sub, theta0, options=jp.HMCOptions(num_warmup=500, num_samples=1000), seed=2
    )
    assert h.method == "hmc"
    dg, dh = jp.diagnostics(g), jp.diagnostics(h)
    assert np.all(dg["max_rhat"] < 1.02), dg["max_rhat"]
    # HMC's chains in logit coordinates need not agree where a colour piles at its bound;
    # compare where they do (most pixels)
    good = dh["max_rhat"] < 1.05
    assert good.sum() >= 4, dh["max_rhat"]
    ess = np.minimum(dg["ess_bulk"], dh["ess_bulk"])[good]  # (N, D)
    mg, mh = g.natural.mean(axis=(1, 2))[good], h.natural.mean(axis=(1, 2))[good]
    sg, sh = g.natural.std(axis=(1, 2))[good], h.natural.std(axis=(1, 2))[good]
    mcse = np.sqrt(sg**2 + sh**2) / np.sqrt(ess)
    assert np.all(np.abs(mg - mh) < 5 * mcse), np.max(np.abs(mg - mh) / mcse)
    np.testing.assert_allclose(sg, sh, rtol=0.1)
    # every draw lies strictly inside the box, so its theta is finite
    assert np.all(np.isfinite(g.theta)) and np.all(np.isfinite(g.stats["lp"]))


def test_only_linear_gaussian_posteriors_take_the_gibbs_path(pooled_posterior):
    lp, sub, theta0 = pooled_posterior
    opts = jp.HMCOptions(num_warmup=20, num_samples=20, num_chains=2)
    gibbs = jp.GibbsOptions(sweeps=1)
    # a censored observation with a fractional weight: not a Tobit likelihood
    cens = np.asarray(sub.censored).copy()
    cens[0, 0, 0] = 1
    wts = np.asarray(sub.weight).copy()
    wts[0, 0, 0] = 0.5
    half = sub.__class__(**{**sub.__dict__, "censored": jnp.asarray(cens), "weight": wts})
    assert not qualifies(lp, half)[0]
    assert jp.sample_pixels(lp, half, theta0, options=opts, gibbs=gibbs).method == "hmc"
    # a per-pixel lobe width: not linear, and alpha's prior is not uniform
    model, space = svbrdf.capture_model("ggx", channels=3)
    ggx = jp.log_posterior(model, space, fit.GaussianNoise(None))
    ok, why = qualifies(ggx, sub)
    assert not ok and "uniform prior" in why
    # a robust loss: not Gaussian
    model, space = lp.model, lp.space
    huber = jp.log_posterior(model, space, fit.GaussianNoise(None), loss=fit.Huber(1.0))
    assert qualifies(huber, sub) == (False, "the loss is Huber, not L2")
    # no GibbsOptions (the default): HMC even where Gibbs would be exact
    assert jp.sample_pixels(lp, sub, theta0, options=opts).method == "hmc"
    with pytest.raises(ValueError, match="sweeps"):
        jp.GibbsOptions(sweeps=0)


def test_gibbs_path_discards_its_fraction_of_the_warm_up(pooled_posterior):
    """sample_pixels' Gibbs path runs sample_gibbs with num_warmup * warmup_fraction
    intervals of warm-up (at least 1): the same draws as a direct call with that count."""
    lp, sub, theta0 = pooled_posterior
    opts = jp.HMCOptions(num_warmup=50, num_samples=20, num_chains=2)
    gibbs = jp.GibbsOptions(sweeps=1)
    assert gibbs.warmup(opts.num_warmup) == 10
    assert jp.GibbsOptions(warmup_fraction=0.1).warmup(2) == 1
    s = jp.sample_pixels(lp, sub, theta0, options=opts, gibbs=gibbs, seed=7)
    kw = dict(num_chains=2, num_samples=20, sweeps=1, seed=7)
    direct = sample_gibbs(lp, sub, theta0, num_warmup=10, **kw)
    longer = sample_gibbs(lp, sub, theta0, num_warmup=50, **kw)
    assert s.method == "gibbs"
    np.testing.assert_array_equal(s.theta, direct.theta)
    assert not np.array_equal(s.theta, longer.theta)
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="warmup_fraction"):
            jp.GibbsOptions(warmup_fraction=bad)


def test_censored_observations_by_data_augmentation_agree_with_hmc(pooled_posterior):
    """The brightest observation of each pixel recorded as clipped (only a lower bound is
    known): Gibbs with latent values and HMC on the Tobit likelihood give the same
    posterior."""
    lp, sub, theta0 = pooled_posterior
    obs = np.asarray(sub.obs)
    cens = np.zeros(obs.shape, np.int8)
    flat = obs.reshape(obs.shape[0], -1)
    top = np.argmax(flat, axis=1)
    cens.reshape(obs.shape[0], -1)[np.arange(obs.shape[0]), top] = 1
    clipped = sub.__class__(**{**sub.__dict__, "censored": jnp.asarray(cens)})
    assert qualifies(lp, clipped) == (True, "")
    g = jp.sample_pixels(
        lp,
        clipped,
        theta0,
        options=jp.HMCOptions(num_warmup=100, num_samples=1000, num_chains=4),
        gibbs=jp.GibbsOptions(sweeps=2),
        seed=3,
    )
    h = jp.sample_pixels(
        lp, clipped, theta0, options=jp.HMCOptions(num_warmup=500, num_samples=1000), seed=4
    )
    assert g.method == "gibbs" and h.method == "hmc"
    dg, dh = jp.diagnostics(g), jp.diagnostics(h)
    assert np.all(dg["max_rhat"] < 1.02), dg["max_rhat"]
    good = dh["max_rhat"] < 1.05
    assert good.sum() >= 4, dh["max_rhat"]
    ess = np.minimum(dg["ess_bulk"], dh["ess_bulk"])[good]
    mg, mh = g.natural.mean(axis=(1, 2))[good], h.natural.mean(axis=(1, 2))[good]
    sg, sh = g.natural.std(axis=(1, 2))[good], h.natural.std(axis=(1, 2))[good]
    mcse = np.sqrt(sg**2 + sh**2) / np.sqrt(ess)
    assert np.all(np.abs(mg - mh) < 5 * mcse), np.max(np.abs(mg - mh) / mcse)
    np.testing.assert_allclose(sg, sh, rtol=0.1)


@pytest.mark.parametrize(
    ("a", "b"),
    [
        (-1.0, 2.0),  # around 0
        (2.5, 3.0),
        (8.0, np.inf),  # beyond where erf(a / sqrt 2) rounds to 1
        (8.0, 8.3),
        (-np.inf, -9.0),  # the lower tail, mirrored
        (20.0, 20.05),
        (45.0, np.inf),  # the exponential limit
    ],
)
def test_truncated_normal_matches_scipy_far_in_the_tails(a, b):
    """The Gibbs sampler's truncated normal against scipy's, by a Kolmogorov-Smirnov test,
    on segments up to 45 standard deviations out: a posterior piled against a bound keeps
    its spread (an erf-based inverse CDF returns the bound itself there)."""
    n = 20_000
    z = np.asarray(truncated_normal(jax.random.key(7), np.full(n, a), np.full(n, b)))
    assert np.all(np.isfinite(z)) and np.all((z >= a) & (z <= b))
    ref = stats.truncnorm(a, b)
    assert stats.kstest(z, ref.cdf).pvalue > 1e-3
    assert np.std(z) == pytest.approx(ref.std(), rel=0.05)
    z32 = np.asarray(truncated_normal(jax.random.key(8), a, b, jnp.float32))
    assert z32.dtype == np.float32 and a <= z32 <= b

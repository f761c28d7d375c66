"""Metropolis-within-Gibbs for posteriors linear-Gaussian given the lobe width
(:mod:`jaxrefl.posterior._width_gibbs`): the exact marginals by quadrature, agreement with
HMC under censoring and an unknown noise scale, and which posteriors take that path."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import special

from jaxrefl import fit, svbrdf
from jaxrefl import posterior as jp
from jaxrefl.demo import demo_scene, photograph_maps
from jaxrefl.posterior._conjugate import theta_of as _theta_of
from jaxrefl.posterior._width_gibbs import qualifies_width, sample_width_gibbs
from jaxrefl.svbrdf._uncertainty import laplace_theta_std

SIZE = 8
SIGMA = 0.004


@pytest.fixture(scope="module")
def ggx_fit():
    """A co-located flash capture of per-pixel GGX + Lambert (alpha 0.05-0.6, F0 0-0.08),
    fitted with ``ggx``; (capture, fit, the 6 pixels with no censored observation whose
    Laplace is flagged first, then the others)."""
    scene = demo_scene(size=SIZE)
    rng = np.random.default_rng(5)
    truth = {
        "albedo": rng.uniform(0.05, 0.5, (SIZE, SIZE, 3)),
        "specular": np.repeat(rng.uniform(0.0, 0.08, (SIZE, SIZE, 1)), 3, -1),
        "alpha": np.exp(rng.uniform(np.log(0.05), np.log(0.6), (SIZE, SIZE))),
    }
    cap = photograph_maps(scene, truth, SIGMA, rng)
    job = svbrdf.FitJob(model="ggx", config=fit.FitConfig(dtype=np.float64), tile_pixels=64)
    cf = svbrdf.fit_capture(cap, job)
    data = svbrdf.pixel_block(cap, 0, SIZE * SIZE, dtype=np.float64)
    clean = ~np.any(np.asarray(data.censored) != 0, axis=(1, 2))
    flag = cf.maps["laplace_flag"].reshape(-1)
    order = np.concatenate(
        [np.flatnonzero(clean & (flag != 0)), np.flatnonzero(clean & (flag == 0))]
    )
    return cap, cf, data, order[:6]


def _posterior(cf, noise, priors=None):
    model, space = cf.model()
    return jp.log_posterior(model, space, noise, priors=priors), space


def _alpha_f0_marginals(lp, d, u_grid, f0_grid):
    """log p(u = log alpha, F0 | y) on a grid by quadrature, the albedo integrated out in
    closed form (channel c's observations depend on albedo_c and F0 only; each albedo's
    integral over [0, 1] is a truncated Gaussian's mass). Known noise SIGMA."""
    y = np.asarray(d.obs)  # (K, C)
    w = np.asarray(d.weight) * np.asarray(lp.residual.usable(d))
    k, c = y.shape
    labels = lp.labels
    ia, i_f0 = labels.index("alpha"), labels.index("specular")
    ialb = [labels.index(f"albedo.{ch}") for ch in "RGB"]
    p = len(lp.space.lower)
    prior = lp.priors[[b.name for b in lp.space.blocks].index("alpha")]
    # natural vectors per width: b (all 0), F0 = 0.2, albedo_c = 0.5 (interior points:
    # the bijections clip at the box's edges); one vmapped prediction of all of them
    base = np.zeros((u_grid.size, 5, p))
    base[:, :, ia] = np.exp(u_grid)[:, None]
    base[:, 1, i_f0] = 0.2
    for ch, i in enumerate(ialb):
        base[:, 2 + ch, i] = 0.5

    @jax.jit
    def pred(v):
        return jax.vmap(lambda vi: lp.residual.predict(_theta_of(lp, vi), d))(v)

    preds = np.asarray(pred(jnp.asarray(base.reshape(-1, p)))).reshape(u_grid.size, 5, k, c)
    b = preds[:, 0]
    a_f0 = (preds[:, 1] - b) / 0.2
    lam = np.stack([(preds[:, 2 + ch] - b)[..., ch] / 0.5 for ch in range(c)], -1)  # (U, K, C)
    out = np.empty((u_grid.size, f0_grid.size))
    for j, _u in enumerate(u_grid):
        r0 = (y[None] - b[j][None] - f0_grid[:, None, None] * a_f0[j][None]) / SIGMA
        lw = lam[j] / SIGMA
        q = np.sum(w * lw * lw, axis=0)  # (C,)
        m = np.sum(w[None] * lw[None] * r0, axis=1) / q  # (F, C)
        min_sse = np.sum(w[None] * r0 * r0, axis=1) - q * m * m
        sq = np.sqrt(q)
        mass = special.ndtr((1.0 - m) * sq) - special.ndtr((0.0 - m) * sq)
        log_int = -0.5 * min_sse + np.log(np.maximum(mass, 1e-300)) - np.log(sq)
        out[j] = np.sum(log_int, axis=1)
    out += (np.asarray(prior.log_prob(jnp.exp(jnp.asarray(u_grid)))) + u_grid)[:, None]
    f0_prior = lp.priors[[b.name for b in lp.space.blocks].index("specular")]
    out += np.asarray(f0_prior.log_prob(jnp.asarray(f0_grid)))[None, :]
    return out


def _ks(draws, grid, log_density):
    """Largest distance between the draws' empirical CDF and the quadrature's on the grid."""
    dens = np.exp(log_density - log_density.max())
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
    cdf /= cdf[-1]
    emp = np.searchsorted(np.sort(draws), grid, side="right") / draws.size
    return float(np.max(np.abs(emp - cdf)))


@pytest.mark.parametrize("f0_prior", [None, jp.Normal(0.02, 0.015)], ids=["uniform", "normal"])
def test_draws_have_the_quadrature_marginals_of_alpha_and_f0(ggx_fit, f0_prior):
    """Known noise: the marginal CDFs of log alpha and of F0 from the draws match the
    posterior integrated on a grid (albedo in closed form) within a Kolmogorov distance of
    0.04 on each of 3 pixels, the flagged first; with F0's uniform prior and with a
    Gaussian one (truncated to F0's box), which the sampler takes into its moves; from the
    fit's start, and from a start more than a decade above a narrow lobe's posterior."""
    _cap, cf, data, pick = ggx_fit
    priors = None if f0_prior is None else {"specular": f0_prior}
    lp, space = _posterior(cf, fit.GaussianNoise(sigma=SIGMA), priors)
    sub = jax.tree.map(lambda x: x[pick[:3]], data)
    assert qualifies_width(lp, sub) == (True, "")
    theta0 = jnp.asarray(cf.theta[pick[:3]])
    std = laplace_theta_std(cf, space)[pick[:3]]
    run = functools.partial(sample_width_gibbs, lp, sub, num_chains=4, num_warmup=20)
    s = run(theta0=theta0, theta_std=std, num_samples=2000, sweeps=1, seed=11)
    assert s.method == "gibbs_mh" and s.natural.shape == (3, 4, 2000, lp.size)
    assert np.all(np.isfinite(s.theta)) and np.all(np.isfinite(s.stats["lp"]))
    assert 0.2 < float(np.mean(s.stats["acceptance_rate"])) <= 1.0
    lo, hi = space.lower[lp.labels.index("alpha")], space.upper[lp.labels.index("alpha")]
    u_grid = np.linspace(np.log(lo), np.log(hi), 700)
    f0_grid = np.linspace(0.0, 0.25, 501)
    ia, i_f0 = lp.labels.index("alpha"), lp.labels.index("specular")
    # A second run from alpha = 0.95 with a tiny Laplace std there (a fit stuck at a
    # bound): the local cells sit at 0.95, the even ones start at 0.095, and only the
    # coarse ones below propose the posterior of a narrower lobe (pixel 0's). The
    # scans between draws are an argument of the compiled program, not a constant of it:
    # twice as many (the second pass of a map, untuned_rerun) compile nothing new.
    from jaxrefl.cli._compile import CompileClock

    high = dict(space.to_natural(theta0))
    high["alpha"] = jnp.full_like(high["alpha"], 0.95)
    theta_high = space.from_natural(high)
    std_high = np.where(np.arange(lp.size) == ia, 1e-6, std)
    clock = CompileClock().start()
    try:
        s2 = run(num_samples=2000, sweeps=2, seed=12, theta0=theta_high, theta_std=std_high)
    finally:
        clock.stop()
    assert clock.programs == 0 and s2.sweeps == 2
    assert np.all(np.isfinite(s2.theta)) and not np.array_equal(s2.theta, s.theta)
    assert np.median(s.natural[0, ..., ia]) < 0.095
    for j in range(3):
        d = jax.tree.map(lambda x, j=j: x[j], sub)
        logp = _alpha_f0_marginals(lp, d, u_grid, f0_grid)
        top = logp.max()
        log_u = np.log(np.sum(np.exp(logp - top), axis=1))
        log_f0 = np.log(np.sum(np.exp(logp - top), axis=0))
        for name, draws in (("fit's start", s), ("alpha 0.95", s2)):
            ks_u = _ks(np.log(draws.natural[j, ..., ia]).reshape(-1), u_grid, log_u)
            ks_f = _ks(draws.natural[j, ..., i_f0].reshape(-1), f0_grid, log_f0)
            assert ks_u < 0.04 and ks_f < 0.04, (name, j, ks_u, ks_f)


def test_agrees_with_hmc_with_censoring_an_unknown_noise_scale_and_a_gaussian_prior(ggx_fit):
    """The brightest observation of each pixel recorded as clipped, noise scale unknown
    (Jeffreys), a Gaussian prior on F0 in units of the noise (N(0.03, 0.02^2) where s is
    the capture's noise, as informative as the photos): the draws and HMC's (4 chains x
    1000) on the Tobit likelihood have the same means (within 5 Monte Carlo standard errors)
    and standard deviations (within 15%; HMC's chains twice as long as without the prior:
    with it, 500 draws leave the tails of a width the photos hardly see short by 10%). The
    same prior in absolute units is not conjugate with an unknown noise scale: it takes
    the HMC path. The prior pulls F0 towards its mean."""
    _cap, cf, data, pick = ggx_fit
    sub = jax.tree.map(lambda x: x[pick], data)
    absolute = jp.MultivariateNormal((0.03,), ((0.02**2,),))
    lp, _ = _posterior(cf, fit.GaussianNoise(None), {"specular": absolute})
    ok, why = qualifies_width(lp, sub)
    assert not ok and "noise_ref" in why
    prior = jp.MultivariateNormal((0.03,), ((0.02**2,),), noise_ref=SIGMA)
    lp, space = _posterior(cf, fit.GaussianNoise(None), {"specular": prior})
    obs = np.asarray(sub.obs)
    cens = np.zeros(obs.shape, np.int8)
    top = np.argmax(obs.reshape(obs.shape[0], -1), axis=1)
    cens.reshape(obs.shape[0], -1)[np.arange(obs.shape[0]), top] = 1
    clipped = sub.__class__(**{**sub.__dict__, "censored": jnp.asarray(cens)})
    noise0 = np.nan_to_num(cf.maps["noise_std"].reshape(-1)[pick], nan=1e-2)
    theta0 = lp.init_theta(jnp.asarray(cf.theta[pick]), noise_scale=np.maximum(noise0, 1e-3))
    std = np.concatenate([laplace_theta_std(cf, space)[pick], np.ones((6, 1))], 1)
    assert qualifies_width(lp, clipped) == (True, "")
    g = jp.sample_pixels(
        lp,
        clipped,
        theta0,
        theta_std=std,
        options=jp.HMCOptions(num_warmup=100, num_samples=1000, num_chains=4),
        gibbs=jp.GibbsOptions(sweeps=2),
        seed=1,
    )
    assert g.method == "gibbs_mh"
    h = jp.sample_pixels(
        lp,
        clipped,
        theta0,
        theta_std=std,
        options=jp.HMCOptions(num_warmup=500, num_samples=1000),
        seed=2,
    )
    dg, dh = jp.diagnostics(g), jp.diagnostics(h)
    assert np.all(dg["max_rhat"] < 1.02), dg["max_rhat"]
    good = dh["max_rhat"] < 1.05
    assert good.sum() >= 4, dh["max_rhat"]
    ess = np.minimum(dg["ess_bulk"], dh["ess_bulk"])[good]
    mg, mh = g.natural.mean(axis=(1, 2))[good], h.natural.mean(axis=(1, 2))[good]
    sg, sh = g.natural.std(axis=(1, 2))[good], h.natural.std(axis=(1, 2))[good]
    mcse = np.sqrt(sg**2 + sh**2) / np.sqrt(ess)
    assert np.all(np.abs(mg - mh) < 5 * mcse), np.max(np.abs(mg - mh) / mcse)
    np.testing.assert_allclose(sg, sh, rtol=0.15)
    # the prior binds: the F0 draws sit nearer its mean than the fit's optimum
    j = lp.labels.index("specular")
    x_fit = np.asarray(space.natural_vector(jnp.asarray(cf.theta[pick])))[good][:, j]
    assert np.mean(np.abs(mg[:, j] - 0.03)) < np.mean(np.abs(x_fit - 0.03))


def test_which_posteriors_take_the_width_path(ggx_fit):
    _cap, cf, data, pick = ggx_fit
    assert jp.UNCERTAINTY_MAP_GIBBS.width_scans == 1 and jp.GibbsOptions().width_scans is None
    with pytest.raises(ValueError, match="width_scans"):
        jp.GibbsOptions(width_scans=0)
    lp, _space = _posterior(cf, fit.GaussianNoise(None))
    sub = jax.tree.map(lambda x: x[pick[:2]], data)
    assert qualifies_width(lp, sub) == (True, "")
    # (sample_pixels takes this path given GibbsOptions and HMC without: the ridge test
    # of tests/test_posterior_reparam.py runs both)
    # a robust loss is not Gaussian
    huber = jp.log_posterior(lp.model, lp.space, fit.GaussianNoise(None), loss=fit.Huber(1.0))
    assert qualifies_width(huber, sub) == (False, "the loss is Huber, not L2")
    # a per-pixel normal: the tilts are a second nonlinear parameter
    model, space = svbrdf.capture_model("ggx_normal", channels=3)
    tilt = jp.log_posterior(model, space, fit.GaussianNoise(None))
    assert qualifies_width(tilt, sub) == (
        False,
        "the model is not linear in its parameters given 'alpha'",
    )
    # Lambert has no width
    model, space = svbrdf.capture_model("lambert", channels=3)
    lam = jp.log_posterior(model, space, fit.GaussianNoise(None))
    assert not qualifies_width(lam, sub)[0]
    # a censored observation with a fractional weight is not a Tobit likelihood
    cens = np.asarray(sub.censored).copy()
    cens[0, 0, 0] = 1
    wts = np.asarray(sub.weight).copy()
    wts[0, 0, 0] = 0.5
    half = sub.__class__(**{**sub.__dict__, "censored": jnp.asarray(cens), "weight": wts})
    assert qualifies_width(lp, half) == (
        False,
        "a censored observation has a weight other than 0 or 1",
    )

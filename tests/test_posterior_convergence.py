"""emcee's stopping rule (a chain of at least 50 autocorrelation times, R-hat, ESS) and
``posterior.nc`` as ArviZ users use it: weights and censoring in ``constant_data``, named
coordinates, a pointwise ``log_likelihood`` that ``az.loo`` / ``az.compare`` rank models by."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import fit
from jaxrefl import posterior as jp
from jaxrefl.measured import build_model
from jaxrefl.posterior._diagnostics import log_likelihood_draws
from jaxrefl.posterior._emcee import autocorr_check

with warnings.catch_warnings():
    warnings.simplefilter("ignore", FutureWarning)
    import arviz as az


def _ar1(n_steps: int, phi: float, n_walkers: int = 16, d: int = 2, seed: int = 0):
    """(steps, walkers, D) AR(1) chains x_t = phi x_{t-1} + e_t: tau = (1 + phi) / (1 - phi)."""
    rng = np.random.default_rng(seed)
    x = np.zeros((n_steps, n_walkers, d))
    x[0] = rng.normal(size=(n_walkers, d)) / np.sqrt(1 - phi**2)  # stationary start
    e = rng.normal(size=(n_steps, n_walkers, d))
    for t in range(1, n_steps):
        x[t] = phi * x[t - 1] + e[t]
    return x


def test_stopping_rule_refuses_a_chain_shorter_than_50_tau():
    phi = 0.9  # tau = 19 steps
    tau_true = (1 + phi) / (1 - phi)
    short = _ar1(600, phi)  # about 32 tau
    tau, ok = autocorr_check(short)
    assert not ok
    v = jp.convergence(np.swapaxes(short, 0, 1), tau=tau, n_steps=600, labels=("a", "b"))
    assert not v.converged and "tau" in v.reasons[0] and "needs 50" in v.reasons[0]
    assert v.to_dict()["chain_length"] == 600
    long = _ar1(2400, phi)  # about 126 tau
    tau, ok = autocorr_check(long)
    assert ok
    np.testing.assert_allclose(tau, tau_true, rtol=0.3)
    # the same chain judged against a stricter rule is refused again
    assert not autocorr_check(long, n_tau=200.0)[1]
    v = jp.convergence(np.swapaxes(long, 0, 1)[:, ::10], tau=tau, n_steps=2400)
    assert v.converged and v.reasons == () and v.max_rhat < 1.01
    # R-hat and ESS are targets too: chains stuck apart are refused whatever their length
    apart = np.swapaxes(long, 0, 1)[:, ::10] + np.arange(16)[:, None, None]
    v = jp.convergence(apart, tau=tau, n_steps=2400, labels=("a", "b"))
    assert not v.converged and any("R-hat of" in r for r in v.reasons)
    with pytest.raises(ValueError, match="steps, walkers, D"):
        autocorr_check(long[:, 0])


def _gauss(theta):
    return -0.5 * jnp.sum((theta / 0.1) ** 2)


def test_sample_emcee_runs_until_converged_or_the_cap():
    o = jp.EmceeOptions(n_walkers=8, max_steps=20_000, check_every=250, seed=3)
    s = jp.sample_emcee(_gauss, np.zeros(1), (), o)
    assert s.emcee is not None
    c = s.emcee.convergence
    assert c.converged and s.emcee.tau_reliable and c.tau == s.emcee.tau
    n = s.emcee.n_steps
    assert n % 250 == 0 and 50 * max(s.emcee.tau) <= n < 20_000 and c.n_steps == n
    assert c.max_rhat <= 1.01 and c.min_ess_bulk >= 400
    np.testing.assert_allclose(np.std(s.theta[0]), 0.1, rtol=0.15)
    capped = jp.sample_emcee(_gauss, np.zeros(1), (), jp.EmceeOptions(8, max_steps=120, seed=3))
    assert capped.emcee is not None
    c = capped.emcee.convergence
    assert capped.emcee.n_steps == 120 and not c.converged and c.reasons
    # The seed is an option: the same options, the same draws; another seed, others.
    again = jp.sample_emcee(_gauss, np.zeros(1), (), jp.EmceeOptions(8, max_steps=120, seed=3))
    other = jp.sample_emcee(_gauss, np.zeros(1), (), jp.EmceeOptions(8, max_steps=120, seed=4))
    np.testing.assert_array_equal(again.theta, capped.theta)
    assert not np.array_equal(other.theta, capped.theta)
    for bad in (-1, 1.5):
        with pytest.raises(ValueError, match="seed must be an integer >= 0"):
            jp.EmceeOptions(seed=bad)
    with pytest.raises(ValueError, match="max_steps"):
        jp.EmceeOptions(max_steps=0)
    with pytest.raises(ValueError, match="max_rhat"):
        jp.EmceeOptions(max_rhat=0.9)


def _geometry(k: int, seed: int):
    rng = np.random.default_rng(seed)
    th_i, th_o = rng.uniform(0.05, 1.2, k), rng.uniform(0.05, 1.2, k)
    ph_o = rng.uniform(np.pi - 0.5, np.pi + 0.5, k)  # around the mirror direction
    wi = np.stack([np.sin(th_i), np.zeros(k), np.cos(th_i)], -1)
    wo = np.stack([np.sin(th_o) * np.cos(ph_o), np.sin(th_o) * np.sin(ph_o), np.cos(th_o)], -1)
    return wi, wo


def test_posterior_nc_ranks_ggx_above_lambert_by_loo(tmp_path):
    """Data from a glossy GGX material: the two posteriors written to NetCDF, read back,
    and ranked by PSIS-LOO; GGX's expected log predictive density is far higher. The files
    carry weights and censoring flags as constant data and name their coordinates."""
    truth = {"albedo": jnp.array([0.3, 0.2, 0.1]), "specular": jnp.full(3, 0.05), "alpha": 0.15}
    wi, wo = _geometry(40, 0)
    weight = np.ones((40, 3))
    weight[0] = 0.0  # one masked sample: constant_data must say so
    data = fit.pixel_data(np.zeros((40, 3)), wi, wo, weight=weight, dtype=np.float64)
    ggx = build_model("ggx")
    lp = jp.log_posterior(ggx, fit.ParamSpace(ggx, channels=3), fit.GaussianNoise(None))
    clean = np.asarray(lp.predict(lp.init_theta(lp.space.from_natural(truth, np.float64)), data))
    obs = clean + 0.01 * np.random.default_rng(1).normal(size=clean.shape)
    data = fit.pixel_data(obs, wi, wo, weight=weight, dtype=np.float64)
    paths = {}
    for name in ("ggx", "lambert"):
        m = build_model(name)
        sp = fit.ParamSpace(m, channels=3)
        lp = jp.log_posterior(m, sp, fit.GaussianNoise(None))
        start = {k: v for k, v in truth.items() if k in sp.free_names}
        th0 = lp.init_theta(sp.from_natural(start, np.float64), noise_scale=0.01)
        s = jp.sample_emcee(
            lp, th0, (data,), jp.EmceeOptions(20, 300), natural=lp.natural, labels=lp.labels
        )
        one = jax.tree.map(lambda a: a[None], data)
        ll = log_likelihood_draws(lp, s, one)
        assert ll.shape == (1, *s.theta.shape[1:3], 40, 3) and np.all(ll[..., 0, :] == 0)
        # the pointwise terms sum to the sampler's log-likelihood (plus the Gaussian constant)
        t = jnp.asarray(s.theta[0, 0, 0])
        n_used = 39 * 3
        expect = float(lp.log_likelihood(t, data)) - 0.5 * np.log(2 * np.pi) * n_used
        np.testing.assert_allclose(ll[0, 0, 0].sum(), expect, rtol=1e-10)
        idata = jp.to_inference_data(s, one, log_likelihood=ll, observation="sample")
        paths[name] = jp.save_netcdf(idata, tmp_path / f"{name}.nc")
    back = {name: az.from_netcdf(str(p)) for name, p in paths.items()}
    g = back["ggx"]
    assert {"posterior", "log_likelihood", "observed_data", "constant_data"} <= set(g.groups())
    assert list(g.constant_data["weight"].dims) == ["pixel", "sample", "channel"]
    assert list(g.constant_data["channel"].values) == ["R", "G", "B"]
    assert float(g.constant_data["weight"].sel(sample=0).sum()) == 0.0
    assert int(g.constant_data["censored"].sum()) == 0
    assert "weight" not in g.observed_data
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # short chains: ArviZ warns about Pareto k
        loo = az.loo(g)
        cmp = az.compare(back)
    assert np.isfinite(loo.elpd_loo)
    assert list(cmp.index) == ["ggx", "lambert"]
    assert cmp.loc["lambert", "elpd_diff"] > 5 * cmp.loc["lambert", "dse"]


def test_arviz_is_the_supported_major_version():
    # jaxrefl writes InferenceData through ArviZ 0.x's from_dict (pyproject pins arviz<1).
    assert int(az.__version__.split(".")[0]) == 0
    assert hasattr(az, "InferenceData") and hasattr(az, "from_dict")

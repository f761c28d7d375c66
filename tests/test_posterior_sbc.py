"""Simulation-based calibration of the batched HMC sampler, emcee and the Laplace
approximation (where flagged reliable) on GGX + Lambert pixels under a flash."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import fit, svbrdf
from jaxrefl import posterior as jp
from jaxrefl.posterior._priors import sample_truncated
from jaxrefl.posterior._sbc import thin

SIGMA = 0.01
K = 16
ALPHA_MIN = 0.05


def _flash_geometry(rng, n, k):
    """Co-located light and camera over a plane: wi = wo within 45 degrees of the normal."""
    th = np.arccos(rng.uniform(np.cos(np.radians(45)), 1.0, size=(n, k)))
    ph = rng.uniform(0, 2 * np.pi, size=(n, k))
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)


def _simulate(lp, rng, n, channels):
    """Truth from the (truncated) prior, observations with Gaussian noise SIGMA."""
    space = lp.space
    lo, hi = space.lower, space.upper
    cols = []
    for blk, prior in zip(space.blocks, lp.priors, strict=True):
        for j in range(blk.start, blk.stop):
            cols.append(sample_truncated(prior, rng, (n,), lo[j], hi[j]))
    nat = np.stack(cols, -1)
    names = [b.name for b in space.blocks]
    params = {nm: nat[:, b.start : b.stop] for nm, b in zip(names, space.blocks, strict=True)}
    params["alpha"] = params["alpha"][:, 0]
    theta = np.asarray(space.from_natural(params, dtype=jnp.float64))
    wi = _flash_geometry(rng, n, K)
    scale = np.repeat(wi[..., 2:3], channels, axis=-1) * 1.5
    d0 = fit.pixel_data(np.zeros((n, K, channels)), wi, None, scale=scale)
    pred = np.asarray(jax.jit(jax.vmap(lp.predict))(jnp.asarray(theta), d0))
    obs = pred + SIGMA * rng.normal(size=pred.shape)
    return theta, fit.pixel_data(obs, wi, None, scale=scale)


@pytest.fixture(scope="module")
def ggx1():
    """One-channel GGX + Lambert pixels (albedo, specular F0, alpha) simulated from the
    prior; shared by the three methods."""
    model, space = svbrdf.capture_model("ggx", channels=1, alpha_min=ALPHA_MIN)
    lp = jp.log_posterior(model, space, fit.GaussianNoise(SIGMA))
    rng = np.random.default_rng(11)
    theta, data = _simulate(lp, rng, 300, 1)
    return model, space, lp, theta, data


def test_sbc_batched_hmc(ggx1):
    """80 simulated pixels in one vmapped run: rank chi-square p > 0.001 and central
    50% / 90% coverage within 3.5 binomial standard errors for every parameter. The chains
    move in the non-centred albedo coordinates (the default), so this also calibrates them."""
    _, _, lp, theta, data = ggx1
    n = 80
    sub = jax.tree.map(lambda a: a[:n], data)
    opts = jp.HMCOptions(
        num_warmup=120, num_samples=80, num_chains=2, num_integration_steps=8, batch_size=40
    )
    s = jp.sample_pixels(lp, sub, jnp.asarray(theta[:n]), options=opts, seed=5)
    assert s.reparam == "albedo"
    draws = thin(s.theta, 19)
    res = jp.sbc_summary(theta[:n], draws, labels=lp.labels, bins=5)
    assert np.all(res.tests["chi2_p"] > 1e-3), res.to_dict()
    for lv in (0.5, 0.9):
        assert np.all(np.abs(res.coverage_z(lv)) < 3.5), (lv, res.to_dict())
    assert np.mean(s.stats["diverging"]) < 0.01


def test_sbc_laplace_where_reliable(ggx1):
    """The Laplace Gaussian in theta (flat prior) on pixels flagged reliable: PIT uniform
    and nominal coverage within 3.5 standard errors."""
    model, space, _lp, theta, data = ggx1
    r = fit.fit_pixels(
        model, data, config=fit.FitConfig(noise=fit.GaussianNoise(SIGMA)), space=space
    )
    res_fn = fit.make_residual(model, space, fit.GaussianNoise(SIGMA))
    lap = fit.laplace(r, data, residual=res_fn, options=fit.LaplaceOptions(noise="known"))
    ok = np.asarray(lap.reliable)
    assert ok.sum() >= 80, lap.flag_counts()
    res = jp.sbc_summary(
        theta[ok],
        mean=np.asarray(r.theta)[ok],
        std=np.asarray(lap.theta_std)[ok],
        labels=space.labels,
        bins=5,
    )
    assert np.all(res.tests["chi2_p"] > 1e-3), res.to_dict()
    for lv in (0.5, 0.9):
        assert np.all(np.abs(res.coverage_z(lv)) < 3.5), (lv, res.to_dict())


def test_sbc_emcee(ggx1):
    """emcee on 24 of the pixels: ranks uniform and coverage nominal (few simulations: a
    coarse check, 5 bins)."""
    _, _, lp, theta, data = ggx1
    n = 24
    draws = []
    for i in range(n):
        d = jax.tree.map(lambda a, i=i: a[i], data)
        s = jp.sample_emcee(lp, theta[i], (d,), jp.EmceeOptions(12, 400, seed=i))
        draws.append(thin(s.theta, 19)[0])
    res = jp.sbc_summary(theta[:n], np.stack(draws), labels=lp.labels, bins=5)
    assert np.all(res.tests["chi2_p"] > 1e-3), res.to_dict()
    for lv in (0.5, 0.9):
        assert np.all(np.abs(res.coverage_z(lv)) < 3.5), (lv, res.to_dict())

"""Population priors (:mod:`jaxrefl.svbrdf._population`): the empirical Bayes estimates
from the reliably fitted pixels, the fallbacks, and what they change on the pixels whose
lobe no photo saw."""

from __future__ import annotations

from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import fit, svbrdf
from jaxrefl import posterior as jp
from jaxrefl.cli._fit import print_summary
from jaxrefl.demo import demo_scene, photograph_maps
from jaxrefl.posterior._priors import resolve_priors
from jaxrefl.svbrdf import _check, _population
from jaxrefl.svbrdf._models import ALPHA_RANGE
from jaxrefl.svbrdf._uncertainty import (
    fit_theta,
    laplace_theta_std,
    map_posterior,
    posterior_space,
)

SIZE = 10
SIGMA = 0.004


@pytest.fixture(scope="module")
def grey_capture():
    """A co-located flash capture of grey-F0 dielectrics (F0 0-0.5, alpha 0.04-0.64),
    fitted with the coloured-F0 ``ggx_rgb``: (capture, fit, truth)."""
    scene = demo_scene(size=SIZE)
    rng = np.random.default_rng(8)
    f0 = rng.uniform(0.0, 0.5, (SIZE, SIZE))
    truth = {
        "albedo": rng.uniform(0.05, 0.8, (SIZE, SIZE, 3)),
        "specular": np.repeat(f0[..., None], 3, -1),
        "alpha": rng.uniform(0.2, 0.8, (SIZE, SIZE)) ** 2,
    }
    cap = photograph_maps(scene, truth, SIGMA, rng)
    # the light as stated: the light is not what this tests (tests/test_light*.py)
    # one tile of the capture's 100 pixels (the default 4096 rows would be mostly padding)
    config = fit.FitConfig(dtype=np.float64)
    job = svbrdf.FitJob(model="ggx_rgb", config=config, light="fixed", tile_pixels=SIZE * SIZE)
    return cap, svbrdf.fit_capture(cap, job), truth


def test_a_lobe_narrower_than_the_photos_resolve_is_flagged_at_the_floor(grey_capture, capsys):
    """The grey capture's alpha reaches 0.04, below its resolvable width (about 0.05): such
    pixels' widths pile against the floor, and the fit's ``misspecified`` map marks them
    ALPHA_AT_FLOOR (with AT_MODEL_BOUND); ``jaxrefl fit`` says how many."""
    _cap, cf, truth = grey_capture
    bits = cf.maps["misspecified"].reshape(-1)
    floor = (bits & svbrdf.ModelCheck.ALPHA_AT_FLOOR) != 0
    alpha_min = cf.report["alpha_min"]
    assert floor.any() and np.all(bits[floor] & svbrdf.ModelCheck.AT_MODEL_BOUND)
    assert cf.report["misspecified_counts"]["ALPHA_AT_FLOOR"] == int(floor.sum())
    fitted = cf.params()["alpha"].reshape(-1)
    assert np.all(fitted[floor] < alpha_min + _check.NEAR * (1.0 - alpha_min))
    # a sub-resolution truth is among them, and a width well inside the range never is
    below = truth["alpha"].reshape(-1) < alpha_min
    assert np.any(floor & below)
    assert not np.any(floor & (fitted > 2 * alpha_min))
    print_summary(cf.report)
    out = capsys.readouterr().out
    assert f"of them {int(floor.sum())} with alpha at its floor {alpha_min:.3f}" in out, out


def test_population_priors_of_a_grey_capture(grey_capture, monkeypatch):
    """The priors are the fitted pixels' moments, the pixels Laplace flags included (F0's
    covariance with the floor, in units of their median noise; alpha's log-normal), with
    fallbacks to the defaults. Then,
    on the pixels Laplace flags (mostly lobes no photo saw), the default uniform prior on
    a coloured F0 lets each channel wander over [0, 1]: the draws' spread of F0.R - F0.G is
    that of independent channels. The population prior of this grey capture keeps them
    together (spread at most a third) and its draws of F0 lie nearer the truth. The
    posterior is the map's (``map_posterior``): where the fit's alpha sits at the
    resolvable width, its draws reach below it, down to a narrower truth."""
    cap, cf, truth = grey_capture
    model, space = cf.model()
    priors, summary = svbrdf.population_priors(cf, space)
    flag = cf.maps["laplace_flag"].reshape(-1)
    noise = cf.maps["noise_std"].reshape(-1)
    ok = np.all(np.isfinite(cf.theta), -1) & np.isfinite(noise) & (noise > 0)
    assert summary["source"] == "population" and summary["pixels"] == int(ok.sum())
    # the flagged pixels are part of the population (a sample selected by identifiability
    # would be biased towards the lobes that are easy to see)
    assert 0 < ((flag != 0) & ok).sum() and ok.sum() >= _population.MIN_PIXELS
    x = np.asarray(space.natural_vector(jnp.asarray(cf.theta[ok])))
    f0 = x[:, space.index("specular")]
    spec = priors["specular"]
    assert isinstance(spec, jp.MultivariateNormal)
    np.testing.assert_allclose(spec.mean, f0.mean(0), rtol=1e-12)
    want = np.cov(f0.T) + _population.F0_FLOOR_STD**2 * np.eye(3)
    np.testing.assert_allclose(np.asarray(spec.cov), want, rtol=1e-10)
    assert spec.noise_ref == pytest.approx(float(np.median(noise[ok])))
    # the population is grey: its channels move together
    corr = want / np.sqrt(np.outer(np.diag(want), np.diag(want)))
    assert corr[0, 1] > 0.9 and corr[1, 2] > 0.9
    log_a = np.log(x[:, space.index("alpha")].reshape(-1))
    assert priors["alpha"].median == pytest.approx(float(np.exp(np.median(log_a))))
    assert priors["alpha"].log_std == pytest.approx(
        max(float(np.std(log_a)), _population.ALPHA_FLOOR_LOG_STD)
    )
    # fallbacks: too few fitted pixels, a model without a per-pixel lobe
    with monkeypatch.context() as mp:
        mp.setattr(_population, "MIN_PIXELS", 10_000)
        none, why = svbrdf.population_priors(cf)
        assert none == {} and why["source"] == "default" and "fewer than" in why["why"]
    none, why = svbrdf.population_priors(cf, svbrdf.capture_model("lambert")[1])
    assert none == {} and "no per-pixel lobe" in why["why"]
    with pytest.raises(ValueError, match="priors must be one of"):
        jp.AdaptiveOptions(priors="uniform")
    with pytest.raises(ValueError, match="priors must be one of"):
        jp.AdaptiveOptions(priors=0.5)  # type: ignore[arg-type]
    # what it changes on the flagged pixels (those with alpha at its floor among them),
    # sampled as uncertainty_maps samples them
    floor = (cf.maps["misspecified"].reshape(-1) & svbrdf.ModelCheck.ALPHA_AT_FLOOR) != 0
    rows = np.concatenate([np.flatnonzero(floor), np.flatnonzero((flag != 0) & ~floor)])[:16]
    block = svbrdf.pixel_block(cap, 0, SIZE * SIZE, dtype=np.float64)
    data = jax.tree.map(lambda a: a[rows], block)
    noise0 = np.nan_to_num(cf.maps["noise_std"].reshape(-1)[rows], nan=1e-2)
    lp_map, source = map_posterior(cf)
    assert source == summary
    want = resolve_priors(lp_map.space, priors)
    assert repr(lp_map.priors) == repr(tuple(want[b.name] for b in lp_map.space.blocks))
    post = lp_map.space
    std = np.concatenate([laplace_theta_std(cf, post)[rows], np.ones((rows.size, 1))], 1)
    theta = fit_theta(cf, post)[rows]
    opts = jp.HMCOptions(num_warmup=50, num_samples=200, num_chains=2)
    gibbs = jp.GibbsOptions(sweeps=1)
    spread, err, alpha = {}, {}, {}
    for name, chosen in (("default", {}), ("population", priors)):
        lp = jp.log_posterior(model, post, fit.GaussianNoise(None), priors=chosen)
        th0 = lp.init_theta(jnp.asarray(theta), noise_scale=np.maximum(noise0, 1e-3))
        s = jp.sample_pixels(lp, data, th0, theta_std=std, options=opts, gibbs=gibbs, seed=2)
        assert s.method == "gibbs_mh"
        r, g = (s.natural[..., lp.labels.index(f"specular.{c}")] for c in "RG")
        spread[name] = float(np.median(np.std(r - g, axis=(1, 2))))
        f0_true = truth["specular"][..., 0].reshape(-1)[rows]
        err[name] = float(np.median(np.abs(np.median(r, axis=(1, 2)) - f0_true)))
        alpha[name] = s.natural[..., lp.labels.index("alpha")]
    assert spread["population"] < spread["default"] / 3, spread
    assert err["population"] < err["default"], err
    # Below the resolvable width: the posterior's floor is the microfacet one, so the draws
    # of a floor pixel reach narrower lobes than the fit allowed, down to a truth there.
    alpha_min = cf.report["alpha_min"]
    q05 = np.quantile(alpha["population"], 0.05, axis=(1, 2))
    n_floor = int(floor.sum())
    assert n_floor and np.all(q05[:n_floor] < alpha_min), (q05[:n_floor], alpha_min)
    a_true = truth["alpha"].reshape(-1)[rows[:n_floor]]
    below = a_true < alpha_min
    assert below.any() and np.all(q05[:n_floor][below] <= a_true[below]), (q05, a_true)


def test_the_posterior_reaches_below_the_resolvable_width(grey_capture):
    """The map's posterior space is the fit's with alpha's floor at the microfacet models'
    1e-3 where the fit's was the capture's resolvable width; a floor the job gives is kept.
    The fit's optimum and Laplace std carry over through natural units."""
    _cap, cf, _truth = grey_capture
    own = cf.model()[1]
    _model, post = posterior_space(cf)
    j = own.labels.index("alpha")
    assert post.labels == own.labels and own.lower[j] == pytest.approx(cf.report["alpha_min"])
    assert post.lower[j] == ALPHA_RANGE[0] and post.upper[j] == own.upper[j]
    others = np.arange(own.size) != j
    np.testing.assert_array_equal(post.lower[others], own.lower[others])
    theta, theta_own = fit_theta(cf, post), fit_theta(cf)
    ok = np.all(np.isfinite(theta_own), -1)
    assert ok.any() and np.array_equal(np.all(np.isfinite(theta), -1), ok)
    np.testing.assert_array_equal(theta[:, others], theta_own[:, others])
    nat = np.asarray(post.natural_vector(jnp.asarray(theta[ok])))
    nat_own = np.asarray(own.natural_vector(jnp.asarray(theta_own[ok])))
    np.testing.assert_allclose(nat, nat_own, rtol=1e-9)
    std = laplace_theta_std(cf, post)[ok] * np.abs(post.dnatural(jnp.asarray(theta[ok])))
    std_map = cf.maps["alpha_std"].reshape(-1)[ok]
    np.testing.assert_allclose(std[:, j], std_map, rtol=1e-9)
    # the job's own floor is the user's: kept
    given = replace(cf, job=replace(cf.job, alpha_min=cf.report["alpha_min"]))
    assert posterior_space(given)[1].lower[j] == own.lower[j]
    # another model's space is refused
    with pytest.raises(ValueError, match="not the fit's"):
        fit_theta(cf, svbrdf.capture_model("lambert")[1])

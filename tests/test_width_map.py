"""Each pixel's own width around the pooled model's shared one (svbrdf._width_map): the
empirical-Bayes population, the per-pixel widths against a known truth, and the map it
relaxes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import fit
from jaxrefl import posterior as jp
from jaxrefl.demo import demo_scene, photograph_maps
from jaxrefl.io import read_exr
from jaxrefl.svbrdf import FitJob, fit_capture, uncertainty_maps, write_uncertainty
from jaxrefl.svbrdf._data import pixel_block
from jaxrefl.svbrdf._population import ALPHA_FLOOR_LOG_STD
from jaxrefl.svbrdf._uncertainty import fit_theta, map_posterior
from jaxrefl.svbrdf._width_map import (
    TAU_GRID,
    pixel_widths,
    population,
    population_bounds,
    relax_shared_width,
)

SIZE = 16


def _hierarchy(rng, n, c, tau):
    """Estimates l_i ~ N(log alpha_i, V_i), log alpha_i ~ N(c, tau^2) (module docstring)."""
    var = rng.uniform(0.05, 0.5, n) ** 2
    return c + tau * rng.standard_normal(n) + np.sqrt(var) * rng.standard_normal(n), var


@pytest.mark.parametrize(("c", "tau"), [(-1.5, 0.3), (-0.6, 0.15), (-2.0, 0.6)])
def test_population_recovers_the_centre_and_spread(c, tau):
    rng = np.random.default_rng(1)
    est, var = _hierarchy(rng, 4000, c, tau)
    # pixels that saw nothing of their lobe carry no information and change nothing
    est = np.concatenate([est, rng.uniform(-7, 0, 500)])
    var = np.concatenate([var, np.full(500, np.inf)])
    # a few fits at a wrong optimum, far out, must not set the spread
    est[:20] = c + 5.0
    c_hat, tau_hat = population(est, var)
    assert c_hat == pytest.approx(c, abs=0.03)
    assert tau_hat == pytest.approx(tau, rel=0.1)


def _shrunk_cover(est, var, theta, c, tau):
    """Share of the normal-normal 90% intervals (module docstring of _width_map) that cover
    the true log widths ``theta``."""
    prec = 1.0 / var + tau**-2
    m = (est / var + c / tau**2) / prec
    return np.mean(np.abs(m - theta) <= 1.645 / np.sqrt(prec))


@pytest.mark.parametrize("seed", [0, 1])
def test_population_bounds_hold_widths_whose_precision_follows_them(seed):
    # Narrow lobes seen sharply, wide ones hardly: V_i grows 200x across the widths. The
    # deconvolved population collapses onto the narrow ones and its intervals miss; the
    # map's bounds keep 90% intervals near 90%, and stay near it where V_i is independent.
    rng = np.random.default_rng(seed)
    theta = rng.uniform(-2.3, -0.5, 4000)
    var = 0.01 * np.exp(3.0 * (theta + 2.3))
    est = theta + np.sqrt(var) * rng.standard_normal(theta.size)
    c_eb, tau_eb = population(est, var)
    c, tau = population_bounds(est, var, c_eb)
    assert _shrunk_cover(est, var, theta, c_eb, tau_eb) < 0.7
    assert 0.85 < _shrunk_cover(est, var, theta, c, tau) < 0.95
    theta2 = rng.normal(-1.5, 0.3, 4000)
    var2 = rng.uniform(0.01, 0.2, 4000)
    est2 = theta2 + np.sqrt(var2) * rng.standard_normal(4000)
    c2, tau2 = population_bounds(est2, var2, -1.5)
    assert 0.85 < _shrunk_cover(est2, var2, theta2, c2, tau2) < 0.96
    # no informing pixel: the shared width at the floor
    assert population_bounds(np.zeros(3), np.full(3, np.inf), -1.0) == (-1.0, ALPHA_FLOOR_LOG_STD)


def test_population_of_one_width_is_narrow_and_of_nothing_is_undefined():
    rng = np.random.default_rng(2)
    est, var = _hierarchy(rng, 4000, -1.0, 0.0)
    _c, tau_hat = population(est, var)
    assert tau_hat < 0.03
    c_none, tau_none = population(np.zeros(10), np.full(10, np.inf))
    assert np.isnan(c_none) and tau_none == TAU_GRID[0]


def _capture(alpha_map, seed=5):
    scene = demo_scene(size=SIZE)
    rng = np.random.default_rng(seed)
    truth = {
        "albedo": rng.uniform(0.1, 0.4, (SIZE, SIZE, 3)),
        "specular": rng.uniform(0.3, 0.6, (SIZE, SIZE, 3)),
        "alpha": alpha_map,
    }
    return photograph_maps(scene, truth, 0.003, rng), truth


def _widths(cap):
    """(fit, Laplace posterior, width spread) of ``cap``, fitted as ``uncertainty_maps`` fits
    it: in one tile of the capture's pixels (so the ``varying`` fixture's programs serve)."""
    with jax.enable_x64(True):
        config = fit.FitConfig(dtype=np.float64)
        job = FitJob(model="pooled", light="fixed", config=config, tile_pixels=SIZE * SIZE)
        cf = fit_capture(cap, job)
        lp, _ = map_posterior(cf)
        data = pixel_block(cap, 0, SIZE * SIZE, dtype=np.float64)
        return cf, lp, pixel_widths(cf, lp, data, fit_theta(cf, lp.space), cap)


@pytest.fixture(scope="module")
def varying():
    """Widths spread by a factor of ~1.5 (log std 0.4) around 0.2, left half smoother: the
    truth and the capture's uncertainty map (pooled, the light as stated)."""
    rng = np.random.default_rng(4)
    alpha = 0.2 * np.exp(0.4 * rng.standard_normal((SIZE, SIZE)))
    alpha[:, : SIZE // 2] *= 0.6
    cap, truth = _capture(np.clip(alpha, 0.03, 0.9))
    with jax.enable_x64(True):
        job = FitJob(model="pooled", light="fixed", config=fit.FitConfig(dtype=np.float64))
        res = uncertainty_maps(cap, job)
    return truth, res


def test_each_pixel_gets_its_own_width_near_the_truth(varying):
    truth, res = varying
    sp = res.width_spread
    t = truth["alpha"].reshape(-1)
    ok = np.isfinite(sp.mean)
    assert ok.mean() > 0.95
    err = np.abs(np.log(sp.mean[ok] / t[ok]))
    shared = np.abs(np.log(sp.alpha / t[ok]))
    # the pixels' own widths are much closer to the truth than the one shared width
    assert np.median(err) < 0.5 * np.median(shared)
    assert np.corrcoef(np.log(sp.mean[ok]), np.log(t[ok]))[0, 1] > 0.8
    # the population's spread is the truth's (log std ~0.45 with the halves), not 0
    assert 0.25 < sp.tau < 0.8
    cover = np.mean((sp.q05[ok] <= t[ok]) & (t[ok] <= sp.q95[ok]))
    assert 0.75 < cover <= 1.0


def test_a_shared_width_stays_shared(varying):
    sp_varying = varying[1].width_spread
    cap, _truth = _capture(np.full((SIZE, SIZE), 0.2))
    _cf, _lp, sp = _widths(cap)
    # the population's spread is its floor (one material's), well below the varying one's
    assert sp.tau == pytest.approx(ALPHA_FLOOR_LOG_STD)
    assert sp_varying.tau > 1.5 * sp.tau
    ok = np.isfinite(sp.mean)
    assert np.mean((sp.q05[ok] <= 0.2) & (0.2 <= sp.q95[ok])) > 0.85
    assert np.median(np.abs(np.log(sp.mean[ok] / 0.2))) < 0.05


def test_relaxed_map_widens_inside_the_box_and_adds_the_width(varying):
    _truth, res = varying
    cf, lp, sp = res.fit, res.posterior, res.width_spread
    n, d = SIZE * SIZE, len(lp.labels)
    rng = np.random.default_rng(0)
    mean = np.asarray(lp.space.natural_vector(fit_theta(cf, lp.space)), np.float64)
    mean = np.concatenate([mean, np.full((n, d - mean.shape[1]), 0.01)], 1)
    std = np.abs(rng.normal(0.01, 0.003, (n, d)))
    umap = jp.UncertaintyMap(
        labels=lp.labels,
        mean=mean,
        std=std,
        q05=mean - 1.645 * std,
        q95=mean + 1.645 * std,
        method=np.zeros(n, np.uint8),
        rhat=np.full(n, np.nan),
        ess_bulk=np.full(n, np.nan),
        ess_tail=np.full(n, np.nan),
        divergences=np.zeros(n, np.int32),
        mcmc_pixels=np.zeros(0, np.int64),
        samples=None,
        laplace_std=std,
        rerun=np.zeros(n, bool),
        rhat_first=np.full(n, np.nan),
    )
    out = relax_shared_width(umap, sp, lp.space.lower, lp.space.upper)
    p = len(lp.space.labels)
    assert out.labels == (*lp.labels, "alpha")
    assert out.mean.shape == (n, d + 1)
    np.testing.assert_allclose(out.mean[:, -1], sp.mean)
    np.testing.assert_allclose(out.q95[:, -1], sp.q95)
    assert np.all(out.std[:, :p] >= std[:, :p] - 1e-15)
    # no wider than the uniform distribution over the box (unless the map was already)
    box_sd = (np.asarray(lp.space.upper) - np.asarray(lp.space.lower))[:p] / np.sqrt(12.0)
    assert np.all(out.std[:, :p] <= np.maximum(std[:, :p], box_sd) + 1e-15)
    lo, hi = np.asarray(lp.space.lower), np.asarray(lp.space.upper)
    assert np.all(out.q05[:, :p] >= lo - 1e-12) and np.all(out.q95[:, :p] <= hi + 1e-12)
    assert np.all(out.q05 <= out.q95)
    # albedo and F0 (finite down/up): the interval holds the conditional optimum's range
    # over the width's 90% range, about the moved mean
    ex = np.isfinite(sp.down) & (std[:, :p] > 0)
    assert ex.sum() > n
    lo_end = np.maximum(out.mean[:, :p] - sp.down, lo[:p])
    hi_end = np.minimum(out.mean[:, :p] + sp.up, hi[:p])
    assert np.all(out.q05[:, :p][ex] <= lo_end[ex] + 1e-12)
    assert np.all(out.q95[:, :p][ex] >= hi_end[ex] - 1e-12)
    # columns past the model's parameters (the noise scale) are left as they were
    np.testing.assert_array_equal(out.std[:, p:d], std[:, p:d])


def test_pooled_uncertainty_map_gives_each_pixel_its_width(varying, tmp_path):
    """Through uncertainty_maps and write_uncertainty: the widths are the map's last column,
    in uncertainty.exr and the report; the draws stay the pooled posterior's."""
    _truth, res = varying
    assert res.map.labels[-1] == "alpha"
    np.testing.assert_array_equal(res.map.q95[:, -1], res.width_spread.q95)
    assert "alpha" not in res.map.samples.labels
    rep = res.report()
    assert rep["width_spread"]["pixels_informing"] > 0
    assert rep["timings"]["width_s"] >= 0
    write_uncertainty(res, tmp_path)
    ch = read_exr(tmp_path / "uncertainty.exr").channels
    np.testing.assert_allclose(ch["alpha_q95.Y"].reshape(-1), res.map.q95[:, -1], rtol=1e-3)


def test_conditional_fit_is_the_exact_nonnegative_least_squares_at_each_width():
    """_conditional's albedo and F0 at each pixel's own width, with F0's prior as one more
    row, against scipy's NNLS on the same rows (the pooled model's basis images)."""
    from scipy.optimize import nnls

    from jaxrefl.svbrdf._pooled import _lobe_basis
    from jaxrefl.svbrdf._width_map import _conditional

    cap, _truth = _capture(np.full((SIZE, SIZE), 0.2))
    with jax.enable_x64(True):
        data = pixel_block(cap, 0, 6, dtype=np.float64)
        alpha = np.array([0.05, 0.1, 0.2, 0.3, 0.5, 0.8])
        prior_w, prior_mu = np.array([0.0, 0.5, 2.0]), np.array([0.1, 0.3, 0.05])
        got = np.asarray(_conditional(jnp.asarray(alpha), data, prior_w, prior_mu))
        lobe = np.asarray(_lobe_basis(jnp.asarray(alpha)[:, None], data))
    obs, scale = np.asarray(data.obs), np.asarray(data.scale)
    use = (np.asarray(data.weight) > 0) & (np.asarray(data.censored) == 0)
    for i in range(6):
        for ch in range(3):
            u = use[i, :, ch]
            a_mat = np.stack([scale[i, u, ch] / np.pi, lobe[i, u, ch]], 1)
            y = obs[i, u, ch]
            a_mat = np.vstack([a_mat, [0.0, prior_w[ch]]])
            y = np.append(y, prior_w[ch] * prior_mu[ch])
            want, _ = nnls(a_mat, y)
            np.testing.assert_allclose(got[i, [ch, 3 + ch]], want, rtol=1e-7, atol=1e-10)


def test_group_centres_follow_a_precision_that_follows_the_width():
    """Wide lobes seen hardly (V_i growing with alpha_i): the least precise group's centre
    sits near its own widths, not at the precise narrow lobes' median (module docstring)."""
    from jaxrefl.svbrdf._width_map import GROUPS, group_centres

    rng = np.random.default_rng(3)
    n = 2000
    log_a = np.log(0.2) + 0.5 * rng.standard_normal(n)
    var = (0.05 * np.exp(3.0 * (log_a - np.log(0.2)))) ** 2  # rougher: far less precise
    est = log_a + np.sqrt(var) * rng.standard_normal(n)
    est[:10], var[:10] = np.nan, np.inf  # no estimate: the global centre
    c = float(np.median(est[10:]))
    got = group_centres(est, var, c)
    assert np.all(got[:10] == c)
    worst = var >= np.quantile(var[10:], 1.0 - 1.0 / GROUPS)
    best = var <= np.quantile(var[10:], 1.0 / GROUPS)
    assert abs(np.median(got[worst]) - np.median(log_a[worst])) < 0.25
    assert np.median(got[worst]) > c + 0.4 > np.median(got[best]) + 0.8
    # too few informing pixels for two groups: the global centre everywhere
    assert np.all(group_centres(est[:40], var[:40], c) == c)

"""The uncertainty map under an estimated flash (``FitJob.light``): the posterior sees the
light the fit estimated, the report says which, ``jaxrefl sample --light`` asks for it, and
the light's own uncertainty widens every pixel's intervals (:mod:`jaxrefl.svbrdf._light_map`)."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxrefl import fit, svbrdf
from jaxrefl import posterior as jp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import capture_family as cf

SIZE = 10


@pytest.fixture(scope="module")
def offset_capture():
    m = next(x for x in cf.FAMILY if x.name == "grey_gloss")
    return cf.render_member(dataclasses.replace(m, size=SIZE, flash_offset_cm=1.0))


def test_map_is_sampled_under_the_fit_light(offset_capture):
    jax.config.update("jax_enable_x64", True)
    cap = offset_capture.capture()  # the files' light: at the lens
    job = svbrdf.FitJob(model="lambert", config=fit.FitConfig(dtype=np.float64), light="offset")
    res = svbrdf.uncertainty_maps(cap, job, jp.AdaptiveOptions(mcmc="none"))
    light = res.fit.light
    assert light is not None and light.mode == "offset"
    rep = res.report()
    assert rep["light"]["mode"] == "offset"
    assert rep["light"]["offset_cm"] == pytest.approx(list(light.offset_cm))
    # the estimate moved the flash away from the lens, towards its true place
    true_off = (offset_capture.light_pos - offset_capture.camera_pos)[0]
    assert np.linalg.norm(light.offset_cm[:2] - true_off[:2]) < 0.5 * np.linalg.norm(true_off)
    # the posterior's data are the estimated light's, not the stated light's
    want = svbrdf.pixel_block(light.apply(cap), 0, SIZE * SIZE, dtype=np.float64)
    stated = svbrdf.pixel_block(cap, 0, SIZE * SIZE, dtype=np.float64)
    np.testing.assert_array_equal(np.asarray(res.data.wi), np.asarray(want.wi))
    np.testing.assert_array_equal(np.asarray(res.data.scale), np.asarray(want.scale))
    assert np.max(np.abs(np.asarray(res.data.wi) - np.asarray(stated.wi))) > 1e-3
    # a fixed light leaves the data as the capture states it
    fixed = svbrdf.uncertainty_maps(
        cap, dataclasses.replace(job, light="fixed"), jp.AdaptiveOptions(mcmc="none")
    )
    assert fixed.report()["light"]["mode"] == "fixed"
    np.testing.assert_array_equal(np.asarray(fixed.data.wi), np.asarray(stated.wi))


def _opt(res_fn, t0, d):
    """Gauss-Newton on ``res_fn(theta, d)`` from ``t0`` (30 steps: converged for these
    near-linear problems)."""

    def step(u, _):
        r = res_fn(u, d)
        j = jax.jacfwd(res_fn)(u, d)
        return u - jax.numpy.linalg.solve(j.T @ j, j.T @ r), None

    return jax.lax.scan(step, t0, None, length=30)[0]


def test_light_uncertainty_widens_intervals_by_the_moves_of_each_optimum(offset_capture):
    """The light's Laplace spread enters every pixel's intervals (svbrdf._light_map): the
    first-order move of a pixel's optimum under a shifted flash matches the optimum found
    again under that flash, the map's std is the root sum of squares of the posterior's and
    the light's, and a fixed light adds nothing."""
    from jaxrefl.svbrdf import _light_map
    from jaxrefl.svbrdf._uncertainty import fit_theta

    jax.config.update("jax_enable_x64", True)
    cap = offset_capture.capture()
    job = svbrdf.FitJob(model="lambert", config=fit.FitConfig(dtype=np.float64), light="offset")
    res = svbrdf.uncertainty_maps(cap, job, jp.AdaptiveOptions(mcmc="none"))
    est = res.fit.light
    theta = fit_theta(res.fit, res.posterior.space)
    # a flash 1 mm further along x: the linearised move against the optimum found again
    off = est.offset_cm + np.array([0.1, 0.0, 0.0])
    moved = est.apply(cap, off, est.photo_gain)
    n = SIZE * SIZE
    data = svbrdf.pixel_block(moved, 0, n, dtype=np.float64)
    t = jax.numpy.asarray(theta)
    jac, w, chol = _light_map._gauss_newton(res.posterior.residual, t, res.data)
    lin = np.asarray(_light_map._moves(res.posterior.residual, t, res.data, data, jac, w, chol))
    # the exact move of the map's objective's optimum: Gauss-Newton to convergence under
    # each light (L2 on the map's whitened residual), from the fit's optimum
    res_fn = res.posterior.residual

    ok = np.all(np.isfinite(theta), -1)
    both = [jax.vmap(lambda t0_, d_: _opt(res_fn, t0_, d_))(t, d) for d in (res.data, data)]
    exact = np.asarray(both[1] - both[0])
    ok &= np.all(np.isfinite(exact), -1)  # Gauss-Newton fails where an albedo sits at 0
    assert ok.sum() > n // 2
    rel = np.abs(lin - exact)[ok] / np.maximum(np.abs(exact[ok]), 1e-12)
    assert np.median(rel) < 0.05 and np.quantile(rel, 0.9) < 0.25, np.quantile(rel, [0.5, 0.9])
    # the map's std: the posterior's (Laplace here) and the light's in quadrature
    assert res.light_std is not None and res.light_std.shape == (n, 3)
    base = res.map.laplace_std[:, :3]
    np.testing.assert_allclose(
        res.map.std[:, :3] ** 2, base**2 + res.light_std**2, rtol=1e-9, equal_nan=True
    )
    assert np.nanmedian(res.light_std) > 0
    summary = res.report()["light_std"]
    assert set(summary) == {"albedo.R", "albedo.G", "albedo.B"}
    assert all(v["widening_median"] >= 1.0 for v in summary.values())
    # the estimate's interval holds the quantiles' widening too
    width = res.map.q95[:, :3] - res.map.q05[:, :3]
    assert np.all(width[np.isfinite(width)] >= 0)
    # the offset's z is held at its prior, not estimated: a common scale the maps are
    # conditional on, so its prior variance alone moves nothing
    only_z = np.zeros_like(est.cov)
    only_z[2, 2] = est.cov[2, 2]
    held = dataclasses.replace(res.fit, light=dataclasses.replace(est, cov=only_z))
    var_z = _light_map.light_spread(held, res.posterior, res.data, cap, theta, n_draws=4)
    assert var_z is not None and np.nanmax(var_z) == 0.0
    # a fixed light: nothing to propagate
    assert (
        _light_map.light_spread(
            dataclasses.replace(res.fit, light=None), res.posterior, res.data, cap, theta
        )
        is None
    )

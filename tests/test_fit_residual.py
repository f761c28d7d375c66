"""The per-pixel problem (jaxrefl/fit/_residual.py): robust losses, censoring, defensive
masking of non-finite inputs (values and Jacobians), noise whitening and weights."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrefl
from jaxrefl import fit


def test_losses_match_rho_and_are_smooth_at_zero():
    z = jnp.linspace(-10.0, 10.0, 401)
    for loss in (fit.L2(), fit.Huber(1.5), fit.Cauchy(0.7)):
        r = loss.residual(z)
        np.testing.assert_allclose(0.5 * r * r, loss.rho(z), rtol=1e-12, atol=1e-15)
        np.testing.assert_array_equal(np.sign(r), np.sign(z))
        g0 = jax.grad(loss.residual)(0.0)
        assert np.isfinite(g0) and abs(float(g0) - 1.0) < 1e-12  # dr/dz = 1 at 0
        assert np.all(np.isfinite(jax.vmap(jax.grad(loss.residual))(z)))
    hub = fit.Huber(1.5)
    inside = jnp.abs(z) < 1.5
    np.testing.assert_allclose(hub.residual(z)[inside], z[inside], rtol=1e-12)
    # beyond delta the cost grows linearly: rho(z + 1) - rho(z) = delta
    big = jnp.asarray([3.0, 5.0, 8.0])
    np.testing.assert_allclose(hub.rho(big + 1.0) - hub.rho(big), 1.5, rtol=1e-12)
    cau = fit.Cauchy(0.7)
    # Cauchy: ~z^2/2 near 0, logarithmic growth far out
    np.testing.assert_allclose(cau.rho(jnp.asarray(1e-4)), 0.5e-8, rtol=1e-6)
    np.testing.assert_allclose(
        cau.rho(jnp.asarray(1e3 * np.e)) - cau.rho(jnp.asarray(1e3)), 0.49, rtol=1e-5
    )


def _lambert_pixel(obs, censored=None, weight=None, noise=None, loss=None):
    """One pixel, Lambert with albedo a: pred = a / pi * scale, scale = pi (pred = a)."""
    m = jaxrefl.brdf.get("lambert")
    space = fit.ParamSpace(m, channels=1)
    res = fit.make_residual(m, space, noise, loss)
    k = len(obs)
    d = fit.pixel_data(
        jnp.asarray(obs)[:, None],
        jnp.tile(jnp.asarray([0.0, 0.0, 1.0]), (k, 1)),
        scale=jnp.pi,
        weight=None if weight is None else jnp.asarray(weight)[:, None],
        censored=None if censored is None else jnp.asarray(censored)[:, None],
    )
    return res, space, d


def test_censoring_is_one_sided():
    # obs = 0.5 saturated (true >= 0.5), 0.2 dark-clipped (true <= 0.2), 0.3 plain
    res, space, d = _lambert_pixel(
        [0.5, 0.2, 0.3], censored=[1, -1, 0], noise=fit.GaussianNoise(0.1)
    )
    for a in (0.1, 0.25, 0.4, 0.6):
        r = res(space.from_natural({"albedo": jnp.asarray([a])}), d)
        sat = (a - 0.5) / 0.1 if a < 0.5 else 0.0
        dark = (a - 0.2) / 0.1 if a > 0.2 else 0.0
        np.testing.assert_allclose(r, [sat, dark, (a - 0.3) / 0.1], rtol=1e-9, atol=1e-12)


def test_nonfinite_observations_are_masked_gradient_safely():
    m = jaxrefl.brdf.get("cook_torrance", distribution="ggx", diffuse="lambert")
    space = fit.ParamSpace(m)
    res = fit.make_residual(m, space)
    rng = np.random.default_rng(1)
    wi = rng.normal(size=(8, 3))
    wi[:, 2] = np.abs(wi[:, 2]) + 0.3
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    obs = rng.uniform(0.1, 1.0, (8, 3))
    theta = space.from_natural(
        {"albedo": jnp.full(3, 0.4), "specular": jnp.full(3, 0.1), "alpha": 0.2}
    )
    clean = fit.pixel_data(jnp.asarray(obs), jnp.asarray(wi))
    bad_obs = obs.copy()
    bad_obs[2, 1] = np.nan
    bad_obs[5, 0] = np.inf
    bad_wi = wi.copy()
    bad_wi[6] = np.nan
    bad = fit.pixel_data(jnp.asarray(bad_obs), jnp.asarray(bad_wi), jnp.asarray(wi))
    # the same pixel with those observations zero-weighted by hand
    w = np.ones((8, 3))
    w[2, 1] = w[5, 0] = 0.0
    w[6] = 0.0
    manual = fit.pixel_data(
        jnp.asarray(obs), jnp.asarray(wi), jnp.asarray(wi), weight=jnp.asarray(w)
    )
    r_fn = jax.jit(lambda t, d: res(t, d))
    jf = jax.jit(lambda t, d: jax.jacfwd(res)(t, d))
    jr = jax.jit(lambda t, d: jax.jacrev(res)(t, d))
    r_bad, r_manual = r_fn(theta, bad), r_fn(theta, manual)
    assert np.all(np.isfinite(r_bad))
    np.testing.assert_allclose(r_bad, r_manual, rtol=1e-12)
    j_bad, j_rev = jf(theta, bad), jr(theta, bad)
    assert np.all(np.isfinite(j_bad)) and np.all(np.isfinite(j_rev))
    np.testing.assert_allclose(j_bad, jf(theta, manual), rtol=1e-12)
    assert int(res.n_usable(bad)) == 24 - 2 - 3
    assert bool(res.nonfinite_input(bad)) and not bool(res.nonfinite_input(clean))
    assert not bool(res.nonfinite_input(manual))
    # a NaN in an observation that is already weighted 0 is not a "non-finite input"
    nan_masked = fit.pixel_data(jnp.asarray(bad_obs), jnp.asarray(wi), weight=jnp.asarray(w))
    assert not bool(res.nonfinite_input(nan_masked))


def test_shot_noise_and_weights():
    obs = [0.5, 0.02, -0.01]
    noise = fit.ShotNoise(read=0.01, gain=0.2)
    res, space, d = _lambert_pixel(obs, weight=[4.0, 1.0, 1.0], noise=noise)
    a = 0.3
    r = res(space.from_natural({"albedo": jnp.asarray([a])}), d)
    var = 0.01**2 + 0.2 * np.maximum(obs, 0.0)  # observation-based, clamped at obs = 0
    expected = np.sqrt([4.0, 1.0, 1.0]) * (a - np.asarray(obs)) / np.sqrt(var)
    np.testing.assert_allclose(r, expected, rtol=1e-9)
    with pytest.raises(ValueError, match="read > 0"):
        fit.ShotNoise(read=0.0, gain=1.0)
    # Gaussian noise per channel
    g = fit.GaussianNoise(jnp.asarray([0.1, 0.2]))
    np.testing.assert_allclose(g.std(jnp.zeros((4, 2))), [[0.1, 0.2]] * 4)
    # robust loss on whitened residuals: Huber with delta 1 in units of sigma
    res_h, space_h, d_h = _lambert_pixel(
        [0.3, 0.9], noise=fit.GaussianNoise(0.1), loss=fit.Huber(1.0)
    )
    r_h = res_h(space_h.from_natural({"albedo": jnp.asarray([0.35])}), d_h)
    z = np.asarray([0.5, -5.5])
    np.testing.assert_allclose(r_h, [0.5, -np.sqrt(2 * 5.5 - 1)], rtol=1e-9)
    assert np.all(np.abs(r_h) <= np.abs(z))


def test_pixel_data_builder():
    obs = jnp.ones((5, 7, 3), jnp.float32)
    wi = jnp.tile(jnp.asarray([0.0, 0.6, 0.8], jnp.float32), (5, 7, 1))
    d = fit.pixel_data(obs, wi)
    assert d.colocated and d.wo.shape == (5, 7, 3)
    assert d.scale.shape == d.weight.shape == d.censored.shape == (5, 7, 3)
    assert d.censored.dtype == jnp.int8 and d.scale.dtype == jnp.float32
    d2 = fit.pixel_data(obs, wi, wi + 0.0, scale=jnp.full((7, 3), 2.0))
    assert not d2.colocated and float(d2.scale[4, 6, 2]) == 2.0
    assert d2.astype(jnp.float64).obs.dtype == jnp.float64
    with pytest.raises(ValueError, match="trailing axis of 3"):
        fit.pixel_data(obs, wi[..., :2])
    # co-located evaluation gives the same residual as passing wo explicitly
    m = jaxrefl.brdf.get("cook_torrance", diffuse="lambert")
    res = fit.make_residual(m, fit.ParamSpace(m))
    th = res.space.default_theta(jnp.float32)
    one = jax.tree.map(lambda x: x[0], d)
    one2 = jax.tree.map(lambda x: x[0], fit.pixel_data(obs, wi, wi + 0.0))
    r_fn = jax.jit(lambda t, d: res(t, d))
    np.testing.assert_allclose(r_fn(th, one), r_fn(th, one2), rtol=1e-6)


def test_pixel_data_refuses_bad_arguments_naming_them():
    obs = np.ones((4, 5, 3))
    wi = np.tile([0.0, 0.6, 0.8], (4, 5, 1))
    for kw, msg in (
        ({"scale": np.ones((4, 2, 3))}, r"scale has shape \(4, 2, 3\).*\(4, 5, 3\)"),
        ({"weight": np.ones((3, 5, 3))}, r"weight has shape \(3, 5, 3\)"),
        ({"censored": np.zeros((1, 4, 5, 3))}, r"censored has shape .*more axes"),
        ({"scale": np.full((4, 5, 3), np.nan)}, r"scale holds a non-finite"),
        ({"wo": np.tile([0.0, 0.3, 0.4], (4, 5, 1))}, r"wo must be unit.*length 0\.5"),
        ({"wi": 1e-3 * wi}, r"wi must be unit.*length 0\.001"),
        ({"wo": np.ones((4, 2, 3))}, r"wo has shape \(4, 2, 3\)"),
    ):
        args = {"wi": wi, **kw}
        with pytest.raises(ValueError, match=msg):
            fit.pixel_data(obs, **args)
    # A non-unit direction of an observation at weight 0 is not used: accepted.
    w = np.ones((4, 5, 3))
    w[1, 2] = 0.0
    bad = wi.copy()
    bad[1, 2] *= 0.5
    fit.pixel_data(obs, bad, weight=w)


def test_fixed_values_must_be_finite():
    m = jaxrefl.brdf.get("cook_torrance", diffuse="lambert")
    for v in (np.nan, np.inf, [0.1, np.nan, 0.2]):
        name = "alpha" if np.ndim(v) == 0 else "albedo"
        with pytest.raises(ValueError, match=rf"fixed\['{name}'\].*not finite"):
            fit.ParamSpace(m, fixed={name: v})
    data = fit.pixel_data(np.ones((2, 3, 3)), np.tile([0.0, 0.0, 1.0], (2, 3, 1)))
    with pytest.raises(ValueError, match=r"fixed\['alpha'\]"):
        fit.fit_pixels(m, data, fixed={"alpha": np.nan})

"""Light direction from shading: a Lambertian sphere with known normals and albedo."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import brdf, fit
from jaxrefl import posterior as jp
from jaxrefl.posterior._sphere import angle_deg, lit_geometry

K = 8
SIGMA = 0.01
ALBEDO = 0.6
E = 3.0
PRIOR = jp.VonMisesFisher((0.0, 0.0, 1.0), 2.0)


def _normals(rng, n, coplanar=False):
    """K unit normals on the upper half of a sphere (or all in the x-z plane)."""
    th = np.radians(rng.uniform(0, 60, size=(n, K)))
    ph = rng.uniform(0, 2 * np.pi, size=(n, K))
    if coplanar:
        ph = np.where(rng.uniform(size=(n, K)) < 0.5, 0.0, np.pi)
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)


@pytest.fixture(scope="module")
def sphere():
    m = brdf.get("lambert")
    space = fit.ParamSpace(m, channels=1, fixed={"albedo": ALBEDO})
    lp = jp.log_posterior(m, space, fit.GaussianNoise(SIGMA), light=jp.SphereDirection(PRIOR))
    return lp


def _data(lp, normals, light, rng, weight=None):
    n = normals.shape[0]
    cos = np.maximum(np.sum(normals * light[:, None, :], -1), 0.0)
    obs = ALBEDO / np.pi * cos * E + SIGMA * rng.normal(size=cos.shape)
    wo = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (n, K, 3))
    return fit.pixel_data(obs[..., None], wo, wo, scale=np.full((n, K, 1), E), weight=weight)


@pytest.fixture(scope="module")
def runs(sphere):
    """One batched run: 60 identifiable scenes (8 normals), then one with 2 usable points
    (the others weight 0) and one with co-planar normals; 4 chains each."""
    rng = np.random.default_rng(21)
    n = 60
    light = PRIOR.sample(rng, (n,))  # the truth drawn from the prior: calibrated coverage
    normals = _normals(rng, n)
    # the two unidentifiable scenes, light out of the normals' plane
    l_bad = np.array([[0.3, 0.4, 0.866], [0.3, 0.4, 0.866]])
    l_bad /= np.linalg.norm(l_bad, axis=-1, keepdims=True)
    nb = np.concatenate([_normals(rng, 1), _normals(rng, 1, coplanar=True)])
    w = np.ones((n + 2, K, 1))
    w[n, 2:] = 0.0  # only two points seen
    all_l = np.concatenate([light, l_bad])
    all_n = np.concatenate([normals, nb])
    data = _data(sphere, all_n, all_l, rng, weight=w)
    # Chains start from directions spread over the sphere, so that separate modes show up.
    starts = rng.normal(size=(n + 2, 4, 3))
    theta0 = jnp.asarray(np.sqrt(2) * starts / np.linalg.norm(starts, axis=-1, keepdims=True))
    opts = jp.HMCOptions(num_warmup=120, num_samples=120, num_chains=4, num_integration_steps=8)
    s = jp.sample_pixels(sphere, data, theta0, normals=jnp.asarray(all_n), options=opts, seed=2)
    return all_l, all_n, w, s


def test_light_direction_contains_truth_at_nominal_rate(runs):
    """Truth drawn from the vMF prior; the angular credible region about the posterior mean
    direction holds it at the nominal 50% / 90% rate (within 3.5 binomial std errors);
    most scenes (those with the light above enough points) are identified."""
    light, normals, w, s = runs
    n = 60
    inside = {0.5: [], 0.9: []}
    ident = 0
    for i in range(n):
        x = s.flat(i)
        summ = jp.direction_summary(x, PRIOR, geometry=lit_geometry(normals[i], w[i]))
        ang = angle_deg(x, np.asarray(summ["mean"])[None])
        a_true = angle_deg(light[i], np.asarray(summ["mean"]))
        for lv in inside:
            inside[lv].append(a_true <= np.quantile(ang, lv))
        ident += summ["identified"]
    assert ident >= 0.7 * n, ident
    for lv, v in inside.items():
        q = np.mean(v)
        se = np.sqrt(lv * (1 - lv) / n)
        assert abs(q - lv) < 3.5 * se, (lv, q)


def test_light_direction_not_identified_with_few_or_coplanar_points(runs):
    from jaxrefl.posterior._diagnostics import split_rhat

    """Two points or co-planar normals: the geometry check says not identifiable, and the
    posterior itself is visibly wide (a 90% radius beyond 15 degrees) or split between
    chains (R-hat > 1.05: the mirrored modes)."""
    _light, normals, w, s = runs
    for i, why in ((60, "two points"), (61, "co-planar normals")):
        x = s.natural[i]
        rhat = float(np.max(split_rhat(x)))
        geo = lit_geometry(normals[i], w[i])
        assert not geo["identifiable"], (why, geo)
        summ = jp.direction_summary(x, PRIOR, rhat=rhat)  # the posterior alone
        assert not summ["identified"], (why, summ)
        assert summ["radius_deg"] > 15.0 or rhat > 1.05, (why, summ)
        full = jp.direction_summary(x, PRIOR, rhat=rhat, geometry=geo)
        assert "non-coplanar normals are needed" in full["reason"], full
    i_good = next(i for i in range(60) if lit_geometry(normals[i], w[i])["identifiable"])
    x = s.natural[i_good]
    good = jp.direction_summary(x, PRIOR, rhat=float(np.max(split_rhat(x))))
    assert good["identified"], good


def test_shared_light_counts_the_light_prior_once(sphere):
    """N pixels sharing one light: the joint log density is the sum of the pixels' log
    densities with the light's prior counted once."""
    m = brdf.get("lambert")
    space = fit.ParamSpace(m, channels=1)
    pix = jp.log_posterior(m, space, fit.GaussianNoise(SIGMA), light=jp.SphereDirection(PRIOR))
    shared = jp.SharedLight(pix, 3)
    rng = np.random.default_rng(3)
    normals = _normals(rng, 3)
    light = np.array([[0.3, 0.2, 0.93]] * 3) / np.linalg.norm([0.3, 0.2, 0.93])
    data = _data(sphere, normals, light, rng)
    u = np.sqrt(2) * light[0]
    alb = np.asarray(space.from_natural({"albedo": np.array([[0.3], [0.5], [0.7]])}))
    theta = jnp.asarray(np.concatenate([u, alb.reshape(-1)]))
    nrm = jnp.asarray(normals)
    joint = float(jax.jit(lambda t: shared(t, data, nrm))(theta))
    full = shared.expand(theta)
    each = jax.jit(jax.vmap(lambda t, d, n: pix(t, d, n)))(full, data, nrm)
    prior_u = float(pix.light.log_density(jnp.asarray(u)))
    assert joint == pytest.approx(float(np.sum(each)) - 2 * prior_u, rel=1e-12)

"""The conditional non-centring of the diffuse albedo (jaxrefl.posterior._reparam): an exact
change of variables (round trip, log-Jacobian, density, prediction), a known answer at a
bound, and the mixing it buys on the ridge of a pixel without an observed highlight."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxrefl import brdf, fit, svbrdf
from jaxrefl import posterior as jp
from jaxrefl.posterior._fastdiag import rhat_rank
from jaxrefl.posterior._reparam import ConditionalAlbedo, conditional_albedo


def _hemi(rng, n, min_z=0.3):
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + min_z
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _ggx_pixel(rng, k=12, censor=True):
    model, space = svbrdf.capture_model("ggx", channels=3, alpha_min=0.05)
    lp = jp.log_posterior(model, space, fit.GaussianNoise(None))
    wi, wo = _hemi(rng, k), _hemi(rng, k)
    truth = space.from_natural(
        {"albedo": np.array([0.3, 0.5, 0.1]), "specular": np.array([0.05]), "alpha": 0.3}
    )
    d0 = fit.pixel_data(np.zeros((k, 3)), wi, wo, scale=np.full((k, 3), 2.0))
    y = np.asarray(lp.predict(jnp.r_[truth, 0.0], d0)) + 0.01 * rng.normal(size=(k, 3))
    cens = np.zeros((k, 3), np.int8)
    if censor:
        cens[0, 1], cens[1, 2] = 1, -1  # one saturated, one dark-clipped observation
    d = fit.pixel_data(y, wi, wo, scale=np.full((k, 3), 2.0), censored=cens)
    return lp, d, jnp.r_[truth, np.log(0.01)]


def test_change_of_variables_is_exact():
    """T(T^-1(theta)) = theta; log|dT/dtheta'| is the log-determinant of T's Jacobian; the
    prediction from the affine pieces is the model's; the density is p(T(theta')) |T'|."""
    lp, d, theta = _ggx_pixel(np.random.default_rng(0))
    rp = conditional_albedo(lp)

    @jax.jit
    def check(t):
        tp = rp.from_theta(t, d)
        back, log_det, pred = rp.to_theta(tp, d)
        jac = jax.jacfwd(lambda x: rp.to_theta(x, d)[0])(tp)
        return back, log_det, pred, jac, rp(tp, d), lp(t, d), jax.grad(rp)(tp, d), lp.predict(t, d)

    for t in (theta, theta + jnp.asarray([0.3, -0.2, 0.5, -1.0, 0.7, 0.4])):
        back, log_det, pred, jac, lp_p, lp_t, grad, pred_t = check(t)
        np.testing.assert_allclose(back, t, atol=1e-12)
        assert float(log_det) == pytest.approx(np.linalg.slogdet(np.asarray(jac))[1], abs=1e-10)
        np.testing.assert_allclose(pred, pred_t, atol=1e-13)
        assert float(lp_p) == pytest.approx(float(lp_t + log_det), abs=1e-9)
        assert np.all(np.isfinite(np.asarray(grad)))
    # Only the albedo entries move, and they move with the rest: the ridge is followed.
    tp = rp.from_theta(theta, d)
    moved = rp.to_theta(tp.at[3].add(1.0), d)[0]
    assert np.all(np.asarray(moved[:3]) != np.asarray(theta[:3]))
    np.testing.assert_array_equal(moved[4:], theta[4:])


def test_light_direction_path_and_what_does_not_apply():
    """With a sampled light the affine pieces come from the world-frame prediction; models
    without a bounded albedo are refused with a reason, and "auto" then falls back."""
    rng = np.random.default_rng(1)
    m = brdf.get("lambert")
    space = fit.ParamSpace(m)
    lp = jp.log_posterior(m, space, fit.GaussianNoise(0.01), light=jp.SphereDirection())
    k = 8
    normals = _hemi(rng, k, min_z=1.0)
    wo = np.tile([0.0, 0.0, 1.0], (k, 1))
    d = fit.pixel_data(np.full((k, 3), 0.2), wo, wo, scale=np.ones((k, 3)))
    rp = conditional_albedo(lp)
    theta = lp.init_theta(jnp.asarray([0.1, -0.3, 0.2]), light=jnp.asarray([0.2, 0.1, 0.97]))
    tp = rp.from_theta(theta, d, normals)
    back, _, pred = rp.to_theta(tp, d, normals)
    np.testing.assert_allclose(back, theta, atol=1e-12)
    np.testing.assert_allclose(pred, lp.predict(theta, d, normals), atol=1e-13)

    unbounded = fit.ParamSpace(m, transforms={"albedo": fit.Identity()})
    lp_u = jp.log_posterior(m, unbounded, fit.GaussianNoise(0.01))
    with pytest.raises(ValueError, match="bounded"):
        conditional_albedo(lp_u)
    phong = brdf.get("phong")
    fixed = fit.ParamSpace(phong, fixed={"albedo": 0.3})
    lp_none = jp.log_posterior(phong, fixed, fit.GaussianNoise(0.01))
    with pytest.raises(ValueError, match="no free parameter"):
        conditional_albedo(lp_none)
    with pytest.raises(ValueError, match="reparam"):
        jp.HMCOptions(reparam="both")


def test_known_answer_against_the_bound():
    """Lambert, unknown noise scale s (Jeffreys), uniform albedo: given s each channel is a
    normal truncated to [0, 1], and p(s | y) is a 1-D integral (on a grid here), so the
    posterior moments are exact. The conditional sd w is proportional to s, so the
    log-Jacobian varies along the chain: a wrong one would bias the moments. Channels whose
    least-squares value lies below 0 (the soft clamp's region), near 0 and inside."""
    rng = np.random.default_rng(2)
    m = brdf.get("lambert")
    sigma, k = 0.02, 6
    lp = jp.log_posterior(m, fit.ParamSpace(m), fit.GaussianNoise(None))
    wi = _hemi(rng, k, min_z=0.8)
    scale = 3.0 * np.repeat(wi[:, 2:3], 3, axis=1)  # irradiance with the cosine
    a = scale / np.pi  # pred = f_r * scale = a * albedo
    y = a * np.array([-0.05, 0.03, 0.4]) + sigma * rng.normal(size=(k, 3))
    d = fit.pixel_data(y, wi, wi, scale=scale)
    data = jax.tree.map(lambda v: jnp.asarray(v)[None], d)
    opts = jp.HMCOptions(num_warmup=300, num_samples=2000, num_chains=2, reparam="albedo")
    theta0 = lp.init_theta(
        fit.ParamSpace(m).from_natural({"albedo": np.array([0.05, 0.05, 0.4])}),
        noise_scale=sigma,
    )
    s = jp.sample_pixels(lp, data, theta0[None], options=opts, seed=4)
    assert s.reparam == "albedo"
    x = s.flat(0)  # albedo R, G, B, noise_scale

    saa = np.sum(a * a, 0)
    mu = np.sum(a * y, 0) / saa
    ssr = float(np.sum((y - a * mu) ** 2))
    n = y.size
    grid = np.exp(np.linspace(np.log(sigma / 20), np.log(sigma * 20), 4001))
    sd = grid[:, None] / np.sqrt(saa)
    lo, hi = (0 - mu) / sd, (1 - mu) / sd
    mass = stats.norm.cdf(hi) - stats.norm.cdf(lo)
    log_mass = np.sum(np.log(sd * np.maximum(mass, 1e-300)), -1)
    log_w = -(n + 1) * np.log(grid) - ssr / (2 * grid**2) + log_mass
    w = np.exp(log_w - log_w.max()) * grid  # d(log s) grid: weights times s
    w /= w.sum()
    tn = stats.truncnorm(lo, hi, loc=mu, scale=sd)
    mean = np.r_[w @ tn.mean(), w @ grid]
    second = np.r_[w @ (tn.var() + tn.mean() ** 2), w @ grid**2]
    std = np.sqrt(second - mean**2)
    assert mu[0] < 0 < mu[1]  # the first channel's conditional mean is clamped
    ess = 800.0  # conservative for 4000 draws of a 4-D near-Gaussian
    np.testing.assert_array_less(np.abs(x.mean(0) - mean), 4 * std / ess**0.5)
    np.testing.assert_allclose(x.std(0), std, rtol=0.12)
    # In theta' the red channel (piled against 0) has a tail that falls like -exp(2 w theta')
    # (the Gaussian tail of rho = exp(u) above the bound) and log s one like -exp(-2 log s):
    # a leapfrog step sized for the bulk that lands far out there can diverge. The moments
    # above are what must hold; a divergence is allowed in 1,000 draws (seeds and code
    # generations give 0 or 1 in these 4,000), no more.
    assert np.mean(s.stats["diverging"]) <= 1e-3, int(np.sum(s.stats["diverging"]))


def test_the_ridge_of_an_unseen_highlight_mixes_only_non_centred():
    """Co-located flash views of a glossy pixel far from its highlight: specular and
    alpha trade against the albedo along a curved ridge. Under UNCERTAINTY_MAP_HMC the fit's
    coordinates do not mix (median max R-hat > 1.15); the non-centred ones do (< 1.08).
    UNCERTAINTY_MAP_GIBBS takes the width sampler here (its joint move draws alpha from its
    marginal, across the ridge): median max R-hat < 1.05."""
    rng = np.random.default_rng(3)
    model, space = svbrdf.capture_model("ggx", channels=3, alpha_min=0.05)
    lp = jp.log_posterior(model, space, fit.GaussianNoise(None))
    n, k = 24, 9
    # Views 35-55 degrees off the normal, the flash at the camera: h is far from n, so a
    # lobe of alpha <= 0.5 is hardly seen and looks like diffuse light.
    ang = np.deg2rad(rng.uniform(35, 55, size=(n, k)))
    phi = rng.uniform(0, 2 * np.pi, size=(n, k))
    w = np.stack([np.sin(ang) * np.cos(phi), np.sin(ang) * np.sin(phi), np.cos(ang)], -1)
    truth = space.from_natural(
        {
            "albedo": rng.uniform(0.2, 0.6, (n, 3)),
            "specular": np.full((n, 1), 0.04),
            "alpha": np.full(n, 0.4),
        }
    )
    scale = np.full((n, k, 3), 2.0)
    d0 = fit.pixel_data(np.zeros((n, k, 3)), w, None, scale=scale)
    pred = jax.vmap(lambda t, dd: lp.predict(jnp.r_[t, 0.0], dd))(truth, d0)
    y = np.asarray(pred) * (1 + 0.005 * rng.normal(size=(n, k, 3)))
    data = fit.pixel_data(y, w, None, scale=scale)
    x0 = lp.init_theta(truth, noise_scale=0.01)
    med = {}
    for mode in ("none", "albedo", "width"):
        width = mode == "width"
        opts = jp.UNCERTAINTY_MAP_HMC
        opts = opts if width else dataclasses.replace(opts, reparam=mode)
        gibbs = jp.UNCERTAINTY_MAP_GIBBS if width else None
        s = jp.sample_pixels(lp, data, x0, options=opts, gibbs=gibbs, seed=5)
        assert s.method == ("gibbs_mh" if mode == "width" else "hmc")
        th = np.moveaxis(s.theta, -1, 1).reshape(-1, *s.theta.shape[1:3])
        med[mode] = float(np.median(rhat_rank(th).reshape(n, -1).max(1)))
    assert med["none"] > 1.15 and med["albedo"] < 1.08 and med["width"] < 1.05, med


def test_conditional_albedo_is_a_module_of_the_posterior():
    lp, d, _ = _ggx_pixel(np.random.default_rng(4), censor=False)
    rp = conditional_albedo(lp).for_data(d)
    assert isinstance(rp, ConditionalAlbedo) and not rp.base.censoring
    assert rp.size == lp.size and rp.labels == lp.labels

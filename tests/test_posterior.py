"""Log-posterior, priors, sphere parameterisation; the linear-Gaussian known answer; the
power of the SBC statistics against a 20% over/under-dispersed posterior."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import brdf, fit
from jaxrefl import posterior as jp
from jaxrefl.posterior._priors import sample_truncated
from jaxrefl.posterior._sbc import sbc_summary
from jaxrefl.scene import orthonormal_basis

SIGMA = 0.02


def _hemi(rng, n, min_z=0.3):
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + min_z
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@pytest.fixture(scope="module")
def linear():
    """Cook–Torrance + Lambert with alpha fixed and identity bijections: the prediction is
    affine in (albedo RGB, specular), so with normal priors the posterior is exactly
    Gaussian: Sigma = (A^T A / s^2 + S0^-1)^-1, mu = Sigma (A^T (y - b) / s^2 + S0^-1 m0)."""
    m = brdf.get("cook_torrance", distribution="ggx", diffuse="lambert")
    space = fit.ParamSpace(
        m,
        grey=("specular",),
        fixed={"alpha": 0.2},
        transforms={"albedo": fit.Identity(), "specular": fit.Identity()},
    )
    priors = {"albedo": jp.Normal(0.5, 0.2), "specular": jp.Normal(0.1, 0.1)}
    lp = jp.log_posterior(m, space, fit.GaussianNoise(SIGMA), priors=priors)
    rng = np.random.default_rng(0)
    k = 16
    wi, wo = _hemi(rng, k), _hemi(rng, k)
    scale = np.repeat(wi[:, 2:3], 3, axis=1)

    d0 = fit.pixel_data(np.zeros((k, 3)), wi, wo, scale=scale)
    predict = jax.jit(lambda t: lp.predict(t, d0).reshape(-1))

    def pred(t):
        return np.asarray(predict(jnp.asarray(t, jnp.float64)))

    b = pred(np.zeros(4))
    a = np.stack([pred(np.eye(4)[i]) - b for i in range(4)], axis=1)
    m0 = np.array([0.5, 0.5, 0.5, 0.1])
    s0 = np.diag([0.2, 0.2, 0.2, 0.1]) ** 2
    post_prec = a.T @ a / SIGMA**2 + np.linalg.inv(s0)
    cov = np.linalg.inv(post_prec)
    return dict(lp=lp, wi=wi, wo=wo, scale=scale, a=a, b=b, m0=m0, s0=s0, cov=cov, pred=pred)


def _exact_mean(lin, y):
    prior_term = np.linalg.solve(lin["s0"], lin["m0"])
    return lin["cov"] @ (lin["a"].T @ (y - lin["b"]) / SIGMA**2 + prior_term)


def test_linear_model_is_affine(linear):
    t = np.array([0.3, 0.2, 0.7, 0.4])
    np.testing.assert_allclose(linear["pred"](t), linear["b"] + linear["a"] @ t, atol=1e-12)


def test_log_density_matches_exact_gaussian(linear):
    """Differences of log p at two points equal those of the exact Gaussian posterior."""
    rng = np.random.default_rng(1)
    truth = np.array([0.4, 0.6, 0.3, 0.15])
    y = linear["b"] + linear["a"] @ truth + SIGMA * rng.normal(size=linear["b"].size)
    d = fit.pixel_data(y.reshape(-1, 3), linear["wi"], linear["wo"], scale=linear["scale"])
    mu = _exact_mean(linear, y)
    prec = np.linalg.inv(linear["cov"])
    f = jax.jit(lambda t, d: linear["lp"](t, d))
    for t in (mu + 0.01, mu - np.array([0.02, 0.0, 0.01, 0.005])):
        lhs = float(f(jnp.asarray(t), d) - f(jnp.asarray(mu), d))
        rhs = -0.5 * (t - mu) @ prec @ (t - mu)
        assert lhs == pytest.approx(rhs, rel=1e-8, abs=1e-9)


def _noisy_pixels(lin, truths, rng):
    """(observations (N, M), PixelData) of N pixels of the linear model at ``truths`` (N, 4)
    with noise SIGMA, all seen from the fixture's 16 directions."""
    n = len(truths)
    ys = truths @ lin["a"].T + lin["b"] + SIGMA * rng.normal(size=(n, lin["b"].size))
    data = fit.pixel_data(
        ys.reshape(n, -1, 3),
        np.broadcast_to(lin["wi"], (n, 16, 3)),
        np.broadcast_to(lin["wo"], (n, 16, 3)),
        scale=np.broadcast_to(lin["scale"], (n, 16, 3)),
    )
    return ys, data


def test_known_answer_mean_and_covariance(linear):
    """Batched HMC on 4 pixels of the linear-Gaussian model: mean within 4 MC standard
    errors, covariance within 25% per pixel and 12% averaged over the 3 pixels (entrywise,
    relative to the diagonal scale; the MC error of a variance is ~ sqrt(2 / ESS) ~ 5%)."""
    rng = np.random.default_rng(2)
    truths = np.array([[0.4, 0.6, 0.3, 0.15], [0.2, 0.2, 0.9, 0.05], [0.7, 0.5, 0.5, 0.2]])
    ys, data = _noisy_pixels(linear, truths, rng)
    n = len(ys)
    opts = jp.HMCOptions(num_warmup=200, num_samples=1000, num_chains=2)
    s = jp.sample_pixels(linear["lp"], data, jnp.asarray(truths), options=opts, seed=3)
    cov = linear["cov"]
    sd = np.sqrt(np.diag(cov))
    errs = []
    for i in range(n):
        x = s.flat(i)
        mu = _exact_mean(linear, ys[i])
        ess = 400.0  # conservative: HMC on a 4-D Gaussian gives ESS ~ draws (1000 here)
        assert np.all(np.abs(x.mean(0) - mu) < 4 * sd / math.sqrt(ess)), (x.mean(0), mu)
        err = (np.cov(x.T) - cov) / np.outer(sd, sd)
        assert np.max(np.abs(err)) < 0.25, err
        errs.append(err)
    assert np.max(np.abs(np.mean(errs, axis=0))) < 0.12, np.mean(errs, axis=0)
    assert not np.any(s.stats["diverging"])


def test_float32_chains_agree_with_float64_and_the_exact_answer(linear):
    """Chains on float32 data under ``jax_enable_x64`` stay float32 throughout (BlackJAX's
    dense metric makes its identity matrix without a dtype: traced with 64-bit types on,
    it promoted the state and the sampler's loop failed on a dtype mismatch). Their draws
    match the exact Gaussian as the float64 chains' do, and the two runs agree within
    their Monte Carlo error."""
    rng = np.random.default_rng(4)
    truths = np.array([[0.4, 0.6, 0.3, 0.15], [0.2, 0.2, 0.9, 0.05]])
    ys, data = _noisy_pixels(linear, truths, rng)
    n = len(ys)
    opts = jp.HMCOptions(num_warmup=200, num_samples=1000, num_chains=2, dense_mass=True)
    runs = {
        dt: jp.sample_pixels(linear["lp"], data.astype(dt), jnp.asarray(truths, dt), options=opts)
        for dt in (jnp.float32, jnp.float64)
    }
    sd = np.sqrt(np.diag(linear["cov"]))
    for dt, s in runs.items():
        assert s.theta.shape == (n, 2, 1000, 4)
        assert not np.any(s.stats["diverging"]), dt
        assert np.max(jp.diagnostics(s)["max_rhat"]) < 1.02, dt
        for i in range(n):
            x = s.flat(i)
            mu = _exact_mean(linear, ys[i])
            assert np.all(np.abs(x.mean(0) - mu) < 4 * sd / math.sqrt(400.0)), (dt, x.mean(0), mu)
            err = (np.cov(x.T) - linear["cov"]) / np.outer(sd, sd)
            assert np.max(np.abs(err)) < 0.25, (dt, err)
    for i in range(n):
        gap = runs[jnp.float32].flat(i).mean(0) - runs[jnp.float64].flat(i).mean(0)
        assert np.all(np.abs(gap) < 4 * sd * math.sqrt(2 / 400.0)), gap


def test_thinning_keeps_every_thin_th_step(linear):
    """``thin=2`` runs the same chain as ``thin=1`` with twice the kept steps (same seed,
    same keys) and keeps its every second draw; acceptance is the mean of, and a
    divergence any of, the steps between."""
    rng = np.random.default_rng(5)
    truth = np.array([0.4, 0.6, 0.3, 0.15])
    y = truth @ linear["a"].T + linear["b"] + SIGMA * rng.normal(size=linear["b"].size)
    data = fit.pixel_data(
        y.reshape(1, -1, 3), linear["wi"][None], linear["wo"][None], scale=linear["scale"][None]
    )
    base = jp.HMCOptions(num_warmup=20, num_samples=20, num_chains=2, reparam="none")
    one = jp.sample_pixels(linear["lp"], data, jnp.asarray(truth), options=base, seed=3)
    two = jp.sample_pixels(
        linear["lp"],
        data,
        jnp.asarray(truth),
        options=jp.HMCOptions(num_warmup=20, num_samples=10, num_chains=2, reparam="none", thin=2),
        seed=3,
    )
    assert two.theta.shape == (1, 2, 10, 4)
    # equal up to rounding: XLA may fuse the two programs differently
    np.testing.assert_allclose(two.theta, one.theta[:, :, 1::2], rtol=1e-9)
    acc = one.stats["acceptance_rate"]
    np.testing.assert_allclose(two.stats["acceptance_rate"], (acc[..., ::2] + acc[..., 1::2]) / 2)
    div = one.stats["diverging"]
    np.testing.assert_array_equal(two.stats["diverging"], div[..., ::2] | div[..., 1::2])
    with pytest.raises(ValueError, match="thin"):
        jp.HMCOptions(thin=0)


def test_sbc_statistics_reject_20_percent_dispersion_error(linear):
    """With the exact posterior the statistics pass; sd scaled by 1.2 or 0.8 fails both
    the rank chi-square and the 90% coverage, by a wide margin."""
    rng = np.random.default_rng(4)
    s_n, m = 2000, 19
    cov = linear["cov"]
    chol = np.linalg.cholesky(cov)
    truth = rng.multivariate_normal(linear["m0"], linear["s0"], size=s_n)
    ys = truth @ linear["a"].T + linear["b"] + SIGMA * rng.normal(size=(s_n, linear["b"].size))
    mus = np.stack([_exact_mean(linear, y) for y in ys])
    for factor, ok in ((1.0, True), (1.2, False), (0.8, False)):
        eps = rng.normal(size=(s_n, m, 4)) @ chol.T
        draws = mus[:, None, :] + factor * eps
        res = sbc_summary(truth, draws, labels=linear["lp"].labels)
        z90 = res.coverage_z(0.9)
        if ok:
            assert np.all(res.tests["chi2_p"] > 1e-3), res.tests
            assert np.all(np.abs(z90) < 3.5), z90
        else:
            assert np.all(res.tests["chi2_p"] < 1e-3), (factor, res.tests)
            assert np.all(np.abs(z90) > 4.0), (factor, z90)


def test_priors_log_prob_and_sampling():
    rng = np.random.default_rng(5)
    ln = jp.LogNormal(0.1, 0.5)
    x = ln.sample(rng, (20000,))
    assert np.median(x) == pytest.approx(0.1, rel=0.03)
    # density ratio against the analytic log-normal pdf
    a, b = 0.05, 0.3
    ratio = float(ln.log_prob(jnp.asarray(a)) - ln.log_prob(jnp.asarray(b)))

    def pdf(v):
        return math.exp(-((math.log(v) - math.log(0.1)) ** 2) / (2 * 0.25)) / v

    assert ratio == pytest.approx(math.log(pdf(a) / pdf(b)), rel=1e-10)
    hc = jp.HalfCauchy(2.0)
    assert float(hc.log_prob(jnp.asarray(-1.0))) == -math.inf
    assert np.median(hc.sample(rng, (20000,))) == pytest.approx(2.0, rel=0.05)
    tr = sample_truncated(ln, rng, (500,), 0.05, 0.2)
    assert tr.min() >= 0.05 and tr.max() <= 0.2
    vmf = jp.VonMisesFisher((0.0, 1.0, 1.0), 50.0)
    d = vmf.sample(rng, (5000,))
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    # mean resultant length of vMF in 3-D: coth(k) - 1/k
    r = np.linalg.norm(d.mean(0))
    assert r == pytest.approx(1 / math.tanh(50.0) - 1 / 50.0, abs=3e-3)
    np.testing.assert_allclose(d.mean(0) / r, vmf.mu, atol=5e-3)
    # normalised: integrates to 1 over the sphere (Monte Carlo with uniform directions)
    u = rng.normal(size=(200000, 3))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    vmf5 = jp.VonMisesFisher((0.0, 0.0, 1.0), 5.0)
    est = 4 * math.pi * np.mean(np.exp(np.asarray(vmf5.log_prob(jnp.asarray(u)))))
    assert est == pytest.approx(1.0, rel=0.02)


def test_multivariate_normal_prior_is_scipys_density_over_the_block():
    from scipy import stats

    cov = ((0.02, 0.019, 0.018), (0.019, 0.02, 0.019), (0.018, 0.019, 0.021))
    mvn = jp.MultivariateNormal((0.2, 0.25, 0.3), cov)
    hash(mvn)  # static in a compiled sampler
    x = np.random.default_rng(3).uniform(0.0, 1.0, (7, 3))
    ref = stats.multivariate_normal((0.2, 0.25, 0.3), cov).logpdf(x)
    got = np.asarray(mvn.log_prob(jnp.asarray(x)))
    assert got.shape == (7,)
    np.testing.assert_allclose(got - got[0], ref - ref[0], rtol=1e-10, atol=1e-9)
    d = mvn.sample(np.random.default_rng(4), (40000,))
    np.testing.assert_allclose(np.cov(d.T), cov, atol=1.5e-3)
    # in units of the noise: N(mean, (s / s_ref)^2 cov), normalising factor included
    scaled = jp.MultivariateNormal((0.2, 0.25, 0.3), cov, noise_ref=0.01)
    x0 = jnp.asarray(x[0])
    offs = [
        float(scaled.log_prob_scaled(x0, s_))
        - stats.multivariate_normal((0.2, 0.25, 0.3), np.asarray(cov) * (s_ / 0.01) ** 2).logpdf(
            x[0]
        )
        for s_ in (0.005, 0.01, 0.03)
    ]
    np.testing.assert_allclose(offs, offs[0], rtol=0, atol=1e-9)
    assert float(scaled.log_prob_scaled(x0, 0.01)) == pytest.approx(float(mvn.log_prob(x0)))
    with pytest.raises(ValueError, match="noise_ref"):
        jp.MultivariateNormal((0.0,), ((1.0,),), noise_ref=0.0)
    with pytest.raises(ValueError, match="positive definite"):
        jp.MultivariateNormal((0.0, 0.0), ((1.0, 2.0), (2.0, 1.0)))
    with pytest.raises(ValueError, match="symmetric"):
        jp.MultivariateNormal((0.0, 0.0), ((1.0, 0.5), (0.0, 1.0)))


def test_default_priors_follow_the_space():
    model, space = __import__("jaxrefl.svbrdf", fromlist=["x"]).capture_model("ggx")
    pri = jp.default_priors(space)
    assert isinstance(pri["albedo"], jp.Uniform)
    assert isinstance(pri["specular"], jp.Uniform) and pri["specular"].upper == 0.25
    assert isinstance(pri["alpha"], jp.LogNormal)
    with pytest.raises(KeyError, match="not a free parameter"):
        jp.log_posterior(model, space, priors={"nope": jp.Uniform()})


def test_sphere_parameterisation_has_no_pole():
    """The density of u is smooth through the poles and the prior direction marginal is the
    von Mises–Fisher: gradients are finite at +-z and the log density is rotation-covariant."""
    sph = jp.SphereDirection(jp.VonMisesFisher((0.0, 0.0, 1.0), 3.0))
    u = jnp.asarray([[0, 0, 1.3], [0, 0, -0.7], [1e-9, 0, 1]])
    g = jax.jit(jax.vmap(jax.grad(sph.log_density)))(u)
    assert np.all(np.isfinite(np.asarray(g)))
    # direction(u) is unit and insensitive to the radius
    l12 = sph.direction(jnp.asarray([[0.3, -0.2, 0.5], [0.6, -0.4, 1.0]]))
    np.testing.assert_allclose(l12[0], l12[1], atol=1e-15)
    t, b = jax.jit(orthonormal_basis)(jnp.asarray([[0.0, 0.0, -1.0], [0.6, 0.0, 0.8]]))
    n = np.array([[0.0, 0.0, -1.0], [0.6, 0.0, 0.8]])
    for i in range(2):
        frame = np.stack([t[i], b[i], n[i]])
        np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-12)


def test_censored_and_unknown_scale_likelihood():
    """A saturated observation contributes log Phi((pred - obs) / sd); an unknown noise
    scale adds log s and the Jeffreys prior: the log density in log s peaks near the true
    residual scale."""
    m = brdf.get("lambert")
    space = fit.ParamSpace(m, channels=1, transforms={"albedo": fit.Identity()})
    lp = jp.log_posterior(m, space, fit.GaussianNoise(0.1), priors={"albedo": jp.Normal(0.5, 10)})
    wi = np.array([[0.0, 0.0, 1.0]] * 2)
    d = fit.pixel_data(np.array([[0.2], [0.3]]), wi, censored=np.array([[0], [1]]))
    t = jnp.asarray([0.5])
    pred = 0.5 / math.pi
    z1 = (pred - 0.2) / 0.1
    expect = -0.5 * z1 * z1 - math.log(0.1) + float(jax.scipy.special.log_ndtr((pred - 0.3) / 0.1))
    got = float(jax.jit(lambda t, d: lp.log_likelihood(t, d))(t, d))
    assert got == pytest.approx(expect, rel=1e-12)
    lp2 = jp.log_posterior(m, space, fit.GaussianNoise(None), priors={"albedo": jp.Normal(0.5, 10)})
    assert lp2.labels[-1] == "noise_scale" and isinstance(lp2.noise_scale, jp.Jeffreys)
    rng = np.random.default_rng(0)
    obs = 0.4 / math.pi + 0.05 * rng.normal(size=(400, 1))
    d2 = fit.pixel_data(obs, np.broadcast_to(wi[:1], (400, 3)))
    grid = np.log(np.linspace(0.03, 0.08, 101))
    f = jax.jit(jax.vmap(lambda g: lp2(jnp.stack([jnp.asarray(0.4), g]), d2)))
    vals = np.asarray(f(jnp.asarray(grid)))
    assert math.exp(grid[int(np.argmax(vals))]) == pytest.approx(0.05, rel=0.1)


def test_dark_clipped_term_and_the_uncensored_specialisation():
    """A dark-clipped observation contributes log Phi(-z); ``for_data`` drops the censored
    branch only for data without censored observations, with the same value and gradient."""
    m = brdf.get("lambert")
    space = fit.ParamSpace(m, channels=1, transforms={"albedo": fit.Identity()})
    lp = jp.log_posterior(m, space, fit.GaussianNoise(0.1), priors={"albedo": jp.Normal(0.5, 10)})
    wi = np.array([[0.0, 0.0, 1.0]] * 3)
    obs = np.array([[0.2], [0.3], [0.1]])
    d = fit.pixel_data(obs, wi, censored=np.array([[0], [1], [-1]]))
    t = jnp.asarray([0.5])
    pred = 0.5 / math.pi
    z = (pred - obs[:, 0]) / 0.1
    ndtr = jax.scipy.special.log_ndtr
    expect = -0.5 * z[0] ** 2 - math.log(0.1) + float(ndtr(z[1])) + float(ndtr(-z[2]))
    assert float(lp.for_data(d).log_likelihood(t, d)) == pytest.approx(expect, rel=1e-12)
    assert lp.for_data(d).censoring and lp.censoring
    plain = fit.pixel_data(obs, wi)
    fast = lp.for_data(plain)
    assert not fast.censoring
    g_full = jax.value_and_grad(lambda x: lp(x, plain))(t)
    g_fast = jax.value_and_grad(lambda x: fast(x, plain))(t)
    np.testing.assert_allclose(np.asarray(g_fast[0]), np.asarray(g_full[0]), rtol=1e-14)
    np.testing.assert_allclose(np.asarray(g_fast[1]), np.asarray(g_full[1]), rtol=1e-14)
    # Under a trace the data are not concrete: the general posterior is kept.
    kept = jax.jit(lambda d: jnp.asarray(lp.for_data(d).censoring))(plain)
    assert bool(kept)

"""The public API (jaxrefl/fit/_problem.py) and the automatic start (jaxrefl/fit/_init.py):
fits to measured samples (synthetic and the Cornell acrylic), the closed-form pieces of the
initialisation, and the ways to give a start."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from fit_zoo import directions, problem_zoo

import jaxrefl
from jaxrefl import fit
from jaxrefl.fit._affine import linear_params
from jaxrefl.fit._box_ls import _box_ls


def _ggx():
    return jaxrefl.brdf.get("cook_torrance", distribution="ggx", diffuse="lambert")


def test_linear_params_found_numerically():
    get = jaxrefl.brdf.get
    cases = [
        (_ggx(), ("albedo", "specular")),
        (get("ward"), ("albedo", "specular")),
        (get("blinn_phong"), ("albedo", "specular")),
        (get("lambert"), ("albedo",)),
        (get("oren_nayar"), ("albedo",)),  # qualitative model: linear in albedo
        (get("oren_nayar", variant="full"), ()),  # albedo^2 interreflection term
        (get("cook_torrance", fresnel="dielectric", diffuse="lambert"), ("albedo",)),
    ]
    for model, expected in cases:
        assert linear_params(model, fit.ParamSpace(model)) == expected, model
    # fixed parameters are not free, so not linear unknowns either
    m = _ggx()
    assert linear_params(m, fit.ParamSpace(m, fixed={"specular": 0.04})) == ("albedo",)


def test_box_constrained_ls_is_exact():
    rng = np.random.default_rng(0)
    grid = np.linspace(0.0, 1.0, 201)
    xx, yy = np.meshgrid(grid, grid, indexing="ij")
    for _ in range(20):
        f = rng.normal(size=(10, 2))
        f[:, 1] = f[:, 0] + 0.3 * f[:, 1]  # correlated columns, as albedo and a broad lobe
        y = f @ rng.uniform(-0.5, 1.5, 2) + 0.1 * rng.normal(size=10)
        a, b = f.T @ f, f.T @ y
        x = np.asarray(_box_ls(jnp.asarray(a), jnp.asarray(b), np.zeros(2), np.ones(2)))

        def q(u, v, a=a, b=b):
            return (
                a[0, 0] * u * u + 2 * a[0, 1] * u * v + a[1, 1] * v * v - 2 * (b[0] * u + b[1] * v)
            )

        brute = np.min(q(xx, yy))
        assert np.all((x >= 0) & (x <= 1))
        assert q(*x) <= brute + 1e-9


def test_initial_theta_is_close_on_exact_pixels():
    pr = problem_zoo()[0]
    space = fit.ParamSpace(pr.model)
    res = fit.make_residual(pr.model, space)
    x0 = np.asarray(space.natural_vector(fit.initial_theta(res, pr.data)))
    alpha0, alpha = x0[:, 6], pr.truth["alpha"]
    wp = pr.well_posed
    # 12 log-spaced grid values plus 8 between the best one's neighbours: alpha within ~10%
    assert np.median(np.abs(alpha0[wp] / alpha[wp] - 1)) < 0.05
    assert np.mean(np.abs(alpha0 / alpha - 1) < 0.25) >= 0.95
    # albedo and specular: exact for the grid alpha, so close as well
    assert np.median(np.abs(x0[wp, :3] / pr.truth["albedo"][wp] - 1)) < 0.05


def _synthetic_samples(model, truth, k=300, seed=5):
    rng = np.random.default_rng(seed)
    wi, wo = directions("gonio", 1, k, rng)
    p = {n: jnp.asarray(v)[None] for n, v in truth.items()}
    f = np.array(model.eval(p, jnp.asarray(wi[0]), jnp.asarray(wo[0])))
    return wi[0], wo[0], f


def test_fit_samples_recovers_a_known_brdf():
    m = _ggx()
    truth = {
        "albedo": np.array([0.3, 0.5, 0.2]),
        "specular": np.array([0.05, 0.06, 0.07]),
        "alpha": np.array(0.15),
    }
    wi, wo, f = _synthetic_samples(m, truth)
    f[7, 1] = np.nan  # a bad sample is simply not used
    r = fit.fit_samples(m, (wi, wo, f))
    assert int(r.status) == fit.Status.CONVERGED and r.theta.shape == (7,)
    assert int(r.n_used) == 3 * 300 - 1
    for name, v in truth.items():
        np.testing.assert_allclose(r.params[name], v, rtol=1e-4)
    # channels fitted separately: one problem per channel, results with a leading axis C
    separate = fit.SamplesOptions(channels="separate", cosine=True)
    rs = fit.fit_samples(m, (wi, wo, np.nan_to_num(f)), options=separate)
    assert rs.status.shape == (3,) and rs.params["albedo"].shape == (3,)
    assert rs.params["alpha"].shape == (3,)
    np.testing.assert_allclose(rs.params["specular"], truth["specular"], rtol=1e-3)
    np.testing.assert_allclose(rs.params["alpha"], 0.15, rtol=1e-3)
    assert separate.to_json() == {"type": "samples", "channels": "separate", "cosine": True}
    with pytest.raises(ValueError, match="channels must be 'joint' or 'separate'"):
        fit.SamplesOptions(channels="split")


def test_cornell_acrylic_band(shared_data):
    cornell = jaxrefl.io.read_cornell(shared_data / "brdf/cornell/acryl_blue.astm")
    band = cornell.select_channels(["450nm"])  # the blue band: a clear diffuse part
    ct = fit.fit_samples(_ggx(), band)
    lam = fit.fit_samples(jaxrefl.brdf.get("lambert"), band)
    assert int(ct.status) in (fit.Status.CONVERGED, fit.Status.MAX_ITERATIONS)
    assert all(np.all(np.isfinite(np.asarray(v))) for v in ct.params.values())
    assert ct.space.labels == ("albedo.450nm", "specular.450nm", "alpha")
    # the specular lobe explains the highlight: a 3x lower cost than Lambert alone (measured
    # 145 against 578 (1/sr)^2), with a glossy acrylic's roughness and Fresnel F0
    assert float(ct.cost) < 0.5 * float(lam.cost)
    assert 0.02 < float(ct.params["alpha"]) < 0.5
    assert 0.01 < float(ct.params["specular"][0]) < 0.2


def test_init_options_and_errors():
    pr = problem_zoo()[2]  # Lambert, exact
    m = pr.model
    good = fit.fit_pixels(m, pr.data)
    np.testing.assert_allclose(good.params["albedo"], pr.truth["albedo"], rtol=1e-8)
    n = pr.data.obs.shape[0]
    for init in ("defaults", {"albedo": jnp.full(3, 0.9)}, jnp.zeros(3), jnp.zeros((n, 3))):
        r = fit.fit_pixels(m, pr.data, init=init)
        np.testing.assert_allclose(r.params["albedo"], pr.truth["albedo"], rtol=1e-6)
        assert r.status_counts()["CONVERGED"] == n
    with pytest.raises(ValueError, match="init must be"):
        fit.fit_pixels(m, pr.data, init="grid")
    with pytest.raises(ValueError, match="channels"):
        fit.fit_pixels(m, pr.data, space=fit.ParamSpace(m, channels=1))
    with pytest.raises(ValueError, match=r"\(N, K, C\)"):
        fit.fit_pixels(m, jax.tree.map(lambda x: x[0], pr.data))

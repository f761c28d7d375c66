"""CookTorrance and Dichromatic: reference values, reciprocity, energy, gradients, edges."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _helpers import hemisphere_quadrature

import jaxrefl
from jaxrefl.brdf._cook_torrance import CookTorrance
from jaxrefl.brdf._dichromatic import Dichromatic
from jaxrefl.brdf._fresnel import fresnel_schlick
from jaxrefl.brdf._microfacet import GGX, SmithSeparable

SHADOWING = ("smith_height_correlated", "smith_separable", "vgroove")
FRESNEL = ("schlick", "dielectric", "conductor", "none")


def directional_albedo(model, params, theta_o, alpha):
    """int f(wi, wo) cos_i dw_i, integrated over the half vector: dw_i = 4 (wo.h) dw_h."""
    h, W = hemisphere_quadrature(alpha)
    wo = np.array([np.sin(theta_o), 0.0, np.cos(theta_o)])
    d = h @ wo
    wi = 2 * d[:, None] * h - wo
    weight = np.where(d > 0, 4 * d * W, 0.0) * np.maximum(wi[:, 2], 0.0)
    f = model.eval(params, jnp.asarray(wi), jnp.asarray(np.broadcast_to(wo, wi.shape)))
    return np.asarray(jnp.sum(f * weight[:, None], axis=0))


def random_directions(n, seed, grazing=True):
    rng = np.random.default_rng(seed)
    th = rng.uniform(0, np.pi / 2, n)
    if grazing:
        th[:4] = np.pi / 2 - np.array([1e-6, 1e-3, 1e-2, 0.1])
    ph = rng.uniform(0, 2 * np.pi, n)
    return jnp.asarray(np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1))


def test_reference_values():
    """At wi = wo = n: G = 1, D = 1/(pi alpha^2) for both distributions, so
    f = F0 / (4 pi alpha^2). Off-peak GGX matches the textbook tan-form (Walter 2007 eqs. 33,
    34 with Heitz 2014 eq. 99)."""
    n = jnp.asarray([0.0, 0.0, 1.0])
    for dist in ("ggx", "beckmann"):
        m = CookTorrance(dist)
        f = m.eval({"specular": jnp.asarray([0.04, 0.5, 1.0]), "alpha": 0.3}, n, n)
        np.testing.assert_allclose(f, np.array([0.04, 0.5, 1.0]) / (4 * np.pi * 0.09), rtol=1e-12)
    ti, to, phi, a = 0.6, 1.1, 2.0, 0.35
    wi = np.array([np.sin(ti), 0.0, np.cos(ti)])
    wo = np.array([np.sin(to) * np.cos(phi), np.sin(to) * np.sin(phi), np.cos(to)])
    h = (wi + wo) / np.linalg.norm(wi + wo)
    tan2 = (1 - h[2] ** 2) / h[2] ** 2
    D = 1 / (np.pi * a**2 * h[2] ** 4 * (1 + tan2 / a**2) ** 2)

    def lam(w):
        return 0.5 * (-1 + np.sqrt(1 + a**2 * (1 - w[2] ** 2) / w[2] ** 2))

    G = 1 / (1 + lam(wi) + lam(wo))
    F = 0.04 + 0.96 * (1 - h @ wo) ** 5
    f = CookTorrance().eval({"specular": 0.04, "alpha": a}, jnp.asarray(wi), jnp.asarray(wo))
    assert float(f[0]) == pytest.approx(F * D * G / (4 * wi[2] * wo[2]), rel=1e-12)


def test_reciprocity_and_nonnegativity_all_combinations():
    wi, wo = random_directions(64, 0), random_directions(64, 1)
    for dist, aniso, shadow, fres, diffuse in itertools.product(
        ("ggx", "beckmann"), (False, True), SHADOWING, FRESNEL, (None, "lambert")
    ):
        m = CookTorrance(dist, aniso, shadow, fres, diffuse)
        assert m.reciprocal
        p = m.default_params(jnp.float64)
        if aniso:
            p["alpha_u"], p["alpha_v"] = jnp.asarray(0.5), jnp.asarray(0.08)
        f, fr = m.eval(p, wi, wo), m.eval(p, wo, wi)
        assert f.shape == (64, 3)
        assert bool(jnp.all(f >= 0) & jnp.all(jnp.isfinite(f)))
        np.testing.assert_allclose(f, fr, rtol=1e-12, err_msg=str((dist, aniso, shadow, fres)))
    m = Dichromatic("beckmann")
    p = m.default_params(jnp.float64)
    np.testing.assert_allclose(m.eval(p, wi, wo), m.eval(p, wo, wi), rtol=1e-12)


def test_directional_albedo_at_most_one():
    """Energy: with F = 1 every distribution/shadowing combination reflects <= 1, from
    normal to grazing view, for smooth to rough surfaces (deterministic quadrature, error
    < 1e-4 here; checked against visible-normal Monte Carlo during development)."""
    table = {}
    for dist, shadow in itertools.product(("ggx", "beckmann"), SHADOWING):
        m = CookTorrance(dist, shadowing=shadow, fresnel="none")
        assert m.energy_conserving
        for alpha in (0.05, 0.3, 1.0):
            p = {"specular": jnp.ones(1), "alpha": jnp.asarray(alpha)}
            for theta in np.radians([0.0, 60.0, 85.0, 89.9]):
                rho = float(directional_albedo(m, p, theta, alpha)[0])
                table[dist, shadow, alpha, round(float(np.degrees(theta)), 1)] = rho
                assert 0.0 < rho <= 1.0 + 1e-4, (dist, shadow, alpha, theta, rho)
    # Height-correlated Smith loses less than the separable form (Heitz 2014, sec. 6).
    for key, rho in table.items():
        if key[1] == "smith_separable":
            assert rho <= table[key[0], "smith_height_correlated", *key[2:]] + 1e-9
    assert not CookTorrance(diffuse="lambert").energy_conserving
    # Anisotropic GGX with a Fresnel term keeps it below 1 too.
    m = CookTorrance(anisotropic=True, fresnel="conductor")
    p = {"eta": 0.2, "k": 3.0, "alpha_u": 0.6, "alpha_v": 0.1}
    assert float(directional_albedo(m, p, 1.2, 0.25)[0]) < 1.0


def test_white_furnace_smith_ggx():
    """GGX + height-correlated Smith, F = 1: single scattering loses only the energy of
    multiple bounces: < 1% at alpha = 0.05, ~3% at alpha = 0.1 and ~12% at alpha = 0.3 at
    normal incidence (cf. Kulla & Conty 2017, fig. 1; Heitz et al. 2016)."""
    m = CookTorrance("ggx", fresnel="none")
    rho = {
        a: float(directional_albedo(m, {"specular": 1.0, "alpha": a}, 0.0, a)[0])
        for a in (0.05, 0.1, 0.3)
    }
    assert 0.99 < rho[0.05] < 1.0
    assert 0.96 < rho[0.1] < 0.99
    assert 0.85 < rho[0.3] < 0.90


def test_gradients_match_finite_differences_for_every_parameter():
    """Reverse-mode gradient against a central difference along a random direction, for
    every parameter of every part (float64)."""
    wi = jnp.asarray([[0.3, 0.2, np.sqrt(0.87)], [0.0, -0.6, 0.8]])
    wo = jnp.asarray([[-0.5, 0.1, np.sqrt(0.74)], [0.1, 0.5, np.sqrt(0.74)]])
    configs = [
        (CookTorrance("ggx", fresnel="schlick", diffuse="lambert"), {}),
        (CookTorrance("beckmann", shadowing="smith_separable", fresnel="dielectric"), {}),
        (CookTorrance("ggx", True, "vgroove", "conductor"), {"alpha_v": 0.1}),
        (CookTorrance("beckmann", True, fresnel="none", diffuse="lambert"), {"alpha_u": 0.4}),
    ]
    rng = np.random.default_rng(7)
    for m, override in configs:
        p = {**m.default_params(jnp.float64), **{k: jnp.asarray(v) for k, v in override.items()}}
        cot = jnp.asarray(rng.normal(size=(2, 3)))

        def loss(p, m=m, cot=cot):
            return jnp.sum(m.eval(p, wi, wo) * cot)

        grad, fwd = jax.jit(jax.grad(loss)), jax.jit(loss)
        g = grad(p)
        for name in m.param_names:
            v = jnp.asarray(rng.normal(size=p[name].shape))
            eps = 1e-6
            up = fwd({**p, name: p[name] + eps * v})
            down = fwd({**p, name: p[name] - eps * v})
            fd = float(up - down) / (2 * eps)
            assert float(jnp.sum(g[name] * v)) == pytest.approx(fd, rel=1e-6, abs=1e-9), (
                m,
                name,
            )


EDGE_MODELS = [
    CookTorrance("ggx", False, "smith_height_correlated", "schlick"),
    CookTorrance("beckmann", False, "smith_separable", "dielectric"),
    CookTorrance("ggx", False, "vgroove", "conductor"),
    CookTorrance("beckmann", False, "vgroove", "none", "lambert"),
    CookTorrance("ggx", True, fresnel="conductor"),
    Dichromatic("beckmann"),
]


def _edge_values_and_grads(colours, alphas, wi, wo):
    """f and d(sum f cos)/d(params) for every edge model, in one jitted call."""
    out = []
    for m in EDGE_MODELS:
        p = {q.name: colours[q.name] if q.kind == "color" else alphas for q in m.params}
        out.append((m.eval(p, wi, wo), jax.grad(lambda p, m=m: m.eval_cos(p, wi, wo).sum())(p)))
    return out


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_values_and_gradients_finite_at_edges(dtype):
    """alpha 1e-4..1, cos 1e-6 and 0, wi == wo, h along the normal at grazing angles,
    eta 1.0001..4 (and < 1: total internal reflection), k up to 10, in one batch."""
    s = np.sqrt(1 - 1e-12)
    wi = [[0, 0, 1], [s, 0, 1e-6], [s, 0, 1e-6], [1, 0, 0], [0.6, 0, 0.8], [0, s, 1e-6]]
    wo = [[0, 0, 1], [-s, 0, 1e-6], [s, 0, 1e-6], [0, 0, 1], [0.6, 0, 0.8], [0.6, 0, 0.8]]
    wi, wo = jnp.asarray(wi, dtype), jnp.asarray(wo, dtype)
    n = wi.shape[0]
    alphas = jnp.asarray([1e-4, 1e-4, 1.0, 0.2, 1e-4, 1.0], dtype)
    eta = jnp.asarray([1.0001, 4.0, 1.5, 1.0001, 4.0, 1.0], dtype)
    colours = {
        "specular": jnp.full((n, 3), 1.0, dtype),
        "albedo": jnp.full((n, 3), 0.5, dtype),
        "eta": jnp.stack([eta, eta * 0.01, eta * 2.5], -1),
        "k": jnp.stack([jnp.zeros_like(eta), jnp.full_like(eta, 10.0), eta], -1),
    }
    results = jax.jit(_edge_values_and_grads)(colours, alphas, wi, wo)
    for m, (f, g) in zip(EDGE_MODELS, results, strict=True):
        assert f.dtype == dtype and f.shape == (n, 3)
        assert bool(jnp.all(jnp.isfinite(f)) & jnp.all(f >= 0)), (m, f)
        for k, v in g.items():
            assert bool(jnp.all(jnp.isfinite(v))), (m, k, v)
        assert float(f[3].max()) == 0.0  # wi on the horizon (cos = 0) gives exactly 0


def test_jit_vmap_and_broadcasting():
    m = CookTorrance("ggx", diffuse="lambert")
    n = 5
    wi, wo = random_directions(n, 2, grazing=False), random_directions(n, 3, grazing=False)
    rng = np.random.default_rng(4)
    p = {
        "albedo": jnp.asarray(rng.uniform(0, 1, (n, 3))),
        "specular": jnp.asarray(rng.uniform(0, 1, (n, 3))),
        "alpha": jnp.asarray(rng.uniform(0.05, 1, n)),
    }
    f = m.eval(p, wi, wo)
    assert f.shape == (n, 3)
    np.testing.assert_allclose(jax.jit(m.eval)(p, wi, wo), f, rtol=1e-12)
    np.testing.assert_allclose(jax.vmap(m.eval)(p, wi, wo), f, rtol=1e-12)
    # Per-sample evaluation agrees with the batch; a (3,) colour and scalar alpha broadcast
    # against an (n, 3) batch of wo and a single wi.
    one = m.eval({k: v[1] for k, v in p.items()}, wi[1], wo[1])
    np.testing.assert_allclose(one, f[1], rtol=1e-12)
    q = {"albedo": p["albedo"][0], "specular": p["specular"][0], "alpha": jnp.asarray(0.3)}
    g = m.eval(q, wi[0], wo)
    assert g.shape == (n, 3)
    np.testing.assert_allclose(g[2], m.eval(q, wi[0], wo[2]), rtol=1e-12)


def test_parts_registry_and_dichromatic():
    m = jaxrefl.brdf.get("cook_torrance", distribution="beckmann", fresnel="conductor")
    assert isinstance(m, CookTorrance) and m.param_names == ("eta", "k", "alpha")
    m = CookTorrance(GGX(anisotropic=True), shadowing=SmithSeparable(), diffuse="lambert")
    assert m.param_names == ("albedo", "specular", "alpha_u", "alpha_v")
    with pytest.raises(ValueError, match="unknown shadowing"):
        CookTorrance(shadowing="smith")
    with pytest.raises(ValueError, match="unknown diffuse"):
        CookTorrance(diffuse="oren_nayar")
    d = jaxrefl.brdf.get("dichromatic", distribution="beckmann")
    assert d.param_names == ("albedo", "specular", "alpha") and not d.energy_conserving
    ref = CookTorrance("beckmann", fresnel="none", diffuse="lambert")
    wi, wo = random_directions(16, 5), random_directions(16, 6)
    p = {"albedo": jnp.asarray([0.2, 0.4, 0.6]), "specular": 0.3, "alpha": 0.25}
    np.testing.assert_allclose(d.eval(p, wi, wo), ref.eval(p, wi, wo), rtol=1e-12)
    # The interface colour is the illuminant's: the specular part of a grey interface is grey.
    p0 = {**p, "albedo": jnp.zeros(3), "specular": jnp.full(3, 0.3)}
    spec = d.eval(p0, wi, wo)
    np.testing.assert_allclose(spec[:, 0], spec[:, 2], rtol=1e-12)
    # Schlick with F0 = 1 equals no Fresnel at all.
    a = CookTorrance(fresnel="schlick").eval({"specular": 1.0, "alpha": 0.3}, wi, wo)
    b = CookTorrance(fresnel="none").eval({"specular": 1.0, "alpha": 0.3}, wi, wo)
    np.testing.assert_allclose(a, b, rtol=1e-12)
    assert float(fresnel_schlick(0.5, 1.0)) == 1.0

"""Diffuse models (jaxrefl/brdf/_lambert.py): Lambert, and Oren–Nayar with hand-computed
values, the sigma = 0 identity, reciprocity, energy by quadrature, gradients against central
differences, and finite values/gradients at the edges."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _helpers import albedo_on_grid, assert_finite_edges, fd_check, sph, unit

import jaxrefl
from jaxrefl.brdf._lambert import Lambert, OrenNayar


def test_lambert_value_and_shape():
    m = jaxrefl.brdf.get("lambert")
    wi = jnp.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    wo = jnp.array([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]])
    f = m.eval({"albedo": jnp.array([0.2, 0.5, 1.0])}, wi, wo)
    assert f.shape == (2, 3)
    np.testing.assert_allclose(f[0], np.array([0.2, 0.5, 1.0]) / np.pi, rtol=1e-12)


def test_lambert_below_horizon_is_zero_with_finite_grad():
    m = jaxrefl.brdf.get("lambert")
    wi = jnp.array([0.6, 0.0, -0.8])
    wo = jnp.array([0.0, 0.0, 1.0])
    g = jax.grad(lambda a: m.eval({"albedo": a}, wi, wo).sum())(jnp.array([0.5]))
    assert float(m.eval({"albedo": 0.5}, wi, wo)[0]) == 0.0
    assert np.all(np.isfinite(g))


# ============================================================================ Oren–Nayar
ON_VARIANTS = ("qualitative", "full")


def _on_hand(variant, albedo, sigma, wi, wo):
    """Oren & Nayar 1994 written with explicit angles (arccos, arctan2), in numpy."""
    ti, to = np.arccos(wi[2]), np.arccos(wo[2])
    cdp = np.cos(np.arctan2(wo[1], wo[0]) - np.arctan2(wi[1], wi[0]))
    a, b = max(ti, to), min(ti, to)
    s2 = sigma**2
    A = 1 - 0.5 * s2 / (s2 + 0.33)
    B = 0.45 * s2 / (s2 + 0.09)
    if variant == "qualitative":
        return albedo / np.pi * (A + B * max(0.0, cdp) * np.sin(a) * np.tan(b))
    c2 = B * np.sin(a) if cdp >= 0 else B * (np.sin(a) - (2 * b / np.pi) ** 3)
    c3 = 0.125 * s2 / (s2 + 0.09) * (4 * a * b / np.pi**2) ** 2
    l1 = A + cdp * c2 * np.tan(b) + (1 - abs(cdp)) * c3 * np.tan((a + b) / 2)
    l1 = max(l1, 0.0)  # the documented clamp (negative for grazing forward scattering)
    l2 = 0.17 * albedo * s2 / (s2 + 0.13) * (1 - cdp * (2 * b / np.pi) ** 2)
    return albedo / np.pi * (l1 + l2)


ON_PAIRS = [
    (sph(30, 10), sph(60, 40)),  # cos dphi > 0
    (sph(88, 0), sph(87, 180)),  # grazing forward scattering: clamped for sigma = 1
    (sph(70, 0), sph(20, 150)),  # cos dphi < 0
    (sph(80, 0), sph(85, 90)),  # cos dphi = 0, both grazing
    (sph(45, 0), sph(45, 0)),  # wi = wo (retro)
    (sph(0, 0), sph(50, 0)),  # wi = n (phi_i undefined)
]


@pytest.mark.parametrize("variant", ON_VARIANTS)
def test_oren_nayar_reference_values(variant):
    m = OrenNayar(variant)
    albedo = np.array([0.2, 0.6, 1.0])
    for sigma in (0.3, 1.0):
        for wi, wo in ON_PAIRS:
            want = _on_hand(variant, albedo, sigma, wi, wo)
            got = np.asarray(m.eval({"albedo": albedo, "sigma": sigma}, wi, wo))
            np.testing.assert_allclose(got, want, rtol=1e-12)
    if variant == "full":
        # grazing forward scattering, sigma = 1: the paper's single-bounce bracket is
        # negative there (C1 + cos(dphi) C2 tan(beta) < 0); only the interreflection is left.
        wi, wo = ON_PAIRS[1]
        a, b = np.arccos(wi[2]), np.arccos(wo[2])
        a, b = max(a, b), min(a, b)
        A, B = 1 - 0.5 / 1.33, 0.45 / 1.09
        assert A - B * (np.sin(a) - (2 * b / np.pi) ** 3) * np.tan(b) < -0.05
        got = np.asarray(m.eval({"albedo": albedo, "sigma": 1.0}, wi, wo))
        inter = 0.17 * albedo**2 / np.pi / 1.13 * (1 + (2 * b / np.pi) ** 2)
        np.testing.assert_allclose(got, inter, rtol=1e-12)
    # backscatter: with the light at 45 deg the view at 45 deg on the light's side is ~30%
    # brighter than the mirror view (qualitative: (A + B sin45 tan45)/A = 1.30 for sigma 0.5)
    p = {"albedo": 1.0, "sigma": 0.5}
    retro = float(m.eval(p, sph(45), sph(45))[0])
    mirror = float(m.eval(p, sph(45), sph(45, 180))[0])
    assert retro > 1.25 * mirror


@pytest.mark.parametrize("variant", ON_VARIANTS)
def test_oren_nayar_sigma_zero_is_lambert_exactly(variant):
    rng = np.random.default_rng(2)
    wi = unit(rng.normal(size=(200, 3)) + np.array([0, 0, 1]))
    wo = unit(rng.normal(size=(200, 3)) + np.array([0, 0, 1]))
    albedo = rng.uniform(size=(200, 3))
    for dtype in (jnp.float32, jnp.float64):
        a = OrenNayar(variant).eval(
            {"albedo": jnp.asarray(albedo, dtype), "sigma": jnp.zeros(200, dtype)},
            jnp.asarray(wi, dtype),
            jnp.asarray(wo, dtype),
        )
        b = Lambert().eval(
            {"albedo": jnp.asarray(albedo, dtype)}, jnp.asarray(wi, dtype), jnp.asarray(wo, dtype)
        )
        assert a.dtype == dtype
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("variant", ON_VARIANTS)
def test_oren_nayar_reciprocity_non_negativity_batching(variant):
    m = jaxrefl.brdf.get("oren_nayar", variant=variant)
    rng = np.random.default_rng(6)
    N = 300
    wi = unit(rng.normal(size=(N, 3)) + np.array([0, 0, 0.5]))
    wo = unit(rng.normal(size=(N, 3)) + np.array([0, 0, 0.5]))
    p = {"albedo": rng.uniform(size=(N, 3)), "sigma": rng.uniform(0, 1.5, N)}
    a, b = np.asarray(m.eval(p, wi, wo)), np.asarray(m.eval(p, wo, wi))
    assert np.all(np.isfinite(a)) and np.all(a >= 0.0)
    np.testing.assert_allclose(a, b, rtol=1e-12)
    np.testing.assert_allclose(jax.jit(m.eval)(p, wi, wo), a, rtol=1e-13)
    np.testing.assert_allclose(jax.vmap(m.eval)(p, wi, wo), a, rtol=1e-13)
    q = {"albedo": [0.3, 0.5, 0.7], "sigma": 0.4}
    assert m.eval(q, np.stack([wi, wo]), np.stack([wo, wi])).shape == (2, N, 3)
    # wi = n: phi_i is undefined and the value must not depend on the azimuth of wo
    f = m.eval(q, np.array([0.0, 0.0, 1.0]), np.stack([sph(40, ph) for ph in (0, 77, 200)]))
    np.testing.assert_allclose(f, f[:1] * jnp.ones((3, 1)), rtol=1e-13)


def test_oren_nayar_energy():
    """Directional albedo with albedo = 1. At normal incidence it is A (qualitative) and
    C1 + 0.17 sigma^2/(sigma^2 + 0.13) (full) exactly (beta = 0 removes every other term).
    Neither model is bounded by 1: the qualitative one reaches 1.0152 (sigma = 0.2, grazing
    incidence), the full one 1.0509 (sigma = 0.3); both lose energy at large sigma."""
    q, full = OrenNayar("qualitative"), OrenNayar("full")
    p = {"albedo": 1.0, "sigma": 0.7}
    s2 = 0.49
    rho_q = albedo_on_grid(q, p, sph(0), [0, 0, 1], np.pi / 2)[0]
    rho_f = albedo_on_grid(full, p, sph(0), [0, 0, 1], np.pi / 2)[0]
    np.testing.assert_allclose(rho_q, 1 - 0.5 * s2 / (s2 + 0.33), rtol=1e-10)
    np.testing.assert_allclose(
        rho_f, 1 - 0.5 * s2 / (s2 + 0.33) + 0.17 * s2 / (s2 + 0.13), rtol=1e-10
    )
    worst = {"qualitative": 0.0, "full": 0.0}
    for m in (q, full):
        for sigma in (0.1, 0.2, 0.3, 0.5, 1.5):
            for t in (0.0, 45.0, 80.0, 89.9):
                rho = albedo_on_grid(
                    m, {"albedo": 1.0, "sigma": sigma}, sph(t), [0, 0, 1], np.pi / 2
                )[0]
                worst[m.variant] = max(worst[m.variant], rho)
    np.testing.assert_allclose(worst["qualitative"], 1.0151, atol=1e-3)
    np.testing.assert_allclose(worst["full"], 1.0500, atol=1e-3)
    assert not q.energy_conserving and not full.energy_conserving


@pytest.mark.parametrize("variant", ON_VARIANTS)
def test_oren_nayar_gradients_match_finite_differences(variant):
    m = OrenNayar(variant)
    wi = jnp.asarray(np.stack([ON_PAIRS[0][0], ON_PAIRS[2][0]]))
    wo = jnp.asarray(np.stack([ON_PAIRS[0][1], ON_PAIRS[2][1]]))
    p = {"albedo": jnp.array([0.2, 0.5, 0.8]), "sigma": jnp.array([0.3, 0.8])}
    fd_check(m, p, wi, wo)
    # and with respect to the directions (through theta, phi, alpha, beta)
    fn = jax.jit(lambda a, b: jnp.sum(m.eval(p, a, b)))
    ga = jax.grad(fn)(wi, wo)
    num = np.zeros((2, 3))
    for idx in np.ndindex(2, 3):
        d = np.zeros((2, 3))
        d[idx] = 1e-6
        num[idx] = (fn(wi + d, wo) - fn(wi - d, wo)) / 2e-6
    np.testing.assert_allclose(ga, num, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("variant", ON_VARIANTS)
def test_oren_nayar_finite_values_and_gradients_at_edges(variant, dtype):
    m = OrenNayar(variant)
    for sigma in (0.0, 0.1, 1.5):
        assert_finite_edges(m, {"albedo": [1.0, 0.0, 0.5], "sigma": sigma}, dtype)

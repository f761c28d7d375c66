"""Phong and Blinn–Phong (jaxrefl/brdf/_phong.py): hand-computed values, reciprocity of the
normalized forms and non-reciprocity of the classic ones, energy by quadrature, gradients
against central differences, and finite values/gradients at the edges."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _helpers import albedo_on_grid, assert_finite_edges, fd_check, mirror, sph, unit

import jaxrefl
from jaxrefl.brdf._phong import BlinnPhong, Phong, cos_power

VARIANTS = [
    ("phong", False),
    ("phong", True),
    ("blinn_phong", False),
    ("blinn_phong", True),
]
IDS = [f"{n}{'_normalized' if z else ''}" for n, z in VARIANTS]


# ----------------------------------------------------------------------------- values
def _hand(name, normalized, albedo, spec, n, wi, wo):
    """The models written out once more, in numpy, from the formulas in the docstring."""
    if name == "phong":
        r = np.array([-wi[0], -wi[1], wi[2]])
        c = max(0.0, float(wo @ r))
        norm = (n + 2) / (2 * np.pi)
    else:
        h = (wi + wo) / np.linalg.norm(wi + wo)
        c = max(0.0, float(h[2]))
        norm = (n + 8) / (8 * np.pi)
    lobe = c**n
    scale = norm if normalized else 1.0 / wi[2]
    return albedo / np.pi + spec * scale * lobe


@pytest.mark.parametrize(("name", "normalized"), VARIANTS, ids=IDS)
def test_reference_values(name, normalized):
    m = jaxrefl.brdf.get(name, normalized=normalized)
    albedo = np.array([0.2, 0.5, 0.9])
    spec = np.array([0.3, 0.1, 0.7])
    cases = [
        (unit([0.3, 0.2, 0.9]), unit([-0.4, -0.1, 0.8]), 20.0),  # near the mirror direction
        (unit([0.7, -0.1, 0.3]), unit([0.1, 0.5, 0.6]), 3.5),  # far from it, low exponent
        (sph(60), sph(60, 180), 1e5),  # exact mirror (wh = n) with n = 1e5
    ]
    for wi, wo, n in cases:
        p = {"albedo": albedo, "specular": spec, "exponent": n}
        want = _hand(name, normalized, albedo, spec, n, wi, wo)
        got = np.asarray(m.eval(p, wi, wo))
        np.testing.assert_allclose(got, want, rtol=1e-10)
    # The lobe is not negligible in these cases, so the check constrains the specular term.
    p = {"albedo": 0.0 * albedo, "specular": spec, "exponent": 20.0}
    assert float(m.eval(p, cases[0][0], cases[0][1])[0]) > 0.01


def test_mirror_peak_with_huge_exponent_float32():
    """At the exact mirror direction the normalised Phong lobe is (n + 2)/(2 pi) ~ 1.6e4 for
    n = 1e5: huge but finite, also in float32."""
    m = Phong(normalized=True)
    wi = jnp.asarray(sph(60), dtype=jnp.float32)
    wo = jnp.asarray(sph(60, 180), dtype=jnp.float32)
    p = {"albedo": 0.0, "specular": 1.0, "exponent": 1e5}
    f = m.eval(p, wi, wo)
    assert f.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(f), (1e5 + 2) / (2 * np.pi), rtol=1e-2)


def test_cos_power_guard():
    c = jnp.array([-0.5, 0.0, 1e-30, 0.5, 1.0, 1.0 + 1e-7])
    n = jnp.array([3.0, 2.0, 0.5, 2.0, 1e5, 1e5])
    v = np.asarray(cos_power(c, n))
    np.testing.assert_allclose(v, [0.0, 0.0, 1e-15, 0.25, 1.0, 1.0], rtol=1e-12)
    g = jax.grad(lambda c, n: jnp.sum(cos_power(c, n)), argnums=(0, 1))(c, n)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in g)
    np.testing.assert_allclose(np.asarray(g[0])[:4], [0.0, 0.0, 0.5e15, 1.0], rtol=1e-12)


# ----------------------------------------------------------------------------- reciprocity
def test_classic_forms_are_not_reciprocal():
    """The classic forms divide by cos(theta_i) only: swapping wi and wo scales the lobe by
    exactly cos_i/cos_o. The normalised forms are symmetric."""
    wi, wo = unit([0.5, 0.1, 0.6]), unit([-0.3, -0.05, 0.9])
    p = {"albedo": 0.0, "specular": 1.0, "exponent": 5.0}
    for cls in (Phong, BlinnPhong):
        classic = cls(normalized=False)
        assert classic.reciprocal is False
        a, b = float(classic.eval(p, wi, wo)[0]), float(classic.eval(p, wo, wi)[0])
        np.testing.assert_allclose(a / b, wo[2] / wi[2], rtol=1e-12)
        assert abs(a / b - 1.0) > 0.2
        normalized = cls(normalized=True)
        assert normalized.reciprocal is True
        a, b = float(normalized.eval(p, wi, wo)[0]), float(normalized.eval(p, wo, wi)[0])
        np.testing.assert_allclose(a, b, rtol=1e-13)


@pytest.mark.parametrize(("name", "normalized"), VARIANTS, ids=IDS)
def test_reciprocity_and_non_negativity(name, normalized):
    m = jaxrefl.brdf.get(name, normalized=normalized)
    rng = np.random.default_rng(3)
    wi = unit(rng.normal(size=(500, 3)) * [1, 1, 0.5] + [0, 0, 0.6])
    wo = unit(rng.normal(size=(500, 3)) * [1, 1, 0.5] + [0, 0, 0.6])
    p = {
        "albedo": rng.uniform(0, 1, (500, 3)),
        "specular": rng.uniform(0, 1, (500, 3)),
        "exponent": np.exp(rng.uniform(0, np.log(1e5), 500)),
    }
    a, b = np.asarray(m.eval(p, wi, wo)), np.asarray(m.eval(p, wo, wi))
    assert np.all(np.isfinite(a)) and np.all(a >= 0.0)
    if normalized:
        np.testing.assert_allclose(a, b, rtol=1e-12)
    else:
        assert np.max(np.abs(a - b) / (a + b + 1e-300)) > 0.1


# ----------------------------------------------------------------------------- energy
def test_normalized_phong_energy_with_albedo_plus_specular_one():
    """Lewis' normalisation: the lobe's directional albedo is exactly 1 at normal incidence
    and smaller elsewhere, so albedo + specular = 1 gives rho <= 1 (equality at normal)."""
    m = Phong(normalized=True)
    for n in (0.0, 1.0, 20.0, 1e3):
        p = {"albedo": 0.3, "specular": 0.7, "exponent": n}
        width = min(np.pi / 2, 3.0 / np.sqrt(n + 1.0))
        rho = [albedo_on_grid(m, p, sph(t), mirror(sph(t)), width)[0] for t in (0, 30, 60, 85, 89)]
        assert max(rho) <= 1.0 + 1e-6, (n, rho)
        np.testing.assert_allclose(rho[0], 1.0, atol=1e-6)
        assert rho[-1] < 0.9
    assert Phong(normalized=True).energy_conserving is False  # albedo + specular may reach 2


def test_normalized_blinn_phong_energy_is_approximate():
    """RTR's (n + 8)/(8 pi): at normal incidence the lobe albedo has the closed form
    (n + 8)(n + 2^(-n/2)) / ((n + 2)(n + 4)), which is 1 at n = 0, peaks at 1.0752 at
    n = 8.76 and tends to 1 from above; at grazing incidence it falls far below 1."""
    m = BlinnPhong(normalized=True)
    peak = 0.0
    for n in (0.0, 2.0, 9.0, 100.0, 1e4):
        p = {"albedo": 0.0, "specular": 1.0, "exponent": n}
        width = min(np.pi / 2, 3.0 / np.sqrt(n + 1.0))
        rho0 = albedo_on_grid(m, p, sph(0), [0, 0, 1], width)[0]
        exact = (n + 8) * (n + 2 ** (-n / 2)) / ((n + 2) * (n + 4))
        np.testing.assert_allclose(rho0, exact, rtol=1e-6)
        peak = max(peak, rho0)
        rho85 = albedo_on_grid(m, p, sph(85), mirror(sph(85)), width)[0]
        assert rho85 < 0.7 or n == 0.0
    np.testing.assert_allclose(peak, 1.0752, atol=1e-4)
    assert BlinnPhong(normalized=True).energy_conserving is False


# ----------------------------------------------------------------------------- gradients


@pytest.mark.parametrize(("name", "normalized"), VARIANTS, ids=IDS)
def test_gradients_match_finite_differences(name, normalized):
    m = jaxrefl.brdf.get(name, normalized=normalized)
    wi = jnp.asarray(unit([[0.3, 0.2, 0.9], [0.5, -0.1, 0.6]]))
    wo = jnp.asarray(unit([[-0.35, -0.1, 0.85], [-0.4, 0.2, 0.7]]))
    p = {
        "albedo": jnp.array([0.2, 0.5, 0.8]),
        "specular": jnp.array([0.3, 0.6, 0.9]),
        "exponent": jnp.asarray(12.0),
    }
    fd_check(m, p, wi, wo)


# ----------------------------------------------------------------------------- edges


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["f32", "f64"])
@pytest.mark.parametrize(("name", "normalized"), VARIANTS, ids=IDS)
def test_finite_values_and_gradients_at_edges(name, normalized, dtype):
    m = jaxrefl.brdf.get(name, normalized=normalized)
    for n in (0.0, 0.5, 1e4, 1e5):
        assert_finite_edges(m, {"albedo": [1.0, 0.0, 0.5], "specular": 1.0, "exponent": n}, dtype)


# ----------------------------------------------------------------------------- batching
def test_jit_vmap_and_broadcasting():
    m = Phong(normalized=True)
    rng = np.random.default_rng(5)
    N = 7
    wi = jnp.asarray(unit(rng.normal(size=(N, 3)) + np.array([0, 0, 2])))
    wo = jnp.asarray(unit(rng.normal(size=(N, 3)) + np.array([0, 0, 2])))
    p = {
        "albedo": jnp.asarray(rng.uniform(size=(N, 3))),
        "specular": jnp.asarray(rng.uniform(size=(N, 1))),
        "exponent": jnp.asarray(rng.uniform(1, 50, size=N)),
    }
    f = m.eval(p, wi, wo)
    assert f.shape == (N, 3)
    np.testing.assert_allclose(jax.jit(m.eval)(p, wi, wo), f, rtol=1e-13)
    np.testing.assert_allclose(jax.vmap(m.eval)(p, wi, wo), f, rtol=1e-13)
    # row j equals an unbatched evaluation of row j
    j = 3
    pj = {k: v[j] for k, v in p.items()}
    np.testing.assert_allclose(m.eval(pj, wi[j], wo[j]), f[j], rtol=1e-13)
    # unbatched parameters against a (2, N) batch of directions; one wi against N wo
    q = {"albedo": jnp.array([0.1, 0.2, 0.3]), "specular": 0.5, "exponent": 10.0}
    assert m.eval(q, jnp.stack([wi, wo]), jnp.stack([wo, wi])).shape == (2, N, 3)
    np.testing.assert_allclose(m.eval(q, wi[0], wo)[2], m.eval(q, wi[0], wo[2]), rtol=1e-13)

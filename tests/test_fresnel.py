"""Fresnel functions and parts: reference values, identities, stability, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxrefl.brdf._fresnel import (
    ConductorFresnel,
    DielectricFresnel,
    NoFresnel,
    SchlickFresnel,
    f0_from_eta,
    fresnel_conductor,
    fresnel_dielectric,
    fresnel_dielectric_polarized,
    fresnel_schlick,
)


def complex_fresnel(cos_i, eta, k=0.0):
    """Independent reference: textbook complex-amplitude Fresnel equations (Hecht, Optics, sec. 4.6;
    Born & Wolf 13.2) in numpy complex128, for light arriving from outside."""
    n = np.asarray(eta) + 1j * np.asarray(k)
    c = np.asarray(cos_i, dtype=np.complex128)
    ct = np.sqrt(n * n - (1 - c * c))  # n cos(theta_t), principal root
    r_s = (c - ct) / (c + ct)
    r_p = (n * n * c - ct) / (n * n * c + ct)
    return 0.5 * (np.abs(r_s) ** 2 + np.abs(r_p) ** 2)


def test_dielectric_reference_values():
    # Hecht, Optics (4th ed.), sec. 4.6: R = ((n - 1)/(n + 1))^2 = 0.04 for glass, n = 1.5.
    assert float(fresnel_dielectric(1.0, 1.5)) == pytest.approx(0.04, abs=1e-15)
    assert float(f0_from_eta(1.5)) == pytest.approx(0.04, abs=1e-15)
    # Water n = 1.333 reflects "about 2%" at normal incidence (Hecht, same section).
    assert float(fresnel_dielectric(1.0, 1.333)) == pytest.approx(0.02, abs=5e-4)
    # Grazing incidence reflects everything; from inside at normal incidence it is symmetric.
    assert float(fresnel_dielectric(0.0, 1.5)) == 1.0
    assert float(fresnel_dielectric(-1.0, 1.5)) == pytest.approx(0.04, abs=1e-15)
    cos = np.linspace(0.0, 1.0, 201)
    for eta in (1.0001, 1.33, 1.5, 2.4, 4.0):
        np.testing.assert_allclose(
            fresnel_dielectric(cos, eta), complex_fresnel(cos, eta), rtol=1e-10, atol=1e-15
        )


def test_dielectric_inside_and_total_internal_reflection():
    # From inside glass (cos < 0, eta = 1.5 outside/inside ratio) the critical angle is
    # asin(1/1.5) = 41.8 degrees: beyond it F = 1 exactly.
    theta_c = np.arcsin(1 / 1.5)
    beyond = -np.cos(np.linspace(theta_c + 1e-6, np.pi / 2, 50))
    assert np.all(np.asarray(fresnel_dielectric(beyond, 1.5)) == 1.0)
    # Inside the cone the result equals the outside formula with 1/eta.
    before = np.cos(np.linspace(0.0, theta_c - 1e-3, 50))
    np.testing.assert_allclose(
        fresnel_dielectric(-before, 1.5), complex_fresnel(before, 1 / 1.5), rtol=1e-12
    )
    # eta < 1 from outside is the same physics.
    np.testing.assert_array_equal(fresnel_dielectric(-beyond, 1 / 1.5), 1.0)


def test_brewster_angle_zero_of_p_polarised_part():
    for eta in (1.33, 1.5, 2.4):
        cos_b = np.cos(np.arctan(eta))  # Brewster: tan(theta_B) = n_t / n_i (Hecht, sec. 8.6)
        r_s, r_p = fresnel_dielectric_polarized(cos_b, eta)
        assert float(r_p) == pytest.approx(0.0, abs=1e-14)
        assert float(r_s) > 0.01
        # Away from Brewster's angle R_p > 0.
        assert float(fresnel_dielectric_polarized(cos_b + 0.05, eta)[1]) > 1e-5


def test_conductor_with_k0_equals_dielectric():
    cos = np.concatenate([[0.0, 1e-6, 1e-3], np.linspace(0.01, 1.0, 200)])
    for eta in (0.3, 1 / 1.5, 0.95, 1.0001, 1.5, 2.4, 4.0):
        np.testing.assert_allclose(
            fresnel_conductor(cos, eta, 0.0), fresnel_dielectric(cos, eta), rtol=1e-12, atol=2e-8
        )
    # ... and with k > 0 it matches the complex-amplitude reference (gold, silver, extremes).
    for eta, k in ((0.143, 3.983), (0.124, 3.35), (1.44, 1.6), (0.05, 10.0), (10.0, 10.0)):
        np.testing.assert_allclose(
            fresnel_conductor(cos, eta, k), complex_fresnel(cos, eta, k), rtol=1e-12
        )


def test_conductor_stable_in_float32():
    cos = np.array([0.0, 1e-6, 1e-3, 0.3, 0.7, 1 - 1e-6, 1.0])
    for eta, k in ((0.05, 10.0), (0.143, 3.983), (1.5, 0.0), (0.5, 1e-4), (10.0, 10.0), (0.0, 5.0)):
        ref = complex_fresnel(cos, eta, k)
        f32 = fresnel_conductor(jnp.asarray(cos, jnp.float32), jnp.float32(eta), jnp.float32(k))
        assert f32.dtype == jnp.float32
        np.testing.assert_allclose(f32, ref, rtol=2e-6)


def test_dielectric_near_eta_one_stable_in_float32():
    """eta -> 1 at grazing incidence: the naive 1 - sin^2/eta^2 loses every digit in float32
    (F jumped between 0.01 and 1 for cos < 3e-4 at eta = 1); the cancellation-free form
    keeps float32 within 1e-5 of the float64 reference, and eta = 1 gives F = 0 exactly."""
    cos = np.array([1e-6, 1e-5, 1e-4, 1.5e-4, 2e-4, 3e-4, 1e-3, 0.1, 1.0])
    for eta in (1.0001, 1.001, 1.5):
        # Reference at the float32-rounded inputs: float32(1.0001) - 1 is off by 1.7e-4.
        c32, e32 = cos.astype(np.float32), np.float32(eta)
        ref = complex_fresnel(c32.astype(np.float64), float(e32))
        f32 = fresnel_dielectric(jnp.asarray(c32), jnp.asarray(e32))
        np.testing.assert_allclose(f32, ref, rtol=1e-5, atol=1e-9)
    f32 = fresnel_dielectric(jnp.asarray(cos, jnp.float32), jnp.float32(1.0))
    np.testing.assert_array_equal(f32, 0.0)


def test_schlick_exact_at_normal_and_grazing():
    for eta in (1.2, 1.5, 2.4):
        f0 = f0_from_eta(eta)
        assert float(fresnel_schlick(1.0, f0)) == pytest.approx(float(fresnel_dielectric(1.0, eta)))
        assert float(fresnel_schlick(0.0, f0)) == 1.0
    # Schlick's known error for glass stays below 0.04 absolute (largest near 85 degrees).
    cos = np.linspace(0, 1, 2001)
    err = np.abs(fresnel_schlick(cos, f0_from_eta(1.5)) - fresnel_dielectric(cos, 1.5))
    assert 0.01 < float(err.max()) < 0.04


def _edge_values_and_grads(c, e, c3, e3, k3):
    """All edge-case values and their gradients, in one jitted call (one compile)."""

    def schlick(c, e):
        return fresnel_schlick(c, f0_from_eta(e))

    out = []
    for fn, args in (
        (fresnel_dielectric, (c, e)),
        (schlick, (c, e)),
        (fresnel_conductor, (c3, e3, k3)),
    ):
        v = fn(*args)
        g = jax.grad(lambda *a, fn=fn: fn(*a).sum(), argnums=tuple(range(len(args))))(*args)
        out.append((v, g))
    return out


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_fresnel_values_and_gradients_finite_at_edges(dtype):
    # Incidence from inside (TIR for eta = 1.5), the horizon, the critical angle of
    # eta = 1/1.5 (cos = 0.745), normal incidence; eta from TIR through 1 to 4.
    cos = jnp.asarray([-1.0, -0.5, -1e-6, 0.0, 1e-6, 0.3, 0.745, 1 - 1e-7, 1.0], dtype)
    etas = jnp.asarray([1 / 1.5, 1.0, 1.0001, 1.5, 4.0], dtype)
    c, e = (x.ravel() for x in jnp.meshgrid(cos, etas))
    cos_c = jnp.asarray([0.0, 1e-6, 0.5, 1.0], dtype)
    eta_c = jnp.asarray([0.0, 0.05, 1.0, 1.5, 10.0], dtype)
    k_c = jnp.asarray([0.0, 1e-4, 1.0, 10.0], dtype)
    c3, e3, k3 = (x.ravel() for x in jnp.meshgrid(cos_c, eta_c, k_c))
    for v, grads in jax.jit(_edge_values_and_grads)(c, e, c3, e3, k3):
        assert v.dtype == dtype
        assert bool(jnp.all(jnp.isfinite(v)) & jnp.all((v >= 0) & (v <= 1)))
        assert all(bool(jnp.all(jnp.isfinite(g))) for g in grads)


def test_gradients_match_finite_differences():
    c = jnp.asarray([0.05, 0.4, 0.9])
    check_grads(jax.jit(fresnel_dielectric), (c, jnp.asarray(1.7)), 1, modes=["rev"])
    check_grads(
        jax.jit(lambda c, e: fresnel_dielectric(-c, e)), (c, jnp.asarray(1.3)), 1, modes=["rev"]
    )
    conductor = jax.jit(fresnel_conductor)
    for eta, k in ((0.143, 3.983), (1.5, 0.0), (0.6, 0.2), (2.0, 8.0)):
        check_grads(conductor, (c, jnp.asarray(eta), jnp.asarray(k)), 1, modes=["rev"])


def test_parts_shapes_values_and_params():
    cos_d = jnp.asarray([0.2, 1.0])
    spec = jnp.asarray([[0.04, 0.5, 1.0]])
    f = SchlickFresnel()({"specular": spec}, cos_d)
    assert f.shape == (2, 3)
    np.testing.assert_allclose(f[1], spec[0])
    f = NoFresnel()({"specular": spec}, cos_d)
    np.testing.assert_allclose(f, jnp.broadcast_to(spec, (2, 3)))
    f = DielectricFresnel()({"eta": jnp.asarray([[1.5]])}, cos_d)
    assert f.shape == (2, 1) and float(f[1, 0]) == pytest.approx(0.04)
    f = ConductorFresnel()(
        {"eta": jnp.asarray([[1.5, 0.2]]), "k": jnp.asarray([[0.0, 3.0]])}, cos_d
    )
    assert f.shape == (2, 2) and float(f[1, 0]) == pytest.approx(0.04)
    assert [q.name for q in ConductorFresnel().params] == ["eta", "k"]
    for part in (SchlickFresnel(), DielectricFresnel(), ConductorFresnel(), NoFresnel()):
        assert part.at_most_one
        for q in part.params:
            assert q.kind == "color" and q.lower <= np.min(q.default) <= q.upper

"""Diffuse models (jaxrefl/brdf/_lambert.py): Lambert, and Oren–Nayar with hand-computed
values, the sigma = 0 identity, reciprocity, energy by quadrature, gradients against central
differences, and finite values/gradients at the edges."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

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


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _sph(theta_deg, phi_deg=0.0):
    t, p = np.deg2rad(theta_deg), np.deg2rad(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


# ----------------------------------------------------------------------------- quadrature
def _lobe_grid(axis, width, n_gl=32, n_phi=256, n_panels=6):
    """Directions and solid-angle weights on a sphere grid centred on ``axis``: Gauss-Legendre
    panels in the polar angle, the first of ``width`` and the rest growing geometrically,
    midpoint rule in azimuth. Centred on the normal it stops at the horizon (a panel edge).
    The grid size does not depend on ``width`` so that one compiled evaluation serves all."""
    a = _unit(axis)
    t = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    t1 = _unit(t - a * (t @ a))
    t2 = np.cross(a, t1)
    tmax = np.pi / 2 if a[2] > 1 - 1e-12 else np.pi
    edges = np.concatenate([[0.0], np.geomspace(min(width, tmax / 2), tmax, n_panels)])
    x, wt = np.polynomial.legendre.leggauss(n_gl)
    th = np.concatenate([(lo + hi) / 2 + (hi - lo) / 2 * x for lo, hi in itertools.pairwise(edges)])
    tw = np.concatenate([(hi - lo) / 2 * wt for lo, hi in itertools.pairwise(edges)])
    ph = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    T, P = np.meshgrid(th, ph, indexing="ij")
    W = np.sin(T) * tw[:, None] * (2 * np.pi / n_phi)
    d = (
        (np.sin(T) * np.cos(P))[..., None] * t1
        + (np.sin(T) * np.sin(P))[..., None] * t2
        + np.cos(T)[..., None] * a
    )
    return d.reshape(-1, 3), W.reshape(-1)


_JIT = {}


def _albedo(m, p, wi, axis, width, **kw):
    """rho(wi) = ∫ f(wi, wo) cos(theta_o) dω_o, by quadrature on a grid centred on ``axis``."""
    d, W = _lobe_grid(axis, width, **kw)
    ev = _JIT.setdefault(m, jax.jit(m.eval))
    p = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in p.items()}
    f = np.asarray(ev(p, jnp.asarray(np.broadcast_to(wi, d.shape)), jnp.asarray(d)))
    return np.sum(f * (W * np.maximum(d[:, 2], 0.0))[:, None], axis=0)


def _mirror(w):
    return np.array([-w[0], -w[1], w[2]])


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
    (_sph(30, 10), _sph(60, 40)),  # cos dphi > 0
    (_sph(88, 0), _sph(87, 180)),  # grazing forward scattering: clamped for sigma = 1
    (_sph(70, 0), _sph(20, 150)),  # cos dphi < 0
    (_sph(80, 0), _sph(85, 90)),  # cos dphi = 0, both grazing
    (_sph(45, 0), _sph(45, 0)),  # wi = wo (retro)
    (_sph(0, 0), _sph(50, 0)),  # wi = n (phi_i undefined)
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
    retro = float(m.eval(p, _sph(45), _sph(45))[0])
    mirror = float(m.eval(p, _sph(45), _sph(45, 180))[0])
    assert retro > 1.25 * mirror


@pytest.mark.parametrize("variant", ON_VARIANTS)
def test_oren_nayar_sigma_zero_is_lambert_exactly(variant):
    rng = np.random.default_rng(2)
    wi = _unit(rng.normal(size=(200, 3)) + np.array([0, 0, 1]))
    wo = _unit(rng.normal(size=(200, 3)) + np.array([0, 0, 1]))
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
    wi = _unit(rng.normal(size=(N, 3)) + np.array([0, 0, 0.5]))
    wo = _unit(rng.normal(size=(N, 3)) + np.array([0, 0, 0.5]))
    p = {"albedo": rng.uniform(size=(N, 3)), "sigma": rng.uniform(0, 1.5, N)}
    a, b = np.asarray(m.eval(p, wi, wo)), np.asarray(m.eval(p, wo, wi))
    assert np.all(np.isfinite(a)) and np.all(a >= 0.0)
    np.testing.assert_allclose(a, b, rtol=1e-12)
    np.testing.assert_allclose(jax.jit(m.eval)(p, wi, wo), a, rtol=1e-13)
    np.testing.assert_allclose(jax.vmap(m.eval)(p, wi, wo), a, rtol=1e-13)
    q = {"albedo": [0.3, 0.5, 0.7], "sigma": 0.4}
    assert m.eval(q, np.stack([wi, wo]), np.stack([wo, wi])).shape == (2, N, 3)
    # wi = n: phi_i is undefined and the value must not depend on the azimuth of wo
    f = m.eval(q, np.array([0.0, 0.0, 1.0]), np.stack([_sph(40, ph) for ph in (0, 77, 200)]))
    np.testing.assert_allclose(f, f[:1] * jnp.ones((3, 1)), rtol=1e-13)


def test_oren_nayar_energy():
    """Directional albedo with albedo = 1. At normal incidence it is A (qualitative) and
    C1 + 0.17 sigma^2/(sigma^2 + 0.13) (full) exactly (beta = 0 removes every other term).
    Neither model is bounded by 1: the qualitative one reaches 1.0152 (sigma = 0.2, grazing
    incidence), the full one 1.0509 (sigma = 0.3); both lose energy at large sigma."""
    q, full = OrenNayar("qualitative"), OrenNayar("full")
    p = {"albedo": 1.0, "sigma": 0.7}
    s2 = 0.49
    rho_q = _albedo(q, p, _sph(0), [0, 0, 1], np.pi / 2)[0]
    rho_f = _albedo(full, p, _sph(0), [0, 0, 1], np.pi / 2)[0]
    np.testing.assert_allclose(rho_q, 1 - 0.5 * s2 / (s2 + 0.33), rtol=1e-10)
    np.testing.assert_allclose(
        rho_f, 1 - 0.5 * s2 / (s2 + 0.33) + 0.17 * s2 / (s2 + 0.13), rtol=1e-10
    )
    worst = {"qualitative": 0.0, "full": 0.0}
    for m in (q, full):
        for sigma in (0.1, 0.2, 0.3, 0.5, 1.5):
            for t in (0.0, 45.0, 80.0, 89.9):
                rho = _albedo(m, {"albedo": 1.0, "sigma": sigma}, _sph(t), [0, 0, 1], np.pi / 2)[0]
                worst[m.variant] = max(worst[m.variant], rho)
    np.testing.assert_allclose(worst["qualitative"], 1.0151, atol=1e-3)
    np.testing.assert_allclose(worst["full"], 1.0500, atol=1e-3)
    assert not q.energy_conserving and not full.energy_conserving


def _fd_check(m, p, wi, wo, rtol=1e-6, atol=1e-9):
    """jax.grad against a central difference for every element of every parameter."""
    fn = jax.jit(lambda q: jnp.sum(m.eval(q, wi, wo) * jnp.arange(1.0, 4.0)[None, :]))
    g = jax.grad(fn)(p)
    for name, x in p.items():
        x = np.asarray(x, dtype=np.float64)
        num = np.zeros_like(x)
        for idx in np.ndindex(x.shape):
            h = 1e-6 * max(1.0, abs(x[idx]))
            xp, xm = x.copy(), x.copy()
            xp[idx] += h
            xm[idx] -= h
            num[idx] = (fn({**p, name: jnp.asarray(xp)}) - fn({**p, name: jnp.asarray(xm)})) / (
                2 * h
            )
        np.testing.assert_allclose(np.asarray(g[name]), num, rtol=rtol, atol=atol, err_msg=name)
        assert np.any(np.abs(num) > 1e-6), name  # the check must be able to fail


@pytest.mark.parametrize("variant", ON_VARIANTS)
def test_oren_nayar_gradients_match_finite_differences(variant):
    m = OrenNayar(variant)
    wi = jnp.asarray(np.stack([ON_PAIRS[0][0], ON_PAIRS[2][0]]))
    wo = jnp.asarray(np.stack([ON_PAIRS[0][1], ON_PAIRS[2][1]]))
    p = {"albedo": jnp.array([0.2, 0.5, 0.8]), "sigma": jnp.array([0.3, 0.8])}
    _fd_check(m, p, wi, wo)
    # and with respect to the directions (through theta, phi, alpha, beta)
    fn = jax.jit(lambda a, b: jnp.sum(m.eval(p, a, b)))
    ga = jax.grad(fn)(wi, wo)
    num = np.zeros((2, 3))
    for idx in np.ndindex(2, 3):
        d = np.zeros((2, 3))
        d[idx] = 1e-6
        num[idx] = (fn(wi + d, wo) - fn(wi - d, wo)) / 2e-6
    np.testing.assert_allclose(ga, num, rtol=1e-6, atol=1e-9)


_G = 1e-6
_S = np.sqrt(1 - _G * _G)
_C = np.sqrt(0.5)
EDGE_WI = np.array(
    [[0, 0, 1], [_C, 0, _C], [0.8660254037844386, 0, 0.5], [_S, 0, _G], [0, 0, 1],
     [_S, 0, _G], [_S, 0, _G], [1, 0, 0], [0.6, 0, -0.8], [_S, 0, _G]]
)  # fmt: skip
EDGE_WO = np.array(
    [[0, 0, 1], [_C, 0, _C], [-0.8660254037844386, 0, 0.5], [0, 0, 1], [0, _S, _G],
     [-_S, 0, _G], [_S, 0, _G], [0, 0, 1], [0, 0, 1], [-_S, 0, 0]]
)  # fmt: skip
# normal (wi = wo, wh = n); wi = wo at 45; mirror pair (wh = n); grazing wi; grazing wo;
# grazing mirror pair; wi = wo grazing; wi on the horizon; wi below; wo exactly at cos 0.


def _assert_finite_edges(m, p, dtype):
    wi = jnp.asarray(EDGE_WI, dtype=dtype)
    wo = jnp.asarray(EDGE_WO, dtype=dtype)
    p = {k: jnp.asarray(v, dtype=dtype) for k, v in p.items()}
    ev = _JIT.setdefault(m, jax.jit(m.eval))
    gr = _JIT.setdefault(
        ("grad", m),
        jax.jit(jax.grad(lambda q, a, b: jnp.sum(m.eval(q, a, b)), argnums=(0, 1, 2))),
    )
    f = ev(p, wi, wo)
    assert f.dtype == dtype and np.all(np.isfinite(np.asarray(f))), f
    assert np.all(np.asarray(f)[-3:] == 0.0)  # cos = 0 and below the horizon are exactly 0
    for leaf in jax.tree_util.tree_leaves(gr(p, wi, wo)):
        assert np.all(np.isfinite(np.asarray(leaf))), (p, leaf)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("variant", ON_VARIANTS)
def test_oren_nayar_finite_values_and_gradients_at_edges(variant, dtype):
    m = OrenNayar(variant)
    for sigma in (0.0, 0.1, 1.5):
        _assert_finite_edges(m, {"albedo": [1.0, 0.0, 0.5], "sigma": sigma}, dtype)

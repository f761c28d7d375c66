"""Phong and Blinn–Phong (jaxrefl/brdf/_phong.py): hand-computed values, reciprocity of the
normalized forms and non-reciprocity of the classic ones, energy by quadrature, gradients
against central differences, and finite values/gradients at the edges."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrefl
from jaxrefl.brdf._phong import BlinnPhong, Phong, cos_power

VARIANTS = [
    ("phong", False),
    ("phong", True),
    ("blinn_phong", False),
    ("blinn_phong", True),
]
IDS = [f"{n}{'_normalized' if z else ''}" for n, z in VARIANTS]


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
        (_unit([0.3, 0.2, 0.9]), _unit([-0.4, -0.1, 0.8]), 20.0),  # near the mirror direction
        (_unit([0.7, -0.1, 0.3]), _unit([0.1, 0.5, 0.6]), 3.5),  # far from it, low exponent
        (_sph(60), _sph(60, 180), 1e5),  # exact mirror (wh = n) with n = 1e5
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
    wi = jnp.asarray(_sph(60), dtype=jnp.float32)
    wo = jnp.asarray(_sph(60, 180), dtype=jnp.float32)
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
    wi, wo = _unit([0.5, 0.1, 0.6]), _unit([-0.3, -0.05, 0.9])
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
    wi = _unit(rng.normal(size=(500, 3)) * [1, 1, 0.5] + [0, 0, 0.6])
    wo = _unit(rng.normal(size=(500, 3)) * [1, 1, 0.5] + [0, 0, 0.6])
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
        rho = [_albedo(m, p, _sph(t), _mirror(_sph(t)), width)[0] for t in (0, 30, 60, 85, 89)]
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
        rho0 = _albedo(m, p, _sph(0), [0, 0, 1], width)[0]
        exact = (n + 8) * (n + 2 ** (-n / 2)) / ((n + 2) * (n + 4))
        np.testing.assert_allclose(rho0, exact, rtol=1e-6)
        peak = max(peak, rho0)
        rho85 = _albedo(m, p, _sph(85), _mirror(_sph(85)), width)[0]
        assert rho85 < 0.7 or n == 0.0
    np.testing.assert_allclose(peak, 1.0752, atol=1e-4)
    assert BlinnPhong(normalized=True).energy_conserving is False


# ----------------------------------------------------------------------------- gradients
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


@pytest.mark.parametrize(("name", "normalized"), VARIANTS, ids=IDS)
def test_gradients_match_finite_differences(name, normalized):
    m = jaxrefl.brdf.get(name, normalized=normalized)
    wi = jnp.asarray(_unit([[0.3, 0.2, 0.9], [0.5, -0.1, 0.6]]))
    wo = jnp.asarray(_unit([[-0.35, -0.1, 0.85], [-0.4, 0.2, 0.7]]))
    p = {
        "albedo": jnp.array([0.2, 0.5, 0.8]),
        "specular": jnp.array([0.3, 0.6, 0.9]),
        "exponent": jnp.asarray(12.0),
    }
    _fd_check(m, p, wi, wo)


# ----------------------------------------------------------------------------- edges
_G = 1e-6
_S = np.sqrt(1 - _G * _G)
_C = np.sqrt(0.5)
EDGE_WI = np.array(
    [[0, 0, 1], [_C, 0, _C], [0.8660254037844386, 0, 0.5], [_S, 0, _G], [0, 0, 1],
     [_S, 0, _G], [_S, 0, _G], [1, 0, 1e-30], [1, 0, 1e-30], [1, 0, 0], [0.6, 0, -0.8],
     [_S, 0, _G]]
)  # fmt: skip
EDGE_WO = np.array(
    [[0, 0, 1], [_C, 0, _C], [-0.8660254037844386, 0, 0.5], [0, 0, 1], [0, _S, _G],
     [-_S, 0, _G], [_S, 0, _G], [-1, 0, 1e-30], [0, 0, 1], [0, 0, 1], [0, 0, 1],
     [-_S, 0, 0]]
)  # fmt: skip
# normal (wi = wo, wh = n); wi = wo at 45; mirror pair (wh = n); grazing wi; grazing wo;
# grazing mirror pair; wi = wo grazing; mirror pair and one direction at cos = 1e-30 (below
# every floor); wi on the horizon; wi below; wo exactly at cos 0.


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
@pytest.mark.parametrize(("name", "normalized"), VARIANTS, ids=IDS)
def test_finite_values_and_gradients_at_edges(name, normalized, dtype):
    m = jaxrefl.brdf.get(name, normalized=normalized)
    for n in (0.0, 0.5, 1e4, 1e5):
        _assert_finite_edges(m, {"albedo": [1.0, 0.0, 0.5], "specular": 1.0, "exponent": n}, dtype)


# ----------------------------------------------------------------------------- batching
def test_jit_vmap_and_broadcasting():
    m = Phong(normalized=True)
    rng = np.random.default_rng(5)
    N = 7
    wi = jnp.asarray(_unit(rng.normal(size=(N, 3)) + np.array([0, 0, 2])))
    wo = jnp.asarray(_unit(rng.normal(size=(N, 3)) + np.array([0, 0, 2])))
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

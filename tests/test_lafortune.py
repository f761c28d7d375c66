"""Lafortune lobes (jaxrefl/brdf/_lafortune.py): hand-computed values, the Phong identity,
retro-reflective and anisotropic lobes, reciprocity, energy by quadrature, gradients against
central differences, and finite values/gradients at the edges."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _helpers import albedo_on_grid, assert_finite_edges, fd_check, sph, unit

from jaxrefl.brdf._lafortune import Lafortune, default_lobes
from jaxrefl.brdf._phong import Phong


# ----------------------------------------------------------------------------- values
def _hand(albedo, lobes, wi, wo):
    """Lafortune et al. 1997 eq. (4) written out in numpy, lobe by lobe."""
    total = 0.0
    for cx, cy, cz, n in lobes:
        x = cx * wi[0] * wo[0] + cy * wi[1] * wo[1] + cz * wi[2] * wo[2]
        total += max(x, 0.0) ** n
    return albedo / np.pi + total


LOBES = np.array(
    [
        [-0.9, -0.9, 0.95, 12.0],  # Phong-like
        [-1.1, -1.1, 0.4, 3.0],  # off-specular (Cz < |Cx|)
        [0.6, 0.6, 0.6, 2.0],  # retro-reflective
        [-1.0, -0.5, 1.0, 30.0],  # anisotropic
    ]
)


def test_reference_values():
    m = Lafortune(num_lobes=4)
    albedo = np.array([0.1, 0.4, 0.8])
    pairs = [
        (unit([0.3, 0.2, 0.9]), unit([-0.4, -0.1, 0.8])),
        (unit([0.7, -0.1, 0.3]), unit([0.1, 0.5, 0.6])),
        (unit([0.6, 0.3, 0.4]), unit([0.5, 0.35, 0.45])),  # near retro
    ]
    for wi, wo in pairs:
        got = np.asarray(m.eval({"albedo": albedo, "lobes": LOBES}, wi, wo))
        np.testing.assert_allclose(got, _hand(albedo, LOBES, wi, wo), rtol=1e-12)
        # each lobe contributes in at least one of the pairs
    contrib = [
        [_hand(0.0, LOBES[j : j + 1], wi, wo) for wi, wo in pairs] for j in range(len(LOBES))
    ]
    assert all(max(c) > 1e-3 for c in contrib)


def test_one_lobe_equals_normalized_phong():
    """(Cx, Cy, Cz) = (-1, -1, 1) is cos^n of the angle to the mirror direction, i.e. Phong's
    lobe: Lafortune with that lobe equals Phong(normalized) with specular = 2 pi/(n + 2); with
    C scaled by k the lobe is scaled by k^n."""
    rng = np.random.default_rng(0)
    wi = unit(rng.normal(size=(64, 3)) * [1, 1, 0.4] + [0, 0, 1])
    wo = unit(rng.normal(size=(64, 3)) * [1, 1, 0.4] + [0, 0, 1])
    wo[:8] = wi[:8] * [-1, -1, 1]  # exact mirror pairs
    lafortune, phong = Lafortune(), Phong(normalized=True)
    for n, k in [(0.5, 1.0), (7.0, 1.0), (150.0, 0.98)]:
        lobe = np.array([[-k, -k, k, n]])
        a = lafortune.eval({"albedo": [0.2, 0.3, 0.4], "lobes": lobe}, wi, wo)
        spec = k**n * 2 * np.pi / (n + 2)
        b = phong.eval({"albedo": [0.2, 0.3, 0.4], "specular": spec, "exponent": n}, wi, wo)
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-14)
        # at the mirror pairs the lobe is exactly k^n (so the comparison exercises the lobe)
        np.testing.assert_allclose(
            np.asarray(a[:8]) - np.array([0.2, 0.3, 0.4]) / np.pi, k**n, rtol=1e-11
        )


def test_retro_reflective_lobe_peaks_at_wo_equal_wi():
    m = Lafortune()
    lobe = np.array([[0.8, 0.8, 0.8, 20.0]])
    wi = unit([0.5, 0.2, 0.6])
    th, ph = np.meshgrid(np.linspace(0, 1.5, 151), np.linspace(0, 2 * np.pi, 360, endpoint=False))
    wo = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    wo = np.concatenate([wo, wi[None]])
    f = np.asarray(m.eval({"albedo": 0.0, "lobes": lobe}, wi, wo))[:, 0]
    assert int(np.argmax(f)) == len(wo) - 1  # the maximum over the grid is wo = wi
    np.testing.assert_allclose(f[-1], 0.8**20, rtol=1e-12)  # x = 0.8 |wi|^2 there
    # and it is not a specular lobe: at the mirror direction it is much smaller
    mirror = float(m.eval({"albedo": 0.0, "lobes": lobe}, wi, wi * [-1, -1, 1])[0])
    assert mirror < 1e-3 * f[-1]


def test_anisotropic_lobe_differs_between_x_and_y():
    """Cx != Cy: the same mirror configuration in the x-z and y-z planes gives
    (|Cx| sin^2 + Cz cos^2)^n versus (|Cy| sin^2 + Cz cos^2)^n."""
    m = Lafortune()
    lobe = np.array([[-1.0, -0.6, 1.0, 10.0]])
    t = np.deg2rad(50.0)
    s2, c2 = np.sin(t) ** 2, np.cos(t) ** 2
    wi_x, wo_x = sph(50, 0), sph(50, 180)
    wi_y, wo_y = sph(50, 90), sph(50, 270)
    fx = float(m.eval({"albedo": 0.0, "lobes": lobe}, wi_x, wo_x)[0])
    fy = float(m.eval({"albedo": 0.0, "lobes": lobe}, wi_y, wo_y)[0])
    np.testing.assert_allclose(fx, (1.0 * s2 + c2) ** 10, rtol=1e-12)
    np.testing.assert_allclose(fy, (0.6 * s2 + c2) ** 10, rtol=1e-12)
    assert fx > 5 * fy


def test_off_specular_lobe_peaks_beyond_the_mirror_direction():
    """Cz < |Cx|: in the plane of incidence x = |Cx| sin(ti) sin(to) + Cz cos(ti) cos(to)
    peaks at tan(to) = |Cx| tan(ti) / Cz, beyond the mirror angle: 49.1 degrees for ti = 30
    and Cz = |Cx|/2 (with Cz = |Cx| it is the mirror angle itself)."""
    m = Lafortune()
    th = np.deg2rad(np.linspace(0.0, 89.9, 900))
    wo = np.stack([-np.sin(th), 0 * th, np.cos(th)], -1)
    for cz, peak in [(0.5, np.rad2deg(np.arctan(2 * np.tan(np.deg2rad(30))))), (1.0, 30.0)]:
        lobe = np.array([[-1.0, -1.0, cz, 8.0]])
        f = np.asarray(m.eval({"albedo": 0.0, "lobes": lobe}, sph(30), wo))[:, 0]
        np.testing.assert_allclose(np.rad2deg(th[np.argmax(f)]), peak, atol=0.1)


def test_reciprocity_non_negativity_and_batching():
    m = Lafortune(num_lobes=3)
    rng = np.random.default_rng(4)
    N = 400
    wi = unit(rng.normal(size=(N, 3)) + np.array([0, 0, 0.5]))
    wo = unit(rng.normal(size=(N, 3)) + np.array([0, 0, 0.5]))
    lobes = np.concatenate(
        [rng.uniform(-1.2, 1.2, (N, 3, 3)), np.exp(rng.uniform(0, np.log(1e5), (N, 3, 1)))], -1
    )
    p = {"albedo": rng.uniform(size=(N, 3)), "lobes": lobes}
    a, b = np.asarray(m.eval(p, wi, wo)), np.asarray(m.eval(p, wo, wi))
    assert a.shape == (N, 3) and np.all(np.isfinite(a)) and np.all(a >= 0.0)
    np.testing.assert_allclose(a, b, rtol=1e-12)
    # jit and vmap agree; row j is an unbatched evaluation; (L, 4) lobes broadcast
    np.testing.assert_allclose(jax.jit(m.eval)(p, wi, wo), a, rtol=1e-13)
    np.testing.assert_allclose(jax.vmap(m.eval)(p, wi, wo), a, rtol=1e-13)
    j = 17
    np.testing.assert_allclose(
        m.eval({"albedo": p["albedo"][j], "lobes": lobes[j]}, wi[j], wo[j]), a[j], rtol=1e-13
    )
    q = {"albedo": [0.5], "lobes": lobes[j]}
    assert m.eval(q, np.stack([wi, wo]), np.stack([wo, wi])).shape == (2, N, 1)
    # the default lobes: (num_lobes, 4), distinct exponents
    d = np.asarray(default_lobes(3))
    assert d.shape == (3, 4) and len(set(d[:, 3])) == 3
    assert m.default_params()["lobes"].shape == (3, 4)


def test_lobe_energy_matches_phong_closed_form():
    """A (-c, -c, c, n) lobe reflects c^n 2 pi/(n + 2) at normal incidence (the Phong lobe
    integral); the default lobes therefore sum to a lobe albedo of 0.5 there."""
    m = Lafortune()
    for n, c in [(1.0, 0.9), (40.0, 0.99), (2000.0, 1.0)]:
        p = {"albedo": 0.0, "lobes": [[-c, -c, c, n]]}
        rho = albedo_on_grid(m, p, sph(0), [0, 0, 1], min(np.pi / 2, 3 / np.sqrt(n + 1)))[0]
        np.testing.assert_allclose(rho, c**n * 2 * np.pi / (n + 2), rtol=1e-6)
    m3 = Lafortune(num_lobes=3)
    p = {"albedo": 0.0, "lobes": default_lobes(3)}
    rho = albedo_on_grid(m3, p, sph(0), [0, 0, 1], 0.1)[0]
    np.testing.assert_allclose(rho, 0.5, rtol=1e-5)


# ----------------------------------------------------------------------------- gradients


def test_gradients_match_finite_differences():
    m = Lafortune(num_lobes=4)
    wi = jnp.asarray(unit([[0.3, 0.2, 0.9], [0.6, 0.3, 0.4]]))
    wo = jnp.asarray(unit([[-0.4, -0.1, 0.8], [0.5, 0.35, 0.45]]))
    lobes = jnp.asarray(LOBES).at[:, 3].set(jnp.array([5.0, 3.0, 2.0, 6.0]))
    p = {"albedo": jnp.array([0.2, 0.5, 0.8]), "lobes": lobes}
    fd_check(m, p, wi, wo, rtol=1e-6)


# ----------------------------------------------------------------------------- edges


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["f32", "f64"])
def test_finite_values_and_gradients_at_edges(dtype):
    m = Lafortune(num_lobes=2)
    for n in (0.0, 0.5, 1e4, 1e5):
        for c in ([-1.0, -1.0, 1.0], [1.0, 1.0, 1.0], [-1.1, -1.1, 0.0], [-3.0, -0.2, 2.0]):
            lobes = [[*c, n], [-1.0, -1.0, 1.0, 1e5]]
            assert_finite_edges(m, {"albedo": [1.0, 0.0, 0.5], "lobes": lobes}, dtype)


def test_huge_lobe_is_capped_not_infinite():
    """|C| > 1 with n = 1e5 would overflow; the value is capped at exp(60) with finite grads."""
    m = Lafortune()
    wi, wo = sph(60), sph(60, 180)
    for dtype in (jnp.float32, jnp.float64):
        p = {"albedo": jnp.zeros(1, dtype), "lobes": jnp.asarray([[-1.5, -1.5, 1.5, 1e5]], dtype)}
        f = m.eval(p, jnp.asarray(wi, dtype), jnp.asarray(wo, dtype))
        np.testing.assert_allclose(np.asarray(f), np.exp(60.0), rtol=1e-5)
    # below the cap the value is exact: 1.5^100
    p = {"albedo": 0.0, "lobes": [[-1.5, -1.5, 1.5, 100.0]]}
    np.testing.assert_allclose(m.eval(p, wi, wo)[0], 1.5**100, rtol=1e-12)

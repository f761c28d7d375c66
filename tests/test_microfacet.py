"""Microfacet distributions and shadowing: normalisation, Smith identities, limits, edges."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _helpers import hemisphere_quadrature
from scipy.special import erf

from jaxrefl import brdf
from jaxrefl.brdf._microfacet import (
    ALPHA_MIN,
    GGX,
    Beckmann,
    SmithHeightCorrelated,
    SmithSeparable,
    VGroove,
)

DISTS = [GGX(), Beckmann(), GGX(anisotropic=True), Beckmann(anisotropic=True)]


def params_for(dist, alpha, ratio=0.25):
    if dist.anisotropic:
        return {"alpha_u": jnp.asarray(alpha), "alpha_v": jnp.asarray(alpha * ratio)}, np.sqrt(
            ratio
        ) * alpha
    return {"alpha": jnp.asarray(alpha)}, alpha


def direction(theta, phi=0.3):
    return jnp.asarray([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


@pytest.mark.parametrize("dist", DISTS, ids=lambda d: f"{type(d).__name__}-{d.anisotropic}")
def test_projected_area_normalisation_and_smith_identity(dist):
    """int D(h) h_z dw_h = 1 (Walter 2007 eq. 4) and, for the Smith G1 of the same
    distribution, int G1(wo, h) max(0, wo.h) D(h) dw_h = cos(theta_o) (Heitz 2014 eq. 2)."""
    for alpha in (0.01, 0.05, 0.3, 1.0):
        p, width = params_for(dist, alpha)
        h, W = (jnp.asarray(a) for a in hemisphere_quadrature(width))
        d = dist.D(p, h)
        assert float(jnp.sum(d * h[:, 2] * W)) == pytest.approx(1.0, abs=1e-6)
        for theta in (0.0, 0.7, 1.3, 1.5):
            wo = jnp.broadcast_to(direction(theta), h.shape)
            proj = jnp.sum(jnp.maximum(jnp.sum(h * wo, -1), 0.0) * dist.G1(p, wo, h) * d * W)
            assert float(proj) / np.cos(theta) == pytest.approx(1.0, abs=1e-3)


def test_smith_identity_fails_with_the_wrong_lambda():
    """Negative control: Beckmann D with the GGX Lambda violates Heitz eq. 2 by >1%, so the
    identity test above can tell a wrong Lambda from the right one."""
    p, _ = params_for(Beckmann(), 0.5)
    h, W = (jnp.asarray(a) for a in hemisphere_quadrature(0.5))
    wo = jnp.broadcast_to(direction(1.3), h.shape)
    d = Beckmann().D(p, h)
    proj = jnp.sum(jnp.maximum(jnp.sum(h * wo, -1), 0.0) * GGX().G1(p, wo, h) * d * W)
    assert abs(float(proj) / np.cos(1.3) - 1.0) > 0.01


def test_lambda_closed_forms_and_limits():
    thetas = np.concatenate([[0.0], np.linspace(0.05, 1.5, 30), [np.pi / 2 - 1e-4]])
    w = jnp.stack([direction(t) for t in thetas])
    for alpha in (0.05, 0.3, 1.0):
        p = {"alpha": jnp.asarray(alpha)}
        a = 1.0 / (alpha * np.tan(thetas[1:]))
        lam_ggx = np.asarray(GGX().Lambda(p, w))
        lam_beck = np.asarray(Beckmann().Lambda(p, w))
        # Walter et al. 2007, eqs. 27 and 34 (in Lambda form), evaluated independently.
        ref_ggx = 0.5 * (-1 + np.sqrt(1 + 1 / a**2))
        ref_beck = 0.5 * (erf(a) - 1) + np.exp(-(a**2)) / (2 * a * np.sqrt(np.pi))
        np.testing.assert_allclose(lam_ggx[1:], ref_ggx, rtol=1e-10, atol=1e-300)
        np.testing.assert_allclose(lam_beck[1:], ref_beck, rtol=1e-7, atol=1e-14)
        # Normal incidence: no masking. Longer GGX tails mask more than Beckmann everywhere.
        assert lam_ggx[0] == 0.0 and lam_beck[0] == 0.0
        assert np.all(lam_ggx[1:] >= lam_beck[1:])
        # Grazing asymptotes (a -> 0): Lambda + 1/2 = 1/(2a) (1 + O(a^2)) for GGX and
        # 1/(2 a sqrt(pi)) (1 + O(a^2)) for Beckmann.
        assert (lam_ggx[-1] + 0.5) * 2 * a[-1] == pytest.approx(1.0, rel=1e-5)
        assert (lam_beck[-1] + 0.5) * 2 * a[-1] * np.sqrt(np.pi) == pytest.approx(1.0, rel=1e-5)
        # Near the normal (a >= 20) GGX decays like 1/(4 a^2), Beckmann like exp(-a^2).
        assert lam_ggx[1] * 4 * a[0] ** 2 == pytest.approx(1.0, rel=1e-2)
        assert lam_beck[1] < 1e-40


def test_anisotropic_lambda_uses_projected_roughness():
    """Lambda_aniso(w) = Lambda_iso(w) at alpha(phi) = sqrt(cos^2 phi a_u^2 + sin^2 phi a_v^2)
    (Heitz 2014, sec. 5.3)."""
    au, av = 0.6, 0.1
    for phi in (0.0, 0.4, 1.2, np.pi / 2, 2.5):
        a_phi = np.sqrt(np.cos(phi) ** 2 * au**2 + np.sin(phi) ** 2 * av**2)
        w = jnp.stack([direction(t, phi) for t in (0.3, 1.0, 1.5)])
        for cls in (GGX, Beckmann):
            aniso = cls(anisotropic=True).Lambda(
                {"alpha_u": jnp.asarray(au), "alpha_v": jnp.asarray(av)}, w
            )
            iso = cls().Lambda({"alpha": jnp.asarray(a_phi)}, w)
            np.testing.assert_allclose(aniso, iso, rtol=1e-12)


def test_shadowing_ordering_and_range():
    rng = np.random.default_rng(1)
    th = rng.uniform(0, np.pi / 2, (2, 200))
    ph = rng.uniform(0, 2 * np.pi, (2, 200))
    wi = jnp.stack(
        [np.sin(th[0]) * np.cos(ph[0]), np.sin(th[0]) * np.sin(ph[0]), np.cos(th[0])], -1
    )
    wo = jnp.stack(
        [np.sin(th[1]) * np.cos(ph[1]), np.sin(th[1]) * np.sin(ph[1]), np.cos(th[1])], -1
    )
    wh = (wi + wo) / jnp.linalg.norm(wi + wo, axis=-1, keepdims=True)
    for dist in (GGX(), Beckmann()):
        p = {"alpha": jnp.asarray(0.4)}
        g1i, g1o = dist.G1(p, wi, wh), dist.G1(p, wo, wh)
        g_hc = SmithHeightCorrelated().G(dist, p, wi, wo, wh)
        g_sep = SmithSeparable().G(dist, p, wi, wo, wh)
        np.testing.assert_allclose(g_sep, g1i * g1o, rtol=1e-12)
        np.testing.assert_allclose(
            g_hc, 1 / (1 + dist.Lambda(p, wi) + dist.Lambda(p, wo)), rtol=1e-12
        )
        # Heitz 2014 sec. 6: G1 G1 <= G2_height-correlated <= min(G1(wi), G1(wo)).
        assert bool(jnp.all(g_sep <= g_hc + 1e-12))
        assert bool(jnp.all(g_hc <= jnp.minimum(g1i, g1o) + 1e-12))
    hz, d = wh[:, 2], jnp.sum(wo * wh, -1)
    ref = jnp.minimum(1.0, jnp.minimum(2 * hz * wo[:, 2] / d, 2 * hz * wi[:, 2] / d))
    np.testing.assert_allclose(VGroove().G(GGX(), {}, wi, wo, wh), ref, rtol=1e-12)


def _edge_eval(alpha, w, wh):
    """D, G1, c Lambda, a visibility and their gradients for every distribution (one jit)."""
    out = []
    for dist in DISTS:
        p = {"alpha_u": alpha, "alpha_v": alpha[::-1]} if dist.anisotropic else {"alpha": alpha}

        def total(p, w, wh, dist=dist):
            vis = SmithHeightCorrelated().visibility(dist, p, w, w[::-1], wh)
            return dist.D(p, wh).sum() + dist.G1(p, w, wh).sum() + 1e-10 * vis.sum()

        vals = (dist.D(p, wh), dist.G1(p, w, wh), dist.cos_lambda(p, w))
        out.append((vals, jax.grad(total, argnums=(0, 1, 2))(p, w, wh)))
    return out


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_values_and_gradients_finite_at_edges(dtype):
    """alpha from 1e-4 to 1, h along the normal and at the horizon, w at cos 0 and 1e-6."""
    w = jnp.asarray(
        [[0, 0, 1], [1, 0, 0], [np.sqrt(1 - 1e-12), 0, 1e-6], [0.6, 0.0, 0.8], [0, 1, 0]], dtype
    )
    wh = jnp.asarray([[0, 0, 1], [0, 0, 1], [1e-6, 0, 1], [0.6, 0, 0.8], [0, 1e-3, 1]], dtype)
    wh = wh / jnp.linalg.norm(wh, axis=-1, keepdims=True)
    alpha = jnp.asarray([ALPHA_MIN, ALPHA_MIN, 1e-3, 0.5, 1.0], dtype)
    for leaf in jax.tree_util.tree_leaves(jax.jit(_edge_eval)(alpha, w, wh)):
        assert leaf.dtype == dtype
        assert bool(jnp.all(jnp.isfinite(leaf))), leaf
    # At alpha = 1e-4, h = normal: D = 1/(pi alpha^2) ~ 3.2e7 in float32 too.
    d = GGX().D({"alpha": jnp.asarray([ALPHA_MIN], dtype)}, jnp.asarray([[0, 0, 1]], dtype))
    assert float(d[0]) == pytest.approx(1 / (np.pi * ALPHA_MIN**2), rel=1e-5)
    # Below the floor alpha is held at 1e-4 (documented), so D stops growing.
    d0 = GGX().D({"alpha": jnp.asarray([0.0], dtype)}, jnp.asarray([[0, 0, 1]], dtype))
    assert float(d0[0]) == float(d[0])


@pytest.mark.parametrize("shadowing", ["smith_height_correlated", "smith_separable"])
def test_both_cosines_at_the_horizon_give_finite_gradients(shadowing):
    """wi = wo within 1e-298 of the horizon with a narrow anisotropic Beckmann lobe: D = 0
    and 1/den overflows in the gradient unless den is floored (hypothesis found it)."""
    m = brdf.get(
        "cook_torrance",
        distribution="beckmann",
        anisotropic=True,
        shadowing=shadowing,
        fresnel="schlick",
    )
    p = {
        "specular": jnp.asarray([0.97, 0.32, 0.66]),
        "alpha_u": jnp.asarray(2.1e-4),
        "alpha_v": jnp.asarray(0.04),
    }
    wi = jnp.asarray([1.0, 0.0, 1.0180281434065522e-298])
    for name in ("alpha_u", "alpha_v", "specular"):
        g = jax.grad(lambda x, n=name: jnp.sum(m.eval({**p, n: x}, wi, wi)))(p[name])
        assert np.all(np.isfinite(np.asarray(g))), (name, g)
    assert np.all(np.isfinite(np.asarray(m.eval(p, wi, wi))))

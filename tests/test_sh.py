"""Nine-term spherical-harmonic irradiance (Ramamoorthi & Hanrahan 2001)."""

import jax.numpy as jnp
import numpy as np
from scipy import integrate

import jaxrefl
from jaxrefl import scene

LAMBERT = jaxrefl.brdf.get("lambert")


def _normals(k=40, seed=0):
    n = np.random.default_rng(seed).normal(size=(k, 3))
    n = np.concatenate([n, [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0]]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _sky(h):
    """L = max(cos theta, 0) sampled at the texel centres of an h x 2h map."""
    th = (np.arange(h) + 0.5) * np.pi / h
    return np.broadcast_to(np.maximum(np.cos(th), 0.0)[:, None, None], (h, 2 * h, 1))


def _sky_irradiance(t):
    """Exact irradiance of a normal tilted by t under the clamped-cosine sky:
    int max(w.z, 0) max(w.n, 0) dw = (2/3)((pi - t) cos t + sin t) (checked below)."""
    return 2.0 / 3.0 * ((np.pi - t) * np.cos(t) + np.sin(t))


def test_constants_are_the_papers():
    # Ramamoorthi & Hanrahan 2001 eq. 12 prints c1..c5 rounded from rounded Y_lm constants;
    # ours are computed from the definitions and agree to the printed digits (within 1.2e-6).
    paper = (0.429043, 0.511664, 0.743125, 0.886227, 0.247708)
    np.testing.assert_allclose(scene.SH_CONSTANTS, paper, atol=1.5e-6)


def test_basis_is_orthonormal():
    d, domega, _ = scene.EnvironmentMap(jnp.ones((64, 128, 1))).texels()
    y = scene.sh_basis(d)
    gram = jnp.einsum("hwi,hwj,hw->ij", y, y, domega)
    np.testing.assert_allclose(gram, np.eye(9), atol=1e-3)  # midpoint rule, measured 4e-4


def test_constant_environment_gives_pi_L_for_every_normal():
    # Texels are integrated exactly, so a constant map projects to L00 = 2 sqrt(pi) L only.
    lum = jnp.array([2.0, 0.5])
    for h in (4, 16):
        c = scene.sh_project(jnp.broadcast_to(lum, (h, 2 * h, 2)))
        assert c.shape == (9, 2)
        np.testing.assert_allclose(c[0], 2 * np.sqrt(np.pi) * lum, rtol=1e-14)
        np.testing.assert_allclose(c[1:], 0.0, atol=1e-14)
        e = scene.sh_irradiance(c, _normals())
        np.testing.assert_allclose(e, np.broadcast_to(np.pi * lum, e.shape), rtol=1e-13)


def test_sky_closed_form_and_nine_term_error():
    t = 1.0
    n = np.array([np.sin(t), 0.0, np.cos(t)])

    def integrand(ph, th):
        w = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
        return np.cos(th) * max(w @ n, 0.0) * np.sin(th)

    ref, _ = integrate.dblquad(integrand, 0, np.pi / 2, 0, 2 * np.pi, epsabs=1e-11)
    np.testing.assert_allclose(_sky_irradiance(t), ref, rtol=1e-8)

    ts = np.linspace(0, np.pi, 37)
    nrm = np.stack([np.sin(ts), 0 * ts, np.cos(ts)], -1)
    exact = _sky_irradiance(ts)
    env = scene.EnvironmentMap(_sky(64))
    e_sh = np.asarray(scene.sh_irradiance(scene.sh_project(env), nrm))[:, 0]
    err = np.abs(e_sh - exact) / exact[0]
    # The clamped-cosine sky has energy beyond l = 2 (l = 4, 6, ...), which nine terms drop:
    # measured max error 0.79% of E(0) (converged in H: 0.80% at H = 32, 0.78% at 256) and
    # mean relative error 0.33% over the upper hemisphere, within the paper's "< 3%".
    assert err.max() < 0.01
    assert err.max() > 1e-3  # the truncation is real: the test would see a wrong constant
    up = ts <= np.pi / 2
    assert np.mean(np.abs(e_sh - exact)[up] / exact[up]) < 0.005
    # Brute-force quadrature of the same map converges to the exact value (O(1/H^2)).
    d, domega, lum = (np.asarray(a) for a in env.texels())
    e_bf = np.einsum("hwk,nk->nhw", d, nrm).clip(0) * domega * lum[None, ..., 0]
    assert np.abs(e_bf.sum((1, 2)) - exact).max() / exact[0] < 5e-4  # measured 2.3e-4


def test_sh_agrees_with_brute_force_lambert_rendering():
    # Radiance with harmonics up to l = 2 only (a positive quadratic in the direction):
    # nine terms are then exact and the two sides differ by the brute force's quadrature.
    nrm = _normals(11, seed=4)
    nrm = nrm[np.abs(nrm[:, 2]) > 0.1]
    nrm = (nrm * np.where(nrm[:, 2:3] < 0, -1.0, 1.0))[None]  # (1, k, 3), facing the camera
    albedo = jnp.array([0.3, 0.6, 0.9])
    cam = scene.OrthographicCamera()
    errs = []
    for h in (16, 32):
        d, _, _ = scene.EnvironmentMap(jnp.ones((h, 2 * h, 1))).texels()
        x, y, z = (np.asarray(d[..., i]) for i in range(3))
        img = np.stack(
            [1.0 + 0.5 * x - 0.3 * z + 0.4 * x * y, 1.0 + 0.8 * z * z, 1.5 - 0.6 * y * z], -1
        )
        env = scene.EnvironmentMap(img)
        sh = scene.sh_lambert(scene.sh_project(env), nrm, albedo)
        bf = scene.render(
            LAMBERT, {"albedo": albedo}, env, cam, points=jnp.zeros(nrm.shape), normals=nrm,
            cos4=False,
        )  # fmt: skip
        assert bf.shape == (1, *sh.shape)
        errs.append(np.abs(np.asarray(bf[0]) / np.asarray(sh) - 1).max())
    assert errs[1] < 2e-3  # measured 1.2e-3 (4.8e-3 at h = 16)
    assert 3.0 < errs[0] / errs[1] < 5.0  # second-order quadrature error: the model is exact


def test_rotated_environment_rotates_the_irradiance():
    rot = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # map -> world
    sky = _sky(16)
    n = _normals()
    e0 = scene.sh_irradiance(scene.sh_project(scene.EnvironmentMap(sky)), n)
    e1 = scene.sh_irradiance(scene.sh_project(scene.EnvironmentMap(sky, rotation=rot)), n @ rot.T)
    np.testing.assert_allclose(e1, e0, atol=1e-12)

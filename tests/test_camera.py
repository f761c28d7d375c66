"""Cameras (view directions, cos^4 falloff) and response curves."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import scene

RESPONSES = [
    scene.LinearResponse(clip=False),
    scene.SRGBResponse(clip=False),
    scene.GammaResponse(clip=False),
    scene.GammaResponse(1.8, exposure=3.0, clip=False),
    scene.TabulatedResponse([0.0, 0.1, 0.5, 1.0], [0.0, 0.3, 0.8, 1.0], clip=False),
]


def test_srgb_reference_values():
    # IEC 61966-2-1: y = 1.055 x^(1/2.4) - 0.055 above x = 0.0031308, 12.92 x below.
    r = scene.SRGBResponse()
    np.testing.assert_allclose(r.apply(0.5), 0.7353569830524495, rtol=1e-15)
    np.testing.assert_allclose(r.apply(0.0031308), 12.92 * 0.0031308, rtol=1e-15)
    np.testing.assert_allclose(r.apply(0.002), 12.92 * 0.002, rtol=1e-15)
    np.testing.assert_allclose(r.apply(jnp.array([0.0, 1.0])), [0.0, 1.0], atol=1e-15)
    # The two branches meet at the threshold (to the standard's 5 digits).
    above = 1.055 * 0.0031308 ** (1 / 2.4) - 0.055
    assert abs(above - 12.92 * 0.0031308) < 1e-7
    np.testing.assert_allclose(r.invert(0.04045), 0.04045 / 12.92, rtol=1e-15)
    np.testing.assert_allclose(r.invert(0.7353569830524495), 0.5, rtol=1e-14)
    # Gradients finite on both sides of the threshold and at 0.
    g = jax.vmap(jax.grad(r.apply))(jnp.array([0.0, 0.0031308, 0.0031309, 0.5]))
    np.testing.assert_allclose(g[:2], 12.92)
    np.testing.assert_allclose(g[3], 1.055 / 2.4 * 0.5 ** (1 / 2.4 - 1), rtol=1e-14)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("resp", RESPONSES, ids=lambda r: type(r).__name__)
def test_apply_invert_round_trip(resp, dtype):
    x = jnp.concatenate([jnp.linspace(0.0, 0.3, 101), jnp.array([0.0031308, 1e-6])]).astype(dtype)
    y = resp.apply(x)
    assert y.dtype == dtype
    assert np.all(np.diff(np.asarray(y[:101])) > 0)  # strictly increasing
    back = resp.invert(y)
    assert back.dtype == dtype
    tol = 3e-6 if dtype == jnp.float32 else 1e-12
    np.testing.assert_allclose(back, x, rtol=tol, atol=tol * 1e-3)
    np.testing.assert_allclose(resp.apply(resp.invert(y)), y, rtol=tol, atol=tol * 1e-3)


def test_exposure_and_clipping():
    x = jnp.array([0.1, 0.5, 2.0])
    clipped, raw = scene.GammaResponse(exposure=2.0), scene.GammaResponse(exposure=2.0, clip=False)
    np.testing.assert_allclose(raw.apply(x), (2.0 * x) ** (1 / 2.2), rtol=1e-15)
    np.testing.assert_allclose(clipped.apply(x), np.minimum((2.0 * x) ** (1 / 2.2), 1.0))
    assert float(clipped.apply(-0.1)) == 0.0
    np.testing.assert_allclose(raw.invert(raw.apply(x)), x, rtol=1e-14)
    # Clipped values are censored: their gradient is zero, the others' is not.
    g = jax.grad(lambda v: clipped.apply(v).sum())(x)
    assert g[2] == 0.0 and np.all(g[:2] > 0)


def test_gamma_is_gradient_safe_at_zero():
    r = scene.GammaResponse(clip=False)
    for f in (r.apply, r.invert):
        g = jax.vmap(jax.grad(f))(jnp.array([0.0, -0.0, 1e-30, -0.2]))
        assert np.all(np.isfinite(g))
    np.testing.assert_allclose(r.apply(-0.25), -(0.25 ** (1 / 2.2)), rtol=1e-15)
    g_gamma = jax.grad(lambda gm: scene.GammaResponse(gm, clip=False).apply(0.5))(2.2)
    np.testing.assert_allclose(g_gamma, 0.5 ** (1 / 2.2) * np.log(0.5) * (-1 / 2.2**2), rtol=1e-12)


def test_tabulated_response_interpolates_and_validates():
    r = scene.TabulatedResponse([0.0, 0.5, 1.0], [0.0, 0.8, 1.0])
    np.testing.assert_allclose(r.apply(jnp.array([0.25, 0.75, 1.5])), [0.4, 0.9, 1.0])
    np.testing.assert_allclose(r.invert(jnp.array([0.4, 0.9])), [0.25, 0.75])
    with pytest.raises(ValueError, match=r"strictly increasing y; y\[1\] = 0.8 >= y\[2\] = 0.7"):
        scene.TabulatedResponse([0.0, 0.5, 1.0], [0.0, 0.8, 0.7])
    with pytest.raises(ValueError, match="strictly increasing x"):
        scene.TabulatedResponse([0.0, 0.5, 0.5], [0.0, 0.8, 0.9])
    with pytest.raises(ValueError, match="same length"):
        scene.TabulatedResponse([0.0, 1.0], [0.0, 0.5, 1.0])


def test_cos4_falloff_and_pinhole_camera():
    cam = scene.PinholeCamera([0.0, 0.0, 2.0])  # looks at the origin
    np.testing.assert_allclose(cam.axis, [0.0, 0.0, -1.0])
    pts = jnp.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 3.0]])
    f = cam.falloff(pts)
    # On axis 1; lateral offset d at depth h: h^4/(h^2 + d^2)^2; behind the camera 0.
    np.testing.assert_allclose(f, [1.0, 0.25, 16.0 / 36.0, 0.0], rtol=1e-14)
    np.testing.assert_allclose(
        scene.cos4_falloff(pts, jnp.array([0.0, 0.0, 2.0]), jnp.array([0.0, 0.0, -1.0])), f
    )
    wo = cam.view_direction(pts[:3])
    np.testing.assert_allclose(wo[1], np.array([-2.0, 0.0, 2.0]) / np.sqrt(8.0), rtol=1e-14)
    tilted = scene.PinholeCamera([1.0, 0.0, 2.0], axis=[0.0, 0.0, -2.0])
    np.testing.assert_allclose(tilted.falloff(jnp.array([[1.0, 0.0, 0.0]])), [1.0])
    with pytest.raises(ValueError, match="either"):
        scene.PinholeCamera([0.0, 0.0, 1.0], look_at=[0.0, 0.0, 0.0], axis=[0.0, 0.0, -1.0])
    ortho = scene.OrthographicCamera([0.0, 0.0, 2.0])
    np.testing.assert_allclose(ortho.view_direction(pts), np.tile([0.0, 0.0, 1.0], (4, 1)))
    np.testing.assert_allclose(ortho.falloff(pts), 1.0)

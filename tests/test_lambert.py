import jax
import jax.numpy as jnp
import numpy as np

import jaxrefl


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

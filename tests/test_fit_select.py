"""keep_lower (jaxrefl/fit/_select.py): per pixel the candidate of lower cost, on pytrees."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxrefl.fit._select import keep_lower


def test_keep_lower_per_pixel():
    nan, inf = np.nan, np.inf
    cost_a = jnp.asarray([1.0, 2.0, nan, 3.0, 1.0, 5.0])
    cost_b = jnp.asarray([0.5, 2.0, 4.0, nan, inf, 4.0])
    params_a = {"theta": jnp.zeros((6, 2)), "status": jnp.zeros(6, jnp.int32)}
    params_b = {"theta": jnp.ones((6, 2)), "status": jnp.ones(6, jnp.int32)}
    cost, params = keep_lower(cost_a, params_a, cost_b, params_b)
    # lower wins; a tie keeps the first; a NaN first loses; a non-finite second never wins
    take_b = np.array([True, False, True, False, False, True])
    np.testing.assert_array_equal(np.asarray(params["status"]), take_b.astype(np.int32))
    np.testing.assert_array_equal(np.asarray(params["theta"]), np.repeat(take_b, 2).reshape(6, 2))
    np.testing.assert_array_equal(np.asarray(cost), np.where(take_b, cost_b, cost_a))
    assert params["status"].dtype == jnp.int32
    # ``where`` limits which pixels may take the second candidate
    only = np.array([False, True, True, True, True, True])
    _, params = keep_lower(cost_a, params_a, cost_b, params_b, where=only)
    np.testing.assert_array_equal(np.asarray(params["status"]), take_b & only)

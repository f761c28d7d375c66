"""Small batches of different sizes share one compiled solver: ``fit.batched_lm`` pads a
batch of fewer than 256 pixels to a power of two (at least 16) and ``fit.initial_theta``
pads a small variable-projection batch to a power-of-two number of blocks, with copies of
pixel 0 cut off after. A pixel's result does not depend on the batch it came in."""

from __future__ import annotations

import logging

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl import brdf, fit


def _data(n: int, k: int = 8):
    rng = np.random.default_rng(0)
    wi = rng.normal(size=(n, k, 3)) * [1, 1, 0] + [0, 0, 2.0]
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    albedo = rng.uniform(0.2, 0.8, (n, 1, 3))
    spec = rng.uniform(0.02, 0.1, (n, 1, 1))
    return fit.pixel_data(jnp.asarray(albedo / np.pi + spec * wi[..., 2:] ** 8), jnp.asarray(wi))


def _lowered(caplog, name: str) -> int:
    """How many programs named ``name`` were lowered (then compiled or read from the
    persistent cache); a program already in this process's memory is not lowered again."""
    return sum(f"Compiling jit({name})" in r.getMessage() for r in caplog.records)


def test_batch_sizes_share_the_compiled_start_and_solver(caplog):
    model = brdf.get("lambert")
    space = fit.ParamSpace(model)
    res = fit.make_residual(model, space)
    d5 = _data(5)
    d3 = jax.tree.map(lambda x: x[:3], d5)
    t5 = fit.initial_theta(res, d5)
    x5, r5 = fit.batched_lm(res, t5, d5, space=space)
    with jax.log_compiles(True), caplog.at_level(logging.WARNING):
        t3 = fit.initial_theta(res, d3)
        x3, r3 = fit.batched_lm(res, t3, d3, space=space)
    # Three pixels run the programs compiled for five: nothing new is lowered.
    assert _lowered(caplog, "_initial_theta_jit") == 0
    assert _lowered(caplog, "_batched_lm") == 0
    # The padding is cut off, and the first three pixels get the same answers either way.
    assert t3.shape == (3, space.size) and x3.shape == (3, space.size)
    assert r3.status.shape == (3,) and isinstance(x3, jax.Array)
    np.testing.assert_array_equal(t3, t5[:3])
    np.testing.assert_array_equal(x3, x5[:3])
    np.testing.assert_array_equal(r3.status, r5.status[:3])
    np.testing.assert_array_equal(r3.iterations, r5.iterations[:3])

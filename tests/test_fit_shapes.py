"""Batches of different sizes share one compiled start: ``fit.initial_theta`` pads a
variable-projection batch to a power-of-two number of blocks (a multiple of 16 blocks for
large batches) with copies of pixel 0, cut off after. A pixel's start does not depend on
the batch it came in."""

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


def test_batch_sizes_share_the_compiled_start(caplog):
    model = brdf.get("lambert")
    space = fit.ParamSpace(model)
    res = fit.make_residual(model, space)
    d5 = _data(5)
    d3 = jax.tree.map(lambda x: x[:3], d5)
    t5 = fit.initial_theta(res, d5)
    with jax.log_compiles(True), caplog.at_level(logging.WARNING):
        t3 = fit.initial_theta(res, d3)
    # Three pixels run the program compiled for five: nothing new is lowered.
    assert _lowered(caplog, "_initial_theta_jit") == 0
    # The padding is cut off, and the first three pixels start the same either way.
    assert t3.shape == (3, space.size) and isinstance(t3, jax.Array)
    np.testing.assert_array_equal(t3, t5[:3])

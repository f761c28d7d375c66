"""Spread a batch of independent pixels over the devices of this process.

Pixels are independent problems, so the batch axis is split into equal contiguous shards, one
per device (``jax.shard_map`` over a 1-D mesh named ``"pixels"``); each device runs the same
solver on its shard, and no communication is needed. The batch is padded to a multiple of the
device count with copies of its last pixel, which are dropped afterwards.

No step of a pixel reads another pixel (the lean LM freezes converged pixels; see ``_lm``),
so the results equal those of one device *up to rounding*, not bit for bit: XLA compiles
each batch shape on its own, and its fusion choices, hence how the sums over a pixel's
observations are rounded, depend on the shape (the starting points (``_init``) are padded
to a few shapes; the LM and the Laplace step on equal inputs can differ in the last bit
between layouts). Statuses
and Laplace flags are decided far above that rounding (the status thresholds; the Laplace
step's condition test, ``_laplace``), so they agree between layouts, and converged pixels
agree to rounding in theta and cost. An iterate that has not converged carries the rounding
of its path further: a pixel stopped by the iteration limit (MAX_ITERATIONS, or AT_BOUND,
which takes precedence) can differ visibly in a poorly determined parameter at equal cost.

In a multi-process job (:class:`jaxrefl.fit.Distributed`) the mesh holds this process's
own devices (``jax.local_devices()``): the processes split the work among themselves
(tiles, MCMC chunks), and each spreads its share over its devices.

On the CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` (set before JAX starts)
gives two host devices: that is how the tests check it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

__all__ = ["device_count", "map_sharded"]


def device_count(devices: int | None = None) -> int:
    """The number of this process's devices to use: ``devices`` (clipped to what exists) or
    all of them."""
    n = jax.local_device_count()
    return n if devices is None else max(1, min(int(devices), n))


def map_sharded(fn: Callable[..., Any], args: tuple, n_devices: int) -> Any:
    """``fn(*args)`` with every array leaf of ``args`` split along axis 0 over ``n_devices``.

    ``fn`` maps batched inputs (leading axis N) to batched outputs (leading axis N).
    """
    leaves = [x for x in jax.tree.leaves(args) if hasattr(x, "shape")]
    n = int(leaves[0].shape[0])
    if n_devices <= 1 or n < n_devices:
        return fn(*args)
    pad = (-n) % n_devices

    def padded(x):
        if not hasattr(x, "shape") or pad == 0:
            return x
        return jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)], axis=0)

    args = jax.tree.map(padded, args)
    out = _sharded(fn, n_devices)(*args)
    return jax.tree.map(lambda x: x[:n], out)


def _sharded(fn: Callable[..., Any], n_devices: int) -> Callable[..., Any]:
    """``fn`` under ``shard_map`` over this process's first ``n_devices``, jitted.

    JAX compiles per function object, and ``shard_map`` makes a new one at every call: the
    result is kept on ``fn`` itself (freed with it), so that a caller passing the same
    ``fn`` again (one sampler for every MCMC chunk) compiles it once."""
    cache = getattr(fn, "_jaxrefl_sharded", None)
    if cache is None:
        cache = {}
        try:
            fn._jaxrefl_sharded = cache  # type: ignore[attr-defined]
        except AttributeError:  # e.g. a bound method: compiled at each call
            pass
    if n_devices not in cache:
        mesh = Mesh(np.asarray(jax.local_devices()[:n_devices]), ("pixels",))
        spec = PartitionSpec("pixels")
        # Checking replication is irrelevant here (nothing is replicated); it also does not
        # know every primitive of the solver.
        sharded = jax.shard_map(fn, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)
        cache[n_devices] = jax.jit(sharded)
    return cache[n_devices]

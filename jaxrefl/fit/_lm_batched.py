"""``batched_lm``: the lean Levenberg-Marquardt over N independent pixels, in blocks.

The pixels go in blocks of ``LMOptions.chunk`` (the last padded with copies of pixel 0);
each block is solved by the host scheduler (:mod:`._lm_host`) when called outside a trace
with ``LMOptions.host_loop``, else by the in-trace scheduler (:mod:`._lm_staged`), all
blocks as one compiled program.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Float, Int

from ._lm import LMOptions, LMResult
from ._lm_host import _solve_host
from ._lm_staged import _solve_block
from ._transform import ParamSpace

__all__ = ["batched_lm"]

ResidualFn = Callable[[Array, Any], Array]


def batched_lm(
    residual_fn: ResidualFn,
    theta0: Float[Array, "N P"],
    data: Any,
    options: LMOptions | None = None,
    *,
    space: ParamSpace | None = None,
    n_usable: Int[Array, " N"] | None = None,
) -> tuple[Float[Array, "N P"], LMResult]:
    """``lm_solve`` over N independent pixels; ``data`` has a leading N axis on every leaf,
    ``n_usable`` is (N,) or None.

    Equivalent to ``jit(vmap(lm_solve))`` up to float rounding (which can move poorly
    determined parameters along flat valleys in float32), organised for speed: all pixels
    take the first ``options.compact_after`` steps, then only the still-unconverged pixels,
    gathered into fewer slots, take the remaining ones. Outside a trace, with
    ``options.host_loop``, each step is its own compiled program driven from Python
    (:func:`_solve_host`); inside one, the steps are loops of one program with the slots of
    ``options.compact_stages`` (:func:`_solve_block`). Either way pixels go in blocks of
    ``options.chunk``.
    """
    options = LMOptions() if options is None else options
    n = theta0.shape[0]
    nu = jnp.full((n,), jnp.iinfo(jnp.int32).max, jnp.int32) if n_usable is None else n_usable
    leaves = jax.tree.leaves((residual_fn, theta0, data, nu))
    if options.host_loop and not any(isinstance(x, jax.core.Tracer) for x in leaves):
        if n <= options.chunk:
            return _solve_host(residual_fn, theta0, data, nu, options, space)
        # One block after the other, each driven from Python.
        args = _blocks((theta0, data, nu), options.chunk)
        parts = []
        for i in range(args[0].shape[0]):
            t, d, u = jax.tree.map(lambda x, i=i: x[i], args)
            parts.append(_solve_host(residual_fn, t, d, u, options, space))
        out = jax.tree.map(lambda *xs: jnp.stack(xs), *parts)
    else:
        out = _batched_lm_graph(residual_fn, theta0, data, nu, options, space)
    return jax.tree.map(lambda x: x.reshape((-1, *x.shape[2:]))[:n], out)


def _blocks(args, chunk: int):
    """Every leaf of ``args`` (leading axis N) as (blocks, chunk', ...), chunk' = min(chunk,
    N): blocks of pixels whose working set stays in cache. The last block is padded with
    copies of pixel 0 (their results are cut off after), so every block runs the same
    compiled programs."""
    n = jax.tree.leaves(args)[0].shape[0]
    chunk = max(1, min(chunk, n))
    blocks = -(-n // chunk)
    pad = blocks * chunk - n

    def padded(x):
        x = jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad, *x.shape[1:]))]) if pad else x
        return x.reshape((blocks, chunk, *x.shape[1:]))

    return jax.tree.map(padded, args)


@eqx.filter_jit
def _batched_lm_graph(residual_fn, theta0, data, n_usable, options, space):
    """:func:`batched_lm` as one compiled program, block by block (``lax.map``), each
    solved by :func:`_solve_block`; results (blocks, chunk, ...)."""

    def block(a):
        theta_b, data_b, nu_b = a
        return _solve_block(residual_fn, theta_b, data_b, nu_b, options, space)

    return lax.map(block, _blocks((theta0, data, n_usable), options.chunk))

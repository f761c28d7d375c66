"""The in-trace scheduler of :func:`~jaxrefl.fit.batched_lm`: a block of pixels as loops of
one compiled program, the unconverged pixels gathered into ever fewer slots.

Used where ``batched_lm`` is called inside a trace (``jit``, ``shard_map``) or without
``LMOptions.host_loop``; :func:`_solve_block` solves one block, stage by stage
(``LMOptions.compact_stages``). A converged pixel is frozen, so every pixel takes the same
steps as :func:`~jaxrefl.fit.lm_solve` alone. :func:`_steps_until_converged` is also the
inner loop of the host scheduler's fused rounds (:mod:`._lm_host`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

from . import _lm
from ._lm import LMOptions, _finish, lm_init, lm_step


def _steps(residual_fn, states, data, options, n):
    """n steps of vmap(lm_step) over a block of pixels."""
    step = jax.vmap(lambda s, d: lm_step(residual_fn, s, d, options)[0])
    return lax.scan(lambda s, _: (step(s, data), None), states, None, length=n)[0]


def _steps_until_converged(residual_fn, states, data, options, n):
    """Up to n steps of vmap(lm_step), stopping once every pixel has converged (they are
    frozen then, so the steps skipped would change nothing): a round of stragglers costs
    its slowest pixel's steps, not the stage's."""
    step = jax.vmap(lambda s, d: lm_step(residual_fn, s, d, options)[0])

    def cond(carry):
        k, s = carry
        return (k < n) & ~jnp.all(s.converged)

    return lax.while_loop(cond, lambda c: (c[0] + 1, step(c[1], data)), (0, states))[1]


def _stages(b: int, options: LMOptions) -> tuple[int, list[tuple[int, int]]]:
    """(steps every pixel takes, [(until, slots)] of the compaction stages) for a block of
    b pixels; no stages means one plain loop of up to ``max_iters`` steps (see
    :func:`_solve_block`)."""
    done = min(options.compact_after, options.max_iters)
    stages = [
        (min(u, options.max_iters), max(1, math.ceil(b * f))) for u, f in options.compact_stages
    ]
    # Stages narrower than _MIN_COMPACT slots are not worth a compiled copy of the step:
    # the stage before them runs on to their end instead.
    stages = [(u, c) for u, c in stages if u > done and c >= _lm._MIN_COMPACT]
    if stages:
        stages[-1] = (options.max_iters, stages[-1][1])
    if b < _lm._MIN_BLOCK or not stages:
        # A small block is not worth more compiled copies of the step (compile time).
        return 0, []
    return done, stages


def _solve_block(residual_fn, theta0, data, n_usable, options, space):
    """lm_solve for a block of B pixels, organised to skip the work of converged pixels.

    All B pixels take the first ``compact_after`` steps. Then come the stages of
    ``compact_stages``, each ``(until, fraction)``: the pixels still unconverged are gathered
    ``cap = fraction * B`` at a time and take the steps up to iteration ``until`` (the last
    stage runs to ``max_iters``), and are scattered back (a while loop over rounds at the
    block level, never inside vmap). The caps shrink with the stages as pixels converge
    (the tail of slow pixels is short but long-running). A converged pixel is frozen, so
    each pixel's result equals ``lm_solve``'s: the same steps, in the same order."""
    b = theta0.shape[0]
    states = jax.vmap(lambda t, d: lm_init(residual_fn, t, d, options))(theta0, data)
    done, stages = _stages(b, options)
    if not stages:
        # One loop of up to max_iters steps for all pixels, stopping when all converged.
        states = _steps_until_converged(residual_fn, states, data, options, options.max_iters)
    else:
        states = _steps(residual_fn, states, data, options, done)
    for until, cap in stages:
        if until <= done:
            continue
        n_steps = until - done

        def todo(states, until=until):
            return ~states.converged & (states.iterations < until)

        def round_(states, until=until, cap=cap, n_steps=n_steps):
            idx = jnp.nonzero(todo(states), size=cap, fill_value=b)[0]
            live = idx < b
            get = jnp.minimum(idx, b - 1)
            sub = jax.tree.map(lambda x: x[get], states)
            # Padding slots (copies of the last pixel) are frozen and dropped on the way
            # back. Every live pixel has taken all ``done`` steps so far (it never
            # converged), so n_steps brings each exactly to ``until``.
            sub = eqx.tree_at(lambda s: s.converged, sub, sub.converged | ~live)
            sub_data = jax.tree.map(lambda x: x[get], data)
            sub = _steps_until_converged(residual_fn, sub, sub_data, options, n_steps)
            return jax.tree.map(lambda x, y: x.at[idx].set(y, mode="drop"), states, sub)

        def any_todo(states, todo=todo):
            return jnp.any(todo(states))

        states = lax.while_loop(any_todo, round_, states)
        done = until
    return jax.vmap(lambda s, t, n: _finish(s, t, options, space, n))(states, theta0, n_usable)

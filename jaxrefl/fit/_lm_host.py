"""The host scheduler of :func:`~jaxrefl.fit.batched_lm`: steps driven from Python, each one
compiled program, the unconverged pixels gathered into slots of two fixed sizes.

Used where ``batched_lm`` is called outside a trace with ``LMOptions.host_loop``
(:func:`_solve_host`); the programs of both slot sizes compile once per block shape and
residual (:func:`_warm`). Every unconverged pixel is in every round, so each takes the same
steps in the same order as :func:`~jaxrefl.fit.lm_solve` alone.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _lm
from ._lm import _finish, lm_init, lm_step
from ._lm_staged import _steps_until_converged


@eqx.filter_jit
def _init_all(residual_fn, theta0, data, options):
    return jax.vmap(lambda t, d: lm_init(residual_fn, t, d, options))(theta0, data)


@eqx.filter_jit
def _step_all(residual_fn, states, data, options):
    return jax.vmap(lambda s, d: lm_step(residual_fn, s, d, options)[0])(states, data)


@eqx.filter_jit
def _gather(states, data, idx, live):
    """The pixels ``idx`` of states and data; slots that are not ``live`` are frozen."""
    sub = jax.tree.map(lambda x: x[idx], states)
    sub = eqx.tree_at(lambda s: s.converged, sub, sub.converged | ~live)
    return sub, jax.tree.map(lambda x: x[idx], data)


@eqx.filter_jit
def _scatter(states, sub, idx):
    """states with pixels ``idx`` replaced by ``sub`` (an index of N or more is dropped)."""
    return jax.tree.map(lambda x, y: x.at[idx].set(y, mode="drop"), states, sub)


@eqx.filter_jit
def _round(residual_fn, states, data, idx, n, options):
    """A gathered round as one program (``host_fused``): the pixels ``idx`` take up to ``n``
    steps (a traced count: one program for any count), stopping once all of them have
    converged, and are scattered back."""
    b = states.theta.shape[0]
    sub, sub_data = _gather(states, data, jnp.minimum(idx, b - 1), idx < b)
    sub = _steps_until_converged(residual_fn, sub, sub_data, options, n)
    return _scatter(states, sub, idx)


@eqx.filter_jit
def _finish_all(states, theta0, n_usable, options, space):
    return jax.vmap(lambda s, t, n: _finish(s, t, options, space, n))(states, theta0, n_usable)


def _slot_sizes(b: int) -> tuple[int, int]:
    """The two slot counts of a gathered round for a block of b pixels: b/16 and b/4 (at
    least ``_MIN_COMPACT``). Two fixed sizes, not the tightest power of two, so the programs a
    block can use do not depend on how its pixels converge: they compile once, before they
    are needed (:func:`_warm`), and a later batch of the same shape compiles nothing."""
    return max(_lm._MIN_COMPACT, b // 16), max(_lm._MIN_COMPACT, b // 4)


def _rounds(todo: np.ndarray, b: int) -> list[np.ndarray] | None:
    """The unconverged pixels ``todo`` split into gathered rounds (slot indices, padded with
    b), or None where stepping the whole block costs no more."""
    small, big = _slot_sizes(b)
    cap = small if todo.size <= small else big
    if -(-todo.size // cap) * cap >= b:
        return None
    out = []
    for i in range(0, todo.size, cap):
        idx = np.full(cap, b, np.int32)
        part = todo[i : i + cap]
        idx[: part.size] = part
        out.append(idx)
    return out


# Blocks whose gathered-round programs have compiled (see _warm).
_WARMED: set = set()


def _warm(residual_fn, states, data, options) -> None:
    """Compile the gathered-round programs of both slot sizes the first time a block of
    this shape and residual is solved in the process: one step (``host_fused``: a round of
    none) on slots that are all padding (frozen, and dropped on the way back), which
    changes nothing."""
    leaves = jax.tree.leaves((residual_fn, data))
    key = (
        jax.tree.structure((residual_fn, data)),
        tuple((x.shape, str(x.dtype)) for x in leaves if hasattr(x, "shape")),
        states.theta.shape,
        str(states.theta.dtype),
        options,
    )
    if key in _WARMED:
        return
    b = states.theta.shape[0]
    for cap in _slot_sizes(b):
        idx = np.full(cap, b, np.int32)
        if options.host_fused:
            zero = jnp.asarray(0, np.int32)
            states = _round(residual_fn, states, data, jnp.asarray(idx), zero, options)
            continue
        sub, sub_data = _gather(
            states, data, jnp.asarray(np.minimum(idx, b - 1)), jnp.asarray(idx < b)
        )
        sub = _step_all(residual_fn, sub, sub_data, options)
        states = _scatter(states, sub, jnp.asarray(idx))
    jax.block_until_ready(states)
    _WARMED.add(key)


def _solve_host(residual_fn, theta0, data, n_usable, options, space):
    """:func:`batched_lm` for all N pixels, driven from Python, each step one compiled
    program. All pixels take the first ``compact_after`` steps; then, in rounds of
    ``host_round`` steps, the unconverged pixels are gathered into slots of one of two fixed
    sizes (:func:`_slot_sizes`), step, and are scattered back, or the whole block steps
    where that costs no more. Every unconverged pixel is in every round, so each takes the
    same steps in the same order as ``lm_solve`` alone. Fewer than ``_MIN_BLOCK`` pixels
    take plain steps (no gathering), until all have converged. ``host_fused``: each round
    is one program (:func:`_round`), and the pixels left when they fit in the smaller slots
    take all their remaining steps in one last round."""
    b = theta0.shape[0]
    states = _init_all(residual_fn, theta0, data, options)
    it = min(options.compact_after, options.max_iters) if b >= _lm._MIN_BLOCK else 0
    for _ in range(it):  # every pixel, converged or not (frozen ones are unchanged)
        states = _step_all(residual_fn, states, data, options)
    if b >= _lm._MIN_BLOCK and it < options.max_iters:
        _warm(residual_fn, states, data, options)
    while it < options.max_iters:
        todo = np.flatnonzero(~np.asarray(states.converged))
        if todo.size == 0:
            break
        n = min(options.host_round, options.max_iters - it)
        rounds = None if b < _lm._MIN_BLOCK else _rounds(todo, b)
        if rounds is None:
            for _ in range(n):
                states = _step_all(residual_fn, states, data, options)
        elif options.host_fused:
            last = todo.size <= _slot_sizes(b)[0]  # the rest in one round
            steps = jnp.asarray(options.max_iters - it if last else n, np.int32)
            for idx in rounds:
                states = _round(residual_fn, states, data, jnp.asarray(idx), steps, options)
            if last:
                break
        else:
            for idx in rounds:
                # Padding slots repeat the last pixel, frozen, and are dropped on the way back.
                sub, sub_data = _gather(
                    states, data, jnp.asarray(np.minimum(idx, b - 1)), jnp.asarray(idx < b)
                )
                for _ in range(n):
                    sub = _step_all(residual_fn, sub, sub_data, options)
                states = _scatter(states, sub, jnp.asarray(idx))
        it += n
    return _finish_all(states, theta0, n_usable, options, space)

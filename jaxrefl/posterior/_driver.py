"""The one driver of the pixel samplers: the chains' starts, the loop of one chain, and the
draws packaged as :class:`~jaxrefl.posterior.Samples`.

Each sampler (HMC/NUTS :mod:`._hmc`, exact Gibbs :mod:`._gibbs`, the width sampler
:mod:`._width_gibbs`) is a :class:`Kernel` of one chain: pure functions over explicit
state, in the manner of BlackJAX's ``init``/``step``: ``init(*start)`` builds a chain's
first state from its start; ``step(state) -> (state, info)`` makes one move (the random key is
part of the state, or the step's own where the sampler splits its keys up front);
``begin(state)`` prepares a phase (the warm-up, then the kept draws); ``draw(state)`` is
what a kept draw records. :func:`run_chain` runs the warm-up, then ``num_samples`` kept
draws, each ``per_draw`` steps after the last, with each draw's ``info`` averaged over its
steps (a boolean: whether any step had it). Both phases run one compiled loop (an outer
scan over the two, half the program of two loops), and the step counts may be traced
values: a second pass with more steps between draws reuses the first pass's program.

:func:`chain_starts` and :func:`package` are the host side every sampler shares: one start
per chain, with the pixels that have no estimate (a non-finite start) run from 0 and
returned NaN.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._samples import Samples

__all__ = ["Kernel", "chain_starts", "package", "run_chain"]


def _same(state):
    return state


class Kernel(NamedTuple):
    """One chain's moves (module docstring)."""

    init: Callable[..., Any]
    step: Callable[[Any], tuple[Any, Any]]
    draw: Callable[[Any], Any]
    begin: Callable[[Any], Any] = _same


def run_chain(kernel: Kernel, start, *, warmup, warmup_steps, num_samples: int, per_draw):
    """(draws (num_samples, ...), info (num_samples, ...), the last state) of one chain
    from ``kernel.init(*start)``: ``warmup`` intervals of ``warmup_steps`` steps whose
    draws are dropped, then ``num_samples`` draws ``per_draw`` steps apart (module
    docstring)."""
    state = kernel.init(*start)
    draw0 = jax.eval_shape(kernel.draw, state)
    info0 = jax.eval_shape(kernel.step, state)[1]

    def zeros(s, n=()):
        return jnp.zeros((*n, *s.shape), s.dtype)

    out0 = (
        jax.tree.map(lambda s: zeros(s, (num_samples,)), draw0),
        jax.tree.map(lambda s: zeros(s, (num_samples,)), info0),
    )

    def phase(carry, spec):
        state, out = carry
        length, steps, keep = spec[0], spec[1], spec[2] > 0
        state = kernel.begin(state)

        def interval(t, c):
            state, (draws, infos) = c

            def one(_, sc):
                state, acc = sc
                state, info = kernel.step(state)
                return state, jax.tree.map(_accumulate, acc, info)

            acc0 = jax.tree.map(zeros, info0)
            state, acc = jax.lax.fori_loop(0, steps, one, (state, acc0))
            info = jax.tree.map(lambda a: a if a.dtype == bool else a / steps, acc)
            at = jnp.where(keep, t, num_samples)  # out of range in the warm-up: dropped
            put = lambda d, v: d.at[at].set(v, mode="drop")  # noqa: E731
            out = (jax.tree.map(put, draws, kernel.draw(state)), jax.tree.map(put, infos, info))
            return state, out

        return jax.lax.fori_loop(0, length, interval, (state, out)), None

    specs = jnp.stack(
        [
            jnp.stack([jnp.asarray(warmup), jnp.asarray(warmup_steps), jnp.asarray(0)]),
            jnp.stack([jnp.asarray(num_samples), jnp.asarray(per_draw), jnp.asarray(1)]),
        ]
    ).astype(jnp.int32)
    (state, (draws, infos)), _ = jax.lax.scan(phase, (state, out0), specs)
    return draws, infos, state


def _accumulate(acc, info):
    return acc | info if acc.dtype == bool else acc + info


def chain_starts(theta0, n: int, num_chains: int, dtype):
    """(x (N, chains, D), ok (N,)): theta0 ((D,), (N, D) or (N, chains, D)) as one start
    per chain; ``ok`` where every entry of a pixel's starts is finite, and 0 elsewhere."""
    t0 = jnp.asarray(theta0, dtype)
    if t0.ndim < 3:
        t0 = jnp.broadcast_to(t0, (n, t0.shape[-1]))[:, None, :]
    x = jnp.broadcast_to(t0, (n, num_chains, t0.shape[-1]))
    ok = jnp.all(jnp.isfinite(x), axis=(-2, -1))
    return jnp.where(ok[:, None, None], x, 0.0), ok


def package(
    lp, theta, ok, *, stats: dict, method: str, tuning: dict, run_s: float, **kw
) -> Samples:
    """:class:`Samples` of theta draws (N, chains, draws, D) in float64, NaN on the pixels
    without an estimate (``~ok``, also :attr:`Samples.no_estimate`), with their natural
    values; ``kw``: the other fields of :class:`Samples` (``compile_s``, ``reparam``,
    ``options``, ``sweeps``)."""
    pos = np.array(theta, np.float64)
    bad = ~np.asarray(ok)
    pos[bad] = np.nan
    nat = np.asarray(lp.natural(jnp.asarray(pos)), np.float64)
    return Samples(
        theta=pos,
        natural=nat,
        labels=lp.labels,
        stats=stats,
        method=method,
        tuning=tuning,
        run_s=run_s,
        no_estimate=bad,
        **kw,
    )

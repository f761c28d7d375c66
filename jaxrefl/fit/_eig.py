r"""Is an equilibrated J^T J worse conditioned than a bound? Without an eigensolver.

The per-pixel status (``_status.classify``) asks, for millions of small P x P matrices,
whether kappa(C) = lambda_max / lambda_min > kappa_max for C = D^-1/2 J^T J D^-1/2 (unit
diagonal). ``jnp.linalg.eigvalsh`` answers by handing each matrix to LAPACK in turn, with a
call's overhead per small matrix on the CPU. The answer needs no eigenvalues, only
definiteness tests, which are a fixed chain of elementwise operations that vectorises over
the batch:

* Sylvester's law of inertia (Golub & Van Loan, *Matrix Computations*, 4th ed., Sec. 8.1):
  a symmetric A is positive definite iff every pivot d_j of its LDL^T factorisation is
  positive, so "lambda_min(C) > mu" is the test "C - mu I has positive pivots" and
  "lambda_max(C) < mu" is "mu I - C has positive pivots".
* lambda_max is bracketed by bisection: C has unit diagonal, so
  1 = max_j c_jj <= lambda_max <= tr C = P for positive semi-definite C. ``BISECTIONS``
  halvings leave an upper end u with lambda_max <= u <= lambda_max + (P - 1) 2^-BISECTIONS
  (relative error below 2^-BISECTIONS (P - 1)).
* kappa(C) > kappa_max is then decided as "lambda_min(C) <= u / kappa_max": exact, except
  that the bound is in effect kappa_max * u / lambda_max, at most a factor
  1 + (P - 1) 2^-BISECTIONS above kappa_max (1e-3 for P = 5 and 12 halvings).

A matrix that is not positive definite (lambda_min <= 0, also in rounding) fails the last
test and counts as ill conditioned, which is what kappa = inf means.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

__all__ = ["BISECTIONS", "MAX_P", "condition_exceeds", "positive_definite"]

MAX_P = 8
"""Largest P for which the status uses these tests (beyond it the unrolled factorisation's
compile time outgrows what it saves; ``_status.ill_conditioned`` falls back to LAPACK)."""

BISECTIONS = 12
"""Halvings of [1, P] that bracket lambda_max (module docstring: threshold error bound)."""


def positive_definite(a: Float[Array, "*b P P"]) -> Bool[Array, "*b"]:
    """All LDL^T pivots of symmetric ``a`` positive (P static and small: unrolled)."""
    p = a.shape[-1]
    el: list[list[Array]] = [[a[..., i, j] for j in range(p)] for i in range(p)]
    d: list[Array] = []
    ok = jnp.ones(a.shape[:-2], dtype=bool)
    for j in range(p):
        dj = el[j][j]
        for k in range(j):
            dj = dj - el[j][k] * el[j][k] * d[k]
        pos = dj > 0
        ok = ok & pos
        # A non-positive pivot has decided the answer; 1 keeps the divisions below finite.
        dj = jnp.where(pos, dj, 1.0)
        d.append(dj)
        for i in range(j + 1, p):
            t = el[i][j]
            for k in range(j):
                t = t - el[i][k] * el[j][k] * d[k]
            el[i][j] = t / dj
    return ok


def condition_exceeds(c: Float[Array, "*b P P"], cond_max: float) -> Bool[Array, "*b"]:
    """kappa(c) > ``cond_max`` for symmetric ``c`` with unit diagonal (module docstring).

    Rounds 0 .. BISECTIONS - 1 bisect lambda_max (test mu I - c); the last round tests
    c - (u / cond_max) I. One loop body, so the factorisation is compiled once.
    """
    p = c.shape[-1]
    eye = jnp.broadcast_to(jnp.eye(p, dtype=c.dtype), c.shape)
    batch = c.shape[:-2]

    def body(state):
        k, lo, hi, _ = state
        last = k == BISECTIONS
        mid = 0.5 * (lo + hi)
        sign = jnp.where(last, 1.0, -1.0).astype(c.dtype)
        shift = jnp.where(last, -hi / cond_max, mid)
        pd = positive_definite(sign * c + shift[..., None, None] * eye)
        # Bisection rounds: pd means lambda_max < mid, the upper end comes down to mid.
        lo = jnp.where(last | pd, lo, mid)
        hi = jnp.where(~last & pd, mid, hi)
        return k + 1, lo, hi, ~pd

    ones, top = jnp.ones(batch, c.dtype), jnp.full(batch, float(p), c.dtype)
    init = (jnp.int32(0), ones, top, jnp.zeros(batch, bool))
    return jax.lax.while_loop(lambda s: s[0] <= BISECTIONS, body, init)[3]

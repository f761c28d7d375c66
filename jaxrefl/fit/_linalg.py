"""Shared small linear algebra: a Cholesky factor and triangular solves written out entry
by entry, for many small symmetric positive definite systems at once.

P (the matrix size) is small and static, so the factorisation and the substitutions unroll
into scalar arithmetic on whole batches (leading axes, or ``vmap``): batched LAPACK calls
on matrices this small cost more than the arithmetic itself. The lean Levenberg-Marquardt
(:mod:`._lm`), the Laplace step, photometric stereo and the width sampler of
:mod:`jaxrefl.posterior` all factor through these functions.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

__all__ = [
    "cho_solve_unrolled",
    "cholesky_unrolled",
    "solve_lower_t_unrolled",
    "solve_lower_unrolled",
]


def cholesky_unrolled(
    a: Float[Array, "*b P P"],
) -> tuple[Float[Array, "*b P P"], Bool[Array, "*b"]]:
    """Lower Cholesky factor of a symmetric matrix, unrolled for small static P.

    Returns (L, ok). Where a pivot is not positive (the matrix is not positive definite in
    floating point) ``ok`` is False and that pivot is replaced by 1 (gradient-safe; the
    factor is then meaningless and must not be used).
    """
    p = a.shape[-1]
    cols: list[list[Array]] = [[jnp.zeros_like(a[..., 0, 0])] * p for _ in range(p)]
    ok = jnp.ones(a.shape[:-2], dtype=bool)
    for j in range(p):
        s = a[..., j, j]
        for k in range(j):
            s = s - cols[j][k] * cols[j][k]
        pos = s > 0
        ok = ok & pos
        d = jnp.sqrt(jnp.where(pos, s, 1.0))
        cols[j][j] = d
        for i in range(j + 1, p):
            t = a[..., i, j]
            for k in range(j):
                t = t - cols[i][k] * cols[j][k]
            cols[i][j] = t / d
    rows = [jnp.stack(cols[i], axis=-1) for i in range(p)]
    return jnp.stack(rows, axis=-2), ok


def solve_lower_unrolled(
    l: Float[Array, "*b P P"], b: Float[Array, "*b P"]
) -> Float[Array, "*b P"]:
    """L^-1 b for a lower-triangular L, by forward substitution unrolled for small P."""
    p = l.shape[-1]
    y: list[Array] = []
    for i in range(p):
        t = b[..., i]
        for k in range(i):
            t = t - l[..., i, k] * y[k]
        y.append(t / l[..., i, i])
    return jnp.stack(y, axis=-1)


def solve_lower_t_unrolled(
    l: Float[Array, "*b P P"], y: Float[Array, "*b P"]
) -> Float[Array, "*b P"]:
    """L^-T y for a lower-triangular L, by back substitution unrolled for small P."""
    p = l.shape[-1]
    x: list[Array] = [jnp.zeros_like(y[..., 0])] * p
    for i in reversed(range(p)):
        t = y[..., i]
        for k in range(i + 1, p):
            t = t - l[..., k, i] * x[k]
        x[i] = t / l[..., i, i]
    return jnp.stack(x, axis=-1)


def cho_solve_unrolled(l: Float[Array, "*b P P"], b: Float[Array, "*b P"]) -> Float[Array, "*b P"]:
    """Solve (L L^T) x = b by forward and back substitution, unrolled for small P."""
    return solve_lower_t_unrolled(l, solve_lower_unrolled(l, b))

"""Keep the lower-cost of two fits, pixel by pixel.

A fit run twice on the same pixels (a second stage with more parameters, a continuation
from where the first stopped, another start) gives two candidates per pixel;
:func:`keep_lower` keeps, for each pixel, the one of lower cost. A candidate whose cost is
not finite never replaces the other, and on equal costs the first is kept.
"""

from __future__ import annotations

from typing import Any, TypeVar

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

__all__ = ["keep_lower"]

T = TypeVar("T")


def keep_lower(
    cost_a: Float[ArrayLike, " *n"],
    params_a: T,
    cost_b: Float[ArrayLike, " *n"],
    params_b: T,
    where: Bool[ArrayLike, " *n"] | None = None,
) -> tuple[Float[Array, " *n"], T]:
    """(cost, params) of the lower-cost candidate per pixel (module docstring).

    ``params_a`` and ``params_b`` are pytrees of the same structure whose leaves have the
    pixel axes of the costs first (any trailing axes); ``where`` (optional, the costs'
    shape) limits the pixels that may take the second candidate.
    """
    ca, cb = jnp.asarray(cost_a), jnp.asarray(cost_b)
    # The second wins where its cost is finite and the first's is not lower (a NaN loses).
    take_b: Bool[Array, " *n"] = jnp.isfinite(cb) & ~(ca <= cb)
    if where is not None:
        take_b = take_b & jnp.asarray(where)

    def pick(x: Any, y: Any) -> Array:
        m = take_b.reshape(take_b.shape + (1,) * (jnp.ndim(x) - take_b.ndim))
        return jnp.where(m, y, x)

    return pick(ca, cb), jax.tree.map(pick, params_a, params_b)

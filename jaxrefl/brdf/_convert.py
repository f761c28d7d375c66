"""Conversions between roughness conventions.

The models take the microfacet distribution's own ``alpha`` (Walter et al. 2007: the GGX or
Beckmann width parameter, alpha = RMS slope for Beckmann). Artists and many capture papers
(Burley 2012, the MaterialGAN renderer) use a perceptual roughness r with alpha = r^2.
Walter et al. 2007 (eq. 33) relate Beckmann alpha to a Phong exponent: n = 2/alpha^2 - 2.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "alpha_to_phong_exponent",
    "alpha_to_roughness",
    "phong_exponent_to_alpha",
    "roughness_to_alpha",
]


def roughness_to_alpha(roughness: Float[ArrayLike, "*b"]) -> Float[Array, "*b"]:
    """Perceptual roughness r in [0, 1] to alpha = r^2 (Burley 2012)."""
    r = jnp.asarray(roughness)
    return r * r


def alpha_to_roughness(alpha: Float[ArrayLike, "*b"]) -> Float[Array, "*b"]:
    """alpha >= 0 to perceptual roughness sqrt(alpha)."""
    a = jnp.asarray(alpha)
    # alpha is non-negative by contract; max(., 0) only absorbs round-off before the sqrt.
    return jnp.sqrt(jnp.maximum(a, 0.0))


def alpha_to_phong_exponent(alpha: Float[ArrayLike, "*b"]) -> Float[Array, "*b"]:
    """Beckmann alpha to the equivalent Phong exponent n = 2/alpha^2 - 2 (Walter 2007 eq. 33)."""
    a = jnp.asarray(alpha)
    return 2.0 / (a * a) - 2.0


def phong_exponent_to_alpha(n: Float[ArrayLike, "*b"]) -> Float[Array, "*b"]:
    """Phong exponent n >= 0 to Beckmann alpha = sqrt(2/(n + 2)) (Walter 2007 eq. 33)."""
    e = jnp.asarray(n)
    return jnp.sqrt(2.0 / (e + 2.0))

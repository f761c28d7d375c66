"""Conversions between roughness conventions, and the metallic-roughness view.

The models take the microfacet distribution's own ``alpha`` (Walter et al. 2007: the GGX or
Beckmann width parameter, alpha = RMS slope for Beckmann). Artists and many capture papers
(Burley 2012, the MaterialGAN renderer) use a perceptual roughness r with alpha = r^2.
Walter et al. 2007 (eq. 33) relate Beckmann alpha to a Phong exponent: n = 2/alpha^2 - 2.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "DIELECTRIC_F0_DEFAULT",
    "alpha_to_phong_exponent",
    "alpha_to_roughness",
    "metallic_to_specular",
    "phong_exponent_to_alpha",
    "roughness_to_alpha",
    "specular_to_metallic",
]

# The F0 every dielectric gets in the metallic-roughness convention (glTF 2.0, Burley 2012):
# about that of glass or plastic, eta = 1.5.
DIELECTRIC_F0_DEFAULT = 0.04


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


def _luminance(c: Array) -> Array:
    # Rec. 709 / sRGB luminance weights; a grey (one-channel) colour is its own luminance.
    if c.shape[-1] != 3:
        return jnp.mean(c, axis=-1)
    return c @ jnp.asarray([0.2126, 0.7152, 0.0722], c.dtype)


def metallic_to_specular(
    base_color: Float[ArrayLike, "*b C"], metallic: Float[ArrayLike, "*b"]
) -> tuple[Float[Array, "*b C"], Float[Array, "*b C"]]:
    """The metallic-roughness parametrisation (glTF 2.0 core, Burley 2012) as the specular
    one the capture models fit: (diffuse albedo, Schlick F0).

        albedo = base_color (1 - F0_d) (1 - metallic),   F0 = F0_d (1 - metallic)
                 + base_color metallic,                  F0_d = 0.04 (a dielectric's)

    base_color and F0 are colours in [0, 1] (trailing channel axis), metallic in [0, 1];
    roughness is unchanged (alpha = roughness^2). The (1 - F0_d) factor is glTF's energy
    split between the dielectric's specular and its diffuse base.
    """
    b = jnp.asarray(base_color)
    m = jnp.asarray(metallic)[..., None]
    f0d = DIELECTRIC_F0_DEFAULT
    return b * (1.0 - f0d) * (1.0 - m), f0d * (1.0 - m) + b * m


def specular_to_metallic(
    albedo: Float[ArrayLike, "*b C"], specular: Float[ArrayLike, "*b C"]
) -> tuple[Float[Array, "*b C"], Float[Array, "*b"]]:
    """(base_color, metallic) of a fitted (diffuse albedo, F0): the inverse of
    :func:`metallic_to_specular` where one exists.

    Metallic is solved from luminances (Y = Rec. 709 weights), as in the Khronos
    specular-glossiness to metallic-roughness converter: with d = Y(albedo) / (1 - F0_d) and
    s = Y(F0), metallic m and the base luminance b solve b (1 - m) = d and
    F0_d (1 - m) + b m = s; eliminating b gives F0_d m^2 + (d + s - 2 F0_d) m + F0_d - s = 0,
    whose root in [0, 1] is taken (0 where s <= F0_d: a dielectric). The base colour per
    channel is then the least-squares blend of the two ways to read it:
    albedo / ((1 - F0_d)(1 - m)) and (F0 - F0_d (1 - m)) / m, weighted by (1 - m)^2 and m^2,
    clipped to [0, 1]. A pair made
    by :func:`metallic_to_specular` comes back exactly (up to round-off); a pair that no
    metallic-roughness material makes (a coloured F0 and an unrelated albedo) comes back
    as its nearest such material in that least-squares sense.
    """
    a = jnp.asarray(albedo)
    f = jnp.asarray(specular)
    f0d = DIELECTRIC_F0_DEFAULT
    d = _luminance(a) / (1.0 - f0d)
    s = _luminance(f)
    qa, qb, qc = f0d, d + s - 2.0 * f0d, f0d - s
    disc = jnp.maximum(qb * qb - 4.0 * qa * qc, 0.0)  # >= 0 for s >= F0_d; round-off only
    root = (-qb + jnp.sqrt(disc)) / (2.0 * qa)
    m = jnp.where(s > f0d, jnp.clip(root, 0.0, 1.0), 0.0)
    mm = m[..., None]
    # Weighted least squares of the two linear readings of the base colour:
    #   (1 - F0_d)(1 - m) b = albedo,   m b = F0 - F0_d (1 - m).
    wd, ws = (1.0 - f0d) * (1.0 - mm), mm
    num = wd * a + ws * (f - f0d * (1.0 - mm))
    den = wd * wd + ws * ws
    base = jnp.clip(num / den, 0.0, 1.0)
    return base, m

"""Angle helpers in the local shading frame, written once and used by every model.

Convention (pbrt-v4 ``util/vecmath.h``, Mitsuba 3 ``frame.h``): directions are unit vectors
in the local frame where +z is the surface normal and the tangent is +x; ``wi`` points from
the surface towards the light and ``wo`` from the surface towards the viewer, so both lie in
the upper hemisphere (z > 0) for a visible, lit surface point.

All helpers are gradient-safe: wherever a square root, division or normalisation could see
zero, the unsafe input is replaced *before* the operation (``jnp.where`` on the input, not on
the output), so that ``jax.grad`` never sees ``0 * inf``.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

__all__ = [
    "cos2_theta",
    "cos_phi",
    "cos_theta",
    "half_vector",
    "reflect",
    "safe_div",
    "safe_normalize",
    "safe_sqrt",
    "sin2_theta",
    "sin_phi",
    "spherical_direction",
    "upper_hemisphere",
]


def safe_sqrt(x: Float[Array, "*b"]) -> Float[Array, "*b"]:
    """sqrt(max(x, 0)) with a finite gradient at 0.

    Clamp: only round-off pushes arguments such as 1 - cos^2 below zero (pbrt-v4 SafeSqrt);
    at exactly 0 the derivative of sqrt is infinite, so the input is swapped for 1 there and
    the gradient through that branch is defined as 0.
    """
    pos = x > 0
    x_safe = jnp.where(pos, x, 1.0)
    return jnp.where(pos, jnp.sqrt(x_safe), 0.0)


def safe_div(num: Float[Array, "*b"], den: Float[Array, "*b"]) -> Float[Array, "*b"]:
    """num / den, returning 0 where den == 0 (and a zero gradient there)."""
    ok = den != 0
    den_safe = jnp.where(ok, den, 1.0)
    return jnp.where(ok, num / den_safe, 0.0)


def safe_normalize(v: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
    """v / |v|; a zero vector maps to +z (the normal) rather than NaN."""
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = n2 > 0
    # A zero-length vector has no direction; +z is the one direction that is always valid.
    v_safe = jnp.where(ok, v, jnp.asarray([0.0, 0.0, 1.0], dtype=v.dtype))
    n2_safe = jnp.where(ok, n2, 1.0)
    return v_safe / jnp.sqrt(n2_safe)


def cos_theta(w: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
    """cos(theta) = w_z."""
    return w[..., 2]


def cos2_theta(w: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
    return w[..., 2] * w[..., 2]


def sin2_theta(w: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
    """sin^2(theta) = x^2 + y^2, computed without the cancellation of 1 - cos^2.

    For a unit vector this equals 1 - cos^2 exactly in real arithmetic; the x^2 + y^2 form
    keeps full relative precision near the normal, where 1 - cos^2 loses every digit in
    float32 (the GGX denominator alpha^2 cos^2 + sin^2 needs sin^2 exactly there).
    """
    return w[..., 0] * w[..., 0] + w[..., 1] * w[..., 1]


def cos_phi(w: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
    """cos(phi), guarded: along the normal phi is undefined and 1 is returned (pbrt-v4 CosPhi)."""
    s2 = sin2_theta(w)
    ok = s2 > 0
    s = jnp.sqrt(jnp.where(ok, s2, 1.0))
    return jnp.where(ok, jnp.clip(w[..., 0] / s, -1.0, 1.0), 1.0)


def sin_phi(w: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
    """sin(phi), guarded: along the normal 0 is returned (pbrt-v4 SinPhi)."""
    s2 = sin2_theta(w)
    ok = s2 > 0
    s = jnp.sqrt(jnp.where(ok, s2, 1.0))
    return jnp.where(ok, jnp.clip(w[..., 1] / s, -1.0, 1.0), 0.0)


def half_vector(wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
    """Normalised half vector (wi + wo)/|wi + wo|; wi = -wo (undefined) maps to +z."""
    return safe_normalize(wi + wo)


def reflect(w: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
    """Mirror direction about the normal: (-x, -y, z)."""
    return jnp.stack([-w[..., 0], -w[..., 1], w[..., 2]], axis=-1)


def upper_hemisphere(wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]) -> Bool[Array, " *b"]:
    """True where both directions are strictly above the surface (cos > 0)."""
    return (wi[..., 2] > 0) & (wo[..., 2] > 0)


def spherical_direction(
    theta: Float[Array, " *b"], phi: Float[Array, " *b"]
) -> Float[Array, "*b 3"]:
    """Unit vector from polar angle theta (from +z) and azimuth phi (from +x towards +y)."""
    st = jnp.sin(theta)
    return jnp.stack([st * jnp.cos(phi), st * jnp.sin(phi), jnp.cos(theta)], axis=-1)

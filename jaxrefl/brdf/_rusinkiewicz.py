"""Rusinkiewicz half/difference coordinates for a pair of directions.

Rusinkiewicz, "A New Change of Variables for Efficient BRDF Representation", EGWR 1998:
a pair (wi, wo) is described by the half vector

    wh = (wi + wo) / |wi + wo| = (sin θh cos φh, sin θh sin φh, cos θh)

and by the *difference* vector, which is wi seen from a frame in which wh is the pole:

    wd = Ry(-θh) Rz(-φh) wi = (sin θd cos φd, sin θd sin φd, cos θd).

In that frame wo is the mirror image of wd about the pole, wo_d = (-x, -y, z) of wd, so
swapping wi and wo maps φd -> φd + π (mod 2π) and leaves θh, φh, θd unchanged. For
isotropic materials f_r does not depend on φh; reciprocity then makes it π-periodic in φd
(the MERL tables store φd in [0, π)).

Ranges: θh in [0, π/2] for directions in the upper hemisphere, φh in (-π, π],
θd in [0, π/2], φd in (-π, π]. These are the conventions of MERL's ``BRDFRead.cpp``
(``std_coords_to_half_diff_coords``: "in" = wi); angles in radians. Directions are unit
vectors in the local frame (z = normal), both pointing away from the surface.

Edges: φh is undefined where wh is the normal (θh = 0), φd where wi == wo (θd = 0); both
are then defined as 0 (also within 4 ulps of those points, where they are round-off), and
the rotation uses φh = 0, so :func:`from_half_diff` inverts :func:`to_half_diff` there too.
Values and gradients are finite everywhere (guarded inputs).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ._frame import half_vector, safe_sqrt, spherical_direction

__all__ = ["from_half_diff", "to_half_diff"]


def _polar_azimuth(v: Float[Array, "*b 3"]) -> tuple[Float[Array, " *b"], ...]:
    """(θ, φ, cos φ, sin φ, sin θ) of a unit vector, φ = 0 where it is the pole."""
    s2 = v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1]
    # Within a few ulps of the pole (sin θ < 4 eps) the azimuth is pure round-off (wi == wo
    # gives |xy| ~ 1e-17, not 0) and the atan2 gradient ~1/|xy| explodes: treat it as the pole.
    eps = jnp.finfo(v.dtype).eps
    ok = s2 > (4 * eps) ** 2
    x = jnp.where(ok, v[..., 0], 1.0)
    y = jnp.where(ok, v[..., 1], 0.0)
    s = safe_sqrt(jnp.where(ok, s2, 0.0))
    theta = jnp.arctan2(s, v[..., 2])  # atan2 keeps full precision near the pole, unlike acos
    phi = jnp.where(ok, jnp.arctan2(y, x), 0.0)
    r = jnp.where(ok, s, 1.0)
    return theta, phi, x / r, y / r, s


def to_half_diff(
    wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]
) -> tuple[Float[Array, " *b"], Float[Array, " *b"], Float[Array, " *b"], Float[Array, " *b"]]:
    """(θh, φh, θd, φd) of the pair (wi, wo), radians (Rusinkiewicz 1998).

    wi = -wo (no half vector) maps wh to the normal (:func:`half_vector`).
    """
    wi = jnp.asarray(wi)
    wo = jnp.asarray(wo, dtype=wi.dtype)
    wh = half_vector(wi, wo)
    theta_h, phi_h, cp, sp, sin_h = _polar_azimuth(wh)
    cos_h = wh[..., 2]
    # Rz(-φh): rotate wh's azimuth onto +x.
    tx = cp * wi[..., 0] + sp * wi[..., 1]
    ty = -sp * wi[..., 0] + cp * wi[..., 1]
    tz = wi[..., 2]
    # Ry(-θh): tilt wh onto +z.
    wd = jnp.stack([tx * cos_h - tz * sin_h, ty, tx * sin_h + tz * cos_h], axis=-1)
    theta_d, phi_d, *_ = _polar_azimuth(wd)
    return theta_h, phi_h, theta_d, phi_d


def from_half_diff(
    theta_h: Float[Array, " *b"],
    phi_h: Float[Array, " *b"],
    theta_d: Float[Array, " *b"],
    phi_d: Float[Array, " *b"],
) -> tuple[Float[Array, "*b 3"], Float[Array, "*b 3"]]:
    """(wi, wo) from half/difference angles: wi = Rz(φh) Ry(θh) wd, wo likewise from the
    mirror image of wd about the pole.

    Every combination gives unit vectors, but not every one lies in the upper hemisphere
    (θh + θd > π/2 can put wi or wo below the horizon: MERL's missing cells).
    """
    theta_h, phi_h, theta_d, phi_d = jnp.broadcast_arrays(
        *(jnp.asarray(a) for a in (theta_h, phi_h, theta_d, phi_d))
    )
    wd = spherical_direction(theta_d, phi_d)
    ch, sh = jnp.cos(theta_h)[..., None], jnp.sin(theta_h)[..., None]
    cp, sp = jnp.cos(phi_h)[..., None], jnp.sin(phi_h)[..., None]

    def rotate(v: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
        x, y, z = v[..., 0:1], v[..., 1:2], v[..., 2:3]
        # Ry(θh) then Rz(φh): the inverse of the rotations in to_half_diff.
        x, z = x * ch + z * sh, -x * sh + z * ch
        x, y = x * cp - y * sp, x * sp + y * cp
        return jnp.concatenate([x, y, z], axis=-1)

    # Built with stack, not `wd * [-1, -1, 1]`: implicit rank promotion is an error here.
    wd_mirror = jnp.stack([-wd[..., 0], -wd[..., 1], wd[..., 2]], axis=-1)
    return rotate(wd), rotate(wd_mirror)

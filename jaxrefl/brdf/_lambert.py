"""Diffuse models: Lambert and Oren–Nayar.

Lambert
-------
    f_r = albedo / pi                                                          [1/sr]

``albedo`` in [0, 1] per channel (the directional-hemispherical reflectance); reciprocal and
energy conserving (albedo 1 integrates to exactly 1 over the cosine-weighted hemisphere).
Returns f_r without the cosine factor.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ._base import BRDF, Param

__all__ = ["Lambert"]

ALBEDO = Param(
    name="albedo",
    kind="color",
    default=0.5,
    lower=0.0,
    upper=1.0,
    units="1 (directional-hemispherical reflectance)",
    doc="diffuse albedo per channel",
)


class Lambert(BRDF):
    """Lambertian diffuse reflection, f_r = albedo / pi (Lambert 1760)."""

    @property
    def params(self) -> tuple[Param, ...]:
        return (ALBEDO,)

    @property
    def energy_conserving(self) -> bool:
        return True

    def _eval(
        self, p: dict[str, Array], wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]
    ) -> Float[Array, "*b C"]:
        batch = jnp.broadcast_shapes(wi.shape[:-1], wo.shape[:-1])
        albedo = p["albedo"]
        shape = jnp.broadcast_shapes((*batch, 1), albedo.shape)
        return jnp.broadcast_to(albedo / jnp.pi, shape)

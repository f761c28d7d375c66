"""Shafer's dichromatic reflection model with a microfacet interface lobe.

Shafer (1985), "Using color to separate reflection components": light reflected by an
inhomogeneous dielectric (paint, plastic, skin) is the sum of *body* reflection, scattered
under the surface and coloured by its pigments, and *interface* reflection at the
air-surface boundary. Under the neutral-interface assumption (Lee et al. 1990) the interface
term has the colour of the illuminant, and its angular shape is a pure geometric factor that
does not depend on wavelength. Here::

    f_r(wi, wo) = albedo / pi  +  specular * D(h) G(wi, wo, h) / (4 cos_i cos_o)     [1/sr]

* body: Lambertian with body colour ``albedo`` (colour, [0, 1]);
* interface: ``specular`` (colour, [0, 1]) is the interface colour and strength, i.e. the
  illuminant colour times the (assumed constant) Fresnel reflectance -- neutral interface
  means ``specular`` is grey for a white illuminant; D is GGX (default) or Beckmann with
  roughness ``alpha`` (scalar, [1e-4, 1]) and G the height-correlated Smith term
  (Heitz 2014). The angle dependence of the Fresnel factor is deliberately left out: in
  Shafer's model it is absorbed into the geometric scale factor.

This is :class:`~jaxrefl.brdf._cook_torrance.CookTorrance` with ``fresnel="none"`` and
``diffuse="lambert"``, under the model's own names. Returns f_r without the cosine factor;
directions are unit vectors in the local frame (z = normal) pointing away from the surface.
Reciprocal. Not marked energy conserving: albedo + specular may exceed 1 (the caller keeps
albedo + specular <= 1 for a physical surface; each lobe alone integrates to <= its weight).
"""

from __future__ import annotations

from dataclasses import replace

import jax.numpy as jnp
from jaxtyping import Array, Float

from ._base import BRDF, Param
from ._cook_torrance import _DISTRIBUTIONS, _pick, align_ranks, microfacet_specular
from ._fresnel import SPECULAR_SCALE, NoFresnel
from ._lambert import ALBEDO
from ._microfacet import Distribution, SmithHeightCorrelated

__all__ = ["Dichromatic"]

# The constant Fresnel factor of NoFresnel (which Dichromatic uses), in the model's own words.
INTERFACE = replace(
    SPECULAR_SCALE,
    doc="interface (specular) reflection colour: illuminant colour x interface strength",
)


class Dichromatic(BRDF):
    """albedo/pi + specular D G / (4 cos_i cos_o) (Shafer 1985); see the module docstring."""

    distribution: Distribution
    shadowing: SmithHeightCorrelated
    fresnel: NoFresnel

    def __init__(self, distribution: str | Distribution = "ggx"):
        self.distribution = _pick("distribution", _DISTRIBUTIONS, distribution, False)
        self.shadowing = SmithHeightCorrelated()
        self.fresnel = NoFresnel()

    @property
    def params(self) -> tuple[Param, ...]:
        return (ALBEDO, INTERFACE, *self.distribution.params)

    def _eval(
        self, p: dict[str, Array], wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]
    ) -> Float[Array, "*b C"]:
        p, wi, wo = align_ranks(self.params, p, wi, wo)
        spec = microfacet_specular(self.distribution, self.shadowing, self.fresnel, p, wi, wo)
        return p["albedo"] / jnp.pi + spec

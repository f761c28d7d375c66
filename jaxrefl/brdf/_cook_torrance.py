"""The Cook–Torrance microfacet BRDF, assembled from a distribution, a shadowing term and a
Fresnel term (Mitsuba's ``roughconductor`` / pbrt-v4's ``ConductorBxDF`` pattern).

    f_r(wi, wo) = F(wo.h) D(h) G(wi, wo, h) / (4 cos_i cos_o)  [+ albedo / pi]      [1/sr]

with h = (wi + wo)/|wi + wo| (Cook & Torrance 1982; Walter et al. 2007, eq. 20; Heitz 2014).
Returns f_r **without** the cosine factor. Directions are unit vectors in the local frame
(z = normal), both pointing away from the surface; below the horizon f_r = 0 (base class).

Parts (strings or part objects):

* ``distribution``: ``"ggx"`` (default) or ``"beckmann"``, isotropic (``alpha``) or
  ``anisotropic=True`` (``alpha_u`` along the tangent x, ``alpha_v`` along y); alpha in
  [1e-4, 1], floored at 1e-4 (:mod:`jaxrefl.brdf._microfacet`).
* ``shadowing``: ``"smith_height_correlated"`` (default, Heitz 2014 eq. 99),
  ``"smith_separable"`` (Walter 2007 eq. 23) or ``"vgroove"`` (Cook & Torrance 1982).
* ``fresnel``: ``"schlick"`` (default; ``specular`` = F0 in [0, 1]), ``"dielectric"``
  (``eta`` in [1, 4]), ``"conductor"`` (``eta`` in [0, 10], ``k`` in [0, 10]) or ``"none"``
  (F = ``specular``, a colour scale in [0, 1]). Colours have a trailing channel axis.
* ``diffuse``: ``None`` (default) or ``"lambert"`` (adds ``albedo`` / pi, albedo in [0, 1]).

Defaults: alpha 0.2, specular 0.04 (eta = 1.5), eta 1.5 (dielectric), eta/k of gold in RGB
(conductor), albedo 0.5.

Physics: reciprocal for every combination (the Smith terms and V-groove are symmetric in
wi, wo and F depends on wi.h = wo.h). Without a diffuse term the directional albedo is <= 1:
every Fresnel part keeps F <= 1, and both Smith forms satisfy G <= G1(wo), whose integral
int G1(wo, h) D(h) (wo.h) dw_h = cos_o (Heitz 2014, eq. 2) bounds the albedo by 1. The
V-groove term has no such bound in general; tests integrate it numerically (<= 1, tending to
1 at grazing view). Single scattering loses energy as alpha grows (white furnace, GGX,
height-correlated Smith, F = 1, normal view: 0.997 at alpha = 0.05, 0.88 at 0.3, 0.31 at 1,
where half the microfacets send light below the horizon; tests/test_cook_torrance.py).
With ``diffuse="lambert"`` the two lobes are simply added, so albedo + specular can exceed
1: ``energy_conserving`` is False then.

Numerics: the shadowing parts return G / (4 cos_i cos_o) directly (finite as either cosine
-> 0), GGX uses the cancellation-free denominator, and at alpha = 1e-4 with h = normal and
cos = 1e-6 values stay below ~1e19, finite in float32 together with their gradients.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxrefl._errors import JaxreflError

from ._base import BRDF, Param
from ._frame import half_vector
from ._fresnel import ConductorFresnel, DielectricFresnel, FresnelPart, NoFresnel, SchlickFresnel
from ._lambert import ALBEDO
from ._microfacet import (
    GGX,
    Beckmann,
    Distribution,
    Shadowing,
    SmithHeightCorrelated,
    SmithSeparable,
    VGroove,
)

__all__ = ["CookTorrance", "align_ranks", "microfacet_specular"]

_DISTRIBUTIONS = {"ggx": GGX, "beckmann": Beckmann}
_SHADOWING = {
    "smith_height_correlated": SmithHeightCorrelated,
    "smith_separable": SmithSeparable,
    "vgroove": VGroove,
}
_FRESNEL = {
    "schlick": SchlickFresnel,
    "dielectric": DielectricFresnel,
    "conductor": ConductorFresnel,
    "none": NoFresnel,
}


def _pick(kind: str, table: dict, value, *args):
    if isinstance(value, str):
        try:
            return table[value](*args)
        except KeyError:
            raise JaxreflError(f"unknown {kind} {value!r}; choose one of {tuple(table)}") from None
    return value


def _lift(x: Array, ndim: int) -> Array:
    return x.reshape((1,) * (ndim - x.ndim) + x.shape)


def align_ranks(
    specs: tuple[Param, ...], p: dict[str, Array], wi: Array, wo: Array
) -> tuple[dict[str, Array], Array, Array]:
    """Give parameters and directions one common batch rank (leading unit axes).

    Needed because the package runs with ``jax_numpy_rank_promotion="raise"`` in tests: a
    ``(3,)`` colour must become ``(1, 3)`` before it meets ``(N, 3)`` values. Scalars get
    rank ``nb``, colours and directions ``nb + 1``.
    """
    nb = max(wi.ndim, wo.ndim) - 1
    for q in specs:
        nb = max(nb, p[q.name].ndim - (0 if q.kind == "scalar" else 1))
    out = {q.name: _lift(p[q.name], nb if q.kind == "scalar" else nb + 1) for q in specs}
    return out, _lift(wi, nb + 1), _lift(wo, nb + 1)


def microfacet_specular(
    distribution: Distribution,
    shadowing: Shadowing,
    fresnel: FresnelPart,
    p: dict[str, Array],
    wi: Float[Array, "*b 3"],
    wo: Float[Array, "*b 3"],
) -> Float[Array, "*b C"]:
    """F(wo.h) D(h) G / (4 cos_i cos_o) for directions above the horizon, ranks aligned."""
    wh = half_vector(wi, wo)
    cos_d = 0.5 * (jnp.sum(wi * wh, axis=-1) + jnp.sum(wo * wh, axis=-1))
    dv = distribution.D(p, wh) * shadowing.visibility(distribution, p, wi, wo, wh)
    return fresnel(p, cos_d) * dv[..., None]


class CookTorrance(BRDF):
    """Microfacet BRDF F D G / (4 cos_i cos_o) [+ albedo/pi]; see the module docstring."""

    distribution: Distribution
    shadowing: Shadowing
    fresnel: FresnelPart
    diffuse: str | None = eqx.field(static=True)

    def __init__(
        self,
        distribution: str | Distribution = "ggx",
        anisotropic: bool = False,
        shadowing: str | Shadowing = "smith_height_correlated",
        fresnel: str | FresnelPart = "schlick",
        diffuse: str | None = None,
    ):
        self.distribution = _pick("distribution", _DISTRIBUTIONS, distribution, anisotropic)
        self.shadowing = _pick("shadowing", _SHADOWING, shadowing)
        self.fresnel = _pick("fresnel", _FRESNEL, fresnel)
        if diffuse not in (None, "lambert"):
            raise JaxreflError(f"unknown diffuse {diffuse!r}; choose None or 'lambert'")
        self.diffuse = diffuse

    @property
    def params(self) -> tuple[Param, ...]:
        base = (ALBEDO,) if self.diffuse == "lambert" else ()
        return base + self.fresnel.params + self.distribution.params

    @property
    def energy_conserving(self) -> bool:
        return self.diffuse is None and self.fresnel.at_most_one

    def _eval(
        self, p: dict[str, Array], wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]
    ) -> Float[Array, "*b C"]:
        p, wi, wo = align_ranks(self.params, p, wi, wo)
        f = microfacet_specular(self.distribution, self.shadowing, self.fresnel, p, wi, wo)
        if self.diffuse == "lambert":
            f = f + p["albedo"] / jnp.pi
        return f

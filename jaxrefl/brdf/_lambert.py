"""Diffuse models: Lambert and Oren–Nayar.

Lambert
-------
    f_r = albedo / pi                                                          [1/sr]

``albedo`` in [0, 1] per channel (the directional-hemispherical reflectance); reciprocal and
energy conserving (albedo 1 integrates to exactly 1 over the cosine-weighted hemisphere).

Oren–Nayar
----------
Oren & Nayar (1994), "Generalization of Lambert's reflectance model", SIGGRAPH '94,
pp. 239-246: a surface of long symmetric V-cavities whose facet slopes are normally
distributed with standard deviation ``sigma`` (radians), each facet Lambertian. With
alpha = max(theta_i, theta_o), beta = min(theta_i, theta_o) and dphi = phi_o - phi_i:

*qualitative* model (the paper's simplified "qualitative model"),
``variant="qualitative"``::

    A = 1 - 0.5 sigma^2 / (sigma^2 + 0.33),    B = 0.45 sigma^2 / (sigma^2 + 0.09)
    f_r = albedo/pi * (A + B * max(0, cos dphi) * sin(alpha) * tan(beta))

*full* model (the functional approximation with interreflections, the paper's eqs. for
L_r^1 and L_r^2), ``variant="full"``::

    C1 = A
    C2 = B sin(alpha)                         if cos dphi >= 0
       = B (sin(alpha) - (2 beta/pi)^3)       otherwise
    C3 = 0.125 sigma^2/(sigma^2 + 0.09) (4 alpha beta / pi^2)^2
    f_1 = albedo/pi * (C1 + cos(dphi) C2 tan(beta)
                       + (1 - |cos dphi|) C3 tan((alpha + beta)/2))
    f_2 = 0.17 albedo^2/pi * sigma^2/(sigma^2 + 0.13) * (1 - cos(dphi) (2 beta/pi)^2)
    f_r = f_1 + f_2

(the interreflection term f_2 is quadratic in the albedo, per channel). As published, the
bracket of f_1 becomes negative for grazing forward scattering (both directions near the
horizon, cos dphi < 0) when sigma > 0.664 rad, because cos(dphi) C2 tan(beta) tends to
-(6/pi) B there; it is clamped at 0 (the only departure from the paper's formulas).

Both variants are reciprocal and reduce to Lambert exactly at sigma = 0. ``sigma`` is in
radians, valid range [0, pi/2) (slopes of 90 degrees are not a surface). Neither variant is
energy conserving in the sense of :attr:`BRDF.energy_conserving`. Directional albedo with
albedo = 1, measured by quadrature (``tests/test_lambert.py``): at normal incidence it is
exactly A (qualitative) and A + 0.17 sigma^2/(sigma^2 + 0.13) (full), below 1 and falling
with sigma; towards grazing incidence it rises and passes 1 for small sigma, up to 1.015
(qualitative, sigma ~ 0.2) and 1.05 (full, sigma ~ 0.3) at theta_i = 89.9 deg.

Numerics. The qualitative term is evaluated without angles: cos(dphi) sin(alpha) sin(beta)
is the projected dot product wi_x wo_x + wi_y wo_y, and cos(beta) = max(cos_i, cos_o), so
no azimuth (undefined along the normal) and no arccos (infinite slope at 1) appear. The full
model needs the angles themselves: theta = atan2(sin, cos) with a guarded sin, and cos(dphi)
from the guarded :func:`cos_phi`/:func:`sin_phi` (where theta = 0 its value is arbitrary but
every term it multiplies vanishes with beta). tan((alpha + beta)/2) is written as
(sin_i + sin_o)/(cos_i + cos_o).

All models return f_r without the cosine factor, in 1/sr, directions in the local frame
(z = normal) pointing away from the surface.
"""

from __future__ import annotations

import math
from typing import Literal

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxrefl._errors import JaxreflError

from ._base import BRDF, Param
from ._frame import cos_phi, cos_theta, safe_sqrt, sin2_theta, sin_phi

__all__ = ["Lambert", "OrenNayar", "broadcast_inputs"]

ALBEDO = Param(
    name="albedo",
    kind="color",
    default=0.5,
    lower=0.0,
    upper=1.0,
    units="1 (directional-hemispherical reflectance)",
    doc="diffuse albedo per channel",
)

SIGMA = Param(
    name="sigma",
    kind="scalar",
    default=0.3,
    lower=0.0,
    upper=math.pi / 2,
    units="rad",
    doc="standard deviation of the facet slope angle (Oren-Nayar); valid in [0, pi/2)",
)

# cos(beta) = max(cos_i, cos_o) divides in tan(beta) (finite unless *both* directions are
# grazing; f cos(theta_i) stays bounded by B anyway). It is > 0 above the horizon, but a
# subnormal cosine would overflow 1/cos and its derivative in float32; the floor sits below
# the cos = 1e-6 edge the contract promises, so it never changes a value there.
_COS_FLOOR = 1e-7


def broadcast_inputs(
    spec: tuple[Param, ...], p: dict[str, Array], wi: Array, wo: Array
) -> tuple[dict[str, Array], Array, Array, tuple[int, ...]]:
    """Broadcast parameters and directions to one batch shape, explicitly.

    Scalars become ``(*batch,)``, colours ``(*batch, C)``, lobes ``(*batch, L, 4)`` and
    directions ``(*batch, 3)``, so that model code can combine them without implicit rank
    promotion (which the tests make an error).
    """

    def core(kind: str) -> int:
        return {"scalar": 0, "color": 1, "lobes": 2}[kind]

    shapes = [wi.shape[:-1], wo.shape[:-1]]
    for q in spec:
        v = p[q.name]
        k = core(q.kind)
        shapes.append(v.shape[: v.ndim - k])
    batch = tuple(jnp.broadcast_shapes(*shapes))
    out = {}
    for q in spec:
        v = p[q.name]
        k = core(q.kind)
        out[q.name] = jnp.broadcast_to(v, (*batch, *v.shape[v.ndim - k :]))
    return out, jnp.broadcast_to(wi, (*batch, 3)), jnp.broadcast_to(wo, (*batch, 3)), batch


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


class OrenNayar(BRDF):
    """Oren–Nayar (1994) rough diffuse reflection; see the module docstring for the math.

    ``variant="qualitative"`` (default): the A, B model. ``variant="full"``: the C1, C2, C3
    model plus the interreflection term. Parameters ``albedo`` (colour, [0, 1]) and ``sigma``
    (radians, [0, pi/2)); sigma = 0 is Lambert exactly. Returns f_r (no cosine), 1/sr.
    """

    variant: str = eqx.field(static=True)

    def __init__(self, variant: Literal["qualitative", "full"] = "qualitative"):
        if variant not in ("qualitative", "full"):
            raise JaxreflError(f"variant must be 'qualitative' or 'full', got {variant!r}")
        self.variant = variant

    @property
    def params(self) -> tuple[Param, ...]:
        return (ALBEDO, SIGMA)

    def _eval(
        self, p: dict[str, Array], wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]
    ) -> Float[Array, "*b C"]:
        p, wi, wo, _ = broadcast_inputs(self.params, p, wi, wo)
        albedo = p["albedo"]
        s2 = p["sigma"] * p["sigma"]
        c1 = 1.0 - 0.5 * s2 / (s2 + 0.33)  # A
        b = 0.45 * s2 / (s2 + 0.09)  # B
        cos_i, cos_o = cos_theta(wi), cos_theta(wo)
        cos_beta = jnp.maximum(jnp.maximum(cos_i, cos_o), _COS_FLOOR)
        # cos(dphi) sin(alpha) sin(beta) = sin_i sin_o cos(dphi) = projected dot product.
        dot_xy = wi[..., 0] * wo[..., 0] + wi[..., 1] * wo[..., 1]
        if self.variant == "qualitative":
            shape = c1 + b * jnp.maximum(dot_xy, 0.0) / cos_beta
            return albedo / jnp.pi * shape[..., None]

        sin_i, sin_o = safe_sqrt(sin2_theta(wi)), safe_sqrt(sin2_theta(wo))
        theta_i, theta_o = jnp.arctan2(sin_i, cos_i), jnp.arctan2(sin_o, cos_o)
        alpha = jnp.maximum(theta_i, theta_o)
        beta = jnp.minimum(theta_i, theta_o)
        tan_beta = jnp.minimum(sin_i, sin_o) / cos_beta
        cos_dphi = cos_phi(wi) * cos_phi(wo) + sin_phi(wi) * sin_phi(wo)
        two_beta_pi = 2.0 * beta / jnp.pi
        # cos(dphi) C2 tan(beta) = B [dot_xy / cos(beta) - [cos dphi < 0] cos(dphi) (2b/pi)^3 tan b]
        term2 = b * (
            dot_xy / cos_beta - jnp.where(cos_dphi < 0.0, cos_dphi * two_beta_pi**3 * tan_beta, 0.0)
        )
        c3 = 0.125 * s2 / (s2 + 0.09) * (4.0 * alpha * beta / jnp.pi**2) ** 2
        # tan((alpha + beta)/2) = (sin a + sin b)/(cos a + cos b); the sum of cosines is
        # floored like cos(beta) (it only vanishes when both directions are grazing).
        tan_half = (sin_i + sin_o) / jnp.maximum(cos_i + cos_o, _COS_FLOOR)
        term3 = (1.0 - jnp.abs(cos_dphi)) * c3 * tan_half
        # Clamp: the published approximation of the single-bounce term turns negative for
        # grazing forward scattering (theta_i, theta_o -> 90 deg, cos dphi < 0: the C2 term
        # tends to -(6/pi) B) once sigma > 0.664; a BRDF cannot be negative, so it stops at 0.
        f1 = albedo / jnp.pi * jnp.maximum(c1 + term2 + term3, 0.0)[..., None]
        inter = 0.17 * s2 / (s2 + 0.13) * (1.0 - cos_dphi * two_beta_pi**2)
        f2 = (albedo * albedo) / jnp.pi * inter[..., None]
        return f1 + f2

"""Fresnel reflectance: exact dielectric and conductor formulas, Schlick's approximation, and
the Fresnel *parts* that microfacet models plug in.

Functions (no parameter dicts; plain arrays that broadcast):

* :func:`fresnel_dielectric` -- unpolarised reflectance of a smooth dielectric interface,
  relative index ``eta = n_t / n_i`` (pbrt-v4 ``FrDielectric``; Hecht, *Optics*, sec. 4.6).
  Sign convention for ``cos_theta_i`` (pbrt-v4): positive means the light arrives from the
  side the normal points to (outside, index n_i); negative means it arrives from inside, and
  the formula then uses ``1/eta`` and ``|cos_theta_i|``. Total internal reflection gives
  exactly 1, with zero (finite) gradient.
* :func:`fresnel_dielectric_polarized` -- the same, split into (R_s, R_p).
* :func:`fresnel_conductor` -- unpolarised reflectance for a complex index ``eta + i k``
  (real-arithmetic form of Moeller, *Optics* 1988, as in Mitsuba 3 ``fresnel_conductor``),
  rewritten without cancellation; with ``k = 0`` it equals :func:`fresnel_dielectric`.
* :func:`fresnel_schlick` -- F0 + (1 - F0)(1 - cos)^5 (Schlick 1994), and
  :func:`f0_from_eta` -- F0 = ((eta - 1)/(eta + 1))^2 (Hecht, *Optics*, sec. 4.6, normal incidence).

Parts (``eqx.Module``): each declares the :class:`Param` entries it needs and maps
``(p, cos_theta_d) -> F`` of shape ``(*b, C)``, where ``cos_theta_d = wo . wh`` (= wi . wh) is
the cosine of the angle between a direction and the microfacet normal. Colour parameters in
``p`` carry a trailing channel axis and must have the same rank as ``cos_theta_d[..., None]``
(the assembling model aligns ranks). Every part returns values in [0, 1] when its colour
parameters are within their declared ranges, so a microfacet model built on it keeps F <= 1.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._base import Param
from ._frame import safe_div, safe_sqrt

__all__ = [
    "ConductorFresnel",
    "DielectricFresnel",
    "FresnelPart",
    "NoFresnel",
    "SchlickFresnel",
    "f0_from_eta",
    "fresnel_conductor",
    "fresnel_dielectric",
    "fresnel_dielectric_polarized",
    "fresnel_schlick",
]


# --------------------------------------------------------------------------- functions
def fresnel_dielectric_polarized(
    cos_theta_i: Float[ArrayLike, "*b"], eta: Float[ArrayLike, "*b"]
) -> tuple[Float[Array, "*b"], Float[Array, "*b"]]:
    """Reflectances (R_s, R_p) of a smooth dielectric interface (Hecht, *Optics*, sec. 4.6).

    ``eta = n_t / n_i > 0`` is the relative index; ``cos_theta_i`` in [-1, 1] with the sign
    convention of :func:`fresnel_dielectric`. R_p vanishes at Brewster's angle
    tan(theta_B) = eta. Total internal reflection (cos^2 theta_t <= 0) gives R_s = R_p = 1.
    """
    cos_i = jnp.asarray(cos_theta_i)
    eta = jnp.asarray(eta)
    # Clamp: only round-off of a dot product of unit vectors leaves [-1, 1].
    cos_i = jnp.clip(cos_i, -1.0, 1.0)
    inside = cos_i < 0
    # Arriving from inside: the interface is seen with the inverse relative index.
    eta = jnp.where(inside, 1.0 / eta, eta)
    cos_i = jnp.abs(cos_i)
    # cos^2 theta_t = 1 - sin^2 theta_i / eta^2 = ((eta - 1)(eta + 1) + cos^2 theta_i) / eta^2:
    # the second form has no cancellation for eta >= 1 (exactly cos_i at eta = 1, even at
    # grazing incidence in float32, where 1 - sin^2/eta^2 rounds to 0 or to 1e-7 at random).
    cos2_t = ((eta - 1.0) * (eta + 1.0) + cos_i * cos_i) / (eta * eta)
    tir = cos2_t <= 0.0
    # Gradient-safe: under TIR the transmitted cosine does not exist; use 1 and mask below.
    cos_t = jnp.sqrt(jnp.where(tir, 1.0, cos2_t))
    r_s = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    r_p = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    one = jnp.ones((), dtype=r_s.dtype)
    return jnp.where(tir, one, r_s * r_s), jnp.where(tir, one, r_p * r_p)


def fresnel_dielectric(
    cos_theta_i: Float[ArrayLike, "*b"], eta: Float[ArrayLike, "*b"]
) -> Float[Array, "*b"]:
    """Unpolarised Fresnel reflectance of a smooth dielectric, F = (R_s + R_p) / 2.

    Args:
        cos_theta_i: cosine of the incidence angle, in [-1, 1]. Positive: light arrives from
            the outside (index n_i, the side the normal points to); negative: from the inside,
            in which case ``1/eta`` is used (pbrt-v4 ``FrDielectric`` convention).
        eta: relative index of refraction n_t / n_i > 0 (e.g. 1.5 for glass in air). eta < 1
            (or a negative cosine with eta > 1) can give total internal reflection: F = 1.

    F(normal incidence) = ((eta - 1)/(eta + 1))^2, e.g. 0.04 for eta = 1.5 (Hecht, *Optics*).
    Values and gradients are finite everywhere for eta > 0, including grazing incidence and
    the critical angle.
    """
    r_s, r_p = fresnel_dielectric_polarized(cos_theta_i, eta)
    return 0.5 * (r_s + r_p)


def fresnel_conductor(
    cos_theta_i: Float[ArrayLike, "*b"],
    eta: Float[ArrayLike, "*b"],
    k: Float[ArrayLike, "*b"],
) -> Float[Array, "*b"]:
    """Unpolarised Fresnel reflectance for a complex relative index eta + i k (eta, k >= 0).

    With z = (eta + i k)^2 - sin^2(theta) = t + 2 i eta k and sqrt(z) = a + i b (principal
    root), the exact reflectances are (Moeller, *Optics*, 1988; the form used by Mitsuba 3
    ``fresnel_conductor``, pbrt-v4 ``FrComplex`` in complex arithmetic)::

        R_s = ((a - c)^2 + b^2) / ((a + c)^2 + b^2),                         c = cos(theta)
        R_p = R_s ((a c - s^2)^2 + b^2 c^2) / ((a c + s^2)^2 + b^2 c^2),     s^2 = 1 - c^2
        F   = (R_s + R_p) / 2

    a and b are computed without cancellation: u = sqrt((|z| + |t|)/2) is the larger of the
    two and eta k / u the smaller (the usual stable complex square root); the textbook
    ``a^2 = (|z| + t)/2`` loses digits in float32 for metals, where t << 0. With k = 0 this
    is exactly :func:`fresnel_dielectric` (including total internal reflection for eta < 1).

    ``cos_theta_i`` is clamped to [0, 1]: a conductor is opaque, light only arrives from
    outside. Values and gradients are finite for eta in [0, 10], k in [0, 10], any angle
    (the single non-smooth point, eta = sin(theta) with k = 0, gets a zero gradient).
    """
    c = jnp.asarray(cos_theta_i)
    eta = jnp.asarray(eta)
    k = jnp.asarray(k)
    # Clamp: light cannot arrive from inside an opaque conductor; negative is round-off or
    # a below-horizon caller that masks the result anyway.
    c = jnp.clip(c, 0.0, 1.0)
    s2 = (1.0 - c) * (1.0 + c)
    # t = eta^2 - k^2 - sin^2 written as (eta - 1)(eta + 1) - k^2 + cos^2: no cancellation
    # near eta = 1 at grazing incidence (the dielectric limit), see fresnel_dielectric.
    t = (eta - 1.0) * (eta + 1.0) - k * k + c * c
    ek = eta * k
    abs_z = safe_sqrt(t * t + 4.0 * ek * ek)
    u = safe_sqrt(0.5 * (abs_z + jnp.abs(t)))
    v = safe_div(ek, u)
    pos = t >= 0
    a = jnp.where(pos, u, v)
    b = jnp.where(pos, v, u)
    b2 = b * b
    num_s = (a - c) ** 2 + b2
    den_s = (a + c) ** 2 + b2
    # den_s = 0 only for eta = 1, k = 0 at grazing incidence, whose limit is F = 1.
    r_s = jnp.where(den_s > 0, num_s / jnp.where(den_s > 0, den_s, 1.0), 1.0)
    ac = a * c
    b2c2 = b2 * c * c
    num_p = (ac - s2) ** 2 + b2c2
    den_p = (ac + s2) ** 2 + b2c2
    # den_p = 0 only for eta = k = 0 at normal incidence (a perfect mirror): ratio 1.
    ratio = jnp.where(den_p > 0, num_p / jnp.where(den_p > 0, den_p, 1.0), 1.0)
    return 0.5 * (r_s + r_s * ratio)


def fresnel_schlick(
    cos_theta: Float[ArrayLike, "*b"], f0: Float[ArrayLike, "*b"]
) -> Float[Array, "*b"]:
    """Schlick's approximation F = F0 + (1 - F0)(1 - cos)^5 (Schlick 1994, eq. 24).

    Exact at normal incidence (F = F0) and at grazing incidence (F = 1); ``cos_theta`` is
    clamped to [0, 1] (round-off only). F0 in [0, 1] gives F in [F0, 1].
    """
    c = jnp.clip(jnp.asarray(cos_theta), 0.0, 1.0)  # clamp: round-off of unit-vector dots
    m = 1.0 - c
    m2 = m * m
    return jnp.asarray(f0 + (1.0 - f0) * (m2 * m2 * m))


def f0_from_eta(eta: Float[ArrayLike, "*b"]) -> Float[Array, "*b"]:
    """Normal-incidence reflectance of a dielectric, ((eta - 1)/(eta + 1))^2 (Hecht, sec. 4.6)."""
    eta = jnp.asarray(eta)
    r = (eta - 1.0) / (eta + 1.0)
    return r * r


# --------------------------------------------------------------------------- parts
SPECULAR_F0 = Param(
    name="specular",
    kind="color",
    default=0.04,
    lower=0.0,
    upper=1.0,
    units="1 (reflectance at normal incidence)",
    doc="Schlick F0 per channel; 0.04 is glass/plastic (eta = 1.5), metals 0.5-0.98",
)
SPECULAR_SCALE = Param(
    name="specular",
    kind="color",
    default=0.04,
    lower=0.0,
    upper=1.0,
    units="1",
    doc="constant, angle-independent Fresnel factor (a colour scale of the specular lobe)",
)
ETA_DIELECTRIC = Param(
    name="eta",
    kind="color",
    default=1.5,
    lower=1.0,
    upper=4.0,
    units="1 (relative index n_t / n_i)",
    doc=(
        "relative index of refraction of the surface (1.33 water, 1.5 glass, 2.4 diamond); "
        "eta = 1 is a safe edge (no interface: F = 0, gradient 0)"
    ),
)
ETA_CONDUCTOR = Param(
    name="eta",
    kind="color",
    default=(0.143, 0.374, 1.442),  # gold, RGB (pbrt-v3 scenes, from Palik's data)
    lower=0.0,
    upper=10.0,
    units="1 (real part of the relative complex index)",
    doc="real part of the complex index of refraction per channel",
)
K_CONDUCTOR = Param(
    name="k",
    kind="color",
    default=(3.983, 2.385, 1.603),  # gold, RGB (pbrt-v3 scenes, from Palik's data)
    lower=0.0,
    upper=10.0,
    units="1 (extinction coefficient)",
    doc="imaginary part of the complex index of refraction per channel",
)


class FresnelPart(eqx.Module):
    """A Fresnel term F(cos_theta_d) for a microfacet model: declares its parameters and
    returns F of shape ``(*b, C)`` for ``cos_theta_d`` of shape ``(*b,)``."""

    @property
    @abc.abstractmethod
    def params(self) -> tuple[Param, ...]:
        """Parameters this part reads from ``p``."""

    @property
    def at_most_one(self) -> bool:
        """Whether F <= 1 for every parameter value in its declared range."""
        return True

    @abc.abstractmethod
    def __call__(
        self, p: dict[str, Array], cos_theta_d: Float[Array, " *b"]
    ) -> Float[Array, "*b C"]:
        """F for the cosine between a direction and the microfacet normal."""


class SchlickFresnel(FresnelPart):
    """F = F0 + (1 - F0)(1 - cos_theta_d)^5 with F0 = ``specular`` (Schlick 1994)."""

    @property
    def params(self) -> tuple[Param, ...]:
        return (SPECULAR_F0,)

    def __call__(self, p: dict[str, Array], cos_theta_d: Float[Array, " *b"]) -> Array:
        return fresnel_schlick(cos_theta_d[..., None], p["specular"])


class DielectricFresnel(FresnelPart):
    """Exact unpolarised dielectric Fresnel with relative index ``eta`` (colour, 1..4).

    The light arrives from outside (cos_theta_d > 0), so with eta >= 1 there is no total
    internal reflection. eta -> 1 is safe: F -> 0 smoothly (F ~ ((eta-1)/2)^2 at normal
    incidence), with a finite gradient, and F = 0 exactly at eta = 1 for every cos_theta_d > 0
    in float32 too (the transmitted cosine is computed without cancellation). Only the
    limit cos_theta_d -> 0 stays singular: F -> 1 for any eta != 1.
    """

    @property
    def params(self) -> tuple[Param, ...]:
        return (ETA_DIELECTRIC,)

    def __call__(self, p: dict[str, Array], cos_theta_d: Float[Array, " *b"]) -> Array:
        return fresnel_dielectric(cos_theta_d[..., None], p["eta"])


class ConductorFresnel(FresnelPart):
    """Exact unpolarised conductor Fresnel with complex index ``eta + i k`` (colours).

    Defaults are gold in RGB; see :func:`jaxrefl.spectral.load_ior` for measured spectra.
    """

    @property
    def params(self) -> tuple[Param, ...]:
        return (ETA_CONDUCTOR, K_CONDUCTOR)

    def __call__(self, p: dict[str, Array], cos_theta_d: Float[Array, " *b"]) -> Array:
        return fresnel_conductor(cos_theta_d[..., None], p["eta"], p["k"])


class NoFresnel(FresnelPart):
    """F = ``specular``: no angular dependence, a colour scale of the specular lobe."""

    @property
    def params(self) -> tuple[Param, ...]:
        return (SPECULAR_SCALE,)

    def __call__(self, p: dict[str, Array], cos_theta_d: Float[Array, " *b"]) -> Array:
        spec = p["specular"]
        return spec + jnp.zeros_like(cos_theta_d)[..., None]

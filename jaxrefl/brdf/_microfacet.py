"""Microfacet parts: normal distributions (Beckmann, GGX) and shadowing-masking terms.

Distributions (Walter et al. 2007, "Microfacet models for refraction through rough
surfaces"; Heitz 2014, "Understanding the masking-shadowing function"). In the local frame
(z = normal, x = tangent) with microfacet normal h = (h_x, h_y, h_z), h_z > 0::

    Beckmann  D(h) = exp(-((h_x/a_x)^2 + (h_y/a_y)^2) / h_z^2) / (pi a_x a_y h_z^4)
    GGX       D(h) = 1 / (pi a_x a_y ((h_x/a_x)^2 + (h_y/a_y)^2 + h_z^2)^2)

both normalised so that the projected microfacet area is the macro-surface area,
int D(h) h_z dw_h = 1 over the hemisphere. The GGX form is the cancellation-free
"alpha^2 cos^2 + sin^2" denominator, sin^2 taken as h_x^2 + h_y^2: the usual
(alpha^2 - 1) cos^2 + 1 form computes sin^2 as 1 - cos^2, which cancels near the normal,
where a narrow lobe peaks, and loses relative precision in float32. Isotropic:
a_x = a_y = ``alpha``; anisotropic: a_x = ``alpha_u`` along the tangent x, a_y = ``alpha_v``
along y. alpha is the distribution's own
width (Beckmann: RMS slope), in [1e-4, 1], dimensionless.

Smith Lambda, exact for each distribution (Heitz 2014, sec. 5.3; Walter 2007, eqs. 25-27),
with r^2 = (a_x w_x)^2 + (a_y w_y)^2 = alpha(phi)^2 sin^2(theta), c = cos(theta) = w_z and
a = c / r = 1 / (alpha(phi) tan(theta))::

    GGX       Lambda = (-1 + sqrt(1 + 1/a^2)) / 2
    Beckmann  Lambda = (erf(a) - 1) / 2 + exp(-a^2) / (2 a sqrt(pi))

G1(w, h) = chi+(w.h) / (1 + Lambda(w)). Every part works with c * Lambda, which stays finite
as c -> 0 (GGX: r^2 / (2 (c + sqrt(c^2 + r^2))); Beckmann: (r exp(-a^2)/sqrt(pi) -
c erfc(a)) / 2), so the visibility term V = G / (4 cos_i cos_o) of each shadowing part is
finite at grazing angles (it tends to a finite limit; f_r * cos still goes to 0).

Roughness -> 0: alpha is floored at 1e-4 (as Mitsuba 3 does) and no mirror special case is
made; at alpha = 1e-4 and h = normal D = 1/(pi alpha^2) ~ 3.2e7 and dD/dalpha ~ 6e11, both
finite in float32. The limit alpha -> 0 is a Dirac delta that no finite grid resolves.

Shadowing parts return V = G(wi, wo, h) / (4 cos_i cos_o) (the "visibility" of real-time
rendering), so models need no division by the cosines:

* :class:`SmithHeightCorrelated`: G = 1/(1 + Lambda_i + Lambda_o) (Heitz 2014, eq. 99).
* :class:`SmithSeparable`: G = G1(wi) G1(wo) (Walter 2007, eq. 23; Heitz 2014, eq. 98).
* :class:`VGroove`: G = min(1, 2 h_z c_o / (wo.h), 2 h_z c_i / (wo.h)) (Torrance & Sparrow
  1967; Cook & Torrance 1982); independent of the distribution.

Array conventions: directions ``(*b, 3)`` unit vectors pointing away from the surface,
scalar parameters ``(*b,)`` of the same rank as the direction batch (the model aligns ranks).
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
from jax.scipy.special import erfc
from jaxtyping import Array, Float

from ._base import Param
from ._frame import safe_div, safe_sqrt

__all__ = [
    "ALPHA_MIN",
    "GGX",
    "Beckmann",
    "Distribution",
    "Shadowing",
    "SmithHeightCorrelated",
    "SmithSeparable",
    "VGroove",
]

# Mitsuba 3 floors alpha at 1e-4 too: below it D and its gradient leave the float32 range
# within a few ulps of the normal, and no measurement resolves a narrower lobe anyway.
ALPHA_MIN = 1e-4

_SQRT_PI = 1.7724538509055159

# Beckmann Lambda is set to 0 where a = c/r > 10: there Lambda < exp(-100)/400 ~ 1e-46,
# far below float64 resolution relative to 1, and the guard keeps 1/r out of gradients.
_BECKMANN_A_MAX = 10.0
# Beckmann D is set to 0 where the exponent exceeds 700: exp(-700) ~ 1e-304 is the float64
# underflow edge, and the guard keeps e / h_z^2 from overflowing near the horizon.
_BECKMANN_EXP_MAX = 700.0


def _alpha_param(name: str, doc: str) -> Param:
    return Param(
        name=name,
        kind="scalar",
        default=0.2,
        lower=ALPHA_MIN,
        upper=1.0,
        units="1 (distribution width; Beckmann: RMS slope)",
        doc=doc,
    )


ALPHA = _alpha_param("alpha", "isotropic microfacet roughness (the distribution's alpha)")
ALPHA_U = _alpha_param("alpha_u", "roughness along the tangent (x)")
ALPHA_V = _alpha_param("alpha_v", "roughness along the bitangent (y)")


class Distribution(eqx.Module):
    """A microfacet normal distribution: D(h), Smith Lambda(w), G1(w, h).

    ``anisotropic=False`` reads ``alpha``; ``True`` reads ``alpha_u`` and ``alpha_v``.
    """

    anisotropic: bool = eqx.field(default=False, static=True)

    @property
    def params(self) -> tuple[Param, ...]:
        return (ALPHA_U, ALPHA_V) if self.anisotropic else (ALPHA,)

    def alphas(self, p: dict[str, Array]) -> tuple[Array, Array]:
        """(a_x, a_y), floored at :data:`ALPHA_MIN` (see the module docstring)."""
        if self.anisotropic:
            ax, ay = p["alpha_u"], p["alpha_v"]
        else:
            ax = ay = p["alpha"]
        # Floor: below 1e-4 values and gradients leave float32 range (Mitsuba does the same).
        # ``where(>=)`` rather than ``maximum`` keeps the full gradient at exactly ALPHA_MIN.
        ax = jnp.where(ax >= ALPHA_MIN, ax, ALPHA_MIN)
        ay = jnp.where(ay >= ALPHA_MIN, ay, ALPHA_MIN)
        return ax, ay

    @abc.abstractmethod
    def D(self, p: dict[str, Array], wh: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
        """Microfacet normal density (1/sr), 0 for h_z <= 0."""

    @abc.abstractmethod
    def cos_lambda(self, p: dict[str, Array], w: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
        """cos(theta) * Lambda(w) for w_z >= 0: finite (-> r/(2 sqrt pi) or r/2) at w_z -> 0."""

    def _r2(self, p: dict[str, Array], w: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
        ax, ay = self.alphas(p)
        x = ax * w[..., 0]
        y = ay * w[..., 1]
        return x * x + y * y

    def Lambda(self, p: dict[str, Array], w: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
        """Smith Lambda(w) (dimensionless); +inf for w_z <= 0."""
        c = w[..., 2]
        ok = c > 0
        lam = self.cos_lambda(p, w) / jnp.where(ok, c, 1.0)
        return jnp.where(ok, lam, jnp.inf)

    def G1(
        self, p: dict[str, Array], w: Float[Array, "*b 3"], wh: Float[Array, "*b 3"]
    ) -> Float[Array, " *b"]:
        """Smith masking chi+(w.h) chi+(w_z) / (1 + Lambda(w)), in [0, 1]."""
        c = jnp.maximum(w[..., 2], 0.0)  # below the horizon G1 = 0; keep c_lambda's input valid
        g = safe_div(c, c + self.cos_lambda(p, w))
        ok = (jnp.sum(w * wh, axis=-1) > 0) & (c > 0)
        return jnp.where(ok, g, 0.0)


class GGX(Distribution):
    """Trowbridge-Reitz / GGX distribution (Trowbridge & Reitz 1975; Walter et al. 2007)."""

    def D(self, p: dict[str, Array], wh: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
        ax, ay = self.alphas(p)
        hx = wh[..., 0] / ax
        hy = wh[..., 1] / ay
        hz = wh[..., 2]
        q = hx * hx + hy * hy + hz * hz  # >= min(1, 1/alpha^2) > 0 for a unit vector
        ok = (hz > 0) & (q > 0)
        q = jnp.where(ok, q, 1.0)
        return jnp.where(ok, 1.0 / (jnp.pi * ax * ay * q * q), 0.0)

    def cos_lambda(self, p: dict[str, Array], w: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
        # c Lambda = (sqrt(c^2 + r^2) - c) / 2 = r^2 / (2 (c + sqrt(c^2 + r^2))): no cancellation.
        c = jnp.maximum(w[..., 2], 0.0)  # defined for the upper hemisphere only
        r2 = self._r2(p, w)
        return safe_div(r2, 2.0 * (c + safe_sqrt(c * c + r2)))


class Beckmann(Distribution):
    """Beckmann distribution (Beckmann & Spizzichino 1963; Walter et al. 2007, eq. 25).

    Lambda is the exact erf form (Walter eq. 27 states G1 with it; its rational
    approximation is not used).
    """

    def D(self, p: dict[str, Array], wh: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
        ax, ay = self.alphas(p)
        hx = wh[..., 0] / ax
        hy = wh[..., 1] / ay
        hz = wh[..., 2]
        e = hx * hx + hy * hy
        hz2 = hz * hz
        # Gradient-safe: decide with a product (no division) and replace inputs first.
        ok = (hz > 0) & (e < _BECKMANN_EXP_MAX * hz2)
        hz2 = jnp.where(ok, hz2, 1.0)
        e = jnp.where(ok, e, 0.0)
        d = jnp.exp(-e / hz2) / (jnp.pi * ax * ay * hz2 * hz2)
        return jnp.where(ok, d, 0.0)

    def cos_lambda(self, p: dict[str, Array], w: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
        # c Lambda = (r exp(-a^2)/sqrt(pi) - c erfc(a)) / 2 with a = c / r.
        c = jnp.maximum(w[..., 2], 0.0)  # defined for the upper hemisphere only
        r = safe_sqrt(self._r2(p, w))
        ok = (r > 0) & (c <= _BECKMANN_A_MAX * r)
        r = jnp.where(ok, r, 1.0)
        c = jnp.where(ok, c, 0.0)
        a = c / r
        out = 0.5 * (r * jnp.exp(-a * a) / _SQRT_PI - c * erfc(a))
        # Clamp: Lambda >= 0 exactly; the difference above can round to a tiny negative.
        return jnp.where(ok, jnp.maximum(out, 0.0), 0.0)


# --------------------------------------------------------------------------- shadowing
# The shadowing terms' directions (unit, local frame, pointing away from the surface) and
# their value per direction triple.
_Dir = Float[Array, "*b 3"]
_PerDir = Float[Array, " *b"]


def _cosines(wi: Array, wo: Array, wh: Array) -> tuple[Array, Array, Array, Array]:
    ci = wi[..., 2]
    co = wo[..., 2]
    # wi.h == wo.h for the reflection half vector; the mean makes the term exactly symmetric.
    d = 0.5 * (jnp.sum(wi * wh, axis=-1) + jnp.sum(wo * wh, axis=-1))
    ok = (ci > 0) & (co > 0) & (d > 0)
    return ci, co, d, ok


def _reciprocal(den: Array, ok: Array) -> Array:
    """1 / den where ``ok`` and den > 0, else 0; den is floored at sqrt(tiny) of its dtype.

    Clamp: the derivative of 1/den is -1/den^2, which overflows for den below sqrt(tiny)
    (1.5e-154 in float64, 1.1e-19 in float32): both cosines within that of the horizon. There
    D(h) is usually 0, and inf * 0 would make the gradient NaN. The floor caps V at
    1/sqrt(tiny) with a zero gradient below it, so values and gradients stay finite."""
    ok = ok & (den > 0)
    floor = jnp.sqrt(jnp.finfo(den.dtype).tiny)
    d = jnp.where(ok, jnp.where(den >= floor, den, floor), 1.0)
    return jnp.where(ok, 1.0 / d, 0.0)


class Shadowing(eqx.Module):
    """A shadowing-masking term, returned as V = G / (4 cos_i cos_o) (dimensionless)."""

    @abc.abstractmethod
    def visibility(
        self, dist: Distribution, p: dict[str, Array], wi: _Dir, wo: _Dir, wh: _Dir
    ) -> _PerDir:
        """G(wi, wo, h) / (4 cos_i cos_o); 0 where a cosine or wo.h is <= 0."""

    def G(self, dist: Distribution, p: dict[str, Array], wi: _Dir, wo: _Dir, wh: _Dir) -> _PerDir:
        """The shadowing-masking factor G in [0, 1] itself."""
        return self.visibility(dist, p, wi, wo, wh) * 4.0 * wi[..., 2] * wo[..., 2]


class SmithHeightCorrelated(Shadowing):
    """G = 1 / (1 + Lambda(wi) + Lambda(wo)) (Heitz 2014, eq. 99): the default; reciprocal,
    and with it a microfacet BRDF loses only the energy of multiple scattering."""

    def visibility(
        self, dist: Distribution, p: dict[str, Array], wi: Array, wo: Array, wh: Array
    ) -> Array:
        ci, co, _, ok = _cosines(wi, wo, wh)
        # 4 c_i c_o (1 + L_i + L_o) = 4 (c_i c_o + c_o (c_i L_i) + c_i (c_o L_o)).
        den = 4.0 * (ci * co + co * dist.cos_lambda(p, wi) + ci * dist.cos_lambda(p, wo))
        return _reciprocal(den, ok)


class SmithSeparable(Shadowing):
    """G = G1(wi) G1(wo) (Walter et al. 2007, eq. 23; Heitz 2014, eq. 98): ignores the
    correlation of masking and shadowing, so it darkens more than
    :class:`SmithHeightCorrelated`."""

    def visibility(
        self, dist: Distribution, p: dict[str, Array], wi: Array, wo: Array, wh: Array
    ) -> Array:
        ci, co, _, ok = _cosines(wi, wo, wh)
        den = 4.0 * (ci + dist.cos_lambda(p, wi)) * (co + dist.cos_lambda(p, wo))
        return _reciprocal(den, ok)


class VGroove(Shadowing):
    """G = min(1, 2 h_z c_o / (wo.h), 2 h_z c_i / (wo.h)) (Torrance & Sparrow 1967; Cook &
    Torrance 1982, eq. in sec. 2.2): symmetric V-grooves, independent of the distribution."""

    def visibility(
        self, dist: Distribution, p: dict[str, Array], wi: Array, wo: Array, wh: Array
    ) -> Array:
        ci, co, d, ok = _cosines(wi, wo, wh)
        ci = jnp.where(ok, ci, 1.0)
        co = jnp.where(ok, co, 1.0)
        d = jnp.where(ok, d, 1.0)
        hz = wh[..., 2]
        # min(1, 2 h_z min(c_i, c_o) / d) / (4 c_i c_o), written without dividing by the
        # smaller cosine: the second branch is h_z / (2 d max(c_i, c_o)).
        v = jnp.minimum(1.0 / (4.0 * ci * co), hz / (2.0 * d * jnp.maximum(ci, co)))
        return jnp.where(ok, v, 0.0)

"""Phong and Blinn–Phong: a Lambertian base plus a cosine-power lobe.

All four forms share ``albedo`` (colour, [0, 1]; the diffuse part is albedo/pi, so the
``kd`` of the lecture-notes form "kd + ks cos^n" is albedo/pi here), ``specular`` (colour,
[0, 1], the lobe scale ks) and ``exponent`` (scalar n, [0, 1e5]). They return f_r without the
cosine factor, in 1/sr; directions are unit vectors in the local frame (z = normal) pointing
away from the surface.

Phong (Phong 1975, as a BRDF)
-----------------------------
cos(theta_r) = max(0, wo . reflect(wi)), the cosine of the angle between wo and the mirror
direction of wi (symmetric in wi and wo).

* classic (``normalized=False``)::

      f_r = albedo/pi + specular * cos^n(theta_r) / cos(theta_i)

  so that f_r cos(theta_i) is the shading-language "ks cos^n". Dividing by cos(theta_i) only
  makes it **non-reciprocal** (f(wi, wo) != f(wo, wi) unless cos_i = cos_o), and it is not
  energy conserving (the reflected energy diverges at grazing incidence).

* normalized (``normalized=True``; Lewis 1994, "Making shaders more physically plausible",
  Computer Graphics Forum 13(2); the "modified Phong" of Lafortune & Willems 1994)::

      f_r = albedo/pi + specular * (n + 2)/(2 pi) * cos^n(theta_r)

  Reciprocal. The lobe's directional albedo is at most ``specular`` (equality at normal
  incidence), so the model conserves energy when albedo + specular <= 1 per channel; since
  the base contract asks for conservation with *every* colour parameter up to 1,
  :attr:`energy_conserving` stays False (tests check the sum rule numerically).

Blinn–Phong (Blinn 1977), with h = (wi + wo)/|wi + wo| and cos(theta_h) = h_z
------------------------------------------------------------------------------
* classic::     f_r = albedo/pi + specular * cos^n(theta_h) / cos(theta_i)   (non-reciprocal)
* normalized::  f_r = albedo/pi + specular * (n + 8)/(8 pi) * cos^n(theta_h)

  The (n + 8)/(8 pi) factor is from Akenine-Möller, Haines & Hoffman, *Real-Time Rendering*
  (3rd ed., 2008, ch. 7), an approximation to energy normalisation. Measured here
  (``tests/test_phong.py``): with specular = 1 the lobe's directional albedo at normal
  incidence is (n + 8)(n + 2^(-n/2)) / ((n + 2)(n + 4)): 1 at n = 0, at most 1.0752 (at
  n = 8.8), tending to 1 from above as n grows; at grazing incidence it falls far below 1
  (< 0.7 at 85 degrees for n >= 2). So it is not flagged energy conserving.

Numerics: cos^n is exp(n log c) with c guarded (c <= 0 gives exactly 0 and a zero
gradient), so n up to 1e5 gives finite values and finite gradients with respect to c and to
n in float32 and float64; at the exact mirror direction with n = 1e5 the normalised lobe is
(n + 2)/(2 pi) ~ 1.6e4, large but finite.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._base import BRDF, Param
from ._frame import cos_theta, half_vector
from ._lambert import ALBEDO, broadcast_inputs

__all__ = ["SPECULAR", "BlinnPhong", "Phong", "cos_power", "positive_power"]

SPECULAR = Param(
    name="specular",
    kind="color",
    default=0.5,
    lower=0.0,
    upper=1.0,
    units="1 (lobe scale)",
    doc="specular lobe scale per channel",
)

EXPONENT = Param(
    name="exponent",
    kind="scalar",
    default=32.0,
    lower=0.0,
    upper=1e5,
    units="1",
    doc="cosine-power exponent of the specular lobe",
)

# Denominators cos(theta_i) are > 0 above the horizon; a subnormal cosine would overflow 1/cos
# and its derivative in float32. The floor sits below the contract's cos = 1e-6 edge.
_COS_FLOOR = 1e-7
# exp(60) ~ 1e26: the largest lobe value kept. Only lobes scaled above 1 (Lafortune |C| > 1)
# reach it; capping n log x keeps f and n x^(n-1) finite in float32 for n up to 1e5.
_LOG_CAP = 60.0


def positive_power(x: Float[Array, " *b"], n: Float[Array, " *b"]) -> Float[Array, " *b"]:
    """[x]_+^n = exp(n log x) for x > 0, else 0, with finite gradients for n in [0, 1e5].

    Subnormal x counts as 0: the derivative n x^(n-1) of a subnormal x overflows float32 for
    n < 1. The result is capped at exp(60) (see ``_LOG_CAP``).
    """
    pos = x >= jnp.finfo(x.dtype).tiny
    x_safe = jnp.where(pos, x, 1.0)
    t = jnp.minimum(n * jnp.log(x_safe), _LOG_CAP)
    return jnp.where(pos, jnp.exp(t), 0.0)


def cos_power(c: Float[Array, " *b"], n: Float[Array, " *b"]) -> Float[Array, " *b"]:
    """max(c, 0)^n for a cosine c.

    Clamp: round-off can push a cosine a few ulp above 1 (wo equal to the mirror direction
    in float32), which n = 1e5 would amplify by up to ~1%; the cosine is capped at 1.
    """
    return positive_power(jnp.minimum(c, 1.0), n)


class _CosineLobe(BRDF):
    """Shared parts: parameters, claims, the classic/normalized switch."""

    normalized: bool = eqx.field(static=True, default=False)

    @property
    def params(self) -> tuple[Param, ...]:
        return (ALBEDO, SPECULAR, EXPONENT)

    @property
    def reciprocal(self) -> bool:
        # The classic forms divide by cos(theta_i) only, which breaks f(wi, wo) = f(wo, wi).
        return self.normalized

    def _lobe(self, wi: Array, wo: Array, n: Array) -> Array:
        raise NotImplementedError

    def _norm(self, n: Array) -> Array:
        raise NotImplementedError

    def _eval(
        self, p: dict[str, Array], wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]
    ) -> Float[Array, "*b C"]:
        p, wi, wo, _ = broadcast_inputs(self.params, p, wi, wo)
        n = p["exponent"]
        lobe = self._lobe(wi, wo, n)
        if self.normalized:
            scale = self._norm(n)
        else:
            scale = 1.0 / jnp.maximum(cos_theta(wi), _COS_FLOOR)
        return p["albedo"] / jnp.pi + p["specular"] * (scale * lobe)[..., None]


class Phong(_CosineLobe):
    """Phong lobe about the mirror direction; ``normalized`` picks Lewis' (n+2)/(2 pi)."""

    def _lobe(self, wi: Array, wo: Array, n: Array) -> Array:
        # wo . reflect(wi) with reflect(w) = (-w_x, -w_y, w_z), written out (symmetric).
        c = wi[..., 2] * wo[..., 2] - wi[..., 0] * wo[..., 0] - wi[..., 1] * wo[..., 1]
        return cos_power(c, n)

    def _norm(self, n: Array) -> Array:
        return (n + 2.0) / (2.0 * jnp.pi)


class BlinnPhong(_CosineLobe):
    """Blinn–Phong lobe in the half vector; ``normalized`` picks RTR's (n+8)/(8 pi)."""

    def _lobe(self, wi: Array, wo: Array, n: Array) -> Array:
        return cos_power(cos_theta(half_vector(wi, wo)), n)

    def _norm(self, n: Array) -> Array:
        return (n + 8.0) / (8.0 * jnp.pi)

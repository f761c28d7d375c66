"""A per-pixel normal perturbation: a BRDF seen through a tilted shading normal.

A planar sample is rarely flat at the scale of a pixel (grout, bumps, a warped tile). With
the shading normal

    n = (t_x, t_y, 1) / sqrt(1 + t_x^2 + t_y^2)                (t = the surface's slopes)

and the tangent t = normalize(x - (x . n) n), bitangent b = n x t (Gram–Schmidt of the
geometric x axis; the frame turns continuously with n and is the identity at t = 0), the
wrapped model returns, in the *geometric* frame (z = the sample's normal),

    f'(wi, wo) = f(R wi, R wo) * (wi . n) / (wi . z)               [1/sr]

where R maps geometric to shading coordinates (rows t, b, n) and f is the base model. So
f' cos_z = f cos_n: a caller that multiplies by the geometric cosine (a capture's
irradiance = power cos_z / r^2) gets the radiance of the tilted facet, with the *shading*
cosine, as in normal mapping (pbrt-v4, section 10.5.3: the BSDF is evaluated in the
shading frame). Directions below the shading horizon give 0 (the base model's guard);
below the geometric horizon, 0 as for every model.

Parameters: the base model's, then ``tilt_x`` and ``tilt_y`` (scalar slopes, dimensionless,
in [-1, 1]: up to 45 degrees along each axis; ``tilt = 0`` is the base model exactly).
Not reciprocal (the cosine ratio is not symmetric in wi and wo), not energy conserving in
the geometric frame. Returns f_r (1/sr), without the geometric cosine.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxrefl._errors import JaxreflError

from ._base import BRDF, Param

__all__ = ["NormalTilt", "tilt_frame", "tilt_normal"]

TILT_RANGE = (-1.0, 1.0)
# The geometric cosine is divided out; below this the ratio would amplify float error, and no
# capture direction is that grazing (the guard keeps values and gradients finite at cos -> 0).
_COS_FLOOR = 1e-6


def tilt_normal(tx: Float[Array, "*b"], ty: Float[Array, "*b"]) -> Float[Array, "*b 3"]:
    """Shading normal (t_x, t_y, 1)/|.| in the geometric frame (norm >= 1: always safe)."""
    v = jnp.stack([tx, ty, jnp.ones_like(tx)], axis=-1)
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def tilt_frame(
    tx: Float[Array, "*b"], ty: Float[Array, "*b"]
) -> tuple[Float[Array, "*b 3"], Float[Array, "*b 3"], Float[Array, "*b 3"]]:
    """(t, b, n): the shading frame of slopes (t_x, t_y), rows of the rotation R."""
    n = tilt_normal(tx, ty)
    # x - n_x n has norm sqrt(1 - n_x^2) >= 1/sqrt(2 + t_y^2) > 0 for bounded slopes: safe.
    x = jnp.zeros_like(n).at[..., 0].set(1.0)
    t = x - n[..., :1] * n
    t = t / jnp.linalg.norm(t, axis=-1, keepdims=True)
    b = jnp.cross(n, t)
    return t, b, n


class NormalTilt(BRDF):
    """``base`` seen through a tilted shading normal (see the module docstring)."""

    base: BRDF

    def __check_init__(self):
        clash = {"tilt_x", "tilt_y"} & set(self.base.param_names)
        if clash:
            raise JaxreflError(f"the base model already has parameters {sorted(clash)}")

    @property
    def params(self) -> tuple[Param, ...]:
        doc = "slope of the shading normal along {} (n = (tilt_x, tilt_y, 1)/|.|)"
        lo, hi = TILT_RANGE
        return (
            *self.base.params,
            Param("tilt_x", "scalar", 0.0, lo, hi, "1", doc.format("x")),
            Param("tilt_y", "scalar", 0.0, lo, hi, "1", doc.format("y")),
        )

    @property
    def reciprocal(self) -> bool:
        return False

    def _eval(self, p, wi, wo):
        t, b, n = tilt_frame(p["tilt_x"], p["tilt_y"])

        def local(w):
            return jnp.stack([jnp.sum(w * t, -1), jnp.sum(w * b, -1), jnp.sum(w * n, -1)], axis=-1)

        wi_s, wo_s = local(wi), local(wo)
        base_p = {k: p[k] for k in self.base.param_names}
        f = self.base.eval(base_p, wi_s, wo_s)
        cos_z = jnp.maximum(wi[..., 2], _COS_FLOOR)
        ratio = jnp.maximum(wi_s[..., 2], 0.0) / cos_z
        return f * ratio[..., None]

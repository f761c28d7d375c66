"""Lafortune: a Lambertian base plus generalised cosine lobes.

Lafortune, Foo, Torrance & Greenberg (1997), "Non-linear approximation of reflectance
functions", SIGGRAPH '97::

    f_r = albedo/pi + sum_j [Cx_j wi_x wo_x + Cy_j wi_y wo_y + Cz_j wi_z wo_z]_+^{n_j}   [1/sr]

Each lobe j is a row (Cx, Cy, Cz, n) of the parameter ``lobes``, shape (*b, L, 4). The
lobe's axis and scale come from C: (Cx, Cy, Cz) = (-1, -1, 1) is exactly the Phong lobe
cos^n of the angle between wo and the mirror direction of wi; scaling C by k scales the lobe
by k^n. Typical shapes:

* off-specular: Cx = Cy = -a, Cz < a (the peak moves towards grazing angles);
* retro-reflective: Cx = Cy > 0 (the peak is at wo = wi);
* anisotropic: Cx != Cy (the lobe is wider along one tangent axis; tangent = +x);
* Cx = Cy = 0: a lobe depending on the elevations only ("generalised diffuse").

Ranges: (Cx, Cy, Cz) any reals (|C|^n sets the peak value), n in [0, 1e5]. ``albedo`` is a
colour in [0, 1]. The lobes are achromatic: the lobe sum is added to every channel (the
paper's per-channel lobe coefficients are left out, so a fit cannot give the highlight its own
colour; use several channels of ``albedo`` and a white lobe).

Reciprocal (each lobe is symmetric in wi and wo); not energy conserving in general (the
lobe albedo depends on |C| and n). Returns f_r without the cosine factor; directions are
unit vectors in the local frame (z = normal) pointing away from the surface.

Numerics: [x]_+^n is :func:`positive_power`, exp(n log x) with x guarded, so n up to 1e5 is
finite in value and gradient; values are capped at exp(60) for lobes with |C| > 1.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxrefl._errors import JaxreflError

from ._base import BRDF, Param
from ._lambert import ALBEDO, broadcast_inputs
from ._phong import positive_power

__all__ = ["Lafortune", "default_lobes"]


def default_lobes(num_lobes: int) -> tuple[tuple[float, float, float, float], ...]:
    """Specular lobes (-c, -c, c, n_j) with n_j = 10 * 4^j and directional albedo about
    0.5/L each at normal incidence (c^n 2 pi/(n + 2) = 0.5/L); distinct exponents keep the
    lobes from being interchangeable when a fit starts from the defaults."""
    rows = []
    for j in range(num_lobes):
        n = 10.0 * 4.0**j
        c = ((n + 2.0) / (4.0 * math.pi * num_lobes)) ** (1.0 / n)
        rows.append((-c, -c, c, n))
    return tuple(rows)


class Lafortune(BRDF):
    """Lambert + ``num_lobes`` Lafortune lobes; see the module docstring for the math.

    ``lobes`` has shape (*b, num_lobes, 4) with rows (Cx, Cy, Cz, n); the class accepts any
    number of rows at evaluation time, ``num_lobes`` sets the default.
    """

    num_lobes: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        if self.num_lobes < 1:
            raise JaxreflError(f"num_lobes must be >= 1, got {self.num_lobes}")

    @property
    def params(self) -> tuple[Param, ...]:
        lobes = Param(
            name="lobes",
            kind="lobes",
            # Param.default is annotated flat; lobes need a nested (L, 4) tuple.
            default=default_lobes(self.num_lobes),  # type: ignore[arg-type]
            lower=-math.inf,
            upper=math.inf,
            units="Cx, Cy, Cz: 1/sr^(1/n); n: 1",
            doc="rows (Cx, Cy, Cz, n); n in [0, 1e5]",
        )
        return (ALBEDO, lobes)

    def _eval(
        self, p: dict[str, Array], wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]
    ) -> Float[Array, "*b C"]:
        p, wi, wo, _ = broadcast_inputs(self.params, p, wi, wo)
        lobes = p["lobes"]  # (*b, L, 4)
        c = lobes[..., :3]
        # Negative exponents would make the lobe diverge at its boundary (x -> 0+); they are
        # outside the stated range, and the clamp keeps an unconstrained fit finite.
        n = jnp.maximum(lobes[..., 3], 0.0)
        ww = (wi * wo)[..., None, :]  # (*b, 1, 3): wi_x wo_x, wi_y wo_y, wi_z wo_z
        x = jnp.sum(c * ww, axis=-1)  # (*b, L)
        lobe_sum = jnp.sum(positive_power(x, n), axis=-1)  # (*b,)
        return p["albedo"] / jnp.pi + lobe_sum[..., None]

"""Shading frames and sample geometry: from world directions to the BRDF's local frame.

Every BRDF takes directions in a local frame whose z axis is the surface normal ``n``, whose
x axis is the tangent ``t`` and whose y axis is the bitangent ``b = n x t`` (right-handed,
``t x b = n``). :func:`to_local` and :func:`to_world` change coordinates between that frame
and the world; :func:`orthonormal_basis` builds ``(t, b)`` from ``n`` alone and
:func:`shading_frame` uses a given tangent instead (anisotropic models need one).

Planar samples follow the flash-capture convention of MaterialGAN (Guo et al. 2020; see
:mod:`jaxrefl.io._capture`): the sample is the square ``[-S/2, S/2]^2`` of the plane z = 0,
+z is its normal, and pixel (row i, column j) of an H x W image lies at

    x = ((j + 0.5)/W - 0.5) S,     y = -((i + 0.5)/H - 0.5) S,     z = 0,

so row 0 is the top (+y) edge and column 0 the left (-x) edge, as a photo seen from +z.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Float

from ..brdf import safe_normalize

__all__ = [
    "orthonormal_basis",
    "planar_points",
    "shading_frame",
    "to_local",
    "to_world",
]


def orthonormal_basis(
    n: Float[Array, "*b 3"],
) -> tuple[Float[Array, "*b 3"], Float[Array, "*b 3"]]:
    """Tangent and bitangent ``(t, b)`` completing the unit normal ``n`` to a right-handed frame.

    Duff, Burgess, Christensen, Hery, Kensler, Liani, Villemin 2017, "Building an
    orthonormal basis, revisited", JCGT 6(1), listing 3 (branchless):

        s = sign(n_z),  a = -1/(s + n_z),  c = n_x n_y a
        t = (1 + s n_x^2 a,  s c,  -s n_x),    b = (c,  s + n_y^2 a,  -n_y)

    ``|s + n_z| >= 1`` so nothing divides by zero and the gradient is finite everywhere
    (``sign`` is taken with ``copysign`` so n_z = +0 gives s = +1). For n = +z this gives
    t = +x and b = +y, the world axes of a planar sample.
    """
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    s = jnp.copysign(jnp.ones_like(nz), nz)
    a = -1.0 / (s + nz)
    c = nx * ny * a
    t = jnp.stack([1.0 + s * nx * nx * a, s * c, -s * nx], axis=-1)
    b = jnp.stack([c, s + ny * ny * a, -ny], axis=-1)
    return t, b


def shading_frame(
    n: Float[Array, "*b 3"], tangent: Float[Array, "*b 3"] | None = None
) -> tuple[Float[Array, "*b 3"], Float[Array, "*b 3"], Float[Array, "*b 3"]]:
    """The frame ``(n, t, b)`` at a surface point: normalised normal, tangent, bitangent.

    Without ``tangent`` the frame is :func:`orthonormal_basis`. With one, the tangent is
    projected onto the plane orthogonal to ``n`` (Gram-Schmidt: t = normalise(t - (t.n) n)),
    so it fixes the azimuth of an anisotropic model's x axis; where it is (nearly) parallel
    to ``n`` the projection has no direction and the Duff basis is used instead.
    """
    n = safe_normalize(n)
    t0, b0 = orthonormal_basis(n)
    if tangent is None:
        return n, t0, b0
    tangent = jnp.broadcast_to(jnp.asarray(tangent, dtype=n.dtype), n.shape)
    tp = tangent - jnp.sum(tangent * n, axis=-1, keepdims=True) * n
    len2 = jnp.sum(tp * tp, axis=-1, keepdims=True)
    # A tangent within ~1e-6 rad of the normal leaves only round-off after the projection.
    ok = len2 > 1e-12 * jnp.sum(tangent * tangent, axis=-1, keepdims=True)
    tp_safe = jnp.where(ok, tp, t0)
    t = jnp.where(ok, tp_safe / jnp.sqrt(jnp.where(ok, len2, 1.0)), t0)
    b = jnp.cross(n, t)
    return n, t, b


def to_local(
    v: Float[Array, "*b 3"],
    n: Float[Array, "*b 3"],
    t: Float[Array, "*b 3"],
    b: Float[Array, "*b 3"],
) -> Float[Array, "*b 3"]:
    """World vector ``v`` in the local frame: ``(v.t, v.b, v.n)`` (z = normal).

    All arguments must have the same rank; insert axes explicitly to broadcast.
    """
    return jnp.stack(
        [jnp.sum(v * t, axis=-1), jnp.sum(v * b, axis=-1), jnp.sum(v * n, axis=-1)], axis=-1
    )


def to_world(
    v: Float[Array, "*b 3"],
    n: Float[Array, "*b 3"],
    t: Float[Array, "*b 3"],
    b: Float[Array, "*b 3"],
) -> Float[Array, "*b 3"]:
    """Local vector ``v`` back in world coordinates: ``v_x t + v_y b + v_z n``."""
    return v[..., 0:1] * t + v[..., 1:2] * b + v[..., 2:3] * n


def planar_points(
    height: int,
    width: int,
    side: float | tuple[float, float],
    dtype: DTypeLike | None = None,
) -> Float[Array, "H W 3"]:
    """World positions of the pixel centres of an H x W image of a planar sample.

    ``side`` is the side S of the imaged square (any length unit, cm in the MaterialGAN
    data), or ``(S_x, S_y)`` for a rectangle: x = ((j + 0.5)/W - 0.5) S_x,
    y = -((i + 0.5)/H - 0.5) S_y, z = 0 (module docstring).
    """
    sx, sy = (side, side) if np.ndim(side) == 0 else side  # type: ignore[misc]
    dtype = dtype if dtype is not None else jnp.result_type(float)
    j = (jnp.arange(width, dtype=dtype) + 0.5) / width - 0.5
    i = (jnp.arange(height, dtype=dtype) + 0.5) / height - 0.5
    x = jnp.broadcast_to(j[None, :] * jnp.asarray(sx, dtype), (height, width))
    y = jnp.broadcast_to(-i[:, None] * jnp.asarray(sy, dtype), (height, width))
    return jnp.stack([x, y, jnp.zeros_like(x)], axis=-1)


def _as_float(x: ArrayLike, dtype=None) -> Array:
    """``x`` as a floating array (float32/float64 as JAX's default, or ``dtype``)."""
    a = jnp.asarray(x, dtype=dtype)
    if not jnp.issubdtype(a.dtype, jnp.floating):
        a = a.astype(jnp.result_type(float))
    return a

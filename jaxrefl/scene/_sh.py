"""Irradiance from distant lighting with nine spherical-harmonic coefficients.

Ramamoorthi & Hanrahan 2001, "An efficient representation for irradiance environment
maps", SIGGRAPH. The radiance L(w) of an environment is projected on the real spherical
harmonics Y_lm with l <= 2 (their eq. 3 for the basis, eq. 10 for the projection),

    L_lm = integral L(w) Y_lm(w) dw,

and the irradiance of a surface with unit normal n = (x, y, z) is (their eq. 12/13, with
A_0 = pi, A_1 = 2 pi/3, A_2 = pi/4 the clamped-cosine coefficients)

    E(n) = c1 L22 (x^2 - y^2) + c3 L20 z^2 + c4 L00 - c5 L20
           + 2 c1 (L2-2 xy + L21 xz + L2-1 yz) + 2 c2 (L11 x + L1-1 y + L10 z).

The paper prints the constants rounded (from rounded Y_lm) as c1..c5 = 0.429043, 0.511664,
0.743125, 0.886227, 0.247708; here they are computed from their definitions
(c1 = A_2 sqrt(15/pi)/4, c2 = A_1 sqrt(3/(4 pi))/2, c3 = 3 A_2 sqrt(5/pi)/4,
c4 = A_0/(2 sqrt(pi)), c5 = A_2 sqrt(5/pi)/4; they agree to 1.2e-6), so a constant
environment L gives E = pi L to rounding. A Lambertian surface of albedo a then reflects
radiance a/pi * E(n) (:func:`sh_lambert`). The nine terms capture irradiance with an average
error under 3% for natural lighting (Ramamoorthi & Hanrahan 2001, section 3); they are exact
for radiance made of harmonics up to l = 2 (any quadratic polynomial in the direction).

Coefficient order (axis 0 of the (9, C) arrays): L00, L1-1, L10, L11, L2-2, L2-1, L20, L21,
L22, with Y1-1 ~ y, Y10 ~ z, Y11 ~ x, Y2-2 ~ xy, Y2-1 ~ yz, Y20 ~ 3z^2 - 1, Y21 ~ xz,
Y22 ~ x^2 - y^2. Directions use the environment map's frame (+z up, see
:class:`~jaxrefl.scene.EnvironmentMap`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._geometry import _as_float
from ._lights import EnvironmentMap

__all__ = ["SH_CONSTANTS", "sh_basis", "sh_irradiance", "sh_lambert", "sh_project"]

_A0, _A1, _A2 = math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0
_Y00 = 0.5 / math.sqrt(math.pi)  # 0.282095
_Y1 = math.sqrt(3.0 / (4.0 * math.pi))  # 0.488603
_Y2a = 0.5 * math.sqrt(15.0 / math.pi)  # 1.092548: Y2-2, Y2-1, Y21
_Y20 = 0.25 * math.sqrt(5.0 / math.pi)  # 0.315392
_Y22 = 0.25 * math.sqrt(15.0 / math.pi)  # 0.546274

#: (c1, c2, c3, c4, c5) of Ramamoorthi & Hanrahan 2001 eq. 12, unrounded.
SH_CONSTANTS: tuple[float, float, float, float, float] = (
    _A2 * _Y22,
    _A1 * _Y1 / 2.0,
    3.0 * _A2 * _Y20,
    _A0 * _Y00,
    _A2 * _Y20,
)


def sh_basis(w: Float[Array, "*b 3"]) -> Float[Array, "*b 9"]:
    """The nine real spherical harmonics Y_lm(w), l <= 2, at unit vectors ``w``."""
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    return jnp.stack(
        [
            jnp.full_like(x, _Y00),
            _Y1 * y,
            _Y1 * z,
            _Y1 * x,
            _Y2a * x * y,
            _Y2a * y * z,
            _Y20 * (3.0 * z * z - 1.0),
            _Y2a * x * z,
            _Y22 * (x * x - y * y),
        ],
        axis=-1,
    )


def _texel_integrals(h: int, w: int, dtype) -> Float[Array, "h w 9"]:
    """Exact integrals of the nine Y_lm over each texel of an h x w equirectangular grid.

    With u = cos(theta), a texel is theta in [th0, th1], phi in [ph0, ph1] and
    dOmega = sin(theta) dtheta dphi; each Y_lm (a polynomial of degree <= 2 in
    x = sin th cos ph, y = sin th sin ph, z = cos th) integrates to a product of a theta and
    a phi factor, evaluated in closed form below.
    """
    th = jnp.arange(h + 1, dtype=dtype) * (jnp.pi / h)
    ph = jnp.arange(w + 1, dtype=dtype) * (2.0 * jnp.pi / w)
    u, s = jnp.cos(th), jnp.sin(th)
    d = lambda f: f[1:] - f[:-1]  # noqa: E731  (integral from the lower to the upper edge)
    t0 = -d(u)  # int sin
    tz = -d(u * u) / 2.0  # int cos sin
    tzz = -d(u**3) / 3.0  # int cos^2 sin
    ts = d(th / 2.0 - jnp.sin(2.0 * th) / 4.0)  # int sin^2
    tss = t0 - tzz  # int sin^3
    tsz = d(s**3) / 3.0  # int sin^2 cos
    p0 = d(ph)
    pc, ps = d(jnp.sin(ph)), -d(jnp.cos(ph))
    pcc = p0 / 2.0 + d(jnp.sin(2.0 * ph)) / 4.0
    pss = p0 - pcc
    pcs = d(jnp.sin(ph) ** 2) / 2.0
    rows = jnp.stack(
        [_Y00 * t0, _Y1 * ts, _Y1 * tz, _Y1 * ts, _Y2a * tss,
         _Y2a * tsz, _Y20 * (3.0 * tzz - t0), _Y2a * tsz, _Y22 * tss],
        axis=-1,
    )  # fmt: skip
    cols = jnp.stack([p0, ps, p0, pc, pcs, ps, p0, pc, pcc - pss], axis=-1)
    return rows[:, None, :] * cols[None, :, :]


def _rotation_matrix(r: Float[Array, "3 3"]) -> Float[Array, "9 9"]:
    """D with Y(R v) = D Y(v) for all v (block diagonal in l), by least squares over a fixed,
    well-spread set of directions (the relation is exact, so the fit is to rounding)."""
    k = jnp.arange(64, dtype=r.dtype) + 0.5
    z = 1.0 - 2.0 * k / 64.0
    phi = k * (jnp.pi * (3.0 - jnp.sqrt(5.0)))  # Fibonacci sphere
    rho = jnp.sqrt(1.0 - z * z)
    v = jnp.stack([rho * jnp.cos(phi), rho * jnp.sin(phi), z], axis=-1)
    y, yr = sh_basis(v), sh_basis(v @ r.T)
    return jnp.linalg.lstsq(y, yr)[0].T


@eqx.filter_jit
def sh_project(env: EnvironmentMap | Float[ArrayLike, "H W C"]) -> Float[Array, "9 C"]:
    """Coefficients L_lm = integral L Y_lm dOmega of an equirectangular radiance map.

    ``env`` is an :class:`EnvironmentMap` (its subsampling and rotation apply) or a raw
    (H, W, C) radiance array in the same orientation. Each texel is taken as constant
    radiance over its exact solid angle and Y_lm is integrated exactly over it, so the
    coefficients are exact for that piecewise-constant map (a constant map gives
    L00 = 2 sqrt(pi) L and all others 0 to rounding). With a rotation R the map-frame
    coefficients are rotated: L_world = D L_map with Y(R v) = D Y(v).
    """
    if not isinstance(env, EnvironmentMap):
        env = EnvironmentMap(env)
    _, _, lum = env.texels()
    h, w = lum.shape[:2]
    c = jnp.einsum("hwk,hwc->kc", _texel_integrals(h, w, lum.dtype), lum)
    if env.rotation is not None:
        c = _rotation_matrix(env.rotation.astype(lum.dtype)) @ c
    return c


@eqx.filter_jit
def sh_irradiance(
    coeffs: Float[ArrayLike, "9 C"], normals: Float[ArrayLike, "*b 3"]
) -> Float[Array, "*b C"]:
    """Irradiance E(n) (Ramamoorthi & Hanrahan 2001 eq. 13) at unit ``normals``.

    Units: those of the radiance times sr (W/m^2 for radiance in W/(m^2 sr)). E is the
    cosine-weighted integral of radiance over the hemisphere around n, so pi L for a constant L.
    """
    n = _as_float(normals)
    c = jnp.asarray(coeffs, dtype=n.dtype)
    c1, c2, c3, c4, c5 = SH_CONSTANTS
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    # E = sum_lm A_l L_lm Y_lm(n) written as the weights of each coefficient (eq. 13).
    w = jnp.stack(
        [
            jnp.full_like(x, c4),
            2.0 * c2 * y,
            2.0 * c2 * z,
            2.0 * c2 * x,
            2.0 * c1 * x * y,
            2.0 * c1 * y * z,
            c3 * z * z - c5,
            2.0 * c1 * x * z,
            c1 * (x * x - y * y),
        ],
        axis=-1,
    )
    return jnp.einsum("...k,kc->...c", w, c)


def sh_lambert(
    coeffs: Float[ArrayLike, "9 C"],
    normals: Float[ArrayLike, "*b 3"],
    albedo: Float[ArrayLike, "*b C"],
) -> Float[Array, "*b C"]:
    """Radiance reflected by a Lambertian surface: albedo/pi * E(n) (view-independent)."""
    e = sh_irradiance(coeffs, normals)
    a = jnp.asarray(albedo, dtype=e.dtype)
    shape = jnp.broadcast_shapes(a.shape, e.shape)
    return jnp.broadcast_to(a, shape) / jnp.pi * jnp.broadcast_to(e, shape)

"""Light sources as incident-light samples at surface points.

Every light answers one question: ``wi, irradiance = light.incident(points)``, with
``points`` of shape ``(*b, 3)`` (world positions), ``wi`` of shape ``(*b, S, 3)`` (unit
vectors in world coordinates from the point **towards** the light, the BRDF's convention)
and ``irradiance`` of shape ``(*b, S, C)``: the irradiance that sample s would deliver to a
surface facing it (normal incidence). The radiance reflected towards ``wo`` is then

    L_o(wo) = sum_s f_r(wi_s, wo) * irradiance_s * max(cos theta_s, 0),

with cos theta_s = wi_s . n, which is what :func:`jaxrefl.scene.render` computes. Units are
the caller's: irradiance in W/m^2 (or any consistent unit) per channel, intensity in W/sr,
radiance in W/(m^2 sr), lengths in one unit throughout (cm in the MaterialGAN data, where
1/r^2 is then in 1/cm^2). S is 1 for directional and point lights, ``n^2`` quadrature nodes
for an area light and the number of texels for an environment map.

Parameters are stored as arrays (so a light can be differentiated, e.g. for calibration)
and cast to the dtype of ``points``; colour quantities have a trailing channel axis (a
scalar is taken as one channel).
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxrefl._errors import JaxreflError

from ..brdf import safe_normalize
from ._geometry import _as_float

__all__ = ["AreaLight", "DirectionalLight", "EnvironmentMap", "Light", "PointLight"]


def _color(x: ArrayLike) -> Array:
    """A colour quantity with a trailing channel axis (scalar -> one channel)."""
    a = _as_float(x)
    return a[None] if a.ndim == 0 else a


def _unit(v: ArrayLike) -> Array:
    v = _as_float(v)
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def _lift(x: Array, batch: tuple[int, ...]) -> Array:
    """Give ``x`` leading unit axes so it has the rank of ``(*batch, *x.shape)``."""
    return x.reshape((1,) * len(batch) + x.shape)


def _times_color(g: Float[Array, "*b S"], color: Float[Array, " C"]) -> Float[Array, "*b S C"]:
    """g[..., None] * color, with explicit ranks (no implicit rank promotion)."""
    return g[..., None] * _lift(color, g.shape)


def _towards(
    target: Float[Array, "S 3"], points: Float[Array, "*b 3"]
) -> tuple[Float[Array, "*b S 3"], Float[Array, "*b S"]]:
    """Unit vectors from ``points`` to ``target`` and the squared distances (0 where equal)."""
    d = _lift(target, points.shape[:-1]) - points[..., None, :]
    r2 = jnp.sum(d * d, axis=-1)
    return safe_normalize(d), r2


def _inverse_square(r2: Float[Array, "*b S"]) -> Float[Array, "*b S"]:
    """1/r^2, and 0 at r = 0 (a point on the emitter itself receives no defined irradiance)."""
    ok = r2 > 0
    return jnp.where(ok, 1.0 / jnp.where(ok, r2, 1.0), 0.0)


class Light(eqx.Module):
    """Base class: a light is anything with :meth:`incident`."""

    @abc.abstractmethod
    def incident(
        self, points: Float[Array, "*b 3"]
    ) -> tuple[Float[Array, "*b S 3"], Float[Array, "*b S C"]]:
        """``(wi, irradiance)``: world directions towards the light and normal-incidence
        irradiance per sample; reflected radiance = sum_s f_r * irradiance_s * max(cos_s, 0)."""


class DirectionalLight(Light):
    """A distant light: the same direction and irradiance at every point.

    ``direction`` points from the surface towards the light (normalised on construction);
    ``irradiance`` E is the irradiance on a surface facing the light (W/m^2 per channel), so a
    surface with normal n receives E max(n . direction, 0). A light below a point's horizon
    contributes 0 (the BRDF is 0 there). S = 1.
    """

    direction: Float[Array, " 3"]
    irradiance: Float[Array, " C"]

    def __init__(self, direction: Float[ArrayLike, " 3"], irradiance: Float[ArrayLike, " C"]):
        self.direction = _unit(direction)
        self.irradiance = _color(irradiance)

    def incident(self, points):
        dt = points.dtype
        batch = points.shape[:-1]
        wi = jnp.broadcast_to(self.direction.astype(dt), (*batch, 1, 3))
        e = jnp.broadcast_to(self.irradiance.astype(dt), (*batch, 1, self.irradiance.shape[-1]))
        return wi, e


class PointLight(Light):
    """An isotropic point light (e.g. a phone flash close to the sample).

    ``intensity`` I is the radiant intensity in W/sr per channel (MaterialGAN's
    ``light_power``); a point at distance r receives irradiance I / r^2 at normal incidence
    from direction (position - point)/r, different at every point. S = 1.
    """

    position: Float[Array, " 3"]
    intensity: Float[Array, " C"]

    def __init__(self, position: Float[ArrayLike, " 3"], intensity: Float[ArrayLike, " C"]):
        self.position = _as_float(position)
        self.intensity = _color(intensity)

    def incident(self, points):
        dt = points.dtype
        wi, r2 = _towards(self.position.astype(dt)[None, :], points)
        return wi, _times_color(_inverse_square(r2), self.intensity.astype(dt))


def _nodes_1d(n: int, rule: str) -> tuple[np.ndarray, np.ndarray]:
    """Nodes in [-1/2, 1/2] and weights summing to 1 of an n-point rule."""
    if rule == "gauss":
        x, w = np.polynomial.legendre.leggauss(n)
        return x / 2.0, w / 2.0
    if rule == "midpoint":
        return (np.arange(n) + 0.5) / n - 0.5, np.full(n, 1.0 / n)
    raise JaxreflError(f"unknown quadrature rule {rule!r}; use 'gauss' or 'midpoint'")


class AreaLight(Light):
    """A one-sided Lambertian emitter: the rectangle ``centre + s u + t v``, s, t in [-1/2, 1/2].

    ``radiance`` L (W/(m^2 sr) per channel) leaves the side of the unit normal
    n_l = (u x v)/|u x v|; the back emits nothing. The irradiance at x is the integral over
    the rectangle (area A = |u x v|) of L cos(theta_l) cos(theta) / r^2 dA, evaluated with an
    ``n x n`` tensor rule (``rule="gauss"``: Gauss-Legendre, exact for polynomials of degree
    2n - 1 in each edge coordinate; ``"midpoint"``: n x n equal cells). Sample s at y_s with
    weight w_s returns

        irradiance_s = L * max(cos theta_l, 0) * A w_s / r_s^2,   cos theta_l = n_l . (x - y_s)/r_s.

    Far away (r >> |u|, |v|) this is a point light with direction-dependent radiant intensity
    I(theta_l) = L A cos(theta_l) (L A along the normal); the total emitted power is pi L A.
    """

    centre: Float[Array, " 3"]
    edge_u: Float[Array, " 3"]
    edge_v: Float[Array, " 3"]
    radiance: Float[Array, " C"]
    n: int = eqx.field(static=True)
    rule: str = eqx.field(static=True)

    def __init__(self, centre, edge_u, edge_v, radiance, n: int = 4, rule: str = "gauss"):
        self.centre = _as_float(centre)
        self.edge_u = _as_float(edge_u)
        self.edge_v = _as_float(edge_v)
        self.radiance = _color(radiance)
        if n < 1:
            raise JaxreflError(f"AreaLight needs n >= 1 quadrature nodes per edge, got {n}")
        _nodes_1d(1, rule)  # validates the rule name
        self.n = int(n)
        self.rule = rule

    @property
    def normal(self) -> Float[Array, " 3"]:
        """The emitting side's unit normal (u x v)/|u x v|."""
        return _unit(jnp.cross(self.edge_u, self.edge_v))

    @property
    def area(self) -> Float[Array, ""]:
        return jnp.linalg.norm(jnp.cross(self.edge_u, self.edge_v))

    def incident(self, points):
        dt = points.dtype
        x, w = _nodes_1d(self.n, self.rule)
        su = jnp.asarray(np.repeat(x, self.n), dt)[:, None]  # (S, 1)
        sv = jnp.asarray(np.tile(x, self.n), dt)[:, None]
        ws = jnp.asarray(np.outer(w, w).reshape(-1), dt)  # (S,)
        c, u, v = (a.astype(dt) for a in (self.centre, self.edge_u, self.edge_v))
        nrm = jnp.cross(u, v)
        area = jnp.linalg.norm(nrm)
        y = c[None, :] + su * u[None, :] + sv * v[None, :]  # (S, 3)
        wi, r2 = _towards(y, points)
        # One-sided emitter: points behind the rectangle's plane get nothing from it.
        cos_l = jnp.maximum(-jnp.sum(wi * _lift(nrm / area, wi.shape[:-1]), axis=-1), 0.0)
        g = cos_l * _lift(area * ws, points.shape[:-1]) * _inverse_square(r2)  # (*b, S)
        return wi, _times_color(g, self.radiance.astype(dt))


class EnvironmentMap(Light):
    """Distant lighting from every direction: an equirectangular radiance image (H, W, C).

    Orientation: +z is up (the normal of a planar sample). Row i covers polar angles
    theta in [i, i + 1] pi/H measured from +z (row 0 is the zenith, row H - 1 the nadir);
    column j covers azimuths phi in [j, j + 1] 2 pi/W measured from +x towards +y. The
    texel's direction is that of its centre, (sin th cos ph, sin th sin ph, cos th), and its
    solid angle is the exact one, dOmega = (cos theta_top - cos theta_bottom) 2 pi/W
    (= sin theta dtheta dphi to second order; the texels sum to exactly 4 pi). ``rotation``
    (3 x 3, optional) maps these map directions to world directions.

    The quadrature treats each texel as one sample: irradiance_s = L_s dOmega_s, so a constant
    map L gives irradiance pi L on any surface (to quadrature precision, O(1/H^2)) and a
    Lambertian surface of albedo a reflects a L. ``subsample = k`` averages k x k texel blocks
    (weighted by solid angle, so the power is kept) before the quadrature: S = HW/k^2.
    """

    radiance: Float[Array, "H W C"]
    rotation: Float[Array, "3 3"] | None
    subsample: int = eqx.field(static=True)

    def __init__(self, radiance, rotation=None, subsample: int = 1):
        r = _as_float(radiance)
        if r.ndim == 2:
            r = r[..., None]
        if r.ndim != 3:
            raise JaxreflError(f"environment map must have shape (H, W, C), got {r.shape}")
        h, w = r.shape[:2]
        if subsample < 1 or h % subsample or w % subsample:
            raise JaxreflError(
                f"subsample={subsample} must be >= 1 and divide the map size {h} x {w}"
            )
        self.radiance = r
        self.rotation = None if rotation is None else _as_float(rotation)
        self.subsample = int(subsample)

    def texels(
        self, dtype=None
    ) -> tuple[Float[Array, "h w 3"], Float[Array, "h w"], Float[Array, "h w C"]]:
        """Directions (world), solid angles and radiance of the (subsampled) texels."""
        dt = dtype if dtype is not None else self.radiance.dtype
        lum = self.radiance.astype(dt)
        h, w, c = lum.shape
        k = self.subsample
        th_edges = jnp.arange(h + 1, dtype=dt) * (jnp.pi / h)
        band = jnp.cos(th_edges[:-1]) - jnp.cos(th_edges[1:])  # (h,) fine rows
        if k > 1:
            wgt = band[:, None, None]
            lum = (lum * wgt).reshape(h // k, k, w // k, k, c).sum(axis=(1, 3))
            lum = lum / (wgt.reshape(h // k, k).sum(axis=1)[:, None, None] * k)
            h, w = h // k, w // k
            th_edges = jnp.arange(h + 1, dtype=dt) * (jnp.pi / h)
            band = jnp.cos(th_edges[:-1]) - jnp.cos(th_edges[1:])
        theta = (jnp.arange(h, dtype=dt) + 0.5) * (jnp.pi / h)
        phi = (jnp.arange(w, dtype=dt) + 0.5) * (2.0 * jnp.pi / w)
        st = jnp.sin(theta)[:, None]
        d = jnp.stack(
            [
                st * jnp.cos(phi)[None, :],
                st * jnp.sin(phi)[None, :],
                jnp.broadcast_to(jnp.cos(theta)[:, None], (h, w)),
            ],
            axis=-1,
        )
        if self.rotation is not None:
            d = jnp.einsum("ij,hwj->hwi", self.rotation.astype(dt), d)
        domega = jnp.broadcast_to(band[:, None] * (2.0 * jnp.pi / w), (h, w))
        return d, domega, lum

    def incident(self, points):
        dt = points.dtype
        d, domega, lum = self.texels(dt)
        c = lum.shape[-1]
        wi = d.reshape(-1, 3)
        e = (lum * domega[..., None]).reshape(-1, c)
        batch = points.shape[:-1]
        return (
            jnp.broadcast_to(wi, (*batch, *wi.shape)),
            jnp.broadcast_to(e, (*batch, *e.shape)),
        )

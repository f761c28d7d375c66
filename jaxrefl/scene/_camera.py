"""Cameras (where the viewer is) and camera response curves (radiance to pixel values).

Geometry
--------
:class:`PinholeCamera` sits at ``position`` and looks along the unit optical axis ``axis``
(from the camera into the scene). For a surface point x it gives the view direction
wo = (position - x)/|position - x| (from the surface towards the camera, the BRDF's
convention) and the natural-vignetting factor cos^4(angle between the ray and the axis)
(:func:`cos4_falloff`; e.g. Kang & Weiss 2000, "Can we calibrate a camera using an image of
a flat, textureless Lambertian surface?"). :class:`OrthographicCamera` is a distant viewer
(photometric-stereo data): one direction for every point and no falloff.

Response
--------
A response maps linear radiance (scaled by ``exposure``) to encoded values,

    encoded = clip(curve(exposure * radiance), 0, 1)    (clip only if ``clip=True``),

and ``invert`` undoes it: radiance = curve^-1(encoded)/exposure. Clipped values cannot be
undone (treat them as censored). Curves: :class:`LinearResponse`, :class:`SRGBResponse`
(IEC 61966-2-1), :class:`GammaResponse` (value^(1/gamma), as in the MaterialGAN data with
gamma = 2.2) and :class:`TabulatedResponse` (a measured, monotone curve).
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

__all__ = [
    "GammaResponse",
    "LinearResponse",
    "OrthographicCamera",
    "PinholeCamera",
    "Response",
    "SRGBResponse",
    "TabulatedResponse",
    "cos4_falloff",
]


# ---------------------------------------------------------------------------- geometry
def cos4_falloff(
    points: Float[Array, "*b 3"],
    camera_position: Float[ArrayLike, " 3"],
    optical_axis: Float[ArrayLike, " 3"],
) -> Float[Array, " *b"]:
    """cos^4 of the angle between the ray camera -> point and the unit optical axis.

    1 on the axis; a point at lateral offset d from the axis at depth h gets
    h^4/(h^2 + d^2)^2. Points behind the camera (cos <= 0) get 0.
    """
    c = jnp.asarray(camera_position, dtype=points.dtype)
    a = jnp.asarray(optical_axis, dtype=points.dtype)
    lead = (1,) * (points.ndim - 1)
    ray = safe_normalize(points - c.reshape(*lead, 3))
    # The camera cannot see behind itself; there the factor is 0, not cos^4 of an obtuse angle.
    cos = jnp.maximum(jnp.sum(ray * a.reshape(*lead, 3), axis=-1), 0.0)
    c2 = cos * cos
    return c2 * c2


class Camera(eqx.Module):
    """Base class: a viewer gives view directions and a vignetting factor per point."""

    @abc.abstractmethod
    def view_direction(self, points: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
        """Unit world vectors wo from each point towards the camera."""

    @abc.abstractmethod
    def falloff(self, points: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
        """Multiplicative vignetting factor per point."""


class PinholeCamera(Camera):
    """A pinhole at ``position`` looking along ``axis`` (or towards ``look_at``).

    Give ``axis`` (direction into the scene, normalised on construction) or ``look_at``
    (a point); with neither, the camera looks at the origin (the centre of a planar sample).
    """

    position: Float[Array, " 3"]
    axis: Float[Array, " 3"]

    def __init__(self, position, look_at=None, axis=None):
        self.position = _as_float(position)
        if axis is not None and look_at is not None:
            raise JaxreflError("give either look_at or axis, not both")
        if axis is None:
            target = jnp.zeros(3) if look_at is None else _as_float(look_at)
            axis = target.astype(self.position.dtype) - self.position
        axis = _as_float(axis)
        self.axis = axis / jnp.linalg.norm(axis)

    def view_direction(self, points):
        lead = (1,) * (points.ndim - 1)
        return safe_normalize(self.position.astype(points.dtype).reshape(*lead, 3) - points)

    def falloff(self, points):
        return cos4_falloff(points, self.position, self.axis)


class OrthographicCamera(Camera):
    """A distant viewer in ``direction`` (from the scene towards the camera); no falloff."""

    direction: Float[Array, " 3"]

    def __init__(self, direction=(0.0, 0.0, 1.0)):
        d = _as_float(direction)
        self.direction = d / jnp.linalg.norm(d)

    def view_direction(self, points):
        return jnp.broadcast_to(self.direction.astype(points.dtype), points.shape)

    def falloff(self, points):
        return jnp.ones(points.shape[:-1], points.dtype)


# ---------------------------------------------------------------------------- response
class Response(eqx.Module):
    """Base class: ``apply`` = clip(curve(exposure * radiance)), ``invert`` its inverse.

    ``exposure`` (> 0, an array so it can be fitted) scales linear radiance before the curve;
    ``clip`` (static) clips the encoded values to [0, 1] in :meth:`apply`.
    """

    exposure: Float[Array, ""] = eqx.field(default=1.0, converter=_as_float, kw_only=True)
    clip: bool = eqx.field(default=True, static=True, kw_only=True)

    @abc.abstractmethod
    def curve(self, x: Float[Array, "*b"]) -> Float[Array, "*b"]:
        """The encoding curve on linear values (no exposure, no clipping)."""

    @abc.abstractmethod
    def curve_inverse(self, y: Float[Array, "*b"]) -> Float[Array, "*b"]:
        """Inverse of :meth:`curve`."""

    def apply(self, radiance: Float[ArrayLike, "*b"]) -> Float[Array, "*b"]:
        """Linear radiance -> encoded values (clipped to [0, 1] if ``clip``)."""
        x = _as_float(radiance)
        y = self.curve(x * self.exposure.astype(x.dtype))
        if not self.clip:
            return y
        # Sensor range [0, 1]; where() rather than clip() so that a value exactly at 0 or 1
        # keeps the full gradient of the curve (clip() splits it at ties), beyond it none.
        return jnp.where(y < 0.0, 0.0, jnp.where(y > 1.0, 1.0, y))

    def invert(self, encoded: Float[ArrayLike, "*b"]) -> Float[Array, "*b"]:
        """Encoded values -> linear radiance (exact inverse of unclipped :meth:`apply`)."""
        y = _as_float(encoded)
        return self.curve_inverse(y) / self.exposure.astype(y.dtype)


class LinearResponse(Response):
    """curve(x) = x (a linear RAW or HDR camera)."""

    def curve(self, x):
        return x

    def curve_inverse(self, y):
        return y


# IEC 61966-2-1:1999 (sRGB), section 5.2/5.3: the linear segment meets the power segment at
# x = 0.0031308 (encoded 0.04045).
_SRGB_X0 = 0.0031308
_SRGB_Y0 = 0.04045


class SRGBResponse(Response):
    """The sRGB transfer function (IEC 61966-2-1:1999):

        y = 12.92 x                      for x <= 0.0031308,
        y = 1.055 x^(1/2.4) - 0.055      otherwise;
        x = y/12.92 for y <= 0.04045, else ((y + 0.055)/1.055)^2.4.

    Negative inputs follow the linear segment. Linear 0.5 encodes to 0.7353569830524495.
    """

    def curve(self, x):
        hi = x > _SRGB_X0
        x_safe = jnp.where(hi, x, 1.0)  # keeps pow's gradient finite on the linear branch
        return jnp.where(hi, 1.055 * x_safe ** (1.0 / 2.4) - 0.055, 12.92 * x)

    def curve_inverse(self, y):
        hi = y > _SRGB_Y0
        y_safe = jnp.where(hi, y, 1.0)
        return jnp.where(hi, ((y_safe + 0.055) / 1.055) ** 2.4, y / 12.92)


class GammaResponse(Response):
    """A pure power law y = x^(1/gamma), extended oddly to x < 0 (y = -|x|^(1/gamma)).

    ``gamma`` > 0 (2.2 in the MaterialGAN data). The slope is infinite at x = 0 for gamma > 1;
    the gradient there is defined as 0 (gradient-safe guard) so optimisers never see inf.
    """

    gamma: Float[Array, ""]

    def __init__(
        self,
        gamma: Float[ArrayLike, ""] = 2.2,
        *,
        exposure: Float[ArrayLike, ""] = 1.0,
        clip: bool = True,
    ):
        # Written out so that type checkers see numbers accepted: mypy does not apply the
        # converters of ``eqx.field`` to the generated ``__init__``.
        self.gamma = _as_float(gamma)
        self.exposure = _as_float(exposure)
        self.clip = clip

    def _pow(self, v, e):
        a = jnp.abs(v)
        ok = a > 0
        # pow(0, e) has an infinite or undefined derivative; evaluate at 1 and zero it instead.
        a_safe = jnp.where(ok, a, 1.0)
        return jnp.where(ok, jnp.sign(v) * a_safe ** e.astype(v.dtype), 0.0)

    def curve(self, x):
        return self._pow(x, 1.0 / self.gamma)

    def curve_inverse(self, y):
        return self._pow(y, self.gamma)


class TabulatedResponse(Response):
    """A measured response: linear interpolation through ``(x[k], y[k])``.

    Both ``x`` (linear) and ``y`` (encoded) must be strictly increasing (checked on
    construction); the inverse interpolates with the roles swapped. Outside the table the
    curve is held at the end values (``jnp.interp``), so tabulate the full range, e.g. [0, 1].
    """

    x: Float[Array, " N"]
    y: Float[Array, " N"]

    def __init__(self, x, y, *, exposure=1.0, clip: bool = True):
        xs = np.asarray(x, dtype=np.float64)
        ys = np.asarray(y, dtype=np.float64)
        if xs.ndim != 1 or xs.shape != ys.shape or xs.size < 2:
            raise JaxreflError(
                f"x and y must be 1-D of the same length >= 2, got {xs.shape} and {ys.shape}"
            )
        for name, v in (("x", xs), ("y", ys)):
            bad = np.flatnonzero(~(np.diff(v) > 0))
            if bad.size:
                k = int(bad[0])
                raise JaxreflError(
                    f"TabulatedResponse needs strictly increasing {name}; "
                    f"{name}[{k}] = {float(v[k])} >= {name}[{k + 1}] = {float(v[k + 1])}"
                )
        self.x = _as_float(x)
        self.y = _as_float(y)
        self.exposure = _as_float(exposure)
        self.clip = clip

    def curve(self, x):
        return jnp.interp(x, self.x.astype(x.dtype), self.y.astype(x.dtype))

    def curve_inverse(self, y):
        return jnp.interp(y, self.y.astype(y.dtype), self.x.astype(y.dtype))

"""Image formation: BRDF parameters, lights and a camera to pixel values.

For each light k (one image per light, as in photometric stereo or a flash capture) and
each pixel with surface point x, frame (n, t, b) and view direction wo (towards camera k):

    radiance_k(x) = sum_s f_r(wi_s, wo; params(x)) * E_s * max(wi_s . n, 0) * V_ks(x)
    image_k(x)    = response.apply( cos4_k(x) * radiance_k(x) )

where (wi_s, E_s) are the light's samples (:meth:`Light.incident`: direction towards the
light and normal-incidence irradiance), V the optional ``shadow`` visibility in [0, 1],
cos4_k the camera's falloff (:meth:`Camera.falloff`, only if ``cos4=True``) and the
response (exposure, curve, clipping) is applied last, only if given. The BRDF sees the
directions in each pixel's local frame (z = n, x = tangent; :func:`shading_frame`) through
``model.eval(params, wi_local, wo_local)``, so it returns f_r without the cosine, and
gives 0 (with zero gradient, no NaN) wherever the light or the camera is below the horizon.

Memory stays bounded: lights of one kind (same class and shapes) are stacked and mapped one
at a time with ``lax.map``, and inside each light the pixels are processed in chunks of
about ``chunk_samples`` light samples (``lax.map`` with ``batch_size``), so the forward pass
of a 1024 x 1024 image under 9 lights holds one light's chunk of intermediates at a time
(reverse-mode gradients keep the residuals of every chunk). The function is pure JAX:
differentiate it with respect to ``params``, light or camera parameters, ``points`` or
``normals``.

:func:`render` is compiled with ``eqx.filter_jit``: the first call for given shapes, model
and kinds of lights traces and compiles, later calls reuse it. Python numbers in ``params``
are static under ``filter_jit`` (each new value recompiles): pass arrays for values that
change, e.g. inside a fitting loop.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from jaxrefl._errors import JaxreflError

from ..brdf import BRDF
from ._camera import Camera, Response
from ._geometry import _as_float, planar_points, shading_frame, to_local
from ._lights import Light

__all__ = ["render", "render_planar_sample"]

_DEFAULT_CHUNK = 2**18


def _per_pixel_params(
    model: BRDF, params: Mapping[str, ArrayLike], image: tuple[int, ...], dtype
) -> dict[str, Array]:
    """Broadcast each parameter to the image and flatten the pixels: (N, *trailing)."""
    out = {}
    n = math.prod(image)
    for q in model.params:
        if q.name not in params:
            raise KeyError(f"{type(model).__name__} needs parameter {q.name!r}")
        v = jnp.asarray(params[q.name]).astype(dtype)
        if q.kind == "color":
            v = v[None] if v.ndim == 0 else v
            trailing = v.shape[-1:]
        elif q.kind == "lobes":
            trailing = v.shape[-2:]
        else:
            trailing = ()
        if v.ndim not in (len(trailing), len(image) + len(trailing)):
            raise JaxreflError(
                f"{q.kind} parameter {q.name!r} must have shape {trailing} or "
                f"(*{image}, *{trailing}) (a trailing channel axis for colours), got {v.shape}"
            )
        out[q.name] = jnp.broadcast_to(v, (*image, *trailing)).reshape(n, *trailing)
    extra = set(params) - set(model.param_names)
    if extra:
        raise KeyError(f"unexpected parameters {sorted(extra)} for {type(model).__name__}")
    return out


def _shade(model, light, camera, x, n, t, b, p, vis, cos4):
    """Radiance (C,) at one pixel under one light; ``vis`` is None, () or (S,)."""
    wi, e = light.incident(x)  # (S, 3), (S, C)
    wo = camera.view_direction(x)  # (3,)
    wi_l = to_local(wi, n[None], t[None], b[None])
    wo_l = to_local(wo, n, t, b)[None]
    f = model.eval({k: v[None] for k, v in p.items()}, wi_l, wo_l)  # (S, C)
    # Light from below the surface does not reach it (the BRDF is 0 there too).
    w = jnp.maximum(wi_l[:, 2], 0.0)
    if vis is not None:
        w = w * vis
    out = jnp.sum(f * e * w[:, None], axis=0)
    return out * camera.falloff(x) if cos4 else out


def _image(model, light, camera, geom, p, vis, cos4, chunk_samples):
    """(N, C) radiance of all pixels under one light, in chunks of pixels."""
    x = geom[0]
    n_pix = x.shape[0]
    n_samples = jax.eval_shape(light.incident, x[:1])[0].shape[1]
    batch = max(1, min(n_pix, chunk_samples // max(n_samples, 1)))

    def one(args):
        xi, ni, ti, bi, pi, vi = args
        return _shade(model, light, camera, xi, ni, ti, bi, pi, vi, cos4)

    xs = (*geom, p, vis)
    if batch >= n_pix:
        return jax.vmap(one)(xs)
    return jax.lax.map(one, xs, batch_size=batch)


def _same_layout(items: Sequence) -> bool:
    s0 = jax.tree.structure(items[0])
    leaves0 = [(a.shape, a.dtype) for a in jax.tree.leaves(items[0])]
    for it in items[1:]:
        if jax.tree.structure(it) != s0:  # type: ignore[operator]  # PyTreeDef has __ne__
            return False
        if [(a.shape, a.dtype) for a in jax.tree.leaves(it)] != leaves0:
            return False
    return True


@eqx.filter_jit
def render(
    model: BRDF,
    params: Mapping[str, ArrayLike],
    lights: Light | Sequence[Light],
    camera: Camera | Sequence[Camera],
    *,
    points: Float[ArrayLike, "*P 3"],
    normals: Float[ArrayLike, "*P 3"] | None = None,
    tangents: Float[ArrayLike, "*P 3"] | None = None,
    shadow: Float[ArrayLike, " K *P"] | Float[ArrayLike, "K *P S"] | None = None,
    response: Response | None = None,
    cos4: bool = True,
    chunk_samples: int = _DEFAULT_CHUNK,
) -> Float[Array, "K *P C"]:
    """Render one image per light (module docstring for the formula and the order).

    Args:
        model: a BRDF (``jaxrefl.brdf.get(...)``).
        params: the model's parameters, each broadcastable to the image: scalar ones to
            ``P`` (e.g. ``alpha`` of shape (H, W) or ()), colour ones with a trailing channel
            axis to ``(*P, C)`` (e.g. ``albedo`` (H, W, 3) or (3,)), lobes to ``(*P, L, 4)``.
        lights: K lights, or one (K = 1).
        camera: one camera for all lights, or K cameras (e.g. a phone moving with its flash).
        points: world positions of the pixels, shape ``(*P, 3)`` (usually (H, W, 3)), in the
            lights' length unit; the dtype (float32/float64) sets the computation's.
        normals: unit normals ``(*P, 3)`` or (3,); default +z (a planar sample).
        tangents: optional tangents (x axis of the local frame, for anisotropic models).
        shadow: visibility in [0, 1] per light and pixel ``(K, *P)``, or per light sample
            ``(K, *P, S)`` (all lights must then have S samples); multiplies the contribution.
        response: camera response applied last (exposure, curve, clip); None -> radiance.
        cos4: multiply by the camera's falloff (cos^4 vignetting for a pinhole camera).
        chunk_samples: pixels are processed in chunks of about this many light samples.

    Returns:
        ``(K, *P, C)`` images (linear radiance if ``response`` is None).
    """
    pts = _as_float(points)
    dt = pts.dtype
    image = pts.shape[:-1]
    n_pix = math.prod(image)
    light_list = [lights] if isinstance(lights, Light) else list(lights)
    k = len(light_list)
    if k == 0:
        raise JaxreflError("render needs at least one light")
    cams = [camera] * k if isinstance(camera, Camera) else list(camera)
    if len(cams) != k:
        raise JaxreflError(f"got {k} lights but {len(cams)} cameras; give one camera or K")

    nrm = jnp.asarray([0.0, 0.0, 1.0], dt) if normals is None else jnp.asarray(normals, dt)
    nrm = jnp.broadcast_to(nrm, pts.shape)
    tan = None if tangents is None else jnp.broadcast_to(jnp.asarray(tangents, dt), pts.shape)
    n, t, b = shading_frame(nrm, tan)
    geom = tuple(a.reshape(n_pix, 3) for a in (pts, n, t, b))
    p = _per_pixel_params(model, params, image, dt)

    vis = None
    if shadow is not None:
        vis = jnp.asarray(shadow).astype(dt)
        if vis.shape[: 1 + len(image)] != (k, *image) or vis.ndim > len(image) + 2:
            raise JaxreflError(
                f"shadow must have shape (K, *P) or (K, *P, S) = ({k}, {image}[, S]), "
                f"got {vis.shape}"
            )
        vis = vis.reshape(k, n_pix, *vis.shape[1 + len(image) :])

    def one_light(light, cam, v):
        return _image(model, light, cam, geom, p, v, cos4, chunk_samples)

    pairs = list(zip(light_list, cams, strict=True))
    if k > 1 and _same_layout(pairs):
        stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *pairs)
        if vis is None:
            out = jax.lax.map(lambda lc: one_light(lc[0], lc[1], None), stacked)
        else:
            out = jax.lax.map(lambda a: one_light(a[0][0], a[0][1], a[1]), (stacked, vis))
    else:
        imgs = [
            one_light(lt, c, None if vis is None else vis[i]) for i, (lt, c) in enumerate(pairs)
        ]
        # Lights may differ in channel count (a grey light beside an RGB one): broadcast.
        shape = jnp.broadcast_shapes(*(a.shape for a in imgs))
        out = jnp.stack([jnp.broadcast_to(a, shape) for a in imgs])
    out = out.reshape(k, *image, out.shape[-1])
    return out if response is None else response.apply(out)


def render_planar_sample(
    model: BRDF,
    params: Mapping[str, ArrayLike],
    lights: Light | Sequence[Light],
    camera: Camera | Sequence[Camera],
    *,
    image_size: int | tuple[int, int],
    side: float | tuple[float, float],
    dtype=None,
    **kwargs,
) -> Float[Array, "K H W C"]:
    """:func:`render` of a flat sample of side ``side`` imaged at ``image_size`` = N or (H, W).

    Pixel centres follow the flash-capture convention (:func:`planar_points`): the sample
    lies on z = 0 centred at the origin with normal +z, row 0 at +y. ``kwargs`` go to
    :func:`render` (``shadow``, ``response``, ``cos4``, ``normals``, ...). To reproduce the
    MaterialGAN data (radiance = light_power f_r cos(theta_i)/r^2, then value^(1/2.2) clipped;
    :mod:`jaxrefl.io._capture`) use ``PointLight(light_pos, light_pow)``,
    ``PinholeCamera(camera_pos)``, ``response=GammaResponse(2.2)`` and ``cos4=False``.
    """
    h, w = (image_size, image_size) if isinstance(image_size, int) else image_size
    pts = planar_points(h, w, side, dtype=dtype)
    return render(model, params, lights, camera, points=pts, **kwargs)

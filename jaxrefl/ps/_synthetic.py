"""Synthetic photometric-stereo captures with known normals (for tests and examples).

Surfaces are height fields z(x, y) over the image in the frame of :mod:`jaxrefl.ps`
(x right, y up, z towards the camera, pixel units): a sphere (:func:`sphere_surface`) or a
smooth bump (:func:`bump_surface`). :func:`render` shades the normals with a BRDF of
:mod:`jaxrefl.brdf` under distant lights:

    I_kc = E_kc f_r(wi_k, wo)_c max(n . l_k, 0)        (wo = +z, local frame of n)

so a Lambertian surface of albedo a gives I = E (a / pi) n.l, i.e. rho = a / pi.
No cast shadows are modelled (a convex surface has none).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["bump_surface", "render", "sphere_surface", "spiral_lights"]


def sphere_surface(h: int, w: int, radius: float | None = None):
    """(depth, normals (H, W, 3), mask) of a sphere centred in an H x W image."""
    r = 0.45 * min(h, w) if radius is None else radius
    i, j = np.mgrid[:h, :w].astype(np.float64)
    x, y = j - (w - 1) / 2, -(i - (h - 1) / 2)
    s = (x * x + y * y) / (r * r)
    mask = s < 1.0
    nz = np.sqrt(np.where(mask, 1.0 - s, 0.0))
    n = np.stack([x / r, y / r, nz], axis=-1)
    return np.where(mask, r * nz, np.nan), np.where(mask[..., None], n, np.nan), mask


def bump_surface(h: int, w: int, height: float = 6.0, sigma: float | None = None):
    """(depth, normals, mask) of z = height exp(-(x^2 + y^2) / (2 sigma^2)) on a disc."""
    sig = 0.2 * min(h, w) if sigma is None else sigma
    i, j = np.mgrid[:h, :w].astype(np.float64)
    x, y = j - (w - 1) / 2, -(i - (h - 1) / 2)
    z = height * np.exp(-(x * x + y * y) / (2 * sig * sig))
    zx, zy = -x / (sig * sig) * z, -y / (sig * sig) * z
    n = np.stack([-zx, -zy, np.ones_like(z)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    mask = (x * x + y * y) < (0.45 * min(h, w)) ** 2
    return np.where(mask, z, np.nan), np.where(mask[..., None], n, np.nan), mask


def spiral_lights(k: int, max_zenith_deg: float = 60.0) -> np.ndarray:
    """K unit directions on a Fibonacci spiral over the cap of half-angle max_zenith_deg."""
    g = np.pi * (3.0 - np.sqrt(5.0))
    t = (np.arange(k) + 0.5) / k
    cos_t = 1.0 - t * (1.0 - np.cos(np.radians(max_zenith_deg)))
    sin_t = np.sqrt(1.0 - cos_t * cos_t)
    phi = g * np.arange(k)
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


def render(model, params, normals, mask, lights, intensities) -> np.ndarray:
    """(K, H, W, C) images of the masked normals (module docstring); 0 outside the mask.

    The image formation of :func:`jaxrefl.scene.render` with one
    :class:`~jaxrefl.scene.DirectionalLight` per row of ``lights`` (irradiance
    ``intensities[k]``), an orthographic camera looking down -z and no cos^4 falloff.

    params: natural parameters for ``model.eval`` broadcastable to (H, W) pixels, e.g.
    ``{"albedo": (H, W, C) or (C,)}``.
    """
    from jaxrefl.scene import DirectionalLight, OrthographicCamera
    from jaxrefl.scene import render as render_scene

    normals = np.asarray(normals)
    dt = jnp.asarray(normals).dtype
    # Pixels outside the mask carry NaN normals: shade them as +z and zero them afterwards.
    n = np.where(mask[..., None], normals, np.array([0.0, 0.0, 1.0]))
    e = np.asarray(intensities)
    lts = [DirectionalLight(np.asarray(lights[k]), e[k]) for k in range(len(lights))]
    img = render_scene(
        model,
        {k: jnp.asarray(v, dt) for k, v in params.items()},
        lts,
        OrthographicCamera(),
        points=jnp.zeros(n.shape, dt),
        normals=jnp.asarray(n, dt),
        cos4=False,
    )
    return np.where(mask[None, ..., None], np.asarray(img), 0.0)

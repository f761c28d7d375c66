"""A capture's pixels as least-squares data: observations, geometry, weights, censoring.

For pixel x and photo k of a :class:`jaxrefl.io.Capture` (planar sample, local frame = world
frame, normal +z), the prediction of channel c is

    L_kc(x) = f_r(params(x); wi_k(x), wo_k(x))_c * E_kc(x) * cos(theta_i,k(x))

(``Capture.per_pixel_geometry``), so :class:`jaxrefl.fit.PixelData` gets ``scale = E cos_i``.
Observations are used by their status (:class:`jaxrefl.io.ObsStatus`):

* ``ok``: a value, weight 1;
* ``saturated``: censored from above at ``saturation_level`` (the value is replaced by that
  level; the residual is one-sided: only a prediction *below* it is penalised);
* ``dark``: censored from below at ``dark_level``;
* everything else (non-finite, negative, masked, light or camera below the horizon, mixed
  censoring) and held-out photos: weight 0, left out.

Pixels are taken in row-major order; :func:`pixel_block` returns pixels [start, stop) padded
to ``size`` with weight-0 copies (so every block has one compiled shape; padding pixels come
back MASKED and are dropped by the caller).
"""

from __future__ import annotations

import numpy as np

from jaxrefl.fit import PixelData, pixel_data

__all__ = ["is_colocated", "pixel_block"]


def is_colocated(capture, tol: float = 1e-9) -> bool:
    """Whether every photo's light sits at its camera (a phone flash): then wo = wi."""
    if capture.light_pos is None:
        return False
    return bool(np.all(np.abs(capture.light_pos - capture.camera_pos) <= tol))


def _rows_for(start: int, stop: int, w: int) -> tuple[int, int]:
    return start // w, -(-stop // w)


def pixel_block(
    capture,
    start: int,
    stop: int,
    size: int | None = None,
    *,
    photos: np.ndarray | None = None,
    dtype=np.float32,
) -> PixelData:
    """:class:`PixelData` of pixels [start, stop) (row-major), padded to ``size`` pixels.

    photos: boolean (K,) of the photos to fit (default all); the others get weight 0 and
            stay in the data (so held-out predictions use the same arrays).
    """
    k, h, w, _ = capture.shape
    n = stop - start
    size = n if size is None else int(size)
    if not 0 <= start < stop <= h * w or size < n:
        raise ValueError(f"pixel block [{start}, {stop}) of {h * w} pixels, size {size}")
    r0, r1 = _rows_for(start, stop, w)
    sub = capture.crop(r0, r1, 0, w)
    geo = sub.per_pixel_geometry(dtype=np.float64)
    off = start - r0 * w

    def flat(a):  # (K, rows, W, ...) -> (n, K, ...)
        a = a.reshape(k, (r1 - r0) * w, *a.shape[3:])[:, off : off + n]
        return np.moveaxis(a, 0, 1)

    status = flat(sub.status)
    obs = flat(sub.images).astype(np.float64)
    scale = flat(geo["irradiance"] * geo["cos_i"][..., None])
    wi = flat(geo["wi"])
    wo = flat(geo["wo"])
    sat = status == 1
    dark = status == 2
    weight = ((status == 0) | sat | dark).astype(np.float64)
    if photos is not None:
        weight = weight * np.asarray(photos, bool)[None, :, None]
    obs = np.where(sat, capture.saturation_level, obs)
    obs = np.where(dark, capture.dark_level, obs)
    # Values of unused observations are irrelevant (weight 0) but must be finite.
    obs = np.where(weight > 0, obs, 0.0)
    censored = np.where(sat, 1, np.where(dark, -1, 0)).astype(np.int8)
    if size > n:
        pad = size - n

        def padded(a, fill=None):
            if fill is None:
                rep = np.repeat(a[-1:], pad, axis=0)
            else:
                rep = np.full((pad, *a.shape[1:]), fill, a.dtype)
            return np.concatenate([a, rep], axis=0)

        obs, scale, wi, wo, censored = (padded(a) for a in (obs, scale, wi, wo, censored))
        weight = padded(weight, 0.0)
    colocated = is_colocated(capture)
    return pixel_data(
        obs.astype(dtype),
        wi.astype(dtype),
        None if colocated else wo.astype(dtype),
        scale=scale.astype(dtype),
        weight=weight.astype(dtype),
        censored=censored,
        dtype=dtype,
    )

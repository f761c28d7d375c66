"""A capture's pixels as least-squares data: observations, geometry, weights, censoring.

For pixel x and photo k of a :class:`jaxrefl.io.Capture` (planar sample, local frame = world
frame, normal +z), the prediction of channel c is

    L_kc(x) = f_r(params(x); wi_k(x), wo_k(x))_c * E_kc(x) * cos(theta_i,k(x))

(``Capture.per_pixel_geometry``), so :class:`jaxrefl.fit.PixelData` gets ``scale = E cos_i``.
Observations are used by their status (:class:`jaxrefl.io.ObsStatus`):

* ``ok``: a value, weight 1;
* ``saturated``: censored: the true value is at least min(recorded, ``saturation_level``)
  (the residual is one-sided: only a prediction *below* it is penalised). At full
  resolution that is the saturation level; after :meth:`Capture.downsample` a block with
  some clipped pixels records their mean, which the true mean exceeds, and which may be far
  below the saturation level: the block's own value is the bound then;
* ``dark``: censored the other way: the true value is at most max(recorded, ``dark_level``);
* everything else (non-finite, negative, masked, light or camera below the horizon, mixed
  censoring) and held-out photos: weight 0, left out.

Pixels are taken in row-major order; :func:`pixel_block` returns pixels [start, stop) padded
to ``size`` with weight-0 copies (so every block has one compiled shape; padding pixels come
back MASKED and are dropped by the caller). :func:`pixel_take` reads pixels at any indices,
:func:`subsample` a random set of them, and :func:`stack_folds` repeats such data once per
leave-one-photo-out fold (the model selection's and the discrepancy's held-out scores).
"""

from __future__ import annotations

from dataclasses import replace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import PixelData, pixel_data
from jaxrefl.io import ObsStatus

__all__ = [
    "is_colocated",
    "pixel_block",
    "pixel_take",
    "resolvable_alpha",
    "stack_folds",
    "subsample",
]


def is_colocated(capture, tol: float = 1e-9) -> bool:
    """Whether every photo's light sits at its camera (a phone flash): then wo = wi."""
    if capture.light_pos is None:
        return False
    return bool(np.all(np.abs(capture.light_pos - capture.camera_pos) <= tol))


def resolvable_alpha(
    capture, floor: float = 1e-3, cap: float = 0.1, *, photos: np.ndarray | None = None
) -> float:
    """The narrowest specular lobe a capture can resolve: a GGX/Beckmann alpha.

    Each photo k samples a pixel's BRDF at one half vector h_k = (wi + wo)/|wi + wo|. A lobe
    whose width is below the angular spacing of those samples has its peak between photos:
    its height and width trade off freely against each other (one bright sample fits a
    needle of any width), so on a real surface that is not exactly the model (glitter,
    tilted tiles) the fit extrapolates wildly to unseen directions. We take half the median
    nearest-neighbour angle (radians) between the half vectors at the sample centre (alpha
    is about the lobe's angular half width), clipped to [floor, cap].

    Example: ``bath_tile`` (9 flash photos about 24 cm above the sample) has its half
    vectors about 5.5 degrees apart, so alpha_min = 0.048. Bounded there, a fit predicts a
    held-out photo better than Lambert; allowed down to 1e-3, its needles predict it worse.

    photos: boolean (K,) of the photos in use (default all): the photos a fit is given. Only
            their half vectors count: a held-out photo (weight 0) resolves nothing, and
            counting it would let the fit's lobes be narrower than its own photos resolve.
    """
    if photos is not None:
        capture = capture.select(np.asarray(photos, bool))
    k = capture.n_photos
    if k < 2:
        return float(floor)
    h, w = capture.shape[1:3]
    p = capture.points[h // 2, w // 2]
    if capture.light_pos is not None:
        wi = capture.light_pos - p
    else:
        wi = capture.light_dir.copy()
    wo = capture.camera_pos - p
    wi = wi / np.linalg.norm(wi, axis=-1, keepdims=True)
    wo = wo / np.linalg.norm(wo, axis=-1, keepdims=True)
    hv = wi + wo
    hv = hv / np.linalg.norm(hv, axis=-1, keepdims=True)
    ang = np.arccos(np.clip(hv @ hv.T, -1.0, 1.0))
    np.fill_diagonal(ang, np.inf)
    nn = ang.min(axis=1)
    nn = nn[np.isfinite(nn) & (nn > 0)]
    if nn.size == 0:  # every photo at the same half vector: nothing to resolve a width with
        return float(cap)
    return float(np.clip(0.5 * np.median(nn), floor, cap))


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
        raise JaxreflError(f"pixel block [{start}, {stop}) of {h * w} pixels, size {size}")
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
    sat = status == ObsStatus.SATURATED
    dark = status == ObsStatus.DARK
    weight = ((status == ObsStatus.OK) | sat | dark).astype(np.float64)
    if photos is not None:
        weight = weight * np.asarray(photos, bool)[None, :, None]
    obs = np.where(sat, np.minimum(obs, capture.saturation_level), obs)
    obs = np.where(dark, np.maximum(obs, capture.dark_level), obs)
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


def pixel_take(capture, pixels: np.ndarray, *, dtype=np.float32) -> PixelData:
    """:class:`PixelData` of the pixels at the row-major indices ``pixels`` (n,), in that
    order: the same arrays :func:`pixel_block` gives for them, with the geometry computed
    for those pixels alone (a random sample costs its own size, not the capture's)."""
    _k, h, w, _ = capture.shape
    idx = np.asarray(pixels, np.int64).ravel()
    if idx.size == 0 or idx.min() < 0 or idx.max() >= h * w:
        raise JaxreflError(f"pixel indices must be in [0, {h * w}) and not empty")
    rows, cols = np.divmod(idx, w)
    # The picked pixels as a capture one row high: every per-pixel array gathered alike.
    line = replace(
        capture,
        images=capture.images[:, rows, cols][:, None],
        status=capture.status[:, rows, cols][:, None],
        points=capture.points[rows, cols][None],
    )
    return pixel_block(line, 0, idx.size, dtype=dtype)


def subsample(capture, n_pixels: int, seed: int, dtype) -> PixelData:
    """PixelData of ``n_pixels`` random pixels (all where the capture has fewer), in
    row-major order."""
    _k, h, w, _c = capture.shape
    total = h * w
    pick = np.arange(total)
    if total > n_pixels:
        pick = np.sort(np.random.default_rng(seed).choice(total, n_pixels, replace=False))
    return pixel_take(capture, pick, dtype=dtype)


def stack_folds(data: PixelData, train: list[int], k: int, size: int):
    """``data`` (n pixels) once per training photo j, each copy fitted without photo j, padded
    to a multiple of ``size`` rows with unweighted rows. Returns (stacked data, (rows, K)
    training mask, (rows,) the copy's held-out photo, -1 for padding)."""
    n = data.obs.shape[0]
    rows = -(-(n * len(train)) // size) * size
    pad = rows - n * len(train)
    idx = np.concatenate([np.tile(np.arange(n), len(train)), np.full(pad, n - 1)])
    held = np.concatenate([np.repeat(np.asarray(train), n), np.full(pad, -1)])
    stacked = jax.tree.map(lambda a: a[idx], data)
    live = jnp.asarray(held >= 0, stacked.weight.dtype)[:, None, None]
    stacked = eqx.tree_at(lambda d: d.weight, stacked, stacked.weight * live)
    mask = np.zeros((rows, k), bool)
    mask[:, train] = True
    mask[held >= 0, held[held >= 0]] = False
    return stacked, mask, held

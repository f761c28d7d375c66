"""Error metrics for a BRDF fitted to measured samples: cosine-weighted, log-space and
relative L2.

Notation: samples k = 1..K with directions (wi_k, wo_k), channels c = 1..C, measured
f_kc and fitted f̂_kc (f_r in 1/sr, no cosine), cos_i,k = cos(theta_i) of sample k, and a
non-negative weight w_k per sample: the solid-angle measure (dwi dwo) the sample stands for.
``w_k = 0`` leaves a sample out. Default weights are 1 (every sample counts the same, the
right choice for a gonioreflectometer's roughly uniform grid); for MERL cells see
:func:`sample_weights`. The three metrics are

    cosine-weighted L2 (Ngan, Durand & Matusik 2005, "Experimental analysis of BRDF models",
    EGSR 2005, Sec. 4):

        E_cos = sqrt( sum_k w_k sum_c (f̂_kc - f_kc)^2 cos_i,k^2  /  (C sum_k w_k) )   [1/sr]

      the discrete form of sqrt( ∫∫ (f̂ - f)^2 cos^2 theta_i dwi dwo / ∫∫ dwi dwo ) over the
      measured domain: the RMS difference of the *cosine-weighted* BRDF f_r cos(theta_i).
      Like Ngan et al., :func:`error_metrics` leaves out directions beyond 80 degrees from
      the normal by default (``max_theta_deg``).

    log-space L2 (the cosine-weighted log metric of Löw, Kronander, Ynnerman & Unger 2012,
    "BRDF models for accurate and efficient rendering of glossy surfaces", ACM TOG 31(1)):

        E_log = sqrt( sum_k w_k sum_c [ln(1 + f̂_kc cos_i,k) - ln(1 + f_kc+ cos_i,k)]^2
                      / (C sum_k w_k) )                                          [1]

      with f+ = max(f, 0) and f̂ clamped at 0 likewise: ln(1 + x) is not defined for
      x <= -1, and negative values are sensor noise around 0. It compresses the highlight,
      so a fit good at the diffuse part scores well even if the peak is off.

    relative L2:

        E_rel = sqrt( sum_k w_k sum_c (f̂_kc - f_kc)^2  /  sum_k w_k sum_c f_kc^2 )      [1]

      on f_r itself (no cosine): 0 is a perfect fit, 1 is as bad as predicting f_r = 0.

All three are computed over the same samples: finite measured values (every channel), both
directions above the horizon and, in :func:`error_metrics`, within ``max_theta_deg`` of the
normal. Functions take NumPy or JAX arrays and return JAX scalars (jit- and grad-safe: a
masked sample is swapped for 0 before any arithmetic).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxrefl._errors import JaxreflError

__all__ = [
    "METRICS",
    "cosine_weighted_l2",
    "error_metrics",
    "log_l2",
    "relative_l2",
    "sample_weights",
    "usable_samples",
]

#: Names of the metrics, in report order.
METRICS = ("cosine_weighted_l2", "log_l2", "relative_l2")

# The metrics' arguments: f_r of K samples in C channels, and one value per sample.
_Values = Float[ArrayLike, "K C"]
_PerSample = Float[ArrayLike, " K"]


def _prepare(measured, fitted, cos_i, weight):
    f = jnp.asarray(measured)
    dtype = f.dtype if jnp.issubdtype(f.dtype, jnp.floating) else jnp.float32
    f = f.astype(dtype)
    g = jnp.asarray(fitted, dtype=dtype)
    if f.ndim == 1:
        f, g = f[:, None], g.reshape(-1, 1)
    if g.shape != f.shape:
        raise JaxreflError(f"measured {f.shape} and fitted {g.shape} values differ in shape")
    k = f.shape[0]
    c = jnp.broadcast_to(jnp.asarray(cos_i, dtype=dtype).reshape(-1), (k,))
    w = jnp.ones((k,), dtype) if weight is None else jnp.asarray(weight, dtype).reshape(-1)
    if w.shape != (k,):
        raise JaxreflError(f"weight must have one entry per sample ({k}), got {w.shape}")
    ok = jnp.all(jnp.isfinite(f) & jnp.isfinite(g), axis=-1) & jnp.isfinite(c) & (w > 0)
    # Gradient-safe: masked samples become exact zeros before any arithmetic.
    f = jnp.where(ok[:, None], f, 0.0)
    g = jnp.where(ok[:, None], g, 0.0)
    c = jnp.where(ok, c, 0.0)
    w = jnp.where(ok & jnp.isfinite(w), w, 0.0)
    return f, g, c, w


def _weighted_mean(sq: Array, w: Array) -> Array:
    """sum_k w_k sum_c sq_kc / (C sum_k w_k); NaN when no sample has weight."""
    den = sq.shape[-1] * jnp.sum(w)
    num = jnp.sum(w[:, None] * sq)
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), jnp.nan)


def _sqrt(x: Array) -> Array:
    # sqrt of a mean of squares (>= 0); the swap keeps d sqrt / dx finite at an exact fit.
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), jnp.where(jnp.isnan(x), x, 0.0))


def _rms(d: Array, w: Array) -> Array:
    """The weighted root mean square of the differences ``d`` (K, C)."""
    return _sqrt(_weighted_mean(d * d, w))


def cosine_weighted_l2(
    measured: _Values, fitted: _Values, cos_i: _PerSample, weight: _PerSample | None = None
) -> Float[Array, ""]:
    """E_cos of Ngan et al. 2005 (module docstring), in 1/sr."""
    f, g, c, w = _prepare(measured, fitted, cos_i, weight)
    return _rms((g - f) * c[:, None], w)


def log_l2(
    measured: _Values, fitted: _Values, cos_i: _PerSample, weight: _PerSample | None = None
) -> Float[Array, ""]:
    """E_log, the cosine-weighted log-space L2 of Löw et al. 2012 (module docstring)."""
    f, g, c, w = _prepare(measured, fitted, cos_i, weight)
    # Clamp at 0: ln(1 + x) needs x > -1, and negative f_r is noise (module docstring).
    lf = jnp.log1p(jnp.maximum(f, 0.0) * c[:, None])
    lg = jnp.log1p(jnp.maximum(g, 0.0) * c[:, None])
    return _rms(lg - lf, w)


def relative_l2(
    measured: _Values, fitted: _Values, weight: _PerSample | None = None
) -> Float[Array, ""]:
    """E_rel = |f̂ - f|_w / |f|_w on f_r (module docstring); NaN if f is 0 everywhere."""
    f, g, _, w = _prepare(measured, fitted, 1.0, weight)
    num = jnp.sum(w[:, None] * (g - f) ** 2)
    den = jnp.sum(w[:, None] * f * f)
    return _sqrt(jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), jnp.nan))


def usable_samples(wi: ArrayLike, wo: ArrayLike, values: ArrayLike, max_theta_deg=80.0):
    """Boolean (K,) mask: finite values in every channel, both directions above the horizon
    and (unless ``max_theta_deg`` is None) within ``max_theta_deg`` of the normal."""
    wi, wo, values = np.asarray(wi), np.asarray(wo), np.asarray(values)
    if values.ndim == 1:
        values = values[:, None]
    ok = np.all(np.isfinite(values), axis=-1) & (wi[:, 2] > 0) & (wo[:, 2] > 0)
    if max_theta_deg is not None:
        # A hair of slack: grid angles written as radians in text files round either way.
        cmin = np.cos(np.deg2rad(float(max_theta_deg) + 1e-6))
        ok &= (wi[:, 2] >= cmin) & (wo[:, 2] >= cmin)
    return ok


def sample_weights(measured: Any) -> np.ndarray:
    """Solid-angle weight of each sample of a :class:`~jaxrefl.io.MeasuredBRDF`.

    MERL cells (``measured.meta["cell"]`` from :func:`jaxrefl.io.merl_to_measured`) cover
    unequal parts of (wi, wo) space: in Rusinkiewicz coordinates dwi dwo =
    4 cos(theta_d) sin(theta_d) sin(theta_h) dtheta_h dtheta_d dphi_h dphi_d, and the table's
    theta_h = (u/90)^2 pi/2 makes dtheta_h proportional to u. The weight of cell (i, j, k)
    is therefore cos(theta_d) sin(theta_d) sin(theta_h) (i + 1/2) at its centre, scaled to a
    mean of 1. Every other source gets weight 1 per sample.
    """
    meta: Mapping[str, Any] = getattr(measured, "meta", {}) or {}
    cells = meta.get("cell")
    n = len(measured)
    if cells is None or str(meta.get("format", "")).lower() != "merl binary":
        return np.ones(n)
    cells = np.asarray(cells)
    u = cells[:, 0] + 0.5
    theta_h = (u / 90.0) ** 2 * (np.pi / 2)
    theta_d = (cells[:, 1] + 0.5) / 90.0 * (np.pi / 2)
    w = np.cos(theta_d) * np.sin(theta_d) * np.sin(theta_h) * u
    return w / np.mean(w)


def error_metrics(
    measured: Float[ArrayLike, "K C"],
    fitted: Float[ArrayLike, "K C"],
    wi: Float[ArrayLike, "K 3"],
    wo: Float[ArrayLike, "K 3"],
    *,
    weight: Float[ArrayLike, " K"] | None = None,
    max_theta_deg: float | None = 80.0,
) -> dict[str, float]:
    """All three metrics (``METRICS``) as Python floats, over the samples selected by
    :func:`usable_samples` (``max_theta_deg``: 80 degrees as Ngan et al.; None for all)."""
    f = np.asarray(measured, dtype=np.float64)
    if f.ndim == 1:
        f = f[:, None]
    g = np.asarray(fitted, dtype=np.float64).reshape(f.shape)
    wi = np.asarray(wi, dtype=np.float64)
    ok = usable_samples(wi, wo, f, max_theta_deg)
    w = np.ones(len(f)) if weight is None else np.asarray(weight, dtype=np.float64)
    w = np.where(ok, w, 0.0)
    cos_i = wi[:, 2]
    return {
        "cosine_weighted_l2": float(cosine_weighted_l2(f, g, cos_i, w)),
        "log_l2": float(log_l2(f, g, cos_i, w)),
        "relative_l2": float(relative_l2(f, g, w)),
    }

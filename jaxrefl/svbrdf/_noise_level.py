"""A capture's noise-level function, estimated from its own residuals.

The per-pixel models' default noise is Gaussian of unknown scale s per pixel, the same for
every observation of the pixel. A camera's noise is not: photon noise grows with the
signal, and so do the errors that scale with it (flat field, tone curve, JPEG, a misfit
that grows with the highlight). A pixel's few bright observations (its highlight, which
carries F0 and the lobe's width) are then noisier than its many dark ones, and a flat
noise model, its scale set by the dark ones, makes the highlight's parameters look better
known than they are. :func:`estimate_noise_level` estimates one shape for the capture,
the noise level function of :class:`jaxrefl.fit.LevelNoise` (Liu et al., TPAMI 2008),

    sd_ik = s_i sqrt(1 + gain y_ik + (rel y_ik)^2),     y = max(obs, 0),

with the scale s_i still each pixel's own, and keeps it where the residuals support it.

Estimate. The job's model is fitted with the flat noise model to ``AutoOptions.max_pixels``
random pixels (one tile: the tile program the model's choice compiled serves it). A least
squares residual e_k is shorter than the noise by its leverage h_k (the diagonal of the
hat matrix W^1/2 J (J^T W J)^-1 J^T W^1/2 at the optimum): E[e_k^2] = sd_k^2 (1 - h_k) to
first order. The bright observations have the highest leverage (one highlight fixes the
lobe), so uncorrected residuals would say the highlights are the quietest. Each squared
residual is divided by 1 - h_k; observations with h_k above :data:`MAX_LEVERAGE` are left
out (their residual says almost nothing about the noise). The shape maximises the Gaussian
likelihood of the corrected residuals with each pixel's s profiled out,

    l(gain, rel) = -1/2 sum_i [n_i log(mean_k z_ik^2 / g_ik^2) + sum_k log g_ik^2],

g^2 = 1 + gain y + (rel y)^2, over a grid in log10(gain) and log10(rel) (:data:`GRID`),
then a finer grid around its best point. The flat model (gain = rel = 0) is its special
case; the shape is kept only where its log-likelihood gain beats the flat one by more than
the BIC's penalty of its two parameters, log(n) with n the observations used, and ``why``
says which.

Scope: the per-pixel models with the flat default noise (``GaussianNoise(sigma=None)``).
A job that gives its noise model keeps it, and ``pooled`` keeps its capture-wide noise
scale (chosen with its width: :func:`jaxrefl.svbrdf.choose_pooled`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl import fit

from ._data import subsample
from ._job_types import FitJob
from ._tile_fitter import TileFitter

__all__ = ["GRID", "MAX_LEVERAGE", "NoiseLevel", "estimate_noise_level", "with_noise"]

#: Observations of larger leverage are left out of the estimate: at h = 0.9 a residual is
#: a tenth of the noise's variance and its correction 1 / (1 - h) amplifies its error 10x.
MAX_LEVERAGE = 0.9
#: The coarse grid of log10(gain) and log10(rel), in units of obs^-1 (obs in the capture's
#: radiance units, about 1 at full exposure): from shapes that barely bend over the
#: camera's range to a floor 1000 x below the brightest observation's noise.
GRID = np.arange(-1.0, 4.01, 0.5)
# Ridge relative to the curvature's largest diagonal entry: keeps the leverage finite
# where a direction of theta is unseen (a lobe no photo saw), which then takes none.
_RIDGE = 1e-9


@dataclass(frozen=True)
class NoiseLevel:
    """The estimate: ``noise`` (the noise model the fit runs with: the
    :class:`~jaxrefl.fit.LevelNoise` where kept, else the job's own), ``gain``/``rel`` as
    estimated (kept or not), the log-likelihood gain over the flat model and the BIC
    penalty it had to beat, the observations and pixels used, and ``why``."""

    noise: fit.NoiseModel
    kept: bool
    gain: float | None
    rel: float | None
    loglik_gain: float | None
    penalty: float | None
    n_obs: int
    n_pixels: int
    why: str

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (the report's ``noise_level``)."""
        out = {
            "kept": self.kept,
            "noise": self.noise.to_json(),
            "gain": self.gain,
            "rel": self.rel,
            "loglik_gain": self.loglik_gain,
            "penalty": self.penalty,
            "n_obs": self.n_obs,
            "n_pixels": self.n_pixels,
            "why": self.why,
        }
        return out


def _skip(job: FitJob, why: str) -> NoiseLevel:
    """Nothing estimated (None for the figures; ``why`` says why)."""
    return NoiseLevel(job.config.noise, False, None, None, None, None, 0, 0, why)


@eqx.filter_jit
def _corrected(residual, theta, data):
    """Per observation (N, K*C): the squared residual over 1 - leverage, the leverage, the
    clipped observation y and whether it counts (usable, uncensored, weight > 0)."""

    def pixel(t, d):
        pred = residual.predict(t, d)
        jac = jax.jacfwd(lambda u: residual.predict(u, d))(t).reshape(-1, t.shape[0])
        ok = (residual.usable(d) & (d.censored == 0)).reshape(-1)
        w = jnp.where(ok, d.weight.reshape(-1), 0.0)
        h = jac.T @ (w[:, None] * jac)
        h = h + _RIDGE * jnp.max(jnp.diag(h)) * jnp.eye(t.shape[0], dtype=t.dtype)
        sol = jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(h), True), jac.T)
        lev = w * jnp.sum(jac * sol.T, axis=-1)
        e = jnp.where(ok, (pred - d.obs).reshape(-1), 0.0)
        z2 = w * e * e / jnp.maximum(1.0 - lev, 1.0 - MAX_LEVERAGE)  # the kept ones only
        return z2, lev, jnp.maximum(d.obs, 0.0).reshape(-1), ok & (lev <= MAX_LEVERAGE)

    return jax.vmap(pixel)(theta, data)


def _profile(z2, y, use, gains, rels):
    """l(gain, rel) (module docstring) on the grid of ``gains`` x ``rels`` (0 allowed)."""
    n = use.sum(axis=1)
    out = np.empty((gains.size, rels.size))
    for a, gain in enumerate(gains):
        for b, rel in enumerate(rels):
            g2 = 1.0 + gain * y + (rel * y) ** 2
            s2 = np.where(use, z2 / g2, 0.0).sum(axis=1) / n
            out[a, b] = -0.5 * (np.sum(n * np.log(s2)) + np.sum(np.where(use, np.log(g2), 0.0)))
    return out


def fit_noise_level(z2: np.ndarray, y: np.ndarray, use: np.ndarray) -> tuple[float, float, float]:
    """(gain, rel, log-likelihood gain over gain = rel = 0) of leverage-corrected squared
    residuals ``z2``, observations ``y`` and the observations to use ``use`` (each
    (pixels, M)); pixels need two observations to count."""
    z2, y = np.asarray(z2, np.float64), np.asarray(y, np.float64)
    use = np.asarray(use, bool) & np.isfinite(z2) & np.isfinite(y)
    rows = use.sum(axis=1) >= 2
    z2, y, use = z2[rows], y[rows], use[rows]
    # A residual of exactly 0 (rounding) would send its pixel's log-scale to -inf.
    pos = z2[use]
    floor = 1e-12 * float(np.median(pos)) if pos.size and np.median(pos) > 0 else 1e-300
    z2 = np.maximum(z2, floor)
    flat = float(_profile(z2, y, use, np.zeros(1), np.zeros(1))[0, 0])
    grid = np.concatenate([[0.0], 10.0**GRID])
    prof = _profile(z2, y, use, grid, grid)
    a, b = np.unravel_index(np.argmax(prof), prof.shape)

    def around(i):  # a finer grid (a tenth of a decade) between the neighbours
        lo = GRID[0] - 0.5 if i == 0 else np.log10(grid[i]) - 0.5
        return np.concatenate([[0.0], 10.0 ** np.arange(lo, lo + 1.01, 0.1)])

    fine_g, fine_r = around(a), around(b)
    prof2 = _profile(z2, y, use, fine_g, fine_r)
    a2, b2 = np.unravel_index(np.argmax(prof2), prof2.shape)
    if prof2[a2, b2] >= prof[a, b]:
        return float(fine_g[a2]), float(fine_r[b2]), float(prof2[a2, b2]) - flat
    return float(grid[a]), float(grid[b]), float(prof[a, b]) - flat


def estimate_noise_level(capture, job: FitJob) -> NoiseLevel:
    """The capture's noise-level function for ``job`` (module docstring): fitted with the
    job's model to ``job.auto``'s pixel count and seed, kept where the BIC supports it.
    Returns a :class:`NoiseLevel`; its ``noise`` is the one the fit runs with."""
    if job.noise_level == "flat":
        return _skip(job, "the job asks for the flat noise model (noise_level='flat')")
    noise = job.config.noise
    if not (isinstance(noise, fit.GaussianNoise) and noise.sigma is None):
        return _skip(job, f"the job gives its noise model ({noise.kind})")
    if job.model == "pooled":
        return _skip(job, "pooled's noise scale is capture-wide, chosen with its width")
    fitter = TileFitter(capture, job)
    _k, h, w, _c = capture.shape
    n = min(job.auto.max_pixels, job.tile_pixels, h * w)
    data = subsample(capture, n, job.auto.seed, job.dtype)
    rows = job.tile_pixels  # the tile's shape: the model's compiled tile program serves
    if rows > n:
        idx = np.concatenate([np.arange(n), np.full(rows - n, n - 1)])
        data = jax.tree.map(lambda a: a[idx], data)
        live = jnp.asarray(np.arange(rows) < n, data.weight.dtype)[:, None, None]
        data = eqx.tree_at(lambda d: d.weight, data, data.weight * live)
    r, res, _noise_var, fit_data = fitter._fit(data)
    ok_t = np.all(np.isfinite(np.asarray(r.theta)), axis=-1)
    theta = jnp.where(jnp.asarray(ok_t)[:, None], r.theta, 0.0)
    z2, _lev, y, use = (np.asarray(a) for a in _corrected(res, theta, fit_data))
    use = use & ok_t[:, None]
    n_obs = int(use.sum())
    n_pix = int((use.sum(axis=1) >= 2).sum())
    if n_pix < 2:
        return _skip(job, "too few pixels with residuals to estimate a noise shape")
    gain, rel, gain_ll = fit_noise_level(z2, y, use)
    penalty = float(np.log(max(n_obs, 2)))  # BIC: (2 parameters / 2) log n
    kept = gain_ll > penalty and (gain > 0 or rel > 0)
    if kept:
        why = (
            f"the residuals grow with the signal: log-likelihood +{gain_ll:.1f} over the flat "
            f"noise model (BIC penalty {penalty:.1f}) on {n_obs} observations of {n_pix} pixels"
        )
        level: fit.NoiseModel = fit.LevelNoise(gain=gain, rel=rel)
    else:
        why = (
            f"the flat noise model: the best shape gains {gain_ll:.1f} in log-likelihood, "
            f"not more than the BIC penalty {penalty:.1f} ({n_obs} observations)"
        )
        level = noise
    return NoiseLevel(level, kept, gain, rel, float(gain_ll), penalty, n_obs, n_pix, why)


def with_noise(job: FitJob, level: NoiseLevel) -> FitJob:
    """``job`` with the estimate's noise model."""
    return replace(job, config=job.config.replace(noise=level.noise))

"""The light's uncertainty carried into an uncertainty map's per-pixel intervals.

The map's posterior is sampled under one light: the fit's estimate (``FitJob.light``,
:class:`jaxrefl.svbrdf.LightEstimate`). The light itself is known only to its reported
covariance (the Laplace's, its offset widened to the delete-one-photo jackknife's where the
photos disagree more than the noise model allows: :mod:`jaxrefl.svbrdf._light_cov`), so each
pixel's parameters have a second source of spread: the parameters that
would fit the pixel under another draw of the light. To first order (the delta method,
through the implicit function theorem at the pixel's optimum theta*), a light that changes
the pixel's predictions by dp moves its optimum by

    d theta = -(J^T W J)^-1 J^T W dp

with J = d pred / d theta at theta* (its Gauss-Newton curvature J^T W J) and W the
whitened weights (weight / std(obs)^2 of the noise model; censored observations left out).
dp (from the estimated light to a draw) is computed exactly for each of
:data:`LIGHT_DRAWS` draws of the light (:func:`jaxrefl.svbrdf.light_draws`); the variance
of the moves over the draws is the spread of the optimum over the light's posterior,
mapped to natural units by the bijections' slopes at theta*. The map's intervals are then
those of the convolution of the pixel's posterior with that spread: its std becomes
sqrt(std^2 + var_light), and its 5% / 95% quantiles move away from the mean by the same
factor, inside the parameter's box (exact for a Gaussian posterior, the Laplace pixels; a
first-order widening for the sampled ones). What the light estimate holds at its prior
(the offset's components past ``ESTIMATED_OFFSET`` of :mod:`jaxrefl.svbrdf._light_problem`)
is not propagated: it scales every photo nearly alike, a common factor of the maps that the
photos cannot tell apart from them (as the stated power and the gains' common factor), so
the maps are conditional on it, as on those. The draws in ``posterior.nc`` stay conditional
on the estimated light; ``uncertainty.exr`` holds the widened summaries, and the result's
``light_std`` the light's share, per pixel and parameter.

Which light term a map carries (:func:`map_term`; ``report.json`` ``light.map_term``):

* ``estimate``: the fit's light is an estimate (``offset``, ``offset+gains``): draws from
  its covariance around it, the spread taken about the draws' mean, as above.
* ``fixed: lens-position spread``: ``auto`` kept the stated light (``fixed``) after scoring
  the candidates. Keeping ``fixed`` says only that the held-out photos did not support
  moving the flash, not that it sits at the lens (a phone's flash is 0.5-1.5 cm from it),
  so the map still carries the light's uncertainty about the lens position. The photos'
  own account of the offset is the ``offset`` estimate (:func:`jaxrefl.svbrdf.estimate_light`
  with ``offset``, its reported covariance C: the same subsample, seed and held-out photos
  as ``auto``'s score), from the problem ``auto`` scored and kept on the fit's light. Its
  draws come from the mixture of the two models ``auto`` could not tell apart, with equal
  weights: the flash at the lens (d = 0) and the flash at the estimate mu (d ~ N(mu, C)).
  The spread is the second moment of the moves about the map's centre, the fit under d = 0
  (the draws at d = 0 move nothing): 1/2 E[move^2] over N(mu, C). A zero-mean N(0, C)
  would be the other choice; it is not the honest one: C says how well the photos pin the
  offset where it is estimated, and where mu lies many of C's stds from 0 (a flash 1-1.5 cm
  off, pinned to a millimetre) N(0, C) gives the estimate itself no weight and widens by C
  alone, far less than the move to the estimate that the photos allow. Where mu is within
  C of 0 (a flash at the lens) the two choices differ little. The gains stay the stated
  ones (``fixed`` has no gains), the offset's z its prior's, as above.
* ``none``: the light was given, not estimated: ``FitJob.light="fixed"`` (the user stated
  the light: the map is conditional on it), a capture with directional lights, or too few
  training photos for ``auto`` to score the light.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._data import pixel_block
from ._light import estimate_light, light_draws
from ._light_options import LightOptions
from ._light_problem import ESTIMATED_OFFSET

__all__ = ["LIGHT_DRAWS", "MAP_TERMS", "light_spread", "map_term", "widen_for_light"]

#: Draws of the light over which its spread is taken: the std of a std from n draws has a
#: relative error of about 1 / sqrt(2 n), 13% at 32, small beside a std's own uncertainty.
LIGHT_DRAWS = 32
# Ridge relative to the curvature's largest diagonal entry: keeps the solve finite where a
# direction of theta is unseen (a lobe no photo saw); such a direction gets no light spread
# from it, as it has no optimum to move.
_RIDGE = 1e-9
#: The light terms a map can carry (module docstring), as ``report.json`` names them.
MAP_TERMS = ("estimate", "fixed: lens-position spread", "none")


@eqx.filter_jit
def _gauss_newton(residual, theta, data0):
    """Per pixel: J (KC, P) at theta*, the whitened weights (KC,) (censored and unusable
    observations 0) and the Cholesky factor of the ridged curvature J^T W J (P, P)."""

    def pixel(t, d0):
        jac = jax.jacfwd(lambda u: residual.predict(u, d0))(t).reshape(-1, t.shape[0])
        ok = residual.usable(d0) & (d0.censored == 0)
        w = jnp.where(ok, d0.weight / residual.noise.std(d0.obs) ** 2, 0.0).reshape(-1)
        h = jac.T @ (w[:, None] * jac)
        h = h + _RIDGE * jnp.max(jnp.diag(h)) * jnp.eye(t.shape[0], dtype=t.dtype)
        return jac, w, jnp.linalg.cholesky(h)

    return jax.vmap(pixel)(theta, data0)


@eqx.filter_jit
def _moves(residual, theta, data0, data, jac, w, chol):
    """(N, P) the first-order move of each pixel's optimum from ``data0``'s light to
    ``data``'s (module docstring), in theta."""

    def pixel(t, d0, d, j, wf, c):
        dp = (residual.predict(t, d) - residual.predict(t, d0)).reshape(-1)
        g = j.T @ (wf * dp)
        return -jax.scipy.linalg.cho_solve((c, True), g)

    return jax.vmap(pixel)(theta, data0, data, jac, w, chol)


def map_term(light) -> str:
    """The light term (:data:`MAP_TERMS`, module docstring) that a map of a fit under
    ``light`` carries: its :class:`jaxrefl.svbrdf.LightEstimate`, None for the light as
    the capture states it."""
    if light is None:
        return MAP_TERMS[2]
    if light.mode != "fixed":
        return MAP_TERMS[0] if light.cov is not None else MAP_TERMS[2]
    # auto kept the stated light after scoring the candidates (cv_rmse holds their scores)
    if light.asked == "auto" and light.cv_rmse:
        return MAP_TERMS[1]
    return MAP_TERMS[2]


def _held(cov: np.ndarray) -> np.ndarray:
    """``cov`` with the offset's components past ``ESTIMATED_OFFSET`` zeroed: they change
    every photo's irradiance nearly alike, a common scale of the maps (as the stated power
    and the gains' common factor are), on which the maps are conditional."""
    cov = np.array(cov, np.float64)
    cov[ESTIMATED_OFFSET:3, :] = 0.0
    cov[:, ESTIMATED_OFFSET:3] = 0.0
    return cov


def _lens_estimate(cf, capture):
    """The ``offset`` estimate of ``capture`` for a fit whose ``auto`` kept ``fixed``, with
    the stated gains and a covariance over the estimated offset alone (module docstring);
    None where it has no covariance. The estimate is the one ``auto``'s problem gives
    (:class:`jaxrefl.svbrdf._light.OffsetSource`, kept on the fit's light) where that was
    computed on this capture with the job's held-out photos and lobe bound; otherwise
    :func:`jaxrefl.svbrdf.estimate_light` computes it afresh."""
    job = cf.job
    source = cf.light.offset_source
    if source is not None and source.serves(capture, job.holdout, job.alpha_min):
        est = source.estimate()
    else:
        est = estimate_light(capture, "offset", LightOptions.of_job(job))
    if est.cov is None:
        return None
    cov = np.zeros_like(est.cov)
    cov[:3, :3] = est.cov[:3, :3]
    return replace(est, cov=_held(cov), photo_gain=np.ones(capture.n_photos))


def light_spread(
    cf, lp, data, capture, theta: np.ndarray, n_draws: int = LIGHT_DRAWS, seed: int = 0
) -> np.ndarray | None:
    """(N, P) the light's variance of each pixel's fitted parameters in natural units
    (module docstring), for the map's model parameters in the order of its space; None where
    the map carries no light term (:func:`map_term` ``none``).

    ``estimate``: the variance of the moves over draws of the fit's light. ``fixed:
    lens-position spread``: their second moment about the fit under the stated light over
    the mixture of d = 0 and the ``offset`` estimate (``n_draws // 2`` draws at the lens,
    which move nothing, the rest from the estimate).

    cf:      the capture fit (:class:`jaxrefl.svbrdf.CaptureFit`; its ``light``, job, holdout)
    lp:      the map's log-posterior (its residual: model, space and noise model)
    data:    (N pixels) the map's data, under the fit's light
    capture: the capture as its files state the light
    theta:   (N, P) the fit's optimum in ``lp``'s space; pixels without a finite one get NaN
    """
    term = map_term(cf.light)
    if term == MAP_TERMS[2] or n_draws < 2:
        return None
    if term == MAP_TERMS[0]:
        est = replace(cf.light, cov=_held(cf.light.cov))
        draws = light_draws(est, n_draws, seed)
    else:
        est = _lens_estimate(cf, capture)
        if est is None:
            return None
        draws = light_draws(est, n_draws - n_draws // 2, seed)
    n = theta.shape[0]
    ok = np.all(np.isfinite(theta), -1)
    t = jnp.asarray(np.where(ok[:, None], theta, 0.0))
    train = np.ones(capture.n_photos, bool)
    train[list(cf.job.holdout)] = False
    jac, w, chol = _gauss_newton(lp.residual, t, data)
    total = np.zeros(theta.shape)
    square = np.zeros(theta.shape)
    for off, gain in draws:
        lit = est.apply(capture, off, gain)
        moved = pixel_block(lit, 0, n, photos=train, dtype=np.float64)
        move = np.asarray(_moves(lp.residual, t, data, moved, jac, w, chol))
        total += move
        square += move**2
    if term == MAP_TERMS[0]:
        mean = total / n_draws
        var_theta = np.maximum(square / n_draws - mean**2, 0.0) * n_draws / (n_draws - 1)
    else:
        var_theta = square / n_draws  # about the map's centre; the lens draws add 0
    slope = np.asarray(lp.space.dnatural(t))
    var = var_theta * slope**2
    var[~ok] = np.nan
    return var


def widen_for_light(umap, var: np.ndarray, lower, upper) -> tuple[Any, np.ndarray]:
    """(the map with std, q05, q95 widened by the light's variance ``var`` (N, P) over its
    first P parameters (module docstring), the quantiles kept inside the parameters' box
    [``lower``, ``upper``] (natural units); the light's std (N, P))."""
    p = var.shape[1]
    extra = np.where(np.isfinite(var), var, 0.0)
    std = np.array(umap.std, np.float64)
    q05, q95 = np.array(umap.q05, np.float64), np.array(umap.q95, np.float64)
    mean = np.asarray(umap.mean, np.float64)[:, :p]
    s0 = std[:, :p]
    s1 = np.sqrt(s0**2 + extra)
    with np.errstate(invalid="ignore", divide="ignore"):
        factor = np.where(s0 > 0, s1 / s0, 1.0)
    lo, hi = np.asarray(lower, np.float64)[:p], np.asarray(upper, np.float64)[:p]
    std[:, :p] = s1
    q05[:, :p] = np.maximum(mean - (mean - q05[:, :p]) * factor, lo)
    q95[:, :p] = np.minimum(mean + (q95[:, :p] - mean) * factor, hi)
    return replace(umap, std=std, q05=q05, q95=q95), np.sqrt(extra)

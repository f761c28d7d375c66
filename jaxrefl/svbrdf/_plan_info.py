"""The linearised model of a new photo behind :func:`jaxrefl.svbrdf.plan_next`: the fit's
Laplace precision on a pixel sample, the Fisher information of a photo (with Tobit censoring)
and the predictive variance of reference renderings (:mod:`._plan`'s docstring states the
criterion and its approximations).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import log_ndtr, ndtr

from jaxrefl import fit
from jaxrefl._errors import JaxreflError

from ._data import pixel_take
from ._job import CaptureFit
from ._models import TWO_STAGE, capture_model

__all__ = [
    "censoring_factor",
    "photo_information",
    "pixel_predictive_variance",
    "predictive_variance",
    "recorded_slope",
    "schur",
]

# Standardised distances to the censoring bounds are clipped here: beyond 30 sigma the
# normal's tail terms are 0 to float64 precision (and inf - inf would make NaN).
_Z_MAX = 30.0


# ------------------------------------------------------------------------ information
def censoring_factor(mean, std, saturation_level=np.inf, dark_level=-np.inf) -> np.ndarray:
    """lambda in (0, 1]: the Fisher information about the mean of a normal observation
    N(mean, std^2) recorded censored above ``saturation_level`` and below ``dark_level``
    (a Tobit observation), as a share of the uncensored 1 / std^2. With
    a = (dark - mean)/std, b = (sat - mean)/std and phi, Phi the standard normal's density
    and distribution,

        lambda = Phi(b) - Phi(a) - b phi(b) + a phi(a) + phi(b)^2 / (1 - Phi(b))
                 + phi(a)^2 / Phi(a)

    (the expected squared score: the integral of z^2 phi over the uncensored range, and each
    censored outcome's probability times its squared score)."""
    mean = np.asarray(mean, np.float64)
    std = np.asarray(std, np.float64)
    b = np.clip((saturation_level - mean) / std, -_Z_MAX, _Z_MAX)
    a = np.clip((dark_level - mean) / std, -_Z_MAX, _Z_MAX)
    log_phi_b = -0.5 * b * b - 0.5 * math.log(2 * math.pi)
    log_phi_a = -0.5 * a * a - 0.5 * math.log(2 * math.pi)
    inner = ndtr(b) - ndtr(a) - b * np.exp(log_phi_b) + a * np.exp(log_phi_a)
    tails = np.exp(2 * log_phi_b - log_ndtr(-b)) + np.exp(2 * log_phi_a - log_ndtr(a))
    # Round-off can leave a hair outside (0, 1]; the factor is a share of the information.
    return np.clip(inner + tails, 0.0, 1.0)


def recorded_slope(mean, std, saturation_level=np.inf, dark_level=-np.inf) -> np.ndarray:
    """d E[recorded value] / d mean in [0, 1] of a normal observation N(mean, std^2) recorded
    censored above ``saturation_level`` and below ``dark_level`` (a Tobit observation): with
    a, b as in :func:`censoring_factor`, Phi(b) - Phi(a), the probability that it is recorded
    uncensored. A reference rendering's predictive variance as the camera would record it
    is this squared times the radiance's (the delta method): a highlight far above the
    saturation level is recorded as saturated whatever the parameters."""
    mean = np.asarray(mean, np.float64)
    std = np.asarray(std, np.float64)
    b = np.clip((saturation_level - mean) / std, -_Z_MAX, _Z_MAX)
    a = np.clip((dark_level - mean) / std, -_Z_MAX, _Z_MAX)
    return ndtr(b) - ndtr(a)


def photo_information(
    jac, mean, var, saturation_level=np.inf, dark_level=-np.inf, *, censoring: bool = True
) -> np.ndarray:
    """(..., P, P) Fisher information of one photo's observations of a pixel about theta:
    sum_c lambda_c j_c j_c^T / var_c, from the Jacobian ``jac`` (..., C, P) of the predicted
    radiance ``mean`` (..., C) with noise variance ``var`` (..., C), lambda the censoring
    factor (:func:`censoring_factor`; 1 with ``censoring=False``)."""
    jac = np.asarray(jac, np.float64)
    var = np.asarray(var, np.float64)
    lam = (
        censoring_factor(mean, np.sqrt(var), saturation_level, dark_level)
        if censoring
        else np.ones_like(var)
    )
    return np.einsum("...cp,...cq,...c->...pq", jac, jac, lam / var)


def _logdet(a: np.ndarray) -> np.ndarray:
    sign, ld = np.linalg.slogdet(a)
    # A precision that lost positive definiteness to round-off has no volume.
    return np.where(sign > 0, ld, -np.inf)


@eqx.filter_jit
def _residual_jacobian(res, theta, data):
    """(n, rows, P) Jacobian of the fit's residual of every pixel at its theta."""
    return jax.vmap(jax.jacfwd(res))(theta, data)


@eqx.filter_jit
def _prediction_jacobian(model, space, inverse, theta, wi, wo, scale):
    """((n, C, P) Jacobian, (n, C) value) of each pixel's predicted radiance under one new
    photo (directions (n, 3), scale = E cos_i (n, C)); theta's entries in the order whose
    inverse permutation is ``inverse``."""

    def pred(t, wi1, wo1, s1):
        params = space.to_natural(t[inverse][None, :])
        return model.eval(params, wi1[None], wo1[None])[0] * s1

    return jax.vmap(jax.jacfwd(pred))(theta, wi, wo, scale), jax.vmap(pred)(theta, wi, wo, scale)


# ------------------------------------------------------------------------ the fit's state
@dataclass(frozen=True)
class _State:
    """What the plan needs of a fit, on the sampled pixels: the model with its shared
    parameters free, theta (n, P + S), the first P entries per pixel, the last S shared."""

    model: Any
    space: fit.ParamSpace
    noise: fit.NoiseModel
    theta: np.ndarray
    s2: np.ndarray  # (n,) Laplace noise scale
    pixels: np.ndarray  # (n,) row-major indices
    n_est: int  # pixels with an estimate
    n_shared: int
    shared: tuple[str, ...]
    precision: np.ndarray  # (n, P + S, P + S) per pixel, without the weak prior


def _fit_noise(capture_fit: CaptureFit, noise_std: np.ndarray):
    """(noise model of the fit's residual, whether the Laplace step estimated its scale)."""
    job, noise = capture_fit.job, capture_fit.job.config.noise
    pooled = capture_fit.pooled
    unknown = noise.scale_unknown
    if unknown and pooled is not None and pooled.alpha is not None:
        assert pooled.sigma is not None  # choose_pooled sets it with alpha
        # An array, not a float: equinox's jit would compile again for every value.
        return noise.with_scale(jnp.asarray(float(pooled.sigma))), False
    if unknown and job.model in TWO_STAGE:
        # The tilted fit's scale: one value for the capture (empirical Bayes), in the map.
        good = noise_std[np.isfinite(noise_std) & (noise_std > 0)]
        sigma = float(np.median(good)) if good.size else 1.0
        return noise.with_scale(jnp.asarray(sigma)), False
    return noise, True


def _prior(capture_fit: CaptureFit, space: fit.ParamSpace) -> fit.GaussianPrior | None:
    job, pooled = capture_fit.job, capture_fit.pooled
    if pooled is not None and pooled.alpha is not None:
        chans = [lab.split(".", 1)[1] for lab in space.labels if lab.startswith("specular.")]
        return fit.gaussian_prior(
            space,
            {
                f"specular.{ch}": (mu, sd)
                for ch, mu, sd in zip(chans, pooled.prior_mean, pooled.prior_std, strict=True)
            },
        )
    if job.model in TWO_STAGE:
        t = float(job.tilt_std)
        return fit.gaussian_prior(space, {"tilt_x": (0.0, t), "tilt_y": (0.0, t)})
    return None


def _state(capture_fit: CaptureFit, capture, max_pixels: int, seed: int) -> _State:
    model, space = capture_fit.model()
    h, w = capture_fit.maps["status"].shape
    k, hc, wc, c = capture.shape
    if (hc, wc) != (h, w):
        raise JaxreflError(
            f"the capture's photos are {hc} x {wc} pixels, the fit's maps {h} x {w}: give the "
            "capture the fit was made from (same resolution and downsampling)"
        )
    theta_all = np.asarray(capture_fit.theta, np.float64)
    ok = np.all(np.isfinite(theta_all), axis=-1)
    if not np.any(ok):
        raise JaxreflError("the fit has no pixel with an estimate: nothing to plan from")
    est = np.flatnonzero(ok)
    rng = np.random.default_rng(seed)
    take = np.sort(rng.choice(est, min(max_pixels, est.size), replace=False))
    dtype = capture_fit.job.dtype
    nat = space.to_natural(jnp.asarray(theta_all[take], dtype))
    shared: tuple[str, ...] = ()
    pooled = capture_fit.pooled
    if pooled is not None and pooled.alpha is not None:
        if capture_fit.alpha_min is None:
            raise JaxreflError(
                "the pooled fit's report.json records no lower bound of its width "
                "(alpha_min): run `jaxrefl fit` again to write one, or plan from the fit "
                "fit_capture returns"
            )
        # The shared width becomes a free parameter of the same model (counted once).
        model, space = capture_model(
            "ggx_rgb", c, alpha_min=min(float(capture_fit.alpha_min), pooled.alpha)
        )
        shared = ("alpha",)
    theta = np.asarray(space.from_natural(nat, dtype=dtype), np.float64)
    noise_std = np.asarray(capture_fit.maps["noise_std"], np.float64).reshape(-1)
    noise, estimated = _fit_noise(capture_fit, noise_std)
    if estimated:
        s = noise_std[take]
        med = np.median(noise_std[np.isfinite(noise_std) & (noise_std > 0)])
        # A pixel without a noise estimate (n <= P) takes the capture's median scale.
        s = np.where(np.isfinite(s) & (s > 0), s, med if np.isfinite(med) else 1.0)
        s2 = s * s
    else:
        s2 = np.ones(take.size)
    res = fit.make_residual(
        model, space, noise, capture_fit.job.config.loss, _prior(capture_fit, space)
    )
    data = pixel_take(capture, take, dtype=dtype)
    train = np.ones(k)
    train[list(capture_fit.job.holdout)] = 0.0
    data = eqx.tree_at(
        lambda d: d.weight, data, data.weight * jnp.asarray(train, data.weight.dtype)[None, :, None]
    )
    jac = _residual_jacobian(res, jnp.asarray(theta, dtype), data)
    jac = np.asarray(jac, np.float64)
    jac = np.where(np.isfinite(jac), jac, 0.0)  # a non-finite row carries no information
    precision = np.einsum("nrp,nrq->npq", jac, jac) / s2[:, None, None]
    return _State(
        model=model,
        space=space,
        noise=noise,
        theta=_shared_last(space, theta, shared),
        s2=s2,
        pixels=take,
        n_est=int(est.size),
        n_shared=sum(space.index(nm).stop - space.index(nm).start for nm in shared),
        shared=shared,
        precision=_shared_last(space, precision, shared, matrix=True),
    )


def _order(space: fit.ParamSpace, shared: tuple[str, ...]) -> np.ndarray:
    """theta entries with the shared parameters' last."""
    last = [j for n in shared for j in range(space.index(n).start, space.index(n).stop)]
    return np.array([j for j in range(space.size) if j not in last] + last, int)


def _shared_last(space, x, shared, matrix=False):
    o = _order(space, shared)
    return x[:, o][:, :, o] if matrix else x[:, o]


def _candidate_geometry(points: np.ndarray, cam: np.ndarray, light: np.ndarray, power):
    """wi, wo (n, 3) and scale = E cos_i (n, C) of one candidate at ``points`` (n, 3)."""
    d = light - points
    r2 = np.sum(d * d, axis=-1)
    wi = d / np.sqrt(r2)[:, None]
    v = cam - points
    wo = v / np.linalg.norm(v, axis=-1, keepdims=True)
    # Light from below the plane does not reach the surface (as Capture does).
    cos_i = np.maximum(wi[:, 2], 0.0)
    return wi, wo, (power[None, :] / r2[:, None]) * cos_i[:, None]


def schur(a_pp, a_ps, a_ss, prior_precision: float, scale_up: float) -> np.ndarray:
    """(S, S) the shared parameters' precision given none of the pixels' (the Schur
    complement of the block-arrow joint precision): prior + scale_up sum_i (c_i - b_i^T
    A_i^-1 b_i), with A_i = ``a_pp`` (n, P, P), b_i = ``a_ps`` (n, P, S), c_i = ``a_ss``."""
    s = a_ss.shape[-1]
    inner = a_ss - np.swapaxes(a_ps, 1, 2) @ np.linalg.solve(a_pp, a_ps)
    return np.eye(s) * prior_precision + scale_up * np.sum(inner, axis=0)


def pixel_predictive_variance(
    a_pp, a_ps, a_ss, moment, prior_precision: float, scale_up: float
) -> np.ndarray:
    """(n,) each pixel's predictive variance of the reference renderings, summed over them
    and the channels: g^T Sigma g, Sigma the inverse of the block-arrow joint precision
    (pixels' blocks ``a_pp`` (n, P, P), their coupling ``a_ps`` (n, P, S) to the S shared
    parameters and ``a_ss`` (n, S, S)); ``moment`` (n, P + S, P + S) is sum_r sum_c g g^T
    over the reference renderings' Jacobians g (shared entries last). With y_i = A_i^-1 b_i:

        v_i = tr(A_i^-1 M_pp,i) + tr(S^-1 (M_ss,i - 2 sym(M_sp,i y_i) + y_i^T M_pp,i y_i))

    (the pixel's variance given the shared parameters, plus theirs carried through the
    Schur complement S, :func:`schur`, whose sum over pixels is scaled by ``scale_up``)."""
    p = a_pp.shape[-1]
    m_pp = moment[:, :p, :p]
    v = np.trace(np.linalg.solve(a_pp, m_pp), axis1=1, axis2=2)
    if moment.shape[-1] == p:
        return v
    y = np.linalg.solve(a_pp, a_ps)
    cross = np.swapaxes(moment[:, :p, p:], 1, 2) @ y
    k = moment[:, p:, p:] - cross - np.swapaxes(cross, 1, 2) + np.swapaxes(y, 1, 2) @ m_pp @ y
    sch = schur(a_pp, a_ps, a_ss, prior_precision, scale_up)
    return v + np.trace(np.linalg.solve(sch[None], k), axis1=1, axis2=2)


def predictive_variance(a_pp, a_ps, a_ss, moment, prior_precision: float, scale_up: float):
    """sum over pixels of :func:`pixel_predictive_variance` (the same arguments), scaled by
    ``scale_up``: the predictive variance of the reference renderings of every pixel with
    an estimate."""
    return scale_up * float(
        np.sum(pixel_predictive_variance(a_pp, a_ps, a_ss, moment, prior_precision, scale_up))
    )

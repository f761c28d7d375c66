"""Exact Gibbs sampling of posteriors that are linear-Gaussian in every BRDF parameter.

Some capture models are linear in all their free parameters: ``pooled`` with its shared
lobe width fixed, under a co-located flash, predicts

    pred_kc(x) = b_kc + sum_j A_kcj x_j        (x = albedo, F0 per channel, natural units)

(Lambert's albedo / pi and the lobe's F0 D G / (4 cos_i cos_o) times the irradiance; the
Schlick term (1 - cos theta_d)^5 vanishes at theta_d = 0). With the L2 loss, Gaussian noise
sd_kc = s u_kc (u_kc = ``noise.std(obs)``, s the unknown scale with the Jeffreys prior
p(s) ~ 1/s, or s = 1 for a known noise model), uniform priors on the parameters' boxes, the
posterior given the uncensored observations is

    p(x, s | y) ~ s^-(n + 1) exp(-|W^1/2 (y - b - A x) / u|^2 / (2 s^2)) 1[lo <= x <= hi]

(n = sum of the weights). Both full conditionals are standard distributions:

* s^2 | x ~ Inverse-Gamma(n / 2, SSE(x) / 2), with SSE(x) = y'^T W y' - 2 x^T r + x^T Q x,
  Q = A'^T W A', r = A'^T W y' in the whitened y' = (y - b) / u, A' = A / u;
* along any fixed direction d, x + t d | rest, s is a 1-D Gaussian in t (mean
  -d.(Q x - r) / d^T Q d, variance s^2 / d^T Q d) truncated to the segment of the line
  inside the box (Geman & Geman 1984; Gelfand & Smith 1990).

Censored observations (clipped highlights, dark pixels: the Tobit likelihood
Phi(+-z) of :mod:`jaxrefl.posterior._logpost`) are handled by data augmentation (Tanner &
Wong 1987; Chib 1992): each scan first draws the latent value of each one, N(pred, s^2 u^2)
truncated to beyond its bound, and the rest of the scan treats those values as
observations. A scan then draws s^2, then moves x along each eigenvector of Q in turn.
Where no bound is active the eigenvectors decouple the Gaussian, so one scan is an
independent draw. A lobe no photo saw trades against the albedo along a ridge, and that
ridge is one of the eigenvectors, not a diagonal that coordinate-wise Gibbs would cross in
tiny steps. The sampler is exact, with no step size, no gradient and no model evaluation
once Q and r are formed. Kept draws are ``sweeps`` scans apart, and the usual diagnostics
(split R-hat, bulk ESS) judge the result as they judge HMC's. The scan, the truncated
normals and the linearity check are shared with the width sampler (:mod:`._conjugate`).

:func:`linear_terms` forms A and b from the model (one forward-mode Jacobian at the box
centre) and checks linearity at a second point; :func:`qualifies` says whether a posterior
and a batch of pixels meet every condition above; :func:`gibbs_kernel` is one chain's
``init``/``step`` (:mod:`._driver`), and :func:`sample_gibbs` returns
:class:`~jaxrefl.posterior.Samples` like :func:`~jaxrefl.posterior.sample_pixels`, which
calls it for such pixels given :class:`~jaxrefl.posterior.GibbsOptions`.
"""

from __future__ import annotations

import functools
import time
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import PixelData, ScaledSigmoid

from ._conjugate import (
    censored_slots,
    censoring_failure,
    is_linear,
    likelihood_failure,
    natural_starts,
    observations,
    package_draws,
    sweep,
    theta_of,
    truncated_normal,
)
from ._driver import Kernel, chain_starts, run_chain
from ._logpost import LogPosterior
from ._priors import Uniform

__all__ = ["gibbs_kernel", "latent_terms", "linear_terms", "qualifies", "sample_gibbs"]


def _box(lp: LogPosterior) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) (P,) when every run is a finite ScaledSigmoid box with a matching uniform
    prior; else None."""
    lo, hi = [], []
    for blk, prior in zip(lp.space.blocks, lp.priors, strict=True):
        for r in blk.runs:
            if not isinstance(r.bijection, ScaledSigmoid):
                return None
            if not (np.isfinite(r.lower) and np.isfinite(r.upper)):
                return None
            if not isinstance(prior, Uniform):
                return None
            if not (float(prior.lower) <= r.lower and float(prior.upper) >= r.upper):
                return None  # a narrower prior: its edges would be walls inside the box
            lo += [r.lower] * (r.stop - r.start)
            hi += [r.upper] * (r.stop - r.start)
    return np.asarray(lo, np.float64), np.asarray(hi, np.float64)


def linear_terms(lp: LogPosterior, data: PixelData):
    """(A (N, M, P), b (N, M), linear (N,) bool) with pred(x) = b + A x over the N pixels'
    M = K * C observations, from the Jacobian at the box centre; ``linear`` where the
    prediction at a second interior point agrees (:func:`._conjugate.is_linear`)."""
    box = _box(lp)
    if box is None:
        raise JaxreflError("linear_terms needs every parameter in a finite box (ScaledSigmoid)")
    lo, hi = (jnp.asarray(v, data.obs.dtype) for v in box)
    return _linear_terms(lp, data, lo, hi)


@eqx.filter_jit
def _linear_terms(lp, data, lo, hi):
    def pred(x, d):
        return lp.residual.predict(theta_of(lp, x), d).reshape(-1)

    x_c = 0.5 * (lo + hi)
    x_2 = lo + 0.3 * (hi - lo)

    def one(d):
        a = jax.jacfwd(pred)(x_c, d)  # (M, P)
        b = pred(x_c, d) - a @ x_c
        return a, b, is_linear(pred(x_2, d), b + a @ x_2)

    return jax.vmap(one)(data)


def qualifies(lp: LogPosterior, data: PixelData) -> tuple[bool, str]:
    """(True, "") when :func:`sample_gibbs` draws this posterior exactly for every pixel of
    ``data`` (module docstring), else (False, the first condition that fails)."""
    if why := likelihood_failure(lp):
        return False, why
    if _box(lp) is None:
        return False, "a parameter is not a finite box with a uniform prior"
    if why := censoring_failure(data):
        return False, why
    _a, _b, ok = linear_terms(lp, data)
    if not bool(np.all(np.asarray(ok))):
        return False, "the model is not linear in its parameters on these pixels"
    return True, ""


class _Terms(NamedTuple):
    """The whitened linear-Gaussian terms of the pixels (module docstring), a leading (N,)
    axis on each: Q = A'^T W A' (P, P), r = A'^T W y' (P,), y'^T W y' (), n = sum of the
    weights (), Q's eigenvectors (P, P, as columns) and eigenvalues (P,); for the latent
    draws, r and y'^T W y' of the observed (uncensored) rows alone, and the R gathered
    censored rows (:func:`._conjugate.censored_slots`): A' (R, P), y' (R,), W (R,; 0 on the
    padding) and their signs (R,) (+1 saturated, -1 dark, 0 padding)."""

    q: Array
    r: Array
    yy: Array
    nw: Array
    evec: Array
    evals: Array
    r_obs: Array
    yy_obs: Array
    aw_c: Array
    yw_c: Array
    w_c: Array
    sign_c: Array


def sample_gibbs(
    lp: LogPosterior,
    data: PixelData,
    theta0: Float[Array, "N D"],
    *,
    num_chains: int,
    num_warmup: int,
    num_samples: int,
    sweeps: int,
    seed: int = 0,
):
    """Exact Gibbs draws (module docstring) of N pixels: ``num_chains`` chains each, the
    first ``num_warmup`` kept-draw intervals discarded, then ``num_samples`` draws
    ``sweeps`` sweeps apart. theta0: (N, D) starts (the LM optimum) or (N, chains, D) one a
    chain; a start on a box edge is moved just inside it, a noise scale that is not a
    positive number starts at 1. Returns :class:`~jaxrefl.posterior.Samples` with
    ``method="gibbs"`` (acceptance 1, no divergences, ``lp`` the log density of each draw).
    The caller checks :func:`qualifies` first."""

    box = _box(lp)
    assert box is not None  # qualifies() checked it
    dtype = data.obs.dtype
    lo, hi = (jnp.asarray(v, dtype) for v in box)
    a, b, _ok = linear_terms(lp, data)
    n = a.shape[0]
    w, obs, u = observations(lp, data)
    yw = (obs.reshape(n, -1) - b) / u
    aw = a / u[..., None]
    q = jnp.einsum("nmp,nm,nmq->npq", aw, w, aw)
    r = jnp.einsum("nmp,nm,nm->np", aw, w, yw)
    yy = jnp.einsum("nm,nm,nm->n", yw, w, yw)
    nw = jnp.sum(w, axis=-1)
    evals, evec = jnp.linalg.eigh(q)
    jeffreys = lp.noise_scale is not None
    cens = jnp.where(lp.residual.usable(data), data.censored, 0).reshape(n, -1)
    cens_np = np.asarray(cens).astype(np.int8)
    censored = bool(np.any(cens_np != 0))

    t0, finite = chain_starts(theta0, n, num_chains, dtype)
    x0, s0 = natural_starts(lp, t0, lo, hi, jeffreys)

    keys = jax.random.split(jax.random.PRNGKey(seed), n)
    t_start = time.perf_counter()
    terms = _Terms(q, r, yy, nw, evec, evals, *latent_terms(aw, yw, w, cens_np))
    xs, s2s = _chains(
        keys,
        x0,
        s0,
        terms,
        lo,
        hi,
        num_warmup=num_warmup,
        num_samples=num_samples,
        sweeps=sweeps,
        jeffreys=jeffreys,
        censored=censored,
    )
    xs, s2s = jax.block_until_ready((xs, s2s))
    run_s = time.perf_counter() - t_start
    return package_draws(
        lp,
        xs,
        s2s,
        finite,
        data,
        acceptance=1.0,
        method="gibbs",
        sweeps=sweeps,
        run_s=run_s,
        jeffreys=jeffreys,
    )


def latent_terms(aw, yw, w, cens: np.ndarray):
    """The latent draws' fixed terms (:class:`_Terms`) of whitened A' (N, M, P), y' (N, M),
    weights W (N, M) and censoring flags (N, M): r and y'^T W y' of the observed rows, and
    the censored rows gathered (A', y', W, signs; (N, R, ...))."""
    w_obs = jnp.where(cens != 0, 0.0, w)
    r_obs = jnp.einsum("nmp,nm,nm->np", aw, w_obs, yw)
    yy_obs = jnp.einsum("nm,nm,nm->n", yw, w_obs, yw)
    c_idx, sign_c = (jnp.asarray(v) for v in censored_slots(cens))
    aw_c = jnp.take_along_axis(aw, c_idx[..., None], axis=1)
    yw_c = jnp.take_along_axis(yw, c_idx, axis=1)
    w_c = jnp.where(sign_c != 0, jnp.take_along_axis(w, c_idx, axis=1), 0.0)
    return r_obs, yy_obs, aw_c, yw_c, w_c, sign_c


def gibbs_kernel(terms: _Terms, lo, hi, *, jeffreys: bool, censored: bool) -> Kernel:
    """One chain's exact Gibbs scan (module docstring) over the state (key, x, s^2): with
    ``censored``, the latent value of every censored observation given x and s first (and
    r and y'^T W y' from them), then s^2 and x (:func:`._conjugate.sweep`)."""
    t = terms

    def latent(key, x, s2):
        # whitened units: y* ~ N(A' x, s^2) truncated to [bound, inf) where saturated and
        # (-inf, bound] where dark, on the gathered censored rows (the padding's draws
        # have weight 0); the observed rows' terms are fixed
        mean = t.aw_c @ x
        sd = jnp.sqrt(s2)
        z0 = (t.yw_c - mean) / sd
        lo_z = jnp.where(t.sign_c > 0, z0, -jnp.inf)
        hi_z = jnp.where(t.sign_c < 0, z0, jnp.inf)
        y = mean + sd * truncated_normal(key, lo_z, hi_z, x.dtype)
        wy = t.w_c * y
        return t.r_obs + wy @ t.aw_c, t.yy_obs + jnp.sum(wy * y)

    def step(state):
        key, x, s2 = state
        key, sub, k_y = jax.random.split(key, 3)
        r, yy = latent(k_y, x, s2) if censored else (t.r, t.yy)
        x, s2 = sweep(sub, x, s2, t.q, r, yy, t.nw, t.evec, t.evals, lo, hi, jeffreys)
        return (key, x, s2), ()

    def init(key, x, s2):
        return key, x, s2

    return Kernel(init=init, step=step, draw=lambda state: state[1:])


@functools.partial(
    jax.jit, static_argnames=("num_warmup", "num_samples", "sweeps", "jeffreys", "censored")
)
def _chains(
    keys, x0, s0, terms: _Terms, lo, hi, *, num_warmup, num_samples, sweeps, jeffreys, censored
):
    """(x draws (N, chains, num_samples, P), s^2 draws (N, chains, num_samples))."""

    def pixel(key, x, s, t):
        kernel = gibbs_kernel(t, lo, hi, jeffreys=jeffreys, censored=censored)

        def chain(k, x0, s2):
            draws, _info, _ = run_chain(
                kernel,
                (k, x0, s2),
                warmup=num_warmup,
                warmup_steps=sweeps,
                num_samples=num_samples,
                per_draw=sweeps,
            )
            return draws

        ks = jax.random.split(key, x.shape[0])
        return jax.vmap(chain)(ks, x, s * s)

    return jax.vmap(pixel)(keys, x0, s0, terms)

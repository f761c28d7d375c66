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
(split R-hat, bulk ESS) judge the result as they judge HMC's. Truncated normals:
:func:`truncated_normal`, the inverse CDF of the tail the segment lies in (a segment far in
a tail keeps its spread: a posterior piled against a bound is drawn as the steep exponential
it is, not as the bound itself).

:func:`linear_terms` forms A and b from the model (one forward-mode Jacobian at the box
centre) and checks linearity at a second point; :func:`qualifies` says whether a posterior
and a batch of pixels meet every condition above; :func:`sample_gibbs` returns
:class:`~jaxrefl.posterior.Samples` like :func:`~jaxrefl.posterior.sample_pixels`, which
calls it for such pixels when ``HMCOptions.gibbs_sweeps`` is above 0.
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
from jaxrefl.fit import L2, PixelData, ScaledSigmoid

from ._logpost import LogPosterior
from ._priors import Jeffreys, Uniform
from ._samples import Samples

__all__ = ["linear_terms", "qualifies", "sample_gibbs"]

# Relative error of the linear prediction at a second point above which a pixel is not
# linear (float64 predictions of a linear model agree to ~1e-15).
_LINEAR_RTOL = 1e-9
# Draws are kept this fraction of the box width inside its edges: a draw exactly on an
# edge would map to an infinite theta through the sigmoid.
_EDGE = 1e-12
# truncated_normal: beyond this many standard deviations (float64, float32) Phi(-a)
# approaches the smallest normal float, and the tail is drawn as its exponential limit
# a + Exp(a) (relative error of the density about 1 / a^2 over the tail's scale 1 / a).
_TAIL = {8: 30.0, 4: 10.0}


def truncated_normal(key, a, b, dtype=jnp.float64):
    """Standard normal draws truncated to [a, b] (arrays broadcast together), exact far in
    either tail.

    ``jax.random.truncated_normal`` inverts Phi through erf, and erf(a / sqrt 2) rounds to 1
    beyond a of about 6 (float64): every draw of such a segment is its near end. Here a
    segment above 0 is inverted in its upper tail, x = -Phi^-1(Phi(-a) + u (Phi(-b) -
    Phi(-a))), where Phi(-a) stays representable to a of about 37; a segment below 0 is
    mirrored into it; a segment around 0 uses Phi itself (no cancellation there). Beyond
    :data:`_TAIL` the tail is the exponential x = a + E / a truncated to b (Robert 1995 sec.
    2 for the limit).
    """
    a = jnp.asarray(a, dtype)
    b = jnp.asarray(b, dtype)
    shape = jnp.broadcast_shapes(a.shape, b.shape)
    a, b = jnp.broadcast_to(a, shape), jnp.broadcast_to(b, shape)
    # u in (0, 1): u = 0 would put p on Phi(-b), which is 0 for an open segment.
    u = jax.random.uniform(key, shape, dtype, minval=jnp.finfo(dtype).tiny, maxval=1.0)
    flip = b < 0  # a segment below 0, mirrored into the upper tail
    lo, hi = jnp.where(flip, -b, a), jnp.where(flip, -a, b)
    # A segment above 0 is inverted through Phi(-x) (sign -1), one around 0 through Phi(x):
    # x = sign Phi^-1(c_lo + u (c_hi - c_lo)) with c = Phi(sign * end).
    upper = lo >= 0
    sign = jnp.where(upper, -1.0, 1.0).astype(dtype)
    c_lo, c_hi = jax.scipy.special.ndtr(sign * lo), jax.scipy.special.ndtr(sign * hi)
    x_inv = sign * jax.scipy.special.ndtri(c_lo + u * (c_hi - c_lo))
    # Far out, the tail's exponential limit: density a exp(-a t) on t in [0, hi - lo].
    far = upper & (lo > _TAIL.get(jnp.dtype(dtype).itemsize, _TAIL[4]))
    rate = jnp.where(far, lo, 1.0)  # the where keeps the other pixels' division finite
    span = jnp.where(far, hi - lo, 1.0)
    x_exp = lo - jnp.log1p(u * jnp.expm1(-rate * span)) / rate
    x = jnp.clip(jnp.where(far, x_exp, x_inv), lo, hi)  # rounding at the ends
    return jnp.where(flip, -x, x)


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


def _theta_of(lp: LogPosterior, x: Float[Array, "*b P"]) -> Float[Array, "*b P"]:
    """Unconstrained theta of natural x (elementwise bijections, in run order)."""
    parts = [
        r.bijection.inverse(x[..., r.start : r.stop]) for blk in lp.space.blocks for r in blk.runs
    ]
    return jnp.concatenate(parts, axis=-1)


def linear_terms(lp: LogPosterior, data: PixelData):
    """(A (N, M, P), b (N, M), linear (N,) bool) with pred(x) = b + A x over the N pixels'
    M = K * C observations, from the Jacobian at the box centre; ``linear`` where the
    prediction at a second interior point agrees to :data:`_LINEAR_RTOL`."""
    box = _box(lp)
    if box is None:
        raise JaxreflError("linear_terms needs every parameter in a finite box (ScaledSigmoid)")
    lo, hi = (jnp.asarray(v, data.obs.dtype) for v in box)
    return _linear_terms(lp, data, lo, hi)


@eqx.filter_jit
def _linear_terms(lp, data, lo, hi):
    def pred(x, d):
        return lp.residual.predict(_theta_of(lp, x), d).reshape(-1)

    x_c = 0.5 * (lo + hi)
    x_2 = lo + 0.3 * (hi - lo)

    def one(d):
        a = jax.jacfwd(pred)(x_c, d)  # (M, P)
        b = pred(x_c, d) - a @ x_c
        p2 = pred(x_2, d)
        err = jnp.max(jnp.abs(p2 - (b + a @ x_2)))
        ok = err <= _LINEAR_RTOL * (jnp.max(jnp.abs(p2)) + 1e-300)
        return a, b, ok

    return jax.vmap(one)(data)


def qualifies(lp: LogPosterior, data: PixelData) -> tuple[bool, str]:
    """(True, "") when :func:`sample_gibbs` draws this posterior exactly for every pixel of
    ``data`` (module docstring), else (False, the first condition that fails)."""
    if lp.light is not None:
        return False, "the light direction is sampled"
    if not isinstance(lp.residual.loss, L2):
        return False, f"the loss is {type(lp.residual.loss).__name__}, not L2"
    if lp.noise_scale is not None and not isinstance(lp.noise_scale, Jeffreys):
        return False, "the noise scale's prior is not Jeffreys'"
    if _box(lp) is None:
        return False, "a parameter is not a finite box with a uniform prior"
    cens = np.asarray(data.censored) != 0
    w = np.asarray(data.weight)
    if np.any(cens & (w != 0) & (w != 1)):
        return False, "a censored observation has a weight other than 0 or 1"
    _a, _b, ok = linear_terms(lp, data)
    if not bool(np.all(np.asarray(ok))):
        return False, "the model is not linear in its parameters on these pixels"
    return True, ""


class _Terms(NamedTuple):
    """The whitened linear-Gaussian terms of the pixels (module docstring), a leading (N,)
    axis on each: Q = A'^T W A' (P, P), r = A'^T W y' (P,), y'^T W y' (), n = sum of the
    weights (), Q's eigenvectors (P, P, as columns) and eigenvalues (P,), A' (M, P), y' (M,),
    the weights W (M,) and the censoring flags (M,) (+1 saturated, -1 dark, 0 observed)."""

    q: Array
    r: Array
    yy: Array
    nw: Array
    evec: Array
    evals: Array
    aw: Array
    yw: Array
    w: Array
    cens: Array


def _sweep(key, x, s2, q, r, yy, nw, evec, evals, lo, hi, jeffreys, pp=None, pm=None, k=0):
    """One scan: s^2 | x (when sampled), then x along each direction in turn (columns of
    ``evec``, with evals[k] = d_k^T Q d_k). One chain. pp, pm, k: where given, a Gaussian
    prior N(pm, s^2 pp^-1) on x (pp in units of s^-2, truncated to the box; s^-k its
    normalising factor, k its rank where it is in units of the noise), else x's prior is
    uniform on the box. It adds d^T pp d to a direction's precision, and (x - pm)^T pp
    (x - pm) and k to s^2's Inverse-Gamma conditional."""
    k_s, k_x = jax.random.split(key)
    dtype = x.dtype
    if jeffreys:
        # SSE >= 0 in exact arithmetic; the expanded form can round below 0 at an exact fit.
        sse = jnp.maximum(yy - 2.0 * x @ r + x @ (q @ x), jnp.finfo(dtype).tiny)
        if pp is not None:
            sse = sse + (x - pm) @ pp @ (x - pm)
        g = jax.random.gamma(k_s, 0.5 * (nw + k), dtype=dtype)
        s2 = 0.5 * sse / g
    keys = jax.random.split(k_x, x.shape[0])
    lam_max = jnp.max(evals)
    width = hi - lo

    def direction(k, x):
        d = evec[:, k]
        lam = evals[k]
        # The line x + t d stays in the box for t in [t_lo, t_hi] (x is inside it).
        moves = jnp.abs(d) > 1e-12
        d_s = jnp.where(moves, d, 1.0)
        t1, t2 = (lo - x) / d_s, (hi - x) / d_s
        t_lo = jnp.max(jnp.where(moves, jnp.minimum(t1, t2), -jnp.inf))
        t_hi = jnp.min(jnp.where(moves, jnp.maximum(t1, t2), jnp.inf))
        # A direction neither the data nor a Gaussian prior sees (precision ~ 0): its
        # conditional is the uniform prior's on the segment. The floor keeps the division
        # finite either way.
        grad = d @ (q @ x - r)
        if pp is not None:  # the prior's precision and pull along d, in units of s^-2
            lam = lam + d @ pp @ d
            grad = grad + d @ (pp @ (x - pm))
        seen = lam > 1e-14 * lam_max
        lam_s = jnp.where(seen, lam, 1.0)
        mean = -grad / lam_s
        sd = jnp.sqrt(s2 / lam_s)
        z = truncated_normal(keys[k], (t_lo - mean) / sd, (t_hi - mean) / sd, dtype)
        u = jax.random.uniform(keys[k], dtype=dtype)
        t = jnp.where(seen, mean + sd * z, t_lo + u * (t_hi - t_lo))
        edge = _EDGE * width
        return jnp.clip(x + t * d, lo + edge, hi - edge)

    x = jax.lax.fori_loop(0, x.shape[0], direction, x)
    return x, s2


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
    n, p = a.shape[0], a.shape[-1]
    use = lp.residual.usable(data)
    w = jnp.where(use, data.weight.astype(dtype), 0.0).reshape(n, -1)
    obs = jnp.where(use, data.obs.astype(dtype), 0.0)
    u = lp.residual.noise.std(obs).reshape(n, -1)
    yw = (obs.reshape(n, -1) - b) / u
    aw = a / u[..., None]
    q = jnp.einsum("nmp,nm,nmq->npq", aw, w, aw)
    r = jnp.einsum("nmp,nm,nm->np", aw, w, yw)
    yy = jnp.einsum("nm,nm,nm->n", yw, w, yw)
    nw = jnp.sum(w, axis=-1)
    evals, evec = jnp.linalg.eigh(q)
    jeffreys = lp.noise_scale is not None
    cens = jnp.where(use, data.censored, 0).reshape(n, -1).astype(jnp.int8)
    censored = bool(np.any(np.asarray(cens) != 0))

    t0 = jnp.asarray(theta0, dtype)
    if t0.ndim == 2:  # one start for every chain of a pixel
        t0 = jnp.broadcast_to(t0[:, None, :], (n, num_chains, t0.shape[-1]))
    finite = jnp.all(jnp.isfinite(t0), axis=(-2, -1))
    t0 = jnp.where(finite[:, None, None], t0, 0.0)
    x0 = lp.space.natural_vector(t0[..., :p])
    edge = _EDGE * (hi - lo)
    x0 = jnp.clip(x0, (lo + edge)[None, None, :], (hi - edge)[None, None, :])
    s0 = jnp.exp(t0[..., -1]) if jeffreys else jnp.ones((n, num_chains), dtype)
    s0 = jnp.where(jnp.isfinite(s0) & (s0 > 0), s0, 1.0)

    keys = jax.random.split(jax.random.PRNGKey(seed), n)
    t_start = time.perf_counter()
    terms = _Terms(q, r, yy, nw, evec, evals, aw, yw, w, cens)
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
    theta = _theta_of(lp, xs)
    if jeffreys:
        theta = jnp.concatenate([theta, 0.5 * jnp.log(s2s)[..., None]], axis=-1)

    lpd = _density(lp, theta, data)
    pos = np.array(theta, np.float64)
    bad = ~np.asarray(finite)
    pos[bad] = np.nan
    nat = np.asarray(lp.natural(jnp.asarray(pos)), np.float64)
    shape = pos.shape[:3]
    return Samples(
        theta=pos,
        natural=nat,
        labels=lp.labels,
        stats={
            "acceptance_rate": np.ones(shape),
            "diverging": np.zeros(shape, bool),
            "lp": np.asarray(lpd, np.float64),
        },
        method="gibbs",
        # no step size: NaN, so that chunks of Gibbs and HMC draws concatenate
        tuning={"step_size": np.full(shape[:2], np.nan)},
        run_s=run_s,
        extra={"no_estimate": bad, "sweeps": sweeps, "reparam": "none"},
    )


@eqx.filter_jit
def _density(lp, theta, data):
    """log p of every draw: theta (N, chains, draws, D)."""

    def per_pixel(t, d):
        return jax.vmap(jax.vmap(lambda ti: lp(ti, d)))(t)

    return jax.vmap(per_pixel)(theta, data)


@functools.partial(
    jax.jit, static_argnames=("num_warmup", "num_samples", "sweeps", "jeffreys", "censored")
)
def _chains(
    keys,
    x0,
    s0,
    terms: _Terms,
    lo,
    hi,
    *,
    num_warmup,
    num_samples,
    sweeps,
    jeffreys,
    censored,
):
    """(x draws (N, chains, num_samples, P), s^2 draws (N, chains, num_samples)).

    With ``censored``, each scan first draws the latent value of every censored
    observation given x and s (module docstring) and forms r and y'^T W y' from them."""

    def latent(key, x, s2, t):
        # whitened units: y* ~ N(A' x, s^2) truncated to [bound, inf) where saturated and
        # (-inf, bound] where dark; the other observations keep their values
        mean = t.aw @ x
        sd = jnp.sqrt(s2)
        z0 = (t.yw - mean) / sd
        lo_z = jnp.where(t.cens > 0, z0, -jnp.inf)
        hi_z = jnp.where(t.cens < 0, z0, jnp.inf)
        z = truncated_normal(key, lo_z, hi_z, x.dtype)
        y = jnp.where(t.cens != 0, mean + sd * z, t.yw)
        return jnp.einsum("mp,m,m->p", t.aw, t.w, y), jnp.sum(t.w * y * y)

    def chain(key, x, s2, t):
        def interval(carry, _):
            def one(c, _):
                key, x, s2 = c
                key, sub, k_y = jax.random.split(key, 3)
                r, yy = latent(k_y, x, s2, t) if censored else (t.r, t.yy)
                x, s2 = _sweep(sub, x, s2, t.q, r, yy, t.nw, t.evec, t.evals, lo, hi, jeffreys)
                return (key, x, s2), None

            carry, _ = jax.lax.scan(one, carry, None, length=sweeps)
            return carry, (carry[1], carry[2])

        carry, _ = jax.lax.scan(interval, (key, x, s2), None, length=num_warmup)
        _, (xs, s2s) = jax.lax.scan(interval, carry, None, length=num_samples)
        return xs, s2s

    def pixel(key, x, s, t):
        ks = jax.random.split(key, x.shape[0])
        return jax.vmap(chain, in_axes=(0, 0, 0, None))(ks, x, s * s, t)

    return jax.vmap(pixel)(keys, x0, s0, terms)

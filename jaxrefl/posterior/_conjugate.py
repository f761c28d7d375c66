"""What the two Gibbs samplers share (:mod:`._gibbs`, exact; :mod:`._width_gibbs`, with the
lobe width by Metropolis-Hastings): the linearity check, the map from natural values to
theta, truncated normal draws, the Gibbs scan of the linear parameters along fixed
directions, and the log density of every draw.

:func:`truncated_normal`: the inverse CDF of the tail the segment lies in (a segment far in
a tail keeps its spread: a posterior piled against a bound is drawn as the steep exponential
it is, not as the bound itself).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrefl.fit import L2

from ._driver import package
from ._logpost import LogPosterior
from ._priors import Jeffreys

__all__ = [
    "CENSORED_GROWTH",
    "CENSORED_SLOTS",
    "EDGE",
    "LINEAR_RTOL",
    "censored_slots",
    "censoring_failure",
    "density",
    "is_linear",
    "likelihood_failure",
    "natural_starts",
    "observations",
    "package_draws",
    "sweep",
    "theta_of",
    "truncated_normal",
]

# Relative error of the linear prediction at a second point above which a pixel is not
# linear (float64 predictions of a linear model agree to ~1e-15).
LINEAR_RTOL = 1e-9
# Draws are kept this fraction of the box width inside its edges: a draw exactly on an
# edge would map to an infinite theta through the sigmoid.
EDGE = 1e-12
# truncated_normal: beyond this many standard deviations (float64, float32) Phi(-a)
# approaches the smallest normal float, and the tail is drawn as its exponential limit
# a + Exp(a) (relative error of the density about 1 / a^2 over the tail's scale 1 / a).
_TAIL = {8: 30.0, 4: 10.0}
# Slots of censored observations a pixel's latent draw gathers (censored_slots): at least
# CENSORED_SLOTS (a pixel has a few), else that times a power of CENSORED_GROWTH, at most
# the pixel's observations. The coarse growth keeps the compiled sizes to two (4 and every
# row) for a capture's 27-48 observations a pixel: each is one more program in a cold run.
CENSORED_SLOTS = 4
CENSORED_GROWTH = 8


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


def theta_of(lp: LogPosterior, x: Float[Array, "*b P"]) -> Float[Array, "*b P"]:
    """Unconstrained theta of natural x (elementwise bijections, in run order)."""
    parts = [
        r.bijection.inverse(x[..., r.start : r.stop]) for blk in lp.space.blocks for r in blk.runs
    ]
    return jnp.concatenate(parts, axis=-1)


def likelihood_failure(lp: LogPosterior) -> str:
    """Why the likelihood is not the Gaussian one both Gibbs samplers draw from ("" where
    it is): the light is known, the loss is L2, the noise scale known or under Jeffreys'
    prior."""
    if lp.light is not None:
        return "the light direction is sampled"
    if not isinstance(lp.residual.loss, L2):
        return f"the loss is {type(lp.residual.loss).__name__}, not L2"
    if lp.noise_scale is not None and not isinstance(lp.noise_scale, Jeffreys):
        return "the noise scale's prior is not Jeffreys'"
    return ""


def censoring_failure(data) -> str:
    """Why the censored observations are not a Tobit likelihood the samplers augment (""
    where they are): each has weight 0 or 1."""
    cens = np.asarray(data.censored) != 0
    w = np.asarray(data.weight)
    if np.any(cens & (w != 0) & (w != 1)):
        return "a censored observation has a weight other than 0 or 1"
    return ""


def censored_slots(cens: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The censored observations of each pixel, gathered, so that a scan draws latent values
    for them only (a pixel has a few at most): their indices (N, R), padded with index 0,
    and their signs (N, R) (+1 above, -1 below, 0 on the padding), of the flags ``cens`` (N,
    M) (+1 saturated, -1 dark, 0 observed). R is the smallest :data:`CENSORED_SLOTS` times
    a power of :data:`CENSORED_GROWTH` that holds every pixel's, at most M, so chunks share
    a few compiled sizes and never gather more rows than a pixel has."""
    count = np.sum(cens != 0, axis=1)
    r_max = CENSORED_SLOTS
    while r_max < int(count.max(initial=0)):
        r_max *= CENSORED_GROWTH
    r_max = min(r_max, cens.shape[1])
    # argsort's stable order puts each pixel's censored observations first, in their order
    order = np.argsort(cens == 0, axis=1, kind="stable")[:, :r_max]
    sign = np.take_along_axis(cens, order, axis=1)
    sign = np.where(np.arange(r_max) < count[:, None], sign, 0).astype(np.int8)
    return np.where(sign != 0, order, 0), sign


def is_linear(pred: Float[Array, " M"], linear: Float[Array, " M"]) -> Array:
    """Whether a prediction agrees with its linear model's at a point to :data:`LINEAR_RTOL`
    of its largest entry."""
    err = jnp.max(jnp.abs(pred - linear))
    return err <= LINEAR_RTOL * (jnp.max(jnp.abs(pred)) + 1e-300)


def sweep(key, x, s2, q, r, yy, nw, evec, evals, lo, hi, jeffreys, pp=None, pm=None, k=0):
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
        edge = EDGE * width
        return jnp.clip(x + t * d, lo + edge, hi - edge)

    x = jax.lax.fori_loop(0, x.shape[0], direction, x)
    return x, s2


@eqx.filter_jit
def density(lp, theta, data):
    """log p of every draw: theta (N, chains, draws, D)."""

    def per_pixel(t, d):
        return jax.vmap(jax.vmap(lambda ti: lp(ti, d)))(t)

    return jax.vmap(per_pixel)(theta, data)


def observations(lp: LogPosterior, data):
    """(weights (N, M), observations (N, K, C), their noise std u (N, M)) of the usable
    observations (zero weight and value elsewhere), M = K * C."""
    n, dtype = data.obs.shape[0], data.obs.dtype
    use = lp.residual.usable(data)
    w = jnp.where(use, data.weight.astype(dtype), 0.0).reshape(n, -1)
    obs = jnp.where(use, data.obs.astype(dtype), 0.0)
    return w, obs, lp.residual.noise.std(obs).reshape(n, -1)


def natural_starts(lp: LogPosterior, t0, lo, hi, jeffreys: bool):
    """(natural x (N, chains, P), noise scale s (N, chains)) of theta starts t0 (N, chains,
    D): x moved just inside the box [lo, hi] (:data:`EDGE`), s = 1 where the noise is known
    or the start's is not a positive number."""
    x0 = lp.space.natural_vector(t0[..., : lo.shape[0]])
    edge = EDGE * (hi - lo)
    x0 = jnp.clip(x0, (lo + edge)[None, None, :], (hi - edge)[None, None, :])
    s0 = jnp.exp(t0[..., -1]) if jeffreys else jnp.ones(t0.shape[:2], t0.dtype)
    return x0, jnp.where(jnp.isfinite(s0) & (s0 > 0), s0, 1.0)


def package_draws(
    lp: LogPosterior,
    xs,
    s2s,
    ok,
    data,
    *,
    acceptance,
    method: str,
    sweeps: int,
    run_s: float,
    jeffreys: bool,
):
    """:class:`~jaxrefl.posterior.Samples` of a Gibbs sampler's natural draws ``xs`` (N,
    chains, draws, P) and noise variances ``s2s``: theta (log s appended where the scale is
    sampled), the log density of every draw, ``acceptance`` (N, chains, draws), no step
    size (NaN, so that chunks of Gibbs and HMC draws concatenate) and ``sweeps``, the
    sweeps between kept draws (:attr:`Samples.sweeps`)."""
    theta = theta_of(lp, xs)
    if jeffreys:
        theta = jnp.concatenate([theta, 0.5 * jnp.log(s2s)[..., None]], axis=-1)
    shape = theta.shape[:3]
    return package(
        lp,
        theta,
        ok,
        stats={
            "acceptance_rate": np.broadcast_to(np.asarray(acceptance, np.float64), shape),
            "diverging": np.zeros(shape, bool),
            "lp": np.asarray(density(lp, theta, data), np.float64),
        },
        method=method,
        tuning={"step_size": np.full(shape[:2], np.nan)},
        run_s=run_s,
        sweeps=sweeps,
    )

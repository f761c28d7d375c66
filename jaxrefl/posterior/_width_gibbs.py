"""Metropolis-within-Gibbs for posteriors that are linear-Gaussian given one lobe width.

The per-pixel capture models (``ggx``, ``beckmann``, ``ggx_rgb``) are linear in every
parameter but the lobe width alpha: for a fixed alpha the prediction is

    pred(alpha, x) = b(alpha) + A(alpha) x        (x = albedo, F0, natural units)

(Lambert's albedo / pi and the lobe's D G / (4 cos_i cos_o) times the Schlick weight and
the irradiance; Schlick is affine in F0 at any theta_d). With the L2 loss, Gaussian noise
sd = s u (``noise.std(obs)``; s with the Jeffreys prior p(s) ~ 1/s, or s = 1), uniform
priors on x's box and any scalar prior p(alpha) on alpha's interval, the posterior is

    p(alpha, x, s | y) ~ s^-(n + 1) exp(-SSE(alpha, x) / (2 s^2)) p(alpha) 1[lo <= x <= hi]

with SSE(alpha, x) = |W^1/2 (y' - b'(alpha) - A'(alpha) x)|^2 in whitened units
(y' = y / u, A' = A / u, b' = b / u). Given alpha it is the linear-Gaussian posterior of
:mod:`jaxrefl.posterior._gibbs`; alpha enters through A' and b'. One scan here is

1. censored observations' latent values given (alpha, x, s) (data augmentation, Tanner &
   Wong 1987, as in :mod:`~jaxrefl.posterior._gibbs`);
2. (alpha, x) jointly by an independence Metropolis-Hastings proposal (Tierney 1994):
   u = log alpha from a piecewise-constant density over cells of u, each cell's weight the
   marginal of alpha with x integrated out against a Gaussian stand-in of x's box prior,
   N(box centre, (box width / 2)^2),

       m(u) = integral exp(-SSE / (2 s^2) - |(x - c) / w|^2 / 2) dx  p(alpha) alpha

   (closed form: a Gaussian integral), evaluated at the cell's midpoint; then
   x ~ N(mu(u), H(u)^-1), the same Gaussian at the proposed u itself, with
   H = (A'^T W A' + D) / s^2. The stand-in's precision D = s_ref^2 diag(w^-2) is held in
   units of s^-2 (s_ref: the start's noise scale in the warm-up, the chain's own at its end
   after it), so the cells' Cholesky factors are formed once per phase, not every scan.
   The acceptance ratio is the exact target over this proposal's density, so the stand-in
   and the cells only set how often a move is accepted, never what the chain converges to.
   Where the posterior of x sits against a bound of its box (an F0 near 0, an albedo near
   1), a Gaussian draw often lands outside the box, where the target is 0. The move then
   takes the first of :data:`_CANDIDATES` independent draws of the proposal that lands
   inside (none inside: a rejection). This is exact: it is delayed rejection (Tierney &
   Mira 1999) whose rejected stages have target 0, so every stage's acceptance and reverse
   term is 0 or 1 and the last stage's ratio is the plain independence one; equivalently,
   the proposal is truncated to the box, whose normalising constant (the inside mass) does
   not depend on the chain's state (stages are tried only after draws outside the box, a
   rule the reverse path follows too). Two draws cost a second model evaluation per scan
   and turn most of the rejections where a bound binds into moves, so that one scan between
   kept draws (``HMCOptions.width_scans`` of :data:`~jaxrefl.posterior.MAP_OPTIONS`) mixes
   about as two did with one draw. The cells are 32 even ones in log alpha from a tenth of
   the fit's optimum (or the interval's lower end, if higher) to the upper end, 6 below
   that, and 16 over +-6 Laplace standard deviations around the optimum, where an
   identified width is narrow. A ridge along which a lobe no photo saw trades width
   against F0 and albedo is crossed in one move: the proposal draws alpha from its
   marginal, not from its conditional given x;
3. s^2 | alpha, x (Inverse-Gamma) and x | alpha, s along Q-conjugate directions (Q =
   A'^T W A'), each a truncated 1-D Gaussian on the segment inside the box (the exact
   Gibbs moves of :mod:`~jaxrefl.posterior._gibbs`, which also hold x against a bound the
   Gaussian proposal of step 2 keeps crossing). The directions are the columns of L^-T for
   the Cholesky factor L of Q + ridge: conjugate directions decouple the Gaussian as its
   eigenvectors do, and a Cholesky of a P x P matrix written out elementwise is cheap on
   a batch of chains where an eigendecomposition per scan is not.

Gaussian priors on x: an entry's uniform prior may be replaced by a Gaussian one (truncated
to the box): :class:`~jaxrefl.posterior.MultivariateNormal` with ``noise_ref``, in units of
the noise, N(m, (s / s_ref)^2 S) (the conjugate Normal-Inverse-Gamma prior), or, where the
noise is known (s = 1), any Gaussian. It adds (x - m)^T S^-1 s_ref^2 (x - m) / (2 s^2) to
the exponent, a quadratic in units of s^-2 like the SSE: the proposal below takes it as its
own stand-in for those entries, the Gibbs moves add it to each direction's precision, and
s^2's conditional gains it and the prior's rank k (its normalising factor s^-k). A Gaussian
prior in absolute units with an unknown noise scale is not this conjugate form: HMC samples
it (:func:`qualifies_width`).

There is no step size, metric or gradient to tune; a kept draw is ``sweeps`` scans after
the last, a number the compiled program takes as an argument (a longer second pass of a map
reuses the first pass's program). :func:`qualifies_width` says whether a posterior and a
batch of pixels meet the conditions above; :func:`sample_width_gibbs` returns
:class:`~jaxrefl.posterior.Samples` with ``method="gibbs_mh"`` (``acceptance_rate`` the
joint moves' acceptance).
"""

from __future__ import annotations

import dataclasses
import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrefl.fit import (
    L2,
    PixelData,
    ScaledSigmoid,
    cholesky_unrolled,
    device_count,
    map_sharded,
    solve_lower_t_unrolled,
    solve_lower_unrolled,
)

from ._bind import bind_once
from ._gibbs import _EDGE, _density, _sweep, _theta_of, truncated_normal
from ._logpost import LogPosterior
from ._priors import Jeffreys, MultivariateNormal, Normal, Uniform
from ._samples import Samples

__all__ = ["WIDTH", "qualifies_width", "sample_width_gibbs"]

# The nonlinear parameter: a lobe width (GGX / Beckmann alpha), one scalar per pixel.
WIDTH = "alpha"
# Cells of the proposal over log alpha (module docstring): _GLOBAL_CELLS even ones from a
# tenth of the optimum's width (or the interval's lower end, if higher) to the upper end,
# _COARSE_CELLS even ones below that, and _LOCAL_CELLS over +-_LOCAL_SD Laplace standard
# deviations around the optimum. Over a capture's resolvable range [0.05, 1] the even cells
# are about 0.1 wide in log alpha; spread over the microfacet floor's [1e-3, 1] they would
# be twice as wide. Where the local cells miss the posterior (a width at the fit's bound),
# the even ones are the proposal, and cells that coarse mix more slowly. A posterior a
# decade narrower than its fit's optimum is rare, and the coarse cells still propose it.
_GLOBAL_CELLS = 32
_COARSE_CELLS = 6
_DENSE_BELOW = math.log(10.0)
_LOCAL_CELLS = 16
_LOCAL_SD = 6.0
# Laplace std of log alpha used where the fit's is missing or not finite, and the range it
# is clipped to (below the lower end the local cells would be narrower than float64 can
# tell the proposal's density apart from the target's; above it they add nothing to the
# even cells).
_LOCAL_SD_DEFAULT = 0.5
_LOCAL_SD_RANGE = (1e-4, 2.0)
# Censored observations per pixel the compiled sampler has room for (doubled where a pixel
# has more): a clipped highlight is seen in one or two photos.
_CENSORED_SLOTS = 4
# Relative error of the linear prediction at a second point (see _gibbs._LINEAR_RTOL).
_LINEAR_RTOL = 1e-9
# Draws of the joint proposal per move, the first inside the box proposed (module docstring).
_CANDIDATES = 2
# Ridge relative to Q's largest diagonal entry in the Cholesky factor that gives step 3's
# directions: keeps the factor finite where a direction is unseen (Q singular, a lobe no
# photo saw); the moves stay exact for any directions.
_RIDGE = 1e-10


def _layout(lp: LogPosterior):
    """(width index, lo (P,), hi (P,) over every natural entry, width prior, Gaussian prior)
    when the posterior has one scalar ``alpha`` in a finite positive box and every other
    entry is in a finite box with a uniform prior that covers it or a Gaussian prior
    (:class:`Normal` per entry, :class:`MultivariateNormal` over its block; truncated to
    the box); else None. The Gaussian prior is None where every such prior is uniform, else
    a hashable (mean (P,), precision (P, P) in units of s^-2, k, absolute): zeros in the
    uniform entries' and the width's rows and columns; a prior in units of the noise
    (``noise_ref``) has precision cov^-1 noise_ref^2 (module docstring), one in absolute
    units cov^-1, exact only where s = 1 (a known noise); k counts the entries of the
    former (their prior's normalising factor s^-k), ``absolute`` says whether any prior is
    of the latter kind."""
    width = None
    lo, hi = [], []
    p = lp.space.size
    mean, prec = np.zeros(p), np.zeros((p, p))
    k_scaled, absolute = 0, False
    for blk, prior in zip(lp.space.blocks, lp.priors, strict=True):
        at = slice(blk.start, blk.stop)
        for r in blk.runs:
            if not isinstance(r.bijection, ScaledSigmoid):
                return None
            if not (np.isfinite(r.lower) and np.isfinite(r.upper)):
                return None
            if blk.name == WIDTH:
                if r.stop - r.start != 1 or width is not None or not r.lower > 0:
                    return None
                width = (r.start, prior)
            elif isinstance(prior, Normal):
                idx = np.arange(r.start, r.stop)
                mean[idx] = float(prior.mean)
                prec[idx, idx] = 1.0 / float(prior.std) ** 2
                absolute = True
            elif isinstance(prior, MultivariateNormal):
                if len(prior.mean) != blk.stop - blk.start:
                    return None
                if r.start == blk.start:  # once per block
                    mean[at] = prior.mean
                    ref = 1.0 if prior.noise_ref is None else float(prior.noise_ref) ** 2
                    prec[at, at] = prior.precision * ref
                    k_scaled += 0 if prior.noise_ref is None else len(prior.mean)
                    absolute |= prior.noise_ref is None
            elif not isinstance(prior, Uniform) or not (
                float(prior.lower) <= r.lower and float(prior.upper) >= r.upper
            ):
                return None
            lo += [r.lower] * (r.stop - r.start)
            hi += [r.upper] * (r.stop - r.start)
    if width is None:
        return None
    gauss = None
    if np.any(prec != 0):
        gauss = tuple(mean.tolist()), tuple(map(tuple, prec.tolist())), k_scaled, absolute
    return width[0], np.asarray(lo, np.float64), np.asarray(hi, np.float64), width[1], gauss


def _general(lp: LogPosterior) -> LogPosterior:
    """``lp`` with its censored branch whatever the data (the same values): chunks with
    and without censored observations then share one compiled program."""
    return dataclasses.replace(lp, censoring=True)


def _insert(x, a, i):
    """The full natural vector: x (P - 1,) with the width a inserted at index i."""
    return jnp.concatenate([x[..., :i], jnp.asarray(a, x.dtype)[..., None], x[..., i:]], -1)


def _drop(v, i):
    return jnp.concatenate([v[..., :i], v[..., i + 1 :]], -1)


def _affine(lp, d, i, x_c, a):
    """(A (M, P - 1), b (M,)) of pixel d's prediction at width a, exact for a model affine
    in x (one forward-mode Jacobian at x_c)."""

    def pred(x):
        return lp.residual.predict(_theta_of(lp, _insert(x, a, i)), d).reshape(-1)

    jac = jax.jacfwd(pred)(x_c)
    return jac, pred(x_c) - jac @ x_c


def qualifies_width(lp: LogPosterior, data: PixelData) -> tuple[bool, str]:
    """(True, "") when :func:`sample_width_gibbs` samples this posterior for every pixel of
    ``data`` (module docstring), else (False, the first condition that fails)."""
    if lp.light is not None:
        return False, "the light direction is sampled"
    if not isinstance(lp.residual.loss, L2):
        return False, f"the loss is {type(lp.residual.loss).__name__}, not L2"
    if lp.noise_scale is not None and not isinstance(lp.noise_scale, Jeffreys):
        return False, "the noise scale's prior is not Jeffreys'"
    lay = _layout(lp)
    if lay is None:
        return False, (
            f"not one scalar {WIDTH!r} in a positive box with every other parameter in a "
            "finite box with a uniform or Gaussian prior"
        )
    cens = np.asarray(data.censored) != 0
    w = np.asarray(data.weight)
    if np.any(cens & (w != 0) & (w != 1)):
        return False, "a censored observation has a weight other than 0 or 1"
    i, lo, hi, _prior, gauss = lay
    if gauss is not None and gauss[3] and lp.noise_scale is not None:
        return False, (
            "a Gaussian prior in absolute units with an unknown noise scale (give a "
            "MultivariateNormal a noise_ref: a prior in units of the noise)"
        )
    ok = _linear_given_width(_general(lp), data, i, jnp.asarray(lo), jnp.asarray(hi))
    if not bool(np.all(np.asarray(ok))):
        return False, f"the model is not linear in its parameters given {WIDTH!r}"
    return True, ""


@eqx.filter_jit
def _linear_given_width(lp, data, i, lo, hi):
    xl, xh = _drop(lo, i), _drop(hi, i)
    x_c, x_2 = 0.5 * (xl + xh), xl + 0.3 * (xh - xl)

    def one(d):
        ok = jnp.asarray(True)
        for f in (0.2, 0.7):  # two widths inside the interval
            a = lo[i] + f * (hi[i] - lo[i])
            jac, b = _affine(lp, d, i, x_c, a)
            p2 = lp.residual.predict(_theta_of(lp, _insert(x_2, a, i)), d).reshape(-1)
            err = jnp.max(jnp.abs(p2 - (b + jac @ x_2)))
            ok = ok & (err <= _LINEAR_RTOL * (jnp.max(jnp.abs(p2)) + 1e-300))
        return ok

    return jax.vmap(one)(data)


def _moments(aw, bw, y, w):
    """(Q = A'^T W A', r = A'^T W z, z^T W z) with z = y - b', for whitened A' (..., M, P),
    b' (..., M), data y (M,) and weights w (M,)."""
    z = jnp.broadcast_to(y, bw.shape) - bw
    q = jnp.einsum("...mp,m,...mq->...pq", aw, w, aw)
    r = jnp.einsum("...mp,m,...m->...p", aw, w, z)
    zz = jnp.einsum("...m,m,...m->...", z, w, z)
    return q, r, zz


def sample_width_gibbs(
    lp: LogPosterior,
    data: PixelData,
    theta0: Float[Array, "N D"],
    *,
    theta_std: Float[Array, "N D"] | None = None,
    num_chains: int,
    num_warmup: int,
    num_samples: int,
    sweeps: int,
    seed: int = 0,
    devices: int | None = None,
):
    """Draws (module docstring) of N pixels: ``num_chains`` chains each, the first
    ``num_warmup`` kept-draw intervals discarded, then ``num_samples`` draws ``sweeps``
    scans apart. theta0: (N, D) starts (the LM optimum) or (N, chains, D); theta_std: (N, D)
    Laplace std in theta (centres the local cells; NaN: a default width). Returns
    :class:`~jaxrefl.posterior.Samples` with ``method="gibbs_mh"``. The caller checks
    :func:`qualifies_width` first."""

    lp = _general(lp)
    lay = _layout(lp)
    assert lay is not None  # qualifies_width() checked it
    i, lo_np, hi_np, prior, gauss = lay
    dtype = data.obs.dtype
    lo, hi = jnp.asarray(lo_np, dtype), jnp.asarray(hi_np, dtype)
    n, p = data.obs.shape[0], lo.shape[0]
    jeffreys = lp.noise_scale is not None
    use = lp.residual.usable(data)
    w = jnp.where(use, data.weight.astype(dtype), 0.0).reshape(n, -1)
    obs = jnp.where(use, data.obs.astype(dtype), 0.0)
    u_std = lp.residual.noise.std(obs).reshape(n, -1)
    cens_np = np.asarray(jnp.where(use, data.censored, 0)).reshape(n, -1).astype(np.int8)
    # The censored observations of each pixel, gathered (a pixel has a few at most): their
    # indices (N, R), padded with index 0 and sign 0, and their signs (+1 above, -1 below).
    # R is a power of 2, at least _CENSORED_SLOTS, and every batch takes the censored path:
    # chunks of a map with and without clipped highlights then share one compiled program.
    count = np.sum(cens_np != 0, axis=1)
    r_max = _CENSORED_SLOTS
    while r_max < int(count.max()):
        r_max *= 2
    order = np.argsort(cens_np == 0, axis=1, kind="stable")[:, :r_max]
    sign = np.take_along_axis(cens_np, order, axis=1)
    c_idx, c_sign = jnp.asarray(np.where(sign != 0, order, 0)), jnp.asarray(sign)

    t0 = jnp.asarray(theta0, dtype)
    if t0.ndim == 2:
        t0 = jnp.broadcast_to(t0[:, None, :], (n, num_chains, t0.shape[-1]))
    finite = jnp.all(jnp.isfinite(t0), axis=(-2, -1))
    t0 = jnp.where(finite[:, None, None], t0, 0.0)
    v0 = lp.space.natural_vector(t0[..., :p])
    edge = _EDGE * (hi - lo)
    v0 = jnp.clip(v0, (lo + edge)[None, None, :], (hi - edge)[None, None, :])
    s0 = jnp.exp(t0[..., -1]) if jeffreys else jnp.ones((n, num_chains), dtype)
    s0 = jnp.where(jnp.isfinite(s0) & (s0 > 0), s0, 1.0)

    # Laplace std of log alpha from theta's: d log(alpha) / d theta = s (1 - s) (hi - lo)
    # / alpha for alpha = lo + (hi - lo) s.
    a_hat = v0[:, 0, i]
    sd_u = jnp.full((n,), _LOCAL_SD_DEFAULT, dtype)
    if theta_std is not None:
        ts = jnp.asarray(theta_std, dtype)[:, i]
        frac = (a_hat - lo[i]) / (hi[i] - lo[i])
        cand = ts * frac * (1.0 - frac) * (hi[i] - lo[i]) / a_hat
        sd_u = jnp.where(jnp.isfinite(cand) & (cand > 0), cand, sd_u)
    sd_u = jnp.clip(sd_u, *_LOCAL_SD_RANGE)

    keys = jax.random.split(jax.random.PRNGKey(seed), n)
    t_start = time.perf_counter()
    # lo and hi as Python floats (hashable: one bound program per posterior and settings)
    box = tuple(float(v) for v in lo_np), tuple(float(v) for v in hi_np)
    settings = dict(i=i, num_warmup=num_warmup, num_samples=num_samples, jeffreys=jeffreys)
    run = bind_once(_run, lp, *box, prior, gauss, **settings)
    # scans between draws: an argument of the compiled program, not a constant of it, so
    # that a second pass with more of them reuses the first pass's program
    scans = jnp.full((n,), sweeps, jnp.int32)
    batched = (data, keys, v0, s0, sd_u, w, u_std, obs.reshape(n, -1), c_idx, c_sign, scans)
    vs, s2s, acc = map_sharded(run, batched, device_count(devices))
    vs, s2s, acc = jax.block_until_ready((vs, s2s, acc))
    run_s = time.perf_counter() - t_start
    theta = _theta_of(lp, vs)
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
            "acceptance_rate": np.asarray(acc, np.float64),
            "diverging": np.zeros(shape, bool),
            "lp": np.asarray(lpd, np.float64),
        },
        method="gibbs_mh",
        tuning={"step_size": np.full(shape[:2], np.nan)},
        run_s=run_s,
        extra={"no_estimate": bad, "sweeps": sweeps, "reparam": "none"},
    )


@eqx.filter_jit
def _run(
    lp,
    lo,
    hi,
    prior,
    gauss,
    data,
    keys,
    v0,
    s0,
    sd_u,
    w,
    u_std,
    obs,
    c_idx,
    c_sign,
    scans,
    *,
    i,
    num_warmup,
    num_samples,
    jeffreys,
):
    """(natural draws (N, chains, S, P), s^2 draws (N, chains, S), acceptance of the joint
    moves (N, chains, S), averaged over the scans of each interval); scans: (N,) scans
    between kept draws."""
    dtype = v0.dtype
    lo, hi = jnp.asarray(lo, dtype), jnp.asarray(hi, dtype)
    xl, xh = _drop(lo, i), _drop(hi, i)
    centre, box_prec = 0.5 * (xl + xh), (2.0 / (xh - xl)) ** 2
    # The stand-in prior of each entry: N(centre, (width / 2)^2) in absolute units; where
    # the entry has a Gaussian prior N(pm, s^2 pp^-1) (pp in units of s^-2), that prior.
    k_prior = 0
    pm = pp = None
    if gauss is not None:
        pm = _drop(jnp.asarray(gauss[0], dtype), i)
        pp = _drop(_drop(jnp.asarray(gauss[1], dtype), i).T, i)
        box_prec = jnp.where(jnp.diagonal(pp) > 0, 0.0, box_prec)
        k_prior = gauss[2]
    u_lo, u_hi = jnp.log(lo[i]), jnp.log(hi[i])
    e_u = _EDGE * (u_hi - u_lo)

    def log_width_prior(u):
        return prior.log_prob(jnp.exp(u)) + u  # density of u = log alpha

    def pixel(key, v0, s0, sd_u, d, w, u_std, obs, c_idx, c_sign, sweeps):
        yw = obs / u_std
        nw = jnp.sum(w)

        def terms(a):
            jac, b = _affine(lp, d, i, centre, a)
            return jac / u_std[:, None], b / u_std

        def factor(aw, bw, y, dref, dc):
            """(Q, r, z'Wz, L, v) at one width: L L^T = Q + D, v = L^-1 (r + D c), for the
            stand-in's precision D = dref (P - 1, P - 1) in units of s^-2 and dc = D c.
            The proposal's Gaussian is N(L^-T v, s^2 (Q + D)^-1), its factor free of s."""
            q, r, zz = _moments(aw, bw, y, w)
            l = cholesky_unrolled(q + jnp.broadcast_to(dref, q.shape))[0]
            return q, r, zz, l, solve_lower_unrolled(l, r + jnp.broadcast_to(dc, r.shape))

        # Cell edges over u: even ones, and local ones around the optimum.
        u_hat = jnp.log(v0[0, i])
        u_dense = jnp.maximum(u_lo, u_hat - _DENSE_BELOW)
        glob = jnp.concatenate(
            [
                jnp.linspace(u_lo, u_dense, _COARSE_CELLS + 1, dtype=dtype)[:-1],
                jnp.linspace(u_dense, u_hi, _GLOBAL_CELLS + 1, dtype=dtype),
            ]
        )
        loc = jnp.clip(
            u_hat + sd_u * jnp.linspace(-_LOCAL_SD, _LOCAL_SD, _LOCAL_CELLS + 1, dtype=dtype),
            u_lo,
            u_hi,
        )
        edges = jnp.sort(jnp.concatenate([glob, loc]))
        width = jnp.diff(edges)
        mids = 0.5 * (edges[:-1] + edges[1:])
        aw_g, bw_g = jax.vmap(terms)(jnp.exp(mids))  # (G, M, P-1), (G, M)
        log_cell = jnp.where(width > 0, jnp.log(jnp.where(width > 0, width, 1.0)), -jnp.inf)
        prior_g = log_width_prior(mids)
        # the censored observations' rows (gathered once; see sample_width_gibbs)
        aw_gc, bw_gc = aw_g[:, c_idx, :], bw_g[:, c_idx]  # (G, R, P-1), (G, R)
        y_c, w_c = yw[c_idx], w[c_idx]

        def cells(s2):
            """The cells' factors for the stand-in with its box part at s: (D in units of
            s^-2, D c, z'Wz (G,), v (G, P-1), log weight without the data term (G,),
            L^-1 A'^T W on the censored rows (G, P-1, R): how a latent value moves v,
            c'Dc)."""
            dref = jnp.diag(box_prec * s2)
            dc = box_prec * s2 * centre
            cdc = jnp.sum(box_prec * s2 * centre * centre)
            if pp is not None:
                dref, dc, cdc = dref + pp, dc + pp @ pm, cdc + pm @ pp @ pm
            _q, _r, zz_g, l_g, v_g = factor(aw_g, bw_g, yw, dref, dc)
            base_g = prior_g + log_cell - jnp.sum(jnp.log(jnp.diagonal(l_g, 0, -2, -1)), -1)
            lia_gc = (
                jax.vmap(
                    lambda l, a: jax.vmap(lambda col: solve_lower_unrolled(l, col), 1, 1)(a.T)
                )(l_g, aw_gc)
                * w_c[None, None, :]
            )
            return dref, dc, zz_g, v_g, base_g, lia_gc, cdc

        def log_q(logits, u):
            """log density of the proposal at u (normalised)."""
            g = jnp.clip(jnp.searchsorted(edges, u, side="right") - 1, 0, width.shape[0] - 1)
            return logits[g] - jax.nn.logsumexp(logits) - log_cell[g]

        def log_target_minus_x(aw, bw, x, u, y, s2, l, v):
            """log target - log N(x; L^-T v, s^2 (L L^T)^-1) at (u, x)."""
            res = y - bw - aw @ x
            sse = jnp.sum(w * res * res)
            dx = l.T @ x - v  # L^T (x - mu)
            log_n = -0.5 * jnp.sum(dx * dx) / s2 + jnp.sum(jnp.log(jnp.diagonal(l)))
            out = -0.5 * sse / s2 + log_width_prior(u) - log_n
            if pp is not None:  # the Gaussian prior of x (uniform ones are constant; s^-k
                out = out - 0.5 * (x - pm) @ pp @ (x - pm) / s2  # is too, s being fixed)
            return out

        def latent(key, aw, bw, x, s2):
            """Latent whitened values of the censored observations minus their bounds
            (R,): N(pred, s^2) truncated beyond the bound; 0 on the padding."""
            mean = bw[c_idx] + aw[c_idx] @ x
            sd = jnp.sqrt(s2)
            z0 = (y_c - mean) / sd
            lo_z = jnp.where(c_sign > 0, z0, -jnp.inf)
            hi_z = jnp.where(c_sign < 0, z0, jnp.inf)
            z = truncated_normal(key, lo_z, hi_z, dtype)
            return jnp.where(c_sign != 0, mean + sd * z - y_c, 0.0)

        def scan_one(carry, grid):
            key, u, x, s2, aw, bw, q, l = carry
            dref, dc, zz_g, v_g, base_g, lia_gc, cdc = grid
            key, k_y, k_g, k_u, k_x, k_a, k_s = jax.random.split(key, 7)
            # 1. the censored observations' latent values (padding slots move nothing)
            dy = latent(k_y, aw, bw, x, s2)
            y = yw + jnp.zeros_like(yw).at[c_idx].add(dy)
            # the cells' terms moved by the latent values: rows c_idx only
            v_g_y = v_g + jnp.einsum("gpr,r->gp", lia_gc, dy)
            dzz = (w_c * dy)[None, :] * (
                2.0 * jnp.broadcast_to(y_c, bw_gc.shape) + dy[None, :] - 2.0 * bw_gc
            )
            zz_g_y = zz_g + jnp.sum(dzz, axis=-1)
            # 2. the joint independence move of (u, x): the cell's weight is the Gaussian
            # integral, -(z'Wz + c'Dc - |v|^2) / (2 s^2) - log det L (+ terms equal in all)
            log_m = -0.5 * (zz_g_y + cdc - jnp.sum(v_g_y * v_g_y, -1)) / s2
            logits = jnp.where(width > 0, log_m + base_g, -jnp.inf)
            # _CANDIDATES draws of the proposal, cells by inverting their CDF (one uniform
            # each, not one Gumbel per cell); the first inside the box is the proposal,
            # none inside a rejection (module docstring)
            cdf = jnp.cumsum(jnp.exp(logits - jnp.max(logits)))
            pick = jax.random.uniform(k_g, (_CANDIDATES,), dtype) * cdf[-1]
            g = jnp.clip(jnp.searchsorted(cdf, pick), 0, width.shape[0] - 1)
            us = edges[g] + jax.random.uniform(k_u, (_CANDIDATES,), dtype) * width[g]
            us = jnp.clip(us, u_lo + e_u, u_hi - e_u)
            eps = jax.random.normal(k_x, (_CANDIDATES, centre.shape[0]), dtype)

            def candidate(u_t, e_t):
                aw_t, bw_t = terms(jnp.exp(u_t))
                q_t, r_t, zz_t, l_t, v_t = factor(aw_t, bw_t, y, dref, dc)
                x_t = solve_lower_t_unrolled(l_t, v_t + jnp.sqrt(s2) * e_t)
                return aw_t, bw_t, q_t, r_t, zz_t, l_t, v_t, x_t

            cand = jax.vmap(candidate)(us, eps)
            inside_t = jnp.all((cand[-1] > xl[None, :]) & (cand[-1] < xh[None, :]), axis=-1)
            first = jnp.argmax(inside_t)
            aw_n, bw_n, q_n, r_n, zz_n, l_n, v_n, x_new = (a[first] for a in cand)
            u_new, inside = us[first], jnp.any(inside_t)
            z_c = y - bw
            r_c = jnp.einsum("mp,m,m->p", aw, w, z_c)
            zz_c = jnp.sum(w * z_c * z_c)
            v_c = solve_lower_unrolled(l, r_c + dc)
            log_w_new = log_target_minus_x(aw_n, bw_n, x_new, u_new, y, s2, l_n, v_n)
            log_w_new = log_w_new - log_q(logits, u_new)
            log_w_cur = log_target_minus_x(aw, bw, x, u, y, s2, l, v_c) - log_q(logits, u)
            log_ratio = jnp.where(inside, log_w_new - log_w_cur, -jnp.inf)
            accept = jnp.log(jax.random.uniform(k_a, dtype=dtype)) < log_ratio
            u = jnp.where(accept, u_new, u)
            x = jnp.where(accept, x_new, x)
            aw = jnp.where(accept, aw_n, aw)
            bw = jnp.where(accept, bw_n, bw)
            q = jnp.where(accept, q_n, q)
            l = jnp.where(accept, l_n, l)
            r = jnp.where(accept, r_n, r_c)
            yy = jnp.where(accept, zz_n, zz_c)
            # 3. s^2 | u, x and x | u, s along the columns of L^-T: conjugate for Q + D,
            # nearly so for Q (the moves are exact for any directions)
            eye = jnp.eye(q.shape[0], dtype=dtype)
            dirs = jax.vmap(lambda e: solve_lower_t_unrolled(l, e), out_axes=1)(eye)
            lam = jnp.einsum("pk,pq,qk->k", dirs, q, dirs)
            x, s2 = _sweep(k_s, x, s2, q, r, yy, nw, dirs, lam, xl, xh, jeffreys, pp, pm, k_prior)
            return (key, u, x, s2, aw, bw, q, l), accept.astype(dtype)

        def chain(key, v, s):
            x = _drop(v, i)
            u = jnp.clip(jnp.log(v[i]), u_lo + e_u, u_hi - e_u)
            aw, bw = terms(jnp.exp(u))
            q = _moments(aw, bw, yw, w)[0]

            # Both phases run one compiled loop (half the program of two): an outer scan
            # over the phases, each rescaling the stand-in to the chain's noise scale then
            # (the start's in the warm-up, which can be far off; the chain's own after it;
            # the proposal is fixed within a phase), and an inner loop over its intervals
            # whose count is the phase's, written into the draws only after the warm-up.
            p_out = v.shape[0]
            draws0 = (
                jnp.zeros((num_samples, p_out), dtype),
                jnp.zeros((num_samples,), dtype),
                jnp.zeros((num_samples,), dtype),
            )

            def phase(state, spec):
                carry, draws = state
                length, keep = spec[0], spec[1] > 0
                grid = cells(carry[3])
                carry = (*carry[:7], cholesky_unrolled(carry[6] + grid[0])[0])

                def interval(t, st):
                    carry, draws = st

                    def scan(_, sc):
                        carry, acc = sc
                        carry, a = scan_one(carry, grid)
                        return carry, acc + a

                    zero = jnp.zeros((), dtype)
                    carry, acc = jax.lax.fori_loop(0, sweeps, scan, (carry, zero))
                    u, x, s2 = carry[1], carry[2], carry[3]
                    new = (_insert(x, jnp.exp(u), i), s2, acc / sweeps)
                    at = jnp.where(keep, t, num_samples)  # out of range in the warm-up: dropped
                    draws = tuple(
                        d.at[at].set(v, mode="drop") for d, v in zip(draws, new, strict=True)
                    )
                    return carry, draws

                return jax.lax.fori_loop(0, length, interval, (carry, draws)), None

            carry = (key, u, x, s * s, aw, bw, q, jnp.zeros_like(q))
            specs = jnp.asarray([[num_warmup, 0], [num_samples, 1]], jnp.int32)
            (_, draws), _ = jax.lax.scan(phase, (carry, draws0), specs)
            return draws

        ks = jax.random.split(key, v0.shape[0])
        return jax.vmap(chain)(ks, v0, s0)

    return jax.vmap(pixel)(keys, v0, s0, sd_u, data, w, u_std, obs, c_idx, c_sign, scans)

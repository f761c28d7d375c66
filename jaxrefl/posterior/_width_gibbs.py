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
   rule the reverse path follows too). A second draw costs a second model evaluation
   per scan and turns most of the rejections where a bound binds into moves. The cells
   (:data:`_GLOBAL_CELLS`, :data:`_COARSE_CELLS`, :data:`_LOCAL_CELLS`) are even in log
   alpha over the interval, coarser a decade below the fit's optimum, and dense around
   the optimum, where an
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

import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrefl.fit import (
    PixelData,
    cholesky_unrolled,
    device_count,
    map_sharded,
    solve_lower_t_unrolled,
    solve_lower_unrolled,
)

from ._bind import bind_once
from ._conjugate import (
    EDGE,
    censored_slots,
    natural_starts,
    observations,
    package_draws,
    sweep,
    truncated_normal,
)
from ._driver import Kernel, chain_starts, run_chain
from ._logpost import LogPosterior
from ._width_layout import (
    WIDTH,
    affine_terms,
    drop_width,
    general,
    insert_width,
    layout,
    qualifies_width,
)

__all__ = ["WIDTH", "qualifies_width", "sample_width_gibbs"]

# Cells of the proposal over log alpha (module docstring): _GLOBAL_CELLS even ones from
# _DENSE_BELOW below the optimum (or the interval's lower end, if higher) to the upper end,
# _COARSE_CELLS even ones below that, and _LOCAL_CELLS over +-_LOCAL_SD Laplace standard
# deviations around the optimum; the local cells hold an identified width, the even ones a
# posterior far from the fit's optimum.
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
# Draws of the joint proposal per move, the first inside the box proposed (module docstring).
_CANDIDATES = 2


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

    lp = general(lp)
    lay = layout(lp)
    assert lay is not None  # qualifies_width() checked it
    i, lo_np, hi_np, prior, gauss = lay
    dtype = data.obs.dtype
    lo, hi = jnp.asarray(lo_np, dtype), jnp.asarray(hi_np, dtype)
    n = data.obs.shape[0]
    jeffreys = lp.noise_scale is not None
    w, obs, u_std = observations(lp, data)
    cens = jnp.where(lp.residual.usable(data), data.censored, 0)
    cens_np = np.asarray(cens).reshape(n, -1).astype(np.int8)
    # The censored observations of each pixel, gathered (:func:`._conjugate.censored_slots`).
    # Every batch takes the censored path: chunks of a map with and without clipped
    # highlights then share one compiled program.
    c_idx, c_sign = (jnp.asarray(v) for v in censored_slots(cens_np))

    t0, finite = chain_starts(theta0, n, num_chains, dtype)
    v0, s0 = natural_starts(lp, t0, lo, hi, jeffreys)

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
    return package_draws(
        lp,
        vs,
        s2s,
        finite,
        data,
        acceptance=acc,
        method="gibbs_mh",
        sweeps=sweeps,
        run_s=run_s,
        jeffreys=jeffreys,
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
    xl, xh = drop_width(lo, i), drop_width(hi, i)
    centre, box_prec = 0.5 * (xl + xh), (2.0 / (xh - xl)) ** 2
    # The stand-in prior of each entry: N(centre, (width / 2)^2) in absolute units; where
    # the entry has a Gaussian prior N(pm, s^2 pp^-1) (pp in units of s^-2), that prior.
    k_prior = 0
    pm = pp = None
    if gauss is not None:
        pm = drop_width(jnp.asarray(gauss[0], dtype), i)
        pp = drop_width(drop_width(jnp.asarray(gauss[1], dtype), i).T, i)
        box_prec = jnp.where(jnp.diagonal(pp) > 0, 0.0, box_prec)
        k_prior = gauss[2]
    u_lo, u_hi = jnp.log(lo[i]), jnp.log(hi[i])
    e_u = EDGE * (u_hi - u_lo)

    def log_width_prior(u):
        return prior.log_prob(jnp.exp(u)) + u  # density of u = log alpha

    def pixel(key, v0, s0, sd_u, d, w, u_std, obs, c_idx, c_sign, sweeps):
        yw = obs / u_std
        nw = jnp.sum(w)

        def terms(a):
            jac, b = affine_terms(lp, d, i, centre, a)
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
            x, s2 = sweep(k_s, x, s2, q, r, yy, nw, dirs, lam, xl, xh, jeffreys, pp, pm, k_prior)
            return (key, u, x, s2, aw, bw, q, l), accept.astype(dtype)

        def begin(state):
            """A phase's proposal: the cells' factors at the chain's noise scale then (the
            start's in the warm-up, which can be far off; the chain's own after it)."""
            carry, _grid = state
            grid = cells(carry[3])
            return (*carry[:7], cholesky_unrolled(carry[6] + grid[0])[0]), grid

        def step(state):
            carry, grid = state
            carry, accepted = scan_one(carry, grid)
            return (carry, grid), accepted

        def draw(state):
            _key, u, x, s2 = state[0][:4]
            return insert_width(x, jnp.exp(u), i), s2

        def init(key, v, s):
            x = drop_width(v, i)
            u = jnp.clip(jnp.log(v[i]), u_lo + e_u, u_hi - e_u)
            aw, bw = terms(jnp.exp(u))
            q = _moments(aw, bw, yw, w)[0]
            carry = (key, u, x, s * s, aw, bw, q, jnp.zeros_like(q))
            grid = jax.tree.map(jnp.zeros_like, jax.eval_shape(cells, s * s))
            return carry, grid

        def chain(key, v, s):
            kernel = Kernel(init=init, step=step, draw=draw, begin=begin)
            (vs, s2s), acc, _ = run_chain(
                kernel,
                (key, v, s),
                warmup=num_warmup,
                warmup_steps=sweeps,
                num_samples=num_samples,
                per_draw=sweeps,
            )
            return vs, s2s, acc

        ks = jax.random.split(key, v0.shape[0])
        return jax.vmap(chain)(ks, v0, s0)

    return jax.vmap(pixel)(keys, v0, s0, sd_u, data, w, u_std, obs, c_idx, c_sign, scans)

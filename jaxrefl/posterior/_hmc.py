"""Per-pixel posteriors on every pixel at once: BlackJAX HMC (or NUTS) under ``vmap``.

Each pixel's posterior is independent (:class:`~jaxrefl.posterior.LogPosterior` with that
pixel's data), so one compiled program runs all of them: ``vmap`` over the chains of a
pixel, ``lax.map(batch_size=...)`` over pixels (a block of pixels vmapped at a time: the
working set stays bounded and the batch keeps the vector units busy), the shared driver
(:mod:`._driver`) over the steps of :func:`hmc_kernel`.

Kernel: fixed-length HMC (``num_integration_steps`` leapfrog steps, default 16) by
default. Under ``vmap`` every lane of a batch runs the same instructions, so NUTS runs
every step at the deepest tree of the batch; fixed-length HMC has no such coupling, and
gives more effective samples per second per pixel on large batches
(``benchmarks/posterior_speed.py`` measures the batched sampler). ``kernel="nuts"`` is
available for small batches.

Adaptation (:func:`_one_chain`: dual averaging of the step size to ``target_accept`` with
BlackJAX's ``dual_averaging_adaptation``, a mass matrix from the warm-up draws by
BlackJAX's Welford estimator, in the same loop as the sampling) runs **per chain, per pixel**:
nothing is shared. Pixels differ by orders of magnitude in their posterior widths (a
highlight pins alpha to 1%, a matte pixel leaves it free), so a shared step size or mass
matrix would be wrong for most of them; adapting per chain costs ``num_warmup`` extra
steps, which the vmapped batch pays once. A **dense** mass matrix is the default:
specular F0 and log alpha are strongly correlated (a narrower lobe is brighter), which a
diagonal metric cannot follow.

Coordinates (``reparam``): by default the chains move in theta', where the diffuse albedo
is non-centred on its conditional given the other parameters
(:mod:`jaxrefl.posterior._reparam`; an exact change of variables, the draws are mapped
back to theta and ``lp`` is theta's log density); ``reparam="none"`` samples the fit's
theta itself. Models without a bounded albedo in which the prediction is affine fall back
to theta under ``"auto"``.

Chains start from the LM optimum plus a jitter of ``init_jitter`` times the Laplace
theta-space std (when given) so that split R-hat compares chains that began apart.
Pixels with no estimate (NaN theta) are run from theta = 0 and come back NaN. With
``reparam`` the start and the jitter are taken in theta' (the albedo's entries with scale
1, its conditional sd), so the chains start on the ridge, not across it.
"""

from __future__ import annotations

import contextlib
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxrefl.fit import PixelData, device_count, map_sharded

from ._bind import bind_once
from ._driver import Kernel, chain_starts, package, run_chain
from ._logpost import LogPosterior
from ._options import HMCOptions
from ._reparam import ConditionalAlbedo, conditional_albedo
from ._samples import Samples

__all__ = ["hmc_kernel", "sample_hmc"]


def _dtype_scope(dtype):
    """Where float32 chains are traced: with 64-bit types off, so that constants made
    without a dtype (BlackJAX's dense metric builds its identity matrix that way) are
    float32 too, instead of promoting the chain's state to float64 under ``jax_enable_x64``."""
    if jnp.dtype(dtype) == jnp.float32:
        return jax.enable_x64(False)
    return contextlib.nullcontext()


def hmc_kernel(lp: LogPosterior | ConditionalAlbedo, opts: HMCOptions, keys, data, normals):
    """One chain's HMC/NUTS step with its warm-up adaptation (:func:`_one_chain`), over the
    state (step index, BlackJAX's state, dual averaging, inverse mass matrix, Welford
    state of the slow window, the kept step size); ``keys`` (steps, 2): one per step."""
    # Imported here, not with the module: importing BlackJAX runs JAX computations, which
    # would fix the process's devices before a multi-process job can start
    # (jaxrefl.fit.Distributed.initialize).
    import blackjax
    from blackjax.adaptation.mass_matrix import welford_algorithm
    from blackjax.adaptation.step_size import dual_averaging_adaptation

    def logdensity(t):
        return lp(t, data, normals)

    algo = blackjax.hmc if opts.kernel == "hmc" else blackjax.nuts
    extra = {"num_integration_steps": opts.num_integration_steps} if opts.kernel == "hmc" else {}
    n_warm = opts.num_warmup
    w1, w2 = max(1, int(0.15 * n_warm)), max(2, int(opts.metric_window_end * n_warm))
    da_init, da_update, _ = dual_averaging_adaptation(opts.target_accept)
    wf_init, wf_update, _ = welford_algorithm(is_diagonal_matrix=not opts.dense_mass)

    def init(x0, imm0):
        d, dtype = x0.shape[-1], x0.dtype
        imm = imm0 if opts.dense_mass else jnp.diagonal(imm0)
        state = algo(logdensity, 1.0, imm, **extra).init(x0)
        eps0 = jnp.asarray(0.5, dtype)
        wf = wf_init(d)._replace(sample_size=jnp.asarray(0, jnp.int32))
        return (jnp.asarray(0, jnp.int32), state, da_init(eps0), imm, wf, eps0)

    def step(carry):
        i, state, da, imm, wf, final_eps = carry
        dtype = final_eps.dtype
        k_eps, k_step = jax.random.split(keys[i])
        warm = i < n_warm
        eps = jnp.where(warm, jnp.exp(da.log_step_size), final_eps)
        # Step size jittered by +-step_jitter each iteration (Neal 2011, sec. 5.4.2): a
        # fixed trajectory length resonates with the period of a near-Gaussian posterior
        # (a chain then barely moves); jitter breaks the resonance.
        lo, hi = 1.0 - opts.step_jitter, 1.0 + opts.step_jitter
        eps = eps * jax.random.uniform(k_eps, (), dtype, lo, hi)
        state, info = algo(logdensity, eps, imm, **extra).step(k_step, state)
        # A NaN acceptance (non-finite energy) counts as a rejection for the adaptation.
        acc = jnp.where(jnp.isfinite(info.acceptance_rate), info.acceptance_rate, 0.0)
        da1 = da_update(da, acc)
        slow = (i >= w1) & (i < w2)
        wf = jax.tree.map(lambda a, b: jnp.where(slow, a, b), wf_update(wf, state.position), wf)
        end_slow = i == w2 - 1
        n = jnp.maximum(wf.sample_size, 2).astype(dtype)
        cov = wf.m2 / (n - 1)
        # Stan's regularisation of the warm-up covariance towards a small multiple of 1
        reg = (n / (n + 5.0)) * cov + 1e-3 * (5.0 / (n + 5.0)) * _ones_like_metric(cov)
        imm = jnp.where(end_slow, reg, imm)
        restart = da_init(jnp.exp(da1.log_step_size))
        da1 = jax.tree.map(lambda a, b: jnp.where(end_slow, a, b), restart, da1)
        final_eps = jnp.where(i == n_warm - 1, jnp.exp(da1.log_step_size_avg), final_eps)
        da = jax.tree.map(lambda a, b: jnp.where(warm, a, b), da1, da)
        return (i + 1, state, da, imm, wf, final_eps), (acc, info.is_divergent)

    def draw(carry):
        return carry[1].position, carry[1].logdensity

    return Kernel(init=init, step=step, draw=draw)


def _ones_like_metric(cov):
    """The identity in the metric's form: a matrix for a dense metric, ones for a diagonal."""
    return jnp.eye(cov.shape[-1], dtype=cov.dtype) if cov.ndim == 2 else jnp.ones_like(cov)


def _one_chain(
    lp: LogPosterior | ConditionalAlbedo, opts: HMCOptions, key, x0, imm0, data, normals
):
    """Warm-up and sampling of one chain (module docstring) through the shared driver.

    Warm-up schedule (Stan's, with one slow window): steps [0, 15%) adapt the step size
    by dual averaging (Hoffman & Gelman 2014, sec. 3.2) on the initial metric ``imm0``
    (the Laplace covariance's diagonal where given); steps [15%, 75%) (the end is
    ``metric_window_end``) also accumulate the covariance of the draws (BlackJAX's
    Welford estimator), which at 75% becomes the inverse mass matrix, regularised as
    Stan does: n/(n+5) Cov + 1e-3 * 5/(n+5) I; dual averaging restarts then and runs to the
    end of the warm-up, whose averaged step size is kept. One kernel serves warm-up and
    sampling, so the model's gradient is compiled once. Of each block of ``thin`` steps
    the last draw is kept, the acceptance averaged and a divergence in any step counted.
    """
    total = opts.num_warmup + opts.num_samples * opts.thin
    kernel = hmc_kernel(lp, opts, jax.random.split(key, total), data, normals)
    (pos, lpd), (acc, div), last = run_chain(
        kernel,
        (x0, imm0),
        warmup=opts.num_warmup,
        warmup_steps=1,
        num_samples=opts.num_samples,
        per_draw=opts.thin,
    )
    return pos, lpd, acc, div, last[-1]


@eqx.filter_jit
def _run(
    lp: LogPosterior | ConditionalAlbedo,
    opts: HMCOptions,
    keys,
    x0,
    imm0,
    data: PixelData,
    normals,
):
    def pixel(args):
        k, x, m, d, n = args
        n = n if lp.light is not None else None  # zeros stand in when the light is known
        kc = jax.random.split(k, opts.num_chains)
        return jax.vmap(lambda kk, xx: _one_chain(lp, opts, kk, xx, m, d, n))(kc, x)

    return jax.lax.map(pixel, (keys, x0, imm0, data, normals), batch_size=opts.batch_size)


def _coordinates(lp: LogPosterior, mode: str) -> ConditionalAlbedo | None:
    """The reparameterisation of ``HMCOptions.reparam`` (None: the fit's theta)."""
    if mode == "none":
        return None
    try:
        return conditional_albedo(lp)
    except ValueError:
        if mode == "albedo":
            raise
        return None  # "auto": not applicable to this model


@eqx.filter_jit
def _map_starts(rp: ConditionalAlbedo, x0, data: PixelData, normals):
    """(N, chains, D) starts theta -> theta'."""

    def pixel(x, d, n):
        return jax.vmap(lambda t: rp.from_theta(t, d, n))(x)

    if normals is None:
        return jax.vmap(lambda x, d: pixel(x, d, None))(x0, data)
    return jax.vmap(pixel)(x0, data, normals)


@eqx.filter_jit
def _map_draws(rp: ConditionalAlbedo, pos, data: PixelData, normals, batch_size: int):
    """(N, chains, draws, D) draws theta' -> (theta, log|dT/dtheta'| (N, chains, draws))."""
    n_c, n_d, d_ = pos.shape[1:]

    def pixel(args):
        x, d, n = args
        t, ld, _ = jax.vmap(lambda y: rp.to_theta(y, d, n))(x.reshape(-1, d_))
        return t.reshape(n_c, n_d, d_), ld.reshape(n_c, n_d)

    if normals is None:
        return jax.lax.map(lambda a: pixel((*a, None)), (pos, data), batch_size=batch_size)
    return jax.lax.map(pixel, (pos, data, normals), batch_size=batch_size)


def sample_hmc(
    lp: LogPosterior,
    data: PixelData,
    theta0: Float[ArrayLike, "*N D"],
    opts: HMCOptions,
    *,
    theta_std: Float[ArrayLike, "*N D"] | None = None,
    normals: Array | None = None,
    seed: int = 0,
    timing: bool = False,
    devices: int | None = None,
) -> Samples:
    """HMC/NUTS draws of every pixel of ``data`` under ``opts`` (the other arguments are
    those of :func:`jaxrefl.posterior.sample_pixels`, which calls it with its options
    resolved and ``lp`` already :meth:`~LogPosterior.for_data`)."""
    n = data.obs.shape[0]
    dtype = data.obs.dtype
    x, ok = chain_starts(theta0, n, opts.num_chains, dtype)
    sd = jnp.ones((n, lp.size), dtype) if theta_std is None else jnp.asarray(theta_std, dtype)
    sd = jnp.broadcast_to(
        jnp.where(jnp.isfinite(sd) & (sd > 0), jnp.minimum(sd, 1.0), 1.0), (n, lp.size)
    )
    if normals is None:
        nrm = jnp.zeros((n, 1, 3), dtype)  # unused without a light; keeps one code path
    else:
        nrm = jnp.broadcast_to(jnp.asarray(normals, dtype), (n, data.obs.shape[1], 3))
    rp = _coordinates(lp, opts.reparam)
    normals_or_none = nrm if lp.light is not None else None
    if rp is not None:  # the chains move in theta': starts mapped there, theta'_rho has scale 1
        x = _map_starts(rp, x, data, normals_or_none)
        sd = sd.at[:, rp.start : rp.stop].set(1.0)
    target = lp if rp is None else rp
    key = jax.random.PRNGKey(seed)
    k_init, k_run = jax.random.split(key)
    eps = jax.random.normal(k_init, (n, opts.num_chains, lp.size), dtype)
    x0 = x + opts.init_jitter * sd[:, None, :] * eps
    keys = jax.random.split(k_run, n)

    imm0 = jax.vmap(jnp.diag)(sd * sd)  # the initial metric: the Laplace scales

    # Pad N up to a multiple of the batch (repeating pixels; dropped below): lax.map would
    # otherwise compile the vmapped sampler a second time for the remainder.
    bs = opts.batch_size
    n_run = n if n <= bs else -(-n // bs) * bs
    rows = np.resize(np.arange(n), n_run)
    args = (keys, x0, imm0, data, nrm)
    if n_run != n:
        args = jax.tree.map(lambda a: a[rows], args)

    ndev = device_count(devices)

    def call():
        run = bind_once(_run, target, opts)
        with _dtype_scope(dtype):
            out = jax.block_until_ready(map_sharded(run, args, ndev))
        return jax.tree.map(lambda a: a[:n], out)

    t0 = time.perf_counter()
    out = call()
    t1 = time.perf_counter()
    compile_s = float("nan")
    if timing:
        out = call()
        t2 = time.perf_counter()
        compile_s = max(0.0, (t1 - t0) - (t2 - t1))
        run_s = t2 - t1
    else:
        run_s = t1 - t0
    if rp is not None:  # draws back to theta; "lp" is theta's density (Jacobian removed)
        pos_p, lpd_p = out[0], out[1]
        pos_t, log_det = _map_draws(rp, pos_p, data, normals_or_none, opts.batch_size)
        out = (pos_t, lpd_p - log_det, *out[2:])
    pos, lpd, acc, div, step = (np.asarray(a) for a in out)
    return package(
        lp,
        pos,
        ok,
        stats={"acceptance_rate": acc, "diverging": div, "lp": lpd},
        method=opts.kernel,
        tuning={"step_size": step},
        compile_s=compile_s,
        run_s=run_s,
        options=opts,
        reparam="none" if rp is None else rp.name,
    )

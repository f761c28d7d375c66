"""Per-pixel posteriors on every pixel at once: BlackJAX HMC (or NUTS) under ``vmap``.

Each pixel's posterior is independent (:class:`~jaxrefl.posterior.LogPosterior` with that
pixel's data), so one compiled program runs all of them: ``vmap`` over the chains of a
pixel, ``lax.map(batch_size=...)`` over pixels (a block of pixels vmapped at a time: the
working set stays bounded and the batch keeps the vector units busy), ``lax.scan`` over
steps.

Kernel: fixed-length HMC (``num_integration_steps`` leapfrog steps, default 16) by
default. Under ``vmap`` every lane of a batch runs the same instructions, so NUTS runs
every step at the deepest tree of the batch; fixed-length HMC has no such coupling, and
gives more effective samples per second per pixel on large batches
(``benchmarks/posterior_speed.py`` measures the batched sampler). ``kernel="nuts"`` is
available for small batches.

Adaptation (:func:`_one_chain`: dual averaging of the step size to ``target_accept`` with
BlackJAX's ``dual_averaging_adaptation``, a mass matrix from the warm-up draws, in the same
scan as the sampling) runs **per chain, per pixel**:
nothing is shared. Pixels differ by orders of magnitude in their posterior widths (a
highlight pins alpha to 1%, a matte pixel leaves it free), so a shared step size or mass
matrix would be wrong for most of them; adapting per chain costs ``num_warmup`` extra
steps, which the vmapped batch pays once. A **dense** mass matrix is the default:
specular F0 and log alpha are strongly correlated (a narrower lobe is brighter), and a
dense metric roughly triples the ESS there.

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
from dataclasses import dataclass
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import PixelData, device_count, map_sharded

from ._bind import bind_once
from ._gibbs import qualifies, sample_gibbs
from ._logpost import LogPosterior
from ._reparam import ConditionalAlbedo, conditional_albedo
from ._samples import Samples
from ._width_gibbs import qualifies_width, sample_width_gibbs

__all__ = ["HMCOptions", "sample_pixels"]


@dataclass(frozen=True)
class HMCOptions:
    """Settings of :func:`sample_pixels` (module docstring)."""

    num_warmup: int = 300
    num_samples: int = 500
    num_chains: int = 4
    kernel: Literal["hmc", "nuts"] = "hmc"
    num_integration_steps: int = 16
    dense_mass: bool = True
    target_accept: float = 0.8
    batch_size: int = 100
    init_jitter: float = 0.5
    step_jitter: float = 0.2
    # 0.75, not Stan's 0.9: more of the warm-up is left to re-tune the step size after
    # the metric update. For the same gradients this lifts the worst pixels' min bulk ESS
    # and keeps the acceptance above the 0.8 target, at some cost in median tail ESS
    # (``benchmarks/posterior_speed.py --only-window`` compares the two windows).
    metric_window_end: float = 0.75
    # Coordinates the chains move in (:mod:`jaxrefl.posterior._reparam`): "albedo", the
    # diffuse albedo non-centred on its conditional given the other parameters; "none",
    # the fit's theta; "auto", "albedo" where the model is affine in a bounded albedo.
    reparam: Literal["auto", "albedo", "none"] = "auto"
    # Keep every thin-th draw: ``num_samples`` draws are kept of num_samples * thin steps
    # (acceptance averaged over, and divergences counted in, the steps between). Used by
    # the longer second pass of adaptive_uncertainty, whose draws keep the first's shape.
    thin: int = 1
    # Where > 0 and the posterior is linear-Gaussian in every BRDF parameter
    # (:func:`jaxrefl.posterior._gibbs.qualifies`: e.g. ``pooled`` under a co-located
    # flash; censored observations by data augmentation), draw it exactly by Gibbs
    # sampling instead; where it is so given one lobe width (the per-pixel ``ggx``:
    # :func:`jaxrefl.posterior._width_gibbs.qualifies_width`), by Metropolis-within-Gibbs
    # with a collapsed proposal of the width; this many scans between kept draws (times
    # ``thin``). 0: always HMC.
    gibbs_sweeps: int = 0
    # Scans between kept draws of the width sampler where it runs (``gibbs_sweeps`` > 0),
    # times ``thin``; None: ``gibbs_sweeps``. Each of its scans makes a joint move of the
    # width and the linear parameters and a Gibbs sweep of the latter, so one can do
    # (:data:`jaxrefl.posterior.MAP_OPTIONS`).
    width_scans: int | None = None
    # Kept-draw intervals the Gibbs path discards, as a fraction of ``num_warmup`` (at
    # least 1): it has no step size or metric to tune, and its chains start at the fit's
    # optimum, inside the bulk (``benchmarks/posterior_speed.py`` reports the R-hat of
    # the maps it samples).
    gibbs_warmup_fraction: float = 0.2

    def __post_init__(self):
        if self.reparam not in ("auto", "albedo", "none"):
            raise JaxreflError(f"reparam must be 'auto', 'albedo' or 'none', not {self.reparam!r}")
        if not 0.15 < self.metric_window_end <= 1.0:
            w = self.metric_window_end
            raise JaxreflError(f"metric_window_end must be in (0.15, 1], got {w}")
        if self.kernel not in ("hmc", "nuts"):
            raise JaxreflError(f"kernel must be 'hmc' or 'nuts', not {self.kernel!r}")
        for k in (
            "num_warmup",
            "num_samples",
            "num_chains",
            "num_integration_steps",
            "batch_size",
            "thin",
        ):
            if getattr(self, k) < 1:
                raise JaxreflError(f"{k} must be >= 1, got {getattr(self, k)}")
        if self.gibbs_sweeps < 0:
            raise JaxreflError(f"gibbs_sweeps must be >= 0, got {self.gibbs_sweeps}")
        if self.width_scans is not None and self.width_scans < 1:
            raise JaxreflError(f"width_scans must be >= 1 or None, got {self.width_scans}")
        if not 0.0 < self.gibbs_warmup_fraction <= 1.0:
            f = self.gibbs_warmup_fraction
            raise JaxreflError(f"gibbs_warmup_fraction must be in (0, 1], got {f}")

    @property
    def gibbs_warmup(self) -> int:
        """Kept-draw intervals of warm-up on the Gibbs path."""
        return max(1, round(self.num_warmup * self.gibbs_warmup_fraction))


def _welford(mean, m2, count, x, on):
    """One step of Welford's running mean and (dense) scatter matrix, where ``on``."""
    c1 = count + on
    delta = x - mean
    mean1 = mean + jnp.where(on, delta / jnp.maximum(c1, 1), 0.0)
    m2_1 = m2 + jnp.where(on, jnp.outer(delta, x - mean1), 0.0)
    return mean1, m2_1, c1


def _dtype_scope(dtype):
    """Where float32 chains are traced: with 64-bit types off, so that constants made
    without a dtype (BlackJAX's dense metric builds its identity matrix that way) are
    float32 too, instead of promoting the chain's state to float64 under ``jax_enable_x64``."""
    if jnp.dtype(dtype) == jnp.float32:
        return jax.enable_x64(False)
    return contextlib.nullcontext()


def _one_chain(
    lp: LogPosterior | ConditionalAlbedo, opts: HMCOptions, key, x0, imm0, data, normals
):
    """Warm-up and sampling of one chain in a single ``lax.scan`` (module docstring).

    Warm-up schedule (Stan's, with one slow window): steps [0, 15%) adapt the step size
    by dual averaging (Hoffman & Gelman 2014, sec. 3.2) on the initial metric ``imm0``
    (the Laplace covariance's diagonal where given); steps [15%, 75%) (the end is
    ``metric_window_end``) also accumulate the covariance of the draws, which at 75%
    becomes the inverse mass matrix, regularised as
    Stan does: n/(n+5) Cov + 1e-3 * 5/(n+5) I; dual averaging restarts then and runs to the
    end of the warm-up, whose averaged step size is kept. One kernel serves warm-up and
    sampling, so the model's gradient is compiled once.
    """

    # Imported here, not with the module: importing BlackJAX runs JAX computations, which
    # would fix the process's devices before a multi-process job can start
    # (jaxrefl.fit.Distributed.initialize).
    import blackjax
    from blackjax.adaptation.step_size import dual_averaging_adaptation

    def logdensity(t):
        return lp(t, data, normals)

    algo = blackjax.hmc if opts.kernel == "hmc" else blackjax.nuts
    extra = {"num_integration_steps": opts.num_integration_steps} if opts.kernel == "hmc" else {}
    n_warm = opts.num_warmup
    w1, w2 = max(1, int(0.15 * n_warm)), max(2, int(opts.metric_window_end * n_warm))
    da_init, da_update, _ = dual_averaging_adaptation(opts.target_accept)
    d = x0.shape[-1]
    dtype = x0.dtype
    eye = jnp.eye(d, dtype=dtype)
    imm = imm0 if opts.dense_mass else jnp.diagonal(imm0)
    state = algo(logdensity, 1.0, imm, **extra).init(x0)
    eps0 = jnp.asarray(0.5, dtype)
    carry0 = (state, da_init(eps0), imm, jnp.zeros(d, dtype), jnp.zeros((d, d), dtype), 0, eps0)

    def body(carry, xs):
        state, da, imm, mean, m2, count, final_eps = carry
        i, k = xs
        k_eps, k_step = jax.random.split(k)
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
        mean, m2, count = _welford(mean, m2, count, state.position, slow)
        end_slow = i == w2 - 1
        n = jnp.maximum(count, 2).astype(dtype)
        cov = m2 / (n - 1)
        reg = (n / (n + 5.0)) * cov + 1e-3 * (5.0 / (n + 5.0)) * eye
        new_imm = reg if opts.dense_mass else jnp.diagonal(reg)
        imm = jnp.where(end_slow, new_imm, imm)
        restart = da_init(jnp.exp(da1.log_step_size))
        da1 = jax.tree.map(lambda a, b: jnp.where(end_slow, a, b), restart, da1)
        final_eps = jnp.where(i == n_warm - 1, jnp.exp(da1.log_step_size_avg), final_eps)
        da = jax.tree.map(lambda a, b: jnp.where(warm, a, b), da1, da)
        out = (state.position, state.logdensity, acc, info.is_divergent)
        return (state, da, imm, mean, m2, count, final_eps), out

    thin, n_keep = opts.thin, opts.num_samples
    total = n_warm + n_keep * thin
    xs = (jnp.arange(total), jax.random.split(key, total))
    # One scan over warm-up and sampling: one copy of the kernel (and the model's gradient)
    # to compile. Thinning afterwards: of each block of ``thin`` steps the last draw is
    # kept, the acceptance averaged and a divergence in any step counted.
    (*_, eps), (pos, lpd, acc, div) = jax.lax.scan(body, carry0, xs)

    def blocks(a):
        return a[n_warm:].reshape(n_keep, thin, *a.shape[1:])

    return (
        blocks(pos)[:, -1],
        blocks(lpd)[:, -1],
        blocks(acc).mean(1),
        blocks(div).any(1),
        eps,
    )


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


def sample_pixels(
    lp: LogPosterior,
    data: PixelData,
    theta0: Float[ArrayLike, "*N D"],
    *,
    theta_std: Float[ArrayLike, "*N D"] | None = None,
    normals: Array | None = None,
    options: HMCOptions | None = None,
    seed: int = 0,
    timing: bool = False,
    devices: int | None = None,
) -> Samples:
    """Sample the posterior of every pixel of ``data`` ((N, K, C)) with vmapped HMC.

    theta0:    (N, D) or (D,) start (the LM optimum via :meth:`LogPosterior.init_theta`),
               or (N, chains, D) one start per chain (e.g. dispersed light directions)
    theta_std: (N, D) theta-space scale of the start jitter and of the initial metric
               (Laplace ``theta_std``); NaN or missing entries use 1
    normals:   (N, K, 3) world normals when the light direction is sampled
    timing:    run twice on the first batch to measure compilation apart (``compile_s``)
    devices:   how many of this process's devices share the pixels (None: all of them;
               :func:`jaxrefl.fit.map_sharded`, contiguous shards over a 1-D mesh).
               Every pixel has its own key, so a pixel's chains take the same random steps
               on any device; its draws agree with one device's up to rounding
    """
    opts = HMCOptions() if options is None else options
    lp = lp.for_data(data)  # drops the censored branch where nothing is censored
    n = data.obs.shape[0]
    dtype = data.obs.dtype
    t0_arr = jnp.asarray(theta0, dtype)
    if t0_arr.shape[-1] != lp.size:
        raise JaxreflError(f"theta0 must end in D = {lp.size} {lp.labels}; got {t0_arr.shape}")
    if opts.gibbs_sweeps > 0 and qualifies(lp, data)[0]:
        s = sample_gibbs(
            lp,
            data,
            jnp.broadcast_to(t0_arr, (n, lp.size)) if t0_arr.ndim < 3 else t0_arr,
            num_chains=opts.num_chains,
            num_warmup=opts.gibbs_warmup,
            num_samples=opts.num_samples,
            sweeps=opts.gibbs_sweeps * opts.thin,
            seed=seed,
        )
        s.extra["options"] = opts
        return s
    if opts.gibbs_sweeps > 0 and qualifies_width(lp, data)[0]:
        s = sample_width_gibbs(
            lp,
            data,
            jnp.broadcast_to(t0_arr, (n, lp.size)) if t0_arr.ndim < 3 else t0_arr,
            theta_std=None if theta_std is None else jnp.asarray(theta_std, dtype),
            num_chains=opts.num_chains,
            num_warmup=opts.gibbs_warmup,
            num_samples=opts.num_samples,
            sweeps=(opts.width_scans or opts.gibbs_sweeps) * opts.thin,
            seed=seed,
            devices=devices,
        )
        s.extra["options"] = opts
        return s
    per_chain = t0_arr.ndim == 3
    if per_chain:
        x = jnp.broadcast_to(t0_arr, (n, opts.num_chains, lp.size))
        ok = jnp.all(jnp.isfinite(x), axis=(-2, -1))
        x = jnp.where(ok[:, None, None], x, 0.0)
    else:
        x = jnp.broadcast_to(t0_arr, (n, lp.size))
        ok = jnp.all(jnp.isfinite(x), axis=-1)
        x = jnp.where(ok[:, None], x, 0.0)
    sd = jnp.ones((n, lp.size), dtype) if theta_std is None else jnp.asarray(theta_std, dtype)
    sd = jnp.broadcast_to(
        jnp.where(jnp.isfinite(sd) & (sd > 0), jnp.minimum(sd, 1.0), 1.0), (n, lp.size)
    )
    if normals is None:
        nrm = jnp.zeros((n, 1, 3), dtype)  # unused without a light; keeps one code path
    else:
        nrm = jnp.broadcast_to(jnp.asarray(normals, dtype), (n, data.obs.shape[1], 3))
    x = x if per_chain else jnp.broadcast_to(x[:, None, :], (n, opts.num_chains, lp.size))
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
    bad = ~np.asarray(ok)
    pos = pos.astype(np.float64)
    pos[bad] = np.nan
    nat = np.asarray(lp.natural(jnp.asarray(pos)), dtype=np.float64)
    return Samples(
        theta=pos,
        natural=nat,
        labels=lp.labels,
        stats={"acceptance_rate": acc, "diverging": div, "lp": lpd},
        method=opts.kernel,
        tuning={"step_size": step},
        compile_s=compile_s,
        run_s=run_s,
        extra={"options": opts, "no_estimate": bad, "reparam": "none" if rp is None else rp.name},
    )

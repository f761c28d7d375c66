"""The choice of sampler for a batch of pixels: :func:`sample_pixels`.

Where :class:`~jaxrefl.posterior.GibbsOptions` are given and the posterior is
linear-Gaussian in every BRDF parameter (:func:`._gibbs.qualifies`: ``pooled`` under a
co-located flash, censored observations by data augmentation), its draws are exact Gibbs
(:mod:`._gibbs`); where it is so given one lobe width (:func:`._width_layout.qualifies_width`:
the per-pixel ``ggx``), Metropolis-within-Gibbs with a collapsed proposal of the width
(:mod:`._width_gibbs`); elsewhere HMC/NUTS (:mod:`._hmc`). Every path returns
:class:`~jaxrefl.posterior.Samples` of one shape: ``HMCOptions.num_chains`` chains of
``num_samples`` draws.
"""

from __future__ import annotations

from dataclasses import replace

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import PixelData

from ._gibbs import qualifies, sample_gibbs
from ._hmc import sample_hmc
from ._logpost import LogPosterior
from ._options import GibbsOptions, HMCOptions
from ._samples import Samples
from ._width_gibbs import sample_width_gibbs
from ._width_layout import qualifies_width

__all__ = ["sample_pixels"]


def sample_pixels(
    lp: LogPosterior,
    data: PixelData,
    theta0: Float[ArrayLike, "*N D"],
    *,
    theta_std: Float[ArrayLike, "*N D"] | None = None,
    normals: Array | None = None,
    options: HMCOptions | None = None,
    gibbs: GibbsOptions | None = None,
    seed: int | None = None,
    timing: bool = False,
    devices: int | None = None,
) -> Samples:
    """Sample the posterior of every pixel of ``data`` ((N, K, C)), vmapped over pixels.

    theta0:    (N, D) or (D,) start (the LM optimum via :meth:`LogPosterior.init_theta`),
               or (N, chains, D) one start per chain (e.g. dispersed light directions)
    theta_std: (N, D) theta-space scale of the start jitter and of the initial metric
               (Laplace ``theta_std``); NaN or missing entries use 1
    normals:   (N, K, 3) world normals when the light direction is sampled
    options:   the chains and HMC (:class:`HMCOptions`; None: its defaults)
    gibbs:     Gibbs sampling where the posterior allows it (module docstring); None: HMC
    seed:      the chains' seed; None: ``options.seed``, or 0 where that is None too. Both
               given and different is refused (one seed, said once)
    timing:    HMC runs twice on the first batch to measure compilation apart
               (``compile_s``)
    devices:   how many of this process's devices share the pixels (None: all of them;
               :func:`jaxrefl.fit.map_sharded`, contiguous shards over a 1-D mesh).
               Every pixel has its own key, so a pixel's chains take the same random steps
               on any device; its draws agree with one device's up to rounding
    """
    opts = HMCOptions() if options is None else options
    if seed is not None and opts.seed is not None and seed != opts.seed:
        raise JaxreflError(
            f"sample_pixels got seed={seed} and HMCOptions.seed={opts.seed}: give one of them"
        )
    seed = seed if seed is not None else (0 if opts.seed is None else opts.seed)
    lp = lp.for_data(data)  # drops the censored branch where nothing is censored
    dtype = data.obs.dtype
    t0 = jnp.asarray(theta0, dtype)
    if t0.shape[-1] != lp.size:
        raise JaxreflError(f"theta0 must end in D = {lp.size} {lp.labels}; got {t0.shape}")
    if gibbs is not None:
        if t0.ndim < 3:
            t0 = jnp.broadcast_to(t0, (data.obs.shape[0], lp.size))
        chains = {"num_chains": opts.num_chains, "num_samples": opts.num_samples}
        warmup = gibbs.warmup(opts.num_warmup)
        s = None
        if qualifies(lp, data)[0]:
            s = sample_gibbs(
                lp,
                data,
                t0,
                num_warmup=warmup,
                sweeps=gibbs.sweeps * opts.thin,
                seed=seed,
                **chains,
            )
        elif qualifies_width(lp, data)[0]:
            s = sample_width_gibbs(
                lp,
                data,
                t0,
                theta_std=None if theta_std is None else jnp.asarray(theta_std, dtype),
                num_warmup=warmup,
                sweeps=gibbs.scans * opts.thin,
                seed=seed,
                devices=devices,
                **chains,
            )
        if s is not None:
            return replace(s, options=opts, gibbs=gibbs)
    return sample_hmc(
        lp,
        data,
        t0,
        opts,
        theta_std=theta_std,
        normals=normals,
        seed=seed,
        timing=timing,
        devices=devices,
    )

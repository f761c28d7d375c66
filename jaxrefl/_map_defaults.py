"""The uncertainty map's default settings, said once and importable without JAX.

One map, one default: :class:`jaxrefl.posterior.AdaptiveOptions` (whose ``hmc`` and
``gibbs`` defaults are :data:`jaxrefl.posterior.UNCERTAINTY_MAP_HMC`, built from
:data:`MAP_SAMPLER`, and :data:`jaxrefl.posterior.UNCERTAINTY_MAP_GIBBS`, from
:data:`MAP_GIBBS`), ``jaxrefl sample CAPTURE`` (its ``--warmup``, ``--samples``,
``--chains``, ``--gibbs-sweeps``, ``--audit``, ``--chunk`` and ``--rerun-rhat``
defaults) and the docs read these values, so a notebook user and a command-line user get
the same map from the same capture. The command line imports this module without
importing JAX (``jaxrefl --help`` stays fast).

The sampler's targets are a std and 5% / 95% quantiles per pixel, not tail probabilities:
a few short chains; HMC where it runs; Gibbs sampling where the posterior allows it (exact
Gibbs ``sweeps`` scans between kept draws, the width sampler's joint move ``width_scans``
times per kept draw). Pixels whose chains disagree (max split R-hat above
:data:`RERUN_RHAT`) run a second pass (:func:`jaxrefl.posterior.longer_options` or
:func:`jaxrefl.posterior.untuned_rerun`).
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "MAP_AUDIT",
    "MAP_CHUNK",
    "MAP_GIBBS",
    "MAP_KEEP_PIXELS",
    "MAP_SAMPLER",
    "RERUN_PASSES",
    "RERUN_RHAT",
]

#: Keyword arguments of :class:`jaxrefl.posterior.HMCOptions` for an uncertainty map.
MAP_SAMPLER: dict[str, Any] = {
    "num_warmup": 100,
    "num_samples": 100,
    "num_chains": 2,
    "num_integration_steps": 32,
    "batch_size": 128,
}
#: Keyword arguments of :class:`jaxrefl.posterior.GibbsOptions` for an uncertainty map.
MAP_GIBBS: dict[str, Any] = {"sweeps": 2, "width_scans": 1}
#: Share of the pixels Laplace calls reliable that are also sampled, to audit it.
MAP_AUDIT = 0.02
#: MCMC pixels per compiled sampler call.
MAP_CHUNK = 2048
#: The most MCMC pixels whose draws a map keeps (in memory and in ``posterior.nc``); above
#: it a seeded random subset keeps them, so a map's memory and files stop growing with the
#: capture's size (the summaries of every MCMC pixel are kept whatever the cap).
MAP_KEEP_PIXELS = 16384
#: The max split R-hat above which a map pixel's chains disagree and run the second pass:
#: the map's convergence threshold (the few short chains of :data:`MAP_SAMPLER` cannot be
#: held to Vehtari et al. 2021's 1.01; BDA3's 1.1 lets a few percent of pixels through).
RERUN_RHAT = 1.05
#: Later passes a map runs at most: the second, on the pixels above :data:`RERUN_RHAT`, and a
#: third, twice as long between kept draws, on those still above it after the second.
RERUN_PASSES = 2

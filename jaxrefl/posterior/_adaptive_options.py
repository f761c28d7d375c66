"""Settings of an uncertainty map (:class:`AdaptiveOptions`), and the map's defaults.

:data:`UNCERTAINTY_MAP_HMC` and :data:`UNCERTAINTY_MAP_GIBBS`, the default samplers of
:class:`AdaptiveOptions`, are built from :mod:`jaxrefl._map_defaults`, the one place the
library, ``jaxrefl sample CAPTURE`` and the docs read them: a map's targets are a std and
5% / 95% quantiles rather than tail probabilities, so they are cheaper than
:class:`HMCOptions`' own (fewer chains, shorter, more leapfrog steps per draw), with
adaptation still per chain and per pixel in the non-centred coordinates of
:mod:`jaxrefl.posterior._reparam`; where the posterior allows it, Gibbs sampling instead
(``benchmarks/posterior_speed.py --only-mixing`` compares the settings).

Second pass: pixels whose first-pass chains disagree (max split R-hat above
``rerun_rhat``, :data:`RERUN_RHAT` by default) run again under ``rerun_hmc`` (default
:func:`longer_options`). Where every first-pass chunk was drawn by a sampler with nothing
to tune (:data:`UNTUNED`: the width sampler, whose joint move draws the width
independently of the chain's state) and ``rerun_hmc`` is not set, the second pass is
:func:`untuned_rerun`: the first pass's settings with more scans between kept draws, whose
compiled program is the first pass's. Exact Gibbs keeps the longer second pass: its moves
along a box's edge can be slow.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from jaxrefl._errors import JaxreflError
from jaxrefl._map_defaults import (
    MAP_AUDIT,
    MAP_CHUNK,
    MAP_GIBBS,
    MAP_KEEP_PIXELS,
    MAP_SAMPLER,
    RERUN_PASSES,
)
from jaxrefl._map_defaults import RERUN_RHAT as _RERUN_RHAT
from jaxrefl._names import PRIOR_SOURCES

from ._options import GibbsOptions, HMCOptions

__all__ = [
    "RERUN_RHAT",
    "UNCERTAINTY_MAP_GIBBS",
    "UNCERTAINTY_MAP_HMC",
    "UNTUNED",
    "AdaptiveOptions",
    "MCMCPixels",
    "longer_options",
    "third_pass_options",
    "untuned_rerun",
]

#: The uncertainty map's chains and HMC (:data:`jaxrefl._map_defaults.MAP_SAMPLER`): the
#: default ``hmc`` of :class:`AdaptiveOptions`.
UNCERTAINTY_MAP_HMC = HMCOptions(**MAP_SAMPLER)
#: The uncertainty map's Gibbs sampling (:data:`jaxrefl._map_defaults.MAP_GIBBS`): the
#: default ``gibbs`` of :class:`AdaptiveOptions`.
UNCERTAINTY_MAP_GIBBS = GibbsOptions(**MAP_GIBBS)
RERUN_RHAT = _RERUN_RHAT  # the second pass's threshold (jaxrefl._map_defaults.RERUN_RHAT)
# Samplers (Samples.method) whose second pass repeats the first's settings (module
# docstring): nothing to tune, nearly independent draws.
UNTUNED = frozenset({"gibbs_mh"})


def untuned_rerun(opts: HMCOptions) -> HMCOptions:
    """The second pass's settings where the first pass had nothing to tune (:data:`UNTUNED`,
    module docstring): the first's, with twice the scans between kept draws (thin x 2). The
    scans are an argument of the width sampler's compiled program, so the first pass's
    program runs them."""
    return dataclasses.replace(opts, thin=2 * opts.thin)


def longer_options(opts: HMCOptions) -> HMCOptions:
    """The second pass's settings from the first's: twice the warm-up and thin=4 (four
    times the steps for the same kept draws), no start jitter (the starts are first-pass
    draws, already apart). ``benchmarks/posterior_speed.py --only-mixing`` compares it with
    restarts from the LM optimum and with thin 2.
    """
    return dataclasses.replace(opts, num_warmup=2 * opts.num_warmup, thin=4, init_jitter=0.0)


def third_pass_options(second: HMCOptions) -> HMCOptions:
    """The third pass's settings from the second's: twice the scans between kept draws
    (thin x 2), for the pixels whose chains still disagree after the second pass."""
    return dataclasses.replace(second, thin=2 * second.thin, init_jitter=0.0)


class MCMCPixels(enum.StrEnum):
    """Which pixels :func:`adaptive_uncertainty` samples (:attr:`AdaptiveOptions.mcmc`)."""

    FLAGGED = "flagged"  # the pixels Laplace flags, and an audit sample of the others
    ALL = "all"  # every pixel with an estimate
    NONE = "none"  # none: Laplace summaries only


@dataclass(frozen=True)
class AdaptiveOptions:
    """Settings of :func:`adaptive_uncertainty` (module docstring), immutable; derive
    variants with :func:`dataclasses.replace`.

    mcmc:        which pixels are sampled (:class:`MCMCPixels`, or its value as a string):
                 ``flagged`` (default), ``all`` or ``none``
    audit:       with ``flagged``, the fraction in [0, 1] of the reliable pixels (flag 0)
                 also sampled, ceil(audit x count), drawn at random (method 3)
    hmc:         the chains and HMC (:class:`HMCOptions`; default
                 :data:`UNCERTAINTY_MAP_HMC`, the map's: :mod:`jaxrefl._map_defaults`)
    gibbs:       Gibbs sampling where the posterior allows it (:class:`GibbsOptions`;
                 default :data:`UNCERTAINTY_MAP_GIBBS`); None: HMC everywhere
    rerun_rhat:  pixels whose first-pass max split R-hat exceeds it (or is NaN) run a
                 second, longer pass; None: no second pass
    rerun_hmc:   the second pass's settings; None: :func:`longer_options` of ``hmc``. It
                 keeps ``hmc``'s ``num_chains`` and ``num_samples`` (its draws replace the
                 first pass's); lengthen it with ``num_warmup`` and ``thin``
    rerun_passes: later passes at most (1: the second; 2, the default
                 :data:`jaxrefl._map_defaults.RERUN_PASSES`: also a third, on the pixels
                 still above ``rerun_rhat`` after the second, :func:`third_pass_options`)
    chunk:       MCMC pixels per compiled sampler call (>= 1)
    seed:        chooses the audit pixels and seeds the chains (chunk i: ``seed + i``);
                 the only seed of a map (an ``hmc`` or ``rerun_hmc`` with its own ``seed``
                 is refused)
    keep_samples: keep the draws in :attr:`UncertaintyMap.samples` (False: summaries only)
    max_kept_pixels: keep the draws of at most this many MCMC pixels (a random subset,
                 seeded by ``seed``, where more were sampled; :attr:`UncertaintyMap.kept_pixels`
                 says which); None: every MCMC pixel's. Default
                 :data:`jaxrefl._map_defaults.MAP_KEEP_PIXELS`
    workers:     chunks sampled at once, each in its own thread (None: 2 on a CPU, else 1:
                 :func:`jaxrefl._threads.default_workers`);
                 the summaries do not depend on it (chunk i is seeded ``seed + i`` wherever
                 it runs)
    time_limit_s: seconds from the call after which no MCMC chunk is started (a chunk is
                 not started where the last one's time would carry it past): the pixels
                 not sampled by then keep their Laplace summaries, with method
                 ``laplace_time_limit``; a rerun with the same chunk folder samples them
                 (resume). One process only (refused in a job of several). None: no limit
    priors:      a capture map's priors (:func:`jaxrefl.svbrdf.uncertainty_maps`): one of
                 :data:`jaxrefl._names.PRIOR_SOURCES` (``population``, the default: the
                 lobe's priors estimated from the pixels Laplace calls reliable;
                 ``default``: :func:`jaxrefl.posterior.default_priors`), or a mapping of
                 parameter names to :class:`jaxrefl.posterior.Prior`
    """

    mcmc: MCMCPixels = MCMCPixels.FLAGGED
    audit: float = MAP_AUDIT
    hmc: HMCOptions = UNCERTAINTY_MAP_HMC
    gibbs: GibbsOptions | None = UNCERTAINTY_MAP_GIBBS
    rerun_rhat: float | None = RERUN_RHAT
    rerun_hmc: HMCOptions | None = None
    rerun_passes: int = RERUN_PASSES
    chunk: int = MAP_CHUNK
    seed: int = 0
    keep_samples: bool = True
    max_kept_pixels: int | None = MAP_KEEP_PIXELS
    workers: int | None = None
    time_limit_s: float | None = None
    priors: str | Mapping[str, Any] = PRIOR_SOURCES[0]

    def __post_init__(self) -> None:
        if isinstance(self.priors, str) and self.priors not in PRIOR_SOURCES:
            raise JaxreflError(
                f"priors must be one of {PRIOR_SOURCES} or a mapping, not {self.priors!r}"
            )
        if not isinstance(self.priors, str | Mapping):
            raise JaxreflError(
                f"priors must be one of {PRIOR_SOURCES} or a mapping of parameter names to "
                f"priors, not {type(self.priors).__name__}"
            )
        try:
            object.__setattr__(self, "mcmc", MCMCPixels(self.mcmc))
        except ValueError:
            names = ", ".join(repr(m.value) for m in MCMCPixels)
            raise JaxreflError(f"mcmc must be one of {names}, not {self.mcmc!r}") from None
        if not 0.0 <= self.audit <= 1.0:
            raise JaxreflError(f"audit must be a fraction in [0, 1], got {self.audit}")
        if self.rerun_rhat is not None and not (
            math.isfinite(self.rerun_rhat) and self.rerun_rhat > 0
        ):
            raise JaxreflError(
                f"rerun_rhat must be a positive number or None, got {self.rerun_rhat}"
            )
        if self.rerun_passes not in (1, 2):
            raise JaxreflError(f"rerun_passes must be 1 or 2, got {self.rerun_passes}")
        if self.chunk < 1:
            raise JaxreflError(f"chunk must be >= 1, got {self.chunk}")
        if self.max_kept_pixels is not None and self.max_kept_pixels < 1:
            raise JaxreflError(f"max_kept_pixels must be >= 1 or None, got {self.max_kept_pixels}")
        if self.workers is not None and self.workers < 1:
            raise JaxreflError(f"workers must be >= 1 or None, got {self.workers}")
        limit = self.time_limit_s
        if limit is not None and not (
            isinstance(limit, int | float)
            and not isinstance(limit, bool)
            and math.isfinite(limit)
            and limit > 0
        ):
            raise JaxreflError(f"time_limit_s must be a positive number of seconds, got {limit}")
        for name in ("hmc", "rerun_hmc"):
            given = getattr(self, name)
            if given is not None and given.seed is not None:
                raise JaxreflError(
                    f"AdaptiveOptions.{name} has seed={given.seed}: an uncertainty map's "
                    "chains are seeded by AdaptiveOptions.seed (chunk i: seed + i); leave "
                    f"{name}.seed None and set AdaptiveOptions(seed=...)"
                )
        second = self.rerun_hmc
        if second is not None and (
            second.num_chains != self.hmc.num_chains or second.num_samples != self.hmc.num_samples
        ):
            raise JaxreflError(
                "rerun_hmc must keep the first pass's num_chains and num_samples (the "
                "draws replace the first pass's); lengthen it with num_warmup and thin"
            )

    @property
    def second_pass(self) -> HMCOptions | None:
        """The second pass's sampler settings; None when there is no second pass."""
        if self.rerun_rhat is None:
            return None
        return longer_options(self.hmc) if self.rerun_hmc is None else self.rerun_hmc

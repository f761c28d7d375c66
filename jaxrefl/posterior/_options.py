"""Settings of the pixel samplers, immutable: :class:`HMCOptions` (the chains' count and
lengths, and HMC/NUTS itself) and :class:`GibbsOptions` (where the posterior allows Gibbs
sampling instead of HMC: :mod:`._gibbs`, :mod:`._width_gibbs`).

The chains' count and lengths (``num_chains``, ``num_warmup``, ``num_samples``, ``thin``)
are :class:`HMCOptions`' whichever sampler :func:`~jaxrefl.posterior.sample_pixels` picks,
so a map's pixels keep one shape of draws.

The chains' seed: ``HMCOptions.seed`` is for a call that samples one problem on its own
(:func:`~jaxrefl.posterior.sample_pixels`, :func:`jaxrefl.measured.sample_posterior`); None
leaves it to the caller (``sample_pixels``' ``seed``, 0 by default). An uncertainty map
seeds its chunks from :attr:`AdaptiveOptions.seed` (chunk i: ``seed + i``), so
:class:`~jaxrefl.posterior.AdaptiveOptions` refuses an ``HMCOptions`` with a seed rather
than ignore it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from jaxrefl._errors import JaxreflError

__all__ = ["GibbsOptions", "HMCOptions"]


@dataclass(frozen=True)
class HMCOptions:
    """Settings of the chains and of HMC/NUTS (:mod:`jaxrefl.posterior._hmc`); ``seed``: the
    chains' seed where one call samples on its own (module docstring; None: the caller's)."""

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
    # the metric update (``benchmarks/posterior_speed.py --only-window`` compares the two).
    metric_window_end: float = 0.75
    # Coordinates the chains move in (:mod:`jaxrefl.posterior._reparam`): "albedo", the
    # diffuse albedo non-centred on its conditional given the other parameters; "none",
    # the fit's theta; "auto", "albedo" where the model is affine in a bounded albedo.
    reparam: Literal["auto", "albedo", "none"] = "auto"
    # Keep every thin-th draw: ``num_samples`` draws are kept of num_samples * thin steps
    # (acceptance averaged over, and divergences counted in, the steps between). Used by
    # the longer second pass of adaptive_uncertainty, whose draws keep the first's shape.
    thin: int = 1
    seed: int | None = None

    def __post_init__(self):
        if self.seed is not None and (
            isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0
        ):
            raise JaxreflError(f"seed must be an integer >= 0 or None, got {self.seed!r}")
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


@dataclass(frozen=True)
class GibbsOptions:
    """Gibbs sampling where the posterior allows it (:func:`jaxrefl.posterior.sample_pixels`).

    sweeps:          scans between kept draws (times ``HMCOptions.thin``) of exact Gibbs,
                     where the posterior is linear-Gaussian in every BRDF parameter
                     (:mod:`jaxrefl.posterior._gibbs`: ``pooled`` under a co-located flash)
    width_scans:     scans between kept draws (times ``thin``) of the width sampler, where
                     it is so given one lobe width (:mod:`jaxrefl.posterior._width_gibbs`:
                     the per-pixel ``ggx``); each scan makes a joint move of the width and
                     the linear parameters and a Gibbs sweep of the latter. None: ``sweeps``
    warmup_fraction: kept-draw intervals discarded, as a fraction of
                     ``HMCOptions.num_warmup`` (at least 1): there is no step size or metric
                     to tune, and the chains start at the fit's optimum, inside the bulk
    """

    sweeps: int = 2
    width_scans: int | None = None
    warmup_fraction: float = 0.2

    def __post_init__(self):
        if self.sweeps < 1:
            raise JaxreflError(f"sweeps must be >= 1, got {self.sweeps}")
        if self.width_scans is not None and self.width_scans < 1:
            raise JaxreflError(f"width_scans must be >= 1 or None, got {self.width_scans}")
        if not 0.0 < self.warmup_fraction <= 1.0:
            f = self.warmup_fraction
            raise JaxreflError(f"warmup_fraction must be in (0, 1], got {f}")

    def warmup(self, num_warmup: int) -> int:
        """Kept-draw intervals of warm-up for ``HMCOptions.num_warmup`` steps of HMC's."""
        return max(1, round(num_warmup * self.warmup_fraction))

    @property
    def scans(self) -> int:
        """Scans between kept draws of the width sampler."""
        return self.width_scans or self.sweeps

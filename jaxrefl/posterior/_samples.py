"""Posterior draws of pixels (:class:`Samples`): what every sampler of
:mod:`jaxrefl.posterior` returns (HMC/NUTS, exact Gibbs, the width sampler, emcee), and
its slicing by pixel (a chunk's real pixels, chunks joined, pixels overwritten by a second
pass)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from ._options import GibbsOptions, HMCOptions

if TYPE_CHECKING:  # _emcee returns Samples: the type of its run facts is named for mypy only
    from ._emcee import EmceeRun

__all__ = ["Samples"]


def _no_pixels() -> np.ndarray:
    return np.zeros(0, bool)


@dataclass
class Samples:
    """Posterior draws of N pixels (N = 1 for a single problem).

    theta:   (N, chains, draws, D) unconstrained draws
    natural: (N, chains, draws, D) natural values, named by ``labels``
    stats:   per-draw sample statistics (N, chains, draws): ``acceptance_rate``,
             ``diverging`` (bool), ``lp`` (log density)
    tuning:  per-chain tuned settings, e.g. ``step_size`` (N, chains)
    method:  ``"hmc"``, ``"nuts"``, ``"gibbs"`` (exact Gibbs), ``"gibbs_mh"`` (the width
             sampler) or ``"emcee"``
    compile_s, run_s: time of compilation (first call minus a warm one, or of tracing),
             and of the sampling itself
    no_estimate: (N,) bool, the pixels without an estimate (a non-finite start: their
             draws are NaN); left empty, it is all False (every pixel has one)
    reparam: the coordinates HMC ran in (``"albedo"``, or ``"none"``: theta itself); the
             draws are theta's whatever it names
    options: the :class:`HMCOptions` that ran (HMC, or the chain counts of a Gibbs
             sampler); None where no HMC settings ran (emcee, a chunk read from disk)
    gibbs:   the :class:`GibbsOptions` where a Gibbs sampler drew the pixels, else None
    sweeps:  the Gibbs sweeps (or width scans) between kept draws, else None
    emcee:   emcee's run facts (:class:`jaxrefl.posterior._emcee.EmceeRun`: tau, burn-in,
             thinning, the convergence verdict), else None
    """

    theta: np.ndarray
    natural: np.ndarray
    labels: tuple[str, ...]
    stats: dict[str, np.ndarray]
    method: str
    tuning: dict[str, np.ndarray] = field(default_factory=dict)
    compile_s: float = float("nan")
    run_s: float = float("nan")
    no_estimate: np.ndarray = field(default_factory=_no_pixels)
    reparam: str = "none"
    options: HMCOptions | None = None
    gibbs: GibbsOptions | None = None
    sweeps: int | None = None
    emcee: EmceeRun | None = None

    def __post_init__(self) -> None:
        ne = np.asarray(self.no_estimate, bool)
        # left empty: every pixel has an estimate
        self.no_estimate = ne if ne.size else np.zeros(self.theta.shape[0], bool)

    @property
    def n_pixels(self) -> int:
        return int(self.theta.shape[0])

    def flat(self, pixel: int = 0) -> np.ndarray:
        """(chains * draws, D) natural draws of one pixel."""
        x = self.natural[pixel]
        return x.reshape(-1, x.shape[-1])

    def take(self, m: int | np.ndarray) -> Samples:
        """The first ``m`` pixels (an int: drops the padding of a chunk), or the pixels at
        the indices ``m`` (an integer array)."""
        at = slice(None, m) if isinstance(m, int) else np.asarray(m, dtype=np.int64)
        return replace(
            self,
            theta=self.theta[at],
            natural=self.natural[at],
            stats={k: v[at] for k, v in self.stats.items()},
            tuning={k: v[at] for k, v in self.tuning.items()},
            no_estimate=self.no_estimate[at],
        )

    @classmethod
    def concat(cls, parts: list[Samples]) -> Samples:
        """Chunks' draws joined along the pixel axis; ``method`` names every sampler that
        drew a part (exact Gibbs and HMC chunks can meet in one map: ``"gibbs+hmc"``), the
        run time is their sum, and the other settings (labels, compile time, ``reparam``,
        ``options``, ``gibbs``, ``sweeps``, ``emcee``) are the first part's."""
        if len(parts) == 1:
            return parts[0]
        p0 = parts[0]
        cat = np.concatenate
        return replace(
            p0,
            theta=cat([p.theta for p in parts]),
            natural=cat([p.natural for p in parts]),
            stats={k: cat([p.stats[k] for p in parts]) for k in p0.stats},
            method="+".join(dict.fromkeys(p.method for p in parts)),
            tuning={k: cat([p.tuning[k] for p in parts]) for k in p0.tuning},
            run_s=float(sum(p.run_s for p in parts)),
            no_estimate=cat([p.no_estimate for p in parts]),
        )

    def put(self, at: list[int], cut: Samples) -> None:
        """Overwrite pixels ``at`` with ``cut``'s (same chains and draws), in place."""

        def put(a, b):
            a = a if a.flags.writeable else a.copy()  # arrays from JAX are read-only views
            a[at] = b
            return a

        self.theta = put(self.theta, cut.theta)
        self.natural = put(self.natural, cut.natural)
        self.stats = {k: put(v, cut.stats[k]) for k, v in self.stats.items()}
        self.tuning = {k: put(v, cut.tuning[k]) for k, v in self.tuning.items()}

"""Posterior draws of pixels (:class:`Samples`): what every sampler of
:mod:`jaxrefl.posterior` returns (HMC/NUTS, exact Gibbs, the width sampler, emcee), and
its slicing by pixel (a chunk's real pixels, chunks joined, pixels overwritten by a second
pass)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Samples"]


@dataclass
class Samples:
    """Posterior draws of N pixels (N = 1 for a single problem).

    theta:   (N, chains, draws, D) unconstrained draws
    natural: (N, chains, draws, D) natural values, named by ``labels``
    stats:   per-draw sample statistics (N, chains, draws): ``acceptance_rate``,
             ``diverging`` (bool), ``lp`` (log density)
    tuning:  per-chain tuned settings, e.g. ``step_size`` (N, chains)
    method:  ``"hmc"``, ``"nuts"`` or ``"emcee"``
    compile_s, run_s: time of compilation (first call minus a warm one, or of tracing),
             and of the sampling itself
    """

    theta: np.ndarray
    natural: np.ndarray
    labels: tuple[str, ...]
    stats: dict[str, np.ndarray]
    method: str
    tuning: dict[str, np.ndarray] = field(default_factory=dict)
    compile_s: float = float("nan")
    run_s: float = float("nan")
    extra: dict[str, Any] = field(default_factory=dict)

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
        return Samples(
            theta=self.theta[at],
            natural=self.natural[at],
            labels=self.labels,
            stats={k: v[at] for k, v in self.stats.items()},
            method=self.method,
            tuning={k: v[at] for k, v in self.tuning.items()},
            compile_s=self.compile_s,
            run_s=self.run_s,
            extra={**self.extra, "no_estimate": self.extra["no_estimate"][at]},
        )

    @classmethod
    def concat(cls, parts: list[Samples]) -> Samples:
        """Chunks' draws joined along the pixel axis; ``method`` names every sampler that
        drew a part (exact Gibbs and HMC chunks can meet in one map: ``"gibbs+hmc"``)."""
        if len(parts) == 1:
            return parts[0]
        p0 = parts[0]
        cat = np.concatenate
        return cls(
            theta=cat([p.theta for p in parts]),
            natural=cat([p.natural for p in parts]),
            labels=p0.labels,
            stats={k: cat([p.stats[k] for p in parts]) for k in p0.stats},
            method="+".join(dict.fromkeys(p.method for p in parts)),
            tuning={k: cat([p.tuning[k] for p in parts]) for k in p0.tuning},
            compile_s=p0.compile_s,
            run_s=float(sum(p.run_s for p in parts)),
            extra={**p0.extra, "no_estimate": cat([p.extra["no_estimate"] for p in parts])},
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

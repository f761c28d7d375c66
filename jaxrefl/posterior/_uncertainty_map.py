"""The result of an uncertainty map (:class:`UncertaintyMap`): per-pixel posterior
summaries, the method that produced each pixel's (:data:`METHODS`), MCMC diagnostics, and
its JSON report.

====  ==============  ===============================================================
code  name            summary from
====  ==============  ===============================================================
0     ``none``         nothing: the pixel had no estimate (masked / non-finite)
1     ``laplace``      the Laplace Gaussian in theta, pushed through the bijections
2     ``mcmc``         MCMC: Laplace was flagged unreliable there
3     ``mcmc_audit``   MCMC on a random audit pixel that Laplace called reliable
4     ``laplace_time_limit``  the Laplace Gaussian: the pixel was chosen for MCMC, but the
                      map's time limit (``deadline``) came first
====  ==============  ===============================================================
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from jaxrefl._map_defaults import RERUN_RHAT
from jaxrefl.fit import LaplaceFlag

from ._methods import MCMC_METHODS, Method
from ._samples import Samples

__all__ = ["METHODS", "UncertaintyMap", "mcmc_reasons"]

METHODS = {int(m): m.name.lower() for m in Method}


@dataclass
class UncertaintyMap:
    """Per-pixel posterior summaries (N pixels, D = ``len(labels)``).

    mean, std, q05, q95: (N, D) natural units; method: (N,) uint8 (:data:`METHODS`);
    rhat, ess_bulk, ess_tail: (N,) max R-hat / min ESS over parameters (NaN off MCMC);
    divergences: (N,) count (0 off MCMC); mcmc_pixels: indices of the sampled pixels
    (those without censored observations first); samples: the draws of the pixels
    ``kept_pixels`` (a subset of ``mcmc_pixels`` in its order, at most
    ``AdaptiveOptions.max_kept_pixels``; None: every MCMC pixel's); laplace_std: (N, D)
    the Laplace std everywhere (NaN where none);
    rerun: (N,) bool, the pixel's numbers come from a later pass (second or third);
    rhat_first: (N,) its first pass's max R-hat (NaN where no second pass ran); reasons:
    why the pixels chosen for MCMC were (:func:`mcmc_reasons`)
    """

    labels: tuple[str, ...]
    mean: np.ndarray
    std: np.ndarray
    q05: np.ndarray
    q95: np.ndarray
    method: np.ndarray
    rhat: np.ndarray
    ess_bulk: np.ndarray
    ess_tail: np.ndarray
    divergences: np.ndarray
    mcmc_pixels: np.ndarray
    samples: Samples | None
    laplace_std: np.ndarray
    rerun: np.ndarray
    rhat_first: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    reasons: dict[str, int] = field(default_factory=dict)
    kept_pixels: np.ndarray | None = None

    @property
    def sample_pixels(self) -> np.ndarray:
        """Indices of the pixels whose draws :attr:`samples` holds, in its order."""
        return self.mcmc_pixels if self.kept_pixels is None else self.kept_pixels

    @property
    def audit_std_ratio(self) -> np.ndarray:
        """(A, D) Laplace std / MCMC std on the audit pixels (method 3)."""
        a = self.method == Method.MCMC_AUDIT
        return self.laplace_std[a] / self.std[a]

    def method_counts(self) -> dict[str, int]:
        return {name: int(np.sum(self.method == code)) for code, name in METHODS.items()}

    def report(self) -> dict[str, Any]:
        """JSON-ready summary: counts by method, MCMC diagnostics, audit ratios, timings."""
        on = np.isin(self.method, MCMC_METHODS)

        def dist(v):
            v = v[np.isfinite(v)]
            if v.size == 0:
                return None
            q = np.quantile(v, [0.0, 0.05, 0.5, 0.95, 1.0])
            return dict(zip(("min", "q05", "median", "q95", "max"), q.tolist(), strict=True))

        ratio = self.audit_std_ratio
        audit = {lab: dist(ratio[:, j]) for j, lab in enumerate(self.labels) if ratio.shape[0] > 0}
        return {
            "labels": list(self.labels),
            "pixels": int(self.method.size),
            "method_counts": self.method_counts(),
            "method_codes": {str(k): v for k, v in METHODS.items()},
            "mcmc": {
                "pixels": int(np.sum(on)),
                "max_rhat": dist(self.rhat[on]),
                "min_ess_bulk": dist(self.ess_bulk[on]),
                "min_ess_tail": dist(self.ess_tail[on]),
                "pixels_rhat_above_1.01": int(np.sum(self.rhat[on] > 1.01)),
                # 1.1: the looser threshold of Gelman et al. (BDA3, sec. 11.4), one a map's
                # short chains can be held to; 1.01 is Vehtari et al. 2021's.
                "pixels_rhat_above_1.1": int(np.sum(self.rhat[on] > 1.1)),
                # RERUN_RHAT: the threshold the maps are held to
                f"pixels_rhat_above_{RERUN_RHAT:g}": int(np.sum(self.rhat[on] > RERUN_RHAT)),
                # NaN: a parameter whose draws did not vary (no R-hat); counted apart
                "pixels_rhat_nan": int(np.sum(np.isnan(self.rhat[on]))),
                # the pixels whose draws are kept (posterior.nc): at most max_kept_pixels
                "pixels_with_draws": int(self.sample_pixels.size) if self.samples else 0,
                "pixels_with_divergences": int(np.sum(self.divergences[on] > 0)),
                "divergences": int(np.sum(self.divergences[on])),
                "second_pass": {
                    "pixels": int(np.sum(self.rerun)),
                    "max_rhat_before": dist(self.rhat_first[self.rerun]),
                    "max_rhat_after": dist(self.rhat[self.rerun]),
                    f"pixels_rhat_above_{RERUN_RHAT:g}_after": int(
                        np.sum(self.rhat[self.rerun] > RERUN_RHAT)
                    ),
                    "pixels_rhat_above_1.1_after": int(np.sum(self.rhat[self.rerun] > 1.1)),
                },
                # the second pass's pixels still above the threshold, run once more
                "third_pass": {
                    "pixels": int(self.timings.get("third_pass_pixels", 0)),
                    "skipped": self.timings.get("third_pass_skipped", ""),
                    f"pixels_rhat_above_{RERUN_RHAT:g}_after": int(
                        self.timings.get("third_pass_rhat_above_after", 0)
                    ),
                },
            },
            "audit_laplace_over_mcmc_std": audit,
            "mcmc_reasons": dict(self.reasons),
            "timings": self.timings,
        }


def mcmc_reasons(method: np.ndarray, flag: np.ndarray, no_summary: np.ndarray) -> dict[str, int]:
    """Why the pixels chosen for MCMC were: per :class:`jaxrefl.fit.LaplaceFlag` bit the
    MCMC pixels (method ``mcmc``, or ``laplace_time_limit`` where the time limit came first)
    whose flag has it (a pixel may count under several), ``NO_FINITE_SUMMARY`` those without
    a flag whose Laplace marginals have no finite std (a Student t of <= 2 degrees of
    freedom), ``audit`` the pixels Laplace calls reliable that were sampled all the same
    (the random audit sample; with ``mcmc="all"`` every one). The report's
    ``mcmc_reasons``: where a map's time goes and why."""
    chosen = np.isin(method, (Method.MCMC, Method.LAPLACE_TIME_LIMIT))
    f = np.asarray(flag)
    out = {b.name or str(b.value): int(np.sum(chosen & ((f & b.value) != 0))) for b in LaplaceFlag}
    out["NO_FINITE_SUMMARY"] = int(np.sum(chosen & (f == 0) & no_summary))
    audit = method == Method.MCMC_AUDIT
    out["audit"] = int(np.sum(audit))
    return out

"""Simulation-based calibration (SBC): is a sampler's posterior the posterior?

Talts et al. 2018, *Validating Bayesian inference algorithms with simulation-based
calibration* (arXiv:1804.06788): draw theta_s from the prior, simulate data y_s, draw M
posterior samples given y_s. If the sampler is right, the rank of theta_s among its M
(independent) draws is uniform on {0, ..., M}, for every parameter. A posterior too wide
piles ranks in the middle, one too narrow at both ends, a biased one on one side.

* :func:`ranks`: rank statistics (S, D) from truths (S, D) and draws (S, M, D). MCMC
  draws must be close to independent: :func:`thin` picks M draws spread over the chains
  (thin to about the ESS).
* :func:`uniformity`: Pearson chi-square of the rank histogram against uniform (B bins of
  equal width, p-value from the chi-square(B - 1) tail) and the Kolmogorov–Smirnov
  distance of the normalised ranks (asymptotic p-value, Stephens' 1970 correction).
* :func:`pit`: the continuous analogue for a Gaussian approximation (Laplace): u = Phi((x
  - mean) / sd), uniform on [0, 1] when calibrated.
* :func:`coverage`: the fraction of truths inside the central 50% / 90% credible
  intervals, with its binomial standard error sqrt(q (1 - q) / S).

Power: a posterior over-dispersed by 20% (sd 1.2x) covers the truth in its central 90%
interval with probability P(|z| < 1.645 * 1.2) = 0.952 instead of 0.90, and its ranks
follow Phi(z / 1.2): with S = 1000 simulations both the chi-square on 10 bins and the
coverage are rejected at far beyond 3 sigma (``tests/test_posterior_sbc.py`` shows it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from jax.scipy.special import gammaincc

from jaxrefl._errors import JaxreflError

__all__ = ["SBCResult", "coverage", "pit", "ranks", "sbc_summary", "thin", "uniformity"]


def ranks(truth: np.ndarray, draws: np.ndarray) -> np.ndarray:
    """(S, D) number of draws (S, M, D) below the truth (S, D), in {0, ..., M}."""
    truth = np.asarray(truth)
    draws = np.asarray(draws)
    return np.sum(draws < truth[:, None, :], axis=1)


def thin(draws: np.ndarray, m: int) -> np.ndarray:
    """(S, m, D) draws spread evenly over chains and draws of (S, chains, n, D)."""
    s, c, n, d = draws.shape
    flat = np.swapaxes(draws, 1, 2).reshape(s, c * n, d)  # interleave the chains
    idx = np.linspace(0, c * n - 1, m).round().astype(int)
    return flat[:, idx]


def _chi2_sf(stat: float, dof: int) -> float:
    return float(gammaincc(dof / 2.0, stat / 2.0))


def _ks_sf(d: float, n: int) -> float:
    """Asymptotic Kolmogorov tail P(D_n > d) with Stephens' (1970) small-n correction."""
    sn = math.sqrt(n)
    lam = (sn + 0.12 + 0.11 / sn) * d
    if lam < 0.2:
        return 1.0
    terms = [(-1) ** (k - 1) * math.exp(-2.0 * k * k * lam * lam) for k in range(1, 101)]
    return float(min(1.0, max(0.0, 2.0 * sum(terms))))


def uniformity(u: np.ndarray, bins: int = 10) -> dict[str, np.ndarray]:
    """Tests of uniformity of values in [0, 1] (S, D), per column.

    For discrete ranks r in {0..M} pass ``(r + 0.5) / (M + 1)`` (what :func:`sbc_summary`
    does). Returns ``chi2`` and ``chi2_p`` (bins - 1 dof), ``ks`` and ``ks_p`` as (D,).
    """
    u = np.asarray(u, dtype=np.float64)
    if u.ndim == 1:
        u = u[:, None]
    s, d = u.shape
    chi2 = np.empty(d)
    chi2_p = np.empty(d)
    ks = np.empty(d)
    ks_p = np.empty(d)
    expected = s / bins
    for j in range(d):
        col = np.sort(u[:, j])
        counts = np.histogram(col, bins=bins, range=(0.0, 1.0))[0]
        chi2[j] = float(np.sum((counts - expected) ** 2 / expected))
        chi2_p[j] = _chi2_sf(chi2[j], bins - 1)
        i = np.arange(1, s + 1)
        ks[j] = float(max(np.max(i / s - col), np.max(col - (i - 1) / s)))
        ks_p[j] = _ks_sf(ks[j], s)
    return {"chi2": chi2, "chi2_p": chi2_p, "ks": ks, "ks_p": ks_p}


def pit(truth: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """Probability integral transform Phi((truth - mean) / std) of a Gaussian posterior."""
    z = (np.asarray(truth) - np.asarray(mean)) / np.asarray(std)
    return 0.5 * (1.0 + np.vectorize(math.erf)(z / math.sqrt(2.0)))


def coverage(
    truth: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(D,) fraction of truths in [lower, upper] ((S, D) each) and its binomial std error."""
    inside = (np.asarray(truth) >= lower) & (np.asarray(truth) <= upper)
    q = inside.mean(axis=0)
    return q, np.sqrt(np.maximum(q * (1 - q), 1e-12) / inside.shape[0])


@dataclass
class SBCResult:
    """Calibration of one method over S simulations (D parameters, named by ``labels``).

    u:        (S, D) normalised ranks or PIT values in [0, 1]
    tests:    :func:`uniformity` of u
    coverage: level -> (fraction (D,), std error (D,)) of the central interval
    """

    labels: tuple[str, ...]
    u: np.ndarray
    tests: dict[str, np.ndarray]
    coverage: dict[float, tuple[np.ndarray, np.ndarray]]

    @property
    def n(self) -> int:
        return int(self.u.shape[0])

    def coverage_z(self, level: float) -> np.ndarray:
        """(D,) (observed - nominal) coverage in units of the nominal binomial std error."""
        q = self.coverage[level][0]
        return (q - level) / math.sqrt(level * (1 - level) / self.n)

    def to_dict(self) -> dict:
        return {
            "n_simulations": self.n,
            "labels": list(self.labels),
            **{k: v.tolist() for k, v in self.tests.items()},
            "coverage": {str(k): v[0].tolist() for k, v in self.coverage.items()},
            "coverage_z": {str(k): self.coverage_z(k).tolist() for k in self.coverage},
        }


def sbc_summary(
    truth: np.ndarray,
    draws: np.ndarray | None = None,
    *,
    mean: np.ndarray | None = None,
    std: np.ndarray | None = None,
    labels: tuple[str, ...] = (),
    bins: int = 10,
    levels: tuple[float, ...] = (0.5, 0.9),
) -> SBCResult:
    """SBC of sample draws (S, M, D), or of a Gaussian (``mean``, ``std`` (S, D)).

    The truth lies in the central interval of level q when its normalised rank u is within
    q / 2 of 1/2: for draws that is the interval between the ranked draws (exact for
    (M + 1) q an integer, e.g. M = 19 for 50% and 90%: sample quantiles of few draws
    would be too narrow), for a Gaussian mean +- z_q sd. Parameters with a monotone
    bijection may be given in either coordinates (ranks are invariant); a Gaussian must
    be given in the coordinates where it is Gaussian (theta for Laplace).
    """
    truth = np.asarray(truth, dtype=np.float64)
    cov: dict[float, tuple[np.ndarray, np.ndarray]] = {}
    if draws is not None:
        draws = np.asarray(draws, dtype=np.float64)
        m = draws.shape[1]
        u = (ranks(truth, draws) + 0.5) / (m + 1)
    else:
        if mean is None or std is None:
            raise JaxreflError("give draws, or mean and std of a Gaussian")
        u = pit(truth, mean, std)
    for lv in levels:
        cov[lv] = coverage(np.abs(u - 0.5), np.zeros_like(u), np.full_like(u, lv / 2))
    labels = labels or tuple(f"p{j}" for j in range(truth.shape[-1]))
    return SBCResult(tuple(labels), u, uniformity(u, bins), cov)

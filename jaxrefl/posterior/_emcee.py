"""emcee's affine-invariant ensemble sampler for single-material and small global problems,
run until its chain is long enough to trust.

The log-probability is compiled once and evaluated for all walkers in one call
(``vectorize=True``: emcee hands it a (walkers, D) array). Walkers start in a small ball
about the LM optimum (``scale`` times the Laplace theta-space std, or 1e-2).

Stopping rule (:func:`autocorr_check`, :func:`convergence`): every ``check_every`` steps
the integrated autocorrelation time tau of every parameter is estimated on the whole chain
(Sokal's windowed estimator over the walkers' mean autocorrelation,
``emcee.autocorr.integrated_time``, the estimator of emcee's ``get_autocorr_time``). The
run stops once the chain is at least ``n_tau`` (default 50) times the largest tau long,
emcee's own reliability rule (``tol``), *and* the kept draws reach the diagnostic targets:
rank-normalised split R-hat <= ``max_rhat`` and bulk ESS >= ``min_ess`` for every
parameter (Vehtari et al. 2021, computed as ArviZ does, walkers as chains). It stops at
``max_steps`` otherwise, and the result says why it is not converged
(:class:`Convergence`). Kept draws: the first ``burn_factor * max tau`` steps are dropped
and the chains thinned by ``max(1, tau_min / 2)``, as emcee's documentation recommends.

Walkers of an ensemble are not independent chains; ArviZ treats each walker as a chain,
so R-hat over walkers is a (conservative) mixing check, not Gelman–Rubin's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import emcee
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import PixelData

from ._fastdiag import ess_bulk, rhat_rank
from ._samples import Samples

__all__ = [
    "Convergence",
    "EmceeOptions",
    "EmceeRun",
    "autocorr_check",
    "convergence",
    "sample_emcee",
]

MAX_RHAT = 1.01  # Vehtari et al. (2021) recommend R-hat < 1.01 before using the draws
MIN_ESS = 400.0  # and a bulk ESS of at least 100 per chain of 4 (stable quantiles)


@dataclass(frozen=True)
class EmceeOptions:
    """Settings of :func:`sample_emcee` (module docstring), immutable.

    n_walkers:   walkers of the ensemble; None: max(32, 2 D + 2) for D parameters
    max_steps:   the cap on steps of every walker (>= 1); the run stops earlier once converged
    check_every: steps between convergence checks (>= 1)
    n_tau:       the chain must be at least this many times the largest tau long (> 0)
    max_rhat:    the largest split R-hat accepted (>= 1)
    min_ess:     the smallest bulk ESS accepted (>= 0)
    scale:       the start ball's radius in units of the theta-space std (> 0)
    burn_factor: the burn-in, in units of the largest tau (>= 0; at most half the run)
    seed:        seeds the start ball and emcee's moves (>= 0): the same seed, the same draws
    """

    n_walkers: int | None = None
    max_steps: int = 30_000
    check_every: int = 500
    n_tau: float = 50.0
    max_rhat: float = MAX_RHAT
    min_ess: float = MIN_ESS
    scale: float = 0.5
    burn_factor: float = 2.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.n_walkers is not None and self.n_walkers < 2:
            raise JaxreflError(f"n_walkers must be >= 2, got {self.n_walkers}")
        if self.max_steps < 1:
            raise JaxreflError(f"max_steps must be >= 1, got {self.max_steps}")
        if self.check_every < 1:
            raise JaxreflError(f"check_every must be >= 1, got {self.check_every}")
        if not self.n_tau > 0:
            raise JaxreflError(f"n_tau must be positive, got {self.n_tau}")
        if not self.max_rhat >= 1:
            raise JaxreflError(f"max_rhat must be >= 1, got {self.max_rhat}")
        if not self.min_ess >= 0:
            raise JaxreflError(f"min_ess must be >= 0, got {self.min_ess}")
        if not self.scale > 0:
            raise JaxreflError(f"scale must be positive, got {self.scale}")
        if not self.burn_factor >= 0:
            raise JaxreflError(f"burn_factor must be >= 0, got {self.burn_factor}")
        if not (isinstance(self.seed, int | np.integer) and self.seed >= 0):
            raise JaxreflError(f"seed must be an integer >= 0, got {self.seed!r}")


@dataclass(frozen=True)
class Convergence:
    """Whether a chain may be trusted, and why not (:func:`convergence`).

    converged:    True when every target is met (``reasons`` empty)
    reasons:      one line per target missed, e.g. "chain of 3000 steps is 20 tau (needs 50)"
    tau:          (D,) integrated autocorrelation times in steps (emcee); empty for HMC
    n_steps:      the chain's length in steps per walker (per chain for HMC)
    max_rhat:     the largest split R-hat over parameters
    min_ess_bulk: the smallest bulk ESS over parameters
    """

    converged: bool
    reasons: tuple[str, ...]
    tau: tuple[float, ...]
    n_steps: int
    max_rhat: float
    min_ess_bulk: float

    def to_dict(self) -> dict:
        """JSON-ready: every field, ``reasons`` as a list."""
        return {
            "converged": self.converged,
            "reasons": list(self.reasons),
            "tau": list(self.tau),
            "max_tau": max(self.tau) if self.tau else None,
            "chain_length": self.n_steps,
            "max_rhat": self.max_rhat,
            "min_ess_bulk": self.min_ess_bulk,
        }


@dataclass(frozen=True)
class EmceeRun:
    """What one :func:`sample_emcee` run did (:attr:`Samples.emcee`).

    tau:          (D,) integrated autocorrelation times in steps at the stop
    burn, thin:   the steps dropped at the start, and the step between kept draws
    tau_reliable: whether the chain is at least ``n_tau`` times the largest tau long
    acceptance:   the walkers' mean acceptance fraction
    n_steps:      the chain's length in steps per walker
    n_walkers:    walkers of the ensemble
    max_steps:    the cap on steps the run had (:attr:`EmceeOptions.max_steps`)
    convergence:  the verdict at the stop (:class:`Convergence`)
    """

    tau: tuple[float, ...]
    burn: int
    thin: int
    tau_reliable: bool
    acceptance: float
    n_steps: int
    n_walkers: int
    max_steps: int
    convergence: Convergence


def autocorr_check(
    chain: Float[ArrayLike, "steps walkers D"], n_tau: float = 50.0
) -> tuple[np.ndarray, bool]:
    """(tau (D,), long enough): emcee's integrated autocorrelation time of every parameter
    of ``chain`` and whether the chain is at least ``n_tau`` times the largest tau long
    (``emcee.autocorr.integrated_time(chain, tol=n_tau)``, which refuses shorter chains)."""
    x = np.asarray(chain, dtype=np.float64)
    if x.ndim != 3:
        raise JaxreflError(f"chain must be (steps, walkers, D), got shape {x.shape}")
    try:
        return np.asarray(emcee.autocorr.integrated_time(x, tol=n_tau)), True
    except emcee.autocorr.AutocorrError as err:  # shorter than n_tau * tau: tau in err.tau
        return np.asarray(err.tau, dtype=np.float64), False


def convergence(
    draws: Float[ArrayLike, "chains draws D"],
    *,
    tau: Float[ArrayLike, " D"] | None = None,
    n_steps: int | None = None,
    n_tau: float = 50.0,
    max_rhat: float = MAX_RHAT,
    min_ess: float = MIN_ESS,
    labels: tuple[str, ...] = (),
) -> Convergence:
    """The verdict on kept ``draws`` (chains, draws, D): split R-hat <= ``max_rhat`` and
    bulk ESS >= ``min_ess`` for every parameter; with ``tau`` (emcee) also a chain of
    ``n_steps`` >= ``n_tau`` * max tau. ``labels`` name the parameters in the reasons."""
    x = np.moveaxis(np.asarray(draws, dtype=np.float64), -1, 0)  # (D, chains, draws)
    d = x.shape[0]
    names = labels or tuple(f"theta{i}" for i in range(d))
    n = int(x.shape[-1] if n_steps is None else n_steps)
    rhat, ess = rhat_rank(x), ess_bulk(x)
    reasons = []
    t = () if tau is None else tuple(float(v) for v in np.asarray(tau))
    if t and not n >= n_tau * max(t):
        j = int(np.argmax(t))
        reasons.append(
            f"chain of {n} steps is {n / t[j]:.1f} tau of {names[j]} (tau {t[j]:.0f} steps; "
            f"needs {n_tau:g})"
        )
    if not np.all(rhat <= max_rhat):  # NaN counts as missed
        j = int(np.nanargmax(rhat)) if np.any(np.isfinite(rhat)) else 0
        reasons.append(f"R-hat of {names[j]} is {rhat[j]:.3f} (needs <= {max_rhat:g})")
    if not np.all(ess >= min_ess):
        j = int(np.nanargmin(ess)) if np.any(np.isfinite(ess)) else 0
        reasons.append(f"bulk ESS of {names[j]} is {ess[j]:.0f} (needs >= {min_ess:g})")
    return Convergence(
        converged=not reasons,
        reasons=tuple(reasons),
        tau=t,
        n_steps=n,
        max_rhat=float(np.max(rhat)),
        min_ess_bulk=float(np.min(ess)),
    )


@eqx.filter_jit
def _log_prob_walkers(logdensity, x, args):
    return jax.vmap(lambda t: logdensity(t, *args))(x)


def sample_emcee(
    logdensity,
    theta0: Float[ArrayLike, " D"],
    args: tuple = (),
    options: EmceeOptions | None = None,
    *,
    natural=None,
    labels: tuple[str, ...] = (),
    theta_std: Float[ArrayLike, " D"] | None = None,
    progress: bool = False,
) -> Samples:
    """Run emcee on ``logdensity(theta (D,), *args) -> scalar`` (a JAX function or an
    equinox Module such as :class:`LogPosterior`; compiled once per structure and shapes,
    so repeated calls with new ``args`` (data) of the same shapes do not recompile) until
    converged or ``max_steps`` (module docstring).

    theta0:  (D,) start (e.g. :meth:`LogPosterior.init_theta` of the LM optimum)
    options: :class:`EmceeOptions` (None: its defaults), the seed included
    natural: maps theta draws (..., D) to natural values (e.g. ``LogPosterior.natural``);
             R-hat and ESS are judged on the natural values
    theta_std: (D,) the start ball's shape (e.g. the Laplace std; None: 1e-2 everywhere)
    progress: a tqdm bar over the steps (to stderr)
    Returns :class:`Samples` with N = 1, walkers as chains (after burn-in and thinning);
    ``emcee`` holds the run's facts (:class:`EmceeRun`: tau, burn-in, thinning, the
    convergence verdict).
    """
    if args and isinstance(args[0], PixelData) and hasattr(logdensity, "for_data"):
        logdensity = logdensity.for_data(args[0])  # drops the unused censored branch
    x0 = np.asarray(theta0, dtype=np.float64)
    d = x0.size
    o = EmceeOptions() if options is None else options
    n_walkers = max(32, 2 * d + 2) if o.n_walkers is None else int(o.n_walkers)
    dtype = jnp.asarray(0.0).dtype
    names = tuple(labels) or tuple(f"theta{i}" for i in range(d))

    def log_prob(x: np.ndarray) -> np.ndarray:
        out = np.asarray(_log_prob_walkers(logdensity, x.astype(dtype), args), np.float64)
        return np.where(np.isnan(out), -np.inf, out)

    def to_natural(theta: np.ndarray) -> np.ndarray:
        return theta if natural is None else np.asarray(natural(jnp.asarray(theta)), np.float64)

    rng = np.random.default_rng(o.seed)
    sd = np.full(d, 1e-2) if theta_std is None else np.asarray(theta_std, dtype=np.float64)
    sd = np.where(np.isfinite(sd) & (sd > 0), np.minimum(sd, 1.0), 1e-2)
    p0 = x0 + o.scale * sd * rng.normal(size=(n_walkers, d))
    t0 = time.perf_counter()
    log_prob(p0)  # compile
    compile_s = time.perf_counter() - t0
    sampler = emcee.EnsembleSampler(n_walkers, d, log_prob, vectorize=True)
    sampler.random_state = np.random.RandomState(o.seed).get_state()  # reproducible moves
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=o.max_steps, desc="emcee steps", unit="step")
    t1 = time.perf_counter()
    state, done = p0, 0
    while True:
        n = min(o.check_every, o.max_steps - done)
        for step in sampler.sample(state, iterations=n):
            state = step  # the last one carries on
            if bar is not None:
                bar.update(1)
        done += n
        chain = sampler.get_chain()  # (steps, walkers, D)
        tau, long_enough = autocorr_check(chain, o.n_tau)
        burn = min(int(np.ceil(o.burn_factor * np.max(tau))), done // 2)
        thin = max(1, int(0.5 * np.min(tau)))
        kept = np.swapaxes(chain[burn::thin], 0, 1)  # (walkers, draws, D)
        verdict = convergence(
            to_natural(kept),
            tau=tau,
            n_steps=done,
            n_tau=o.n_tau,
            max_rhat=o.max_rhat,
            min_ess=o.min_ess,
            labels=names,
        )
        if verdict.converged or done >= o.max_steps:
            break
    if bar is not None:
        bar.close()
    run_s = time.perf_counter() - t1
    lp = sampler.get_log_prob()[burn::thin]
    theta = kept[None]  # (1, walkers, draws, D)
    nat = to_natural(theta)
    acc = np.broadcast_to(sampler.acceptance_fraction[None, :, None], theta.shape[:3])
    return Samples(
        theta=theta,
        natural=nat,
        labels=names,
        stats={
            "acceptance_rate": np.array(acc),
            "diverging": np.zeros(theta.shape[:3], bool),
            "lp": np.swapaxes(lp, 0, 1)[None],
        },
        method="emcee",
        compile_s=compile_s,
        run_s=run_s,
        emcee=EmceeRun(
            tau=tuple(float(t) for t in tau),
            burn=burn,
            thin=thin,
            tau_reliable=long_enough,
            acceptance=float(np.mean(sampler.acceptance_fraction)),
            n_steps=done,
            n_walkers=n_walkers,
            max_steps=o.max_steps,
            convergence=verdict,
        ),
    )

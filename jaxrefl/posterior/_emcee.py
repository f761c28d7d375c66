"""emcee's affine-invariant ensemble sampler for single-material and small global problems.

The log-probability is compiled once and evaluated for all walkers in one call
(``vectorize=True``: emcee hands it a (walkers, D) array). Walkers start in a small ball
about the LM optimum (``scale`` times the Laplace theta-space std, or 1e-2). After the run
the integrated autocorrelation time tau of every parameter is estimated
(Sokal's windowed estimator, ``emcee.autocorr.integrated_time``); the first
``burn_factor * max tau`` steps are dropped and the chains are thinned by
``max(1, tau_min / 2)``, as emcee's documentation recommends. When the run is shorter than
``50 tau`` the estimate is unreliable: the result says so (``tau_reliable``) instead of
raising.

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

from jaxrefl.fit import PixelData

from ._batched import Samples

__all__ = ["EmceeOptions", "sample_emcee"]


@dataclass(frozen=True)
class EmceeOptions:
    """Settings of :func:`sample_emcee` (module docstring), immutable.

    n_walkers:   walkers of the ensemble; None: max(32, 2 D + 2) for D parameters
    n_steps:     steps of every walker (>= 1); at least 50 tau for a reliable tau
    scale:       the start ball's radius in units of the theta-space std (> 0)
    burn_factor: the burn-in, in units of the largest tau (>= 0; at most half the run)
    """

    n_walkers: int | None = None
    n_steps: int = 2000
    scale: float = 0.5
    burn_factor: float = 2.0

    def __post_init__(self) -> None:
        if self.n_walkers is not None and self.n_walkers < 2:
            raise ValueError(f"n_walkers must be >= 2, got {self.n_walkers}")
        if self.n_steps < 1:
            raise ValueError(f"n_steps must be >= 1, got {self.n_steps}")
        if not self.scale > 0:
            raise ValueError(f"scale must be positive, got {self.scale}")
        if not self.burn_factor >= 0:
            raise ValueError(f"burn_factor must be >= 0, got {self.burn_factor}")


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
    seed: int = 0,
) -> Samples:
    """Run emcee on ``logdensity(theta (D,), *args) -> scalar`` (a JAX function or an
    equinox Module such as :class:`LogPosterior`; compiled once per structure and shapes,
    so repeated calls with new ``args`` (data) of the same shapes do not recompile).

    theta0:  (D,) start (e.g. :meth:`LogPosterior.init_theta` of the LM optimum)
    options: :class:`EmceeOptions` (None: its defaults)
    natural: maps theta draws (..., D) to natural values (e.g. ``LogPosterior.natural``)
    theta_std: (D,) the start ball's shape (e.g. the Laplace std; None: 1e-2 everywhere)
    Returns :class:`Samples` with N = 1, walkers as chains (after burn-in and thinning);
    ``extra`` holds ``tau``, ``burn``, ``thin``, ``tau_reliable`` and ``acceptance``.
    """
    if args and isinstance(args[0], PixelData) and hasattr(logdensity, "for_data"):
        logdensity = logdensity.for_data(args[0])  # drops the unused censored branch
    x0 = np.asarray(theta0, dtype=np.float64)
    d = x0.size
    o = EmceeOptions() if options is None else options
    n_walkers = max(32, 2 * d + 2) if o.n_walkers is None else int(o.n_walkers)
    n_steps, burn_factor = o.n_steps, o.burn_factor
    dtype = jnp.asarray(0.0).dtype

    def log_prob(x: np.ndarray) -> np.ndarray:
        out = np.asarray(_log_prob_walkers(logdensity, jnp.asarray(x, dtype), args), np.float64)
        return np.where(np.isnan(out), -np.inf, out)

    rng = np.random.default_rng(seed)
    sd = np.full(d, 1e-2) if theta_std is None else np.asarray(theta_std, dtype=np.float64)
    sd = np.where(np.isfinite(sd) & (sd > 0), np.minimum(sd, 1.0), 1e-2)
    p0 = x0 + o.scale * sd * rng.normal(size=(n_walkers, d))
    t0 = time.perf_counter()
    log_prob(p0)  # compile
    compile_s = time.perf_counter() - t0
    sampler = emcee.EnsembleSampler(n_walkers, d, log_prob, vectorize=True)
    sampler.random_state = np.random.RandomState(seed).get_state()  # reproducible moves
    t1 = time.perf_counter()
    sampler.run_mcmc(p0, n_steps, progress=progress)
    run_s = time.perf_counter() - t1
    chain = sampler.get_chain()  # (steps, walkers, D)
    tau = emcee.autocorr.integrated_time(chain, quiet=True, tol=50)
    reliable = bool(n_steps >= 50 * np.max(tau))
    burn = min(int(np.ceil(burn_factor * np.max(tau))), n_steps // 2)
    thin = max(1, int(0.5 * np.min(tau)))
    kept = chain[burn::thin]  # (draws, walkers, D)
    lp = sampler.get_log_prob()[burn::thin]
    theta = np.swapaxes(kept, 0, 1)[None]  # (1, walkers, draws, D)
    nat = theta if natural is None else np.asarray(natural(jnp.asarray(theta)), np.float64)
    acc = np.broadcast_to(sampler.acceptance_fraction[None, :, None], theta.shape[:3])
    return Samples(
        theta=theta,
        natural=nat,
        labels=tuple(labels) or tuple(f"theta{i}" for i in range(d)),
        stats={
            "acceptance_rate": np.array(acc),
            "diverging": np.zeros(theta.shape[:3], bool),
            "lp": np.swapaxes(lp, 0, 1)[None],
        },
        method="emcee",
        compile_s=compile_s,
        run_s=run_s,
        extra={
            "tau": tau.tolist(),
            "burn": burn,
            "thin": thin,
            "tau_reliable": reliable,
            "acceptance": float(np.mean(sampler.acceptance_fraction)),
            "n_steps": n_steps,
            "n_walkers": n_walkers,
        },
    )

"""Adaptive inference: Laplace everywhere, MCMC where Laplace is not to be trusted.

The Laplace approximation (:func:`jaxrefl.fit.laplace`) costs about one LM iteration per
pixel; its flags (:class:`jaxrefl.fit.LaplaceFlag`) say where the Gaussian is the wrong
shape: a parameter at a bound, a parameter the data do not pin down, a singular
curvature. :func:`adaptive_uncertainty` keeps the Laplace summary on the pixels flagged
reliable (flag 0), runs the batched HMC sampler (:func:`~jaxrefl.posterior.sample_pixels`)
on every pixel with a flag, and also on a random *audit* sample of the reliable ones
(fraction ``audit``) so that the Laplace summaries are checked against MCMC on the same
run (:attr:`UncertaintyMap.audit_std_ratio`). ``method`` records per pixel which method
produced its numbers:

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

Laplace summaries in natural units: ``mean`` is the optimum x* = g(theta*), ``std`` the
delta-method std theta_std |g'(theta*)|, and the quantiles g(theta* + z_q theta_std)
(exact quantiles of the pushed-forward marginal, since g is monotone per entry). z_q is the
normal quantile where the noise scale is known and the Student t quantile of the pixel's
degrees of freedom where the fit estimated it (``dof``, :func:`laplace_summary`), whose
std is then theta_std sqrt(dof / (dof - 2)).
MCMC summaries are the draws' mean, std and empirical 5% / 95% quantiles.

Every setting is one immutable :class:`AdaptiveOptions`: which pixels are sampled
(``mcmc``, ``audit``), the sampler (``hmc``, an :class:`HMCOptions`), the second pass
(``rerun_rhat``, ``rerun_hmc``), the chunk size, the seed and whether draws are kept.

Large maps: the MCMC pixels run in chunks of at most ``chunk`` pixels, of one balanced
size (:func:`_chunk_size`; the last one padded by repeating pixels, whose results are
dropped), so the sampler compiles once for the whole map whatever the number of flagged
pixels (twice where some have censored observations and some none: pixels without any go
first and skip the censored likelihood branch, see :meth:`LogPosterior.for_data`), and
memory stays bounded. :data:`MAP_OPTIONS`, the default sampler of :class:`AdaptiveOptions`
(defined once for the library, the command line and the docs in
:mod:`jaxrefl._map_defaults`), is a cheaper setting than :class:`HMCOptions`' own, since a
map's targets are a std and 5% / 95% quantiles rather than tail probabilities: 2 chains of 100
warm-up and 100 kept steps of 32 leapfrog steps (1/4 of the gradients of the default
:class:`HMCOptions`), adaptation still per chain and per pixel (the Laplace std is the
initial metric), in the non-centred coordinates of :mod:`jaxrefl.posterior._reparam`
(``reparam="auto"``): the flagged pixels are mostly those where no highlight was seen,
whose posterior is a long curved ridge that chains in the fit's coordinates do not cross
(``benchmarks/posterior_speed.py --only-mixing`` compares the settings).
``keep_samples=False`` keeps only the summaries (a 256 x 256 map's draws are ~1 GB).
Where a chunk's posterior is linear-Gaussian in every BRDF parameter (``pooled`` under a
co-located flash, censored observations included: :mod:`jaxrefl.posterior._gibbs`),
:data:`MAP_OPTIONS` (``gibbs_sweeps=2``) draws it exactly by Gibbs sampling instead of HMC,
two scans between kept draws; where it is so given the lobe width (the per-pixel ``ggx``,
``beckmann``, ``ggx_rgb``: :mod:`jaxrefl.posterior._width_gibbs`), by Metropolis-within-
Gibbs whose joint move draws the width from its marginal. A map can hold chunks of
several (its samples' ``method`` is then e.g. ``"gibbs+hmc"``; the report's
``timings.sampler`` names them).

Chunks at once: a process samples :attr:`AdaptiveOptions.workers` chunks at a time, each in
its own thread (:mod:`jaxrefl.posterior._workers`: on a CPU one compiled program leaves
part of the cores idle), the first chunk alone since it compiles; chunk i is seeded
``seed + i`` wherever it runs, so the map does not depend on ``workers``. ``timings``
keeps both the summed seconds of the chunks' samplers (``mcmc_s``, ``rerun_s``) and each
pass's wall time (``mcmc_wall_s``, ``rerun_wall_s``).

Chunks on disk and across processes: with ``chunk_dir`` each chunk's draws are written
there as it finishes (a file named by the pass, a fingerprint of the pixels, sampler
settings and seed, and the chunk's index), and a rerun reads the chunks it finds rather
than sampling them (resume). In a job of several processes (:class:`jaxrefl.fit.Distributed`)
chunk i is sampled by process i mod n, with seed ``seed + i`` as in one process; after a
barrier every process reads every chunk in order and computes the same summaries and
second-pass starts, so the map does not depend on the number of processes. Within a
process, :func:`~jaxrefl.posterior.sample_pixels` spreads a chunk over the process's
devices.

Bounded time and progress: with a ``deadline`` (a :func:`time.perf_counter` value) a chunk
is not started where the last finished chunk's wall time would carry it past the deadline
(the first chunk runs unless the deadline has passed); its pixels keep their Laplace
summaries, with method ``laplace_time_limit``, and a second-pass chunk that is not started
leaves its pixels their first pass's draws. Chunks already written to ``chunk_dir`` are read
on a rerun, so a map stopped by its time limit resumes where it stopped. ``log`` (a function
of one line of text) hears each pass's start and end and, every :data:`HEARTBEAT_S` seconds
while a pass runs, the chunks done and an estimate of the time left.

Second pass: a pixel whose first-pass chains disagree (max split R-hat above
``rerun_rhat``, :data:`RERUN_RHAT` = 1.05 by default: the convergence threshold the maps
are held to) runs again under ``rerun_hmc`` (default
:func:`longer_options`: twice the warm-up, four times the steps between kept draws). Its
chains start from draws of the first pass, chain c from first-pass chain c mod C, so they
begin apart and on the posterior's ridge, with the first pass's draw std as the initial
metric. Where every first-pass chunk was drawn by the width sampler
(:mod:`jaxrefl.posterior._width_gibbs`, :data:`UNTUNED`) and ``rerun_hmc`` is not set, the
second pass (:func:`untuned_rerun`) runs the first pass's settings with twice the scans
between kept draws and a new seed, in chunks of the first pass's size: its joint move draws
the width independently of the chain's state, so its draws are nearly independent and need
no longer warm-up, and the compiled program of the first pass is reused (a rerun of a few
pixels in a new shape would compile a new one, which costs more than sampling a whole
chunk). Exact Gibbs keeps the longer second pass:
its moves along a box's edge can be slow (``benchmarks/posterior_speed.py``). The second
pass's summaries and draws replace the first's (``rerun`` marks those pixels and
``rhat_first`` keeps the first pass's R-hat, so ``report()`` shows what it changed).
Pixels still above the threshold after it stay marked by their ``rhat``: read their std
as a lower bound.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from jaxrefl._errors import JaxreflError
from jaxrefl._map_defaults import MAP_AUDIT, MAP_CHUNK, MAP_SAMPLER
from jaxrefl._map_defaults import RERUN_RHAT as _RERUN_RHAT
from jaxrefl.fit import LaplaceFlag, PixelData, process_barrier, process_share

from ._batched import HMCOptions, sample_pixels
from ._diagnostics import diagnostics
from ._logpost import LogPosterior
from ._methods import MCMC_METHODS, Method
from ._samples import Samples
from ._workers import default_workers, in_order

__all__ = [
    "HEARTBEAT_S",
    "MAP_OPTIONS",
    "METHODS",
    "RERUN_RHAT",
    "AdaptiveOptions",
    "MCMCPixels",
    "UncertaintyMap",
    "adaptive_uncertainty",
    "laplace_summary",
    "longer_options",
    "untuned_rerun",
]

METHODS = {int(m): m.name.lower() for m in Method}
# Samplers (Samples.method) whose second pass repeats the first's settings (module
# docstring): nothing to tune, nearly independent draws.
UNTUNED = frozenset({"gibbs_mh"})
_Z95 = 1.6448536269514722  # standard normal 95% quantile
#: The uncertainty map's sampler (:data:`jaxrefl._map_defaults.MAP_SAMPLER`, module
#: docstring): the default ``hmc`` of :class:`AdaptiveOptions`.
MAP_OPTIONS = HMCOptions(**MAP_SAMPLER)
RERUN_RHAT = _RERUN_RHAT  # the second pass's threshold (jaxrefl._map_defaults.RERUN_RHAT)
HEARTBEAT_S = 30.0  # seconds between the progress lines of a pass (module docstring)
_RERUN_SEED = 100_003  # offsets the second pass's seeds from the first's chunk seeds


def untuned_rerun(opts: HMCOptions) -> HMCOptions:
    """The second pass's settings where the first pass had nothing to tune (:data:`UNTUNED`,
    module docstring): the first's, with twice the scans between kept draws (thin x 2). The
    scans are an argument of the width sampler's compiled program, so the first pass's
    program runs them."""
    return dataclasses.replace(opts, thin=2 * opts.thin)


def longer_options(opts: HMCOptions) -> HMCOptions:
    """The second pass's settings from the first's: twice the warm-up and thin=4 (four
    times the steps for the same kept draws), no start jitter (the starts are first-pass
    draws, already apart). On MAP_OPTIONS (100 + 100 steps) a pixel costs 3x its first
    pass (200 + 4 x 100 steps). ``benchmarks/posterior_speed.py --only-mixing`` compares
    it with restarts from the LM optimum and with thin 2.
    """
    return dataclasses.replace(opts, num_warmup=2 * opts.num_warmup, thin=4, init_jitter=0.0)


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
    hmc:         the sampler's settings (:class:`HMCOptions`; default :data:`MAP_OPTIONS`,
                 the map's: :mod:`jaxrefl._map_defaults`)
    rerun_rhat:  pixels whose first-pass max split R-hat exceeds it (or is NaN) run a
                 second, longer pass; None: no second pass
    rerun_hmc:   the second pass's settings; None: :func:`longer_options` of ``hmc``. It
                 keeps ``hmc``'s ``num_chains`` and ``num_samples`` (its draws replace the
                 first pass's); lengthen it with ``num_warmup`` and ``thin``
    chunk:       MCMC pixels per compiled sampler call (>= 1)
    seed:        chooses the audit pixels and seeds the chains (chunk i: ``seed + i``)
    keep_samples: keep the draws in :attr:`UncertaintyMap.samples` (False: summaries only)
    workers:     chunks sampled at once, each in its own thread (None: :func:`default_workers`);
                 the summaries do not depend on it (chunk i is seeded ``seed + i`` wherever
                 it runs)
    """

    mcmc: MCMCPixels = MCMCPixels.FLAGGED
    audit: float = MAP_AUDIT
    hmc: HMCOptions = MAP_OPTIONS
    rerun_rhat: float | None = RERUN_RHAT
    rerun_hmc: HMCOptions | None = None
    chunk: int = MAP_CHUNK
    seed: int = 0
    keep_samples: bool = True
    workers: int | None = None

    def __post_init__(self) -> None:
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
        if self.chunk < 1:
            raise JaxreflError(f"chunk must be >= 1, got {self.chunk}")
        if self.workers is not None and self.workers < 1:
            raise JaxreflError(f"workers must be >= 1 or None, got {self.workers}")
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


@dataclass
class UncertaintyMap:
    """Per-pixel posterior summaries (N pixels, D = ``len(labels)``).

    mean, std, q05, q95: (N, D) natural units; method: (N,) uint8 (:data:`METHODS`);
    rhat, ess_bulk, ess_tail: (N,) max R-hat / min ESS over parameters (NaN off MCMC);
    divergences: (N,) count (0 off MCMC); mcmc_pixels: indices of the sampled pixels,
    in the order of ``samples`` (those without censored observations first);
    samples: their draws; laplace_std: (N, D) the Laplace std everywhere (NaN where none);
    rerun: (N,) bool, the pixel's numbers come from the second pass; rhat_first: (N,) its
    first pass's max R-hat (NaN where no second pass ran); reasons: why the pixels chosen
    for MCMC were (:func:`mcmc_reasons`)
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
                # 1.1: the looser threshold of Gelman et al. (BDA3, sec. 11.4), the one a
                # 200-draw map chain can be held to; 1.01 is Vehtari et al. 2021's.
                "pixels_rhat_above_1.1": int(np.sum(self.rhat[on] > 1.1)),
                # 1.05: RERUN_RHAT, the threshold the maps are held to
                "pixels_rhat_above_1.05": int(np.sum(self.rhat[on] > 1.05)),
                # NaN: a parameter whose draws did not vary (no R-hat); counted apart
                "pixels_rhat_nan": int(np.sum(np.isnan(self.rhat[on]))),
                "pixels_with_divergences": int(np.sum(self.divergences[on] > 0)),
                "divergences": int(np.sum(self.divergences[on])),
                "second_pass": {
                    "pixels": int(np.sum(self.rerun)),
                    "max_rhat_before": dist(self.rhat_first[self.rerun]),
                    "max_rhat_after": dist(self.rhat[self.rerun]),
                    "pixels_rhat_above_1.05_after": int(np.sum(self.rhat[self.rerun] > 1.05)),
                    "pixels_rhat_above_1.1_after": int(np.sum(self.rhat[self.rerun] > 1.1)),
                },
            },
            "audit_laplace_over_mcmc_std": audit,
            "mcmc_reasons": dict(self.reasons),
            "timings": self.timings,
        }


def laplace_summary(
    lp: LogPosterior,
    theta_hat: np.ndarray,
    theta_std: np.ndarray,
    dof: np.ndarray | None = None,
):
    """(mean, std, q05, q95) in natural units of the Laplace marginals in theta (module
    docstring); the BRDF entries only (P of them).

    dof: (N,) degrees of freedom of each pixel's marginals, or None. Where the noise scale
    was estimated from the pixel's own residuals (n - P degrees of freedom), the marginal of
    theta_j under the Jeffreys prior on the scale is a Student t with scale theta_std, not a
    Gaussian (Gelman et al., *BDA3*, sec. 14.2): the quantiles are theta* +- t_{0.95, dof}
    theta_std and the std is theta_std sqrt(dof / (dof - 2)), pushed through the bijection
    as above. inf (or None): the Gaussian of a known scale. A finite dof <= 2 has no
    finite variance: those pixels get NaN here, and :func:`adaptive_uncertainty` samples
    them."""
    space = lp.space
    t = jnp.asarray(np.nan_to_num(theta_hat))
    n = np.shape(theta_hat)[0]
    nu = np.full(n, np.inf) if dof is None else np.asarray(dof, np.float64).reshape(n)
    t_ok = np.isfinite(nu) & (nu > 2)
    # Quantile and std factor per pixel: Student t where dof is finite, normal where inf.
    z = np.full(n, _Z95)
    z[t_ok] = stats.t.ppf(0.95, nu[t_ok])
    inflate = np.ones(n)
    inflate[t_ok] = np.sqrt(nu[t_ok] / (nu[t_ok] - 2.0))
    s = jnp.asarray(np.nan_to_num(theta_std))
    mean = np.array(space.natural_vector(t))
    std = np.array(s * jnp.abs(space.dnatural(t))) * inflate[:, None]
    q05 = np.array(space.natural_vector(t - z[:, None] * s))
    q95 = np.array(space.natural_vector(t + z[:, None] * s))
    bad = ~(np.all(np.isfinite(theta_hat), -1) & np.all(np.isfinite(theta_std), -1))
    bad |= ~(t_ok | np.isposinf(nu))
    for a in (mean, std, q05, q95):
        a[bad] = np.nan
    return mean, std, q05, q95


def adaptive_uncertainty(
    lp: LogPosterior,
    data: PixelData,
    theta_hat: np.ndarray,
    theta_std: np.ndarray,
    flag: np.ndarray,
    options: AdaptiveOptions | None = None,
    *,
    noise_scale: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    dof: np.ndarray | None = None,
    progress: bool = False,
    chunk_dir: str | Path | None = None,
    deadline: float | None = None,
    log: Callable[[str], None] | None = None,
) -> UncertaintyMap:
    """Laplace on every pixel, MCMC on the flagged ones and an audit sample (module doc).

    theta_hat: (N, P) the LM optimum (NaN: no estimate); theta_std: (N, P) Laplace
    theta-space std; flag: (N,) Laplace flags (:class:`jaxrefl.fit.LaplaceFlag`);
    options: :class:`AdaptiveOptions` (None: its defaults). noise_scale: (N,) starting
    noise scale when ``lp`` samples it (e.g. the Laplace residual std); normals: (N, 3)
    when ``lp`` samples a light. dof: (N,) degrees of freedom of the Laplace marginals
    (:func:`laplace_summary`: Student t where finite, e.g. n - P where the fit estimated
    each pixel's noise scale; None: Gaussian); a pixel whose finite dof is <= 2 is sampled
    as if flagged (its t marginal has no variance). progress: a tqdm bar over the chunks.
    chunk_dir: a folder where each MCMC chunk's draws are written when sampled and read
    back on a rerun (resume); required in a job of several processes (module docstring),
    which exchange their chunks there. deadline: a :func:`time.perf_counter` value after
    which no MCMC chunk is started (module docstring; not in a job of several processes).
    log: called with a line of text at each pass's start and end and every
    :data:`HEARTBEAT_S` seconds during a pass.
    """
    o = AdaptiveOptions() if options is None else options
    if chunk_dir is None and jax.process_count() > 1:
        raise JaxreflError(
            "adaptive_uncertainty in a job of several processes needs chunk_dir: a folder "
            "every process can read and write (the processes exchange their chunks there)"
        )
    if deadline is not None and jax.process_count() > 1:
        raise JaxreflError(
            "a time limit applies to one process: in a job of several processes every "
            "process samples its share of the chunks (drop the time limit)"
        )
    theta_hat = np.asarray(theta_hat, dtype=np.float64)
    theta_std = np.asarray(theta_std, dtype=np.float64)
    flag = np.asarray(flag).astype(np.int64)
    has = np.all(np.isfinite(theta_hat), axis=-1) & ((flag & LaplaceFlag.NO_ESTIMATE) == 0)
    t0 = time.perf_counter()
    mean, std, q05, q95 = laplace_summary(lp, theta_hat, theta_std, dof)
    rng = np.random.default_rng(o.seed)  # the audit pixels, then the second pass's starts
    unreliable = (flag != 0) | (has & np.any(np.isnan(std), -1))
    method = _choose_methods(has, unreliable, o, rng)
    reasons = mcmc_reasons(method, flag, has & np.any(np.isnan(std), -1))
    timings = {"laplace_summary_s": time.perf_counter() - t0}
    out = _Summaries.from_laplace(mean, std, q05, q95, lp.size)
    idx = np.flatnonzero(np.isin(method, MCMC_METHODS))
    # Pixels without censored observations first: their chunks run the cheaper posterior
    # without the censored branch (LogPosterior.for_data); at most one chunk is mixed.
    censored_px = np.any(np.asarray(data.censored)[idx] != 0, axis=(-2, -1))
    idx = idx[np.argsort(censored_px, kind="stable")]
    samples = None
    if idx.size:
        extra = lp.size - theta_hat.shape[1]
        s0_all = None if noise_scale is None else np.asarray(noise_scale)

        def first_starts(rows):
            s0 = None if s0_all is None else s0_all[rows]
            th0 = lp.init_theta(jnp.asarray(theta_hat[rows]), noise_scale=s0)
            return th0, np.concatenate([theta_std[rows], np.ones((rows.size, extra))], -1)

        folder = None if chunk_dir is None else Path(chunk_dir)
        run = _Run(lp, data, normals, o, progress, timings, folder, deadline, log)
        samples, restart = run.first_pass(idx, first_starts, out, rng)
        run.second_pass(idx, restart, out, samples)
        if run.skipped:
            left = np.concatenate(run.skipped)
            method[left] = Method.LAPLACE_TIME_LIMIT
            idx = idx[~np.isin(idx, left)]
    return UncertaintyMap(
        labels=lp.labels,
        mean=out.mean,
        std=out.std,
        q05=out.q05,
        q95=out.q95,
        method=method,
        rhat=out.rhat,
        ess_bulk=out.ess_bulk,
        ess_tail=out.ess_tail,
        divergences=out.divergences,
        mcmc_pixels=idx,
        samples=samples,
        laplace_std=out.laplace_std,
        rerun=out.rerun,
        rhat_first=out.rhat_first,
        timings=timings,
        reasons=reasons,
    )


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


@dataclass
class _Run:
    """The MCMC passes of one :func:`adaptive_uncertainty` call (module docstring)."""

    lp: LogPosterior
    data: PixelData
    normals: np.ndarray | None
    o: AdaptiveOptions
    progress: bool
    timings: dict[str, Any]
    folder: Path | None = None
    deadline: float | None = None
    log: Callable[[str], None] | None = None
    skipped: list[np.ndarray] = field(default_factory=list)  # first-pass pixels not sampled

    @property
    def workers(self) -> int:
        return default_workers() if self.o.workers is None else self.o.workers

    def first_pass(self, idx, starts, out: _Summaries, rng):
        """Sample the pixels ``idx``; returns their draws (None unless ``keep_samples``)
        and, per pixel whose chains disagree, its second-pass starts."""
        o, tm = self.o, self.timings
        second = o.second_pass
        restart: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        parts, run_s, used = [], [], []
        t0 = time.perf_counter()
        for real, cut, rs in self._chunks(idx, starts, o.hmc, o.seed, "MCMC first pass", "first"):
            if cut is None:  # the time limit came first: Laplace summaries stay
                self.skipped.append(real)
                continue
            run_s.append(rs)
            used.append(cut.method)
            out.store(real, cut)
            if second is not None:  # draws kept for the second pass's starts only
                # NaN R-hat (a chain that never moved) counts as disagreeing
                stuck = ~(out.rhat[real] <= o.rerun_rhat) & ~cut.extra["no_estimate"]
                for j in np.flatnonzero(stuck):
                    restart[int(real[j])] = _restarts(cut, int(j), second.num_chains, rng)
            if o.keep_samples:
                parts.append(cut)
        tm["mcmc_s"] = float(np.sum(run_s))
        tm["mcmc_wall_s"] = time.perf_counter() - t0
        tm["mcmc_pixels"] = int(idx.size) - sum(r.size for r in self.skipped)
        tm["mcmc_chunks"] = len(run_s)
        if self.deadline is not None:
            tm["time_limit_pixels_left"] = sum(r.size for r in self.skipped)
        tm["sampler"] = "+".join(dict.fromkeys(used))  # each chunk's (Samples.method)
        tm["mcmc_chunk_size"] = _chunk_size(int(idx.size), o.chunk, o.hmc.batch_size, self.workers)
        if len(run_s) > 1:
            # the first chunk compiles; the others reuse it
            tm["mcmc_compile_s"] = max(0.0, run_s[0] - float(np.median(run_s[1:])))
            tm["mcmc_chunk_s_median"] = float(np.median(run_s[1:]))
        return (Samples.concat(parts) if o.keep_samples and parts else None), restart

    def second_pass(self, idx, restart, out: _Summaries, samples: Samples | None) -> None:
        """Sample the pixels of ``restart`` again from their starts under the second
        pass's settings; their summaries and draws replace the first pass's."""
        second = self.o.second_pass
        if second is None or not restart:
            return
        size = None
        used = set(str(self.timings.get("sampler", "")).split("+"))
        if self.o.rerun_hmc is None and used and used <= UNTUNED:
            second = untuned_rerun(self.o.hmc)  # the same program (module docstring)
            size = int(self.timings["mcmc_chunk_size"])
            self.timings["rerun_settings"] = "untuned"
        again = idx[np.isin(idx, np.fromiter(restart, int))]  # first pass's order
        out.rhat_first[again] = out.rhat[again]

        def starts(rows):
            return tuple(np.stack([restart[int(i)][k] for i in rows]) for k in (0, 1))

        run_s = []
        t0 = time.perf_counter()
        at = {int(i): k for k, i in enumerate(idx)}
        seed = self.o.seed + _RERUN_SEED
        left = 0
        for real, cut, rs in self._chunks(
            again, starts, second, seed, "MCMC second pass", "second", size
        ):
            if cut is None:  # the time limit came first: the first pass's draws stay
                out.rhat_first[real] = np.nan
                left += real.size
                continue
            run_s.append(rs)
            out.store(real, cut)
            out.rerun[real] = True
            if samples is not None:
                samples.put([at[int(i)] for i in real], cut)
        if self.deadline is not None:
            self.timings["time_limit_second_pass_left"] = left
        self.timings["rerun_s"] = float(np.sum(run_s))
        self.timings["rerun_wall_s"] = time.perf_counter() - t0
        self.timings["rerun_pixels"] = int(again.size) - left

    def _chunks(self, idx, starts, opts: HMCOptions, seed: int, desc: str, tag: str, size=None):
        """Sample the pixels ``idx`` in chunks of one compiled size (module docstring).

        size: pixels per chunk (None: the fewest balanced chunks of at most ``chunk``).
        starts(rows) -> (theta0 (R, D) or (R, chains, D), theta_std (R, D)) for the map's
        pixels ``rows``. Yields (real pixels, their Samples, run seconds) in chunk order.
        With a folder, a chunk found there is read rather than sampled, and a sampled one
        is written; with several processes each samples its share (chunk i: process
        i mod n), and after a barrier every process reads all of them.
        """
        if size is None:
            size = _chunk_size(idx.size, self.o.chunk, opts.batch_size, self.workers)
        firsts = list(range(0, idx.size, size))
        many = jax.process_count() > 1
        mine = set(process_share(list(range(len(firsts)))))
        # A chunk file belongs to these pixels, starts of this pass, sampler settings and
        # parameter box only (the draws' theta is in the box's unconstrained coordinates):
        # its name carries their fingerprint, so another run's chunks never match.
        name = None
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
            space = self.lp.space
            box = (self.lp.labels, tuple(space.lower.tolist()), tuple(space.upper.tolist()))
            key = _fingerprint(tag, idx, opts, seed, size, box)
            name = lambda ci: self.folder / f"{tag}_{key}_{ci:05d}.npz"  # noqa: E731
        bar = None
        if self.progress and jax.process_index() == 0:
            from tqdm.auto import tqdm

            bar = tqdm(total=len(firsts), desc=desc, unit="chunk")

        pace = _Pace(desc, len(firsts), int(idx.size), self.log, self.workers)

        def get(ci: int) -> tuple[Samples, float] | _Skipped | None:
            real = idx[firsts[ci] : firsts[ci] + size]
            got = None if name is None else _load_chunk(name(ci), real.size, self.lp.labels)
            if got is None and ci in mine:
                if pace.too_late(self.deadline):
                    return _SKIPPED
                t0 = time.perf_counter()
                got = self._sample(real, size, starts, opts, seed + ci)
                if name is not None:
                    _save_chunk(name(ci), *got)
                pace.took(time.perf_counter() - t0)
            return got

        try:
            with pace:
                for ci, got in enumerate(in_order(get, range(len(firsts)), self.workers)):
                    pace.done(ci, got is _SKIPPED)
                    if bar is not None:
                        bar.update(1)
                    if not many:
                        real = idx[firsts[ci] : firsts[ci] + size]
                        if got is _SKIPPED:
                            yield real, None, 0.0
                            continue
                        assert isinstance(got, tuple)  # one process: every chunk is its own
                        yield real, *got
        finally:
            if bar is not None:
                bar.close()
        if many:
            process_barrier(f"jaxrefl mcmc: {tag} pass")
            assert name is not None  # adaptive_uncertainty requires a folder here
            for ci, a in enumerate(firsts):
                real = idx[a : a + size]
                got = _load_chunk(name(ci), real.size, self.lp.labels)
                if got is None:
                    raise RuntimeError(
                        f"{name(ci)}: missing or unreadable after every process finished; "
                        "is chunk_dir one shared folder for all processes?"
                    )
                yield real, *got

    def _sample(self, real, size, starts, opts: HMCOptions, seed: int):
        """(Samples of the pixels ``real``, run seconds): one chunk, padded to ``size``."""
        # pad the last chunk by repeating its pixels: one compiled shape for the map
        rows = np.resize(real, size)
        sub = jax.tree.map(lambda v: v[rows], self.data)
        th0, sd = starts(rows)
        nrm = None if self.normals is None else jnp.asarray(np.asarray(self.normals)[rows])
        smp = sample_pixels(self.lp, sub, th0, theta_std=sd, normals=nrm, options=opts, seed=seed)
        return smp.take(real.size), smp.run_s


class _Skipped:
    """A chunk not started: the time limit came first."""


_SKIPPED = _Skipped()


class _Pace:
    """One pass's chunks done, their wall time, and its progress lines (module docstring):
    the pass's start and end, and every :data:`HEARTBEAT_S` seconds from a timer thread the
    chunks done and the time left, estimated from the chunks after the first (which
    compiles)."""

    def __init__(self, desc: str, chunks: int, pixels: int, log, workers: int) -> None:
        self.desc, self.chunks, self.pixels, self.log = desc, chunks, pixels, log
        self.workers = max(1, workers)
        self.n_done = self.n_skipped = 0
        self.last_s: float | None = None  # wall time of the last chunk sampled
        self.t0 = time.perf_counter()
        self._stop = threading.Event()
        self._timer: threading.Thread | None = None

    def __enter__(self) -> _Pace:
        if self.log is not None:
            self.log(f"{self.desc}: {self.pixels} pixels in {self.chunks} chunks")
            self._timer = threading.Thread(target=self._beat, daemon=True)
            self._timer.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._timer is not None:
            self._timer.join()
        if self.log is not None and exc[0] is None:
            tail = f", {self.n_skipped} left by the time limit" if self.n_skipped else ""
            self.log(f"{self.desc}: done in {time.perf_counter() - self.t0:.1f} s{tail}")

    def _beat(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            assert self.log is not None
            self.log(self.line())

    def line(self) -> str:
        el = time.perf_counter() - self.t0
        left = self.chunks - self.n_done
        eta = ""
        if self.last_s is not None and self.n_done:
            eta = f", about {max(1, left / self.workers) * self.last_s:.0f} s left"
        return f"{self.desc}: {self.n_done}/{self.chunks} chunks done, {el:.0f} s{eta}"

    def too_late(self, deadline: float | None) -> bool:
        """Whether a chunk started now would end past ``deadline`` (the last chunk's wall
        time ahead; before any chunk has run, only a deadline already passed stops it)."""
        if deadline is None:
            return False
        ahead = 0.0 if self.last_s is None else self.last_s
        return time.perf_counter() + ahead > deadline

    def took(self, seconds: float) -> None:
        self.last_s = seconds

    def done(self, ci: int, skipped: bool) -> None:
        self.n_done += 1
        self.n_skipped += skipped


def _fingerprint(tag, idx, opts: HMCOptions, seed: int, size: int, box) -> str:
    h = hashlib.sha1(f"{tag} {opts!r} {seed} {size} {box}".encode())
    h.update(np.ascontiguousarray(idx, np.int64).tobytes())
    return h.hexdigest()[:12]


def _save_chunk(path: Path, cut: Samples, run_s: float) -> None:
    """One chunk's draws, written to a temporary file then renamed (complete or absent)."""
    arrays: dict[str, Any] = {"theta": cut.theta, "natural": cut.natural, "run_s": run_s}
    arrays.update({f"stats.{k}": v for k, v in cut.stats.items()})
    arrays.update({f"tuning.{k}": v for k, v in cut.tuning.items()})
    arrays["no_estimate"] = cut.extra["no_estimate"]
    arrays["method"] = np.str_(cut.method)
    arrays["reparam"] = np.str_(cut.extra.get("reparam", "none"))
    from jaxrefl.io import save_npz_atomic

    save_npz_atomic(path, **arrays)


def _load_chunk(path: Path, m: int, labels) -> tuple[Samples, float] | None:
    """A chunk written by :func:`_save_chunk` for ``m`` pixels, or None where the file is
    absent, truncated, corrupt or of another size (then it is sampled again)."""
    if not path.exists():
        return None
    try:
        with np.load(path) as z:
            a = {k: z[k] for k in z.files}
    except Exception:  # truncated or corrupt: sample it again
        return None
    if a.get("theta") is None or a["theta"].shape[0] != m:
        return None
    smp = Samples(
        theta=a["theta"],
        natural=a["natural"],
        labels=tuple(labels),
        stats={k[6:]: v for k, v in a.items() if k.startswith("stats.")},
        method=str(a["method"]),
        tuning={k[7:]: v for k, v in a.items() if k.startswith("tuning.")},
        run_s=float(a["run_s"]),
        extra={"no_estimate": a["no_estimate"], "reparam": str(a["reparam"])},
    )
    return smp, float(a["run_s"])


def _choose_methods(has: np.ndarray, unreliable: np.ndarray, o: AdaptiveOptions, rng) -> np.ndarray:
    """(N,) uint8 method codes (:data:`METHODS`): 0 without an estimate, else 1 (Laplace),
    2 (MCMC, Laplace unreliable: flagged, or no finite summary) or 3 (MCMC audit of a
    reliable pixel) as ``o.mcmc`` and ``o.audit`` choose; the audit pixels are drawn with
    ``rng``."""
    method = np.where(has, Method.LAPLACE, Method.NONE).astype(np.uint8)
    if o.mcmc == MCMCPixels.FLAGGED:
        reliable = np.flatnonzero(has & ~unreliable)
        n_audit = int(np.ceil(o.audit * reliable.size)) if o.audit > 0 and reliable.size else 0
        audit_idx = rng.choice(reliable, size=n_audit, replace=False) if n_audit else []
        method[has & unreliable] = Method.MCMC
        method[np.asarray(audit_idx, dtype=int)] = Method.MCMC_AUDIT
    elif o.mcmc == MCMCPixels.ALL:
        method[has] = np.where(unreliable[has], Method.MCMC, Method.MCMC_AUDIT)
    return method


@dataclass
class _Summaries:
    """The map's (N, ...) arrays, Laplace's first, then filled in place chunk by chunk."""

    mean: np.ndarray
    std: np.ndarray
    q05: np.ndarray
    q95: np.ndarray
    laplace_std: np.ndarray
    rhat: np.ndarray
    ess_bulk: np.ndarray
    ess_tail: np.ndarray
    divergences: np.ndarray
    rerun: np.ndarray
    rhat_first: np.ndarray

    @classmethod
    def from_laplace(cls, mean, std, q05, q95, d: int) -> _Summaries:
        """The Laplace summaries (N, P), NaN-padded to the posterior's D entries (the
        noise scale and light have no Laplace summary); no MCMC diagnostics yet."""
        n, p = mean.shape
        big = np.full((n, d - p), np.nan)
        mean, std, q05, q95 = (np.concatenate([a, big], -1) for a in (mean, std, q05, q95))
        return cls(
            mean=mean,
            std=std,
            q05=q05,
            q95=q95,
            laplace_std=std.copy(),
            rhat=np.full(n, np.nan),
            ess_bulk=np.full(n, np.nan),
            ess_tail=np.full(n, np.nan),
            divergences=np.zeros(n, np.int64),
            rerun=np.zeros(n, bool),
            rhat_first=np.full(n, np.nan),
        )

    def store(self, real: np.ndarray, cut: Samples) -> None:
        """Summaries of the draws ``cut`` of the map's pixels ``real``."""
        m = real.size
        flat = cut.natural.reshape(m, -1, cut.natural.shape[-1])
        self.mean[real] = flat.mean(1)
        self.std[real] = flat.std(1, ddof=1)
        self.q05[real] = np.quantile(flat, 0.05, axis=1)
        self.q95[real] = np.quantile(flat, 0.95, axis=1)
        dg = diagnostics(cut)
        self.rhat[real] = dg["max_rhat"]
        self.ess_bulk[real] = dg["min_ess_bulk"]
        self.ess_tail[real] = dg["min_ess_tail"]
        self.divergences[real] = dg["divergences"]


def _chunk_size(n: int, chunk: int, batch: int, workers: int = 1) -> int:
    """The fewest chunks of at most ``chunk`` pixels, balanced: ceil(n / ceil(n / chunk)),
    rounded up to a multiple of the sampler's ``batch`` where that stays within ``chunk``
    (sample_pixels pads a chunk to whole batches). 3,078 pixels in chunks of at most 2048,
    batches of 128, run as 2 chunks of 1664, not 2 of 2048 with 1,018 of them padding.
    With ``workers`` chunks at once after the first (which runs alone: it compiles), the
    count is rounded up so that those after the first fill whole rounds: 12 chunks with
    2 workers leave the last round one chunk and a core idle, 13 smaller ones do not."""
    k = -(-n // chunk)
    if workers > 1 and k > 1:
        k = 1 + -(-(k - 1) // workers) * workers
    k = min(k, n)
    size = -(-n // k)
    if size <= batch:  # one batch: sample_pixels does not pad it
        return size
    whole = -(-size // batch) * batch
    return whole if whole <= chunk else size


def _restarts(cut: Samples, j: int, chains: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Second-pass starts of pixel j of ``cut``: (chains, D) theta, chain c from a random
    draw of first-pass chain c mod C (so the new chains start where the old ones went,
    apart), and (D,) the first pass's theta-space draw std (the initial metric)."""
    th = cut.theta[j]  # (C, K, D)
    c, k = th.shape[:2]
    x = th[np.arange(chains) % c, rng.integers(0, k, size=chains)]
    return x, th.reshape(c * k, -1).std(0)

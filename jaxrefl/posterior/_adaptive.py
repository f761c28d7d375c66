"""Adaptive inference: Laplace everywhere, MCMC where Laplace is not to be trusted.

The Laplace approximation (:func:`jaxrefl.fit.laplace`) costs about one LM iteration per
pixel; its flags (:class:`jaxrefl.fit.LaplaceFlag`) say where the Gaussian is the wrong
shape: a parameter at a bound, a parameter the data do not pin down, a singular
curvature. :func:`adaptive_uncertainty` keeps the Laplace summary
(:func:`~jaxrefl.posterior.laplace_summary`) on the pixels flagged reliable (flag 0), runs
the pixel samplers (:func:`~jaxrefl.posterior.sample_pixels`) on every pixel with a flag,
and also on a random *audit* sample of the reliable ones (fraction ``audit``) so that the
Laplace summaries are checked against MCMC on the same run
(:attr:`~jaxrefl.posterior.UncertaintyMap.audit_std_ratio`). ``method`` records per pixel
which method produced its numbers (:data:`~jaxrefl.posterior.METHODS`). MCMC summaries are
the draws' mean, std and empirical 5% / 95% quantiles.

Every setting is one immutable :class:`~jaxrefl.posterior.AdaptiveOptions`: which pixels
are sampled (``mcmc``, ``audit``), the samplers (``hmc``, ``gibbs``), the second pass
(``rerun_rhat``, ``rerun_hmc``), the chunk size, the seed and whether draws are kept
(``keep_samples=False`` keeps only the summaries).

The MCMC pixels run in chunks (:mod:`._chunks`: one compiled size, several at once, on disk
and across processes, within a time limit), pixels without censored observations first:
their chunks run the cheaper posterior without the censored branch
(:meth:`LogPosterior.for_data`). A map can hold chunks of several samplers (its samples'
``method`` is then e.g. ``"gibbs+hmc"``; ``timings.sampler`` names them). ``timings``
keeps both the summed seconds of the chunks' samplers (``mcmc_s``, ``rerun_s``) and each
pass's wall time (``mcmc_wall_s``, ``rerun_wall_s``). A pixel whose chunk the time limit
left keeps its Laplace summary, with method ``laplace_time_limit``.

Second pass: a pixel whose first-pass chains disagree (max split R-hat above
``rerun_rhat``) runs again under the second pass's settings
(:attr:`~jaxrefl.posterior.AdaptiveOptions.second_pass`). Its chains start from draws of
the first pass, chain c from first-pass chain c mod C, so they begin apart and on the
posterior's ridge, with the first pass's draw std as the initial metric; where the first
pass had nothing to tune (:data:`~jaxrefl.posterior._adaptive_options.UNTUNED`) it runs in
chunks of the first pass's size, reusing its compiled program. The second pass's summaries
and draws replace the first's (``rerun`` marks those pixels and ``rhat_first`` keeps the
first pass's R-hat, so ``report()`` shows what it changed). Pixels still above the
threshold after it run a third pass (``rerun_passes`` 2, the default:
:func:`~jaxrefl.posterior._adaptive_options.third_pass_options`, twice the second pass's
scans between kept draws, from second-pass draws) where the second pass brought most of
its pixels under it (:data:`THIRD_PASS_SHARE`; ``timings["third_pass_skipped"]`` says why
not); pixels still above the threshold after the last pass stay marked by their
``rhat``: read their std as a lower bound. A later pass's chunk the time limit left
leaves its pixels the earlier pass's draws.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl._map_defaults import RERUN_RHAT
from jaxrefl._threads import default_workers
from jaxrefl.fit import LaplaceFlag, PixelData

from ._adaptive_options import (
    UNTUNED,
    AdaptiveOptions,
    MCMCPixels,
    third_pass_options,
    untuned_rerun,
)
from ._chunks import CHUNK_ROUND, Chunks, chunk_size
from ._diagnostics import ChunkSummary
from ._laplace_summary import laplace_summary
from ._logpost import LogPosterior
from ._methods import MCMC_METHODS, Method
from ._samples import Samples
from ._uncertainty_map import UncertaintyMap, mcmc_reasons

__all__ = ["adaptive_uncertainty"]

_RERUN_SEED = 100_003  # offsets the second pass's seeds from the first's chunk seeds
#: The third pass runs where the second left at most this share of its pixels apart
#: (:func:`_third_pass_skipped`).
THIRD_PASS_SHARE = 0.5
_KEEP_STREAM = 1  # the kept pixels' draw has its own stream (the audit's choice is unchanged)


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
    which no MCMC chunk is started (module docstring; not in a job of several processes),
    or ``options.time_limit_s`` from this call where that comes first.
    log: called with a line of text at each pass's start and end and every
    :data:`HEARTBEAT_S` seconds during a pass.

    ``noise_scale``, ``normals`` and ``dof`` are per-pixel data of the fit and the capture
    (like ``theta_hat``), not settings: the map's settings are ``options``'s.
    """
    o = AdaptiveOptions() if options is None else options
    if o.time_limit_s is not None:  # the options' limit, or the caller's deadline if sooner
        end = time.perf_counter() + o.time_limit_s
        deadline = end if deadline is None else min(deadline, end)
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
    # Pixels in order of their count of censored observations, none first: those chunks
    # run the cheaper posterior without the censored branch (LogPosterior.for_data), and a
    # Gibbs chunk's latent draws gather as many slots as its pixels need at most
    # (_conjugate.censored_slots), so pixels with a few do not pay for one with many.
    censored_px = np.sum(np.asarray(data.censored)[idx] != 0, axis=(-2, -1))
    idx = idx[np.argsort(censored_px, kind="stable")]
    samples, kept = None, None
    if idx.size:
        extra = lp.size - theta_hat.shape[1]
        s0_all = None if noise_scale is None else np.asarray(noise_scale)

        def first_starts(rows):
            s0 = None if s0_all is None else s0_all[rows]
            th0 = lp.init_theta(jnp.asarray(theta_hat[rows]), noise_scale=s0)
            return th0, np.concatenate([theta_std[rows], np.ones((rows.size, extra))], -1)

        folder = None if chunk_dir is None else Path(chunk_dir)
        workers = default_workers() if o.workers is None else o.workers
        chunks = Chunks(lp, data, normals, o.chunk, workers, folder, progress, deadline, log)
        kept = _kept(idx, o)
        run = _Run(o, chunks, timings, kept)
        samples, restart = run.first_pass(idx, first_starts, out, rng)
        run.second_pass(idx, restart, out, samples, rng)
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
        kept_pixels=None if samples is None else kept,
    )


@dataclass
class _Run:
    """The MCMC passes of one :func:`adaptive_uncertainty` call (module docstring)."""

    o: AdaptiveOptions
    chunks: Chunks
    timings: dict[str, Any]
    kept: np.ndarray | None = None  # the pixels whose draws are kept (None: all of them)
    skipped: list[np.ndarray] = field(default_factory=list)  # first-pass pixels not sampled

    def _rows(self, real: np.ndarray) -> np.ndarray:
        """Positions in the chunk ``real`` of the pixels whose draws are kept."""
        assert self.kept is not None  # called only where draws are capped
        return np.flatnonzero(np.isin(real, self.kept))

    def first_pass(self, idx, starts, out: _Summaries, rng):
        """Sample the pixels ``idx``; returns their draws (None unless ``keep_samples``)
        and, per pixel whose chains disagree, its second-pass starts."""
        o, tm = self.o, self.timings
        second = o.second_pass
        restart: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        parts, run_s, used = [], [], []
        t0 = time.perf_counter()
        passes = self.chunks.run(idx, starts, o.hmc, o.gibbs, o.seed, "MCMC first pass", "first")
        for real, cut, rs, summary in passes:
            if cut is None:  # the time limit came first: Laplace summaries stay
                self.skipped.append(real)
                continue
            run_s.append(rs)
            used.append(cut.method)
            out.store(real, summary)
            if second is not None:  # draws kept for the second pass's starts only
                # NaN R-hat (a chain that never moved) counts as disagreeing
                stuck = ~(out.rhat[real] <= o.rerun_rhat) & ~cut.no_estimate
                for j in np.flatnonzero(stuck):
                    restart[int(real[j])] = _restarts(cut, int(j), second.num_chains, rng)
            if o.keep_samples:
                parts.append(cut if self.kept is None else cut.take(self._rows(real)))
        tm["mcmc_s"] = float(np.sum(run_s))
        tm["mcmc_wall_s"] = time.perf_counter() - t0
        tm["mcmc_pixels"] = int(idx.size) - sum(r.size for r in self.skipped)
        tm["mcmc_chunks"] = len(run_s)
        if self.chunks.deadline is not None:
            tm["time_limit_pixels_left"] = sum(r.size for r in self.skipped)
        tm["sampler"] = "+".join(dict.fromkeys(used))  # each chunk's (Samples.method)
        tm["mcmc_chunk_size"] = chunk_size(int(idx.size), o.chunk, o.hmc.batch_size)
        if len(run_s) > CHUNK_ROUND:
            # the first round of chunks waits for the one compilation; the others reuse it
            rest = float(np.median(run_s[CHUNK_ROUND:]))
            tm["mcmc_compile_s"] = max(0.0, run_s[0] - rest)
            tm["mcmc_chunk_s_median"] = rest
        return (Samples.concat(parts) if o.keep_samples and parts else None), restart

    def second_pass(self, idx, restart, out: _Summaries, samples: Samples | None, rng) -> None:
        """Sample the pixels of ``restart`` again from their starts under the second
        pass's settings, and those still above the threshold once more under the third
        pass's (module docstring); their summaries and draws replace the earlier pass's."""
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
        kept = idx if self.kept is None else self.kept
        at = {int(i): k for k, i in enumerate(kept)}
        seed = self.o.seed + _RERUN_SEED
        left, restart = self._rerun(
            again, restart, second, size, seed, ("rerun", "second"), out, samples, at, rng
        )
        self.timings["third_pass_skipped"] = _third_pass_skipped(
            self.o.rerun_passes, len(restart), int(again.size) - left
        )
        if self.timings["third_pass_skipped"]:
            return
        third = third_pass_options(second)
        again = idx[np.isin(idx, np.fromiter(restart, int))]
        seed = self.o.seed + 2 * _RERUN_SEED
        self._rerun(
            again, restart, third, None, seed, ("third_pass", "third"), out, samples, at, rng
        )
        # counted against the report's threshold (the key it is filed under), whatever
        # rerun_rhat chose the pixels; NaN (a chain that never moved) counts as above
        self.timings["third_pass_rhat_above_after"] = int(np.sum(~(out.rhat[again] <= RERUN_RHAT)))

    def _rerun(self, again, restart, settings, size, seed, names, out, samples, at, rng):
        """One later pass over the pixels ``again`` from their ``restart`` starts, its
        timings under ``names`` = (timings prefix, pass tag); returns the pixels the time
        limit left and the restarts of the pixels whose chains still disagree."""
        key, tag = names
        t0 = time.perf_counter()

        def starts(rows):
            return tuple(np.stack([restart[int(i)][k] for i in rows]) for k in (0, 1))

        run_s, left, stuck_starts = [], 0, {}
        desc = f"MCMC {tag} pass"
        for real, cut, rs, summary in self.chunks.run(
            again, starts, settings, self.o.gibbs, seed, desc, tag, size
        ):
            if cut is None:  # the time limit came first: the earlier pass's draws stay
                if tag == "second":
                    out.rhat_first[real] = np.nan
                left += real.size
                continue
            run_s.append(rs)
            out.store(real, summary)
            out.rerun[real] = True
            if samples is not None and self.kept is None:
                samples.put([at[int(i)] for i in real], cut)
            elif samples is not None:
                rows = self._rows(real)
                samples.put([at[int(i)] for i in real[rows]], cut.take(rows))
            # NaN R-hat (a chain that never moved) counts as disagreeing
            stuck = ~(out.rhat[real] <= self.o.rerun_rhat) & ~cut.no_estimate
            for j in np.flatnonzero(stuck):
                stuck_starts[int(real[j])] = _restarts(cut, int(j), settings.num_chains, rng)
        if self.chunks.deadline is not None:
            self.timings[f"time_limit_{tag}_pass_left"] = left
        self.timings[f"{key}_s"] = float(np.sum(run_s))
        self.timings[f"{key}_wall_s"] = time.perf_counter() - t0
        self.timings[f"{key}_pixels"] = int(again.size) - left
        return left, stuck_starts


def _third_pass_skipped(passes: int, apart: int, rerun: int) -> str:
    """Why no third pass runs ("" where it does): ``apart`` of the second pass's ``rerun``
    pixels still disagree. A second pass that left most of its pixels apart says their
    chains lack more than length (several modes, a ridge along a bound): a pass twice as
    long would cost more than the second and leave them apart, so their R-hat marks them."""
    if passes < 2:
        return "rerun_passes is 1"
    if apart == 0:
        return "no pixel above the threshold after the second pass"
    if apart > THIRD_PASS_SHARE * rerun:
        return (
            f"{apart} of the second pass's {rerun} pixels still apart: longer chains are not "
            "what they lack"
        )
    return ""


def _kept(idx: np.ndarray, o: AdaptiveOptions) -> np.ndarray | None:
    """The MCMC pixels whose draws are kept, in ``idx``'s order: a random subset of
    ``o.max_kept_pixels`` (seeded by ``o.seed``) where there are more; None: all."""
    cap = o.max_kept_pixels
    if not o.keep_samples or cap is None or idx.size <= cap:
        return None
    chosen = np.random.default_rng([o.seed, _KEEP_STREAM]).choice(idx, cap, replace=False)
    return idx[np.isin(idx, chosen)]


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

    def store(self, real: np.ndarray, summary: ChunkSummary) -> None:
        """The summaries of the draws of the map's pixels ``real`` (computed where the chunk
        was sampled: :meth:`Chunks.run`)."""
        self.mean[real], self.std[real] = summary.mean, summary.std
        self.q05[real], self.q95[real] = summary.q05, summary.q95
        dg = summary.diag
        self.rhat[real] = dg["max_rhat"]
        self.ess_bulk[real] = dg["min_ess_bulk"]
        self.ess_tail[real] = dg["min_ess_tail"]
        self.divergences[real] = dg["divergences"]


def _restarts(cut: Samples, j: int, chains: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Second-pass starts of pixel j of ``cut``: (chains, D) theta, chain c from a random
    draw of first-pass chain c mod C (so the new chains start where the old ones went,
    apart), and (D,) the first pass's theta-space draw std (the initial metric)."""
    th = cut.theta[j]  # (C, K, D)
    c, k = th.shape[:2]
    x = th[np.arange(chains) % c, rng.integers(0, k, size=chains)]
    return x, th.reshape(c * k, -1).std(0)

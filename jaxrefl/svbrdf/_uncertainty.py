"""Uncertainty maps of a capture: the capture job's fit, its Laplace covariance, and MCMC
where Laplace is not to be trusted.

:func:`uncertainty_maps` runs three stages on a :class:`jaxrefl.io.Capture`:

1. :func:`fit_capture` with the job, in float64: per pixel the LM optimum theta*, the
   Laplace std of every parameter in natural units (the job's ``*_std`` maps, named by
   :func:`map_name`), the Laplace flags and the residual noise std.
2. The posterior's parameter space (:func:`posterior_space`: the fit's, with alpha's floor
   at the microfacet models' 1e-3 where the fit's was the capture's resolvable width), the
   optimum in its coordinates and the Laplace std there. The bijections x = g(theta) act
   entry by entry, so the delta method std_x = |g'(theta*)| std_theta reverses exactly:
   std_theta = std_x / |g'(theta*)|.
3. :func:`jaxrefl.posterior.adaptive_uncertainty` with the given
   :class:`~jaxrefl.posterior.AdaptiveOptions`: Laplace summaries where the flags call the
   Gaussian reliable (Student t marginals with :func:`laplace_dof` degrees of freedom where
   the fit estimated the pixel's noise scale, as the sampled posterior does), MCMC on the
   flagged pixels and an audit sample. The posterior is the fitted model's with the fit's
   noise model (:func:`map_noise`), of unknown scale per pixel (Jeffreys prior); the lobe's
   priors are by default estimated from the population of fitted pixels (:func:`population_priors`:
   empirical Bayes, so that a pixel whose highlight no photo saw is not pushed onto a
   bright, rough lobe by the volume of a uniform prior), the others are
   :func:`jaxrefl.posterior.default_priors`; the chains start from theta* and the
   residual noise std (1e-2 where that is not a positive number).

:func:`write_uncertainty` writes ``uncertainty.exr`` (mean, std, q05, q95 per parameter,
method, R-hat, ESS; :func:`jaxrefl.posterior.write_uncertainty_exr`), where pixels were
sampled ``posterior.nc`` (ArviZ InferenceData of the MCMC pixels with their observations,
weights, censoring flags, pointwise log-likelihood and posterior predictive draws), and
PNGs (:func:`jaxrefl.svbrdf.write_uncertainty_plots`). :meth:`CaptureUncertainty.report`
is the JSON-ready summary (counts by method, R-hat/ESS distributions, audit std ratios,
timings).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl import fit
from jaxrefl import posterior as jp
from jaxrefl._errors import JaxreflError
from jaxrefl._names import PRIOR_SOURCES
from jaxrefl.fit import PixelData

from ._data import pixel_block
from ._job import CaptureFit, FitJob, fit_capture, map_name
from ._light_map import MAP_TERMS, light_spread, map_term, widen_for_light

# WIDEN_SHARE, WIDER: the names this module's docstrings refer to
from ._map_model import WIDEN_SHARE, WIDER, map_model, map_noise, noise_text  # noqa: F401
from ._models import capture_model
from ._population import population_priors
from ._uncertainty_plots import write_uncertainty_plots
from ._width_map import WidthSpread, pixel_widths, relax_shared_width

__all__ = [
    "CaptureUncertainty",
    "fit_theta",
    "laplace_dof",
    "laplace_interval",
    "laplace_theta_std",
    "map_posterior",
    "posterior_space",
    "uncertainty_maps",
    "write_uncertainty",
]

_NOISE_START = 1e-2  # the chains' starting noise scale where the fit gave none
_PPC_DRAWS = 50  # posterior predictive draws per MCMC pixel in posterior.nc
LOG_LIKELIHOOD_MAX = 20_000_000  # pointwise log-likelihood values in posterior.nc (float32: 80 MB)


@dataclass
class CaptureUncertainty:
    """Result of :func:`uncertainty_maps` (N = height x width pixels, row-major).

    fit:       the capture job's result (:class:`CaptureFit`, float64)
    map:       the per-pixel posterior summaries (:class:`jaxrefl.posterior.UncertaintyMap`)
    posterior: the log-posterior that was sampled (:class:`jaxrefl.posterior.LogPosterior`)
    data:      (N, K, C) the pixels' observations, float64
    theta_std: (N, P) the Laplace std in the unconstrained space (NaN: no estimate)
    options:   the settings the map was made with
    prior_summary: where the priors came from (``source``: population, default or given;
               for a population, its pixels and estimates: :func:`population_priors`)
    timings:   seconds of each stage: :func:`fit_capture` (``fit_s``, a widened model's
               second fit included), the priors (``priors_s``),
               :func:`jaxrefl.posterior.adaptive_uncertainty` (``posterior_s``; its own
               ``timings`` split it), the light's widening (``light_s``), the
               per-pixel widths (``width_s``) and the call (``total_s``)
    model_choice: the model sampled and why (:func:`uncertainty_maps`)
    light_std: (N, P) the estimated light's share of each pixel's std over the model's
               parameters (:mod:`jaxrefl.svbrdf._light_map`: ``map``'s std, q05 and q95
               include it); None where the map carries no light term (._light_map)
    width_spread: ``pooled``: each pixel's own width around the shared one
               (:class:`jaxrefl.svbrdf._width_map.WidthSpread`: ``map`` includes it and
               has ``alpha`` as its last column); None for the other models
    """

    fit: CaptureFit
    map: jp.UncertaintyMap
    posterior: jp.LogPosterior
    data: PixelData
    theta_std: np.ndarray
    height: int
    width: int
    options: jp.AdaptiveOptions
    timings: dict[str, float] = field(default_factory=dict)
    prior_summary: dict[str, Any] = field(default_factory=dict)
    model_choice: dict[str, Any] = field(default_factory=dict)
    light_std: np.ndarray | None = None
    width_spread: WidthSpread | None = None

    @property
    def time_limit_s(self) -> float | None:
        """The time limit the map was made under (``options.time_limit_s``; None: none)."""
        return self.options.time_limit_s

    @property
    def model(self) -> str:
        """The capture model's name (:data:`jaxrefl.svbrdf.CAPTURE_MODELS`)."""
        return self.fit.job.model

    def inference_data(self, n_draws: int = _PPC_DRAWS):
        """ArviZ InferenceData of the MCMC pixels whose draws are kept (all of them up to
        ``AdaptiveOptions.max_kept_pixels``; None when no pixel was sampled or
        ``AdaptiveOptions.keep_samples`` is False): posterior and sample stats (float32),
        observed data (dims ``pixel``, ``photo``, ``channel``), weights and censoring flags
        (``constant_data``), the pointwise log-likelihood (``log_likelihood``, float32, where it
        holds at most :data:`LOG_LIKELIHOOD_MAX` values; else attr
        ``log_likelihood_left_out`` says why) and ``n_draws`` posterior predictive draws
        per pixel (float32). The ``pixel`` axis (in the order of
        :attr:`UncertaintyMap.sample_pixels`)
        carries coordinates ``row`` and ``col``, each pixel's place in the map; attrs
        ``rows``, ``cols``, ``width``, ``height``."""
        u = self.map
        if u.samples is None:
            return None
        idx = u.sample_pixels
        sub = jax.tree.map(lambda a: a[idx], self.data)
        ppc = jp.posterior_predictive(
            self.posterior, u.samples, sub, n_draws=n_draws, seed=self.options.seed
        )
        rows, cols = np.divmod(idx, self.width)
        attrs: dict[str, Any] = {"rows": rows.tolist(), "cols": cols.tolist()}
        attrs.update(width=self.width, height=self.height)
        n, c, m, _d = u.samples.theta.shape
        size = n * c * m * int(np.prod(sub.obs.shape[1:]))
        ll = None
        if size <= LOG_LIKELIHOOD_MAX:
            ll = jp.log_likelihood_draws(self.posterior, u.samples, sub).astype(np.float32)
        else:
            attrs["log_likelihood_left_out"] = (
                f"{size} values (pixels x draws x photos x channels) exceed "
                f"{LOG_LIKELIHOOD_MAX}: sample a crop (--pixels) for az.loo"
            )
        idata = jp.to_inference_data(
            u.samples,
            sub,
            pixels=idx,
            predictive=ppc,
            log_likelihood=ll,
            observation="photo",
            attrs=attrs,
            dtype=np.float32,
        )
        return idata.assign_coords(row=("pixel", rows), col=("pixel", cols))

    def report(self) -> dict[str, Any]:
        """JSON-ready summary: model and size, noise, priors and the parameters' bounds,
        the sampler settings of both passes, the fit's status and flag counts, the light,
        :meth:`UncertaintyMap.report`, timings."""
        o = self.options
        lp = self.posterior
        # the second pass's settings, also where rerun_rhat turns it off; the first pass's
        # where its samplers had nothing to tune (jaxrefl.posterior._adaptive_options.UNTUNED)
        second = jp.longer_options(o.hmc) if o.rerun_hmc is None else o.rerun_hmc
        if self.map.timings.get("rerun_settings") == "untuned":
            second = jp.untuned_rerun(o.hmc)
        return {
            "model": self.model,
            "height": self.height,
            "width": self.width,
            "noise": noise_text(lp.residual.noise),
            "priors": {b.name: repr(p) for b, p in zip(lp.space.blocks, lp.priors, strict=True)},
            "prior_source": dict(self.prior_summary),
            # the posterior's box in natural units (posterior_space: alpha's floor may lie
            # below the fit's)
            "bounds": {
                lab: [float(a), float(b)]
                for lab, a, b in zip(lp.space.labels, lp.space.lower, lp.space.upper, strict=True)
            },
            "sampler": {**vars(o.hmc), "gibbs": None if o.gibbs is None else {**vars(o.gibbs)}},
            "second_pass": {"rerun_rhat": o.rerun_rhat, "options": {**vars(second)}},
            "third_pass": {"passes": o.rerun_passes, "thin": jp.third_pass_options(second).thin},
            # misspecified pixels (jaxrefl.svbrdf._check): their intervals are not calibrated
            "fit_report": {
                k: self.fit.report.get(k)
                for k in ("status_counts", "laplace_flag_counts", "misspecified_counts")
            },
            "model_choice": dict(self.model_choice),
            # the flash the posterior was sampled under (FitJob.light; the fit's estimate)
            # and the light term its intervals carry (._light_map: map_term; none: no light_std)
            "light": {
                **(self.fit.report.get("light") or {}),
                "map_term": MAP_TERMS[2] if self.light_std is None else map_term(self.fit.light),
            },
            "light_std": self.light_std_summary(),
            # pooled: the per-pixel widths around the shared one (._width_map)
            "width_spread": None if self.width_spread is None else self.width_spread.summary(),
            "uncertainty": self.map.report(),
            # pixels of uncertainty.exr whose non-finite values no method code explains
            "nonfinite_counts": self.nonfinite_counts(),
            "timings": dict(self.timings),
            "time_limit": self.time_limit_report(),
        }

    def light_std_summary(self) -> dict[str, dict[str, float]] | None:
        """Per parameter, the median and 90th percentile over pixels of the light's share
        of the std, and of the ratio of the widened std to the std without it (None: the
        light is the stated one)."""
        if self.light_std is None:
            return None
        out = {}
        p = self.light_std.shape[1]
        for j, lab in enumerate(self.map.labels[:p]):
            ls = self.light_std[:, j]
            tot = np.asarray(self.map.std[:, j], np.float64)
            ok = np.isfinite(ls) & np.isfinite(tot) & (tot > 0)
            if not ok.any():
                continue
            ratio = tot[ok] / np.sqrt(np.maximum(tot[ok] ** 2 - ls[ok] ** 2, 0.0))
            out[lab] = {
                "median": float(np.median(ls[ok])),
                "p90": float(np.quantile(ls[ok], 0.9)),
                "widening_median": float(np.median(ratio)),
                "widening_p90": float(np.quantile(ratio, 0.9)),
            }
        return out

    def nonfinite_counts(self) -> dict[str, int]:
        """Pixels per bit of ``uncertainty.exr``'s ``nonfinite`` channel
        (:class:`jaxrefl.posterior.NonFinite`): summaries or MCMC diagnostics that are not
        finite where the pixel's method says they should be."""
        ch = jp.uncertainty_channels(self.map, self.height, self.width)["nonfinite.Y"]
        return {b.name or str(b.value): int(np.sum((ch & b.value) != 0)) for b in jp.NonFinite}

    def time_limit_report(self) -> dict[str, Any] | None:
        """The time limit and what it left undone: pixels chosen for MCMC that kept their
        Laplace summaries (method ``laplace_time_limit``) and second-pass pixels that kept
        their first pass's draws; None without a limit."""
        if self.time_limit_s is None:
            return None
        t = self.map.timings
        first = int(t.get("time_limit_pixels_left", 0))
        second = int(t.get("time_limit_second_pass_left", 0))
        return {
            "limit_s": self.time_limit_s,
            "pixels_left_laplace": first,
            "second_pass_pixels_left": second,
            "reached": bool(first or second),
        }


def posterior_space(cf: CaptureFit) -> tuple[Any, fit.ParamSpace]:
    """(model, parameter space) of the posterior of a capture fit's pixels: the fit's,
    except that where the fit's floor of the GGX width alpha was the capture's resolvable
    width (:func:`jaxrefl.svbrdf.resolvable_alpha`; the job's ``alpha_min`` None), the
    posterior's is the microfacet models' 1e-3 (:data:`jaxrefl.svbrdf._models.ALPHA_RANGE`).

    The resolvable width regularises the point fit: a lobe narrower than the spacing of the
    photos' half vectors is seen by at most one photo, and a least-squares optimum below it
    extrapolates to a needle. It is not a property of the surface. Where a pixel's width
    piles against it (``ModelCheck.ALPHA_AT_FLOOR``), the posterior bounded there holds
    alpha at the floor and F0 at the value that lobe needs, and its intervals miss a
    narrower truth. With the floor at 1e-3 the posterior says what the photos and the prior
    on alpha (the population's log-normal, :func:`population_priors`) allow: a width at or
    below the resolvable one, with the F0 that goes with it. Elsewhere the posterior is the
    same density in natural units, truncated lower: where the photos resolve the width, the
    old floor lies where it has next to no mass. Alpha's unconstrained coordinate differs,
    so the Laplace summaries of :func:`uncertainty_maps` are formed in the new one. A floor
    the job gives (``alpha_min``) is kept: it is the user's statement about the surface."""
    model, space = cf.model()
    if cf.job.alpha_min is not None or "alpha" not in space.labels:
        return model, space
    return capture_model(cf.job.model, channels=space.channels, alpha_min=None)


def fit_theta(cf: CaptureFit, space: fit.ParamSpace | None = None) -> np.ndarray:
    """(N, P) the fit's optimum in ``space``'s unconstrained coordinates (None: the fit's
    own space, whose coordinates ``cf.theta`` holds); NaN where the fit has none. Entries
    whose bounds are the fit's are copied; the others go through natural units."""
    theta = np.asarray(cf.theta, np.float64)
    if space is None:
        return theta
    own = cf.model()[1]
    if own.labels != space.labels:
        raise JaxreflError(f"space's parameters {space.labels} are not the fit's {own.labels}")
    same = (own.lower == space.lower) & (own.upper == space.upper)
    if np.all(same):
        return theta
    ok = np.all(np.isfinite(theta), -1)
    t = jnp.asarray(np.where(ok[:, None], theta, 0.0))
    moved = np.asarray(space.from_natural(own.to_natural(t), dtype=jnp.float64), np.float64)
    out = np.where(same[None, :], theta, moved)
    return np.where(ok[:, None], out, np.nan)


def laplace_theta_std(cf: CaptureFit, space: fit.ParamSpace | None = None) -> np.ndarray:
    """(N, P) the Laplace std in ``space``'s unconstrained coordinates (None: the fit's)
    from the job's std maps: std_x / |g'(theta*)| per entry, theta* the optimum in those
    coordinates (:func:`fit_theta`; module docstring); NaN where the fit has none."""
    space = cf.model()[1] if space is None else space
    theta = fit_theta(cf, space)
    std = np.stack([cf.maps[map_name(lab, "_std")].reshape(-1) for lab in space.labels], -1)
    ok = np.all(np.isfinite(theta), -1)
    dn = np.asarray(space.dnatural(jnp.asarray(np.where(ok[:, None], theta, 0.0))))
    return std / np.abs(dn)


def laplace_dof(cf: CaptureFit) -> np.ndarray:
    """(N,) degrees of freedom of each pixel's Laplace marginals: n_used - P where the fit
    estimated the pixel's noise scale from its residuals (the per-pixel models' default,
    Gaussian noise of unknown scale), inf where the noise variance is known (``pooled``'s
    capture-wide scale). NaN where n_used <= P (no estimate).

    With the scale estimated as s^2 = 2 cost / (n - P) and a Jeffreys prior
    p(sigma) ~ 1/sigma, the marginal posterior of each parameter of a linear(ised)
    least-squares problem is a Student t with n - P degrees of freedom and scale s times the
    sqrt of the diagonal of (J^T J)^-1 (Gelman et al., *Bayesian Data Analysis*, 3rd ed.,
    sec. 14.2), not the Gaussian of a known variance: with 8 photos x 3 channels and 7
    parameters its 90% interval is 6% wider."""
    n = cf.maps["n_used"].reshape(-1).astype(np.float64)
    if not cf.noise_estimated:
        return np.where(n > 0, np.inf, np.nan)
    p = len(cf.labels)
    return np.where(n > p, n - p, np.nan)


def laplace_interval(
    cf: CaptureFit, level: float, space: fit.ParamSpace | None = None
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Central Laplace interval of ``level`` of every parameter: {label: (lower, upper)},
    each (N,) in natural units.

    The interval is formed in the unconstrained coordinates, theta* +- q std_theta, with q
    the Student t quantile of :func:`laplace_dof` (the normal one where the noise is known),
    and mapped to natural units through the bijection (monotone, so the natural interval has
    the same probability, and it stays inside the parameter's bounds). NaN where the fit has
    no estimate."""
    from scipy import stats

    if not 0.0 < level < 1.0:
        raise JaxreflError(f"level must be in (0, 1), got {level}")
    space = cf.model()[1] if space is None else space
    theta = fit_theta(cf, space)
    s_t = laplace_theta_std(cf, space)
    dof = laplace_dof(cf)
    with np.errstate(invalid="ignore"):
        q = np.where(
            np.isinf(dof),
            stats.norm.ppf(0.5 + 0.5 * level),
            stats.t.ppf(0.5 + 0.5 * level, np.where(np.isfinite(dof), dof, 1.0)),
        )
    q = np.where(np.isnan(dof), np.nan, q)[:, None]
    ok = np.all(np.isfinite(theta), -1)[:, None] & np.isfinite(s_t) & np.isfinite(q)
    lo_t = np.where(ok, theta - q * s_t, 0.0)
    hi_t = np.where(ok, theta + q * s_t, 0.0)
    lo = np.asarray(space.natural_vector(jnp.asarray(lo_t)), np.float64)
    hi = np.asarray(space.natural_vector(jnp.asarray(hi_t)), np.float64)
    lo, hi = np.where(ok, np.minimum(lo, hi), np.nan), np.where(ok, np.maximum(lo, hi), np.nan)
    return {lab: (lo[:, j], hi[:, j]) for j, lab in enumerate(space.labels)}


def map_posterior(
    cf: CaptureFit, priors: str | Mapping[str, jp.Prior] = "population"
) -> tuple[jp.LogPosterior, dict[str, Any]]:
    """(log-posterior, where its priors came from) of a capture fit's pixels, as
    :func:`uncertainty_maps` samples it: the model and space of :func:`posterior_space`,
    noise of unknown scale per pixel (:func:`map_noise`), and ``priors`` as there (``"population"``,
    ``"default"`` or a mapping by parameter name). Its starting points and Laplace std are
    :func:`fit_theta` and :func:`laplace_theta_std` in ``lp.space``."""
    if isinstance(priors, str) and priors not in PRIOR_SOURCES:
        raise JaxreflError(f"priors must be one of {PRIOR_SOURCES} or a mapping, not {priors!r}")
    model, space = posterior_space(cf)
    if isinstance(priors, str):
        # estimated in natural units from the fit's own coordinates
        chosen, prior_summary = (
            population_priors(cf) if priors == "population" else ({}, {"source": "default"})
        )
    else:
        chosen, prior_summary = dict(priors), {"source": "given"}
    return jp.log_posterior(model, space, map_noise(cf), priors=chosen), prior_summary


def uncertainty_maps(
    capture,
    job: FitJob | None = None,
    options: jp.AdaptiveOptions | None = None,
    *,
    progress: bool = False,
    out_dir: str | Path | None = None,
    distributed: fit.Distributed | None = None,
    log: Callable[[str], None] | None = None,
) -> CaptureUncertainty:
    """Posterior uncertainty of every pixel of ``capture`` (module docstring).

    capture:  a :class:`jaxrefl.io.Capture`, or a folder :func:`jaxrefl.io.load_capture`
              reads
    job:      the fit (:class:`FitJob`; None: the default model); it must be float64
              (``FitJob(config=fit.FitConfig(dtype=np.float64))``, the default here), and
              ``jax_enable_x64`` on:
              log densities of thousands of observations differ by less than float32's
              resolution between nearby draws. Its ``tile_pixels`` is capped at the pixel
              count (one tile, no padding, for a small capture or crop)
    options:  :class:`jaxrefl.posterior.AdaptiveOptions` (None: its defaults), the
              map's priors included (its ``priors``: ``"population"``, the default, the
              lobe's priors estimated from the pixels Laplace calls reliable,
              :func:`population_priors`; ``"default"``:
              :func:`jaxrefl.posterior.default_priors`; or priors by parameter name, the
              defaults for the others) and its time limit (``time_limit_s``, counted from
              this call: the fit's time counts; after it no MCMC chunk is started, the
              pixels not sampled keep their Laplace summaries with method
              ``laplace_time_limit``, and with ``out_dir`` a rerun samples them)
    progress: tqdm bars over the fit's tiles and the MCMC chunks
    out_dir:  where the fit's tiles (``out_dir/fit``) and the MCMC chunks' draws
              (``out_dir/mcmc``) are written as they finish, and read back by a rerun
              (resume); None keeps everything in memory
    distributed: run as one process of a group (:class:`jaxrefl.fit.Distributed`, as
              :func:`fit_capture`): the fit's tiles and the MCMC chunks are split among
              the processes, which exchange them in ``out_dir`` (required); every process
              returns the whole result (process 0 writes it: :func:`write_uncertainty`)
    log:      called with one line of text per stage (the fit and the model it chose, the
              priors, each MCMC pass with its pixel count, and every
              :data:`jaxrefl.posterior.HEARTBEAT_S` seconds during a pass the chunks done
              and the time left); None: silent

    The model is the job's; ``auto`` (the default) chooses it as :func:`fit_capture` does,
    by held-out photos (:func:`jaxrefl.svbrdf.choose_model`). A model whose fit piles most
    pixels against a cap that a candidate lifts is not sampled (:mod:`._map_model`: more
    than :data:`WIDEN_SHARE` of the pixels at ``ggx``'s F0 cap -> :data:`WIDER` ``ggx_rgb``).
    ``pooled``'s posterior is conditional on its one shared width; the map relaxes it to a
    population of per-pixel widths (partial pooling, :mod:`._width_map`): each pixel's
    parameters move and widen with its own width, which the map gives as a last column
    ``alpha`` (the report's ``width_spread``: the population's centre and spread).
    """
    if jnp.asarray(0.0).dtype != jnp.float64:  # jax_enable_x64 is off
        raise JaxreflError(
            "uncertainty_maps computes posteriors in float64: enable it first with "
            'jax.config.update("jax_enable_x64", True)'
        )
    job = FitJob(config=fit.FitConfig(dtype=np.float64)) if job is None else job
    if job.dtype != np.float64:
        raise JaxreflError(f"uncertainty_maps needs a float64 FitJob, not {job.dtype}")
    options = jp.AdaptiveOptions() if options is None else options
    if distributed is not None:
        if out_dir is None:
            raise JaxreflError(
                "distributed uncertainty maps need out_dir: a folder every process can read "
                "and write (the processes exchange their tiles and chunks there)"
            )
        distributed.initialize()
    if isinstance(capture, (str, Path)):
        from jaxrefl.io import load_capture

        capture = load_capture(capture)
    time_limit_s = options.time_limit_s
    if time_limit_s is not None and distributed is not None:
        raise JaxreflError("a time limit applies to one process: drop it or --distributed")
    say = log if log is not None else (lambda _line: None)
    t0 = time.perf_counter()
    deadline = None if time_limit_s is None else t0 + time_limit_s
    _k, h, w, _c = capture.shape
    job = replace(job, tile_pixels=min(job.tile_pixels, h * w))
    say(f"fit: {h} x {w} pixels, {capture.n_photos} photos, model {job.model}")
    fit_dir = None if out_dir is None else Path(out_dir) / "fit"
    cf = fit_capture(capture, job, fit_dir, progress=progress, distributed=distributed)
    cf, choice = map_model(capture, cf, job.model, out_dir, progress, distributed, say)
    t_fit = time.perf_counter() - t0
    say(f"fit: model {cf.job.model} ({choice['why']}), {t_fit:.1f} s")
    say(f"noise: {cf.report['noise_level']['why']}")
    if cf.light is not None and cf.light.mode != "fixed":
        d = ", ".join(f"{v:+.2f}" for v in cf.light.offset_cm)
        say(f"light: {cf.light.mode}, flash offset ({d}) cm ({cf.light.frame})")
    t_pri = time.perf_counter()
    lp, prior_summary = map_posterior(cf, options.priors)
    t_pri = time.perf_counter() - t_pri
    say(f"priors: {prior_summary.get('source')}, {t_pri:.1f} s")
    # The job's held-out photos stay out of the posterior as they stayed out of the fit
    # (weight 0: still in the data, for posterior predictive draws of them).
    train = np.ones(capture.n_photos, bool)
    train[list(job.holdout)] = False
    # The posterior sees the light the fit estimated (FitJob.light), as the fit did.
    lit = capture if cf.light is None else cf.light.apply(capture)
    data = pixel_block(lit, 0, h * w, photos=train, dtype=np.float64)
    theta_std = laplace_theta_std(cf, lp.space)
    theta0 = fit_theta(cf, lp.space)
    noise0 = cf.maps["noise_std"].reshape(-1)
    noise0 = np.where(np.isfinite(noise0) & (noise0 > 0), noise0, _NOISE_START)
    t1 = time.perf_counter()
    umap = jp.adaptive_uncertainty(
        lp,
        data,
        theta0,
        theta_std,
        cf.maps["laplace_flag"].reshape(-1),
        options,
        noise_scale=noise0,
        dof=laplace_dof(cf),
        progress=progress,
        chunk_dir=None if out_dir is None else Path(out_dir) / "mcmc",
        deadline=deadline,
        log=log,
    )
    t_post = time.perf_counter() - t1
    # pooled: each pixel's own width around the shared one (._width_map)
    t_width = time.perf_counter()
    spread = pixel_widths(
        cf,
        lp,
        data,
        theta0,
        capture,
        None if out_dir is None else Path(out_dir) / "fit_widths",
        progress=progress,
        distributed=distributed,
    )
    if spread is not None:
        umap = relax_shared_width(umap, spread, lp.space.lower, lp.space.upper)
        say(
            f"widths: per-pixel around the shared {spread.alpha:.3g}, population centre "
            f"{spread.centre:.3g}, log std {spread.tau:.2f}, "
            f"{time.perf_counter() - t_width:.1f} s"
        )
    t_width = time.perf_counter() - t_width
    # The light's own uncertainty widens every pixel's intervals (._light_map), also where
    # auto kept the stated light (its lens-position spread); not where the user stated it.
    t_light = time.perf_counter()
    var = light_spread(cf, lp, data, capture, theta0, seed=options.seed)
    light_std = None
    if var is not None:
        umap, light_std = widen_for_light(umap, var, lp.space.lower, lp.space.upper)
        spent = time.perf_counter() - t_light
        term = map_term(cf.light)
        say(f"light: its uncertainty ({term}) carried into the intervals, {spent:.1f} s")
    t_light = time.perf_counter() - t_light
    return CaptureUncertainty(
        fit=cf,
        map=umap,
        posterior=lp,
        data=data,
        theta_std=theta_std,
        height=h,
        width=w,
        options=options,
        timings={
            "fit_s": t_fit,
            "priors_s": t_pri,
            "posterior_s": t_post,
            "light_s": t_light,
            "width_s": t_width,
            "total_s": time.perf_counter() - t0,
        },
        prior_summary=prior_summary,
        model_choice=choice,
        light_std=light_std,
        width_spread=spread,
    )


def write_uncertainty(result: CaptureUncertainty, out_dir: str | Path) -> list[Path]:
    """Write ``uncertainty.exr``, where pixels were sampled and their draws kept
    ``posterior.nc`` (:meth:`CaptureUncertainty.inference_data`), and the PNGs of
    :func:`write_uncertainty_plots` (std maps, R-hat map, pair plots) into ``out_dir``
    (created if missing); returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    exr = out / "uncertainty.exr"
    jp.write_uncertainty_exr(
        exr, result.map, result.height, result.width, metadata={"model": result.model}
    )
    files = [exr]
    idata = result.inference_data()
    if idata is not None:
        files.append(Path(jp.save_netcdf(idata, out / "posterior.nc")))
    return files + write_uncertainty_plots(result, out)

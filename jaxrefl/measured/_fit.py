"""Fit analytic models to one measured material and report error, parameters and time.

:func:`fit_model` fits one model from a batch of starts solved together
(:func:`~jaxrefl.measured.fit_multistart`: the automatic start, starts read off
the measured highlight and quasi-random ones, the best kept and certified; ``starts=None``
fits the single automatic start with :func:`jaxrefl.fit.fit_samples`), by the lean batched
Levenberg-Marquardt by default (a :class:`jaxrefl.fit.FitConfig` picks the solver, noise,
loss and dtype), and returns a :class:`ModelFit`; :func:`fit_brdf` prepares the samples
once (spectra to RGB or per band as :class:`~jaxrefl.measured.MeasuredOptions` says, angle
limit, solid-angle weights) and fits a whole set of models into a :class:`FitReport` whose
:meth:`FitReport.to_dict` is the ``report.json`` of ``jaxrefl fit-brdf``.

What is minimised (:class:`~jaxrefl.measured.MeasuredOptions`, with the samples a fit uses):
with ``cosine=True`` (default) the residual is (f̂ - f) cos(theta_i) per sample and channel,
i.e. exactly the quantity inside the cosine-weighted L2 of Ngan et al. 2005 (unweighted in
the solver: the solid-angle weights enter only the reported metrics); ``cosine=False`` fits
f_r itself. Samples beyond ``max_theta_deg`` (default 80 degrees, as Ngan et al.) from the
normal are left out of the fit and of the metrics.

Time: ``fit_time_s`` is the wall time of a second, identical call (compiled code is cached
by then), ``compile_time_s`` the extra time of the first call (tracing + XLA compilation +
the first run's transfers). With ``MeasuredOptions.retry_float64`` a float32 fit that
shows a reason of :func:`~jaxrefl.measured._retry.float64_reasons` is redone in float64;
both times are then included and the report says why, and which result was kept.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF
from jaxrefl.fit import FitConfig, FitResult, SamplesOptions, Status, fit_samples
from jaxrefl.io import MeasuredBRDF

from ._certificate import Certificate
from ._data import Channels, fit_channels, restrict
from ._fit_options import MeasuredOptions
from ._metrics import METRICS, error_metrics, sample_weights, usable_samples
from ._models import MODEL_DESCRIPTIONS, fresnel_name, resolve_models
from ._nested import nested_model
from ._retry import choose, float64_enabled, float64_reasons, x64
from ._start_options import MultiStart
from ._starts import fit_multistart

__all__ = ["FitReport", "ModelFit", "fit_brdf", "fit_model", "predict"]

_FLOAT32 = np.dtype(np.float32)
_FLOAT64 = np.dtype(np.float64)
_MEASURED_CONFIG = FitConfig(dtype=np.float32)
_MULTISTART = MultiStart()
_OPTIONS = MeasuredOptions()


def _check_dtype(config: FitConfig) -> np.dtype:
    """The config's dtype (None: float32), refusing any other than float32 or float64."""
    dt = _FLOAT32 if config.dtype is None else np.dtype(config.dtype)
    if dt not in (_FLOAT32, _FLOAT64):
        raise JaxreflError(f"dtype must be float32 or float64, not {dt}")
    return dt


def _run(dtype: np.dtype, fn: Callable[[], FitResult]) -> FitResult:
    if dtype == _FLOAT64 and not float64_enabled():
        with x64():
            return fn()
    return fn()


def _timed(
    dtype: np.dtype, fn: Callable[[], FitResult], timing: bool
) -> tuple[FitResult, float, float]:
    t0 = time.perf_counter()
    r = _run(dtype, fn)
    jax.block_until_ready(r.theta)
    t1 = time.perf_counter()
    if not timing:
        return r, t1 - t0, float("nan")
    r = _run(dtype, fn)
    jax.block_until_ready(r.theta)
    t2 = time.perf_counter()
    warm = t2 - t1
    return r, warm, max(t1 - t0 - warm, 0.0)


def predict(
    result: FitResult, wi: np.ndarray, wo: np.ndarray, channels: Channels = "joint"
) -> np.ndarray:
    """f_r (K, C) of a fit of :func:`fit_samples` at the given directions, in float64.

    ``channels="separate"`` (one problem per channel, theta of shape (C, P)) evaluates each
    channel with its own parameters.
    """
    with x64():
        wi64 = jnp.asarray(wi, jnp.float64)
        wo64 = jnp.asarray(wo, jnp.float64)
        theta = jnp.asarray(np.asarray(result.theta), jnp.float64)
        space = result.space
        if channels == "joint":
            f = result.model.eval(space.to_natural(theta[None]), wi64, wo64)
        else:
            f = jnp.concatenate(
                [
                    result.model.eval(space.to_natural(theta[c : c + 1]), wi64, wo64)
                    for c in range(theta.shape[0])
                ],
                axis=-1,
            )
        return np.asarray(f, dtype=np.float64)


def _cost64(f_hat: np.ndarray, f: np.ndarray, cos_i: np.ndarray, cosine: bool) -> float:
    """1/2 sum (f̂ - f)^2 (times cos_i^2 with ``cosine``): the fit's cost, in float64."""
    d = f_hat - f
    if cosine:
        d = d * cos_i[:, None]
    ok = np.isfinite(f)
    return float(0.5 * np.sum(np.where(ok, d, 0.0) ** 2)) if np.all(np.isfinite(d[ok])) else np.inf


def _status_summary(result: FitResult) -> str | dict[str, int]:
    s = np.asarray(result.status)
    if s.ndim == 0:
        return Status(int(s)).name
    return {k: v for k, v in result.status_counts().items() if v}


def _same(a: BRDF, b: BRDF) -> bool:
    """The same model (type and static settings)."""
    return type(a) is type(b) and bool(a == b)


def _to_list(x: Any) -> Any:
    a = np.asarray(x, dtype=np.float64)
    return float(a) if a.ndim == 0 else a.tolist()


@dataclass(frozen=True, eq=False)
class ModelFit:
    """One model fitted to one material.

    params:         natural parameters (NumPy; a leading channel axis C when fitted per
                    channel), from the kept result
    metrics:        the three errors of :mod:`jaxrefl.measured._metrics` (``METRICS``)
    cost:           the fit's 1/2 sum of squared residuals, re-evaluated in float64
    fit_time_s:     wall time of the fit without compilation (both fits if retried)
    compile_time_s: the extra time of the first call (compilation), NaN if not timed
    n_params:       free parameters per problem (P), times C problems when per channel
    dtype:          precision of the kept result (``np.dtype``, float32 or float64)
    channels:       ``"joint"`` or ``"separate"`` (:func:`~jaxrefl.measured._data.fit_channels`)
    config:         the fit's configuration (solver, noise, loss; its dtype the one asked for)
    retry:          None, or what the float64 retry found (reasons, costs, which was kept)
    certificate:    how far the starts agree on the optimum (:class:`Certificate` of the
                    kept run), None for a single-start fit
    """

    name: str
    model: BRDF
    result: FitResult
    params: dict[str, np.ndarray]
    metrics: dict[str, float]
    cost: float
    fit_time_s: float
    compile_time_s: float
    n_params: int
    dtype: np.dtype
    channels: Channels
    config: FitConfig
    retry: dict[str, Any] | None = None
    certificate: Certificate | None = None

    @property
    def fresnel(self) -> str | None:
        """The Fresnel part of a microfacet model (``"schlick"``, ``"dielectric"``, ...),
        None for a model without one."""
        return fresnel_name(self.model)

    @property
    def status(self) -> str | dict[str, int]:
        return _status_summary(self.result)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the per-model entry of ``report.json``)."""
        return {
            "model": self.name,
            "description": MODEL_DESCRIPTIONS.get(self.name, type(self.model).__name__),
            "n_params": self.n_params,
            "params": {k: _to_list(v) for k, v in self.params.items()},
            "metrics": {k: self.metrics[k] for k in METRICS},
            "cost": self.cost,
            "status": self.status,
            "iterations": np.asarray(self.result.iterations).tolist(),
            "fit_time_s": self.fit_time_s,
            "compile_time_s": self.compile_time_s,
            "dtype": self.dtype.name,
            "channels": self.channels,
            "backend": self.result.backend,
            "retry": self.retry,
            "fresnel": self.fresnel,
            "certificate": None if self.certificate is None else self.certificate.to_dict(),
        }


def fit_model(
    model: BRDF,
    measured: MeasuredBRDF,
    *,
    name: str | None = None,
    options: MeasuredOptions = _OPTIONS,
    config: FitConfig = _MEASURED_CONFIG,
    weight: np.ndarray | None = None,
    timing: bool = True,
    starts: MultiStart | None = _MULTISTART,
    nested: ModelFit | FitResult | None = None,
) -> ModelFit:
    """Fit ``model`` to ``measured`` (module docstring) and compute the error metrics.

    options:       the samples and channels used, what is minimised and the float64 retry
                   (:class:`MeasuredOptions`: angle limit, cosine residual, retry; spectral
                   data as RGB under an illuminant, fitted jointly, or one problem a band)
    config:        solver, noise, loss and dtype (:class:`jaxrefl.fit.FitConfig`); dtype
                   float32 (default; None means float32 here, the fast one) or float64,
                   which works whether or not JAX runs with x64 enabled (it is switched on
                   around the fit)
    weight:        per-sample solid-angle weights for the metrics (default 1), aligned
                   with ``measured`` before the angle limit is applied
    starts:        the multi-start settings (:class:`MultiStart`; default: the data-driven
                   starts and 24 quasi-random ones solved together, continued and
                   perturbed while they disagree, the best kept and certified, see
                   ``_starts``); None: one start, the automatic one of
                   :func:`jaxrefl.fit.fit_samples`
    nested:        for a model that contains a smaller one
                   (:func:`~jaxrefl.measured.nested_model`: Lafortune with L - 1 lobes for
                   L), the smaller model's fit to the same samples and channels; its
                   optimum plus one new lobe joins the starts (``starts.nested``). When
                   None, the smaller model is fitted first by this function with the same
                   settings (recursively; its time is not in ``fit_time_s``)
    """
    name = name or type(model).__name__
    max_theta_deg, cosine = options.max_theta_deg, options.cosine
    measured, channels = fit_channels(measured, options)
    problem = SamplesOptions(channels=channels, cosine=cosine)
    ok = usable_samples(measured.wi, measured.wo, measured.values, max_theta_deg)
    data = measured.select(ok)
    w = None if weight is None else np.asarray(weight, dtype=np.float64)[ok]
    if len(data) == 0:
        raise JaxreflError(f"{measured.source}: no usable samples within {max_theta_deg} degrees")
    f = np.asarray(data.values)
    cos_i = data.wi[:, 2]

    dtype = _check_dtype(config)
    # ``data`` is within the angle limit already (and its channels as fitted here).
    inside = replace(options, max_theta_deg=None)
    inner = nested_model(model) if starts is not None and starts.nested else None
    if inner is not None and nested is None:
        nested = fit_model(
            inner,
            data,
            options=inside,
            config=config,
            timing=False,
            starts=starts,
        )
    seed_fit = nested.result if isinstance(nested, ModelFit) else nested
    if inner is None:
        seed_fit = None

    certs: dict[np.dtype, Certificate] = {}

    def run(dt: np.dtype) -> tuple[FitResult, float, float]:
        def fn() -> FitResult:
            cfg = config.replace(dtype=dt)
            if starts is None:
                return fit_samples(model, data, options=problem, config=cfg)
            r, certs[dt], _ = fit_multistart(
                model,
                data,
                options=inside,
                config=cfg,
                starts=starts,
                nested=seed_fit,
            )
            return r

        return _timed(dt, fn, timing)

    result, t_fit, t_comp = run(dtype)
    kept = dtype
    f_hat = predict(result, data.wi, data.wo, channels)
    cost = _cost64(f_hat, f, cos_i, cosine)
    retry = None
    if options.retry_float64 and dtype == _FLOAT32:
        reasons = float64_reasons(result)
        if not np.isfinite(cost) and "non-finite cost" not in reasons:
            reasons.append("non-finite cost")
        if reasons:
            r64, t64, c64 = run(_FLOAT64)
            f_hat64 = predict(r64, data.wi, data.wo, channels)
            cost64 = _cost64(f_hat64, f, cos_i, cosine)
            kept = np.dtype(choose(cost, cost64))
            retry = {
                "reasons": reasons,
                "float32_status": _status_summary(result),
                "float32_cost": cost,
                "float64_status": _status_summary(r64),
                "float64_cost": cost64,
                "kept": kept.name,
                "float64_fit_time_s": t64,
            }
            t_fit += t64
            t_comp = t_comp + c64
            if kept == _FLOAT64:
                result, f_hat, cost = r64, f_hat64, cost64
    metrics = error_metrics(f, f_hat, data.wi, data.wo, weight=w, max_theta_deg=None)
    params = {k: np.asarray(v, dtype=np.float64) for k, v in result.params.items()}
    n_problems = int(np.asarray(result.status).size)
    return ModelFit(
        name=name,
        model=model,
        result=result,
        params=params,
        metrics=metrics,
        cost=cost,
        fit_time_s=t_fit,
        compile_time_s=t_comp,
        n_params=int(result.space.size) * n_problems,
        dtype=kept,
        channels=channels,
        config=config,
        retry=retry,
        certificate=certs.get(kept),
    )


@dataclass(frozen=True, eq=False)
class FitReport:
    """Every model fitted to one material: :attr:`fits` by model name, the prepared samples
    (:attr:`measured`, after colour conversion and the angle limit) and the settings."""

    measured: MeasuredBRDF
    fits: dict[str, ModelFit]
    settings: dict[str, Any] = field(default_factory=dict)
    weight: np.ndarray | None = None

    def best(self, metric: str = "cosine_weighted_l2") -> str:
        """Name of the model with the lowest ``metric`` (NaN counts as worst)."""
        vals = {k: v.metrics[metric] for k, v in self.fits.items()}
        return min(vals, key=lambda k: np.inf if not np.isfinite(vals[k]) else vals[k])

    def fresnel_comparison(self, metric: str = "cosine_weighted_l2") -> dict[str, Any]:
        """For every microfacet model fitted with both Fresnel terms (a name and its
        ``_dielectric`` variant): both ``metric`` values and the better term, by model name."""
        out: dict[str, Any] = {}
        for k, v in self.fits.items():
            other = self.fits.get(k + "_dielectric")
            if v.fresnel != "schlick" or other is None or other.fresnel != "dielectric":
                continue
            a, b = v.metrics[metric], other.metrics[metric]
            out[k] = {
                "metric": metric,
                "schlick": a,
                "dielectric": b,
                "better": "dielectric" if b < a else "schlick",
            }
        return out

    def table(self) -> str:
        """A Markdown table: model, parameters, the three errors, time, status, and how
        many starts agree on the optimum (``doubtful``: fewer than the stated share)."""
        head = (
            "| model | P | cos-weighted L2 | log L2 | relative L2 | fit ms | compile s | status "
            "| starts agree |"
        )
        rows = [head, "|" + "---|" * 9]
        for k, v in self.fits.items():
            m = v.metrics
            st = v.status if isinstance(v.status, str) else ",".join(v.status)
            if v.retry:
                st += f" (retried: kept {v.retry['kept']})"
            rows.append(
                f"| {k} | {v.n_params} | {m['cosine_weighted_l2']:.4g} | {m['log_l2']:.4g} | "
                f"{m['relative_l2']:.4g} | {1e3 * v.fit_time_s:.1f} | {v.compile_time_s:.2f} | "
                f"{st} | {v.certificate.short() if v.certificate else '-'} |"
            )
        for k, c in self.fresnel_comparison().items():
            rows.append(
                f"\n{k}: {c['better']} Fresnel fits better (cos-weighted L2 Schlick "
                f"{c['schlick']:.4g}, dielectric {c['dielectric']:.4g})"
            )
        return "\n".join(rows)

    def to_dict(self) -> dict[str, Any]:
        """The content of ``report.json``."""
        m = self.measured
        meta = {k: v for k, v in m.meta.items() if k in ("format", "sample", "color", "restricted")}
        return {
            "material": m.name,
            "source": m.source,
            "n_samples": len(m),
            "channels": list(m.channels),
            "data": meta,
            "settings": self.settings,
            "metrics_definition": {
                "cosine_weighted_l2": "sqrt(sum_k w_k sum_c (fhat-f)^2 cos_i^2 / (C sum_k w_k)) "
                "[1/sr], Ngan et al. 2005",
                "log_l2": "sqrt(sum_k w_k sum_c (ln(1+fhat cos_i) - ln(1+max(f,0) cos_i))^2 "
                "/ (C sum_k w_k)), Low et al. 2012",
                "relative_l2": "sqrt(sum_k w_k sum_c (fhat-f)^2 / sum_k w_k sum_c f^2)",
                "weights": "solid angle per sample (MERL cells) else 1",
            },
            "best": {k: self.best(k) for k in METRICS},
            "models": {k: v.to_dict() for k, v in self.fits.items()},
            "fresnel_comparison": self.fresnel_comparison(),
            "jax": {"version": jax.__version__, "backend": jax.default_backend()},
        }


def fit_brdf(
    measured: MeasuredBRDF,
    models: Iterable[str] | Mapping[str, BRDF] | None = None,
    *,
    options: MeasuredOptions = _OPTIONS,
    config: FitConfig = _MEASURED_CONFIG,
    timing: bool = True,
    progress: Callable[[str], None] | None = None,
    starts: MultiStart | None = _MULTISTART,
) -> FitReport:
    """Fit every model in ``models`` (default: :data:`~jaxrefl.measured.DEFAULT_MODELS`) to
    one material and collect a :class:`FitReport`. The options are those of :func:`fit_model`
    (spectral data, e.g. Cornell's: as RGB under ``options.illuminant`` with the CIE 1931
    CMFs, :func:`to_rgb`, fitted jointly, or one problem a band: ``options.spectral``).
    """
    built = resolve_models(models)
    weight_all = sample_weights(measured)
    data, channels = fit_channels(measured, options)
    max_theta_deg = options.max_theta_deg
    ok = usable_samples(data.wi, data.wo, data.values, max_theta_deg)
    prepared = restrict(data, max_theta_deg)
    weight = weight_all[ok]
    if len(prepared) == 0:
        raise JaxreflError(f"{measured.source}: no usable samples within {max_theta_deg} degrees")
    fits: dict[str, ModelFit] = {}
    # A model that contains another (Lafortune with L - 1 lobes for L) starts from its fit:
    # fit the smaller ones first, report in the order asked.
    order = sorted(built, key=lambda k: getattr(built[k], "num_lobes", 0))
    for name in order:
        model = built[name]
        inner = nested_model(model)
        found = [v for v in fits.values() if inner is not None and _same(v.model, inner)]
        if progress is not None:
            progress(name)
        fits[name] = fit_model(
            model,
            prepared,
            name=name,
            # ``prepared`` is within the angle limit already, its channels as fitted here.
            options=replace(options, max_theta_deg=None),
            config=config,
            weight=weight,
            timing=timing,
            starts=starts,
            nested=found[0] if found else None,
        )
    fits = {k: fits[k] for k in built}
    opts = {k: v for k, v in options.to_json().items() if k != "type"}
    settings = {
        # The spectral choice applies to spectral data alone, the illuminant to their RGB.
        "spectral": options.spectral if measured.wavelengths_nm is not None else None,
        "illuminant": options.illuminant if data is not measured else None,
        "channels": channels,
        **{k: v for k, v in opts.items() if k not in ("spectral", "illuminant")},
        "config": config.to_json(),
        "starts": None if starts is None else starts.to_json(),
    }
    return FitReport(prepared, fits, settings, weight)

"""Automatic pruning: drop the components a material (or a cluster of pixels) does not need.

Start from a rich :class:`~jaxrefl.measured.Components` assembly and eliminate backwards:
fit every assembly with one active component removed, and drop the component whose removal
gives the best criterion, as long as that is *no worse* than keeping it; stop when every
removal would worsen it. Criteria, per pixel (or measured material) with n active residuals
(whitened residual r of :func:`jaxrefl.fit.make_residual`, RSS = |r|^2 at the fit theta*,
P free parameters):

* ``"bic"`` (Schwarz 1978), Gaussian noise of unknown variance, lower is better:

      BIC = n ln(RSS / n) + P ln n

* ``"evidence"``: the Laplace approximation of the log marginal likelihood (MacKay 1992,
  eq. 4.7; Bishop 2006, eq. 4.137), higher is better:

      ln Z = ln N(r | 0, s^2) + ln p(theta*) + (P/2) ln 2 pi - 1/2 ln det H,
      H = J^T J / s^2 + I / tau^2,       J = dr/dtheta at theta*  (J^T W J of the fit)

  with the noise variance s^2 = RSS_rich / (n - P_rich) of the richest fit (the same for
  every candidate, so the criteria compare models, not noise estimates) or 1 with
  ``noise="known"`` (residuals already whitened by the right sigma), and a Gaussian prior
  N(mu, tau^2 I) on the unconstrained theta: mu = the model's default parameters,
  tau = ``prior_width`` (default 3: an albedo anywhere in (0.05, 0.95), alpha within a
  factor e^3 = 20 of 0.2). The log-determinant comes from a Cholesky factor of H.

A *group* of pixels shares the decision: its criterion is the sum of its pixels' criteria
(independent pixels, each with its own parameters). ``PruneOptions.groups`` is ``"pixel"``
(every pixel alone), ``"all"`` (one material: the whole batch), ``"labels"`` (an (N,) array
of labels given to :func:`prune`), or ``"kmeans"``: :func:`kmeans` on each pixel's colour
and gloss read from its observations (log median of obs / scale, log ratio of the largest
value to the median, per channel) into ``n_clusters`` clusters (an SVBRDF's materials).
Every setting is a field of :class:`~jaxrefl.measured.PruneOptions` (:mod:`._prune_options`).

Before anything is fitted, pixels the scene does not need are removed
(:func:`~jaxrefl.measured._compact.compact`, with ``min_obs`` = the rich model's parameter
count); the report counts them. Every assembly is fitted once for all kept pixels
(:func:`~jaxrefl.measured._components.fit_components`; the rich one from its core's
automatic start, the others from the rich fit by
:func:`~jaxrefl.measured._components.start_from`) and cached, whichever groups use it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import (
    FitConfig,
    FitResult,
    PixelData,
    make_residual,
    pixel_data,
    sample_arrays,
)

from ._compact import Compacted, compact
from ._components import Components, fit_components, param_space, start_from
from ._prune_options import PruneOptions

__all__ = [
    "GroupPruning",
    "PruneReport",
    "PruneStep",
    "criteria",
    "kmeans",
    "measured_pixel_data",
    "prune",
]

_OPTIONS = PruneOptions()


@eqx.filter_jit
def _rss_logdet(res, theta, data, mu, tau, s2):
    """Per pixel: RSS, active residual count, ln det H, |theta - mu|^2 (module docstring)."""

    def one(t, d, var):
        ok = jnp.all(jnp.isfinite(t))
        # A pixel without an estimate is linearised at mu and gets NaN criteria below.
        t_s = jnp.where(ok, t, mu)
        r = res(t_s, d)
        jac = jax.jacfwd(res)(t_s, d)
        active = jnp.sum(jnp.any(jac != 0.0, axis=-1) | (r != 0.0))
        p = t.shape[-1]
        h = jac.T @ jac / var + jnp.eye(p, dtype=t.dtype) / (tau * tau)
        chol = jnp.linalg.cholesky(h)
        logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))
        dev = jnp.sum((t_s - mu) ** 2)
        nan = jnp.asarray(jnp.nan, t.dtype)
        return (
            jnp.where(ok, jnp.sum(r * r), nan),
            active,
            jnp.where(ok, logdet, nan),
            jnp.where(ok, dev, nan),
        )

    return jax.vmap(one)(theta, data, s2)


def criteria(
    result: FitResult,
    data: PixelData,
    *,
    noise_var: np.ndarray | float | None = None,
    prior_width: float = 3.0,
) -> dict[str, np.ndarray]:
    """Per-pixel ``bic``, ``evidence`` (ln Z), ``rss``, ``n`` and ``P`` of a fit
    (:func:`jaxrefl.fit.fit_pixels` result on ``data``; module docstring for the formulas).

    noise_var: s^2 per pixel (N,) or one value; None estimates it from this fit,
               RSS / (n - P).
    """
    space = result.space
    res = make_residual(result.model, space)
    theta = jnp.asarray(result.theta)
    dtype = theta.dtype
    data = data.astype(dtype)
    p = int(space.size)
    mu = space.default_theta(dtype)
    n_px = theta.shape[0]
    s2 = jnp.ones((n_px,), dtype)
    rss, n, logdet, dev = (
        np.asarray(x, np.float64) for x in _rss_logdet(res, theta, data, mu, float(prior_width), s2)
    )
    if noise_var is None:
        noise_var = rss / np.maximum(n - p, 1.0)
    var = np.broadcast_to(np.asarray(noise_var, np.float64), (n_px,))
    # H depends on s^2: redo the factorisation with the chosen noise variance.
    _, _, logdet, _ = (
        np.asarray(x, np.float64)
        for x in _rss_logdet(res, theta, data, mu, float(prior_width), jnp.asarray(var, dtype))
    )
    n_safe = np.maximum(n, 1.0)
    # A perfect fit (RSS = 0) has BIC -inf; floor RSS at the tiniest normal float instead.
    bic = n * np.log(np.maximum(rss, np.finfo(np.float64).tiny) / n_safe) + p * np.log(n_safe)
    tau2 = prior_width**2
    log_lik = -0.5 * n * np.log(2.0 * np.pi * var) - 0.5 * rss / var
    log_prior = -0.5 * p * np.log(2.0 * np.pi * tau2) - 0.5 * dev / tau2
    evidence = log_lik + log_prior + 0.5 * p * np.log(2.0 * np.pi) - 0.5 * logdet
    return {
        "bic": bic,
        "evidence": evidence,
        "rss": rss,
        "n": n,
        "P": np.full(n_px, p),
        "noise_var": var,
    }


def _cluster_features(data: PixelData) -> np.ndarray:
    """Colour and gloss of each pixel from its own observations, (N, 2 C): per channel the
    log median of obs / scale (the colour) and the log ratio of the largest value to the
    median (how much a highlight stands out). Taken from the data rather than from a fit:
    a rich fit may explain a few noisy samples of a matte pixel with a needle-sharp lobe."""
    obs, scale, w = (np.asarray(x, np.float64) for x in (data.obs, data.scale, data.weight))
    ok = np.isfinite(obs) & (scale > 0) & (w > 0)
    v = np.where(ok, obs / np.where(ok, scale, 1.0), np.nan)
    # Observations at or below 0 (noise around black) would make the logs undefined; the
    # 1e-6 floor is far below any reflectance a capture resolves.
    med = np.maximum(np.nanmedian(v, axis=1), 1e-6)
    hi = np.maximum(np.nanmax(v, axis=1), 1e-6)
    return np.concatenate([np.log(med), np.log(hi / med)], axis=1)


def kmeans(
    features: np.ndarray, k: int, *, seed: int = 0, iters: int = 50, restarts: int = 10
) -> np.ndarray:
    """(N,) labels of Lloyd's k-means with k-means++ seeding (Arthur & Vassilvitskii 2007)
    on the columns of ``features`` (N, D), each standardised to unit variance first; the
    best (lowest within-cluster sum of squares) of ``restarts`` seedings."""
    x = np.asarray(features, np.float64)
    x = np.where(np.isfinite(x), x, np.nanmean(np.where(np.isfinite(x), x, np.nan), axis=0))
    sd = np.std(x, axis=0)
    # Constant columns carry no cluster information; dividing by 1 leaves them at 0 spread.
    x = (x - x.mean(axis=0)) / np.where(sd > 0, sd, 1.0)
    n = x.shape[0]
    k = int(min(k, n))
    rng = np.random.default_rng(seed)
    best, best_ss = np.zeros(n, int), np.inf
    for _ in range(max(1, restarts)):
        centres = [x[rng.integers(n)]]
        for _ in range(1, k):
            d2 = np.min(((x[:, None] - np.asarray(centres)[None]) ** 2).sum(-1), axis=1)
            prob = d2 / d2.sum() if d2.sum() > 0 else np.full(n, 1.0 / n)
            centres.append(x[rng.choice(n, p=prob)])
        c = np.asarray(centres)
        labels = np.full(n, -1)
        for _ in range(iters):
            new = np.argmin(((x[:, None] - c[None]) ** 2).sum(-1), axis=1)
            if np.array_equal(new, labels):
                break
            labels = new
            for j in range(k):
                if np.any(labels == j):
                    c[j] = x[labels == j].mean(axis=0)
        ss = float(((x - c[labels]) ** 2).sum())
        if ss < best_ss:
            best, best_ss = labels, ss
    return best


@dataclass(frozen=True)
class PruneStep:
    """One removal: ``component`` dropped, criterion ``before`` -> ``after`` (summed over
    the group) and the assemblies it went from and to."""

    component: str
    before: float
    after: float
    model_before: str
    model_after: str

    @property
    def why(self) -> str:
        return (
            f"removing {self.component} changed the criterion {self.before:.6g} -> {self.after:.6g}"
        )


@dataclass(frozen=True)
class GroupPruning:
    """The decision for one group of pixels.

    chosen:  the pruned assembly
    dropped: the removals made, in order
    kept:    for each component still in ``chosen``: the criterion after removing it
             (worse than keeping it, which is why it stayed) and the value with it
    """

    group: int
    n_pixels: int
    chosen: Components
    dropped: list[PruneStep]
    kept: dict[str, tuple[float, float]]

    def to_dict(self) -> dict[str, Any]:
        return {
            "group": self.group,
            "n_pixels": self.n_pixels,
            "chosen": self.chosen.label,
            "dropped": [
                {"component": s.component, "before": s.before, "after": s.after, "why": s.why}
                for s in self.dropped
            ],
            "kept": {
                c: {"with": w, "without": wo, "why": "removing it worsens the criterion"}
                for c, (w, wo) in self.kept.items()
            },
        }


@dataclass(frozen=True, eq=False)
class PruneReport:
    """Pruning of every group, the cached fits, and the pixels left out.

    options:  the settings it ran with (:class:`PruneOptions`)
    labels:   (N_kept,) group of each kept pixel (order of ``compacted.index``)
    fits:     assembly label -> (spec, FitResult on the kept pixels, criteria dict)
    """

    options: PruneOptions
    rich: Components
    groups: list[GroupPruning]
    labels: np.ndarray
    compacted: Compacted
    fits: dict[str, tuple[Components, FitResult, dict[str, np.ndarray]]] = field(repr=False)

    @property
    def criterion(self) -> str:
        """``options.criterion``."""
        return self.options.criterion

    def chosen_per_pixel(self) -> np.ndarray:
        """(N_in,) label of the chosen assembly per input pixel ("" where left out)."""
        out = np.full(self.compacted.n_in, "", dtype=object)
        by_group = {g.group: g.chosen.label for g in self.groups}
        out[self.compacted.index] = [by_group[int(g)] for g in self.labels]
        return out.astype(str)

    def summary(self) -> str:
        lines = [f"pruning by {self.criterion} from {self.rich.label}"]
        c = self.compacted.counts
        lines.append(
            f"pixels: {c['kept']} of {c['pixels_in']} fitted; left out: "
            + ", ".join(f"{r} {c[r]}" for r in ("masked", "shadowed", "saturated", "no_signal"))
            + f"; observation columns {c['columns_kept']} of {c['columns_in']}"
        )
        for g in self.groups:
            drops = ", ".join(s.component for s in g.dropped) or "nothing"
            lines.append(f"group {g.group} ({g.n_pixels} px): {g.chosen.label} (dropped {drops})")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return {
            "criterion": self.criterion,
            "options": self.options.to_json(),
            "rich": self.rich.label,
            "pixels": self.compacted.counts,
            "groups": [g.to_dict() for g in self.groups],
        }


def _better(a: float, b: float, criterion: str) -> bool:
    """a is no worse than b."""
    return a <= b if criterion == "bic" else a >= b


def _group_value(crit: dict[str, np.ndarray], criterion: str, members: np.ndarray) -> float:
    v = crit[criterion][members]
    # A pixel without an estimate under this assembly makes the assembly unusable here.
    return (
        float(np.sum(v))
        if np.all(np.isfinite(v))
        else (math.inf if criterion == "bic" else -math.inf)
    )


def prune(
    data: PixelData,
    rich: Components,
    options: PruneOptions = _OPTIONS,
    *,
    mask: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    config: FitConfig = FitConfig(),
    cache: Mapping[str, tuple[Components, FitResult, dict[str, np.ndarray]]] | None = None,
) -> PruneReport:
    """Prune ``rich`` for every group of the pixels of ``data`` (module docstring).

    data:        :class:`~jaxrefl.fit.PixelData` (N, K, C); a measured material is one pixel
                 (:func:`measured_pixel_data`)
    options:     the criterion, the groups and the pixels kept (:class:`PruneOptions`;
                 ``saturation`` and ``noise_floor`` are those of
                 :func:`~jaxrefl.measured._compact.compact`)
    mask:        (N,) bool, False = not part of the scene
    labels:      (N,) group of every pixel, with ``options.groups == "labels"`` only
    config:      solver, noise, loss and dtype of every fit (:class:`jaxrefl.fit.FitConfig`,
                 as :func:`fit_components` takes it)
    cache:       :attr:`PruneReport.fits` of an earlier call on the same data, rich model,
                 fit configuration, ``noise`` and ``prior_width`` (e.g. to compare criteria
                 or groupings without refitting)
    """
    o = options
    if (labels is None) != (o.groups != "labels"):
        raise JaxreflError(
            'prune takes labels with PruneOptions(groups="labels") and only then, got '
            f"groups={o.groups!r} and {'no ' if labels is None else ''}labels"
        )
    criterion = o.criterion
    c = data.obs.shape[-1]
    p_rich = param_space(rich.build(), c).size
    comp = compact(
        data, mask, min_obs=p_rich + 1, saturation=o.saturation, noise_floor=o.noise_floor
    )
    d = comp.data
    n = d.obs.shape[0]
    if n == 0:
        raise JaxreflError(f"no pixel left to fit: {comp.counts}")
    fits = dict(cache or {})
    if rich.label in fits:
        rich_fit, var = fits[rich.label][1], fits[rich.label][2]["noise_var"]
    else:
        rich_fit = fit_components(rich, d, config=config)
        # The rich fit's residual variance is every candidate's s^2 (module docstring).
        base = criteria(rich_fit, d, noise_var=1.0 if o.noise == "known" else None)
        var = base["noise_var"]
        crit = criteria(rich_fit, d, noise_var=var, prior_width=o.prior_width)
        fits[rich.label] = (rich, rich_fit, crit)
    init_params = {k: np.asarray(v) for k, v in rich_fit.params.items()}

    def get(spec: Components) -> dict[str, np.ndarray]:
        if spec.label not in fits:
            init = start_from(init_params, spec, n, c)
            r = fit_components(spec, d, init=init, config=config)
            fits[spec.label] = (spec, r, criteria(r, d, noise_var=var, prior_width=o.prior_width))
        return fits[spec.label][2]

    if o.groups == "pixel":
        labels = np.arange(n)
    elif o.groups == "all":
        labels = np.zeros(n, int)
    elif o.groups == "kmeans":
        labels = kmeans(_cluster_features(d), o.n_clusters, seed=o.seed)
    else:
        labels = np.asarray(labels).reshape(-1)
        if labels.shape[0] == comp.n_in:
            labels = labels[comp.index]
        elif labels.shape[0] != n:
            raise JaxreflError(f"labels has {labels.shape[0]} entries for {comp.n_in} pixels")
    out = []
    for g in np.unique(labels):
        members = np.flatnonzero(labels == g)
        current = rich
        value = _group_value(get(rich), criterion, members)
        dropped: list[PruneStep] = []
        kept: dict[str, tuple[float, float]] = {}
        while True:
            cands = {
                k: _group_value(get(s), criterion, members) for k, s in current.removals().items()
            }
            if not cands:
                break
            pick = (min if criterion == "bic" else max)(cands, key=lambda c: cands[c])
            if not _better(cands[pick], value, criterion):
                kept = {k: (value, v) for k, v in cands.items()}
                break
            nxt = current.without(pick)
            dropped.append(PruneStep(pick, value, cands[pick], current.label, nxt.label))
            current, value = nxt, cands[pick]
        out.append(GroupPruning(int(g), int(members.size), current, dropped, kept))
    return PruneReport(o, rich, out, labels, comp, fits)


def measured_pixel_data(measured: Any, cosine: bool = True, dtype=None) -> PixelData:
    """One measured material (:class:`~jaxrefl.io.MeasuredBRDF`) as a single pixel: K
    samples in C channels, residual (f̂ - f) cos(theta_i) with ``cosine`` (as
    :func:`jaxrefl.measured.fit_model` fits), samples below the horizon or non-finite at
    weight 0."""
    wi, wo, f = (np.asarray(x, np.float64) for x in (measured.wi, measured.wo, measured.values))
    finite = np.isfinite(f)
    obs, scale, weight = sample_arrays(
        wi, wo, np.where(finite, f, 0.0), cosine=cosine, keep=np.all(finite, axis=-1)
    )
    dt = jnp.asarray(0.0).dtype if dtype is None else dtype
    return pixel_data(
        obs[None],
        wi[None],
        wo[None],
        scale=None if scale is None else scale[None],
        weight=weight[None],
        dtype=dt,
    )

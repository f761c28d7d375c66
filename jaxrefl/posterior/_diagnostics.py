"""Posterior draws as ArviZ InferenceData; convergence diagnostics; plots; predictive checks.

:func:`to_inference_data` puts :class:`~jaxrefl.posterior.Samples` into an
``arviz.InferenceData`` with groups ``posterior`` (natural parameters; dims ``(chain,
draw, pixel)``), ``sample_stats`` (``acceptance_rate``, ``diverging``, ``lp``),
``observed_data`` (``obs`` (pixel, OBSERVATION, channel)), ``constant_data`` (the
likelihood's ``weight`` (its power, 0: masked out) and ``censored`` (+1 saturated: the
value is at least obs; -1 dark: at most obs; 0 a value)) and, if given,
``log_likelihood`` (``obs``: the pointwise log-likelihood of every observation at every
draw, :func:`log_likelihood_draws`, so ``az.loo`` and ``az.compare`` rank models fitted
to the same data) and ``posterior_predictive`` (``obs``: a thinned set of draws'
predictions plus noise). OBSERVATION names the K axis (``photo`` for a capture, ``sample``
for a measured file); ``channel`` has coordinates R, G, B for three channels. Variable
names are the parameter labels with dots as underscores (``albedo.R`` -> ``albedo_R``;
NetCDF names stay portable); the labels are kept in ``attrs``. :func:`save_netcdf` writes
it (``idata.to_netcdf``, uncompressed by default: zlib on a whole map's draws costs several
times the write itself), ``arviz.from_netcdf`` reads it back.

ArviZ 0.x only: ArviZ 1.0 replaced ``InferenceData`` by xarray's ``DataTree`` and changed
``from_dict``; ``pyproject.toml`` pins ``arviz<1`` until this module moves to it.

Diagnostics (:func:`diagnostics`): rank-normalised split R-hat, bulk and tail ESS (Vehtari
et al. 2021, *Rank-normalization, folding, and localization: an improved R-hat*, via
ArviZ), the number of divergent transitions and the mean acceptance rate, per pixel and
parameter. Plots: trace, rank (ArviZ), corner (pairwise scatter + marginal histograms),
and posterior predictive checks against the observations (:func:`plot_ppc`).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import L2, PixelData

from ._fastdiag import rank_diagnostics
from ._samples import Samples

__all__ = [
    "ChunkSummary",
    "diagnostics",
    "log_likelihood_draws",
    "plot_corner",
    "plot_ppc",
    "plot_rank",
    "plot_trace",
    "posterior_predictive",
    "save_netcdf",
    "split_rhat",
    "summarise",
    "to_inference_data",
    "var_name",
]


_CHANNELS = {3: ("R", "G", "B"), 1: ("Y",)}  # channel coordinates by channel count


def _az():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # ArviZ's notice of its refactor
        import arviz

    return arviz


def var_name(label: str) -> str:
    """The InferenceData variable of a parameter label (``albedo.R`` -> ``albedo_R``)."""
    return label.replace(".", "_")


def split_rhat(x: np.ndarray) -> np.ndarray:
    """(D,) rank-normalised split R-hat of draws (chains, draws, D)."""
    az = _az()
    x = np.asarray(x, dtype=np.float64)
    return np.array([float(az.rhat(x[..., j])) for j in range(x.shape[-1])])


def posterior_predictive(
    lp, samples: Samples, data: PixelData, *, n_draws: int = 100, seed: int = 0, normals=None
) -> np.ndarray:
    """(N, n_draws, K, C) replicated observations: predictions at thinned draws plus noise
    of the noise model (times the sampled scale, if any)."""
    n, c, m, d = samples.theta.shape
    idx = np.linspace(0, c * m - 1, min(n_draws, c * m)).round().astype(int)
    th = np.swapaxes(samples.theta, 1, 2).reshape(n, c * m, d)[:, idx]
    th = np.nan_to_num(th)
    rng = np.random.default_rng(seed)
    if normals is None:
        normals = jnp.zeros((n, 1, 3), data.obs.dtype)

    def one(t, dd, nn):
        return jax.vmap(lambda tt: lp.predict(tt, dd, nn if lp.light is not None else None))(t)

    pred = np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(th, data.obs.dtype), data, normals))
    sd = np.asarray(jax.vmap(lp.residual.noise.std)(data.obs))[:, None]
    if lp.noise_scale is not None:
        sd = sd * np.exp(th[..., -1])[..., None, None]
    return pred + sd * rng.normal(size=pred.shape)


def log_likelihood_draws(lp, samples: Samples, data: PixelData, normals=None) -> np.ndarray:
    """(N, chains, draws, K, C) the pointwise log-likelihood of every observation at every
    draw (:meth:`LogPosterior.pointwise_log_likelihood`): for ArviZ's ``log_likelihood``
    group. With the L2 loss (Gaussian noise) the normalising constant -w log sqrt(2 pi) of
    every uncensored observation, which the sampler leaves out, is added, so the values are
    log densities; masked observations (weight 0) get 0. Draws with NaN get NaN."""
    n, c, m, d = samples.theta.shape
    th = jnp.asarray(np.nan_to_num(samples.theta).reshape(n, c * m, d), data.obs.dtype)
    if normals is None:
        normals = jnp.zeros((n, 1, 3), data.obs.dtype)
    point = lp.for_data(data).pointwise_log_likelihood

    def pixel(args):
        t, dd, nn = args
        return jax.vmap(lambda tt: point(tt, dd, nn if lp.light is not None else None))(t)

    ll = np.asarray(jax.jit(lambda a: jax.lax.map(pixel, a))((th, data, normals)))
    if isinstance(lp.residual.loss, L2):
        ok = np.asarray(lp.residual.usable(data)) & (np.asarray(data.censored) == 0)
        w = np.where(ok, np.asarray(data.weight, np.float64), 0.0)
        ll = ll - (0.5 * np.log(2 * np.pi) * w)[:, None]
    ll = ll.reshape(n, c, m, *ll.shape[2:])
    bad = ~np.all(np.isfinite(samples.theta), axis=-1)
    ll[bad] = np.nan
    return ll


def to_inference_data(
    samples: Samples,
    data: PixelData | None = None,
    *,
    pixels: np.ndarray | None = None,
    predictive: np.ndarray | None = None,
    log_likelihood: np.ndarray | None = None,
    observation: str = "k",
    attrs: dict[str, Any] | None = None,
    dtype: Any = None,
):
    """``arviz.InferenceData`` of ``samples`` (module docstring).

    pixels:      the pixel indices (coordinate ``pixel``), default 0..N-1
    data:        the observations (``observed_data``, ``constant_data``), same N
    predictive:  (N, draws, K, C) from :func:`posterior_predictive` (``posterior_predictive``)
    log_likelihood: (N, chains, draws, K, C) from :func:`log_likelihood_draws`
    observation: the name of the K axis of the data (``photo``, ``sample``)
    dtype:       the floating type the draws (``posterior``, ``sample_stats``,
                 ``posterior_predictive``) are stored in; None keeps theirs. A whole map's
                 draws in ``numpy.float32`` take half the file, and float32's relative
                 resolution (6e-8) is far below any posterior std they summarise
    """
    az = _az()
    n = samples.n_pixels
    pix = np.arange(n) if pixels is None else np.asarray(pixels)

    def draws(a) -> np.ndarray:
        a = np.asarray(a)
        return a.astype(dtype) if dtype is not None and a.dtype.kind == "f" else a

    post = {
        var_name(lab): np.moveaxis(draws(samples.natural[..., j]), 0, -1)
        for j, lab in enumerate(samples.labels)
    }
    stats = {k: np.moveaxis(draws(v), 0, -1) for k, v in samples.stats.items()}
    dims: dict[str, list[str]] = {k: ["pixel"] for k in (*post, *stats)}
    coords: dict[str, Any] = {"pixel": pix}
    obs_dims = ["pixel", observation, "channel"]
    obs = const = ll = ppc = None
    if data is not None:
        k, c = np.asarray(data.obs).shape[1:]
        coords[observation] = np.arange(k)
        coords["channel"] = list(_CHANNELS.get(c, range(c)))
        obs = {"obs": np.asarray(data.obs)}
        const = {
            "weight": np.asarray(data.weight),
            "censored": np.asarray(data.censored).astype(np.int8),
        }
        for key in (*obs, *const):
            dims[key] = obs_dims
    if log_likelihood is not None:
        if data is None:
            raise JaxreflError("log_likelihood needs the data it was computed on (data=)")
        # (N, chains, draws, K, C) -> (chains, draws, N, K, C)
        ll = {"obs": np.moveaxis(np.asarray(log_likelihood), 0, 2)}
    if predictive is not None:
        # (N, draws, K, C) -> (chain 1, draw, pixel, K, C)
        ppc = {"obs": np.swapaxes(draws(predictive), 0, 1)[None]}
        dims["obs"] = obs_dims
    idata = az.from_dict(
        posterior=post,
        sample_stats=stats,
        log_likelihood=ll,
        observed_data=obs,
        constant_data=const,
        posterior_predictive=ppc,
        coords=coords,
        dims=dims,
    )
    meta = {
        "labels": list(samples.labels),
        "method": samples.method,
        "compile_s": float(samples.compile_s),
        "run_s": float(samples.run_s),
        **(attrs or {}),
    }
    for group in ("posterior", "sample_stats"):
        getattr(idata, group).attrs.update({k: _attr(v) for k, v in meta.items()})
    return idata


def _attr(v: Any) -> Any:
    """NetCDF attributes are strings, numbers or flat lists of them."""
    if isinstance(v, (str, int, float, np.integer, np.floating)):
        return v
    if isinstance(v, (list, tuple)) and all(isinstance(x, str) for x in v):
        return list(v)
    return str(v)


def save_netcdf(idata, path: str | Path, *, compress: bool = False) -> Path:
    """Write InferenceData to NetCDF (read back with ``arviz.from_netcdf``); ``compress``:
    zlib on every variable (smaller file, several times the write time)."""
    path = Path(path)
    idata.to_netcdf(str(path), compress=compress)
    return path


def diagnostics(samples: Samples) -> dict[str, np.ndarray]:
    """Per pixel and parameter (N, D): ``rhat``, ``ess_bulk``, ``ess_tail``; per pixel
    (N,): ``divergences`` (count), ``acceptance`` (mean), and ``min_ess_bulk``,
    ``max_rhat`` over parameters. Pixels without draws (NaN) get NaN. The estimators are
    ArviZ's (rank-normalised split R-hat, bulk / tail ESS), vectorised in ._fastdiag."""
    x = samples.natural  # (N, chains, draws, D)
    n, c, m, d = x.shape
    # ArviZ's estimators, vectorised over pixels and parameters (._fastdiag; ArviZ loops)
    flat = np.moveaxis(x, -1, 1).reshape(n * d, c, m)
    rhat, bulk, tail = (a.reshape(n, d) for a in rank_diagnostics(flat))
    div = np.sum(np.asarray(samples.stats["diverging"]), axis=(1, 2))
    acc = np.mean(np.asarray(samples.stats["acceptance_rate"]), axis=(1, 2))
    bad = ~np.all(np.isfinite(x), axis=(1, 2, 3))
    for a in (rhat, bulk, tail):
        a[bad] = np.nan
    return {
        "rhat": rhat,
        "ess_bulk": bulk,
        "ess_tail": tail,
        "divergences": div,
        "acceptance": acc,
        "max_rhat": np.max(rhat, axis=-1),
        "min_ess_bulk": np.min(bulk, axis=-1),
        "min_ess_tail": np.min(tail, axis=-1),
    }


class ChunkSummary(NamedTuple):
    """A chunk's per-pixel summaries: (M, D) mean, std (ddof 1), 5% and 95% quantiles over
    all chains and draws, and :func:`diagnostics`."""

    mean: np.ndarray
    std: np.ndarray
    q05: np.ndarray
    q95: np.ndarray
    diag: dict[str, np.ndarray]


def summarise(samples: Samples) -> ChunkSummary:
    """:class:`ChunkSummary` of ``samples`` (M pixels): NumPy throughout, so the threads that
    sample a map's chunks (:mod:`jaxrefl._threads`) run it side by side, each on its own chunk."""
    flat = samples.natural.reshape(samples.natural.shape[0], -1, samples.natural.shape[-1])
    return ChunkSummary(
        flat.mean(1),
        flat.std(1, ddof=1),
        np.quantile(flat, 0.05, axis=1),
        np.quantile(flat, 0.95, axis=1),
        diagnostics(samples),
    )


def _select(idata, pixel):
    return idata.posterior.isel(pixel=pixel) if "pixel" in idata.posterior.dims else idata.posterior


def plot_trace(idata, pixel: int = 0, var_names=None):
    """ArviZ trace plot of one pixel's parameters."""
    return _az().plot_trace(_select(idata, pixel), var_names=var_names, compact=False)


def plot_rank(idata, pixel: int = 0, var_names=None):
    """ArviZ rank plot (per-chain rank histograms: flat when the chains mix)."""
    return _az().plot_rank(_select(idata, pixel), var_names=var_names)


def plot_corner(samples: Samples, pixel: int = 0, truth: np.ndarray | None = None, max_points=2000):
    """Corner plot: pairwise scatter of the draws and marginal histograms. Tick labels on
    the outer axes only (a column shares its parameter's axis, a row its own), three ticks
    an axis, and fixed margins rather than a computed layout: a map writes a few of these,
    and laying out d^2 labelled axes costs seconds each."""
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    x = samples.flat(pixel)
    x = x[np.all(np.isfinite(x), axis=-1)]
    if len(x) > max_points:
        x = x[np.linspace(0, len(x) - 1, max_points).round().astype(int)]
    d = x.shape[-1]
    fig, axes = plt.subplots(d, d, figsize=(1.8 * d, 1.8 * d), squeeze=False)
    for i in range(d):
        for j in range(d):
            ax = axes[i, j]
            if j > i:
                ax.remove()
                continue
            if i == j:
                ax.hist(x[:, i], bins=30, color="C0", alpha=0.8)
                if truth is not None:
                    ax.axvline(truth[i], color="C3")
            else:
                ax.plot(x[:, j], x[:, i], ".", ms=1.5, alpha=0.4)
                if truth is not None:
                    ax.plot(truth[j], truth[i], "+", color="C3", ms=10)
                if j > 0:  # a row's scatters share parameter i's axis
                    ax.sharey(axes[i, 0])
                ax.sharex(axes[j, j])  # and a column's, parameter j's
            ax.xaxis.set_major_locator(MaxNLocator(3))
            ax.yaxis.set_major_locator(MaxNLocator(3))
            ax.tick_params(
                labelsize=6, labelbottom=i == d - 1, labelleft=j == 0 and i > 0, labelrotation=0
            )
            if i == d - 1:
                ax.set_xlabel(samples.labels[j], fontsize=8)
            if j == 0 and i > 0:
                ax.set_ylabel(samples.labels[i], fontsize=8)
    fig.subplots_adjust(left=0.1, right=0.98, bottom=0.1, top=0.95, wspace=0.1, hspace=0.1)
    return fig


def plot_ppc(predictive: np.ndarray, data: PixelData, pixel: int = 0, ax=None):
    """Observed values of one pixel against the 5-95% band of replicated observations."""
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(6, 3))
    rep = np.asarray(predictive[pixel])  # (draws, K, C)
    obs = np.asarray(data.obs[pixel])
    w = np.asarray(data.weight[pixel]) > 0
    k = np.arange(obs.shape[0])
    for c in range(obs.shape[1]):
        lo, hi = np.quantile(rep[..., c], [0.05, 0.95], axis=0)
        ax.fill_between(k, lo, hi, alpha=0.3, color=f"C{c}", step="mid")
        ax.plot(k[w[:, c]], obs[w[:, c], c], "o", color=f"C{c}", ms=3)
    ax.set_xlabel("observation k")
    ax.set_ylabel("radiance")
    ax.set_title("posterior predictive 5-95% band vs observed", fontsize=9)
    return ax

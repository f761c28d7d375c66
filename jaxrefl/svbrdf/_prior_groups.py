"""Population priors of a capture of two materials: each pixel sampled under its own's.

:func:`jaxrefl.svbrdf.population_priors` takes the fitted pixels as one Gaussian population
of F0 (and one log-normal of alpha). Where the surface holds two materials (a copper inlay
on a dielectric tile, a printed metallic foil on card) that population is two clusters, and
one Gaussian over both puts most of its mass between them: a dielectric pixel whose lobe no
photo resolves is pulled to a metal's F0 and a lobe wide enough to pass for diffuse, a
metal's towards the dielectric's, and both materials' intervals then miss their truth.

:func:`population_groups` fits a two-component Gaussian mixture to the fitted pixels' F0
(EM, full covariances with the population's floor; Dempster, Laird & Rubin 1977) and
splits the population only where the data say it is two materials:

* the mixture beats one Gaussian by BIC (its extra 1 + k + k(k+1)/2 parameters), and
* the components are apart: Ashman's D (Ashman, Bird & Zepf 1994, AJ 108), |mu1 - mu2|
  over the components' rms spread, in robust statistics (medians and 1.4826 MAD of the
  pixels each component takes; the largest over the channels) is above
  :data:`SEPARATION`. D > 2 makes an equal mixture of two Gaussians bimodal, but a single
  skewed or flat population also beats one Gaussian by BIC with many pixels, and its two
  halves measure up to 2.7; the threshold keeps those one material, and
* each holds at least :data:`MIN_SHARE` of the pixels and :data:`MIN_PIXELS`.

Each pixel goes to the component of higher responsibility at its fitted F0 (a pixel
without an estimate to the larger one), and each component's priors are
:func:`population_priors` of its core: the pixels whose F0 lies within :data:`CORE` robust
standard deviations of the material's median. The scatter of fits along an unidentified
lobe's ridge (F0 anywhere from 0 to 1 at a wide lobe) belongs to no material, and a
prior that spans it pulls the unseen lobes of the material onto that ridge (the volume
effect :func:`population_priors` describes, one material at a time). Where fewer than
:data:`CORE_SHARE` of a material's fits lie in its core, its F0 is not identified and the
population stays one. (A material whose fits pile just above F0 = 0 passes that test
with a core that is the pile: its prior is then centred below a small true F0.) The map's
MCMC runs once per component on its pixels (:func:`sample_groups`), and the parts are
joined into one :class:`jaxrefl.posterior.UncertaintyMap`. The report's
``prior_source`` lists the components (``groups``: their priors and pixel counts) and says
why the population was or was not split (``split``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl import fit
from jaxrefl import posterior as jp

from ._job_types import CaptureFit
from ._population import F0_FLOOR_STD, MIN_PIXELS, population_priors

__all__ = [
    "MIN_SHARE",
    "SEPARATION",
    "material_cores",
    "material_posteriors",
    "merge_maps",
    "population_groups",
    "sample_groups",
    "two_materials",
]

#: Separation (Ashman's D in robust statistics, :func:`_separation`) above which two
#: components are two materials. Two Gaussian clusters 4 standard deviations apart leave a
#: dip between them at a quarter of their peaks; one uniform population cut in halves
#: measures 2.7 (sqrt(12) in standard deviations), a log-normal one less.
SEPARATION = 4.0
#: Smallest share of the fitted pixels a material must hold to get its own prior.
MIN_SHARE = 0.02
#: A material's population: the pixels within CORE robust stds of its median F0 (:func:`_core`).
CORE = 3.0
#: Share of a material's pixels its core must hold: where fewer of its fits agree on its F0,
#: the F0 is not identified and its core (the fits piled at a bound) would be a prior far
#: narrower than what the photos know.
CORE_SHARE = 0.5
_EM_ITERS = 200
_EM_TOL = 1e-8  # relative change of the mean log-likelihood at which EM stops


def _gauss_logpdf(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    k = x.shape[1]
    chol = np.linalg.cholesky(cov)
    z = np.linalg.solve(chol, (x - mean).T)
    logdet = 2.0 * np.sum(np.log(np.diag(chol)))
    return -0.5 * (np.sum(z * z, axis=0) + logdet + k * np.log(2.0 * np.pi))


def _separation(x: np.ndarray, label: np.ndarray) -> float:
    """Ashman's D of the two labelled groups in robust statistics, the largest over the
    channels: |median_1 - median_2| / sqrt((s_1^2 + s_2^2) / 2), s = 1.4826 MAD (floored
    at the population's F0 floor)."""
    med, spread = [], []
    for c in range(2):
        g = x[label == c]
        m = np.median(g, 0)
        med.append(m)
        spread.append(np.maximum(1.4826 * np.median(np.abs(g - m), 0), F0_FLOOR_STD))
    return float(np.max(np.abs(med[0] - med[1]) / np.sqrt(0.5 * (spread[0] ** 2 + spread[1] ** 2))))


def two_materials(f0: np.ndarray) -> tuple[np.ndarray | None, dict[str, Any]]:
    """(component of each row of ``f0`` (n, k) as 0/1, or None where the population is one;
    the test's figures and ``why``) (module docstring)."""
    x = np.asarray(f0, np.float64).reshape(len(f0), -1)
    n, k = x.shape
    floor = F0_FLOOR_STD**2 * np.eye(k)
    mean1 = x.mean(0)
    cov1 = np.atleast_2d(np.cov(x, rowvar=False)) + floor
    ll1 = float(np.sum(_gauss_logpdf(x, mean1, cov1)))
    # Start: the pixels below and above the median of the channels' mean F0.
    grey = x.mean(1)
    resp = (grey > np.median(grey)).astype(np.float64)
    if resp.min() == resp.max():
        return None, {"why": "every fitted pixel has the same F0: one material"}
    resp = np.stack([1.0 - resp, resp], 1)
    prev = -np.inf
    for _ in range(_EM_ITERS):
        w = resp.sum(0)
        means = (resp.T @ x) / w[:, None]
        covs = []
        for c in range(2):
            d = x - means[c]
            covs.append((resp[:, c, None] * d).T @ d / w[c] + floor)
        logp = np.stack(
            [np.log(w[c] / n) + _gauss_logpdf(x, means[c], covs[c]) for c in range(2)], 1
        )
        top = logp.max(1, keepdims=True)
        norm = top[:, 0] + np.log(np.exp(logp - top).sum(1))
        resp = np.exp(logp - norm[:, None])
        ll2 = float(norm.sum())
        if abs(ll2 - prev) <= _EM_TOL * abs(ll2):
            break
        prev = ll2
    extra = 1 + k + k * (k + 1) // 2
    bic_gain = 2.0 * (ll2 - ll1) - extra * np.log(n)
    label = np.argmax(resp, 1)
    counts = np.bincount(label, minlength=2)
    d = _separation(x, label) if counts.min() > 0 else 0.0
    info: dict[str, Any] = {
        "separation": d,
        "bic_gain": float(bic_gain),
        "means": means.tolist(),
        "pixels": counts.tolist(),
    }
    small = int(counts.min()) < max(MIN_PIXELS, MIN_SHARE * n)
    if bic_gain <= 0 or d <= SEPARATION or small:
        reason = (
            f"BIC prefers one Gaussian (gain {bic_gain:.1f})"
            if bic_gain <= 0
            else f"the two components overlap (separation {d:.2f} <= {SEPARATION})"
            if d <= SEPARATION
            else f"the smaller component has {int(counts.min())} pixels"
        )
        info["why"] = f"one material: {reason}"
        return None, info
    info["why"] = (
        f"two materials: F0 clusters at {np.round(means[0], 3).tolist()} and "
        f"{np.round(means[1], 3).tolist()} (separation {d:.2f} > {SEPARATION}, BIC gain "
        f"{bic_gain:.1f}), {counts[0]} and {counts[1]} pixels"
    )
    return label, info


def _core(f0: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The pixels of ``mask`` whose F0 lies within :data:`CORE` robust standard deviations
    (1.4826 x MAD) of the material's median in every channel: the material, without the
    fits that scatter along an unidentified lobe's ridge (module docstring)."""
    sel = f0[mask]
    med = np.median(sel, 0)
    # A floor on the robust spread: a material fitted to one F0 keeps every pixel near it.
    mad = np.maximum(1.4826 * np.median(np.abs(sel - med), 0), F0_FLOOR_STD)
    with np.errstate(invalid="ignore"):
        return mask & np.all(np.abs(f0 - med) <= CORE * mad, axis=1)


def material_cores(
    f0: np.ndarray, label: np.ndarray, ok: np.ndarray, means: np.ndarray
) -> tuple[list[np.ndarray] | None, str]:
    """(each material's core (N,) bool, or None where a material's F0 is not identified;
    why not) of pixels with F0 ``f0`` (N, k), material ``label`` (N,) and an estimate
    ``ok`` (N,); ``means``: the materials' F0, for the message."""
    cores = []
    for c in range(2):
        mine = (label == c) & ok
        core = _core(f0, mine)
        if core.sum() < CORE_SHARE * mine.sum():
            return None, (
                f"one population: the fits of the material at {np.round(means[c], 3).tolist()} "
                f"do not agree on its F0 ({int(core.sum())} of {int(mine.sum())} pixels in its "
                f"core, fewer than {CORE_SHARE:.0%}): it is not identified"
            )
        cores.append(core)
    return cores, ""


def population_groups(
    cf: CaptureFit, space: fit.ParamSpace
) -> tuple[list[tuple[dict[str, jp.Prior], np.ndarray]] | None, dict[str, Any]]:
    """([(priors, pixels (N,) bool)] per material, or None where the population is one;
    the split's summary) of the capture fit ``cf`` in ``space`` (module docstring)."""
    names = [b.name for b in space.blocks]
    if "alpha" not in names or "specular" not in names:
        return None, {"why": "the model has no per-pixel lobe to pool"}
    theta = np.asarray(cf.theta, np.float64)
    noise = np.asarray(cf.maps["noise_std"], np.float64).reshape(-1)
    ok = np.all(np.isfinite(theta), -1) & np.isfinite(noise) & (noise > 0)
    if int(ok.sum()) < 2 * MIN_PIXELS:
        return None, {"why": f"{int(ok.sum())} fitted pixels: too few to split"}
    x = np.asarray(space.natural_vector(jnp.asarray(theta[ok])), np.float64)
    label, info = two_materials(x[:, space.index("specular")])
    means = np.asarray(info.get("means", [[np.nan], [np.nan]]))
    if label is None:
        return None, info
    every = np.full(theta.shape[0], int(np.argmax(np.bincount(label, minlength=2))))
    every[ok] = label
    spec = x[:, space.index("specular")]
    f0 = np.full((theta.shape[0], spec.shape[1]), np.nan)
    f0[ok] = spec
    cores, why = material_cores(f0, every, ok, means)
    if cores is None:
        return None, {**info, "why": why}
    groups, summaries = [], []
    for c in range(2):
        mask = every == c
        priors, summary = population_priors(cf, space, pixels=cores[c])
        groups.append((priors, mask))
        shown = {k: repr(v) for k, v in priors.items()}
        summaries.append({**summary, "map_pixels": int(mask.sum()), "priors": shown})
    return groups, {**info, "groups": summaries}


def material_posteriors(
    cf: CaptureFit, lp: jp.LogPosterior, prior_summary: dict[str, Any]
) -> tuple[jp.LogPosterior, list[jp.LogPosterior], list[np.ndarray], dict[str, Any]]:
    """(the largest material's posterior, the posteriors, their pixels, the priors'
    summary with the split's as ``split``) of a map whose whole population's posterior and
    priors' summary are ``lp`` and ``prior_summary`` (:func:`map_posterior`): one posterior
    per material where the priors are the population's and :func:`population_groups`
    splits it, else ``lp`` on every pixel."""
    every = [np.ones(np.asarray(cf.theta).shape[0], bool)]
    if prior_summary.get("source") != "population":
        return lp, [lp], every, prior_summary
    groups, split = population_groups(cf, lp.space)
    summary = {**prior_summary, "split": split}
    if groups is None:
        return lp, [lp], every, summary
    res = lp.residual
    lps = [jp.log_posterior(res.model, lp.space, res.noise, priors=g) for g, _ in groups]
    masks = [m for _, m in groups]
    return lps[int(np.argmax([m.sum() for m in masks]))], lps, masks, summary


def _merge_timings(parts: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for t in parts:
        for key, v in t.items():
            if key not in out:
                out[key] = v
            elif key == "mcmc_chunk_size":
                out[key] = max(out[key], v)
            elif isinstance(v, (int, float)) and isinstance(out[key], (int, float)):
                out[key] = out[key] + v  # the parts run one after the other
            elif isinstance(v, str) and v != out[key]:
                out[key] = "+".join(dict.fromkeys([*str(out[key]).split("+"), *v.split("+")]))
    return out


# UncertaintyMap's per-pixel fields, first axis N.
_PER_PIXEL = (
    *("mean", "std", "q05", "q95", "method", "rhat", "ess_bulk", "ess_tail"),
    *("divergences", "laplace_std", "rerun", "rhat_first"),
)


def merge_maps(parts: list[jp.UncertaintyMap], masks: list[np.ndarray]) -> jp.UncertaintyMap:
    """One map of the pixels of ``masks`` (a partition of the map's N pixels) from each
    part's map of its pixels (in row-major order)."""
    n = int(sum(int(m.sum()) for m in masks))
    p0 = parts[0]

    def fill(attr: str) -> np.ndarray:
        a0 = getattr(p0, attr)
        out = np.empty((n, *a0.shape[1:]), a0.dtype)
        for part, m in zip(parts, masks, strict=True):
            out[m] = getattr(part, attr)
        return out

    idx = [np.flatnonzero(m) for m in masks]
    samples = [p.samples for p in parts if p.samples is not None]
    reasons: dict[str, int] = {}
    for p in parts:
        for key, v in p.reasons.items():
            reasons[key] = reasons.get(key, 0) + v
    filled: dict[str, Any] = {attr: fill(attr) for attr in _PER_PIXEL}
    return replace(
        p0,
        **filled,
        mcmc_pixels=np.concatenate(
            [i[p.mcmc_pixels] for i, p in zip(idx, parts, strict=True)]
        ).astype(p0.mcmc_pixels.dtype),
        samples=jp.Samples.concat(samples) if samples else None,
        timings=_merge_timings([p.timings for p in parts]),
        reasons=reasons,
    )


def sample_groups(
    lps: list[jp.LogPosterior],
    masks: list[np.ndarray],
    data,
    theta0: np.ndarray,
    theta_std: np.ndarray,
    flag: np.ndarray,
    options: jp.AdaptiveOptions,
    *,
    noise_scale: np.ndarray,
    dof: np.ndarray,
    progress: bool,
    chunk_dir: Path | None,
    deadline: float | None,
    log: Callable[[str], None] | None,
) -> jp.UncertaintyMap:
    """:func:`jaxrefl.posterior.adaptive_uncertainty` once per material (its posterior
    ``lps[i]`` on the pixels ``masks[i]``), joined (:func:`merge_maps`); one material: the
    one call on every pixel. Each material's MCMC chunks go to ``chunk_dir/material_<i>``."""
    common: dict[str, Any] = {"progress": progress, "deadline": deadline, "log": log}
    if len(lps) == 1:
        return jp.adaptive_uncertainty(
            lps[0], data, theta0, theta_std, flag, options,
            noise_scale=noise_scale, dof=dof, chunk_dir=chunk_dir, **common,
        )  # fmt: skip
    parts = []
    for i, (lp, m) in enumerate(zip(lps, masks, strict=True)):
        idx = np.flatnonzero(m)
        sub = jax.tree.map(lambda a, idx=idx: a[idx], data)
        if log is not None:
            log(f"material {i + 1} of {len(lps)}: {idx.size} pixels")
        where = None if chunk_dir is None else chunk_dir / f"material_{i}"
        part = jp.adaptive_uncertainty(
            lp, sub, theta0[idx], theta_std[idx], flag[idx], options,
            noise_scale=noise_scale[idx], dof=dof[idx], chunk_dir=where, **common,
        )  # fmt: skip
        parts.append(part)
    return merge_maps(parts, masks)

"""A capture fit's tiles to its maps and report.

:func:`capture_maps` turns the tiles' arrays (pixels in row-major order) into the (H, W) maps
of :class:`~jaxrefl.svbrdf.CaptureFit`: natural parameters and their standard deviations,
roughness and its std by the delta method, the metallic-roughness view of a coloured
specular (glTF 2.0), the shading normal of a tilted model, correlations, codes and the
``misspecified`` bits (:mod:`jaxrefl.svbrdf._check`). :func:`widen_shared` first adds the
shared width's share of each pixel's uncertainty for ``pooled``
(:mod:`jaxrefl.svbrdf._width_laplace`).
:func:`capture_report` writes what ``report.json`` holds.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl import brdf, fit
from jaxrefl.fit import Status, undefined_correlations
from jaxrefl.io import corr_name, map_name

from ._check import ModelCheck, bound_bits, check_counts, ppc_failed
from ._tile_fitter import TileFitter
from ._width_laplace import WidthUncertainty, widen

__all__ = [
    "capture_maps",
    "capture_report",
    "distributed_timings",
    "status_meanings",
    "widen_shared",
]


def widen_shared(fitter: TileFitter, cat: dict[str, np.ndarray]) -> WidthUncertainty | None:
    """For ``pooled`` with a shared width: its share of every pixel's Laplace covariance
    (:mod:`jaxrefl.svbrdf._width_laplace`) added to ``cat``'s ``std``, ``corr`` and ``flag`` in
    place; returns the width's own uncertainty (None for the other models)."""
    if not (fitter.width_terms and fitter.pooled is not None and fitter.pooled.alpha is not None):
        return None
    # A correlation undefined for a zero std enters as 0 (the covariance entry it stands
    # for): the width's share may give that parameter a std, and its correlations are
    # decided again from the widened stds.
    formed = np.all(np.isfinite(cat["std"]), axis=-1)[:, None, None]
    corr_in = np.where(formed & np.isnan(cat["corr"]), 0.0, cat["corr"])
    cat["std"], corr_w, width = widen(
        fitter.space,
        fitter.pooled.alpha,
        cat["theta"],
        cat["std"],
        corr_in,
        cat["width_v"],
        cat["width_s"],
    )
    cat["corr"], cat["flag"] = undefined_correlations(cat["std"], corr_w, cat["flag"])
    return width


def distributed_timings(report: dict, per: np.ndarray, pixels: float) -> None:
    """The report's timings of a multi-process fit: per process (``processes``), and the
    job's ``run_s`` as the slowest process's, its ``pixels_per_s`` over all processes."""
    t = report["timings"]
    run_s = float(np.max(per[:, 2]))
    t["processes"] = {
        "count": int(per.shape[0]),
        "tiles_computed": [int(v) for v in per[:, 0]],
        "compile_s": per[:, 1].tolist(),
        "run_s": per[:, 2].tolist(),
    }
    t["run_s"] = run_s
    t["compile_s"] = float(np.max(per[:, 1]))
    t["pixels_per_s"] = pixels / run_s if run_s > 0 else None


def capture_maps(
    fitter: TileFitter, cat, h: int, w: int, width: WidthUncertainty | None = None
) -> dict[str, np.ndarray]:
    space = fitter.space
    theta = cat["theta"]
    ok = np.all(np.isfinite(theta), axis=-1)
    nat = np.asarray(space.natural_vector(jnp.asarray(np.where(ok[:, None], theta, 0.0))))
    nat = np.where(ok[:, None], nat, np.nan)
    maps: dict[str, np.ndarray] = {}
    labels = space.labels
    for j, lab in enumerate(labels):
        maps[map_name(lab)] = nat[:, j]
        maps[map_name(lab, "_std")] = cat["std"][:, j]
    if "alpha" in labels:
        j = labels.index("alpha")
        root = np.sqrt(np.maximum(nat[:, j], 0.0))
        maps["roughness"] = root
        # d sqrt(alpha) / d alpha = 1 / (2 sqrt(alpha)): the delta method, as for every map.
        slope = np.where(root > 0, 2.0 * root, np.nan)
        maps[map_name("roughness", "_std")] = cat["std"][:, j] / slope
    if fitter.pooled is not None and fitter.pooled.alpha is not None:
        # The shared width: one value, the same map everywhere a pixel has an estimate.
        shared = np.where(ok, fitter.pooled.alpha, np.nan)
        maps["alpha"] = shared
        maps["roughness"] = np.sqrt(shared)
        if width is not None:
            # Its Laplace std (_width_laplace), by the delta method for roughness = sqrt(alpha).
            maps[map_name("alpha", "_std")] = np.where(ok, width.alpha_std, np.nan)
            maps[map_name("roughness", "_std")] = np.where(
                ok, width.alpha_std / (2.0 * np.sqrt(fitter.pooled.alpha)), np.nan
            )
    spec = [j for j, lab in enumerate(labels) if lab.startswith("specular.")]
    alb = [j for j, lab in enumerate(labels) if lab.startswith("albedo.")]
    if len(spec) > 1 and len(spec) == len(alb):
        # The metallic-roughness view of a coloured specular (glTF 2.0; brdf._convert).
        base_j, metal = brdf.specular_to_metallic(
            jnp.asarray(np.nan_to_num(nat[:, alb])), jnp.asarray(np.nan_to_num(nat[:, spec]))
        )
        base = np.where(ok[:, None], np.asarray(base_j), np.nan)
        for j, lab in zip(range(base.shape[1]), [labels[i] for i in alb], strict=True):
            maps["base_color." + lab.split(".", 1)[1]] = base[:, j]
        maps["metallic"] = np.where(ok, np.asarray(metal), np.nan)
    if "tilt_x" in labels:
        tx, ty = nat[:, labels.index("tilt_x")], nat[:, labels.index("tilt_y")]
        n = np.asarray(brdf.tilt_normal(jnp.asarray(tx), jnp.asarray(ty)))
        for j, axis in enumerate("XYZ"):
            maps[f"normal.{axis}"] = n[:, j]
    for a in range(len(labels)):
        for b in range(a + 1, len(labels)):
            maps[corr_name(labels[a], labels[b])] = cat["corr"][:, a, b]
    maps["status"] = cat["status"].astype(np.uint32)
    maps["laplace_flag"] = cat["flag"].astype(np.uint32)
    maps["noise_std"] = np.sqrt(cat["noise_var"])
    maps["cost"] = cat["cost"]
    maps["n_used"] = cat["n_used"].astype(np.uint32)
    maps["iterations"] = cat["iterations"].astype(np.uint32)
    maps["misspecified"] = _misspecified(fitter, cat).astype(np.uint32)
    return {
        k: np.asarray(v).reshape(h, w).astype(v.dtype if v.dtype == np.uint32 else np.float32)
        for k, v in maps.items()
    }


def _misspecified(fitter: TileFitter, cat) -> np.ndarray:
    """(N,) :class:`ModelCheck` bits of the fit (:mod:`jaxrefl.svbrdf._check`): the bound
    check, and for Gaussian noise the check of the training photos' squared errors against
    the capture's noise variance (the median over pixels, in radiance units)."""
    theta = cat["theta"]
    ok = np.all(np.isfinite(theta), -1)
    dn = np.abs(np.asarray(fitter.space.dnatural(jnp.asarray(np.where(ok[:, None], theta, 0.0)))))
    with np.errstate(divide="ignore", invalid="ignore"):
        theta_std = cat["std"] / dn  # the delta method reversed (laplace_theta_std)
    check = bound_bits(fitter.space, theta, theta_std)
    if not isinstance(fitter.noise, fit.GaussianNoise):
        return check
    var = np.asarray(cat["noise_var"], np.float64)
    if fitter.known_noise is None and fitter.noise.sigma is not None:
        # the estimated scale multiplies the model's variance (its mean over channels)
        var = var * float(np.mean(np.asarray(fitter.noise.sigma, np.float64) ** 2))
    good = var[np.isfinite(var) & (var > 0)]
    if good.size == 0:
        return check
    train = fitter.train
    chi2 = np.sum(cat["sse"][:, train], axis=1) / float(np.median(good))
    dof = np.sum(cat["cnt"][:, train], axis=1) - fitter.space.size
    return check | np.where(ppc_failed(chi2, dof), int(ModelCheck.PPC_FAILED), 0)


def _rmse(sse: np.ndarray, cnt: np.ndarray) -> float | None:
    n = float(np.sum(cnt))
    return float(np.sqrt(np.sum(sse) / n)) if n > 0 else None


def capture_report(fitter, cat, capture, job, maps, compile_s, times, n_tiles, loaded) -> dict:
    from jaxrefl import __version__

    k, h, w, c = capture.shape
    run_s = float(np.sum(times))
    n_px = h * w
    sse, cnt = cat["sse"], cat["cnt"]
    holdout = list(job.holdout)
    train = [i for i in range(k) if i not in holdout]
    report: dict[str, Any] = {
        "jaxrefl": __version__,
        "model": job.model,
        "model_description": type(fitter.model).__name__,
        "parameters": list(fitter.space.labels),
        "bounds": {
            lab: [float(lo), float(hi)]
            for lab, lo, hi in zip(
                fitter.space.labels, fitter.space.lower, fitter.space.upper, strict=True
            )
        },
        # a pooled fit's too: its width was chosen from alpha_min up, and a plan read back
        # from this file frees that width with this bound
        "alpha_min": (
            fitter.alpha_min
            if "alpha" in fitter.space.labels or fitter.pooled is not None
            else None
        ),
        "pooled": None if fitter.pooled is None else fitter.pooled.as_dict(),
        "job": job.to_json(),
        "capture": {
            "layout": capture.layout,
            "source": None if capture.source is None else str(capture.source),
            "photos": k,
            "height": h,
            "width": w,
            "channels": c,
            "observations": capture.summary(),
        },
        "pixels": n_px,
        "status_counts": fit.describe(maps["status"]),
        "laplace_flag_counts": fit.flag_counts(maps["laplace_flag"]),
        # Pixels whose model cannot be right (jaxrefl.svbrdf._check): their Laplace and
        # predictive intervals are not calibrated.
        "misspecified_counts": check_counts(maps["misspecified"]),
        "timings": {
            "compile_s": compile_s,
            "run_s": run_s,
            "pixels_per_s": (n_px * (n_tiles - loaded) / n_tiles) / run_s if run_s > 0 else None,
            "tiles": n_tiles,
            "tiles_loaded": loaded,
            "tile_pixels": job.tile_pixels,
            "devices": jax.device_count(),  # of every process
            "platform": jax.devices()[0].platform,
        },
        "train_rmse": _rmse(sse[:, train], cnt[:, train]),
        "units": "radiance in the capture's linear units; albedo, specular: 1; alpha: GGX width",
    }
    if holdout:
        report["holdout"] = holdout
        report["heldout_rmse"] = _rmse(sse[:, holdout], cnt[:, holdout])
        report["heldout_rmse_per_photo"] = {str(i): _rmse(sse[:, i], cnt[:, i]) for i in holdout}
        report["heldout_observations"] = int(np.sum(cnt[:, holdout]))
        # A robust companion of the RMSE: a few pixels with wild predictions (e.g. a lobe
        # aimed where the training photos were clipped) dominate the RMSE, not the median.
        n_h = np.sum(cnt[:, holdout], axis=1)
        per_px = np.sqrt(np.sum(sse[:, holdout], axis=1)[n_h > 0] / n_h[n_h > 0])
        report["heldout_pixel_rmse_median"] = float(np.median(per_px)) if per_px.size else None
        report["heldout_pixel_rmse_p99"] = float(np.quantile(per_px, 0.99)) if per_px.size else None
    return report


def status_meanings() -> dict[str, str]:
    """Readable meanings of the ``status`` map's codes."""
    return {str(int(s)): f"{s.name}: {fit.STATUS_MEANINGS[s]}" for s in Status}

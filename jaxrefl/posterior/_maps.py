"""Uncertainty maps as EXR channels (through :func:`jaxrefl.io.write_exr`).

Channel names follow :mod:`jaxrefl.io._channels` (``<layer>.<channel>``, R/G/B for a
colour, Y for a scalar). For each parameter label and statistic ``mean``, ``std``, ``q05``,
``q95``: a colour label ``albedo.R`` becomes the channel ``albedo_<stat>.R`` (layer
``albedo_mean`` with R, G, B, so viewers show it as a colour image), a scalar ``alpha``
becomes ``alpha_<stat>.Y``. Then ``method.Y`` (UINT, :data:`~jaxrefl.posterior.METHODS`),
``rhat.Y``, ``ess_bulk.Y``, ``ess_tail.Y`` (FLOAT, NaN off the MCMC pixels),
``divergences.Y`` (UINT) and ``mcmc_pass.Y`` (UINT: 0 off MCMC, 1 the first pass, 2 a
longer later pass, second or third, of the pixels whose first chains disagreed). For GGX-type models
``roughness_<stat>.Y`` (perceptual roughness sqrt(alpha): quantiles and mean mapped through
the square root, std by the delta method std(alpha) / (2 sqrt(alpha))) is added. The
method codes and labels go into the file's metadata.

Non-finite values: the summaries (``<p>_<stat>``, ``roughness_<stat>``) are NaN where
``method`` is 0 (no estimate), the MCMC diagnostics (``rhat``, ``ess_*``) where the pixel
was not sampled, and the entries Laplace has no summary of (the noise scale, a sampled
light) on the pixels whose summary is Laplace's (methods 1 and 4). Anything else non-finite
is flagged in ``nonfinite.Y`` (UINT,
:class:`NonFinite` bits): 1 a summary is not finite although the pixel has an estimate, 2 an
MCMC diagnostic is not finite although the pixel was sampled.
"""

from __future__ import annotations

import enum
from pathlib import Path

import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.io import exr_channels, map_name

from ._methods import MCMC_METHODS, Method
from ._uncertainty_map import METHODS, UncertaintyMap

__all__ = ["NonFinite", "uncertainty_channels", "write_uncertainty_exr"]


class NonFinite(enum.IntFlag):
    """Bits of the ``nonfinite`` channel (module docstring)."""

    SUMMARY = 1
    DIAGNOSTIC = 2


STATS = ("mean", "std", "q05", "q95")


def _channel(label: str, stat: str) -> str:
    return map_name(label, f"_{stat}")


def uncertainty_channels(umap: UncertaintyMap, height: int, width: int) -> dict[str, np.ndarray]:
    """name -> (height, width) array (module docstring); pixels in row-major order."""
    if umap.method.size != height * width:
        raise JaxreflError(f"{umap.method.size} pixels do not fill {height} x {width}")

    def img(v):
        return np.asarray(v).reshape(height, width)

    out: dict[str, np.ndarray] = {}
    for j, lab in enumerate(umap.labels):
        for stat in STATS:
            out[_channel(lab, stat)] = img(getattr(umap, stat)[:, j]).astype(np.float32)
    if "alpha" in umap.labels:
        j = umap.labels.index("alpha")
        a = umap.mean[:, j]
        root = np.sqrt(np.maximum(a, 0.0))
        out["roughness_mean"] = img(root).astype(np.float32)
        # d sqrt(alpha) / d alpha = 1 / (2 sqrt(alpha)) (delta method), quantiles exactly.
        std = img(umap.std[:, j] / np.where(root > 0, 2 * root, np.nan))
        out["roughness_std"] = std.astype(np.float32)
        out["roughness_q05"] = img(np.sqrt(np.maximum(umap.q05[:, j], 0.0))).astype(np.float32)
        out["roughness_q95"] = img(np.sqrt(np.maximum(umap.q95[:, j], 0.0))).astype(np.float32)
    # A pixel without an estimate holds NaN summaries whatever the map held (documented).
    none = img(umap.method == Method.NONE)
    summaries = list(out)
    for name in summaries:
        out[name] = np.where(none, np.float32(np.nan), out[name])
    # Entries without a Laplace summary anywhere (the noise scale, a sampled light) are NaN
    # by design on the Laplace pixels (methods laplace, laplace_time_limit): not flagged.
    no_laplace = np.all(np.isnan(np.asarray(umap.laplace_std)), axis=0)
    laplace_px = img(np.isin(umap.method, (Method.LAPLACE, Method.LAPLACE_TIME_LIMIT)))
    bad_stat = np.zeros(none.shape, bool)
    for j, lab in enumerate(umap.labels):
        for stat in STATS:
            bad = ~np.isfinite(out[_channel(lab, stat)])
            bad_stat |= bad & ~laplace_px if no_laplace[j] else bad
    if "alpha" in umap.labels:
        for stat in STATS:
            bad_stat |= ~np.isfinite(out[f"roughness_{stat}"])
    bad_stat &= ~none
    out["method"] = img(umap.method).astype(np.uint32)
    out["rhat"] = img(umap.rhat).astype(np.float32)
    out["ess_bulk"] = img(umap.ess_bulk).astype(np.float32)
    out["ess_tail"] = img(umap.ess_tail).astype(np.float32)
    out["divergences"] = img(umap.divergences).astype(np.uint32)
    sampled = np.isin(umap.method, MCMC_METHODS)
    rerun = np.zeros(sampled.shape, bool) if umap.rerun is None else umap.rerun
    out["mcmc_pass"] = img(np.where(rerun, 2, sampled)).astype(np.uint32)
    diag = ~np.isfinite(out["rhat"]) | ~np.isfinite(out["ess_bulk"]) | ~np.isfinite(out["ess_tail"])
    bad_diag = diag & img(sampled)
    out["nonfinite"] = (
        np.where(bad_stat, int(NonFinite.SUMMARY), 0)
        | np.where(bad_diag, int(NonFinite.DIAGNOSTIC), 0)
    ).astype(np.uint32)
    return exr_channels(out)


def write_uncertainty_exr(
    path: str | Path, umap: UncertaintyMap, height: int, width: int, metadata=None
) -> Path:
    """Write :func:`uncertainty_channels` to ``path`` (atomic, via jaxrefl.io)."""
    from jaxrefl.io import write_exr

    meta = {
        "labels": list(umap.labels),
        "method_codes": {str(k): v for k, v in METHODS.items()},
        "nonfinite_bits": {b.name: int(b.value) for b in NonFinite},
        "stats": list(STATS),
        **(metadata or {}),
    }
    return write_exr(path, uncertainty_channels(umap, height, width), metadata=meta)

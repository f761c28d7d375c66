"""The model an uncertainty map samples: the fit's, widened where its fit piles against a cap.

A model whose fit piles most pixels against a cap that another candidate lifts is not
sampled: where more than :data:`WIDEN_SHARE` of the fitted pixels have their grey F0 at
(within :data:`jaxrefl.svbrdf._check.NEAR` of) the dielectric cap 0.25 of ``ggx``, the
capture is fitted again with :data:`WIDER` ``ggx_rgb`` (coloured F0 up to 1, metals), and
the report's ``model_choice`` says so and why. Sampling pixels whose mode sits at a limit of
the model would spend the MCMC budget on intervals that cannot be calibrated.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxrefl import fit

from ._check import NEAR
from ._job import CaptureFit, fit_capture
from ._tile_fitter import traced_noise

__all__ = ["WIDEN_SHARE", "WIDER", "map_model", "map_noise", "model_choice", "noise_text"]

#: Models whose fit may pile against a cap that another candidate lifts -> that candidate.
WIDER: dict[str, str] = {"ggx": "ggx_rgb"}
#: Share of fitted pixels at the cap above which the map's model is widened: a capped
#: pixel's interval cannot reach a truth above the cap, and a 90% interval map is held to
#: 85-95% coverage, so more than 5% capped pixels would put the map outside it.
WIDEN_SHARE = 0.05


def model_choice(cf: CaptureFit, requested: str) -> dict[str, Any]:
    """How the map's model was chosen (the report's ``model_choice``): the model, the one
    asked for, why (auto's reason, or given), and the share of fitted pixels whose grey F0
    piles against its cap (0 for a model without one)."""
    auto = cf.report.get("auto")
    why = "given" if auto is None else f"auto: {auto.get('why', 'chosen by held-out photos')}"
    _model, space = cf.model()
    spec = np.array([lab.split(".")[0] == "specular" for lab in space.labels])
    share = 0.0
    theta = np.asarray(cf.theta)
    ok = np.all(np.isfinite(theta), -1)
    if cf.job.model in WIDER and spec.any() and ok.any():
        t = jnp.asarray(theta[ok])
        x = np.asarray(space.natural_vector(t))
        near = np.asarray(space.at_bound(t, NEAR))
        lower, upper = np.asarray(space.lower), np.asarray(space.upper)
        capped = near & (upper - x <= x - lower) & spec
        share = float(np.mean(np.any(capped, -1)))
    return {"model": cf.job.model, "requested": requested, "why": why, "capped_share": share}


def map_model(
    capture,
    cf: CaptureFit,
    requested: str,
    out_dir: str | Path | None,
    progress: bool,
    distributed,
    say: Callable[[str], None],
) -> tuple[CaptureFit, dict[str, Any]]:
    """(the fit whose model the map samples, :func:`model_choice` with ``widened`` where
    the fit ``cf`` was widened: module docstring). A widened fit's tiles go to
    ``out_dir/fit_<model>`` (resume), as :func:`jaxrefl.svbrdf.fit_capture` writes them."""
    choice = model_choice(cf, requested)
    wider = WIDER.get(cf.job.model)
    if wider is None or choice["capped_share"] <= WIDEN_SHARE:
        return cf, choice
    choice["widened"] = {
        "from": cf.job.model,
        "to": wider,
        "why": f"{choice['capped_share']:.0%} of the fitted pixels have F0 at the "
        f"{cf.job.model} model's cap (more than {WIDEN_SHARE:.0%}): {wider} lifts it",
    }
    say(f"fit: {choice['widened']['why']}; fitting {wider}")
    wdir = None if out_dir is None else Path(out_dir) / f"fit_{wider}"
    # The loss and a noise-level function were chosen for the narrower model: the wider
    # one chooses its own (the level is estimated from the flat noise it replaced).
    kept = (cf.report.get("noise_level") or {}).get("kept", False)
    noise = fit.GaussianNoise(None) if kept else cf.job.config.noise
    wjob = replace(cf.job, model=wider, config=cf.job.config.replace(loss=None, noise=noise))
    cf = fit_capture(capture, wjob, wdir, progress=progress, distributed=distributed)
    choice["model"] = cf.job.model
    choice["capped_share_after"] = model_choice(cf, wider)["capped_share"]
    return cf, choice


def map_noise(cf: CaptureFit) -> fit.NoiseModel:
    """The map's noise model: the fit's noise-level function where it kept one
    (:func:`jaxrefl.svbrdf.estimate_noise_level`), else Gaussian; of unknown scale per
    pixel either way (Jeffreys prior)."""
    noise = cf.job.config.noise
    if isinstance(noise, fit.LevelNoise) and noise.scale_unknown:
        return traced_noise(noise, np.dtype(cf.job.dtype))
    return fit.GaussianNoise(None)


def noise_text(noise: fit.NoiseModel) -> str:
    """The report's ``noise``: the map's noise model in words."""
    if isinstance(noise, fit.LevelNoise):
        return (
            "Gaussian, std s sqrt(1 + gain y + (rel y)^2) with the capture's noise-level "
            f"function (gain {float(noise.gain):.4g}, rel {float(noise.rel):.4g}; the fit's "
            "noise_level), unknown scale s per pixel (Jeffreys prior)"
        )
    return "Gaussian, unknown scale per pixel (Jeffreys prior)"

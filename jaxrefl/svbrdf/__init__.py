"""Planar SVBRDF captures to per-pixel reflectance maps: the main job.

Quick use::

    import jax
    import numpy as np
    from jaxrefl.io import load_capture
    from jaxrefl import fit, posterior, svbrdf

    cap = load_capture("bath_tile")                          # any of the three layouts
    result = svbrdf.fit_capture(cap, svbrdf.FitJob(model="ggx", holdout=(0,)), "out")
    svbrdf.write_outputs(result, cap, "out")                # maps.exr, report.json, PNGs
    result.report["heldout_rmse"], result.maps["roughness"]

    jax.config.update("jax_enable_x64", True)               # posteriors are float64
    opts = posterior.AdaptiveOptions()                      # the map's defaults
    job64 = svbrdf.FitJob(config=fit.FitConfig(dtype=np.float64))
    u = svbrdf.uncertainty_maps(cap, job64, opts)
    svbrdf.write_uncertainty(u, "post")                     # uncertainty.exr, posterior.nc
    u.map.std, u.report()["uncertainty"]["method_counts"]

Parts: :mod:`._models` (named capture models), :mod:`._auto` (the capture's model chosen by
held-out photos, under the :class:`AutoOptions` of :mod:`._auto_options`), :mod:`._data`
(capture pixels as least-squares data: weights, censoring, geometry), :mod:`._pooled` (one
lobe shape per capture, chosen by held-out photos), :mod:`._job` (tiled fit with Laplace
uncertainty: :func:`fit_capture`), :mod:`._job_types` (:class:`FitJob`,
:class:`CaptureFit`), :mod:`._tile_fitter` (one tile: fit, Laplace, held-out errors),
:mod:`._tile_store` (tiles on disk: resume, several processes), :mod:`._maps` (tiles to
maps and report),
:mod:`._holdout` (leave-one-photo-out against a baseline), :mod:`._outputs` (EXR maps,
report, previews), :mod:`._export` (textures, a Mitsuba 3 scene and a glTF 2.0 material
for renderers), :mod:`._uncertainty` (the fit's Laplace std, then MCMC where Laplace is
flagged: posterior uncertainty maps), :mod:`._population` (the lobe's priors of flagged
pixels from the reliably fitted ones), :mod:`._check` (where the model cannot be right: the
``misspecified`` map), :mod:`._predictive` (posterior predictive intervals of photos, with a
model-discrepancy term measured on training photos; their coverage of held-out photos),
:mod:`._plan` (where to take the next photo: candidate positions ranked by the expected
reduction of the renderings' predictive variance, or by expected information gain),
:mod:`._plan_files` (a fit's folder read back; ``plan.json`` and figures), :mod:`._light`
(the flash's offset and gains, estimated), :mod:`._light_map` (the light's uncertainty in
an uncertainty map's intervals).
"""

from ._auto import ModelChoice as ModelChoice
from ._auto import choose_model as choose_model
from ._auto_options import AUTO_CANDIDATES as AUTO_CANDIDATES
from ._auto_options import AutoOptions as AutoOptions
from ._check import ModelCheck as ModelCheck
from ._data import is_colocated as is_colocated
from ._data import pixel_block as pixel_block
from ._data import resolvable_alpha as resolvable_alpha
from ._discrepancy_options import DiscrepancyOptions as DiscrepancyOptions
from ._export import write_gltf as write_gltf
from ._export import write_mitsuba as write_mitsuba
from ._export import write_textures as write_textures
from ._holdout import LeaveOneOut as LeaveOneOut
from ._holdout import leave_one_out as leave_one_out
from ._job import fit_capture as fit_capture
from ._job_types import DEFAULT_LOSS as DEFAULT_LOSS
from ._job_types import CaptureFit as CaptureFit
from ._job_types import FitJob as FitJob
from ._light import LightEstimate as LightEstimate
from ._light import estimate_light as estimate_light
from ._light import (
    gain_prior,  # noqa: F401
    light_problem,  # noqa: F401
)
from ._light import light_draws as light_draws
from ._light_options import LightOptions as LightOptions
from ._models import CAPTURE_MODELS as CAPTURE_MODELS
from ._models import capture_model as capture_model
from ._noise_level import NoiseLevel as NoiseLevel
from ._noise_level import estimate_noise_level as estimate_noise_level
from ._outputs import predict_photos as predict_photos
from ._outputs import write_outputs as write_outputs
from ._plan import Candidates as Candidates
from ._plan import Plan as Plan
from ._plan import PlanOptions as PlanOptions
from ._plan import hemisphere_candidates as hemisphere_candidates
from ._plan import listed_candidates as listed_candidates
from ._plan import photo_candidates as photo_candidates
from ._plan import photo_information  # noqa: F401
from ._plan import plan_next as plan_next
from ._plan_files import read_fit as read_fit
from ._plan_files import write_plan as write_plan
from ._population import population_priors as population_priors
from ._predictive import Discrepancy as Discrepancy
from ._predictive import Predictive as Predictive
from ._predictive import estimate_discrepancy as estimate_discrepancy
from ._predictive import predictive as predictive
from ._uncertainty import CaptureUncertainty as CaptureUncertainty
from ._uncertainty import (
    fit_theta,  # noqa: F401
    laplace_dof,  # noqa: F401
    laplace_interval,  # noqa: F401
    laplace_theta_std,  # noqa: F401
    map_posterior,  # noqa: F401
)
from ._uncertainty import uncertainty_maps as uncertainty_maps
from ._uncertainty import write_uncertainty as write_uncertainty

# The public names. Those imported above without ``as`` (gain_prior, light_problem,
# photo_information, fit_theta, laplace_dof, laplace_interval, laplace_theta_std,
# map_posterior) are helpers, reachable here for the benchmarks and tests that import them
# from the package; new code imports them from their modules.
__all__ = [
    "AUTO_CANDIDATES",
    "CAPTURE_MODELS",
    "DEFAULT_LOSS",
    "AutoOptions",
    "Candidates",
    "CaptureFit",
    "CaptureUncertainty",
    "Discrepancy",
    "DiscrepancyOptions",
    "FitJob",
    "LeaveOneOut",
    "LightEstimate",
    "LightOptions",
    "ModelCheck",
    "ModelChoice",
    "NoiseLevel",
    "Plan",
    "PlanOptions",
    "Predictive",
    "capture_model",
    "choose_model",
    "estimate_discrepancy",
    "estimate_light",
    "estimate_noise_level",
    "fit_capture",
    "hemisphere_candidates",
    "is_colocated",
    "leave_one_out",
    "light_draws",
    "listed_candidates",
    "photo_candidates",
    "pixel_block",
    "plan_next",
    "population_priors",
    "predict_photos",
    "predictive",
    "read_fit",
    "resolvable_alpha",
    "uncertainty_maps",
    "write_gltf",
    "write_mitsuba",
    "write_outputs",
    "write_plan",
    "write_textures",
    "write_uncertainty",
]

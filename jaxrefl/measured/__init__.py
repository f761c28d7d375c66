"""Analytic models fitted to measured BRDFs: error metrics, the default model set, fits with
timing and an automatic float64 retry, reports and lobe plots.

Quick use::

    from jaxrefl import measured as jm
    from jaxrefl.io import read_cornell

    m = read_cornell("acryl_blue.astm")            # 31 bands, f_r in 1/sr
    report = jm.fit_brdf(m)                         # every default model, RGB under D65
    print(report.table())
    report.to_dict()                                # what `jaxrefl fit-brdf` writes

    post = jm.sample_posterior(m, "ggx")   # emcee; HMC: jp.HMCOptions()
    post.summary(), jm.write_posterior(post, "out")      # posterior.nc, corner.png

Parts: :mod:`._metrics` (cosine-weighted L2 of Ngan et al. 2005, log-space and relative
L2), :mod:`._models` (the named model set), :mod:`._starts` (multi-start fits, with
:mod:`._start_options`; their starts from :mod:`._seeds`, data-driven and quasi-random, and
:mod:`._nested`; the certificate of the optimum in :mod:`._certificate`), :mod:`._data`
(reading, RGB conversion, angle limit), :mod:`._fit` (fit one model / all of them),
:mod:`._retry` (float32 -> float64),
:mod:`._plots` (measured vs fitted lobes), :mod:`._components` (models assembled from
switched-on components),
:mod:`._compact` (leave out the pixels a scene does not need), :mod:`._prune` (drop
components by BIC or Laplace evidence, per material or cluster), :mod:`._plan` (capture
planning by expected Fisher information), :mod:`._posterior` (a model's posterior given a
material: emcee or HMC after the least-squares fit).
"""

from ._certificate import Certificate as Certificate
from ._components import Components as Components
from ._components import fit_components as fit_components
from ._data import load_measured as load_measured
from ._data import restrict as restrict
from ._data import to_rgb as to_rgb
from ._fit import FitReport as FitReport
from ._fit import ModelFit as ModelFit
from ._fit import fit_brdf as fit_brdf
from ._fit import fit_model as fit_model
from ._fit import predict as predict
from ._fit_options import MeasuredOptions as MeasuredOptions
from ._metrics import METRICS as METRICS
from ._metrics import error_metrics as error_metrics
from ._models import DEFAULT_MODELS as DEFAULT_MODELS
from ._models import MODEL_NAMES as MODEL_NAMES
from ._models import build_model as build_model
from ._models import fresnel_variant  # noqa: F401
from ._plan import Ranking as Ranking
from ._plan import greedy_design as greedy_design
from ._plan import information as information
from ._plan import rank_candidates as rank_candidates
from ._plots import plot_fit_lobes as plot_fit_lobes
from ._posterior import HMC_SEED as HMC_SEED
from ._posterior import BRDFPosterior as BRDFPosterior
from ._posterior import sample_posterior as sample_posterior
from ._posterior import write_posterior as write_posterior
from ._prune import GroupPruning as GroupPruning
from ._prune import PruneReport as PruneReport
from ._prune import PruneStep as PruneStep
from ._prune import measured_pixel_data as measured_pixel_data
from ._prune import prune as prune
from ._prune_options import CRITERIA as CRITERIA
from ._prune_options import PruneOptions as PruneOptions
from ._retry import RetryResult as RetryResult
from ._retry import fit_pixels_retry as fit_pixels_retry
from ._start_options import MultiStart as MultiStart
from ._starts import fit_multistart as fit_multistart

# The public names. fresnel_variant, imported above without ``as``, is a helper of the
# command line's --fresnel, reachable here for it; every other helper is imported from
# its module.
__all__ = [
    "CRITERIA",
    "DEFAULT_MODELS",
    "HMC_SEED",
    "METRICS",
    "MODEL_NAMES",
    "BRDFPosterior",
    "Certificate",
    "Components",
    "FitReport",
    "GroupPruning",
    "MeasuredOptions",
    "ModelFit",
    "MultiStart",
    "PruneOptions",
    "PruneReport",
    "PruneStep",
    "Ranking",
    "RetryResult",
    "build_model",
    "error_metrics",
    "fit_brdf",
    "fit_components",
    "fit_model",
    "fit_multistart",
    "fit_pixels_retry",
    "greedy_design",
    "information",
    "load_measured",
    "measured_pixel_data",
    "plot_fit_lobes",
    "predict",
    "prune",
    "rank_candidates",
    "restrict",
    "sample_posterior",
    "to_rgb",
    "write_posterior",
]

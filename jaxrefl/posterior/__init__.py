"""Pixels to posteriors: MCMC over reflectance parameters and light direction, diagnostics,
calibration and uncertainty maps.

Quick use::

    from jaxrefl import fit, posterior as jp, svbrdf

    model, space = svbrdf.capture_model("ggx")
    lp = jp.log_posterior(model, space, fit.GaussianNoise(0.01))   # priors: jp.default_priors
    s = jp.sample_pixels(lp, data, lp.init_theta(result.theta))    # vmapped HMC, (N, K, C)
    jp.diagnostics(s)["max_rhat"], jp.to_inference_data(s, data).to_netcdf("post.nc")
    opts = jp.AdaptiveOptions(mcmc="flagged")           # the map's defaults: one option object
    umap = jp.adaptive_uncertainty(lp, data, result.theta, lap.theta_std, lap.flag, opts)
    jp.write_uncertainty_exr("uncertainty.exr", umap, h, w)

Parts: :mod:`._priors` (priors in natural units), :mod:`._sphere` (light direction on the
sphere), :mod:`._logpost` (the log-posterior from the fit's model, bijections and noise),
:mod:`._options` (the samplers' settings), :mod:`._choice` (which sampler a batch of
pixels takes), :mod:`._driver` (the one driver of the samplers' init/step kernels:
starts, chains, packaging as :class:`Samples`), :mod:`._hmc` (BlackJAX HMC/NUTS vmapped
over pixels), :mod:`._gibbs` and :mod:`._width_gibbs` (Gibbs sampling where the posterior
is linear-Gaussian, in every parameter or given the lobe width; shared parts in
:mod:`._conjugate`), :mod:`._reparam` (the non-centred albedo coordinates HMC moves in),
:mod:`._emcee` (ensemble sampler), :mod:`._adaptive` (Laplace everywhere, MCMC where
flagged; its settings :mod:`._adaptive_options`, its result :mod:`._uncertainty_map`, its
chunks :mod:`._chunks`), :mod:`._diagnostics` (ArviZ, R-hat/ESS, plots, predictive
checks), :mod:`._sbc` (simulation-based calibration), :mod:`._maps` (EXR uncertainty
channels).
"""

from ._adaptive import adaptive_uncertainty as adaptive_uncertainty
from ._adaptive_options import UNCERTAINTY_MAP_GIBBS as UNCERTAINTY_MAP_GIBBS
from ._adaptive_options import UNCERTAINTY_MAP_HMC as UNCERTAINTY_MAP_HMC
from ._adaptive_options import AdaptiveOptions as AdaptiveOptions
from ._adaptive_options import longer_options as longer_options
from ._adaptive_options import third_pass_options as third_pass_options
from ._adaptive_options import untuned_rerun as untuned_rerun
from ._choice import sample_pixels as sample_pixels
from ._chunks import HEARTBEAT_S  # noqa: F401
from ._diagnostics import diagnostics as diagnostics
from ._diagnostics import log_likelihood_draws  # noqa: F401
from ._diagnostics import plot_corner as plot_corner
from ._diagnostics import plot_ppc as plot_ppc
from ._diagnostics import plot_rank as plot_rank
from ._diagnostics import plot_trace as plot_trace
from ._diagnostics import posterior_predictive as posterior_predictive
from ._diagnostics import save_netcdf as save_netcdf
from ._diagnostics import to_inference_data as to_inference_data
from ._emcee import Convergence as Convergence
from ._emcee import EmceeOptions as EmceeOptions
from ._emcee import EmceeRun as EmceeRun
from ._emcee import convergence as convergence
from ._emcee import sample_emcee as sample_emcee
from ._logpost import LogPosterior as LogPosterior
from ._logpost import SharedLight as SharedLight
from ._logpost import log_posterior as log_posterior
from ._maps import (
    NonFinite,  # noqa: F401
    uncertainty_channels,  # noqa: F401
)
from ._maps import write_uncertainty_exr as write_uncertainty_exr
from ._methods import MCMC_METHODS  # noqa: F401
from ._methods import Method as Method
from ._options import GibbsOptions as GibbsOptions
from ._options import HMCOptions as HMCOptions
from ._priors import HalfCauchy as HalfCauchy
from ._priors import Jeffreys as Jeffreys
from ._priors import LogNormal as LogNormal
from ._priors import MultivariateNormal as MultivariateNormal
from ._priors import Normal as Normal
from ._priors import Prior as Prior
from ._priors import Uniform as Uniform
from ._priors import VonMisesFisher as VonMisesFisher
from ._priors import default_priors as default_priors
from ._priors import sample_truncated  # noqa: F401
from ._samples import Samples as Samples
from ._sbc import SBCResult as SBCResult
from ._sbc import sbc_summary as sbc_summary
from ._sbc import thin  # noqa: F401
from ._sphere import SphereDirection as SphereDirection
from ._sphere import direction_summary as direction_summary
from ._uncertainty_map import METHODS as METHODS
from ._uncertainty_map import UncertaintyMap as UncertaintyMap

# The public names. Those imported above without ``as`` are helpers, not public, that the
# other packages of jaxrefl share (each package uses another through its ``__init__`` only):
# HEARTBEAT_S, NonFinite, log_likelihood_draws, uncertainty_channels; and that benchmarks
# import from the package: MCMC_METHODS, sample_truncated, thin.
__all__ = [
    "METHODS",
    "UNCERTAINTY_MAP_GIBBS",
    "UNCERTAINTY_MAP_HMC",
    "AdaptiveOptions",
    "Convergence",
    "EmceeOptions",
    "EmceeRun",
    "GibbsOptions",
    "HMCOptions",
    "HalfCauchy",
    "Jeffreys",
    "LogNormal",
    "LogPosterior",
    "Method",
    "MultivariateNormal",
    "Normal",
    "Prior",
    "SBCResult",
    "Samples",
    "SharedLight",
    "SphereDirection",
    "UncertaintyMap",
    "Uniform",
    "VonMisesFisher",
    "adaptive_uncertainty",
    "convergence",
    "default_priors",
    "diagnostics",
    "direction_summary",
    "log_posterior",
    "longer_options",
    "plot_corner",
    "plot_ppc",
    "plot_rank",
    "plot_trace",
    "posterior_predictive",
    "sample_emcee",
    "sample_pixels",
    "save_netcdf",
    "sbc_summary",
    "third_pass_options",
    "to_inference_data",
    "untuned_rerun",
    "write_uncertainty_exr",
]

"""Pixels to posteriors: MCMC over reflectance parameters and light direction, diagnostics,
calibration and uncertainty maps.

Quick use::

    from jaxrefl import fit, posterior as jp, svbrdf

    model, space = svbrdf.capture_model("ggx")
    lp = jp.log_posterior(model, space, fit.GaussianNoise(0.01))   # priors: jp.default_priors
    s = jp.sample_pixels(lp, data, lp.init_theta(result.theta))    # vmapped HMC, (N, K, C)
    jp.diagnostics(s)["max_rhat"], jp.to_inference_data(s, data).to_netcdf("post.nc")
    opts = jp.AdaptiveOptions(mcmc="flagged", hmc=jp.MAP_OPTIONS)          # one option object
    umap = jp.adaptive_uncertainty(lp, data, result.theta, lap.theta_std, lap.flag, opts)
    jp.write_uncertainty_exr("uncertainty.exr", umap, h, w)

Parts: :mod:`._priors` (priors in natural units), :mod:`._sphere` (light direction on the
sphere), :mod:`._logpost` (the log-posterior from the fit's model, bijections and noise),
:mod:`._batched` (BlackJAX HMC/NUTS vmapped over pixels), :mod:`._reparam` (the
non-centred albedo coordinates the batched sampler moves in), :mod:`._emcee` (ensemble
sampler), :mod:`._adaptive` (Laplace everywhere, MCMC where flagged), :mod:`._diagnostics`
(ArviZ, R-hat/ESS, plots, predictive checks), :mod:`._sbc` (simulation-based
calibration), :mod:`._maps` (EXR uncertainty channels).
"""

from ._adaptive import HEARTBEAT_S as HEARTBEAT_S
from ._adaptive import MAP_OPTIONS as MAP_OPTIONS
from ._adaptive import METHODS as METHODS
from ._adaptive import RERUN_RHAT as RERUN_RHAT
from ._adaptive import AdaptiveOptions as AdaptiveOptions
from ._adaptive import MCMCPixels as MCMCPixels
from ._adaptive import UncertaintyMap as UncertaintyMap
from ._adaptive import adaptive_uncertainty as adaptive_uncertainty
from ._adaptive import laplace_summary as laplace_summary
from ._adaptive import longer_options as longer_options
from ._adaptive import untuned_rerun as untuned_rerun
from ._batched import HMCOptions as HMCOptions
from ._batched import sample_pixels as sample_pixels
from ._diagnostics import diagnostics as diagnostics
from ._diagnostics import log_likelihood_draws as log_likelihood_draws
from ._diagnostics import plot_corner as plot_corner
from ._diagnostics import plot_ppc as plot_ppc
from ._diagnostics import plot_rank as plot_rank
from ._diagnostics import plot_trace as plot_trace
from ._diagnostics import posterior_predictive as posterior_predictive
from ._diagnostics import save_netcdf as save_netcdf
from ._diagnostics import split_rhat as split_rhat
from ._diagnostics import to_inference_data as to_inference_data
from ._emcee import Convergence as Convergence
from ._emcee import EmceeOptions as EmceeOptions
from ._emcee import autocorr_check as autocorr_check
from ._emcee import convergence as convergence
from ._emcee import sample_emcee as sample_emcee
from ._logpost import LogPosterior as LogPosterior
from ._logpost import SharedLight as SharedLight
from ._logpost import log_posterior as log_posterior
from ._maps import NonFinite as NonFinite
from ._maps import uncertainty_channels as uncertainty_channels
from ._maps import write_uncertainty_exr as write_uncertainty_exr
from ._methods import MCMC_METHODS as MCMC_METHODS
from ._methods import Method as Method
from ._priors import HalfCauchy as HalfCauchy
from ._priors import Jeffreys as Jeffreys
from ._priors import LogNormal as LogNormal
from ._priors import MultivariateNormal as MultivariateNormal
from ._priors import Normal as Normal
from ._priors import Prior as Prior
from ._priors import Uniform as Uniform
from ._priors import VonMisesFisher as VonMisesFisher
from ._priors import default_priors as default_priors
from ._priors import sample_truncated as sample_truncated
from ._reparam import ConditionalAlbedo as ConditionalAlbedo
from ._reparam import conditional_albedo as conditional_albedo
from ._samples import Samples as Samples
from ._sbc import SBCResult as SBCResult
from ._sbc import coverage as coverage
from ._sbc import pit as pit
from ._sbc import ranks as ranks
from ._sbc import sbc_summary as sbc_summary
from ._sbc import thin as thin
from ._sbc import uniformity as uniformity
from ._sphere import SphereDirection as SphereDirection
from ._sphere import angle_deg as angle_deg
from ._sphere import direction_summary as direction_summary
from ._sphere import lit_geometry as lit_geometry
from ._workers import default_workers as default_workers

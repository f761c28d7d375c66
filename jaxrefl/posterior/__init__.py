"""Pixels to posteriors: MCMC over reflectance parameters and light direction, diagnostics,
calibration and uncertainty maps.
"""

from ._batched import HMCOptions as HMCOptions
from ._batched import Samples as Samples
from ._batched import sample_pixels as sample_pixels
from ._emcee import sample_emcee as sample_emcee
from ._logpost import LogPosterior as LogPosterior
from ._logpost import SharedLight as SharedLight
from ._logpost import log_posterior as log_posterior
from ._priors import HalfCauchy as HalfCauchy
from ._priors import Jeffreys as Jeffreys
from ._priors import LogNormal as LogNormal
from ._priors import Normal as Normal
from ._priors import Prior as Prior
from ._priors import Uniform as Uniform
from ._priors import VonMisesFisher as VonMisesFisher
from ._priors import default_priors as default_priors
from ._priors import sample_truncated as sample_truncated
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
from ._sphere import onb as onb
from ._sphere import to_local as to_local

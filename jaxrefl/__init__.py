"""jaxrefl: probabilistic reflectance estimation in JAX."""

from . import brdf as brdf, io as io, scene as scene, spectral as spectral

__version__ = "0.1.0"

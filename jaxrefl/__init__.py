"""jaxrefl: probabilistic reflectance estimation in JAX."""

from . import brdf as brdf

__version__ = "0.1.0"

"""jaxrefl: probabilistic reflectance estimation in JAX."""

from . import brdf as brdf
from . import fit as fit
from . import io as io
from . import scene as scene
from . import spectral as spectral
from ._errors import JaxreflError as JaxreflError

__version__ = "0.1.0"

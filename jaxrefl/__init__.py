"""jaxrefl: probabilistic reflectance estimation in JAX.

``import jaxrefl`` gives every subpackage (``brdf``, ``fit``, ``io``, ``scene``,
``spectral``, ``measured``, ``phone``, ``posterior``, ``ps``, ``svbrdf``, ``cli``, ``demo``,
``plot``), each imported on first attribute access (module ``__getattr__``, PEP 562): ``import
jaxrefl`` itself loads neither JAX nor anything heavier, so ``jaxrefl --help`` answers
without importing JAX, and BlackJAX, emcee, SciPy or Matplotlib load only for the
subpackages that use them.
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import TYPE_CHECKING

from ._errors import JaxreflError as JaxreflError

if TYPE_CHECKING:
    from . import brdf as brdf
    from . import cli as cli
    from . import demo as demo
    from . import fit as fit
    from . import io as io
    from . import measured as measured
    from . import phone as phone
    from . import plot as plot
    from . import posterior as posterior
    from . import ps as ps
    from . import scene as scene
    from . import spectral as spectral
    from . import svbrdf as svbrdf

__version__ = "0.1.0"

#: Imported on first access: ``jaxrefl.svbrdf.fit_capture`` works after ``import jaxrefl``.
_LAZY = (
    "brdf",
    "cli",
    "demo",
    "fit",
    "io",
    "measured",
    "phone",
    "plot",
    "posterior",
    "ps",
    "scene",
    "spectral",
    "svbrdf",
)


def __getattr__(name: str) -> ModuleType:
    if name in _LAZY:
        # import_module also binds the module as an attribute of this package, so this
        # hook runs once per name.
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))

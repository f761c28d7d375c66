"""Which samples and channels of a measured BRDF a fit uses, what it minimises and whether
float32 may be redone in float64: the :class:`MeasuredOptions` of
:func:`~jaxrefl.measured.fit_model`, :func:`~jaxrefl.measured.fit_brdf` (:mod:`._fit`),
:func:`~jaxrefl.measured.fit_multistart` (:mod:`._starts`) and
:func:`~jaxrefl.measured.sample_posterior`.

They sit beside the solver's :class:`~jaxrefl.fit.FitConfig` and the starts'
:class:`~jaxrefl.measured.MultiStart`, so that every setting that changes a measured fit is an
option object, and the report's ``settings`` record them all.
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

from jaxrefl._errors import JaxreflError
from jaxrefl._names import ILLUMINANTS, SPECTRAL_CHOICES
from jaxrefl.fit import Option

__all__ = ["MeasuredOptions"]


class MeasuredOptions(Option):
    """The samples and channels a measured fit uses and what it minimises.

    max_theta_deg: samples with either direction further than this from the normal are left
                   out of the fit and of the metrics (default 80 degrees, as Ngan et al.
                   2005); None keeps every sample above the horizon
    cosine:        minimise (f̂ - f) cos(theta_i), the residual inside the cosine-weighted L2
                   of Ngan et al. (default True); False fits f_r itself
    retry_float64: redo a float32 fit in float64 when it has a non-finite cost or parameter
                   or a NONFINITE_INPUT / ILL_CONDITIONED status, and keep the float64
                   result when it is finite and no worse (:mod:`._retry`; default True)
    spectral:      how spectral data (``wavelengths_nm`` set, e.g. Cornell) are fitted:
                   ``"rgb"`` (default) converts them to linear sRGB under ``illuminant``
                   (:func:`~jaxrefl.measured.to_rgb`) and fits the three channels jointly
                   (colour per channel, shared roughness); ``"bands"`` fits every band as its
                   own problem (its own roughness too). Other data are fitted jointly as
                   they are, whatever this says
    illuminant:    ``"D65"`` (default) or ``"E"`` (equal energy), for the RGB conversion
    """

    kind: ClassVar[str] = "measured"
    max_theta_deg: float | None = 80.0
    cosine: bool = True
    retry_float64: bool = True
    spectral: Literal["rgb", "bands"] = "rgb"
    illuminant: Literal["D65", "E"] = "D65"

    def __check_init__(self):
        t = self.max_theta_deg
        if t is not None and not (isinstance(t, int | float) and math.isfinite(t) and 0 < t <= 90):
            raise JaxreflError(f"MeasuredOptions needs max_theta_deg in (0, 90] or None, got {t}")
        for name in ("cosine", "retry_float64"):
            if not isinstance(getattr(self, name), bool):
                raise JaxreflError(
                    f"MeasuredOptions needs {name} True or False, got {getattr(self, name)!r}"
                )
        for name, allowed in (("spectral", SPECTRAL_CHOICES), ("illuminant", ILLUMINANTS)):
            if getattr(self, name) not in allowed:
                raise JaxreflError(
                    f"MeasuredOptions needs {name} one of {', '.join(map(repr, allowed))}, "
                    f"got {getattr(self, name)!r}"
                )

"""How the model-discrepancy term of a capture's predictive intervals is estimated: the
:class:`DiscrepancyOptions` of :func:`~jaxrefl.svbrdf.estimate_discrepancy`
(:mod:`._predictive`), so that every setting that changes the estimate is one option object.
"""

from __future__ import annotations

from typing import ClassVar

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import Option

__all__ = ["DiscrepancyOptions"]


class DiscrepancyOptions(Option):
    """The rows, bins and noise model of :func:`~jaxrefl.svbrdf.estimate_discrepancy`.

    max_pixels:    rows in all (pixels x training photos; at least 256 pixels a photo),
                   drawn at random with ``seed`` (>= 1; default 4096)
    bins:          quantile bins of predicted radiance (>= 1; default 8)
    seed:          of the random rows (>= 0)
    replace_noise: estimate the whole observation variance beyond the parameter term and
                   use it in place of the fit's noise term (:mod:`._predictive`); None (the
                   default): True exactly when the fit's noise is one known variance for
                   the capture (``pooled``), False where each pixel has its own estimate
    """

    kind: ClassVar[str] = "discrepancy"
    max_pixels: int = 4096
    bins: int = 8
    seed: int = 0
    replace_noise: bool | None = None

    def __check_init__(self):
        for name, low in (("max_pixels", 1), ("bins", 1), ("seed", 0)):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= low):
                raise JaxreflError(
                    f"DiscrepancyOptions needs an integer {name} >= {low}, got {v!r}"
                )
        if self.replace_noise not in (None, True, False):
            raise JaxreflError(
                "DiscrepancyOptions needs replace_noise True, False or None, got "
                f"{self.replace_noise!r}"
            )

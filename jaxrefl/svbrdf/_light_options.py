"""The settings of :func:`~jaxrefl.svbrdf.estimate_light` other than the light asked for:
:class:`LightOptions`, so that every setting that changes the estimate is one option object.

:func:`~jaxrefl.svbrdf.fit_capture` builds one from its :class:`~jaxrefl.svbrdf.FitJob`
(:meth:`LightOptions.of_job`: the job's held-out photos and ``alpha_min``, the default
pixels and seed).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import Option

from ._light_problem import SELECTION_PIXELS

if TYPE_CHECKING:
    from ._job_types import FitJob

__all__ = ["LightOptions"]


class LightOptions(Option):
    """Which photos and pixels the light is estimated from, and the lobe it may use.

    holdout:   photos never looked at (indices; those outside the capture are ignored, as
               ``FitJob.holdout``'s)
    n_pixels:  pixels in each half of the random subsample (the light fitted on one half and
               scored on the other; fewer where the capture is small; >= 1; default
               :data:`jaxrefl.svbrdf._light_problem.SELECTION_PIXELS`)
    seed:      of the random subsample (>= 0)
    alpha_min: the narrowest lobe a pixel may have, the fit's (``FitJob.alpha_min``; None:
               the capture's resolvable width)
    """

    kind: ClassVar[str] = "light"
    holdout: tuple[int, ...] = ()
    n_pixels: int = SELECTION_PIXELS
    seed: int = 0
    alpha_min: float | None = None

    def __check_init__(self) -> None:
        for name, low in (("n_pixels", 1), ("seed", 0)):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= low):
                raise JaxreflError(f"LightOptions needs an integer {name} >= {low}, got {v!r}")
        if not all(isinstance(i, int) and not isinstance(i, bool) for i in self.holdout):
            raise JaxreflError(f"LightOptions.holdout must be photo indices, got {self.holdout!r}")

    @classmethod
    def of_job(cls, job: FitJob) -> LightOptions:
        """The options of ``job``'s light: its held-out photos and ``alpha_min``, the
        default pixels and seed."""
        return cls(holdout=tuple(job.holdout), alpha_min=job.alpha_min)

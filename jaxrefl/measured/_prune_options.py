"""What a pruning decides by and over which pixels: the :class:`PruneOptions` of
:func:`~jaxrefl.measured.prune` (:mod:`._prune`).

They sit beside the fits' :class:`~jaxrefl.fit.FitConfig`, so that every setting that changes
a pruning is an option object and :meth:`~jaxrefl.measured.PruneReport.to_dict` records them
all. The data stay arguments of :func:`~jaxrefl.measured.prune`: the pixels, their ``mask``
and, with ``groups="labels"``, their group ``labels``.
"""

from __future__ import annotations

from typing import ClassVar, Literal

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import Option, check_number

__all__ = ["CRITERIA", "GROUPINGS", "NOISE_SETTINGS", "PruneOptions"]

CRITERIA = ("bic", "evidence")
GROUPINGS = ("pixel", "all", "kmeans", "labels")
NOISE_SETTINGS = ("estimate", "known")


class PruneOptions(Option):
    """The criterion, the groups and the pixels a pruning keeps (:mod:`._prune`).

    criterion:   ``"bic"`` (default; lower is better) or ``"evidence"`` (the Laplace log
                 marginal likelihood; higher is better)
    groups:      which pixels share a decision: ``"pixel"`` (default: each alone), ``"all"``
                 (one material), ``"kmeans"`` (``n_clusters`` clusters of colour and gloss)
                 or ``"labels"`` (the ``labels`` given to :func:`~jaxrefl.measured.prune`)
    n_clusters:  clusters of ``"kmeans"`` (>= 1; default 4)
    seed:        seed of ``"kmeans"`` (>= 0)
    saturation:  observations >= this count as saturated and leave their pixel out of the
                 fits (besides ``censored == +1``; None: only those)
    noise_floor: an observation carries signal only above this value (obs units, >= 0)
    noise:       ``"estimate"`` (default: the noise variance of the richest fit) or
                 ``"known"`` (residuals already whitened by the right sigma: variance 1)
    prior_width: std of the evidence's Gaussian prior on the unconstrained parameters (> 0;
                 default 3)
    """

    kind: ClassVar[str] = "prune"
    criterion: Literal["bic", "evidence"] = "bic"
    groups: Literal["pixel", "all", "kmeans", "labels"] = "pixel"
    n_clusters: int = 4
    seed: int = 0
    saturation: float | None = None
    noise_floor: float = 0.0
    noise: Literal["estimate", "known"] = "estimate"
    prior_width: float = 3.0

    def __check_init__(self):
        for name, allowed in (
            ("criterion", CRITERIA),
            ("groups", GROUPINGS),
            ("noise", NOISE_SETTINGS),
        ):
            if getattr(self, name) not in allowed:
                raise JaxreflError(
                    f"PruneOptions needs {name} one of {', '.join(map(repr, allowed))}, "
                    f"got {getattr(self, name)!r}"
                )
        for name, low in (("n_clusters", 1), ("seed", 0)):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= low):
                raise JaxreflError(f"PruneOptions needs an integer {name} >= {low}, got {v!r}")
        if self.saturation is not None:
            check_number("PruneOptions", "saturation", self.saturation)
        check_number("PruneOptions", "noise_floor", self.noise_floor)
        check_number("PruneOptions", "prior_width", self.prior_width, positive=True)

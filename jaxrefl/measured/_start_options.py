"""How many starts a multi-start measured fit solves, and when their agreement is doubtful:
the :class:`MultiStart` option of :func:`~jaxrefl.measured.fit_multistart` (:mod:`._starts`).
"""

from __future__ import annotations

import math
from typing import ClassVar

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import Option

__all__ = ["MultiStart"]


class MultiStart(Option):
    """How many starts a measured fit solves, and when their agreement is doubtful.

    n_random:   quasi-random starts (Sobol, scrambled with ``seed``), >= 0; default 24
    data:       include the data-driven starts (default True; 6 starts, one for a model
                with no lobe)
    nested:     a model that contains a smaller one (:func:`nested_model`) also starts from
                the smaller model's fit plus one new lobe (default True; 25 + 2 (L-1) starts
                for L Lafortune lobes)

    The automatic start of a single fit is always solved too (:mod:`._starts`).
    seed:       seed of the Sobol scrambling
    rounds:     continuation budgets (:mod:`._starts`), >= 0; default 4
    polish:     how many of the lowest-cost starts of a problem must have converged (or
                stopped for another reason than the budget) for the continuation to end,
                >= 1; default 4; also how many best results the perturbed generation
                starts from
    generations: perturbed generations at most (:mod:`._starts`), >= 0; default 3
    agree_rtol: a start agrees when its cost is within this fraction of the best (0.01)
    min_share:  the certificate flags the optimum as doubtful when fewer than this share
                of the starts agree (0.2)
    """

    kind: ClassVar[str] = "multistart"
    n_random: int = 24
    data: bool = True
    nested: bool = True
    seed: int = 0
    rounds: int = 4
    polish: int = 4
    generations: int = 3
    agree_rtol: float = 0.01
    min_share: float = 0.2

    def __check_init__(self):
        if not isinstance(self.n_random, int) or self.n_random < 0:
            raise JaxreflError(f"MultiStart needs an integer n_random >= 0, got {self.n_random}")
        if not isinstance(self.rounds, int) or self.rounds < 0:
            raise JaxreflError(f"MultiStart needs an integer rounds >= 0, got {self.rounds}")
        if not isinstance(self.generations, int) or self.generations < 0:
            raise JaxreflError(
                f"MultiStart needs an integer generations >= 0, got {self.generations}"
            )
        if not isinstance(self.polish, int) or self.polish < 1:
            raise JaxreflError(f"MultiStart needs an integer polish >= 1, got {self.polish}")
        if self.n_random == 0 and not self.data:
            raise JaxreflError("MultiStart needs at least one start: n_random > 0 or data=True")
        if not (math.isfinite(self.agree_rtol) and self.agree_rtol >= 0):
            raise JaxreflError(f"MultiStart needs a finite agree_rtol >= 0, got {self.agree_rtol}")
        if not (0.0 <= self.min_share <= 1.0):
            raise JaxreflError(f"MultiStart needs min_share in [0, 1], got {self.min_share}")

"""How far the starts of a multi-start fit agree on its optimum.

The :class:`Certificate` counts the starts whose cost is within ``agree_rtol`` (1%) of the
best and flags the optimum as doubtful when their share is below ``min_share``: a user
then sees that the starts disagree, not only the best value found.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Certificate", "certify"]

# Costs below this fraction of the data's own 1/2 |y|^2 are an exact fit, equal within
# round-off (see certify).
_EXACT = 1e-6


@dataclass(frozen=True)
class Certificate:
    """How far the starts of a multi-start fit agree on its optimum.

    n_starts:   starts solved (per problem)
    n_agree:    starts whose cost is within ``rtol`` of the best (the worst problem's count
                when channels are separate problems)
    best_cost:  the lowest cost (the solver's 1/2 |r|^2), summed over problems
    excess:     relative excess (c - c_best)/c_best of the starts that do not agree:
                ``min``, ``median``, ``max`` over the finite ones (None where there are
                none), ``failed`` the count of starts without a finite cost
    rtol, min_share: the thresholds (:class:`MultiStart`)
    """

    n_starts: int
    n_agree: int
    best_cost: float
    excess: dict[str, Any]
    rtol: float
    min_share: float

    @property
    def share(self) -> float:
        """Fraction of the starts that agree."""
        return self.n_agree / max(self.n_starts, 1)

    @property
    def doubtful(self) -> bool:
        """True when fewer than ``min_share`` of the starts agree."""
        return self.share < self.min_share

    def short(self) -> str:
        """``"18/30"``, with ``" doubtful"`` appended when flagged."""
        return f"{self.n_agree}/{self.n_starts}" + (" doubtful" if self.doubtful else "")

    def to_dict(self) -> dict[str, Any]:
        return {
            "n_starts": self.n_starts,
            "n_agree": self.n_agree,
            "share": self.share,
            "agree_rtol": self.rtol,
            "min_share": self.min_share,
            "doubtful": self.doubtful,
            "best_cost": self.best_cost,
            "excess_of_the_rest": self.excess,
        }


def certify(
    costs: np.ndarray, rtol: float = 0.01, min_share: float = 0.2, scale: float = 0.0
) -> Certificate:
    """The :class:`Certificate` of costs (S,) of one problem or (N, S) of N problems.

    A start agrees when c - c_best <= rtol max(c_best, ``_EXACT`` scale), where ``scale`` is
    the cost of a zero prediction (1/2 |y|^2): at an (almost) exact fit every cost is
    round-off, and those below a millionth of the data's own agree with each other.
    """
    c = np.atleast_2d(np.asarray(costs, np.float64))
    c = np.where(np.isfinite(c), c, np.inf)
    best = np.min(c, axis=1, keepdims=True)
    tol = rtol * np.maximum(np.abs(best), _EXACT * scale) + np.finfo(np.float64).tiny
    agree = c <= best + tol
    n_agree = int(np.min(np.sum(agree, axis=1)))
    rel = (c - best) / np.where(best > 0, best, 1.0)
    rest = rel[~agree & np.isfinite(rel)]
    excess: dict[str, Any] = {"failed": int(np.sum(~np.isfinite(c)))}
    for k, fn in (("min", np.min), ("median", np.median), ("max", np.max)):
        excess[k] = float(fn(rest)) if rest.size else None
    total = float(np.sum(best)) if np.all(np.isfinite(best)) else math.inf
    return Certificate(c.shape[1], n_agree, total, excess, rtol, min_share)

"""How ``FitJob(model="auto")`` chooses the capture's model: the :class:`AutoOptions` a
:class:`~jaxrefl.svbrdf.FitJob` carries to :func:`~jaxrefl.svbrdf.choose_model`.

They live apart from the choice itself (:mod:`._auto`), so that the job's types
(:mod:`._job_types`) hold them without importing the tile fitter the choice runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from jaxrefl._errors import JaxreflError
from jaxrefl._names import CAPTURE_MODELS, canonical

__all__ = ["AUTO_CANDIDATES", "SELECTION_PIXELS", "AutoOptions"]

# In order of complexity (parameters per pixel, then shared structure): ties go to the first.
AUTO_CANDIDATES: tuple[str, ...] = ("lambert", "pooled", "ggx", "ggx_rgb", "ggx_normal")
SELECTION_PIXELS = 4096


@dataclass(frozen=True)
class AutoOptions:
    """The model choice's settings (:mod:`jaxrefl.svbrdf._auto`); each changes which model a
    capture gets, and ``pooled``'s shared width where it wins.

    candidates: the models scored (names of :data:`jaxrefl.svbrdf.CAPTURE_MODELS`), simplest
                first: ties and near-ties go to the first (default :data:`AUTO_CANDIDATES`)
    max_pixels: selection rows in all (pixels x leave-one-out folds; at least 256 pixels a
                fold), every candidate scored on the same rows
    seed:       of the random selection pixels
    """

    candidates: tuple[str, ...] = AUTO_CANDIDATES
    max_pixels: int = SELECTION_PIXELS
    seed: int = 0

    def __post_init__(self) -> None:
        cands = tuple(canonical(m) for m in self.candidates)
        if not cands or "auto" in cands:
            raise JaxreflError(
                "AutoOptions.candidates must name one or more models other than 'auto'"
            )
        unknown = [m for m in cands if m not in CAPTURE_MODELS]
        if unknown:
            raise JaxreflError(
                f"AutoOptions.candidates: unknown model {', '.join(map(repr, unknown))}; "
                f"choose from {', '.join(CAPTURE_MODELS)}"
            )
        if len(set(cands)) != len(cands):
            raise JaxreflError(f"AutoOptions.candidates names a model twice: {cands}")
        object.__setattr__(self, "candidates", cands)
        if isinstance(self.max_pixels, bool) or not isinstance(self.max_pixels, int):
            raise JaxreflError(
                f"AutoOptions.max_pixels must be an integer, got {self.max_pixels!r}"
            )
        if self.max_pixels < 1:
            raise JaxreflError(f"AutoOptions.max_pixels must be >= 1, got {self.max_pixels}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise JaxreflError(f"AutoOptions.seed must be an integer, got {self.seed!r}")

    def to_json(self) -> dict[str, Any]:
        """The settings as plain JSON values (the report's ``auto`` and the job's record)."""
        return {
            "candidates": list(self.candidates),
            "max_pixels": self.max_pixels,
            "seed": self.seed,
        }

"""Photometric-stereo solvers as option objects: which method, with which settings.

A method is a small immutable object (:class:`PSMethod`, :mod:`._method`: the option style
of :mod:`jaxrefl.fit`) whose :meth:`PSMethod.solve` maps N pixels' observations to a
:class:`PSResult`; each holds every setting of its solver, which takes it as ``options``:

- :class:`LeastSquares` (``"ls"``): Woodham's least-squares Lambertian PS
  (:func:`jaxrefl.ps.woodham`);
- :class:`Robust` (``"robust"``, :mod:`._robust`): Lambertian PS with shadows and
  highlights down-weighted (:func:`jaxrefl.ps.robust`);
- :class:`NormalBRDF` (``"brdf"``, :mod:`._brdf`): normal and microfacet BRDF fitted
  together per pixel (:func:`jaxrefl.ps.fit_normal_brdf`).

``METHODS`` maps each kind to its class; the command line picks one by name
(``jaxrefl ps --method``), the library takes the object (:func:`jaxrefl.ps.solve_capture`).
"""

from __future__ import annotations

from ._brdf import NormalBRDF
from ._method import PSMethod
from ._robust import Robust
from ._woodham import PSResult, woodham

__all__ = ["METHODS", "LeastSquares", "NormalBRDF", "PSMethod", "Robust"]


class LeastSquares(PSMethod):
    """Woodham's least-squares Lambertian PS; saturated observations count as measured."""

    kind = "ls"

    def solve(self, obs, lights, intensities, weight, saturated) -> PSResult:
        return woodham(obs, lights, intensities, weight)


METHODS: dict[str, type[PSMethod]] = {m.kind: m for m in (LeastSquares, Robust, NormalBRDF)}

"""Photometric-stereo solvers as option objects: which method, with which settings.

A method is a small immutable object (the option style of :mod:`jaxrefl.fit`: a
:class:`jaxrefl.fit.Option` that names its ``kind`` and writes itself as JSON) whose
:meth:`PSMethod.solve` maps N pixels' observations to a :class:`PSResult`:

- :class:`LeastSquares` (``"ls"``): Woodham's least-squares Lambertian PS
  (:func:`jaxrefl.ps.woodham`);
- :class:`Robust` (``"robust"``): Lambertian PS with shadows and highlights down-weighted
  (:func:`jaxrefl.ps.robust`);
- :class:`NormalBRDF` (``"brdf"``): normal and microfacet BRDF fitted together per pixel
  (:func:`jaxrefl.ps.fit_normal_brdf`).

``METHODS`` maps each kind to its class; the command line picks one by name
(``jaxrefl ps --method``), the library takes the object (:func:`jaxrefl.ps.solve_capture`).
"""

from __future__ import annotations

import abc
from typing import Any

from jaxtyping import ArrayLike, Float

from jaxrefl import fit as jf
from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF

from ._brdf import fit_normal_brdf
from ._robust import robust
from ._woodham import PSResult, woodham

__all__ = ["METHODS", "LeastSquares", "NormalBRDF", "PSMethod", "Robust"]


class PSMethod(jf.Option):
    """A photometric-stereo solver (module docstring)."""

    @abc.abstractmethod
    def solve(
        self,
        obs: Float[ArrayLike, "N K C"],
        lights: Float[ArrayLike, "K 3"],
        intensities: Float[ArrayLike, "K C"] | None,
        weight: Float[ArrayLike, "N K C"] | None,
        saturated: ArrayLike | None,
    ) -> PSResult:
        """Normals, albedo and status of N pixels. ``obs`` linear values, ``lights`` unit
        directions towards the lights, ``intensities`` E_kc, ``weight`` >= 0 per
        observation, ``saturated`` (N, K, C) bool: observations at the top code."""


class LeastSquares(PSMethod):
    """Woodham's least-squares Lambertian PS; saturated observations count as measured."""

    kind = "ls"

    def solve(self, obs, lights, intensities, weight, saturated) -> PSResult:
        return woodham(obs, lights, intensities, weight)


class Robust(PSMethod):
    """Lambertian PS with shadows and highlights down-weighted (:func:`jaxrefl.ps.robust`:
    ``shadow`` dark threshold relative to the pixel's reference level, ``scale_floor``,
    ``iters`` reweighting rounds, ``trim`` brightest share left out of the starting fit)."""

    kind = "robust"
    shadow: float = 0.05
    scale_floor: float = 1e-3
    iters: int = 5
    trim: float = 0.25

    def __check_init__(self) -> None:
        for name in ("shadow", "scale_floor", "trim"):
            jf.check_number("Robust", name, getattr(self, name))
        if self.iters < 0:
            raise JaxreflError(f"Robust needs iters >= 0, got {self.iters}")

    def solve(self, obs, lights, intensities, weight, saturated) -> PSResult:
        return robust(
            obs,
            lights,
            intensities,
            weight,
            shadow=self.shadow,
            scale_floor=self.scale_floor,
            iters=self.iters,
            trim=self.trim,
        )


class NormalBRDF(PSMethod):
    """Normal and BRDF fitted together per pixel (:func:`jaxrefl.ps.fit_normal_brdf`, whose
    docstring gives ``model`` (None: :func:`jaxrefl.ps.default_model`), ``config``,
    ``shadow``, ``init``, ``batch`` and ``select``); saturated observations are censored."""

    kind = "brdf"
    model: BRDF | None = None
    config: jf.FitConfig = jf.FitConfig()
    shadow: float = 0.05
    init: str = "diffuse"
    batch: int = 2048
    select: float | None = None

    def __check_init__(self) -> None:
        if self.init not in ("diffuse", "grid"):
            raise JaxreflError(f"NormalBRDF init must be 'diffuse' or 'grid', not {self.init!r}")
        jf.check_number("NormalBRDF", "shadow", self.shadow)
        if self.batch < 1:
            raise JaxreflError(f"NormalBRDF needs batch >= 1, got {self.batch}")

    def solve(self, obs, lights, intensities, weight, saturated) -> PSResult:
        return fit_normal_brdf(
            obs,
            lights,
            intensities,
            weight,
            saturated,
            model=self.model,
            config=self.config,
            shadow=self.shadow,
            init=self.init,
            batch=self.batch,
            select=self.select,
        ).ps

    def to_json(self) -> dict[str, Any]:
        out = super().to_json()
        out["model"] = None if self.model is None else type(self.model).__name__
        return out


METHODS: dict[str, type[PSMethod]] = {m.kind: m for m in (LeastSquares, Robust, NormalBRDF)}

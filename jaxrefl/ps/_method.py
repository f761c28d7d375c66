"""The base of the photometric-stereo method objects: :class:`PSMethod`.

A method is a small immutable object (the option style of :mod:`jaxrefl.fit`: a
:class:`jaxrefl.fit.Option` that names its ``kind`` and writes itself as JSON) holding every
setting of its solver; :meth:`PSMethod.solve` maps N pixels' observations to a
:class:`~jaxrefl.ps.PSResult`. Each method lives beside its solver, which takes it as its
``options`` (:mod:`._robust`, :mod:`._brdf`); this module holds only what they share, so
that a solver imports its options without importing the registry (:mod:`._methods`).
"""

from __future__ import annotations

import abc

from jaxtyping import ArrayLike, Float

from jaxrefl import fit as jf

from ._woodham import PSResult

__all__ = ["PSMethod"]


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

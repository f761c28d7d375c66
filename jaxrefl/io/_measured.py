"""The common container for measured BRDF samples, and the error every reader raises.

A :class:`MeasuredBRDF` holds N samples of f_r(wi, wo) in 1/sr (no cosine factor) in the
convention of :mod:`jaxrefl.brdf`: unit vectors in the local frame (z = surface normal,
tangent +x), both ``wi`` (towards the light) and ``wo`` (towards the sensor) pointing away
from the surface. Arrays are NumPy float64: files are read once, on the host, and handed to
JAX by the fitting code (``jnp.asarray(m.wi)``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from jaxrefl._errors import JaxreflError

__all__ = ["MeasuredBRDF", "MeasuredDataError", "directions_from_angles"]


class MeasuredDataError(JaxreflError):
    """A measured-data file is corrupt, truncated or not in the expected format.

    The message names the file and the problem (and the line where there is one).
    """

    def __init__(self, path: str | Path | None, problem: str, line: int | None = None):
        self.path = None if path is None else Path(path)
        self.problem = problem
        self.line = line
        where = "" if line is None else f", line {line}"
        super().__init__(f"{path}{where}: {problem}")


def directions_from_angles(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit vectors (..., 3) from polar angle θ (from +z) and azimuth φ (from +x towards +y),
    radians, float64 (the NumPy twin of ``jaxrefl.brdf._frame.spherical_direction``)."""
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)


@dataclass(frozen=True, eq=False)
class MeasuredBRDF:
    """N measured samples of one material.

    Attributes
    ----------
    wi, wo:
        (N, 3) float64 unit vectors, local frame, pointing away from the surface.
    values:
        (N, C) float64, f_r in 1/sr (no cosine factor). May hold negative numbers (sensor
        noise after dark subtraction) and, from some files, non-finite ones; see
        :meth:`mask_valid`.
    channels:
        C channel names: ``("400nm", ...)`` for spectra, ``("R", "G", "B")`` for colour.
    wavelengths_nm:
        (C,) float64 band centres for spectral data, else None.
    name, source:
        Material name and the file(s) it was read from.
    meta:
        Anything else the file says (header fields, raw angles, counts of dropped rows).
    """

    wi: np.ndarray
    wo: np.ndarray
    values: np.ndarray
    channels: tuple[str, ...]
    wavelengths_nm: np.ndarray | None = None
    name: str = ""
    source: str | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        wi = np.asarray(self.wi, dtype=np.float64)
        wo = np.asarray(self.wo, dtype=np.float64)
        values = np.asarray(self.values, dtype=np.float64)
        channels = tuple(str(c) for c in self.channels)
        if wi.ndim != 2 or wi.shape[1] != 3 or wo.shape != wi.shape:
            raise MeasuredDataError(
                self.source, f"wi and wo must both be (N, 3); got {wi.shape} and {wo.shape}"
            )
        if values.ndim != 2 or values.shape[0] != wi.shape[0]:
            raise MeasuredDataError(
                self.source, f"values must be (N, C) with N = {wi.shape[0]}; got {values.shape}"
            )
        if values.shape[1] != len(channels):
            raise MeasuredDataError(
                self.source,
                f"{values.shape[1]} value columns but {len(channels)} channel names {channels}",
            )
        wl = self.wavelengths_nm
        if wl is not None:
            wl = np.asarray(wl, dtype=np.float64)
            if wl.shape != (len(channels),):
                raise MeasuredDataError(
                    self.source, f"wavelengths_nm must have shape ({len(channels)},): {wl.shape}"
                )
        # frozen dataclass: normalised fields are written through object.__setattr__.
        for k, v in (("wi", wi), ("wo", wo), ("values", values), ("channels", channels)):
            object.__setattr__(self, k, v)
        object.__setattr__(self, "wavelengths_nm", wl)

    def __len__(self) -> int:
        return int(self.wi.shape[0])

    @property
    def n_channels(self) -> int:
        return len(self.channels)

    def __repr__(self) -> str:
        return (
            f"MeasuredBRDF(name={self.name!r}, samples={len(self)}, "
            f"channels={self.n_channels}, source={self.source!r})"
        )

    def select(self, index: np.ndarray | slice) -> MeasuredBRDF:
        """The samples picked by a boolean mask of length N, an integer index array or a slice
        (a new object; ``meta`` is copied shallowly)."""
        if not isinstance(index, slice):
            index = np.asarray(index)
            if index.dtype == bool and index.shape != (len(self),):
                raise JaxreflError(
                    f"boolean mask must have shape ({len(self)},), got {index.shape}"
                )
        return replace(
            self,
            wi=self.wi[index],
            wo=self.wo[index],
            values=self.values[index],
            meta=dict(self.meta),
        )

    def select_channels(self, names: tuple[str, ...] | list[str]) -> MeasuredBRDF:
        """Keep the named channels, in the order given."""
        idx = [self.channels.index(n) for n in names]
        wl = None if self.wavelengths_nm is None else self.wavelengths_nm[idx]
        return replace(
            self,
            values=self.values[:, idx],
            channels=tuple(names),
            wavelengths_nm=wl,
            meta=dict(self.meta),
        )

    def mask_valid(self, *, drop_negative: bool = False) -> MeasuredBRDF:
        """Drop samples with any non-finite value (and, if asked, any negative one), and
        directions below or on the horizon; the counts go to ``meta["dropped"]``."""
        finite = np.all(np.isfinite(self.values), axis=1)
        above = (self.wi[:, 2] > 0) & (self.wo[:, 2] > 0)
        keep = finite & above
        dropped = {"non_finite": int(np.sum(~finite)), "below_horizon": int(np.sum(~above))}
        if drop_negative:
            nonneg = np.all(self.values >= 0, axis=1)
            dropped["negative"] = int(np.sum(finite & ~nonneg))
            keep &= nonneg
        out = self.select(keep)
        out.meta["dropped"] = dropped
        return out

    def count_negative(self) -> int:
        """Number of negative entries in ``values`` (sensor noise around zero)."""
        return int(np.sum(self.values < 0))

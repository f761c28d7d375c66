"""Measured samples ready for fitting: read any supported file, turn spectra into RGB, keep
the samples a fit should see.

* :func:`load_measured` reads a Cornell ASTM E1392 file (``.astm``), a CURET value file
  (``abrdf.dat`` and its ``table.txt``; one sample), or a MERL binary file (``.binary``,
  sampled at random cells), always returning a :class:`~jaxrefl.io.MeasuredBRDF`.
* :func:`to_rgb` converts spectral samples to linear sRGB under a stated illuminant with
  the CIE 1931 2-degree colour-matching functions (:func:`jaxrefl.spectral.spectrum_to_rgb`:
  the analytic CMF fit of Wyman, Sloan & Shirley 2013, XYZ -> linear sRGB by IEC 61966-2-1,
  white-normalised so that a constant f_r maps to the same f_r in every channel). f_r stays
  in 1/sr: the conversion is linear and maps a constant spectrum to itself.
* :func:`restrict` keeps finite samples above the horizon within ``max_theta_deg``.
* :func:`fit_channels` gives the channels a fit sees and whether they are fitted jointly, as
  :class:`~jaxrefl.measured.MeasuredOptions` says (spectra to RGB, or one problem a band).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Literal

import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.io import (
    MeasuredBRDF,
    merl_to_measured,
    read_cornell,
    read_curet,
    read_merl,
)
from jaxrefl.spectral import spectrum_to_rgb

from ._fit_options import MeasuredOptions
from ._metrics import usable_samples

__all__ = ["Channels", "detect_format", "fit_channels", "load_measured", "restrict", "to_rgb"]

Format = Literal["cornell", "curet", "merl"]
# ``joint``: one problem, a colour per channel and a shared roughness; ``separate``: one
# problem a channel (theta of shape (C, P)).
Channels = Literal["joint", "separate"]


def detect_format(path: str | Path) -> Format:
    """``"cornell"`` (``.astm``), ``"merl"`` (``.binary``) or ``"curet"`` (``.dat``); other
    names are recognised by content (a Cornell header has a ``VARS`` line)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".astm":
        return "cornell"
    if suffix == ".binary":
        return "merl"
    if suffix == ".dat":
        return "curet"
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such file")
    with p.open("rb") as fh:
        head = fh.read(4096)
    if b"VARS" in head or b"NUM_POINTS" in head:
        return "cornell"
    raise JaxreflError(
        f"{p}: cannot tell the format from the name; expected a Cornell .astm file, a CURET "
        ".dat value file (with table.txt) or a MERL .binary file"
    )


def load_measured(
    path: str | Path,
    *,
    curet_table: str | Path | None = None,
    curet_sample: int | None = None,
    merl_samples: int | None = 20_000,
    seed: int = 0,
) -> MeasuredBRDF:
    """Read one material from ``path`` (format from :func:`detect_format`).

    curet_table:  the CURET geometry table (default ``table.txt`` beside the value file)
    curet_sample: which of the 61 CURET samples (1-based); required for CURET files
    merl_samples: how many MERL cells to draw at random (``seed``); None keeps all valid
                  cells (about 1.1 million). The MERL table itself is kept in
                  ``meta["table_model"]`` (a :class:`~jaxrefl.brdf.MERL`) for plotting.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    fmt = detect_format(path)
    if fmt == "cornell":
        return read_cornell(path)
    if fmt == "merl":
        merl = read_merl(path)
        m = merl_to_measured(merl, merl_samples, seed=seed, name=path.stem, source=str(path))
        m.meta["table_model"] = merl
        return m
    table = Path(curet_table) if curet_table is not None else path.with_name("table.txt")
    if not table.is_file():
        raise FileNotFoundError(f"{table}: CURET geometry table not found (give curet_table)")
    if curet_sample is None:
        raise JaxreflError(f"{path}: a CURET file holds 61 samples; choose one (curet_sample)")
    return read_curet(path, table, sample=int(curet_sample))


def to_rgb(measured: MeasuredBRDF, illuminant: Literal["D65", "E"] = "D65") -> MeasuredBRDF:
    """Spectral samples as linear sRGB f_r (1/sr) under ``illuminant`` (module docstring).
    Non-finite values stay non-finite (the affected samples are dropped later)."""
    if measured.wavelengths_nm is None:
        raise JaxreflError(f"{measured.source}: not spectral data (no wavelengths)")
    v = np.asarray(measured.values)
    finite = np.all(np.isfinite(v), axis=-1, keepdims=True)
    rgb = np.asarray(
        spectrum_to_rgb(measured.wavelengths_nm, np.where(finite, v, 0.0), illuminant),
        dtype=np.float64,
    )
    rgb = np.where(finite, rgb, np.nan)
    meta = dict(measured.meta)
    meta["color"] = {
        "illuminant": illuminant,
        "cmf": "CIE 1931 2-degree (Wyman, Sloan & Shirley 2013 analytic fit)",
        "space": "linear sRGB (IEC 61966-2-1 matrix), white-normalised",
        "bands": list(measured.channels),
    }
    return replace(measured, values=rgb, channels=("R", "G", "B"), wavelengths_nm=None, meta=meta)


def restrict(measured: MeasuredBRDF, max_theta_deg: float | None = 80.0) -> MeasuredBRDF:
    """Finite samples with both directions above the horizon and within ``max_theta_deg`` of
    the normal (None: no angle limit); ``meta["restricted"]`` counts what was left out."""
    ok = usable_samples(measured.wi, measured.wo, measured.values, max_theta_deg)
    out = measured.select(ok)
    out.meta["restricted"] = {
        "max_theta_deg": max_theta_deg,
        "kept": int(ok.sum()),
        "dropped": int((~ok).sum()),
    }
    return out


def fit_channels(measured: MeasuredBRDF, options: MeasuredOptions) -> tuple[MeasuredBRDF, Channels]:
    """The samples as a fit under ``options`` sees them, and how their channels are fitted:
    spectral data as RGB under ``options.illuminant``, fitted jointly (``spectral="rgb"``), or
    as they are, one problem a band (``"bands"``); other data jointly, as they are."""
    if measured.wavelengths_nm is None:
        return measured, "joint"
    if options.spectral == "bands":
        return measured, "separate"
    return to_rgb(measured, options.illuminant), "joint"

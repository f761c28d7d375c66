"""Spectral utilities: measured complex refractive indices and spectrum -> RGB conversion.

* :func:`load_ior` reads ``NAME.eta.spd`` / ``NAME.k.spd`` tables (two columns: wavelength,
  value; ``#`` starts a comment line), as distributed with Mitsuba and pbrt from the luxpop
  database, and returns an :class:`IOR` with :meth:`IOR.at` (linear interpolation) and
  :meth:`IOR.to_rgb` (eta and k for an RGB renderer).
* :func:`spectrum_to_rgb` turns reflectance spectra (e.g. the Cornell BRDF data, 31 bands
  400..700 nm) into linear sRGB under a chosen illuminant.

Colorimetry. CIE 1931 2-degree colour-matching functions from the multi-lobe piecewise
Gaussian fit of Wyman, Sloan & Shirley (2013), "Simple analytic approximations to the CIE XYZ
color matching functions", JCGT 2(2), eq. 3 (so no CMF table ships; the fit's error is below
the variability between observers). XYZ -> linear sRGB with the IEC 61966-2-1 matrix (D65
white). Normalisation: the chosen illuminant is rendered as white, i.e. a constant
reflectance spectrum 1 maps to RGB exactly (1, 1, 1); this is a per-channel (von Kries)
scaling in linear sRGB after the matrix, which for D65 corrects only the small mismatch
between the tabulated D65 and sRGB's nominal white point. Illuminants: ``"E"`` (equal
energy) or ``"D65"`` (CIE 15:2004 table at 10 nm, 380..780 nm, linearly interpolated).
Results are linear sRGB, not gamma-encoded, and may leave [0, 1] for saturated spectra.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxrefl._errors import JaxreflError

__all__ = [
    "IOR",
    "cie_xyz_cmf",
    "load_ior",
    "spectrum_to_rgb",
]

Illuminant = Literal["E", "D65"]

# Wyman, Sloan & Shirley 2013, eq. 3: (weight, mean nm, 1/sigma below mean, 1/sigma above).
_CMF_LOBES = {
    "x": ((1.056, 599.8, 0.0264, 0.0323), (0.362, 442.0, 0.0624, 0.0374),
          (-0.065, 501.1, 0.0490, 0.0382)),
    "y": ((0.821, 568.8, 0.0213, 0.0247), (0.286, 530.9, 0.0613, 0.0322)),
    "z": ((1.217, 437.0, 0.0845, 0.0278), (0.681, 459.0, 0.0385, 0.0725)),
}  # fmt: skip

# XYZ -> linear sRGB (IEC 61966-2-1:1999, D65 white).
_XYZ_TO_SRGB = np.array(
    [
        [3.2406, -1.5372, -0.4986],
        [-0.9689, 1.8758, 0.0415],
        [0.0557, -0.2040, 1.0570],
    ]
)

# CIE standard illuminant D65, relative spectral power, 380..780 nm every 10 nm
# (CIE 15:2004, Table T.1; public).
_D65_NM = np.arange(380.0, 781.0, 10.0)
_D65 = np.array([
    49.9755, 54.6482, 82.7549, 91.4860, 93.4318, 86.6823, 104.865, 117.008, 117.812, 114.861,
    115.923, 108.811, 109.354, 107.802, 104.790, 107.689, 104.405, 104.046, 100.000, 96.3342,
    95.7880, 88.6856, 90.0062, 89.5991, 87.6987, 83.2886, 83.6992, 80.0268, 80.2146, 82.2778,
    78.2842, 69.7213, 71.6091, 74.3490, 61.6040, 69.8856, 75.0870, 63.5927, 46.4182, 66.8054,
    63.3828,
])  # fmt: skip

# CIE 1931 RGB primaries (nm), used by ``IOR.to_rgb(method="primaries")``.
_CIE_RGB_PRIMARIES_NM = (700.0, 546.1, 435.8)


def cie_xyz_cmf(wavelengths: Float[ArrayLike, " L"]) -> Float[np.ndarray, "L 3"]:
    """CIE 1931 2-degree colour-matching functions (x-bar, y-bar, z-bar) at ``wavelengths``
    in nm, from the analytic fit of Wyman, Sloan & Shirley 2013 (peak y-bar ~ 1 at 555 nm)."""
    lam = np.asarray(wavelengths, dtype=np.float64)
    out = []
    for key in "xyz":
        acc = np.zeros_like(lam)
        for weight, mean, inv_lo, inv_hi in _CMF_LOBES[key]:
            t = (lam - mean) * np.where(lam < mean, inv_lo, inv_hi)
            acc = acc + weight * np.exp(-0.5 * t * t)
        out.append(acc)
    return np.stack(out, axis=-1)


def _illuminant(name: str, lam: np.ndarray) -> np.ndarray:
    if name == "E":
        return np.ones_like(lam)
    if name == "D65":
        if lam.min() < _D65_NM[0] or lam.max() > _D65_NM[-1]:
            raise JaxreflError(
                f"illuminant D65 is tabulated on 380..780 nm; wavelengths span "
                f"{lam.min():g}..{lam.max():g} nm (use illuminant='E' or crop the spectrum)"
            )
        return np.interp(lam, _D65_NM, _D65)
    raise JaxreflError(f"unknown illuminant {name!r}; choose 'E' or 'D65'")


def _trapezoid_weights(lam: np.ndarray) -> np.ndarray:
    if lam.ndim != 1 or lam.size < 2 or not np.all(np.diff(lam) > 0):
        raise JaxreflError("wavelengths must be a 1-D, strictly increasing array of >= 2 values")
    dl = np.diff(lam)
    w = np.zeros_like(lam)
    w[:-1] += 0.5 * dl
    w[1:] += 0.5 * dl
    return w


def _rgb_weights(lam: np.ndarray, illuminant: str) -> np.ndarray:
    """(L, 3) weights W so that values @ W is white-normalised linear sRGB."""
    lam = np.asarray(lam, dtype=np.float64)
    w = _trapezoid_weights(lam) * _illuminant(illuminant, lam)
    xyz_w = w[:, None] * cie_xyz_cmf(lam)  # (L, 3)
    rgb_w = xyz_w @ _XYZ_TO_SRGB.T  # (L, 3), linear in the spectrum
    white = rgb_w.sum(axis=0)  # RGB of the constant spectrum 1
    if np.any(white <= 0):
        raise JaxreflError(f"wavelengths {lam.min():g}..{lam.max():g} nm miss a colour channel")
    return rgb_w / white


def spectrum_to_rgb(
    wavelengths: Float[ArrayLike, " L"],
    values: Float[ArrayLike, "*b L"],
    illuminant: Illuminant = "D65",
) -> Float[Array, "*b 3"]:
    """Linear sRGB of reflectance spectra ``values`` sampled at ``wavelengths`` (nm).

    RGB = N M int rho(lam) S(lam) cmf(lam) dlam (trapezoid rule over the given samples only),
    with S the illuminant, M the XYZ -> sRGB matrix and N the per-channel normalisation that
    maps rho = 1 to (1, 1, 1). Linear in ``values`` (differentiable, jit-able in ``values``).
    """
    lam = np.asarray(wavelengths, dtype=np.float64)
    W = _rgb_weights(lam, illuminant)
    v = jnp.asarray(values)
    if v.shape[-1:] != lam.shape:
        raise JaxreflError(f"values must end in an axis of {lam.size} bands; got {v.shape}")
    if not jnp.issubdtype(v.dtype, jnp.floating):
        v = v.astype(jnp.float32)
    return jnp.einsum("...l,lc->...c", v, jnp.asarray(W, dtype=v.dtype))


# --------------------------------------------------------------------------- IOR tables
@dataclass(frozen=True, eq=False)  # eq=False: numpy fields have no truth value
class IOR:
    """A measured complex index of refraction eta(lam) + i k(lam).

    ``wavelengths`` in nm (strictly increasing), ``eta`` and ``k`` (dimensionless) on that
    grid, ``name`` (e.g. ``"Au"``) and ``source`` (the files and their header comments).
    """

    name: str
    wavelengths: np.ndarray
    eta: np.ndarray
    k: np.ndarray
    source: str

    def at(
        self, wavelengths: Float[ArrayLike, "*b"], *, clamp: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """(eta, k) at ``wavelengths`` (nm) by linear interpolation.

        Outside the measured range a ValueError is raised, unless ``clamp=True``, which holds
        the end values constant (a crude extrapolation: say so wherever it is used).
        """
        lam = np.asarray(wavelengths, dtype=np.float64)
        lo, hi = self.wavelengths[0], self.wavelengths[-1]
        if not clamp and (np.any(lam < lo) or np.any(lam > hi)):
            raise JaxreflError(
                f"{self.name}: wavelengths {lam.min():g}..{lam.max():g} nm leave the measured "
                f"range {lo:g}..{hi:g} nm; pass clamp=True to hold the end values"
            )
        return np.interp(lam, self.wavelengths, self.eta), np.interp(lam, self.wavelengths, self.k)

    def to_rgb(
        self,
        method: Literal["cie", "primaries"] = "cie",
        illuminant: Illuminant = "D65",
    ) -> tuple[np.ndarray, np.ndarray]:
        """(eta_rgb, k_rgb), each shape (3,), for RGB renderers.

        * ``"cie"`` (default): eta(lam) and k(lam) are each projected like a spectrum,
          eta_c = sum_l eta(lam_l) W_lc with the white-normalised CIE/sRGB weights of
          :func:`spectrum_to_rgb` (pbrt-v3's conversion of measured metal spectra), over
          the measured range intersected with 380..780 nm at 1 nm. A constant spectrum
          keeps its value. This is an approximation: F(eta_rgb, k_rgb) differs from the RGB
          of the spectral reflectance by a few percent (tests/test_spectral.py).
        * ``"primaries"``: eta and k sampled at the CIE 1931 RGB primaries 700.0, 546.1 and
          435.8 nm (``illuminant`` is ignored).
        """
        if method == "primaries":
            eta, k = self.at(np.asarray(_CIE_RGB_PRIMARIES_NM))
            return eta, k
        if method != "cie":
            raise JaxreflError(f"unknown method {method!r}; choose 'cie' or 'primaries'")
        lo = max(380.0, float(self.wavelengths[0]))
        hi = min(780.0, float(self.wavelengths[-1]))
        lam = np.arange(np.ceil(lo), np.floor(hi) + 0.5, 1.0)
        W = _rgb_weights(lam, illuminant)
        eta, k = self.at(lam)
        return eta @ W, k @ W


_ROW = re.compile(r"[\s,;]+")


def _read_spd(path: Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Parse one two-column spectrum file; errors name the file and line."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise JaxreflError(f"{path}: not a text spectrum file ({err})") from None
    header: list[str] = []
    rows: list[tuple[float, float]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            header.append(line.lstrip("#; ").strip())
            continue
        fields = [f for f in _ROW.split(line) if f]
        try:
            w_nm, v = (float(f) for f in fields)  # unpacking refuses a count other than two
        except ValueError:
            raise JaxreflError(
                f"{path}:{lineno}: expected two numbers 'wavelength value', got {raw!r} "
                f"(corrupt or truncated file?)"
            ) from None
        if not (np.isfinite(w_nm) and np.isfinite(v)):
            raise JaxreflError(f"{path}:{lineno}: non-finite number in {raw!r}")
        rows.append((w_nm, v))
    if len(rows) < 2:
        raise JaxreflError(f"{path}: needs at least two data rows, found {len(rows)}")
    data = np.asarray(rows, dtype=np.float64)
    lam, val = data[:, 0], data[:, 1]
    bad = np.nonzero(np.diff(lam) <= 0)[0]
    if bad.size:
        raise JaxreflError(
            f"{path}: wavelengths must increase strictly; {lam[bad[0]]:g} is followed by "
            f"{lam[bad[0] + 1]:g} (data row {bad[0] + 2})"
        )
    if np.any(val < 0):
        raise JaxreflError(f"{path}: optical constants must be >= 0; found {val.min():g}")
    # Units: luxpop headers say "Lambda (A)" but the numbers are nm (298..886); convert only
    # when an Angstrom header comes with numbers that cannot be nm for optical data.
    says_angstrom = any(re.search(r"\(A\)|angstrom", h, re.IGNORECASE) for h in header)
    if says_angstrom and lam[0] >= 1000.0:
        lam = lam / 10.0
    if lam[0] < 100.0 or lam[-1] > 100_000.0:
        raise JaxreflError(f"{path}: wavelengths {lam[0]:g}..{lam[-1]:g} do not look like nm")
    return lam, val, header


def _ior_dir(data_dir: str | os.PathLike | None) -> Path:
    if data_dir is not None:
        return Path(data_dir)
    if os.environ.get("JAXREFL_IOR_DIR"):
        return Path(os.environ["JAXREFL_IOR_DIR"])
    if os.environ.get("JAXREFL_SHARED_DATA"):
        return Path(os.environ["JAXREFL_SHARED_DATA"]) / "ior"
    raise FileNotFoundError(
        "no IOR folder: pass data_dir=..., or set JAXREFL_IOR_DIR (or JAXREFL_SHARED_DATA, "
        "whose ior/ subfolder is used)"
    )


def load_ior(name_or_path: str | os.PathLike, data_dir: str | os.PathLike | None = None) -> IOR:
    """Load a measured complex IOR from ``NAME.eta.spd`` and ``NAME.k.spd``.

    ``name_or_path`` is a bare name (``"Au"``, looked up in ``data_dir``, else
    ``$JAXREFL_IOR_DIR``, else ``$JAXREFL_SHARED_DATA/ior``), a path prefix
    (``".../ior/Au"``) or the path of either file (anything with a ``/`` is a path, and
    ``data_dir`` is then not used). Wavelengths are in nm. Raises
    FileNotFoundError for a missing file and ValueError, naming the file, for a corrupt or
    truncated one, non-increasing wavelengths, or eta and k on different grids.
    """
    s = os.fspath(name_or_path)
    for suffix in (".eta.spd", ".k.spd"):
        if s.endswith(suffix):
            s = s[: -len(suffix)]
    is_path = "/" in s or os.sep in s
    prefix = Path(s) if is_path else _ior_dir(data_dir) / s
    name = prefix.name
    files = [prefix.parent / f"{name}.eta.spd", prefix.parent / f"{name}.k.spd"]
    for f in files:
        if not f.is_file():
            have = sorted(p.name[: -len(".eta.spd")] for p in prefix.parent.glob("*.eta.spd"))
            raise FileNotFoundError(f"{f} not found; IOR tables in {prefix.parent}: {have}")
    lam_e, eta, head = _read_spd(files[0])
    lam_k, k, _ = _read_spd(files[1])
    if lam_e.shape != lam_k.shape or not np.allclose(lam_e, lam_k, rtol=1e-9, atol=0.0):
        raise JaxreflError(
            f"{files[0]} and {files[1]} use different wavelength grids "
            f"({lam_e.size} vs {lam_k.size} rows); resample one onto the other"
        )
    # Keep header lines with words (not rulers like "-----" or the column caption).
    notes = "; ".join(
        h for h in head if re.search(r"[A-Za-z]", h) and not h.lower().startswith("lambda")
    )
    source = f"{files[0]}, {files[1]}" + (f" ({notes})" if notes else "")
    return IOR(name=name, wavelengths=lam_e, eta=eta, k=k, source=source)

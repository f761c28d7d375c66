"""Reader for Cornell gonioreflectometer BRDFs in the ASTM E1392 text format.

Layout (Cornell Program of Computer Graphics reflectance data)::

    KEY VALUE                 header lines (LAB_NAME, SAMPLE_NAME, MEAS_NAME, ...)
    NUM_POINTS 1439           number of data rows
    VARS theta_i,phi_i,theta_s,phi_s,400nm,...,700nm
                              (blank line)
    0.872665,0.000000,0.573513,0.000000,0.014369,...   NUM_POINTS comma-separated rows

Angles are in radians: θ from the normal, φ the azimuth; the remaining columns are f_r in
1/sr, one per band named in ``VARS`` (31 bands 400..700 nm in the files we ship tests for).

Direction convention (checked on the data, not assumed): both files have φi = 0 on every
row, and for each of the eight incidence angles 10°..80° the largest band-mean value lies
at φs = π, at the measured direction closest to the mirror of wi (0.2°-3.7° away on the
sampling grid; e.g. θi = 80°: peak f_r ≈ 25 /sr for the acrylic and ≈ 49 /sr for the paint
at θs = 79°, φs = π, against medians of 0.0007 and 0.011 /sr). The specular peak therefore
sits at the mirror direction of the standard convention, (θ, φ) -> (θ, φ + π), with both
(θi, φi) and (θs, φs) describing directions *away* from the surface. The angles are used
as they are: wi = (sin θi cos φi, sin θi sin φi, cos θi), wo likewise from (θs, φs). No π
shift is applied.

Errors are :class:`~jaxrefl.io._measured.MeasuredDataError` (a ``ValueError``) naming the
file, the line and the problem.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ._measured import MeasuredBRDF, MeasuredDataError, directions_from_angles

__all__ = ["read_cornell"]

_ANGLES = ("theta_i", "phi_i", "theta_s", "phi_s")
_WAVELENGTH = re.compile(r"^\s*([0-9]+(?:\.[0-9]*)?)\s*nm\s*$", re.IGNORECASE)
# Angles a little outside [0, π/2] are round-off in the file; beyond this they are errors.
_ANGLE_TOL = 1e-6


def _is_data_line(line: str) -> bool:
    head = line.lstrip()[:1]
    return head.isdigit() or head in "+-."


def read_cornell(path: str | Path) -> MeasuredBRDF:
    """Read one ASTM E1392 file into a :class:`MeasuredBRDF` (f_r in 1/sr, no cosine).

    ``channels`` are the band names from ``VARS`` after the four angles; ``wavelengths_nm``
    is filled when every band name reads ``<number>nm``. ``meta`` holds the header
    (``meta["header"]``), the raw angles (``meta["angles"]``, (N, 4) radians) and the count
    of negative values (``meta["n_negative"]``).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError as e:
        raise MeasuredDataError(path, f"not a text file ({e.reason} at byte {e.start})") from None

    header: dict[str, str] = {}
    rows: list[list[float]] = []
    linenos: list[int] = []
    vars_: list[str] | None = None
    first_data_line: int | None = None
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if first_data_line is None and not _is_data_line(line):
            key, _, value = line.partition(" ")
            header[key.upper()] = value.strip()
            if key.upper() == "VARS":
                vars_ = [v.strip() for v in value.split(",")]
            continue
        if first_data_line is None:
            first_data_line = lineno
            if vars_ is None:
                raise MeasuredDataError(path, "missing VARS line before the data", lineno)
        assert vars_ is not None  # set before the first data line, checked just above
        fields = line.split(",")
        if len(fields) != len(vars_):
            raise MeasuredDataError(
                path,
                f"wrong number of columns: {len(fields)}, expected {len(vars_)} (from VARS)",
                lineno,
            )
        try:
            rows.append([float(f) for f in fields])
            linenos.append(lineno)
        except ValueError:
            col = next(i for i, f in enumerate(fields) if not _parses(f))
            raise MeasuredDataError(
                path, f"non-numeric value {fields[col].strip()!r} in column {vars_[col]!r}", lineno
            ) from None

    if vars_ is None:
        raise MeasuredDataError(path, "missing VARS line (column names)")
    if [v.lower() for v in vars_[:4]] != list(_ANGLES) or len(vars_) < 5:
        raise MeasuredDataError(
            path, f"VARS must start with {','.join(_ANGLES)} and name at least one band: {vars_}"
        )
    if "NUM_POINTS" not in header:
        raise MeasuredDataError(path, "missing NUM_POINTS header line")
    try:
        num_points = int(header["NUM_POINTS"])
    except ValueError:
        raise MeasuredDataError(
            path, f"NUM_POINTS is not an integer: {header['NUM_POINTS']!r}"
        ) from None
    if len(rows) != num_points:
        raise MeasuredDataError(
            path,
            f"row count mismatch: NUM_POINTS says {num_points}, found {len(rows)} data rows"
            + (" (truncated file?)" if len(rows) < num_points else ""),
        )

    data = np.asarray(rows, dtype=np.float64).reshape(num_points, len(vars_))
    angles = data[:, :4]
    # Every angle must be a number: a NaN direction has no safe fallback (values may be NaN:
    # a fit gives such samples weight 0).
    bad = np.argwhere(~np.isfinite(angles))
    if bad.size:
        i, j = (int(x) for x in bad[0])
        raise MeasuredDataError(
            path,
            f"angle {vars_[j]!r} is {angles[i, j]}; angles must be finite numbers (radians)",
            linenos[i],
        )
    theta = angles[:, [0, 2]]
    below = np.flatnonzero(np.any(np.abs(theta) > np.pi / 2 + _ANGLE_TOL, axis=1))
    if below.size:
        raise MeasuredDataError(
            path,
            f"polar angle beyond π/2 (below the surface): {theta[below[0]].tolist()}",
            linenos[int(below[0])],
        )
    bands = tuple(vars_[4:])
    nm = [m.group(1) for b in bands if (m := _WAVELENGTH.match(b)) is not None]
    wavelengths = np.asarray([float(x) for x in nm]) if len(nm) == len(bands) else None
    values = data[:, 4:]
    return MeasuredBRDF(
        wi=directions_from_angles(angles[:, 0], angles[:, 1]),
        wo=directions_from_angles(angles[:, 2], angles[:, 3]),
        values=values,
        channels=bands,
        wavelengths_nm=wavelengths,
        name=header.get("SAMPLE_NAME", path.stem),
        source=str(path),
        meta={
            "format": "ASTM E1392 (Cornell PCG)",
            "header": header,
            "angles": angles,
            "n_negative": int(np.sum(values < 0)),
        },
    )


def _parses(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True

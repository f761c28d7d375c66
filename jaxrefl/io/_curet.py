"""Reader for the CURET BRDF database (Columbia-Utrecht Reflectance and Texture).

Dana, van Ginneken, Nayar, Koenderink, "Reflectance and Texture of Real-World Surfaces",
ACM TOG 18(1), 1999. 61 material samples, each imaged under the same 205 combinations of
illumination and viewing direction.

Files
-----
``table.txt``: 205 rows ``index theta_v phi_v theta_i phi_i`` (radians; v = camera,
i = lamp), index 1..205 in order.

``abrdf.dat``: 61 rows ``sample meas_1 ... meas_205`` (sample 1..61). The CURET web page
("BRDF Measurement Database") says each value is the sample's BRDF for one geometry,
averaged over red, green and blue; ``rbrdf.dat``, ``gbrdf.dat``, ``bbrdf.dat`` hold the
three channels in the same layout. So a row of 1 + 205 numbers is one channel; several
such files can be read together as channels (``read_curet([r, g, b], table)``).

Units and conventions, with the evidence
----------------------------------------
* Values are read as f_r in 1/sr. The CURET calibration notes say the pixel values were
  converted to radiance and divided by the lamp's irradiance, estimated from a Kodak 18%
  grey card, to give BRDF. The numbers agree with 1/sr and not with a radiance factor
  (π f_r): the brightest diffuse samples have medians 0.18-0.26 (a Lambertian surface
  gives at most 1/π ≈ 0.318 /sr; as radiance factors these would be albedos of only
  0.18-0.26 for the brightest of 61 everyday materials, white ones among them), the
  darkest 0.006 (sample 61), and the 565 of 61 x 205 values above 1/π (up to 2.6) are
  directional peaks: 90% of them under grazing light (θi >= 56°), towards the mirror
  direction or back towards the lamp. The values are camera-based (RGB video
  camera, per-sample calibration), not a spectral measurement.
* 29 of the 61 x 205 values are slightly negative (down to -0.016, dark samples:
  calibration offset plus noise); they are kept and counted in ``meta["n_negative"]``.
* Directions: wi = (θi, φi), wo = (θv, φv), both away from the surface, azimuth from +x.
  Checked on the table: with that convention the angle between lamp and camera is one of
  22.5°, 45°, ..., 157.5° for every geometry (the CURET camera positions are multiples of
  22.5° from the lamp), and 7 geometries put wo exactly at the mirror of wi, which is
  where shiny samples peak: the three largest values of sample 15 are at geometries 202,
  203, 196, which lie 0°, 4.5° and 0° from the mirror direction. No π shift is applied.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import overload

import numpy as np

from jaxrefl._errors import JaxreflError

from ._measured import MeasuredBRDF, MeasuredDataError, directions_from_angles

__all__ = ["read_curet", "read_curet_geometry"]

N_SAMPLES = 61
N_GEOMETRIES = 205
_CHANNEL_NAMES = {"abrdf": "mean_rgb", "rbrdf": "R", "gbrdf": "G", "bbrdf": "B"}


def _read_rows(path: Path) -> list[tuple[int, list[str]]]:
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError as e:
        raise MeasuredDataError(path, f"not a text file ({e.reason} at byte {e.start})") from None
    return [(n, line.split()) for n, line in enumerate(text.splitlines(), 1) if line.strip()]


def _floats(path: Path, lineno: int, fields: list[str]) -> list[float]:
    out = []
    for j, f in enumerate(fields):
        try:
            out.append(float(f))
        except ValueError:
            raise MeasuredDataError(
                path, f"non-numeric value {f!r} in column {j + 1}", lineno
            ) from None
    return out


def _index(path: Path, lineno: int, value: float, expected: int | None, what: str) -> int:
    k = int(value) if np.isfinite(value) else None
    if k != value or (expected is not None and k != expected):
        want = "an integer" if expected is None else str(expected)
        raise MeasuredDataError(path, f"{what} index {value:g}, expected {want}", lineno)
    return k


def read_curet_geometry(table_path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The geometry table: (wi, wo, angles), wi/wo (M, 3) unit vectors and angles (M, 4)
    = (θv, φv, θi, φi) radians, rows in index order 1..M."""
    path = Path(table_path)
    rows = _read_rows(path)
    angles = []
    for k, (lineno, fields) in enumerate(rows, start=1):
        if len(fields) != 5:
            raise MeasuredDataError(
                path,
                f"wrong number of columns: {len(fields)}, expected 5 "
                "(index theta_v phi_v theta_i phi_i)",
                lineno,
            )
        vals = _floats(path, lineno, fields)
        _index(path, lineno, vals[0], k, "geometry")
        bad = [j for j, v in enumerate(vals[1:]) if not np.isfinite(v)]
        if bad:
            name = ("theta_v", "phi_v", "theta_i", "phi_i")[bad[0]]
            raise MeasuredDataError(
                path, f"angle {name} is {vals[1 + bad[0]]}; angles must be finite numbers", lineno
            )
        if abs(vals[1]) > np.pi / 2 or abs(vals[3]) > np.pi / 2:
            raise MeasuredDataError(path, f"polar angle beyond π/2: {vals[1:]}", lineno)
        angles.append(vals[1:])
    if not angles:
        raise MeasuredDataError(path, "no geometry rows")
    a = np.asarray(angles, dtype=np.float64)
    return directions_from_angles(a[:, 2], a[:, 3]), directions_from_angles(a[:, 0], a[:, 1]), a


def _read_table(path: Path, n_geometries: int) -> dict[int, np.ndarray]:
    out: dict[int, np.ndarray] = {}
    for lineno, fields in _read_rows(path):
        if len(fields) != 1 + n_geometries:
            raise MeasuredDataError(
                path,
                f"wrong number of columns: {len(fields)}, expected {1 + n_geometries} "
                f"(sample index + one value per geometry of the table)",
                lineno,
            )
        vals = _floats(path, lineno, fields)
        k = _index(path, lineno, vals[0], None, "sample")
        if k in out:
            raise MeasuredDataError(path, f"sample {k} appears twice", lineno)
        out[k] = np.asarray(vals[1:], dtype=np.float64)
    if not out:
        raise MeasuredDataError(path, "no sample rows")
    return out


@overload
def read_curet(
    abrdf_path: str | Path | Sequence[str | Path],
    table_path: str | Path,
    sample: int,
    *,
    channels: Sequence[str] | None = None,
    expected_samples: int | None = N_SAMPLES,
) -> MeasuredBRDF: ...
@overload
def read_curet(
    abrdf_path: str | Path | Sequence[str | Path],
    table_path: str | Path,
    sample: None = None,
    *,
    channels: Sequence[str] | None = None,
    expected_samples: int | None = N_SAMPLES,
) -> list[MeasuredBRDF]: ...
def read_curet(
    abrdf_path: str | Path | Sequence[str | Path],
    table_path: str | Path,
    sample: int | None = None,
    *,
    channels: Sequence[str] | None = None,
    expected_samples: int | None = N_SAMPLES,
) -> MeasuredBRDF | list[MeasuredBRDF]:
    """Read CURET BRDF values (f_r, 1/sr) and their geometry table.

    ``abrdf_path`` is one file (one channel) or several with identical sample rows (one
    channel each, e.g. ``[rbrdf, gbrdf, bbrdf]``). ``sample`` (1-based, as in the file)
    returns that sample; ``None`` returns the list of all samples in file order.
    ``expected_samples`` (61 for CURET; None to skip) guards against truncated files.
    Channel names default to ``mean_rgb`` for ``abrdf``, ``R``/``G``/``B`` for
    ``rbrdf``/``gbrdf``/``bbrdf``, else the file stem.
    """
    paths = (
        [Path(abrdf_path)] if isinstance(abrdf_path, (str, Path)) else [Path(p) for p in abrdf_path]
    )
    if not paths:
        raise JaxreflError("read_curet needs at least one value file")
    wi, wo, angles = read_curet_geometry(table_path)
    n_geom = wi.shape[0]
    if n_geom != N_GEOMETRIES:
        raise MeasuredDataError(
            table_path, f"{n_geom} geometry rows; the CURET table has {N_GEOMETRIES}"
        )
    tables = [_read_table(p, n_geom) for p in paths]
    for p, t in zip(paths, tables, strict=True):
        if expected_samples is not None and len(t) != expected_samples:
            raise MeasuredDataError(
                p, f"{len(t)} sample rows, expected {expected_samples} (truncated file?)"
            )
        if sorted(t) != sorted(tables[0]):
            raise MeasuredDataError(p, f"sample numbers differ from those in {paths[0]}")
    names = (
        tuple(channels)
        if channels is not None
        else tuple(_CHANNEL_NAMES.get(p.stem.lower(), p.stem) for p in paths)
    )
    if len(names) != len(paths):
        raise JaxreflError(f"{len(paths)} value files but {len(names)} channel names")

    def build(k: int) -> MeasuredBRDF:
        values = np.stack([t[k] for t in tables], axis=-1)
        return MeasuredBRDF(
            wi=wi,
            wo=wo,
            values=values,
            channels=names,
            wavelengths_nm=None,
            name=f"curet_{k:02d}",
            source=", ".join(str(p) for p in paths),
            meta={
                "format": "CURET BRDF database",
                "sample": k,
                "table": str(table_path),
                "angles": angles,  # (θv, φv, θi, φi) per geometry
                "n_negative": int(np.sum(values < 0)),
            },
        )

    if sample is None:
        return [build(k) for k in tables[0]]
    if sample not in tables[0]:
        raise KeyError(
            f"sample {sample} not in {paths[0]}; it has {min(tables[0])}..{max(tables[0])}"
        )
    return build(sample)

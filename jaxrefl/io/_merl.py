"""MERL BRDF binary files (Matusik et al. 2003), read and written as MERL's ``BRDFRead.cpp``.

File layout (little-endian)::

    int32 dims[3]                    = 90, 90, 180  (θh, θd, φd cells)
    float64 raw[3][90][90][180]      channel-major: all red, then green, then blue

f_r (1/sr) = raw * scale with scale = 1/1500, 1.15/1500, 1.66/1500 for R, G, B
(``RED_SCALE``... in BRDFRead.cpp). Negative raw values mark missing cells and stay
negative after scaling (see :class:`jaxrefl.brdf.MERL`). A file is
12 + 8 * 3 * 90 * 90 * 180 = 34,992,012 bytes.
"""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from jaxrefl._errors import JaxreflError

from ..brdf import MERL, MERL_SCALE, MERL_SHAPE
from ._measured import MeasuredBRDF, MeasuredDataError

__all__ = ["merl_to_measured", "read_merl", "write_merl"]

_DIMS = MERL_SHAPE[1:]
_N = int(np.prod(_DIMS))
_HEADER_BYTES = 3 * 4
_FILE_BYTES = _HEADER_BYTES + 8 * 3 * _N
_SCALE = np.asarray(MERL_SCALE, dtype=np.float64)[:, None, None, None]


def read_merl_table(path: str | Path) -> np.ndarray:
    """The scaled table (3, 90, 90, 180) float64, f_r in 1/sr (negative = missing)."""
    path = Path(path)
    size = path.stat().st_size
    if size < _HEADER_BYTES:
        raise MeasuredDataError(
            path, f"too short for a MERL header: {size} bytes (expected {_FILE_BYTES})"
        )
    with path.open("rb") as f:
        dims = tuple(int(d) for d in np.frombuffer(f.read(_HEADER_BYTES), dtype="<i4"))
        if dims != _DIMS:
            raise MeasuredDataError(
                path, f"wrong dimensions {dims} in the header, expected {_DIMS} (θh, θd, φd)"
            )
        if size != _FILE_BYTES:
            raise MeasuredDataError(
                path,
                f"file size mismatch: expected {_FILE_BYTES} bytes "
                f"(12-byte header + 3 x {_N} float64), got {size}"
                + (" (truncated file?)" if size < _FILE_BYTES else ""),
            )
        raw = np.frombuffer(f.read(), dtype="<f8").reshape(MERL_SHAPE)
    return raw.astype(np.float64) * _SCALE


def read_merl(path: str | Path, interpolation: str = "nearest") -> MERL:
    """Read a MERL ``.binary`` file into a :class:`~jaxrefl.brdf._merl.MERL` model.

    The table is stored in JAX's default float dtype (float32 unless x64 is enabled).
    """
    return MERL(jnp.asarray(read_merl_table(path)), interpolation=interpolation)


def write_merl(path: str | Path, table: MERL | Float[ArrayLike, "3 90 90 180"]) -> None:
    """Write a scaled table (f_r in 1/sr, or a :class:`MERL`) in the MERL binary format.

    Values are divided by the MERL scale factors; ``read_merl`` multiplies them back, so a
    round trip reproduces a float64 table to within 1 ulp.
    """
    t = np.asarray(table.table if isinstance(table, MERL) else table, dtype=np.float64)
    if t.shape != MERL_SHAPE:
        raise JaxreflError(f"MERL table must have shape {MERL_SHAPE}, got {t.shape}")
    raw = t / _SCALE
    with Path(path).open("wb") as f:
        f.write(np.asarray(_DIMS, dtype="<i4").tobytes())
        f.write(np.ascontiguousarray(raw, dtype="<f8").tobytes())


def merl_to_measured(
    merl: MERL,
    n: int | None = None,
    *,
    seed: int = 0,
    name: str = "merl",
    source: str | None = None,
) -> MeasuredBRDF:
    """Samples of a MERL table for fitting: the centre directions of the valid cells.

    Every cell with no negative channel and both centre directions strictly above the
    horizon gives one sample (wi, wo at φh = 0; the table is isotropic), valued exactly as
    stored. ``n`` picks that many cells at random without replacement (``seed``); None
    keeps all (about 1.1 million for a full table). ``meta["cell"]`` holds the (i, j, k)
    index of each sample, ``meta["n_missing_cells"]`` how many cells were skipped.
    Directions are computed in JAX's default dtype, then stored as float64.
    """
    if n is not None and (isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1):
        raise JaxreflError(f"n (merl_samples) must be a whole number >= 1 or None (all), got {n!r}")
    table = np.asarray(merl.table, dtype=np.float64)
    wi_cells, wo_cells = MERL.cell_directions()
    wi = np.asarray(wi_cells, dtype=np.float64)
    wo = np.asarray(wo_cells, dtype=np.float64)
    ok = np.all(table >= 0, axis=0) & (wi[..., 2] > 0) & (wo[..., 2] > 0)
    cells = np.argwhere(ok)
    if n is not None:
        if n > len(cells):
            raise JaxreflError(f"asked for {n} samples but the table has {len(cells)} valid cells")
        pick = np.random.default_rng(seed).choice(len(cells), size=n, replace=False)
        cells = cells[np.sort(pick)]
    i, j, k = cells.T
    return MeasuredBRDF(
        wi=wi[i, j, k],
        wo=wo[i, j, k],
        values=table[:, i, j, k].T,
        channels=("R", "G", "B"),
        wavelengths_nm=None,
        name=name,
        source=source,
        meta={
            "format": "MERL binary",
            "cell": cells,
            "n_missing_cells": int(ok.size - ok.sum()),
        },
    )

"""MATLAB MAT files of numeric arrays, read and written with :mod:`scipy.io`.

DiLiGenT ships its ground-truth normals as ``Normal_gt.mat`` (a variable ``Normal_gt``,
H x W x 3 double). :func:`read_mat` gives every real numeric variable of a level-5 file
(MATLAB's default up to v7, compressed or not) as float64; v7.3 files are HDF5 and are
refused with a message saying how to re-save them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._capture import PSInputError

__all__ = ["read_mat", "write_mat"]

_HDF5 = b"\x89HDF\r\n\x1a\n"


def read_mat(path: str | Path) -> dict[str, np.ndarray]:
    """name -> float64 array for every numeric variable of a level-5 MAT file."""
    import scipy.io

    path = Path(path)
    with path.open("rb") as f:
        head = f.read(520)
    if head[:8] == _HDF5 or head[512:520] == _HDF5:
        raise PSInputError(path, "MAT v7.3 (HDF5) is not supported; save with -v7 or as PNG")
    if len(head) < 128 or head[126:128] not in (b"IM", b"MI"):
        raise PSInputError(path, "not a level-5 MAT file")
    try:
        raw = scipy.io.loadmat(path, squeeze_me=False, mat_dtype=True)
    except (ValueError, TypeError, NotImplementedError) as e:
        raise PSInputError(path, f"unreadable MAT file ({e})") from None
    out = {}
    for name, value in raw.items():
        if name.startswith("__") or not isinstance(value, np.ndarray):
            continue
        if not np.issubdtype(value.dtype, np.number):
            continue  # cells, structs, strings
        if np.iscomplexobj(value):
            raise PSInputError(path, "complex MAT arrays are not supported")
        out[name] = value.astype(np.float64)
    return out


def write_mat(path: str | Path, arrays: dict[str, np.ndarray], compress: bool = True) -> None:
    """Write float64 arrays as a level-5 MAT file (compressed like MATLAB by default)."""
    import scipy.io

    data = {name: np.asarray(a, np.float64) for name, a in arrays.items()}
    scipy.io.savemat(Path(path), data, do_compression=compress, format="5")

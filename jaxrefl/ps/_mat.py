"""A minimal reader and writer of MATLAB level-5 MAT files holding numeric arrays.

DiLiGenT ships its ground-truth normals as ``Normal_gt.mat`` (a variable ``Normal_gt``,
H x W x 3 double). The library may not depend on SciPy, so this module reads the level-5
format directly (MathWorks, "MAT-File Format", level 5): a 128-byte header (text, then
version 0x0100 and the endian indicator ``IM``/``MI``), then data elements, each an 8-byte
tag (type, byte count) or a 4-byte "small element" tag, padded to 8 bytes. A variable is
a ``miMATRIX`` element (array flags, dimensions, name, real part), possibly inside a
zlib-compressed ``miCOMPRESSED`` element (MATLAB's default since v7). Arrays are stored
column-major. Only real numeric (non-sparse) arrays are read; v7.3 files (HDF5) are not.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from ._capture import PSInputError

__all__ = ["read_mat", "write_mat"]

_NUMERIC = {
    1: np.int8,
    2: np.uint8,
    3: np.int16,
    4: np.uint16,
    5: np.int32,
    6: np.uint32,
    7: np.float32,
    9: np.float64,
    12: np.int64,
    13: np.uint64,
}
_MATRIX, _COMPRESSED = 14, 15


def _elements(buf: bytes, endian: str, path):
    pos = 0
    while pos + 8 <= len(buf):
        (first,) = struct.unpack(endian + "I", buf[pos : pos + 4])
        if first >> 16:  # small data element: 2-byte count, 2-byte type, 4 bytes of data
            kind, n = first & 0xFFFF, first >> 16
            yield kind, buf[pos + 4 : pos + 4 + n]
            pos += 8
            continue
        kind, n = struct.unpack(endian + "II", buf[pos : pos + 8])
        body = buf[pos + 8 : pos + 8 + n]
        if len(body) != n:
            raise PSInputError(path, "truncated MAT file")
        yield kind, body
        pos += 8 + n + ((-n) % 8 if kind != _COMPRESSED else 0)


def _matrix(body: bytes, endian: str, path) -> tuple[str, np.ndarray]:
    parts = list(_elements(body, endian, path))
    if len(parts) < 4:
        raise PSInputError(path, "MAT variable without data")
    flags = struct.unpack(endian + "I", parts[0][1][:4])[0]
    if flags & 0x0800:
        raise PSInputError(path, "complex MAT arrays are not supported")
    dims = np.frombuffer(parts[1][1], dtype=np.dtype(endian + "i4"))
    name = parts[2][1].decode("ascii", "replace")
    kind, data = parts[3]
    if kind not in _NUMERIC:
        raise PSInputError(path, f"MAT variable {name!r} is not a numeric array (type {kind})")
    arr = np.frombuffer(data, dtype=np.dtype(endian + np.dtype(_NUMERIC[kind]).str[1:]))
    if arr.size != int(np.prod(dims)):
        raise PSInputError(path, f"MAT variable {name!r}: {arr.size} values for dims {dims}")
    return name, arr.reshape(tuple(int(d) for d in dims), order="F").astype(np.float64)


def read_mat(path: str | Path) -> dict[str, np.ndarray]:
    """name -> float64 array for every numeric variable of a level-5 MAT file."""
    path = Path(path)
    raw = path.read_bytes()
    if raw[:8] == b"\x89HDF\r\n\x1a\n" or raw[512:520] == b"\x89HDF\r\n\x1a\n":
        raise PSInputError(path, "MAT v7.3 (HDF5) is not supported; save with -v7 or as PNG")
    if len(raw) < 128 or raw[126:128] not in (b"IM", b"MI"):
        raise PSInputError(path, "not a level-5 MAT file")
    endian = "<" if raw[126:128] == b"IM" else ">"
    out = {}
    for kind, body in _elements(raw[128:], endian, path):
        if kind == _COMPRESSED:
            try:
                inner = zlib.decompress(body)
            except zlib.error as e:
                raise PSInputError(path, f"corrupt compressed MAT element ({e})") from None
            for k2, b2 in _elements(inner, endian, path):
                if k2 == _MATRIX:
                    name, arr = _matrix(b2, endian, path)
                    out[name] = arr
        elif kind == _MATRIX:
            name, arr = _matrix(body, endian, path)
            out[name] = arr
    return out


def _tag(kind: int, payload: bytes) -> bytes:
    return struct.pack("<II", kind, len(payload)) + payload + b"\0" * ((-len(payload)) % 8)


def write_mat(path: str | Path, arrays: dict[str, np.ndarray], compress: bool = True) -> None:
    """Write float64 arrays as a level-5 MAT file (little-endian; compressed like MATLAB)."""
    header = b"MATLAB 5.0 MAT-file, written by jaxrefl".ljust(116, b" ")
    out = bytearray(header + b"\0" * 8 + struct.pack("<H", 0x0100) + b"IM")
    for name, a in arrays.items():
        a = np.asarray(a, np.float64)
        body = (
            _tag(6, struct.pack("<II", 6, 0))  # array flags: class 6 = double
            + _tag(5, np.asarray(a.shape, "<i4").tobytes())
            + _tag(1, name.encode("ascii"))
            + _tag(9, a.astype("<f8").tobytes(order="F"))
        )
        element = _tag(_MATRIX, body)
        if compress:
            z = zlib.compress(element)
            out += struct.pack("<II", _COMPRESSED, len(z)) + z
        else:
            out += element
    Path(path).write_bytes(bytes(out))

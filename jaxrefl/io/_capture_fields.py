"""The fields of a capture's description files (``capture.json``, ``parameters.json``,
MaterialGAN's text files), read and checked one by one: every error is a
:class:`~jaxrefl.io.CaptureError` naming the file and the field (or line) at fault.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from ._capture import CaptureError

__all__: list[str] = []


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CaptureError(path, "file not found") from None
    except json.JSONDecodeError as e:
        raise CaptureError(
            path, f"invalid JSON: {e.msg} (line {e.lineno}, column {e.colno})"
        ) from None
    except (OSError, UnicodeDecodeError) as e:
        raise CaptureError(path, f"cannot read: {e}") from None
    if not isinstance(data, dict):
        raise CaptureError(path, f"expected a JSON object at the top, got {type(data).__name__}")
    return data


def _get(data: dict, key: str, path: Path):
    if key not in data:
        raise CaptureError(path, f"missing key {key!r}", key)
    return data[key]


def _has_bool(value) -> bool:
    """Whether a JSON value holds a boolean anywhere (``true`` is not the number 1)."""
    if isinstance(value, (bool, np.bool_)):
        return True
    if isinstance(value, (list, tuple)):
        return any(_has_bool(v) for v in value)
    return False


def _array(value, path: Path, field: str, shape_doc: str) -> np.ndarray:
    if _has_bool(value):
        raise CaptureError(path, f"expected {shape_doc} of numbers, got a boolean", field)
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CaptureError(path, f"expected {shape_doc} of numbers", field) from None
    if not np.all(np.isfinite(a)):
        raise CaptureError(path, "holds a non-finite number", field)
    return a


def _vectors(value, path: Path, field: str) -> np.ndarray:
    a = _array(value, path, field, "a list of [x, y, z]")
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
        raise CaptureError(path, f"expected a list of [x, y, z], got shape {a.shape}", field)
    return a


def _positive(value, path: Path, field: str) -> float:
    a = _array(value, path, field, "a number")
    if a.size < 1 or not np.all(a.ravel() == a.ravel()[0]) or a.ravel()[0] <= 0:
        raise CaptureError(path, f"expected one positive number, got {value!r}", field)
    return float(a.ravel()[0])


def _light_power(value, n: int, rows: np.ndarray, c: int, path: Path, field: str) -> np.ndarray:
    """(K, C) powers of the photos ``rows`` from a scalar, per-channel, per-photo or (n, C) spec."""
    a = _array(value, path, field, "a number or a list")
    k = rows.size
    if a.ndim == 0 or a.size == 1:
        out = np.full((k, c), a.ravel()[0])
    elif a.ndim == 1 and a.size == c:  # one value per channel (the public layouts)
        out = np.broadcast_to(a, (k, c))
    elif a.ndim == 1 and a.size == n:  # one value per photo
        out = np.broadcast_to(a[rows, None], (k, c))
    elif a.ndim == 2 and a.shape[0] == n and a.shape[1] in (1, c):
        out = np.broadcast_to(a[rows], (k, c))
    elif a.ndim == 2 and a.shape[0] == 1 and a.shape[1] in (1, c):
        out = np.broadcast_to(a, (k, c))
    else:
        raise CaptureError(
            path,
            f"has shape {a.shape}; expected one number, {c} (one per channel), {n} (one per "
            f"photo) or {n}x{c}",
            field,
        )
    if np.any(out < 0):
        raise CaptureError(path, "light power must be >= 0", field)
    return np.array(out)


def _read_txt(path: Path) -> np.ndarray:
    """The numbers of a MaterialGAN text file, one row per line; all must be finite."""
    if not path.is_file():
        raise CaptureError(path, "file not found (MaterialGAN layout)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # an empty file is reported below
            a = np.loadtxt(path, delimiter=",", ndmin=2, dtype=np.float64, encoding="utf-8")
    except (ValueError, UnicodeDecodeError) as e:
        raise CaptureError(
            path, f"expected comma-separated numbers, one line per photo: {e}"
        ) from None
    bad = ~np.isfinite(a)
    if np.any(bad):
        row, col = np.argwhere(bad)[0]
        raise CaptureError(
            path,
            f"number {col + 1} is {a[row, col]}; every value must be a finite number",
            f"line {row + 1}",
        )
    return a

"""Reports as strict JSON: a non-finite number becomes ``null``, and the report says why.

JSON has no NaN or Infinity (RFC 8259). Python's :mod:`json` writes them as bare ``NaN`` and
``Infinity`` tokens, which strict parsers (JavaScript's ``JSON.parse``, jq, ``serde_json``)
reject, so one undefined metric would make a whole ``report.json`` unreadable there. A
non-finite number in a report is still a fact worth keeping (a relative error of an all-zero
file, a timing that was not measured), so it is written as ``null`` and recorded:

* :func:`jsonable` converts a report to plain JSON values: dicts (keys as strings), lists,
  str, int, float, bool and None. numpy scalars and arrays (and anything with
  ``__array__``) become Python numbers and nested lists, tuples become lists, paths
  strings; NaN, +inf and -inf become ``None``. It returns the converted value and, for every
  ``None`` that was a non-finite number, its place as a JSON Pointer (RFC 6901: ``""`` is
  the whole document, ``"/timings/compile_s"`` a member, ``"/rmse/2"`` a list element; ``~``
  and ``/`` inside a key are written ``~0`` and ``~1``) with the value's name, ``"NaN"``,
  ``"Infinity"`` or ``"-Infinity"``.
* :func:`report_json` gives the text of a report (a mapping): converted, with the record
  as its top-level member ``"nulls"`` (``{"/timings/compile_s": "NaN"}``; absent when every
  number is finite), and serialised with ``allow_nan=False``, so a non-finite number that
  escaped the conversion raises instead of writing invalid JSON.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from os import PathLike
from typing import Any

import numpy as np

from jaxrefl._errors import JaxreflError

__all__ = ["NULLS_KEY", "jsonable", "report_json"]

NULLS_KEY = "nulls"
"""Top-level member of a report that names each non-finite number written as ``null``."""


def _pointer_token(key: str) -> str:
    return key.replace("~", "~0").replace("/", "~1")


def _name(x: float) -> str:
    if math.isnan(x):
        return "NaN"
    return "Infinity" if x > 0 else "-Infinity"


def _key(k: Any, where: str) -> str:
    """A mapping key as JSON writes it (a string), refusing what it cannot name."""
    if isinstance(k, np.generic):
        k = k.item()
    if isinstance(k, str):
        return k
    if isinstance(k, bool) or k is None:
        return "true" if k is True else "false" if k is False else "null"
    if isinstance(k, int):
        return str(k)
    if isinstance(k, float):
        return repr(k) if math.isfinite(k) else _name(k)
    raise TypeError(f"report key {k!r} at {where or '/'} is not a string or a number")


def jsonable(obj: Any, default: Callable[[Any], Any] | None = None) -> tuple[Any, dict[str, str]]:
    """``obj`` as plain JSON values and ``{pointer: "NaN" | "Infinity" | "-Infinity"}`` for
    each non-finite number written as ``None`` (module docstring).

    ``default`` converts an object of any other type (its result is converted in turn);
    without it such an object raises :class:`TypeError` naming its place.
    """
    nulls: dict[str, str] = {}

    def conv(o: Any, where: str) -> Any:
        if isinstance(o, np.generic):
            o = o.item()
        if o is None or isinstance(o, (str, bool, int)):
            return o
        if isinstance(o, float):
            if math.isfinite(o):
                return o
            nulls[where] = _name(o)
            return None
        if isinstance(o, complex):
            raise TypeError(f"complex number {o!r} at {where or '/'} has no JSON form")
        if isinstance(o, Mapping):
            out = {}
            for k, v in o.items():
                name = _key(k, where)
                out[name] = conv(v, f"{where}/{_pointer_token(name)}")
            return out
        if isinstance(o, (list, tuple)):
            return [conv(v, f"{where}/{i}") for i, v in enumerate(o)]
        if isinstance(o, PathLike):
            return str(o)
        if isinstance(o, np.ndarray) or hasattr(o, "__array__"):
            return conv(np.asarray(o).tolist(), where)
        if default is not None:
            return conv(default(o), where)
        raise TypeError(f"{type(o).__name__} at {where or '/'} is not JSON serialisable")

    return conv(obj, ""), nulls


def report_json(
    report: Mapping[str, Any], *, indent: int = 2, default: Callable[[Any], Any] | None = None
) -> str:
    """The strict-JSON text of ``report`` (ending in a newline), with its ``"nulls"`` record.

    Raises :class:`ValueError` if the report already has a ``"nulls"`` member (the record
    would hide it), :class:`TypeError` for a value without a JSON form (see ``default``).
    """
    if NULLS_KEY in report:
        raise JaxreflError(f"a report must not have a {NULLS_KEY!r} member: it records nulls")
    clean, nulls = jsonable(report, default)
    if nulls:
        clean[NULLS_KEY] = nulls
    return json.dumps(clean, indent=indent, allow_nan=False) + "\n"

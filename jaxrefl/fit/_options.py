"""The common base of the fit's option objects: a small immutable object per choice.

Every choice of a fit is an object, never a string switch: the solver
(:class:`~jaxrefl.fit.LMOptions`, :class:`~jaxrefl.fit.OptimistixLM`,
:class:`~jaxrefl.fit.JaxoptLM`), the noise model (:class:`~jaxrefl.fit.GaussianNoise`,
:class:`~jaxrefl.fit.ShotNoise`), the robust loss (:class:`~jaxrefl.fit.L2`,
:class:`~jaxrefl.fit.Huber`, :class:`~jaxrefl.fit.Cauchy`), and their bundle
:class:`~jaxrefl.fit.FitConfig`. Each one names its kind (``kind``, e.g. ``"shot"``) and
writes itself as JSON (:meth:`Option.to_json`: ``{"type": "shot", "read": 0.002, "gain":
0.002}``), so that a report or a resume manifest records exactly what was fitted.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Any, ClassVar

import equinox as eqx
import numpy as np

from jaxrefl._errors import JaxreflError

__all__ = ["Option", "check_number", "option_json"]


def option_json(value: Any) -> Any:
    """``value`` as plain JSON values: an :class:`Option` as its :meth:`~Option.to_json`, a
    dtype as its name (``"float32"``), an array as a (nested) list, a tuple as a list."""
    if isinstance(value, Option):
        return value.to_json()
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, np.dtype) or (isinstance(value, type) and issubclass(value, np.generic)):
        return np.dtype(value).name
    if isinstance(value, (tuple, list)):
        return [option_json(v) for v in value]
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        return float(value)
    return np.asarray(value).tolist()


def check_number(
    owner: str, name: str, value: Any, *, positive: bool = False, why: str = ""
) -> None:
    """Refuse a Python number ``value`` of field ``name`` that is not finite, or not > 0
    (``positive``) / not >= 0 (otherwise); arrays (traced values included) pass unchecked.
    The message names ``owner`` and ``name`` and adds ``why`` (a reason in parentheses)."""
    if not isinstance(value, numbers.Real):
        return
    v = float(value)
    ok = math.isfinite(v) and (v > 0 if positive else v >= 0)
    if not ok:
        rel = "> 0" if positive else ">= 0"
        note = f" ({why})" if why else ""
        raise JaxreflError(f"{owner} needs a finite {name} {rel}{note}, got {value}")


class Option(eqx.Module):
    """An immutable option object: its ``kind`` names it in reports and resume manifests."""

    kind: ClassVar[str] = ""

    def to_json(self) -> dict[str, Any]:
        """``{"type": kind, field: value, ...}`` in plain JSON values (arrays as lists)."""
        out: dict[str, Any] = {"type": self.kind}
        for f in dataclasses.fields(self):
            out[f.name] = option_json(getattr(self, f.name))
        return out

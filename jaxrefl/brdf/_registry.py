"""Look models up by name: ``jaxrefl.brdf.get("cook_torrance", distribution="ggx", ...)``.

Each entry maps a name to the class that builds it; keyword options go to its constructor.
Modules are imported on first use, so a model that is never asked for costs nothing.
"""

from __future__ import annotations

import importlib
from typing import Any

from jaxrefl._errors import JaxreflError

from ._base import BRDF

__all__ = ["available", "get"]

_MODELS: dict[str, tuple[str, str]] = {
    "lambert": ("jaxrefl.brdf._lambert", "Lambert"),
    "oren_nayar": ("jaxrefl.brdf._lambert", "OrenNayar"),
    "phong": ("jaxrefl.brdf._phong", "Phong"),
    "blinn_phong": ("jaxrefl.brdf._phong", "BlinnPhong"),
    "lafortune": ("jaxrefl.brdf._lafortune", "Lafortune"),
    "ward": ("jaxrefl.brdf._ward", "Ward"),
    "cook_torrance": ("jaxrefl.brdf._cook_torrance", "CookTorrance"),
    "dichromatic": ("jaxrefl.brdf._dichromatic", "Dichromatic"),
}


def available() -> tuple[str, ...]:
    """Names accepted by :func:`get`."""
    return tuple(_MODELS)


def get(name: str, **options: Any) -> BRDF:
    """Build the model called ``name`` with the given constructor options."""
    try:
        module, cls = _MODELS[name]
    except KeyError:
        raise JaxreflError(f"unknown BRDF model {name!r}; choose one of {available()}") from None
    return getattr(importlib.import_module(module), cls)(**options)

"""One bound sampler function per posterior and settings.

:func:`jaxrefl.fit.map_sharded` compiles per function object, so a sampler bound afresh for
every chunk of a map would compile again for every chunk. :func:`bind_once` returns the same
``functools.partial`` for equal arguments: pytrees whose leaves are hashable (static
settings, models, priors). Where a leaf is an array there is no key, and the partial is a
new one (its program compiles once per call site, as any fresh function's would).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax

__all__ = ["bind_once"]

_BOUND: dict[Any, functools.partial] = {}


def bind_once(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Callable[..., Any]:
    """``functools.partial(fn, *args, **kwargs)``, the same object for equal arguments."""
    leaves, treedef = jax.tree.flatten((args, kwargs))
    key = (fn, treedef, tuple(leaves))
    try:
        hash(key)
    except TypeError:  # an array leaf: no key
        return functools.partial(fn, *args, **kwargs)
    if key not in _BOUND:
        _BOUND[key] = functools.partial(fn, *args, **kwargs)
    return _BOUND[key]

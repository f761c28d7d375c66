"""Names of the maps jaxrefl writes: one scheme for values, statistics and correlations.

Every EXR channel is ``<layer>.<channel>``: the last dot separates the layer from the
channel, the split OpenEXR's layer convention and Mitsuba 3's ``Bitmap.split()`` make, and
the channel is one of the standard names, so each layer reads as an image of a known pixel
format:

=================  ====================================  ==================================
layer              what                                  channels
=================  ====================================  ==================================
``<p>``            parameter ``p``'s value               ``R``, ``G``, ``B`` (a colour) or
                   (``albedo``, ``specular``, ``alpha``)  ``Y`` (a scalar)
``<p>_<stat>``     a statistic of ``p``: ``std``          as ``<p>``
                   (Laplace or posterior), ``mean``,
                   ``q05``, ``q95`` (posterior)
``corr_<a>_<b>``   correlation of parameters ``a`` and   ``Y``
                   ``b`` (a channel's dot becomes ``_``:
                   ``corr_albedo_R_alpha``)
``normal``         unit shading normal                   ``X``, ``Y``, ``Z`` (a vector, as
                                                         Mitsuba's ``aov`` writes normals)
any other          ``status``, ``laplace_flag``,          ``Y``
                   ``roughness``, ``noise_std``, ...
=================  ====================================  ==================================

A parameter label is ``p`` or ``p.C`` (:attr:`jaxrefl.fit.ParamSpace.labels`:
``albedo.R``, ``alpha``). In memory (:attr:`jaxrefl.svbrdf.CaptureFit.maps`) a map is
keyed by :func:`map_name`, the channel name without the ``.Y`` of a scalar layer
(``albedo.R``, ``alpha``, ``alpha_std``, ``status``); :func:`exr_channel` and
:func:`map_key` convert between the two.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TypeVar

from jaxrefl._errors import JaxreflError

__all__ = [
    "SCALAR_CHANNEL",
    "corr_name",
    "exr_channel",
    "exr_channels",
    "map_key",
    "map_name",
    "split_channel",
]

SCALAR_CHANNEL = "Y"  # the channel of a one-channel layer (OpenEXR's luminance name)
_V = TypeVar("_V")


def map_name(label: str, suffix: str = "") -> str:
    """The map of parameter ``label`` (``albedo.R``, ``alpha``): its value (suffix ``""``)
    or a statistic (suffix ``"_std"``, ``"_mean"``, ``"_q05"``, ``"_q95"``): ``albedo_std.R``,
    ``alpha_std``. A suffix must start with ``_`` (a dot would start a channel)."""
    if suffix and not suffix.startswith("_"):
        raise JaxreflError(f"a map suffix starts with '_' (e.g. '_std'), got {suffix!r}")
    base, dot, ch = label.rpartition(".")
    return f"{base}{suffix}.{ch}" if dot else f"{label}{suffix}"


def corr_name(a: str, b: str) -> str:
    """The map of the correlation of parameters ``a`` and ``b``: ``corr_albedo_R_alpha``."""
    return f"corr_{a.replace('.', '_')}_{b.replace('.', '_')}"


def exr_channel(name: str) -> str:
    """The EXR channel of map ``name``: itself when it names a channel (``albedo.R``),
    ``<name>.Y`` for a scalar map (``alpha`` -> ``alpha.Y``)."""
    return name if "." in name else f"{name}.{SCALAR_CHANNEL}"


def map_key(channel: str) -> str:
    """The map name of EXR channel ``channel`` (inverse of :func:`exr_channel`)."""
    layer, _, ch = channel.rpartition(".")
    return layer if ch == SCALAR_CHANNEL and layer and layer != "normal" else channel


def split_channel(channel: str) -> tuple[str, str]:
    """(layer, channel) of an EXR channel name, split at the last dot."""
    layer, _, ch = channel.rpartition(".")
    return layer, ch


def exr_channels(maps: Mapping[str, _V]) -> dict[str, _V]:
    """``maps`` keyed by EXR channel names (:func:`exr_channel`)."""
    return {exr_channel(k): v for k, v in maps.items()}

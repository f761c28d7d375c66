"""OpenEXR images in and out, through the official ``OpenEXR`` Python bindings (3.3+ API).

Conventions
-----------
* Pixel arrays are ``(H, W)`` = (rows, columns) of the part's *data window*; row 0 is the
  top line ``y = ymin``. Windows are ``((xmin, ymin), (xmax, ymax))``, inclusive pixel
  coordinates as stored in the file; ``header["dataWindow"]`` and
  ``header["displayWindow"]`` keep both, :meth:`ExrImage.display` pastes the data into
  the display window.
* HALF and FLOAT channels are returned as ``float32`` (every half converts exactly);
  UINT channels as ``uint32``. ``ExrImage.pixel_types`` keeps the type stored in the file.
* NaN and ±Inf are kept as they are, counted per channel in ``ExrImage.nonfinite`` and
  masked by :meth:`ExrImage.valid_mask`.
* Refused with :class:`ExrFormatError` (a ``ValueError`` naming the file): deep images,
  subsampled channels (x/y sampling != 1), luminance/chroma (Y, RY, BY) images, corrupt or
  truncated files. A missing file is a ``FileNotFoundError``.

Writing (:func:`write_exr`) makes one single-part scanline file. Floating arrays become
FLOAT channels (float64 is rounded to float32) or HALF on request; bool and integer arrays
(status codes, counts) become UINT channels, exact for 0 ... 2**32 - 1, so they read back as
the same integers (``uint32``). NaN/Inf are written as they are. A value that is finite
in the input but would overflow the stored type (e.g. > 65504 as HALF) is refused.
User metadata goes to string attributes named ``jaxrefl/<key>`` (a namespace, because
OpenEXR reserves names such as ``version``, ``tiles`` and ``chunkCount`` and silently drops
user attributes that reuse them, and gives others, e.g. ``name``, a meaning): a ``str`` is
stored as is, any other JSON-serialisable value as JSON text, its key listed in the
attribute ``jaxrefl:json`` so that :attr:`ExrImage.metadata` decodes it back exactly. The
standard attributes ``capDate`` and ``utcOffset`` (OpenEXR ``ImfStandardAttributes``) and
``software`` are added. Writes are atomic (:func:`~jaxrefl.io.atomic_path`): on any failure
an existing file at the target path is left untouched.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from importlib import metadata as _pkg_metadata
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR

from jaxrefl._errors import JaxreflError

from ._atomic import atomic_path

__all__ = ["ExrFormatError", "ExrImage", "read_exr", "write_exr", "write_exr_rgb"]

_META_PREFIX = "jaxrefl/"
_JSON_KEYS = "jaxrefl:json"
_UINT_MAX = 2**32 - 1
_TYPE_NAMES = {OpenEXR.HALF: "HALF", OpenEXR.FLOAT: "FLOAT", OpenEXR.UINT: "UINT"}
_EXR_ERRORS = (RuntimeError, ValueError, TypeError, OpenEXR.error)


class ExrFormatError(JaxreflError):
    """An EXR file (or what would be written to one) is corrupt or has an unsupported layout.

    The message names the file, the problem and what to do about it.
    """

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


@dataclass(frozen=True)
class ExrImage:
    """One part of an EXR file, as numpy arrays over its data window.

    Attributes:
        path: the file read.
        channels: name -> (H, W) array, float32 (HALF/FLOAT) or uint32 (UINT).
        pixel_types: name -> ``"HALF"``, ``"FLOAT"`` or ``"UINT"`` as stored in the file.
        header: the part's attributes as Python values (enums as names, windows as
            ``((xmin, ymin), (xmax, ymax))``, ``channels`` as name -> pixel type).
        part_name, part_index: the part read (unnamed parts are named by their index).
        parts: names of all parts in the file, in file order.
        size: (H, W) of the data window.
        tiled: whether the part is stored in tiles (else scanlines).
        nonfinite: name -> number of NaN or ±Inf pixels (0 for UINT channels).
    """

    path: Path
    channels: dict[str, np.ndarray]
    pixel_types: dict[str, str]
    header: dict[str, Any]
    part_name: str
    part_index: int
    parts: list[str]
    size: tuple[int, int]
    tiled: bool
    nonfinite: dict[str, int]

    @property
    def data_window(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """((xmin, ymin), (xmax, ymax)) of the arrays, inclusive."""
        return self.header["dataWindow"]

    @property
    def display_window(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """((xmin, ymin), (xmax, ymax)) of the intended picture, inclusive."""
        return self.header["displayWindow"]

    @property
    def layers(self) -> list[str]:
        """Layer prefixes present (``"diffuse"`` for ``diffuse.R``; ``""`` for bare names)."""
        return sorted({n.rpartition(".")[0] for n in self.channels})

    @property
    def metadata(self) -> dict[str, Any]:
        """The metadata written by :func:`write_exr` (``jaxrefl/*`` attributes), decoded."""
        json_keys = set(json.loads(self.header.get(_JSON_KEYS, "[]")))
        out: dict[str, Any] = {}
        for key, value in self.header.items():
            if key.startswith(_META_PREFIX):
                name = key[len(_META_PREFIX) :]
                out[name] = json.loads(value) if name in json_keys else value
        return out

    def _layer_names(self, components: str, layer: str | None) -> list[str]:
        names = [f"{layer}.{c}" if layer else c for c in components]
        missing = [n for n in names if n not in self.channels]
        if missing:
            has_r = [lay for lay in self.layers if (f"{lay}.R" if lay else "R") in self.channels]
            raise ExrFormatError(
                self.path,
                f"part {self.part_name!r} has no channel(s) {', '.join(missing)}; layers with an "
                f"R channel: {', '.join(lay or '(none)' for lay in has_r) or 'none'} (pass "
                f"layer=...); all channels: {', '.join(self.channels)}",
            )
        return names

    def rgb(self, layer: str | None = None) -> np.ndarray:
        """(H, W, 3) float32 from channels R, G, B (or ``<layer>.R`` ... with ``layer``)."""
        return self.stack(self._layer_names("RGB", layer))

    def rgba(self, layer: str | None = None) -> np.ndarray:
        """(H, W, 4) float32 from channels R, G, B, A (or ``<layer>.R`` ...)."""
        return self.stack(self._layer_names("RGBA", layer))

    def stack(self, names: Sequence[str]) -> np.ndarray:
        """(H, W, len(names)) float32 of the named channels (UINT values converted)."""
        unknown = [n for n in names if n not in self.channels]
        if unknown or not names:
            raise ExrFormatError(
                self.path, f"cannot stack {list(names)}; channels: {', '.join(self.channels)}"
            )
        return np.stack([self.channels[n].astype(np.float32) for n in names], axis=-1)

    def valid_mask(self, names: Sequence[str] | None = None) -> np.ndarray:
        """(H, W) bool: False where any of ``names`` (default: all channels) is NaN or ±Inf."""
        names = list(self.channels) if names is None else list(names)
        mask = np.ones(self.size, dtype=bool)
        for n in names:  # UINT values become finite float32
            mask &= np.isfinite(self.stack([n])[..., 0])
        return mask

    def display(self, names: Sequence[str] | None = None, fill: float = np.nan) -> np.ndarray:
        """(Hd, Wd, n) float32 over the display window: data pasted at its offset, ``fill``
        elsewhere (data outside the display window is cropped)."""
        names = list(self.channels) if names is None else list(names)
        data = self.stack(names)
        (dx0, dy0), (dx1, dy1) = self.display_window
        (x0, y0), _ = self.data_window
        out = np.full((dy1 - dy0 + 1, dx1 - dx0 + 1, len(names)), fill, dtype=np.float32)
        h, w = self.size
        # overlap of the data window with the display window, in display coordinates
        ox0, oy0 = max(x0, dx0), max(y0, dy0)
        ox1, oy1 = min(x0 + w - 1, dx1), min(y0 + h - 1, dy1)
        if ox0 <= ox1 and oy0 <= oy1:
            out[oy0 - dy0 : oy1 - dy0 + 1, ox0 - dx0 : ox1 - dx0 + 1] = data[
                oy0 - y0 : oy1 - y0 + 1, ox0 - x0 : ox1 - x0 + 1
            ]
        return out

    def report(self) -> str:
        """Human-readable summary: size, layout and NaN/Inf counts per channel."""
        h, w = self.size
        layout = "tiled" if self.tiled else "scanline"
        head = (
            f"{self.path.name}, part {self.part_index} {self.part_name!r} of {len(self.parts)}: "
            f"H={h} W={w} {layout}, {len(self.channels)} channels"
        )
        bad = int(h * w - np.count_nonzero(self.valid_mask()))
        if bad == 0:
            return head + "; all values finite"
        lines = [head + f"; {bad} of {h * w} pixels have NaN/Inf in some channel"]
        for n, arr in self.channels.items():
            if self.nonfinite[n]:
                nan = int(np.count_nonzero(np.isnan(arr)))
                lines.append(f"  {n}: {nan} NaN, {self.nonfinite[n] - nan} Inf")
        return "\n".join(lines)


# ----------------------------------------------------------------------------- reading


def _tuples(x: Any) -> Any:
    return tuple(_tuples(v) for v in x) if isinstance(x, list) else x


def _py(v: Any) -> Any:
    """An attribute value from the bindings as a plain Python value."""
    if v is None or isinstance(v, str | bool | int | float):
        return v
    if isinstance(v, np.ndarray | np.generic):
        return _tuples(v.tolist())
    if isinstance(v, tuple | list):
        return type(v)(_py(x) for x in v)
    if isinstance(v, dict):
        return {k: _py(x) for k, x in v.items()}
    if hasattr(type(v), "__members__"):  # pybind11 enum: Compression, LineOrder, Storage...
        return v.name
    if isinstance(v, OpenEXR.TileDescription):
        return dict(xSize=v.xSize, ySize=v.ySize, mode=v.mode.name, rounding=v.roundingMode.name)
    return repr(v)


def _select_part(path: Path, names: list[str], part: int | str | None) -> int:
    if part is None:
        return 0
    if isinstance(part, int | np.integer) and not isinstance(part, bool):
        if 0 <= part < len(names):
            return int(part)
    elif isinstance(part, str) and part in names:
        return names.index(part)
    raise ExrFormatError(
        path, f"no part {part!r}; the file has {len(names)} part(s): {', '.join(names)}"
    )


def _check_layout(path: Path, storage: Any, chans: Iterable[Any]) -> None:
    if storage in (OpenEXR.deepscanline, OpenEXR.deeptile):
        raise ExrFormatError(
            path,
            f"deep EXR ({storage.name}) is not supported: jaxrefl reads flat images; "
            "flatten it first (e.g. oiiotool in.exr --flatten -o flat.exr)",
        )
    chans = list(chans)
    if any(c.name.rpartition(".")[2] in ("RY", "BY") for c in chans):
        raise ExrFormatError(
            path,
            "luminance/chroma (Y, RY, BY) EXR is not supported; convert to RGB first "
            "(e.g. with OpenEXR's C++ RgbaInputFile, which converts Y/RY/BY to R/G/B)",
        )
    sub = [
        f"{c.name} ({c.xSampling}x{c.ySampling})" for c in chans if c.xSampling * c.ySampling > 1
    ]
    if sub:
        raise ExrFormatError(
            path,
            f"subsampled channels are not supported: {', '.join(sub)}; "
            "resample them to full resolution first (e.g. with oiiotool)",
        )


def read_exr(
    path: str | Path, part: int | str | None = None, channels: Sequence[str] | None = None
) -> ExrImage:
    """Read one part of an OpenEXR file (scanline or tiled, single- or multi-part).

    Args:
        path: the ``.exr`` file.
        part: index or name of the part to read (default: part 0); ``ExrImage.parts``
            lists them all.
        channels: names of the channels to keep (default: all).

    Raises:
        FileNotFoundError: no file at ``path``.
        ExrFormatError: corrupt/truncated file, unknown part or channel, deep data,
            subsampled channels or luminance/chroma layout.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(2, f"no EXR file at {path}", str(path))
    try:
        head = OpenEXR.File(str(path), separate_channels=True, header_only=True)
        storages = [p.type() for p in head.parts]
    except _EXR_ERRORS as e:
        raise ExrFormatError(path, f"not a readable OpenEXR file (corrupt?): {e}") from e
    names = [p.name() or str(i) for i, p in enumerate(head.parts)]
    index = _select_part(path, names, part)
    _check_layout(path, storages[index], head.header(index)["channels"])
    try:
        full = OpenEXR.File(str(path), separate_channels=True)
        if len(full.parts) != len(names):
            raise RuntimeError(f"pixel data of only {len(full.parts)} of {len(names)} parts read")
        header = {k: _py(v) for k, v in full.header(index).items() if k != "channels"}
        chans = full.channels(index)
    except _EXR_ERRORS as e:
        raise ExrFormatError(path, f"corrupt or truncated OpenEXR file: {e}") from e

    wanted = list(chans) if channels is None else list(channels)
    if missing := [n for n in wanted if n not in chans]:
        problem = f"part {names[index]!r} has no channel(s) {missing}; available: "
        raise ExrFormatError(path, problem + ", ".join(chans))
    (x0, y0), (x1, y1) = header["dataWindow"]
    size = (y1 - y0 + 1, x1 - x0 + 1)
    arrays, types, nonfinite = {}, {}, {}
    for n in wanted:
        px, kind = chans[n].pixels, _TYPE_NAMES[chans[n].type()]
        if px.shape != size:
            raise ExrFormatError(path, f"channel {n!r} has shape {px.shape}, data window {size}")
        arr = np.array(px, dtype=np.uint32 if kind == "UINT" else np.float32)
        arrays[n], types[n] = arr, kind
        nonfinite[n] = 0 if kind == "UINT" else int(arr.size - np.count_nonzero(np.isfinite(arr)))
    header["channels"] = {n: _TYPE_NAMES[c.type()] for n, c in chans.items()}
    tiled = storages[index] == OpenEXR.tiledimage
    return ExrImage(path, arrays, types, header, names[index], index, names, size, tiled, nonfinite)


# ----------------------------------------------------------------------------- writing


def _compression(path: Path, compression: str | OpenEXR.Compression) -> OpenEXR.Compression:
    if isinstance(compression, OpenEXR.Compression):
        return compression
    members = OpenEXR.Compression.__members__
    key = f"{str(compression).upper()}_COMPRESSION"
    if key not in members or key == "NUM_COMPRESSION_METHODS":
        valid = [m[: -len("_COMPRESSION")].lower() for m in members if m.endswith("_COMPRESSION")]
        raise ExrFormatError(path, f"unknown compression {compression!r}; use one of {valid}")
    return members[key]


def _pixels(path: Path, name: str, arr: np.ndarray, half: bool) -> np.ndarray:
    """The array in the type it is stored as: uint32 (UINT), float16 (HALF), float32 (FLOAT)."""
    if arr.dtype.kind in "bui":
        if half:
            raise ExrFormatError(path, f"channel {name!r} is integer; it cannot be written as half")
        if arr.size and (arr.min() < 0 or arr.max() > _UINT_MAX):
            raise ExrFormatError(
                path,
                f"integer channel {name!r} has values outside 0..2**32-1 (UINT); "
                "shift them or pass a float array",
            )
        return arr.astype(np.uint32)
    if arr.dtype.kind != "f":
        raise ExrFormatError(path, f"channel {name!r} has dtype {arr.dtype}; use float or integer")
    with np.errstate(over="ignore"):  # overflow is detected and reported just below
        out = arr.astype(np.float16 if half else np.float32)
    overflow = np.isfinite(arr) & ~np.isfinite(out)
    if np.any(overflow):
        limit = "half (max 65504)" if half else "float32"
        raise ExrFormatError(
            path,
            f"channel {name!r}: {int(overflow.sum())} finite values overflow {limit}; "
            "rescale them" + (" or write the channel as float" if half else ""),
        )
    return out


def _metadata_attrs(path: Path, metadata: Mapping[str, Any] | None) -> dict[str, Any]:
    attrs: dict[str, Any] = {}
    json_keys = []
    for key, value in (metadata or {}).items():
        if not isinstance(key, str) or not key:
            raise ExrFormatError(path, f"metadata keys must be non-empty strings, got {key!r}")
        if isinstance(value, str):
            attrs[_META_PREFIX + key] = value
            continue
        try:
            attrs[_META_PREFIX + key] = json.dumps(value, sort_keys=True)
        except (TypeError, ValueError) as e:
            raise ExrFormatError(path, f"metadata {key!r} is not JSON-serialisable: {e}") from e
        json_keys.append(key)
    if json_keys:
        attrs[_JSON_KEYS] = json.dumps(sorted(json_keys))
    return attrs


def _software() -> str:
    try:
        return f"jaxrefl {_pkg_metadata.version('jaxrefl')}"
    except _pkg_metadata.PackageNotFoundError:  # running from a source tree
        return "jaxrefl"


def _write_file(exr_file: OpenEXR.File, path: Path) -> None:
    """The one call that writes bytes (a seam for the atomicity tests)."""
    exr_file.write(str(path))


def _atomic_write(exr_file: OpenEXR.File, path: Path) -> None:
    with atomic_path(path) as tmp:
        try:
            _write_file(exr_file, tmp)
        except (RuntimeError, OpenEXR.error) as e:
            raise OSError(f"could not write EXR {path}: {e}") from e


def write_exr(
    path: str | Path,
    channels: Mapping[str, Any],
    metadata: Mapping[str, Any] | None = None,
    half: bool | Iterable[str] = False,
    compression: str | OpenEXR.Compression = "zip",
) -> Path:
    """Write named (H, W) channels to a single-part scanline EXR file, atomically.

    Args:
        path: target file; its directory must exist. An existing file is replaced only
            once the new one is completely written.
        channels: name -> (H, W) array, all the same shape. jaxrefl's own files name
            them ``<layer>.<channel>`` (``albedo.R``, ``roughness.Y``, ``roughness_std.Y``,
            ``status.Y``; :mod:`jaxrefl.io._channels`). Floats -> FLOAT (HALF if selected
            by ``half``); bool/integers -> UINT (0 ... 2**32 - 1).
        metadata: JSON-serialisable values stored under ``jaxrefl/<key>`` (see the module
            docstring); read them back with :attr:`ExrImage.metadata`.
        half: True to store every float channel as HALF, or the names of those to store
            as HALF (10-bit mantissa, |x| <= 65504).
        compression: ``"zip"`` (default, lossless), ``"none"``, ``"rle"``, ``"zips"``,
            ``"piz"``, ... or an ``OpenEXR.Compression``. ``"pxr24"``, ``"b44"``,
            ``"dwaa"``, ``"dwab"`` are lossy for float data.

    Returns:
        The path written. Raises :class:`ExrFormatError` (before touching any file) for
        invalid channels, names, metadata or compression.
    """
    path = Path(path)
    if not isinstance(channels, Mapping) or not channels:
        raise ExrFormatError(path, "nothing to write: pass a non-empty dict name -> (H, W) array")
    half_names = set(channels) if half is True else set() if half is False else set(half)
    unknown = half_names - set(channels)
    if unknown:
        raise ExrFormatError(path, f"half= names unknown channels {sorted(unknown)}")
    pixels: dict[str, np.ndarray] = {}
    shape = None
    for name, value in channels.items():
        if not isinstance(name, str) or not name.strip() or "\0" in name:
            raise ExrFormatError(path, f"channel names must be non-empty strings, got {name!r}")
        arr = np.asarray(value)
        if arr.ndim != 2 or 0 in arr.shape:
            raise ExrFormatError(
                path, f"channel {name!r} must be a non-empty (H, W) array, got shape {arr.shape}"
            )
        if shape is not None and arr.shape != shape[1]:
            raise ExrFormatError(
                path, f"channel {name!r} has shape {arr.shape}, but {shape[0]!r} has {shape[1]}"
            )
        shape = shape or (name, arr.shape)
        is_half = name in half_names and not (half is True and arr.dtype.kind in "bui")
        pixels[name] = _pixels(path, name, arr, is_half)
    now = time.localtime()
    header = {
        "compression": _compression(path, compression),
        "type": OpenEXR.scanlineimage,
        "capDate": time.strftime("%Y:%m:%d %H:%M:%S", now),
        "utcOffset": float(-now.tm_gmtoff),  # OpenEXR: UTC = local time + utcOffset
        "software": _software(),
        **_metadata_attrs(path, metadata),
    }
    try:
        exr_file = OpenEXR.File(header, pixels)
    except _EXR_ERRORS as e:
        raise ExrFormatError(path, f"OpenEXR refused the image: {e}") from e
    _atomic_write(exr_file, path)
    return path


def write_exr_rgb(
    path: str | Path,
    image: Any,
    metadata: Mapping[str, Any] | None = None,
    half: bool = False,
    compression: str | OpenEXR.Compression = "zip",
    layer: str | None = None,
) -> Path:
    """Write an (H, W, 3) or (H, W, 4) image as channels R, G, B(, A), or ``<layer>.R`` ...

    Same conventions and atomicity as :func:`write_exr`.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[-1] not in (3, 4):
        raise ExrFormatError(Path(path), f"image must have shape (H, W, 3|4), got {img.shape}")
    names = "RGBA"[: img.shape[-1]]
    chans = {(f"{layer}.{c}" if layer else c): img[..., i] for i, c in enumerate(names)}
    return write_exr(path, chans, metadata=metadata, half=half, compression=compression)

"""Photo files to linear values and per-observation status; PNG at its full bit depth.

:class:`Photos` reads the K photos of a capture with one transfer curve (linear, sRGB,
a gamma law or a tabulated camera response: :mod:`jaxrefl.scene` responses), checks that
they share one size and format, and gives (K, H, W, C) float32 linear values with
:class:`~jaxrefl.io.ObsStatus` codes: the top code of an integer image is ``saturated``,
code 0 ``dark``; in float (EXR) images NaN/Inf are ``nonfinite`` (value set to 0),
negative values ``negative`` and, with a ``saturation`` level, values at or above it
``saturated``. An alpha channel is dropped from the colours and used as a mask
(alpha = 0 -> ``masked``). Integer images are linearised through a lookup table of all
2^bits codes computed in float64. EXR files go through :mod:`jaxrefl.io._exr`.

PNG: Pillow reads 8-bit PNGs and 16-bit greyscale ones (mode ``"I;16"``) faithfully, but it
silently reduces 16-bit RGB and RGBA to 8 bits per channel (it keeps the high byte). Flash
captures saved as 16-bit PNGs would then lose 8 bits of their dynamic range without a
warning, so :func:`read_png` decodes 16-bit colour PNGs itself: the chunks and the zlib
stream with the standard library, then the scanline filters of the PNG specification
(W3C PNG, 2nd edition, section 9: None, Sub, Up, Average, Paeth) in NumPy.

Filters reconstruct each byte from its left, upper and upper-left neighbours, so a row
depends on the previous row and on its own earlier pixels. Rows using only None/Sub/Up are
undone a row at a time (Sub is a cumulative sum modulo 256); otherwise the image is undone
along anti-diagonals r + x = d, whose pixels depend only on earlier diagonals (H + W - 1
vectorised steps instead of H W scalar ones).

:func:`write_png` writes 8- or 16-bit grey/grey+alpha/RGB/RGBA images (filters chosen per
row, by default cycling through all five so that files written by it exercise every
filter); :func:`jaxrefl.io.save_generic_capture` and the tests use it.
"""

from __future__ import annotations

import contextlib
import re
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from jaxrefl._errors import JaxreflError

from ._capture import CaptureError, ObsStatus, obs_severity

__all__ = [
    "PNGError",
    "Photos",
    "linearise",
    "png_header",
    "read_pixels",
    "read_png",
    "response_for",
    "unfilter",
    "write_png",
    "x64",
]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# PNG colour type -> channels (0 grey, 2 RGB, 4 grey + alpha, 6 RGBA; 3 = palette).
_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}


class PNGError(JaxreflError):
    """A PNG file this module cannot read (corrupt, or a variant it does not handle)."""


def png_header(path: str | Path) -> dict[str, int] | None:
    """The IHDR fields of a PNG file, or None if the file is not a PNG."""
    with open(path, "rb") as f:
        head = f.read(33)
    if len(head) < 33 or head[:8] != _SIGNATURE or head[12:16] != b"IHDR":
        return None
    w, h, depth, ctype, comp, filt, interlace = struct.unpack(">IIBBBBB", head[16:29])
    return {
        "width": w,
        "height": h,
        "bit_depth": depth,
        "color_type": ctype,
        "compression": comp,
        "filter": filt,
        "interlace": interlace,
    }


def _chunks(data: bytes, path) -> list[tuple[bytes, bytes]]:
    out = []
    pos = 8
    while pos + 8 <= len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + n]
        if len(body) != n:
            raise PNGError(f"{path}: truncated PNG ({kind!r} chunk cut short)")
        out.append((kind, body))
        pos += 12 + n
        if kind == b"IEND":
            break
    return out


def _paeth(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """PNG Paeth predictor (spec section 9.4) on int16 arrays."""
    pa = np.abs(b - c)
    pb = np.abs(a - c)
    pc = np.abs(a + b - 2 * c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def unfilter(rows: np.ndarray, bpp: int) -> np.ndarray:
    """Undo the PNG scanline filters: ``rows`` (H, 1 + W bpp) uint8 -> (H, W, bpp) uint8."""
    h = rows.shape[0]
    ftype = rows[:, 0]
    if np.any(ftype > 4):
        r = int(np.flatnonzero(ftype > 4)[0])
        raise PNGError(f"unknown PNG filter type {int(ftype[r])} on row {r}")
    filt = rows[:, 1:].reshape(h, -1, bpp)
    w = filt.shape[1]
    out = np.empty((h, w, bpp), np.uint8)
    if not np.any(ftype >= 3):
        prev = np.zeros((w, bpp), np.uint8)
        for r in range(h):
            f = filt[r]
            if ftype[r] == 1:  # Sub: running sum along the row, modulo 256 (uint8 wraps)
                cur = np.cumsum(f, axis=0, dtype=np.uint8)
            elif ftype[r] == 2:  # Up
                cur = f + prev
            else:
                cur = f.copy()
            out[r] = cur
            prev = cur
        return out
    # General case along anti-diagonals; rec has a zero row and column of padding so that
    # the left/up/upper-left neighbours of the first row and column read 0 (spec 9.2).
    rec = np.zeros((h + 1, w + 1, bpp), np.int16)
    f16 = filt.astype(np.int16)
    ft = ftype.astype(np.int16)
    for d in range(h + w - 1):
        rs = np.arange(max(0, d - w + 1), min(h, d + 1))  # the rows on this anti-diagonal
        x = d - rs
        a = rec[rs + 1, x]  # left
        b = rec[rs, x + 1]  # up
        c = rec[rs, x]  # upper left
        t = ft[rs][:, None]
        pred = np.where(
            t == 1,
            a,
            np.where(
                t == 2, b, np.where(t == 3, (a + b) >> 1, np.where(t == 4, _paeth(a, b, c), 0))
            ),
        )
        rec[rs + 1, x + 1] = (f16[rs, x] + pred) & 255
    out[...] = rec[1:, 1:]
    return out


def _decode(path: Path) -> tuple[np.ndarray, int]:
    data = path.read_bytes()
    hdr = png_header(path)
    if hdr is None:
        raise PNGError(f"{path}: not a PNG file")
    if hdr["color_type"] not in _CHANNELS or hdr["bit_depth"] not in (8, 16):
        raise PNGError(
            f"{path}: PNG colour type {hdr['color_type']} at {hdr['bit_depth']} bits is not "
            "decoded here (only 8/16-bit grey, grey+alpha, RGB, RGBA)"
        )
    if hdr["interlace"] != 0:
        raise PNGError(f"{path}: interlaced 16-bit PNGs are not supported; save it non-interlaced")
    chunks = _chunks(data, path)
    idat = b"".join(body for kind, body in chunks if kind == b"IDAT")
    try:
        raw = zlib.decompress(idat)
    except zlib.error as e:
        raise PNGError(f"{path}: corrupt PNG image data ({e})") from None
    c = _CHANNELS[hdr["color_type"]]
    nbytes = hdr["bit_depth"] // 8
    bpp = c * nbytes
    h, w = hdr["height"], hdr["width"]
    if len(raw) != h * (1 + w * bpp):
        raise PNGError(
            f"{path}: PNG image data holds {len(raw)} bytes, expected {h * (1 + w * bpp)} "
            f"for {w}x{h} pixels of {bpp} bytes"
        )
    px = unfilter(np.frombuffer(raw, np.uint8).reshape(h, 1 + w * bpp), bpp)
    if nbytes == 2:  # big-endian samples (spec 7.1)
        px16 = px.reshape(h, w, c, 2).astype(np.uint16)
        return (px16[..., 0] << 8) | px16[..., 1], 16
    return px.reshape(h, w, c), 8


def read_png(path: str | Path) -> tuple[np.ndarray, int]:
    """Decode a PNG at full depth: ((H, W, C) uint8 or uint16 samples, bit depth).

    C is 1 (grey), 2 (grey + alpha), 3 (RGB) or 4 (RGBA); palette images become RGB(A),
    1/2/4-bit grey becomes 8-bit (through Pillow). 16-bit colour images are decoded here
    (module docstring); everything else goes through Pillow.
    """
    path = Path(path)
    hdr = png_header(path)
    if hdr is not None and hdr["bit_depth"] == 16 and hdr["color_type"] in (2, 4, 6):
        return _decode(path)
    try:
        return _read_png_pillow(path)
    except (OSError, _bomb_error()) as e:  # truncated, not an image, too many pixels
        raise PNGError(f"{path}: cannot read image: {e}") from None


def _bomb_error() -> type[Exception]:
    """Pillow's error for an image whose header claims more pixels than its limit."""
    from PIL import Image

    return Image.DecompressionBombError


def _read_png_pillow(path: Path) -> tuple[np.ndarray, int]:
    from PIL import Image

    with Image.open(path) as file:
        file.load()
        im: Image.Image = file
        mode = im.mode
        if mode in ("I;16", "I;16B", "I;16L", "I"):
            a = np.asarray(im)
            if a.min(initial=0) < 0 or a.max(initial=0) > 65535:
                raise PNGError(f"{path}: {mode} samples outside 0..65535")
            return a.astype(np.uint16)[..., None], 16
        if mode == "P":
            im = im.convert("RGBA" if "transparency" in im.info else "RGB")
        elif mode == "1":
            im = im.convert("L")
        elif mode == "PA":
            im = im.convert("RGBA")
        elif mode not in ("L", "LA", "RGB", "RGBA"):
            raise PNGError(f"{path}: PNG mode {mode!r} is not supported")
        a = np.asarray(im)
    return (a[..., None] if a.ndim == 2 else a).astype(np.uint8), 8


def _filter_rows(px: np.ndarray, bpp: int, filters) -> bytes:
    """Filter (H, W*bpp) uint8 rows with the given per-row filter types (spec section 9)."""
    h, n = px.shape
    x = px.astype(np.int16)
    up = np.vstack([np.zeros((1, n), np.int16), x[:-1]])
    left = np.hstack([np.zeros((h, bpp), np.int16), x[:, :-bpp]])
    upleft = np.hstack([np.zeros((h, bpp), np.int16), up[:, :-bpp]])
    preds = [np.zeros_like(x), left, up, (left + up) >> 1, _paeth(left, up, upleft)]
    out = bytearray()
    for r in range(h):
        t = int(filters[r % len(filters)])
        out.append(t)
        out += ((x[r] - preds[t][r]) & 255).astype(np.uint8).tobytes()
    return bytes(out)


def write_png(path: str | Path, image: np.ndarray, filters=(0, 1, 2, 3, 4)) -> None:
    """Write (H, W) or (H, W, C) uint8/uint16 samples, C in 1..4, as an 8/16-bit PNG.

    ``filters`` are the scanline filter types applied to successive rows (cycled).
    """
    a = np.asarray(image)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[-1] not in (1, 2, 3, 4):
        raise JaxreflError(f"write_png needs (H, W) or (H, W, C<=4) samples, got {a.shape}")
    if a.dtype == np.uint8:
        depth, raw = 8, a
    elif a.dtype == np.uint16:
        depth, raw = 16, a.astype(">u2").view(np.uint8)
    else:
        raise JaxreflError(f"write_png needs uint8 or uint16 samples, got {a.dtype}")
    h, w, c = a.shape
    ctype = {1: 0, 2: 4, 3: 2, 4: 6}[c]
    bpp = c * depth // 8
    body = _filter_rows(np.ascontiguousarray(raw).reshape(h, w * bpp), bpp, filters)

    def chunk(kind: bytes, payload: bytes) -> bytes:
        crc = zlib.crc32(kind + payload) & 0xFFFFFFFF
        return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", w, h, depth, ctype, 0, 0, 0)
    Path(path).write_bytes(
        _SIGNATURE
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(body, 6))
        + chunk(b"IEND", b"")
    )


# ----------------------------------------------------------------------------- transfer
def x64():
    """float64 for the lookup tables even when JAX runs in float32."""
    import jax

    ctx = getattr(jax, "enable_x64", None)
    return ctx(True) if ctx is not None else contextlib.nullcontext()


def response_for(spec: Any, path: Path) -> tuple[Any, str]:
    """A :mod:`jaxrefl.scene` response for a transfer spec, and its name."""
    from ..scene import GammaResponse, LinearResponse, SRGBResponse, TabulatedResponse

    if isinstance(spec, dict):
        try:
            return TabulatedResponse(spec["x"], spec["y"]), "tabulated"
        except (KeyError, TypeError, ValueError) as e:
            raise CaptureError(
                path, f"tabulated transfer needs increasing x and y: {e}", "transfer"
            ) from None
    s = str(spec).strip().lower().replace(" ", "")
    if s == "linear":
        return LinearResponse(), "linear"
    if s in ("srgb", "s-rgb"):
        return SRGBResponse(), "srgb"
    m = re.fullmatch(r"gamma=?([0-9.]+)?", s)
    if m:
        g = float(m.group(1) or 2.2)
        if g > 0:
            return GammaResponse(gamma=g), f"gamma{g:g}"
    raise CaptureError(
        path, f"unknown transfer {spec!r}; use 'linear', 'srgb', 'gammaG' or {{x, y}}", "transfer"
    )


def linearise(response, values: np.ndarray) -> np.ndarray:
    import jax.numpy as jnp

    with x64():
        return np.asarray(response.invert(jnp.asarray(values, jnp.float64)), np.float64)


# ----------------------------------------------------------------------------- pixels
def read_pixels(path: Path) -> tuple[np.ndarray, np.ndarray | None, int, bool]:
    """(H, W, C) samples, alpha == 0 mask or None, bit depth, is-float."""
    if path.suffix.lower() == ".exr":
        from ._exr import read_exr

        try:
            exr = read_exr(path)
        except (ValueError, OSError) as e:
            raise CaptureError(path, f"cannot read EXR: {e}") from None
        ch = exr.channels
        names = ["R", "G", "B"] if all(n in ch for n in "RGB") else ["Y"] if "Y" in ch else None
        if names is None:
            names = [n for n in ch if n != "A"]
            if len(names) != 1:
                raise CaptureError(path, f"no R, G, B or Y channels; channels: {', '.join(ch)}")
        alpha = exr.stack(["A"])[..., 0] == 0 if "A" in ch else None
        depth = 16 if all(exr.pixel_types[n] == "HALF" for n in names) else 32
        return exr.stack(names), alpha, depth, True
    try:
        if path.suffix.lower() == ".png":
            a, depth = read_png(path)
        else:
            a, depth = _read_pillow(path)
    except (PNGError, OSError, _bomb_error()) as e:
        raise CaptureError(path, f"cannot read image: {e}") from None
    alpha = None
    if a.shape[-1] in (2, 4):
        alpha, a = a[..., -1] == 0, a[..., :-1]
    return a, alpha, depth, False


def _read_pillow(path: Path) -> tuple[np.ndarray, int]:
    from PIL import Image

    with Image.open(path) as file:
        file.load()
        if file.mode in ("I;16", "I;16B", "I;16L"):
            return np.asarray(file).astype(np.uint16)[..., None], 16
        raw = "".join(str(t[3]) for t in file.tile) if file.tile else ""
        if ";16" in raw:  # Pillow keeps only the high byte of 16-bit colour samples
            raise OSError(f"16-bit {file.mode} {file.format} is read as 8 bits; use PNG or EXR")
        im = file if file.mode in ("L", "LA", "RGB", "RGBA") else file.convert("RGB")
        a = np.asarray(im)
    return (a[..., None] if a.ndim == 2 else a).astype(np.uint8), 8


class Photos:
    """Linear images and status of a list of files read with one transfer curve."""

    def __init__(self, files: list[Path], transfer: Any, spec_path: Path, saturation=None):
        response, self.transfer = response_for(transfer, spec_path)
        if not files:
            raise CaptureError(spec_path, "lists no photos; a capture needs at least one")
        first = None
        for k, f in enumerate(files):
            a, alpha, depth, is_float = read_pixels(f)
            if first is None:
                first = (f, a.shape, depth, is_float)
                self.bit_depth = depth
                self.images = np.empty((len(files), *a.shape), np.float32)
                self.status = np.zeros((len(files), *a.shape), np.uint8)
                self._prepare(response, depth, is_float, saturation)
            f0, shape0, depth0, float0 = first
            if a.shape[:2] != shape0[:2]:
                raise CaptureError(
                    f,
                    f"image is {a.shape[1]}x{a.shape[0]} (WxH) but {f0.name} is "
                    f"{shape0[1]}x{shape0[0]}; all photos must have one size",
                )
            if a.shape[2] != shape0[2] or depth != depth0 or is_float != float0:
                raise CaptureError(
                    f,
                    f"{a.shape[2]} channels at {depth} bits but {f0.name} has "
                    f"{shape0[2]} at {depth0}; all photos must have one format",
                )
            self.images[k], self.status[k] = self._decode(a, response)
            if alpha is not None:  # a transparent pixel is masked whatever its value
                sk = self.status[k]
                worse = obs_severity(sk[alpha]) > obs_severity(ObsStatus.MASKED)
                sk[alpha] = np.where(worse, sk[alpha], ObsStatus.MASKED)

    def _prepare(self, response, depth, is_float, saturation):
        self.saturation = None if saturation is None else float(saturation)
        if is_float:
            self.lut = None
            self.dark_level = 0.0
            self.saturation_level = float("inf") if saturation is None else float(saturation)
            return
        top = 2**depth - 1
        codes = np.arange(top + 1, dtype=np.float64) / top
        self.lut = linearise(response, codes).astype(np.float32)
        lo, hi = linearise(response, np.array([0.5 / top, (top - 0.5) / top]))
        self.dark_level, self.saturation_level = float(lo), float(hi)
        self.top = top

    def _decode(self, a: np.ndarray, response) -> tuple[np.ndarray, np.ndarray]:
        st = np.zeros(a.shape, np.uint8)
        if self.lut is not None:
            st[a == 0] = ObsStatus.DARK
            st[a == self.top] = ObsStatus.SATURATED
            return self.lut[a], st
        finite = np.isfinite(a)
        x = np.where(finite, a, 0.0).astype(np.float32)
        if self.transfer != "linear":
            x = linearise(response, x).astype(np.float32)
        if self.saturation is not None:
            st[x >= self.saturation] = ObsStatus.SATURATED
        st[x < 0] = ObsStatus.NEGATIVE
        st[~finite] = ObsStatus.NONFINITE
        return x, st

"""A photo's metadata: exposure, sensitivity, aperture, orientation and transfer curve.

Read with Pillow from the EXIF block (CIPA DC-008, Exif 2.3): in IFD0 ``Orientation``
(0x0112, 1-8; how the stored pixels are to be turned for display), ``Make``, ``Model``; in
the Exif sub-IFD ``ExposureTime`` (0x829A, s), ``FNumber`` (0x829D), ``ISOSpeedRatings`` /
``PhotographicSensitivity`` (0x8827), ``FocalLength`` (0x920A, mm),
``FocalLengthIn35mmFilm`` (0xA405, mm) and ``ColorSpace`` (0xA001). A missing tag is None.

The pixels' *exposure* H = t S / N^2 (exposure time t, ISO S, f-number N) sets the scale
between radiance and pixel value: two shots with H in ratio 2 differ by 2 in linear value.
:attr:`PhotoMeta.exposure` gives it where all three are known, so a fit can put the shots
on one scale.

Transfer curve of 8-bit values (how they decode to linear): sRGB (IEC 61966-2-1) unless
the metadata says otherwise. An embedded ICC profile named Adobe RGB, or EXIF
``ColorSpace`` = 0xFFFF (uncalibrated) with the interoperability index ``R03`` (the Exif
convention for Adobe RGB), give Adobe RGB's power law 563/256 (Adobe RGB (1998)
specification, section 4.3.1.2). Display P3 (most phones) uses the sRGB curve. Only the
curve is used; colour primaries are left as they are. The orientation is recorded, not
applied: calibration works in the stored pixels, the sensor's own frame.
"""

from __future__ import annotations

import io
from dataclasses import asdict, dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

__all__ = ["ADOBE_RGB_GAMMA", "PhotoMeta", "read_photo_meta"]

ADOBE_RGB_GAMMA = 563 / 256
_EXIF_IFD, _INTEROP_IFD = 0x8769, 0xA005


@dataclass(frozen=True)
class PhotoMeta:
    """What a photo's metadata says (module docstring); None where a tag is missing."""

    exposure_time: float | None = None  # s
    f_number: float | None = None
    iso: float | None = None
    orientation: int = 1  # EXIF Orientation, 1 = as stored
    focal_length: float | None = None  # mm
    focal_length_35mm: float | None = None  # mm, 35 mm film equivalent
    make: str | None = None
    model: str | None = None
    transfer: str = "srgb"  # "srgb" or "gammaG" (jaxrefl.io transfer names)
    transfer_source: str = "assumed: no colour metadata"

    @property
    def exposure(self) -> float | None:
        """H = t ISO / N^2 (s), or None unless all three are known."""
        if self.exposure_time is None or self.iso is None or not self.f_number:
            return None
        return self.exposure_time * self.iso / self.f_number**2

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        out["exposure"] = self.exposure
        return out


def _number(value) -> float | None:
    if value is None:
        return None
    if isinstance(value, tuple) and len(value) == 2:  # (numerator, denominator)
        return float(Fraction(int(value[0]), int(value[1]))) if value[1] else None
    if isinstance(value, (tuple, list)):
        value = value[0] if value else None
        return _number(value)
    try:
        x = float(value)
    except (TypeError, ValueError):
        return None
    return x if x == x and x not in (float("inf"), float("-inf")) else None


def _text(value) -> str | None:
    if value is None:
        return None
    if isinstance(value, bytes):
        value = value.decode("ascii", "replace")
    return str(value).strip("\x00 ") or None


def _transfer(img, exif_ifd: dict, interop: dict) -> tuple[str, str]:
    icc = img.info.get("icc_profile")
    if icc:
        try:
            from PIL import ImageCms

            name = ImageCms.getProfileDescription(ImageCms.ImageCmsProfile(io.BytesIO(icc)))
            name = name.strip()
        except Exception:  # an unreadable profile: fall back to EXIF and then to sRGB
            name = ""
        if "adobe rgb" in name.lower():
            return f"gamma{ADOBE_RGB_GAMMA!r}", f"ICC profile {name!r}"
        if name:
            return "srgb", f"ICC profile {name!r} (sRGB transfer curve)"
    space = exif_ifd.get(0xA001)
    if space == 1:
        return "srgb", "EXIF ColorSpace sRGB"
    if space == 0xFFFF and _text(interop.get(0x0001)) == "R03":
        return f"gamma{ADOBE_RGB_GAMMA!r}", "EXIF ColorSpace uncalibrated, interop R03 (Adobe RGB)"
    return "srgb", "assumed: no colour metadata"


def read_photo_meta(path: str | Path) -> PhotoMeta:
    """The metadata of the photo at ``path`` (module docstring)."""
    from PIL import Image

    with Image.open(path) as img:
        exif = img.getexif()
        sub = dict(exif.get_ifd(_EXIF_IFD)) if exif else {}
        interop = dict(exif.get_ifd(_INTEROP_IFD)) if exif else {}
        transfer, source = _transfer(img, sub, interop)
    orient = _number(exif.get(0x0112)) if exif else None
    return PhotoMeta(
        exposure_time=_number(sub.get(0x829A)),
        f_number=_number(sub.get(0x829D)),
        iso=_number(sub.get(0x8827)),
        orientation=int(orient) if orient is not None and 1 <= orient <= 8 else 1,
        focal_length=_number(sub.get(0x920A)),
        focal_length_35mm=_number(sub.get(0xA405)),
        make=_text(exif.get(0x010F)) if exif else None,
        model=_text(exif.get(0x0110)) if exif else None,
        transfer=transfer,
        transfer_source=source,
    )

"""Phone photos of a sample in the printed frame to a capture folder ``load_capture`` reads.

:func:`photos_to_capture` runs the whole way:

1. lists the photos of the folder (``.jpg``, ``.jpeg``, ``.png``, 8-bit; name order) and
   refuses photos of different sizes (one camera, one resolution: one set of intrinsics);
2. reads each photo's metadata (:mod:`jaxrefl.phone._exif`), decodes its pixels to linear
   values with its transfer curve (sRGB unless the metadata says otherwise), and detects
   the tags (:mod:`jaxrefl.phone._detect`); a photo with fewer than ``min_markers`` tags is
   left out, with the file and what was found;
3. calibrates the camera over the photos left (or places them with given intrinsics;
   :mod:`jaxrefl.phone._calibrate`); while a photo's reprojection error exceeds
   ``max_error`` the worst photo is left out and the rest calibrated again. Fewer than 3
   usable photos is refused (:class:`PhoneCaptureError`, naming every photo left out and
   why); so is a set whose every photo misfits the layout: the tags do not sit where a
   frame of that side puts them. (A print scaled by the same factor in both directions
   cannot be told from the photos; the printed scale bar checks it.)
4. rectifies each photo to the sample square (:mod:`jaxrefl.phone._rectify`) at N x N;
5. writes, into a temporary folder beside ``out`` renamed to ``out`` at the end (nothing
   half-written on refusal or error), the generic layout of :func:`jaxrefl.io.load_capture`:

   * ``capture.json``: the photos ``00.png`` ... (16-bit PNG, sRGB-encoded linear values;
     code 65535 where the photo was clipped, so they read back as saturated; an alpha
     channel, 0 where a pixel fell outside the photo, when any did), ``transfer`` "srgb",
     ``side`` the sample square's side in cm, a point flash at each camera position
     (co-located with the lens) of power ``flash_power``, the camera positions;
   * ``calibration.json``: the layout (family, ids, side, sample side, depth), the
     intrinsics and distortion (reusable with ``--intrinsics``), and per photo its source
     file, tags found, reprojection error, camera position and orientation (camera-to-frame
     rotation: columns are the camera's x right, y down, z forward), pose (rvec, tvec) and
     metadata (exposure time, ISO, aperture, orientation, transfer curve, exposure H
     relative to the median photo's); the photos left out and why;
   * ``preview/NN.png``: :mod:`jaxrefl.phone._preview`.

Coordinates of the capture are the sample's: origin at the centre of the sample square on
its surface, x, y as the frame's, z up. The sample lies ``depth`` cm below the marker
plane, so a camera at height z above the markers is at z + depth in the capture.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ._calibrate import Calibration, CalibrationOptions, Intrinsics, calibrate, locate
from ._detect import Detection, DetectorOptions, detect_markers
from ._errors import PhoneCaptureError, require_cv2
from ._exif import PhotoMeta, read_photo_meta
from ._frame import TAG_FAMILY, TAG_IDS, FrameLayout
from ._preview import write_preview
from ._rectify import rectify

__all__ = ["CaptureOptions", "PhoneCapture", "list_photos", "photos_to_capture"]

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
MIN_PHOTOS = 3  # fewest photos a capture is made of (and calibrateCamera's useful minimum)


@dataclass(frozen=True)
class CaptureOptions:
    """Everything that shapes the capture: the frame's ``side`` (cm), the sample's
    ``depth`` below the marker plane (cm), the rectified photos' ``size`` (pixels), the
    flash's ``flash_power`` (the light power written; the flash-capture convention of the
    public data), known ``intrinsics`` (else calibrated), the detector and calibration
    options, the largest reprojection error a photo may have (``max_error``, pixels) and
    the previews' size."""

    side: float
    depth: float = 0.0
    size: int = 1024
    flash_power: float = 1500.0
    intrinsics: Intrinsics | None = None
    detector: DetectorOptions = field(default_factory=DetectorOptions)
    calibration: CalibrationOptions = field(default_factory=CalibrationOptions)
    max_error: float = 1.0
    preview_size: int = 512

    def __post_init__(self):
        FrameLayout(self.side)  # checks the side
        checks = {
            "depth": np.isfinite(self.depth) and self.depth >= 0,
            "size": isinstance(self.size, int) and self.size >= 8,
            "flash_power": np.isfinite(self.flash_power) and self.flash_power > 0,
            "max_error": np.isfinite(self.max_error) and self.max_error > 0,
            "preview_size": isinstance(self.preview_size, int) and self.preview_size >= 64,
        }
        for name, ok in checks.items():
            if not ok:
                raise PhoneCaptureError(
                    f"{name} = {getattr(self, name)!r}: depth >= 0 cm, size >= 8 px, "
                    "flash_power > 0, max_error > 0 px, preview_size >= 64 px"
                )
        if self.depth >= self.side:
            raise PhoneCaptureError(
                f"depth {self.depth:g} cm is not below a frame of side {self.side:g} cm"
            )


@dataclass(frozen=True)
class PhoneCapture:
    """What :func:`photos_to_capture` made: the capture folder ``out``, the ``photos`` used
    (in capture order), those ``left_out`` with the reason, the :class:`Calibration`, the
    camera positions in the capture's coordinates (K, 3), cm, and the ``record`` written
    to ``calibration.json``."""

    out: Path
    photos: tuple[Path, ...]
    left_out: tuple[tuple[Path, str], ...]
    calibration: Calibration
    positions: np.ndarray
    record: dict[str, Any]


@dataclass
class _Photo:
    path: Path
    meta: PhotoMeta
    pixels: np.ndarray  # (H, W, 3) uint8
    linear: np.ndarray  # (H, W, 3) float32
    detection: Detection


def list_photos(folder: str | Path) -> list[Path]:
    """The photos of ``folder`` (``PHOTO_SUFFIXES``, any case), in name order."""
    folder = Path(folder)
    if not folder.is_dir():
        raise PhoneCaptureError(f"{folder}: not a folder of photos")
    photos = sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)
    if not photos:
        raise PhoneCaptureError(f"{folder}: no photos ({', '.join(PHOTO_SUFFIXES)}) in this folder")
    return photos


def _check_sizes(photos: list[Path]) -> tuple[int, int]:
    from PIL import Image, UnidentifiedImageError

    sizes = {}
    for p in photos:
        try:
            with Image.open(p) as img:
                sizes[p] = img.size
        except (UnidentifiedImageError, OSError) as e:
            raise PhoneCaptureError(f"{p}: not a readable image: {e}") from None
    first = photos[0]
    for p, s in sizes.items():
        if s != sizes[first]:
            raise PhoneCaptureError(
                f"photos of different sizes: {first.name} is {sizes[first][0]}x"
                f"{sizes[first][1]}, {p.name} is {s[0]}x{s[1]}; one camera at one resolution "
                "(one set of intrinsics) is needed: take them again or resize them alike"
            )
    return sizes[first]


def _response(transfer: str):
    from jaxrefl.scene import GammaResponse, SRGBResponse

    if transfer == "srgb":
        return SRGBResponse()
    return GammaResponse(gamma=float(transfer.removeprefix("gamma")))


def _read(path: Path, options: CaptureOptions) -> _Photo:
    from PIL import Image

    cv2 = require_cv2()
    with Image.open(path) as img:
        if img.mode not in ("RGB", "RGBA", "L", "P"):
            raise PhoneCaptureError(f"{path}: mode {img.mode}; 8-bit RGB or grey photos only")
        pixels = np.asarray(img.convert("RGB"))
    meta = read_photo_meta(path)
    linear = np.asarray(
        _response(meta.transfer).invert(pixels.astype(np.float32) / 255.0), np.float32
    )
    gray = cv2.cvtColor(pixels, cv2.COLOR_RGB2GRAY)
    luminance = linear @ np.array([0.2126, 0.7152, 0.0722], np.float32)  # Rec. 709 weights
    det = detect_markers(gray, options.detector, luminance)
    return _Photo(path, meta, pixels, linear, det)


def _fit(photos: list[_Photo], layout: FrameLayout, options: CaptureOptions) -> Calibration:
    dets = [p.detection for p in photos]
    if options.intrinsics is not None:
        return locate(dets, layout, options.intrinsics)
    return calibrate(dets, layout, options.calibration)


def _refuse(what: str, left_out: list[tuple[Path, str]]) -> PhoneCaptureError:
    lines = "".join(f"\n  {p.name}: {why}" for p, why in left_out)
    return PhoneCaptureError(what + (f"; left out:{lines}" if lines else ""))


def _calibrated(
    photos: list[_Photo], layout: FrameLayout, options: CaptureOptions, left_out: list
) -> tuple[list[_Photo], Calibration]:
    if len(photos) < MIN_PHOTOS:
        raise _refuse(f"{len(photos)} usable photos; a capture needs {MIN_PHOTOS}", left_out)
    cal = _fit(photos, layout, options)
    while np.max(cal.errors) > options.max_error:
        worst = int(np.argmax(cal.errors))
        if len(photos) <= MIN_PHOTOS:
            errs = ", ".join(
                f"{p.path.name} {e:.2f} px" for p, e in zip(photos, cal.errors, strict=True)
            )
            raise _refuse(
                f"reprojection errors {errs} exceed {options.max_error:g} px: the tags are "
                f"not where a {layout.side:g} cm frame of this layout puts them (a print "
                "scaled differently across and down the page, a frame of another layout, a "
                "sheet that is not flat) or were detected badly",
                left_out,
            )
        left_out.append(
            (
                photos[worst].path,
                f"reprojection error {cal.errors[worst]:.2f} px > {options.max_error:g} px "
                f"({photos[worst].detection.describe()}; blurred or moved?)",
            )
        )
        photos = photos[:worst] + photos[worst + 1 :]
        cal = _fit(photos, layout, options)
    return photos, cal


def _encode(linear: np.ndarray, clipped: np.ndarray, valid: np.ndarray, alpha: bool):
    from jaxrefl.scene import SRGBResponse

    enc = np.asarray(SRGBResponse().apply(linear.astype(np.float32)), np.float64)
    enc = np.where(clipped, 1.0, enc)  # top code: read back as saturated
    q = np.rint(np.clip(enc, 0.0, 1.0) * 65535).astype(np.uint16)
    if alpha:
        q = np.concatenate([q, np.where(valid, 65535, 0).astype(np.uint16)[..., None]], -1)
    return q


def _ratio(value: float | None, ref: float | None) -> float | None:
    """value / ref, or None where either is unknown (or ref is 0)."""
    return None if value is None or not ref else value / ref


def _prepare_out(out: Path) -> None:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise PhoneCaptureError(f"{out}: exists and is not an empty folder; name a new one")
    parent = out.parent if str(out.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    if not os.access(parent, os.W_OK | os.X_OK):
        raise PhoneCaptureError(f"{out}: {parent} is not writable")


def photos_to_capture(
    raw_dir: str | Path, out: str | Path, options: CaptureOptions
) -> PhoneCapture:
    """Make a capture of the photos in ``raw_dir`` in the folder ``out`` (module
    docstring). ``out`` must not exist, or be an empty folder."""
    from jaxrefl.io import write_png

    out = Path(out)
    _prepare_out(out)
    layout = FrameLayout(options.side)
    files = list_photos(raw_dir)
    _check_sizes(files)
    left_out: list[tuple[Path, str]] = []
    usable = []
    for f in files:
        photo = _read(f, options)
        if photo.detection.count < options.detector.min_markers:
            left_out.append(
                (
                    f,
                    f"{photo.detection.describe()}: fewer than "
                    f"{options.detector.min_markers} of the frame's tags",
                )
            )
        else:
            usable.append(photo)
    photos, cal = _calibrated(usable, layout, options, left_out)
    shift = np.array([0.0, 0.0, options.depth])  # marker plane -> sample surface
    positions = np.stack([cal.poses[k].position() + shift for k in range(len(photos))])
    rects = [
        rectify(
            p.linear,
            p.pixels == 255,
            cal,
            k,
            layout.sample_side,
            options.size,
            options.depth,
        )
        for k, p in enumerate(photos)
    ]
    alpha = not all(bool(r.valid.all()) for r in rects)
    exposures = [p.meta.exposure for p in photos]
    known = [e for e in exposures if e is not None]
    median = float(np.median(known)) if known else None
    names = [f"{k:02d}.png" for k in range(len(photos))]
    record: dict[str, Any] = {
        "frame": {
            "family": TAG_FAMILY,
            "ids": list(TAG_IDS),
            "side_cm": layout.side,
            "layout": "svbrdf-diff-renderer src/capture.py (5 x 5 ring, tag side S/9)",
            "sample_side_cm": layout.sample_side,
            "depth_cm": options.depth,
        },
        "intrinsics": {
            **cal.intrinsics.to_json(),
            "source": "calibrated over the photos" if cal.estimated else "given",
        },
        "reprojection_error_px": {
            "rms": float(np.sqrt(np.mean(cal.errors**2))),
            "max": float(np.max(cal.errors)),
        },
        "coordinates": "cm; origin at the sample square's centre on its surface, z up; "
        "orientation columns: camera x (right), y (down), z (forward)",
        "photos": [
            {
                "image": name,
                "source": p.path.name,
                "tags": [int(i) for i in p.detection.ids],
                "reprojection_error_px": float(cal.errors[k]),
                "camera_position": positions[k].tolist(),
                "camera_orientation": cal.poses[k].orientation().tolist(),
                "rvec": np.asarray(cal.poses[k].rvec).tolist(),
                "tvec": np.asarray(cal.poses[k].tvec).tolist(),
                "outside_photo_px": int((~rects[k].valid).sum()),
                "metadata": {
                    **p.meta.to_json(),
                    "relative_exposure": _ratio(exposures[k], median),
                },
            }
            for k, (name, p) in enumerate(zip(names, photos, strict=True))
        ],
        "left_out": [{"source": p.name, "reason": why} for p, why in left_out],
    }
    capture = {
        "images": names,
        "transfer": "srgb",
        "side": layout.sample_side,
        "unit": "cm",
        "lights": [
            {"type": "point", "position": c.tolist(), "power": [options.flash_power] * 3}
            for c in positions
        ],
        "cameras": [{"position": c.tolist()} for c in positions],
        "calibration": "calibration.json",
    }
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        (tmp / "preview").mkdir()
        for k, (name, p, r) in enumerate(zip(names, photos, rects, strict=True)):
            write_png(tmp / name, _encode(r.image, r.clipped, r.valid, alpha))
            write_preview(
                tmp / "preview" / name,
                p.pixels,
                p.detection,
                cal,
                k,
                layout,
                depth=options.depth,
                size=options.preview_size,
                label=p.path.name,
            )
        (tmp / "calibration.json").write_text(json.dumps(record, indent=2))
        (tmp / "capture.json").write_text(json.dumps(capture, indent=2))
        if out.exists():
            out.rmdir()  # empty (checked above): rename needs the name free
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return PhoneCapture(
        out=out,
        photos=tuple(p.path for p in photos),
        left_out=tuple(left_out),
        calibration=cal,
        positions=positions,
        record=record,
    )

"""The prior on the flash's per-photo gains, from the photos' EXIF exposure, and the
offset's frame from ``calibration.json`` (:mod:`jaxrefl.svbrdf._light`).

Gain g_k: photo k's flash output times exposure relative to the capture's stated power.
Prior: log g_k ~ N(log(H_k / H_ref), s^2), with H_k = t_k ISO_k / N_k^2 the EXIF exposure
(:mod:`jaxrefl.phone._exif`) where every photo gives it, H_ref their geometric mean, and
s = :data:`GAIN_LOG_STD_EXIF` (flash output still varies); without EXIF, H_k / H_ref = 1 and
s = :data:`GAIN_LOG_STD`. The exposures come from the ``calibration.json`` that
``jaxrefl capture`` keeps beside a capture, else from the photo files' own EXIF.

The offset's frame: each photo's ``camera_orientation`` in ``calibration.json`` (a phone
turned between shots carries its flash with it), else the sample's frame for every photo.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from jaxrefl._errors import JaxreflError

__all__ = ["GAIN_LOG_STD", "GAIN_LOG_STD_EXIF", "GainPrior", "gain_prior", "orientations"]

GAIN_LOG_STD = 0.5  # no EXIF: exposure and flash output free within about x/ 1.6
GAIN_LOG_STD_EXIF = 0.05  # EXIF exposure known: the flash's own output varies by a few %


@dataclass(frozen=True)
class GainPrior:
    """log g_k ~ N(log_mean_k, log_std^2) (module docstring); ``source`` says where the
    means come from, ``exposure`` the EXIF exposures H_k (s) where every photo gives one."""

    log_mean: np.ndarray
    log_std: float
    source: str
    exposure: tuple[float, ...] | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "exif": self.exposure is not None,
            "exposure_s": None if self.exposure is None else list(self.exposure),
            "relative_exposure": [float(v) for v in np.exp(self.log_mean)],
            "log_std": self.log_std,
        }


def _calibration_photos(capture) -> tuple[Path, list] | None:
    """(path, its ``photos`` list) of the ``calibration.json`` that ``jaxrefl capture`` keeps
    beside a capture, or None where there is none."""
    src = capture.source
    if src is None:
        return None
    folder = Path(src) if Path(src).is_dir() else Path(src).parent
    path = folder / "calibration.json"
    if not path.is_file():
        return None
    try:
        return path, list(json.loads(path.read_text())["photos"])
    except (ValueError, KeyError, TypeError) as e:
        raise JaxreflError(
            f"{path}: no readable photos list ({e}); rewrite the file with jaxrefl capture "
            "or remove it"
        ) from None


def _calibration_exposures(capture) -> list[float | None] | None:
    """EXIF exposures kept in ``calibration.json`` beside a capture of ``jaxrefl capture``."""
    found = _calibration_photos(capture)
    if found is None:
        return None
    path, photos = found
    try:
        return [(p.get("metadata") or {}).get("exposure") for p in photos][: capture.n_photos]
    except AttributeError as e:
        raise JaxreflError(
            f"{path}: photos[k].metadata.exposure cannot be read ({e}); rewrite the file "
            "with jaxrefl capture or remove it"
        ) from None


def orientations(capture) -> np.ndarray | None:
    """(K, 3, 3) camera-to-sample rotations from ``calibration.json``, or None."""
    found = _calibration_photos(capture)
    if found is None:
        return None
    try:
        rot_a = np.asarray([p["camera_orientation"] for p in found[1]], np.float64)
        rot_a = rot_a[: capture.n_photos]
    except (ValueError, KeyError, TypeError):
        return None
    return rot_a if rot_a.shape == (capture.n_photos, 3, 3) else None


def gain_prior(capture) -> GainPrior:
    """The gains' prior of ``capture`` (module docstring): EXIF exposures from
    ``calibration.json`` beside the capture, else from the photo files' own EXIF (JPEG or
    TIFF, :func:`jaxrefl.phone.read_photo_meta`); absent unless every photo gives one."""
    k = capture.n_photos
    exposures = _calibration_exposures(capture)
    where = "calibration.json"
    if exposures is None and len(capture.files) == k:
        from jaxrefl.phone import read_photo_meta

        where = "the photos' EXIF"
        exposures = []
        for f in capture.files:
            try:
                exposures.append(read_photo_meta(f).exposure)
            except OSError:  # not an image Pillow reads (an EXR): no EXIF
                exposures.append(None)
    known = [e for e in (exposures or []) if e is not None and e > 0]
    if exposures is not None and len(known) == k:
        h = np.asarray(known, np.float64)
        log_h = np.log(h)
        return GainPrior(
            log_h - log_h.mean(),
            GAIN_LOG_STD_EXIF,
            f"EXIF exposure t ISO / N^2 of every photo ({where})",
            tuple(float(v) for v in h),
        )
    n = len(known)
    why = (
        "no EXIF exposure: every photo's prior gain is 1"
        if n == 0
        else f"EXIF exposure in {n} of {k} photos only: every photo's prior gain is 1"
    )
    return GainPrior(np.zeros(k), GAIN_LOG_STD, why)

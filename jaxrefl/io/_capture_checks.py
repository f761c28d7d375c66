"""Physical checks of a capture as it is read: nonsense is refused where it enters.

:func:`jaxrefl.io.load_capture` runs two checks on what a layout read, each naming the file
and the line or key at fault (:class:`Fields` says where every photo's numbers came from).

Refused (:class:`~jaxrefl.io.CaptureError`), because no fit can mean anything:

* a camera or a point light at or below the sample plane (z <= 0; the sample is the plane
  z = 0 with normal +z, :mod:`jaxrefl.io._capture`), or a directional light from below;
* a camera or light farther from the sample centre than :data:`MAX_SIDES` sample sides (its
  square overflows, or its directions do not vary across the sample in float32: a light
  that far is a directional one), or one whose irradiance at the sample is not a normal
  float32 number (the fit's default precision);
* a light power that is 0 or negative (finiteness is checked as the numbers are read);
* photos in which no observation is a measured value: every one saturated, black, masked
  (a mask or alpha channel that excludes every pixel) or invalid. The message says what to
  change (the exposure, the mask).

Warned about (:class:`CaptureWarning`, a ``UserWarning``), because it is odd but may be
meant:

* in a phone-flash layout (MaterialGAN, svbrdf-diff-renderer), a light farther from its
  camera than :data:`PHONE_SEPARATION` times the camera's distance to the sample;
* photos whose median measured pixel is darker than :data:`DARK_RATIO` or brighter than
  :data:`BRIGHT_RATIO` times the radiance of a white diffuse surface (albedo 1) under the
  stated light power: the power's unit or the exposure is likely wrong;
* one photo whose every observation is saturated or black (it bounds but measures nothing).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ._capture import Capture, CaptureError, ObsStatus

__all__ = ["CaptureWarning", "Fields", "check_geometry", "check_photos"]

_F32 = np.finfo(np.float32)
# Farthest camera or light, in sample sides: beyond 1/eps (float32) sides the direction
# from the light to the sample's pixels changes by less than float32 resolves across it.
MAX_SIDES = float(1.0 / _F32.eps)
# A phone's flash sits about 1 cm from its lens, a few per cent of its distance to the
# sample; a quarter of that distance (about 14 degrees between light and view) is odd.
PHONE_SEPARATION = 0.25
# Median measured pixel over a white diffuse surface's radiance: below 1e-3 is darker than
# the blackest paints; above 2 more than half the pixels outshine any diffuse surface, and a
# highlight covers few of them.
DARK_RATIO = 1e-3
BRIGHT_RATIO = 2.0
# Pixels a side of the subsample the brightness check looks at (it needs a median only).
_CHECK_SIDE = 64


class CaptureWarning(UserWarning):
    """A capture that loads but looks wrong (module docstring): the message names the file
    and the field, and what is odd about it."""


@dataclass(frozen=True)
class Fields:
    """Where each photo's numbers came from, for messages: per quantity the file and one
    field name per photo (``"line 3"``, ``"cameras[2].position"``).

    phone: the layout is a phone flash capture (the light is expected at the camera).
    mask:  the mask file applied, if any.
    """

    camera: tuple[Path, list[str]]
    light: tuple[Path, list[str]]
    power: tuple[Path, list[str]]
    phone: bool = False
    mask: Path | None = None


def _refuse(where: tuple[Path, list[str]], k: int, problem: str) -> CaptureError:
    path, names = where
    return CaptureError(path, problem, names[k])


def _distance(
    pos: np.ndarray,
    what: str,
    where: tuple[Path, list[str]],
    k: int,
    unit: str,
    limit: float,
    advice: str,
) -> float:
    """The distance from the sample's centre of photo ``k``'s ``what`` (camera or light) at
    ``pos``; one on or below the sample plane, or further than ``limit``, is refused
    (``advice``: the way out of the latter)."""
    if not pos[2] > 0:
        raise _refuse(
            where,
            k,
            f"the {what} is at z = {pos[2]:g} {unit}, not above the sample plane; the sample "
            f"lies in z = 0 facing +z, so a {what} needs z > 0",
        )
    with np.errstate(over="ignore"):  # an overflowing square is refused just below
        dist = float(np.sqrt(np.sum(pos * pos)))
    if not dist <= limit:
        raise _refuse(
            where,
            k,
            f"the {what} is {dist:.3g} {unit} from the sample, more than {MAX_SIDES:.3g} sample "
            f"sides ({limit:.3g} {unit}){advice}",
        )
    return dist


def check_geometry(
    camera_pos: np.ndarray,
    light_pos: np.ndarray | None,
    light_dir: np.ndarray | None,
    light_power: np.ndarray,
    side: float,
    fields: Fields,
    unit: str = "cm",
) -> None:
    """Refuse impossible cameras, lights and powers; warn about a phone flash far from its
    camera (module docstring). Arrays are (K, 3) and (K, C), finite."""
    limit = MAX_SIDES * side
    # The sample's farthest point from its centre: a corner.
    reach = side * np.sqrt(0.5)
    far: list[tuple[int, float, float]] = []  # phone flashes far from their camera
    for k in range(camera_pos.shape[0]):
        cam = camera_pos[k]
        dist = _distance(
            cam, "camera", fields.camera, k, unit, limit, f"; give positions in {unit}"
        )
        if light_power[k].size and not np.all(light_power[k] > 0):
            raise _refuse(
                fields.power,
                k,
                f"light power {light_power[k].tolist()} must be > 0 in every channel: a light "
                "of power 0 lights nothing (leave the photo out instead)",
            )
        if light_dir is not None:
            if not light_dir[k, 2] > 0:
                raise _refuse(
                    fields.light,
                    k,
                    f"the light direction {light_dir[k].tolist()} points from below the sample "
                    "plane; a directional light needs z > 0 (towards the light)",
                )
            continue
        assert light_pos is not None  # one of light_pos and light_dir (Capture)
        lp = light_pos[k]
        far_light = f": give it as a directional light, or positions in {unit}"
        r = _distance(lp, "light", fields.light, k, unit, limit, far_light)
        # Irradiance power / r^2 between the nearest possible point (the light's height) and
        # the farthest (a corner): both must be normal float32 numbers.
        with np.errstate(over="ignore", divide="ignore"):
            hi = np.max(light_power[k]) / lp[2] ** 2
            lo = np.min(light_power[k]) / (r + reach) ** 2
        if not (lo >= _F32.tiny and hi <= _F32.max):
            raise _refuse(
                fields.power,
                k,
                f"light power {np.max(light_power[k]):.3g} at {r:.3g} {unit} gives an "
                f"irradiance between {lo:.3g} and {hi:.3g}, outside float32's normal range "
                f"[{_F32.tiny:.3g}, {_F32.max:.3g}]; give the power in the photos' units",
            )
        gap = float(np.linalg.norm(lp - cam))
        if fields.phone and gap > PHONE_SEPARATION * dist:
            far.append((k, gap, dist))
    if far:
        k, gap, dist = far[0]
        path, names = fields.light
        warnings.warn(
            f"{path}: {names[k]}: the flash is {gap:.3g} {unit} from the camera "
            f"({fields.camera[0].name} {fields.camera[1][k]}), {gap / dist:.2f} of the camera's "
            f"distance to the sample ({len(far)} of {camera_pos.shape[0]} photos so); a "
            "phone's flash sits beside its lens. Check that the two files list the same "
            "photos in the same order.",
            CaptureWarning,
            stacklevel=3,
        )


def _names(files: list[Path]) -> str:
    if not files:
        return "the photos"
    return files[0].name if len(files) == 1 else f"{files[0].name} ... {files[-1].name}"


def _no_values(counts: dict[ObsStatus, int], total: int, mask: Path | None) -> str:
    """Why no observation holds a value, and what to change."""
    sat, dark = counts[ObsStatus.SATURATED], counts[ObsStatus.DARK]
    masked = counts[ObsStatus.MASKED]
    if masked == total:
        what = f"the mask {mask.name}" if mask is not None else "the photos' alpha channel"
        return (
            f"{what} excludes every pixel (0 everywhere); non-zero (white, opaque) marks the "
            "pixels to fit"
        )
    if sat + masked == total:
        return (
            f"every observation is saturated ({sat} at the top code): no photo measured a "
            "value; lower the exposure (shorter shutter, lower ISO or a weaker flash)"
        )
    if dark + masked == total:
        return (
            f"every observation is black ({dark} at 0): no photo measured a value; raise the "
            "exposure (longer shutter, higher ISO or a stronger flash)"
        )
    if sat + dark + masked == total:
        return (
            f"every observation is saturated ({sat}) or black ({dark}): no photo measured a "
            "value between; bring the exposure to the middle of the range (photograph the "
            "highlights and the shadows at separate exposures)"
        )
    bad = total - sat - dark - masked
    return (
        f"no observation holds a usable value ({bad} non-finite or negative, {sat} saturated, "
        f"{dark} black, {masked} masked); rewrite the photos as finite values >= 0"
    )


def check_photos(cap: Capture, fields: Fields) -> None:
    """Refuse photos that measured nothing; warn about a photo that is all saturated or all
    black and about photos much darker or brighter than the light power predicts (module
    docstring). ``cap`` as read, before any downsampling."""
    status = cap.status
    total = int(status.size)
    counts = {s: int(np.count_nonzero(status == s)) for s in ObsStatus}
    where = cap.files[0].parent if cap.files else cap.source
    if counts[ObsStatus.OK] == 0:
        raise CaptureError(where, _no_values(counts, total, fields.mask), _names(cap.files))
    for k in range(cap.n_photos):
        st = status[k]
        used = st != ObsStatus.MASKED
        for code, word, fix in (
            (ObsStatus.SATURATED, "saturated", "lower"),
            (ObsStatus.DARK, "black", "raise"),
        ):
            if np.any(used) and np.all(st[used] == code):
                name = cap.files[k].name if cap.files else f"photo {k}"
                warnings.warn(
                    f"{where}: {name}: every pixel is {word}; the photo bounds the radiance "
                    f"but measures none of it ({fix} its exposure)",
                    CaptureWarning,
                    stacklevel=3,
                )
    _check_brightness(cap, fields)


def _check_brightness(cap: Capture, fields: Fields) -> None:
    """Warn where the median measured pixel is far from a white diffuse surface's radiance
    under the stated light power (module docstring)."""
    _k, h, w, _c = cap.shape
    step = max(1, -(-max(h, w) // _CHECK_SIDE))
    sub = replace(
        cap,
        images=cap.images[:, ::step, ::step],
        status=cap.status[:, ::step, ::step],
        points=cap.points[::step, ::step],
    )
    geo = sub.per_pixel_geometry(np.float64)
    # Radiance of albedo 1 (f_r = 1/pi) at every observation.
    white = geo["irradiance"] * geo["cos_i"][..., None] / np.pi
    ok = (sub.status == ObsStatus.OK) & (white > 0)
    if not np.any(ok):
        return
    ratio = float(np.median(sub.images[ok] / white[ok]))
    if DARK_RATIO <= ratio <= BRIGHT_RATIO:
        return
    path, names = fields.power
    how = "darker" if ratio < DARK_RATIO else "brighter"
    warnings.warn(
        f"{path}: {names[0]}: the photos are much {how} than this light power predicts: their "
        f"median measured pixel is {ratio:.3g} times the radiance of a white diffuse surface "
        f"(albedo 1) under it (expected between {DARK_RATIO:g} and {BRIGHT_RATIO:g}); check "
        "the power's unit (the photos' linear units times length^2) and the exposure",
        CaptureWarning,
        stacklevel=3,
    )

"""The flash of a plan where the fit estimated it (``FitJob.light``; :mod:`._light`).

A fit that estimated the light (its report's ``light``: ``mode`` ``offset`` or
``offset+gains``) placed every photo's flash at p_k + R_k d and scaled its intensity by g_k
(:meth:`jaxrefl.svbrdf.LightEstimate.apply`). The plan then uses that light twice:

* the fit's precision is that of the photos as the fit saw them: the capture with the
  estimated light applied (:func:`fit_light`);
* a candidate whose flash is where the capture states it (``Candidates.flash ==
  "stated"``: the hemisphere grid, listed positions without flash positions, the photos of
  a capture) gets the estimated offset too (:func:`place_flash`): the flash of candidate m
  at its stated position + R_m d, R_m the candidate photo's orientation where the capture
  gives it (``calibration.json``'s ``camera_orientation``), else the mean of the fitted
  photos' R_k d (a phone held as for those photos). A new photo's gain is not known before
  it is taken: its intensity is the stated one times the geometric mean of the fitted
  photos' gains (their prior's, 1 without EXIF).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from jaxrefl._errors import JaxreflError

from . import _light_prior
from ._light import LightEstimate

__all__ = ["fit_light", "orientations", "place_flash"]


def orientations(capture) -> np.ndarray | None:
    """(K, 3, 3) camera-to-sample rotations of ``capture``'s photos from its
    ``calibration.json``, or None where it gives none (the offset's frame is then the
    sample's) or the capture has no flash to place."""
    if capture.light_pos is None or capture.source is None:
        return None
    return _light_prior.orientations(capture)


def fit_light(capture_fit, capture) -> Any:
    """The light the fit estimated (its report's ``light``) as a
    :class:`~jaxrefl.svbrdf.LightEstimate` of ``capture``, or None where the fit kept the
    stated light."""
    rep: dict[str, Any] | None = capture_fit.report.get("light")
    if not rep or rep.get("mode", "fixed") == "fixed":
        return None
    offset = np.asarray(rep.get("offset_cm") or (0.0, 0.0, 0.0), np.float64)
    gains = np.asarray(rep.get("photo_gain") or np.ones(capture.n_photos), np.float64)
    if offset.shape != (3,) or gains.shape != (capture.n_photos,):
        raise JaxreflError(
            f"the fit's light has an offset of shape {offset.shape} and {gains.size} photo "
            f"gains; the capture has {capture.n_photos} photos: give the capture it was fitted to"
        )
    rot = orientations(capture) if str(rep.get("frame", "")).startswith("camera") else None
    return LightEstimate(
        mode=str(rep["mode"]),
        asked=str(rep.get("asked", rep["mode"])),
        offset_cm=offset,
        photo_gain=gains,
        frame=str(rep.get("frame", "")),
        rot=rot,
    )


def place_flash(candidates, light, capture, train) -> Any:
    """``candidates`` with the fit's estimated flash (module docstring); unchanged where
    ``light`` (a :class:`~jaxrefl.svbrdf.LightEstimate`) is None or their flash is placed
    already. ``capture``: the fitted one, ``train``: (K,) bool, its training photos."""
    if light is None or candidates.flash != "stated":
        return candidates
    m = len(candidates)
    train = np.asarray(train, bool)
    if candidates.orientation is not None:
        shift = np.einsum("mij,j->mi", candidates.orientation, light.offset_cm)
    else:
        rot = light.rot
        if rot is None:
            mean = light.offset_cm
        else:
            use = train if np.any(train) else np.ones(rot.shape[0], bool)
            mean = np.mean(np.einsum("kij,j->ki", rot[use], light.offset_cm), axis=0)
        shift = np.broadcast_to(mean, (m, 3))
    g = light.photo_gain[train] if np.any(train) else light.photo_gain
    gain = float(np.exp(np.mean(np.log(g))))
    return replace(
        candidates,
        light_pos=candidates.light_pos + shift,
        light_power=candidates.light_power * gain,
        flash="placed",
    )

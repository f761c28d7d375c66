"""A photometric-stereo capture in memory, and the checks every loader applies to it.

Conventions (all of :mod:`jaxrefl.ps`):

* **Camera frame**: x to the right of the image, y up, z towards the camera (viewer); the
  camera is orthographic and looks along -z, so the view direction of every pixel is
  ``wo = (0, 0, 1)``. This is the frame of DiLiGenT (Shi et al. 2019) and of the UW psm
  ``lights.txt`` (checked against the chrome sphere: the highlight moves up the image as
  the light's y grows).
* **Pixels**: arrays are (H, W) with row 0 at the *top*; pixel (row i, column j) sits at
  x = j, y = -i (pixel units). Images flip y, the frame does not.
* **Lights**: unit vectors from the surface towards each distant light, (K, 3), and a
  relative intensity per image and colour channel, (K, C). An image is modelled as

      I_kc(p) = E_kc * rho_c(p) * max(n(p) . l_k, 0)     (Lambertian; rho = albedo / pi)

  so ``rho`` is the albedo *as photometric stereo sees it*, in image units per unit E.
* **Normals**: unit vectors in the camera frame, (H, W, 3), pointing out of the surface
  (n_z > 0 on visible surfaces); NaN outside the mask.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from jaxrefl._errors import JaxreflError

__all__ = ["PSCapture", "PSInputError", "check_lights"]

# A light whose direction is within this angle of the horizon (z = 0) is rejected: it
# grazes every visible surface point and carries almost no shading information.
_MIN_ELEVATION_DEG = 1e-3


class PSInputError(JaxreflError):
    """Bad photometric-stereo input; the message names the file (or argument) and the fix."""

    def __init__(self, where: str | Path | None, problem: str):
        self.where = None if where is None else str(where)
        self.problem = problem
        super().__init__(problem if where is None else f"{where}: {problem}")


def check_lights(
    directions: np.ndarray,
    intensities: np.ndarray | None,
    n_images: int,
    channels: int,
    where: str | Path | None = None,
    intensities_where: str | Path | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Validate light directions (K, 3) and intensities (K, C) or (K,) against K images.

    Errors in the directions name ``where``; errors in the intensities name
    ``intensities_where`` (default ``where``): the file each was read from.

    Returns (unit directions float64 (K, 3), intensities float64 (K, C)). Raises
    :class:`PSInputError` for a count that does not match the images, a zero-length or
    non-finite direction, a direction at or below the horizon (z <= 0: it cannot light a
    surface the camera sees), or a non-positive / non-finite intensity.
    """
    d = np.asarray(directions, np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise PSInputError(where, f"light directions must be K rows of 3 numbers, got {d.shape}")
    if d.shape[0] != n_images:
        raise PSInputError(
            where, f"{d.shape[0]} light directions for {n_images} images; give one per image"
        )
    norm = np.linalg.norm(d, axis=1)
    bad = ~np.isfinite(norm) | (norm <= 1e-12)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise PSInputError(where, f"light {k} (line {k + 1}) has zero length or is not finite")
    d = d / norm[:, None]
    low = d[:, 2] <= np.sin(np.radians(_MIN_ELEVATION_DEG))
    if low.any():
        k = int(np.flatnonzero(low)[0])
        raise PSInputError(
            where,
            f"light {k} (line {k + 1}) points at or below the horizon (z = {d[k, 2]:.3g}); "
            "directions go from the object towards the light with +z towards the camera",
        )
    if intensities is None:
        e = np.ones((n_images, channels))
    else:
        where = where if intensities_where is None else intensities_where
        e = np.asarray(intensities, np.float64)
        if e.ndim == 1:
            e = e[:, None]
        if e.shape[0] != n_images:
            raise PSInputError(
                where, f"{e.shape[0]} light intensities for {n_images} images; give one per image"
            )
        if e.shape[1] == 1:
            e = np.repeat(e, channels, axis=1)
        if e.shape[1] != channels:
            raise PSInputError(where, f"intensities have {e.shape[1]} channels, images {channels}")
        badi = ~np.isfinite(e) | (e <= 0)
        if badi.any():
            k = int(np.flatnonzero(badi.any(axis=1))[0])
            raise PSInputError(where, f"light {k} (line {k + 1}) has a non-positive intensity")
    return d, e


@dataclass(frozen=True, eq=False)
class PSCapture:
    """K images of one object under K distant lights (module docstring for conventions).

    images:      (K, H, W, C) float32 linear values
    lights:      (K, 3) unit directions towards the lights, camera frame
    intensities: (K, C) relative light intensity per image and channel
    mask:        (H, W) bool, the object
    usable:      (K, H, W, C) bool, observations that are neither saturated nor clipped
                 dark (code 0 of an integer image) nor outside the mask
    normals_gt:  (H, W, 3) ground-truth normals or None
    name, root:  for reports; ``files`` the image files in light order
    """

    images: np.ndarray
    lights: np.ndarray
    intensities: np.ndarray
    mask: np.ndarray
    usable: np.ndarray
    normals_gt: np.ndarray | None = None
    name: str = "capture"
    root: Path | None = None
    files: tuple[Path, ...] = field(default=())
    bit_depth: int = 8

    def __post_init__(self):
        k, h, w, c = self.images.shape
        if self.mask.shape != (h, w):
            raise PSInputError(self.root, f"mask is {self.mask.shape}, images are {(h, w)}")
        if not self.mask.any():
            raise PSInputError(self.root, "the mask is empty: no pixel to reconstruct")
        check_lights(self.lights, self.intensities, k, c, self.root)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W)."""
        return tuple(self.images.shape[1:3])

    def with_lights(self, lights: np.ndarray, intensities: np.ndarray | None = None) -> PSCapture:
        """The same capture with other lights (e.g. from a chrome-sphere calibration)."""
        k, _, _, c = self.images.shape
        d, e = check_lights(lights, intensities, k, c, "calibrated lights")
        return replace(self, lights=d, intensities=e)

    def downsample(self, factor: int) -> PSCapture:
        """Every ``factor``-th pixel in both directions (nearest; keeps masks and statuses)."""
        if factor <= 1:
            return self
        s = (slice(None), slice(None, None, factor), slice(None, None, factor))
        gt = None if self.normals_gt is None else self.normals_gt[s[1:]]
        return replace(
            self,
            images=self.images[s],
            mask=self.mask[s[1:]],
            usable=self.usable[s],
            normals_gt=gt,
        )

    def pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """Observations and usable flags of the masked pixels: (N, K, C) each, row-major."""
        obs = np.moveaxis(self.images[:, self.mask], 0, 1)
        ok = np.moveaxis(self.usable[:, self.mask], 0, 1)
        return obs, ok

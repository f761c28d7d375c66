"""Photos to the sample square: undistortion and the plane's homography in one resampling.

For photo k with pose (R, t) and intrinsics K, the sample's plane z = -depth (frame
coordinates, :mod:`jaxrefl.phone._frame`) maps to the undistorted image by the homography

    H = K [r1  r2  t - depth r3],     (u, v, 1)^T ~ H (x, y, 1)^T,

and the lens distortion then moves every undistorted point to where the photo holds it.
Rather than undistort the photo and warp the result (two interpolations), every output
pixel's plane point is carried through both at once (``cv2.projectPoints``: R, t, K and the
distortion) and the photo is sampled there (``cv2.remap``, bilinear).

Output pixel (i, j) of an N x N rectified photo covers the square of side s/N at
x = ((j + 0.5)/N - 0.5) s, y = -((i + 0.5)/N - 0.5) s (:func:`jaxrefl.scene.planar_points`,
s = the sample square's side). Where a photo has more pixels across the square than N the
output would alias, so each output pixel is the mean of m x m bilinear samples spread over
it (m = source pixels per output pixel, rounded up, at most 4): a box filter of the
output pixel's footprint. Interpolation is done on linear values (radiance adds, encoded
values do not). A pixel is ``valid`` when all its samples fall inside the photo, and
``clipped`` (per channel) when any of its samples touches a clipped photo pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._calibrate import Calibration
from ._errors import require_cv2

__all__ = ["Rectified", "image_to_plane", "plane_grid", "rectify", "warp"]

_MAX_SUPERSAMPLE = 4  # samples per output pixel and axis: beyond it the cost grows, not the gain
_ROWS = 64  # output rows resampled at a time (bounds the memory of the sample grid)


@dataclass(frozen=True)
class Rectified:
    """(N, N, C) float32 linear ``image``, (N, N) ``valid``, (N, N, C) ``clipped``."""

    image: np.ndarray
    valid: np.ndarray
    clipped: np.ndarray


def plane_grid(side: float, n: int, z: float, m: int = 1, rows: slice = slice(None)) -> np.ndarray:
    """(n m, n m, 3) points: the centres of an n m x n m grid over the square of ``side``
    centred at the origin at height ``z`` (row 0 at +y); only ``rows`` of it."""
    c = ((np.arange(n * m) + 0.5) / (n * m) - 0.5) * side
    x, y = np.meshgrid(c, -c[rows])
    return np.stack([x, y, np.full_like(x, z)], -1)


def warp(
    image: np.ndarray,
    calibration: Calibration,
    k: int,
    side: float,
    n: int,
    z: float,
    m: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Photo ``k`` resampled on the n x n grid over the square of ``side`` at height ``z``,
    m x m samples averaged per pixel: ((n, n, C) float32, (n, n) all samples inside)."""
    cv2 = require_cv2()
    img = np.asarray(image)
    squeeze = img.ndim == 2
    if squeeze:
        img = img[..., None]
    h, w, c = img.shape
    src = img.astype(np.float32)
    out = np.zeros((n, n, c), np.float32)
    inside = np.zeros((n, n), bool)
    for r0 in range(0, n, _ROWS):
        r1 = min(n, r0 + _ROWS)
        pts = plane_grid(side, n, z, m, slice(r0 * m, r1 * m))
        uv = calibration.project(k, pts).astype(np.float32)
        chans = [cv2.remap(src[..., i], uv[..., 0], uv[..., 1], cv2.INTER_LINEAR) for i in range(c)]
        block = np.stack(chans, -1).reshape(r1 - r0, m, n, m, c).mean((1, 3))
        ok = (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
        out[r0:r1] = block
        inside[r0:r1] = ok.reshape(r1 - r0, m, n, m).all((1, 3))
    return (out[..., 0] if squeeze else out), inside


def supersampling(calibration: Calibration, k: int, side: float, n: int, z: float) -> int:
    """Source pixels per output pixel across the square (its widest projected side), rounded
    up and kept in 1 .. _MAX_SUPERSAMPLE."""
    h = side / 2
    corners = np.array([[-h, h, z], [h, h, z], [h, -h, z], [-h, -h, z]])
    uv = calibration.project(k, corners)
    longest = np.max(np.linalg.norm(uv - np.roll(uv, 1, 0), axis=1))
    return int(np.clip(np.ceil(longest / n), 1, _MAX_SUPERSAMPLE))


def rectify(
    linear: np.ndarray,
    clipped: np.ndarray,
    calibration: Calibration,
    k: int,
    side: float,
    n: int,
    depth: float = 0.0,
) -> Rectified:
    """Photo ``k``'s sample square (module docstring): ``linear`` (H, W, C) values,
    ``clipped`` (H, W, C) bool, the square of ``side`` cm at z = -``depth``, N = ``n``."""
    m = supersampling(calibration, k, side, n, -depth)
    img, valid = warp(linear, calibration, k, side, n, -depth, m)
    clip, _ = warp(np.asarray(clipped, np.float32), calibration, k, side, n, -depth, m)
    return Rectified(img, valid, clip > 0)


def image_to_plane(calibration: Calibration, k: int, uv: np.ndarray, z: float) -> np.ndarray:
    """(..., 2) pixels of photo ``k`` -> (..., 2) (x, y) where their rays meet the plane at
    height ``z`` (frame coordinates)."""
    cv2 = require_cv2()
    uv = np.asarray(uv, np.float64)
    intr, pose = calibration.intrinsics, calibration.poses[k]
    src = uv.reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)  # to convergence
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4: the iterating variant
        ab = cv2.undistortPointsIter(src, intr.camera_matrix, intr.distortion, None, None, crit)
    else:  # OpenCV 5: undistortPoints takes the criteria
        ab = cv2.undistortPoints(src, intr.camera_matrix, intr.distortion, criteria=crit)
    ab = ab.reshape(-1, 2)
    rays = np.concatenate([ab, np.ones((len(ab), 1))], 1) @ pose.rotation()  # R^T (a, b, 1)
    c = pose.position()
    lam = (z - c[2]) / rays[:, 2]
    return (c[None, :2] + lam[:, None] * rays[:, :2]).reshape(*uv.shape[:-1], 2)

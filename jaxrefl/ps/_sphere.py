"""A sphere seen in an image: its circle fitted to a mask, and its normals.

Under orthographic projection a sphere images as a disc; at pixel (row i, column j) inside
the disc of centre (c_row, c_col) and radius r (pixels) its unit normal, in the camera
frame of :mod:`jaxrefl.ps` (x right, y up, z towards the camera), is

    n = (u, v, sqrt(1 - u^2 - v^2)),   u = (j - c_col) / r,   v = -(i - c_row) / r.

The circle is fitted to the mask's boundary pixels (mask pixels with a 4-neighbour outside)
by the algebraic least squares of Kasa (1976), x^2 + y^2 + D x + E y + F = 0, then its
radius is moved out by half a pixel (the boundary pixels' centres lie half a pixel inside
the silhouette). The uncertainty is the Gauss-Newton covariance of the geometric fit,
sigma^2 (J^T J)^-1 with J the Jacobian of the distances |p - c| - r and sigma^2 their mean
square (so it grows with a ragged mask).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._capture import PSInputError

__all__ = ["Circle", "fit_circle", "sphere_normals"]


@dataclass(frozen=True)
class Circle:
    """centre (row, col) and radius in pixels; ``cov`` the 3 x 3 covariance of
    (row, col, radius) in pixels^2."""

    row: float
    col: float
    radius: float
    cov: np.ndarray

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of (row, col, radius) in pixels."""
        return np.sqrt(np.diag(self.cov))


def boundary(mask: np.ndarray) -> np.ndarray:
    """Mask pixels with at least one 4-neighbour outside the mask (or the image)."""
    m = np.pad(mask.astype(bool), 1)
    inner = m[1:-1, 1:-1] & m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:]
    return mask.astype(bool) & ~inner


def fit_circle(mask: np.ndarray, where: str | None = None) -> Circle:
    """The circle of a sphere's mask (module docstring). Raises :class:`PSInputError` for
    an empty mask or one too small (< 8 boundary pixels) to fit."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise PSInputError(where, "the sphere mask is empty")
    rows, cols = np.nonzero(boundary(mask))
    if rows.size < 8:
        raise PSInputError(where, f"the sphere mask has {rows.size} boundary pixels; need >= 8")
    y, x = rows.astype(np.float64), cols.astype(np.float64)
    a = np.stack([x, y, np.ones_like(x)], axis=1)
    d, e, f = np.linalg.lstsq(a, -(x * x + y * y), rcond=None)[0]
    cx, cy = -d / 2, -e / 2
    r_in = np.sqrt(max(cx * cx + cy * cy - f, 0.0))
    dist = np.hypot(x - cx, y - cy)
    res = dist - r_in
    j = np.stack([-(y - cy) / dist, -(x - cx) / dist, -np.ones_like(x)], axis=1)
    sigma2 = float(np.mean(res * res)) + 1.0 / 12.0  # + pixel quantisation variance
    cov = sigma2 * np.linalg.inv(j.T @ j)
    return Circle(float(cy), float(cx), float(r_in + 0.5), cov)


def sphere_normals(shape: tuple[int, int], circle: Circle) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) normals of the sphere and the (H, W) disc where they are defined (NaN
    outside it)."""
    i, j = np.mgrid[: shape[0], : shape[1]].astype(np.float64)
    u = (j - circle.col) / circle.radius
    v = -(i - circle.row) / circle.radius
    s = u * u + v * v
    inside = s < 1.0
    n = np.stack([u, v, np.sqrt(np.where(inside, 1.0 - s, 0.0))], axis=-1)
    return np.where(inside[..., None], n, np.nan), inside

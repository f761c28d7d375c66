"""Angular errors of normal maps: against ground truth, or against the ideal sphere fitted
to a sphere's mask when there is none.

    err(p) = arccos(clip(n(p) . n_gt(p), -1, 1))     in degrees, per pixel

reported as the mean and median over the pixels that have both an estimate and a
reference (the mask, minus pixels without an estimate, which are counted separately): the
statistics of the DiLiGenT benchmark (Shi et al., "A benchmark dataset and evaluation for
non-Lambertian and uncalibrated photometric stereo", TPAMI 2019), which reports the mean.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._sphere import Circle, fit_circle, sphere_normals

__all__ = ["ErrorStats", "angular_error", "error_stats", "sphere_error"]


def angular_error(n: np.ndarray, n_gt: np.ndarray) -> np.ndarray:
    """Per-pixel angle between two (..., 3) normal fields in degrees (NaN where either is
    missing). Both are renormalised first (a decoded 8-bit normal map is not unit length)."""
    n = np.asarray(n, np.float64)
    g = np.asarray(n_gt, np.float64)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    g = g / np.linalg.norm(g, axis=-1, keepdims=True)
    # clip: rounding can push the dot product of two unit vectors just past +-1.
    return np.degrees(np.arccos(np.clip(np.sum(n * g, axis=-1), -1.0, 1.0)))


@dataclass(frozen=True)
class ErrorStats:
    """mean / median / 90th percentile (degrees) over ``n_pixels`` compared pixels;
    ``n_missing`` reference pixels had no estimate."""

    mean: float
    median: float
    p90: float
    n_pixels: int
    n_missing: int

    def to_dict(self) -> dict:
        return {
            "mean_angular_error_deg": self.mean,
            "median_angular_error_deg": self.median,
            "p90_angular_error_deg": self.p90,
            "n_pixels": self.n_pixels,
            "n_missing": self.n_missing,
        }


def error_stats(err: np.ndarray, mask: np.ndarray) -> ErrorStats:
    """Statistics of an error map over ``mask`` (NaN entries are counted as missing)."""
    e = np.asarray(err)[np.asarray(mask, bool)]
    ok = np.isfinite(e)
    if not ok.any():
        nan = float("nan")
        return ErrorStats(nan, nan, nan, 0, int(e.size))
    v = e[ok]
    return ErrorStats(
        float(v.mean()),
        float(np.median(v)),
        float(np.percentile(v, 90)),
        int(v.size),
        int((~ok).sum()),
    )


def sphere_error(
    normals: np.ndarray, mask: np.ndarray, margin: float = 0.0, circle: Circle | None = None
) -> tuple[np.ndarray, ErrorStats, Circle]:
    """Error of an (H, W, 3) normal map of a sphere against the ideal sphere fitted to its
    ``mask`` (:func:`jaxrefl.ps.fit_circle`): (error map, statistics, circle). ``margin``
    (pixels) leaves out a rim of the disc, where the fitted normals are most sensitive to
    the circle (dn/dr grows without bound at the silhouette)."""
    circle = fit_circle(mask) if circle is None else circle
    gt, inside = sphere_normals(mask.shape, circle)
    i, j = np.mgrid[: mask.shape[0], : mask.shape[1]]
    dist = np.hypot(i - circle.row, j - circle.col)
    region = np.asarray(mask, bool) & inside & (dist <= circle.radius - margin)
    err = np.where(region, angular_error(normals, gt), np.nan)
    return err, error_stats(np.where(region, err, np.nan), region), circle

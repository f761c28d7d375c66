"""Tag corners from the four outer edges of the black ring, located in linear intensity.

ArUco's corners lie on the thresholded outline of the black ring: the centres of its
boundary pixels, about half a pixel inside the true edge, and with the threshold applied to
gamma-encoded values the step between ink and paper is met nearer the dark side. Both pull
each corner towards its tag's centre, so every tag looks smaller than it is (0.4-1.1 pixel
per corner on rendered photos: ``benchmarks/marker_detection.py``), which a rigid frame
cannot explain and calibration turns into reprojection error.

:func:`refine_corners` starts from the detector's corners. Along each side of the ring it
reads intensity profiles across the edge (bilinear samples of *linear* intensity, from 0.7
cell inside to 0.7 cell outside, one profile per pixel of the side's middle 70 %), takes
the ink level (the profile's minimum inside) and the paper level (its median beyond
0.3 cell outside), and finds where the profile first rises through their mean: with
linear values and a symmetric blur that is where the edge lies. A straight line fitted to
these points (total least squares) stands for the side; adjacent sides intersect at the
corners. A tag is left as detected (``ok`` False) where a side has too little contrast or
too few crossings.
"""

from __future__ import annotations

import numpy as np

__all__ = ["refine_corners"]

_INSIDE, _OUTSIDE = 0.7, 0.7  # profile extent across the edge, in cells
_MIN_CONTRAST = 0.02  # paper minus ink, linear units: below it the side is not seen


def _line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(point, unit direction) of the total-least-squares line through (m, 2) points."""
    c = points.mean(0)
    _, _, vt = np.linalg.svd(points - c)
    return c, vt[0]


def _intersect(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]):
    (p, d), (q, e) = a, b
    m = np.array([d, -e]).T
    t = np.linalg.solve(m, q - p)
    return p + t[0] * d


def refine_corners(linear: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners of each tag from its ring's edges (module docstring).

    Args:
        linear: (H, W) linear intensity (any scale).
        corners: (n, 4, 2) detected corners, pixels (x, y), in order around the tag.

    Returns:
        (n, 4, 2) refined corners and (n,) bool: refined (True) or left as given.
    """
    from scipy.ndimage import map_coordinates

    img = np.asarray(linear, np.float64)
    out = np.array(corners, np.float64, copy=True)
    ok = np.zeros(len(out), bool)
    for n, quad in enumerate(out):
        centre = quad.mean(0)
        cell = np.mean(np.linalg.norm(quad - np.roll(quad, -1, 0), axis=1)) / 8.0
        lines = []
        for k in range(4):
            p0, p1 = quad[k], quad[(k + 1) % 4]
            length = np.linalg.norm(p1 - p0)
            along = (p1 - p0) / length
            normal = np.array([-along[1], along[0]])
            if normal @ ((p0 + p1) / 2 - centre) < 0:
                normal = -normal  # outwards
            t = np.linspace(0.15, 0.85, max(8, int(0.7 * length)))
            s = np.linspace(-_INSIDE * cell, _OUTSIDE * cell, max(15, int(14 * cell)))
            pts = p0 + t[:, None, None] * (p1 - p0) + s[None, :, None] * normal
            prof = map_coordinates(img, [pts[..., 1], pts[..., 0]], order=1, mode="nearest")
            ink = prof[:, s < 0].min(1)
            paper = np.median(prof[:, s > 0.3 * cell], axis=1)
            level = (ink + paper) / 2
            good = paper - ink > _MIN_CONTRAST * max(float(np.max(paper)), 1e-12)
            j0 = int(np.searchsorted(s, -0.5 * cell))  # start half a cell inside the edge
            above = prof[:, j0:] >= level[:, None]
            first = np.argmax(above, 1)  # first sample at or above the mid level
            valid = good & (first > 0) & above[np.arange(len(t)), first]
            i = first[valid] + j0
            rows = np.flatnonzero(valid)
            y0, y1 = prof[rows, i - 1], prof[rows, i]
            frac = (level[valid] - y0) / np.where(y1 > y0, y1 - y0, 1.0)
            s_hit = s[i - 1] + np.clip(frac, 0, 1) * (s[1] - s[0])
            if valid.sum() < 4:
                break
            hits = p0 + t[valid, None] * (p1 - p0) + s_hit[:, None] * normal
            lines.append(_line(hits))
        if len(lines) < 4:
            continue
        try:
            quad_new = np.array([_intersect(lines[(k - 1) % 4], lines[k]) for k in range(4)])
        except np.linalg.LinAlgError:
            continue
        if np.all(np.linalg.norm(quad_new - quad, axis=1) < cell):  # a corner moves < 1 cell
            out[n], ok[n] = quad_new, True
    return out, ok

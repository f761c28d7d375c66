"""A picture per photo to check the detection before fitting.

The photo is resampled onto the marker plane (z = 0) over the frame and one tag's width
around it (:func:`jaxrefl.phone._rectify.warp`), so the tags stand square as printed.
Drawn on it: each layout corner where the calibrated camera puts it (the reprojected
corner: a green circle), each detected corner carried back to the plane through the same
camera (a red cross), the residual between them magnified RESIDUAL_SCALE times (a red
line), the outline of the sample square at its depth as the photo sees it (yellow), and
the photo's name, tag count and reprojection error. A tag whose cross sits off its circle,
or a long line, marks a bad detection.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._calibrate import Calibration
from ._detect import Detection
from ._errors import require_cv2
from ._frame import FrameLayout
from ._rectify import image_to_plane, warp

__all__ = ["RESIDUAL_SCALE", "write_preview"]

RESIDUAL_SCALE = 20.0  # residuals are a pixel or less: drawn this many times longer


def write_preview(
    path: str | Path,
    photo: np.ndarray,
    detection: Detection,
    calibration: Calibration,
    k: int,
    layout: FrameLayout,
    *,
    depth: float = 0.0,
    size: int = 512,
    label: str = "",
) -> Path:
    """Write the preview of photo ``k`` (``photo``: its (H, W, 3) uint8 pixels) to ``path``."""
    cv2 = require_cv2()
    extent = layout.side + 2 * layout.tag_size
    view, _ = warp(photo, calibration, k, extent, size, 0.0)
    img = np.ascontiguousarray(np.clip(view, 0, 255).astype(np.uint8)[..., ::-1])  # BGR

    def px(xy: np.ndarray) -> np.ndarray:  # plane (x, y) -> preview pixel
        return np.stack(
            [(xy[..., 0] / extent + 0.5) * size - 0.5, (0.5 - xy[..., 1] / extent) * size - 0.5],
            -1,
        )

    shift = 4  # cv2 drawing with 4 fractional bits: sub-pixel positions
    one = 1 << shift

    def pt(p: np.ndarray) -> tuple[int, int]:
        return round(float(p[0]) * one), round(float(p[1]) * one)

    sample = image_to_plane(
        calibration, k, calibration.project(k, layout.sample_corners(depth)), 0.0
    )
    cv2.polylines(
        img,
        [np.round(px(sample) * one).astype(np.int32)],
        True,
        (0, 220, 255),
        1,
        cv2.LINE_AA,
        shift,
    )
    truth = px(layout.corners()[detection.ids][..., :2]).reshape(-1, 2)
    found = px(image_to_plane(calibration, k, detection.corners, 0.0)).reshape(-1, 2)
    for t, f in zip(truth, found, strict=True):
        cv2.circle(img, pt(t), 4 * one, (0, 200, 0), 1, cv2.LINE_AA, shift)
        cv2.line(img, pt(t), pt(t + RESIDUAL_SCALE * (f - t)), (0, 0, 255), 1, cv2.LINE_AA, shift)
        cv2.drawMarker(
            img, (round(float(f[0])), round(float(f[1]))), (0, 0, 255), cv2.MARKER_CROSS, 7, 1
        )
    text = (
        f"{label} {detection.count} tags, reprojection {calibration.errors[k]:.2f} px; "
        f"o reprojected  + detected  - residual x{RESIDUAL_SCALE:g}"
    )
    cv2.putText(img, text, (6, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (40, 40, 40), 1, cv2.LINE_AA)
    path = Path(path)
    cv2.imwrite(str(path), img)
    return path

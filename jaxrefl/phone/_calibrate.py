"""The camera from the tags: intrinsics and lens distortion over all photos, a pose per photo.

Model (OpenCV's pinhole camera): a frame point X (cm, :mod:`jaxrefl.phone._frame`) goes to
camera coordinates x_c = R X + t (x right, y down, z forward, along the optical axis), to
a = x/z, b = y/z, to the distorted d(a, b) with d = 1 + k1 r^2 + k2 r^4 + k3 r^6 (r^2 = a^2
+ b^2; tangential terms p1, p2 as OpenCV's), and to pixels u = fx a' + cx, v = fy b' + cy.

:func:`calibrate` runs ``cv2.calibrateCamera`` over the photos' tag corners (Zhang 2000:
planar targets in several poses). Phone lenses are nearly free of tangential distortion and
have square pixels, and a few views of a plane pin down few distortion terms, so by default
p1 = p2 = k3 = 0 and fx = fy (:class:`CalibrationOptions`). :func:`locate` instead takes
known intrinsics (``--intrinsics``: a camera calibrated once, e.g. the ``intrinsics`` block
of an earlier capture's ``calibration.json``) and solves each photo's pose alone
(``cv2.solvePnP``).

The reprojection error of a photo is the root mean square, over its detected corners, of
the distance in pixels between the detected corner and the model's projection of the
layout's corner.

Camera position C = -R^T t (frame coordinates); its orientation is R^T, whose columns are
the camera's x (right), y (down) and z (forward) axes in the frame's coordinates.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ._detect import Detection
from ._errors import PhoneCaptureError, require_cv2
from ._frame import FrameLayout

__all__ = ["Calibration", "CalibrationOptions", "Intrinsics", "Pose", "calibrate", "locate"]


@dataclass(frozen=True)
class Intrinsics:
    """``camera_matrix`` (3, 3), ``distortion`` (OpenCV's k1, k2, p1, p2[, k3 ...]) and
    the ``image_size`` (width, height) in pixels they hold for."""

    camera_matrix: np.ndarray
    distortion: np.ndarray
    image_size: tuple[int, int]

    def to_json(self) -> dict[str, Any]:
        return {
            "camera_matrix": np.asarray(self.camera_matrix).tolist(),
            "distortion": np.asarray(self.distortion).ravel().tolist(),
            "distortion_model": "opencv k1, k2, p1, p2, k3",
            "image_size": list(self.image_size),
        }

    @classmethod
    def from_json(cls, data: dict, where: str = "intrinsics") -> Intrinsics:
        try:
            k = np.asarray(data["camera_matrix"], np.float64)
            d = np.asarray(data["distortion"], np.float64).ravel()
            size = tuple(int(v) for v in data["image_size"])
        except (KeyError, TypeError, ValueError) as e:
            raise PhoneCaptureError(
                f"{where}: expected camera_matrix (3 x 3), distortion (4, 5, 8, 12 or 14 "
                f"numbers) and image_size [width, height]: {e}"
            ) from None
        if k.shape != (3, 3) or d.size not in (4, 5, 8, 12, 14) or len(size) != 2:
            raise PhoneCaptureError(
                f"{where}: camera_matrix {k.shape}, distortion of {d.size} numbers, "
                f"image_size {list(size)}: expected 3 x 3, 4/5/8/12/14 and [width, height]"
            )
        if not (np.all(np.isfinite(k)) and np.all(np.isfinite(d)) and k[0, 0] > 0 < k[1, 1]):
            raise PhoneCaptureError(f"{where}: non-finite values or a focal length <= 0")
        return cls(k, d, (size[0], size[1]))

    @classmethod
    def read(cls, path: str | Path) -> Intrinsics:
        """From a JSON file: the fields of :meth:`to_json`, at the top or under
        ``intrinsics`` (a ``calibration.json`` written by ``jaxrefl capture``)."""
        path = Path(path)
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise PhoneCaptureError(f"{path}: intrinsics file not found") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise PhoneCaptureError(f"{path}: not a JSON file: {e}") from None
        if isinstance(data, dict) and isinstance(data.get("intrinsics"), dict):
            data = data["intrinsics"]
        if not isinstance(data, dict):
            raise PhoneCaptureError(f"{path}: expected a JSON object")
        return cls.from_json(data, str(path))


@dataclass(frozen=True)
class Pose:
    """Frame to camera: x_c = R X + t, R from the Rodrigues vector ``rvec``."""

    rvec: np.ndarray
    tvec: np.ndarray

    def rotation(self) -> np.ndarray:
        """R (3, 3), frame to camera."""
        return require_cv2().Rodrigues(np.asarray(self.rvec, np.float64))[0]

    def position(self) -> np.ndarray:
        """The camera centre C = -R^T t, frame coordinates (cm)."""
        return -self.rotation().T @ np.asarray(self.tvec, np.float64).ravel()

    def orientation(self) -> np.ndarray:
        """R^T: columns are the camera's x (right), y (down), z (forward) axes."""
        return self.rotation().T


@dataclass(frozen=True)
class CalibrationOptions:
    """Which intrinsics ``cv2.calibrateCamera`` estimates (module docstring)."""

    tangential: bool = False  # estimate p1, p2
    k3: bool = False  # estimate k3
    square_pixels: bool = True  # fx = fy

    def flags(self) -> int:
        cv2 = require_cv2()
        f = 0
        if not self.tangential:
            f |= cv2.CALIB_ZERO_TANGENT_DIST
        if not self.k3:
            f |= cv2.CALIB_FIX_K3
        if self.square_pixels:
            f |= cv2.CALIB_FIX_ASPECT_RATIO
        return f


@dataclass(frozen=True)
class Calibration:
    """The camera over K photos: ``intrinsics``, one :class:`Pose` and reprojection
    error (pixels, RMS) per photo, and whether the intrinsics were ``estimated`` here."""

    intrinsics: Intrinsics
    poses: tuple[Pose, ...]
    errors: np.ndarray
    estimated: bool

    def residuals(self, k: int, detection: Detection, layout: FrameLayout) -> np.ndarray:
        """(n, 4, 2) detected minus reprojected corners of photo ``k``, pixels."""
        return detection.corners - self.project(k, layout.corners()[detection.ids])

    def project(self, k: int, points: np.ndarray) -> np.ndarray:
        """(..., 3) frame points -> (..., 2) pixels of photo ``k`` (with distortion)."""
        cv2 = require_cv2()
        pts = np.asarray(points, np.float64)
        uv, _ = cv2.projectPoints(
            pts.reshape(-1, 1, 3),
            self.poses[k].rvec,
            self.poses[k].tvec,
            self.intrinsics.camera_matrix,
            self.intrinsics.distortion,
        )
        return uv.reshape(*pts.shape[:-1], 2)


def _errors(
    detections: list[Detection], layout: FrameLayout, intr: Intrinsics, poses: list[Pose]
) -> np.ndarray:
    cal = Calibration(intr, tuple(poses), np.zeros(len(poses)), False)
    return np.array(
        [
            float(np.sqrt(np.mean(np.sum(cal.residuals(k, d, layout) ** 2, -1))))
            for k, d in enumerate(detections)
        ]
    )


def calibrate(
    detections: list[Detection],
    layout: FrameLayout,
    options: CalibrationOptions = CalibrationOptions(),
) -> Calibration:
    """Intrinsics, distortion and poses from the tags of K >= 3 photos of one size."""
    cv2 = require_cv2()
    if len(detections) < 3:
        raise PhoneCaptureError(f"calibration needs 3 photos or more, got {len(detections)}")
    size = detections[0].image_size
    obj = [d.object_points(layout) for d in detections]
    img = [d.image_points() for d in detections]
    _, k, dist, rvecs, tvecs = cv2.calibrateCamera(
        obj, img, size, np.eye(3), np.zeros(5), flags=options.flags()
    )
    intr = Intrinsics(np.asarray(k, np.float64), np.asarray(dist, np.float64).ravel(), size)
    poses = [Pose(np.ravel(r), np.ravel(t)) for r, t in zip(rvecs, tvecs, strict=True)]
    return Calibration(intr, tuple(poses), _errors(detections, layout, intr, poses), True)


def locate(detections: list[Detection], layout: FrameLayout, intrinsics: Intrinsics) -> Calibration:
    """Poses of photos taken with a camera of known ``intrinsics`` (``cv2.solvePnP``)."""
    cv2 = require_cv2()
    poses = []
    for d in detections:
        if d.image_size != intrinsics.image_size:
            raise PhoneCaptureError(
                f"the intrinsics are for {intrinsics.image_size[0]}x{intrinsics.image_size[1]} "
                f"photos, these are {d.image_size[0]}x{d.image_size[1]}"
            )
        ok, r, t = cv2.solvePnP(
            d.object_points(layout),
            d.image_points(),
            intrinsics.camera_matrix,
            intrinsics.distortion,
            flags=cv2.SOLVEPNP_IPPE,  # planar target: both solutions, the better one kept
        )
        if not ok:
            raise PhoneCaptureError("cv2.solvePnP found no pose")
        r, t = cv2.solvePnPRefineLM(
            d.object_points(layout),
            d.image_points(),
            intrinsics.camera_matrix,
            intrinsics.distortion,
            r,
            t,
        )
        poses.append(Pose(np.ravel(r), np.ravel(t)))
    return Calibration(
        intrinsics, tuple(poses), _errors(detections, layout, intrinsics, poses), False
    )

"""The phone pipeline's error and its one optional dependency, OpenCV.

:class:`PhoneCaptureError` is the :class:`jaxrefl.JaxreflError` of this package: a photo
folder that cannot become a capture (too few usable photos, photos of different sizes, a
calibration whose reprojection error says the frame does not match its layout, an output
folder in the way). Every message names the file or the argument at fault.

OpenCV (``cv2``: ArUco marker detection, camera calibration, resampling) is the extra
``jaxrefl[capture]``; :func:`require_cv2` imports it on first use, so ``import
jaxrefl.phone`` and ``jaxrefl frame`` work without it.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from jaxrefl._errors import JaxreflError

__all__ = ["PhoneCaptureError", "require_cv2"]

INSTALL_HINT = "pip install 'jaxrefl[capture]'"


class PhoneCaptureError(JaxreflError):
    """Phone photos that cannot become a capture (module docstring)."""


def require_cv2() -> ModuleType:
    """The ``cv2`` module, or a :class:`PhoneCaptureError` saying how to install it."""
    try:
        cv2 = importlib.import_module("cv2")
    except ImportError:
        raise PhoneCaptureError(
            f"marker detection and camera calibration need OpenCV: {INSTALL_HINT}"
        ) from None
    if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, "ArucoDetector"):
        raise PhoneCaptureError(
            f"OpenCV {getattr(cv2, '__version__', '?')} has no cv2.aruco.ArucoDetector "
            f"(OpenCV >= 4.8 needed): {INSTALL_HINT}"
        )
    return cv2

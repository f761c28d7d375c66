"""The project's exception family.

Every error jaxrefl raises about its input derives from :class:`JaxreflError` (itself a
``ValueError``, so ``except ValueError`` keeps working): one ``except`` catches them all, and
each message names the file, field or argument at fault and what would be valid.

=====================================  ==================================================
:class:`jaxrefl.io.CaptureError`       flash captures: folders, JSON, text files, photos
:class:`jaxrefl.io.PNGError`           PNG files the reader cannot decode
:class:`jaxrefl.io.ExrFormatError`     OpenEXR files
:class:`jaxrefl.io.MeasuredDataError`  measured BRDF files (Cornell, CURET, MERL)
:class:`jaxrefl.ps.PSInputError`       photometric-stereo images, lights and arguments
:class:`jaxrefl.phone.PhoneCaptureError`  phone photos to a capture: markers, calibration,
                                       photo sizes, OpenCV missing
=====================================  ==================================================

Argument checks of option objects, parameter spaces, fitters and samplers raise
:class:`JaxreflError` itself. What is merely odd about a capture (a flash far from its
camera, photos much darker than the stated power predicts) is a warning,
:class:`jaxrefl.io.CaptureWarning`, not an error.
"""

from __future__ import annotations

__all__ = ["JaxreflError"]


class JaxreflError(ValueError):
    """Base of every input error jaxrefl raises (module docstring)."""

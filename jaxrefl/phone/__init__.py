"""From a phone's photos of a sample in a printed marker frame to a capture.

* The frame: :class:`FrameLayout` (16 AprilTag 36h11 tags, ids 0-15, in a ring; the
  layout of svbrdf-diff-renderer's ``src/capture.py``), :func:`write_frame_sheet` (a
  printable PDF or PNG page at true size with a scale bar).
* Tags in a photo: :func:`detect_markers` (OpenCV's ArUco detector, corners refined on the
  ring's edges in linear intensity: :class:`DetectorOptions`, :class:`Refinement`).
* The camera: :func:`calibrate` (intrinsics and distortion over the photos, a
  :class:`Pose` per photo), :func:`locate` (poses with known :class:`Intrinsics`).
* The sample square: :func:`rectify` (undistortion and homography in one resampling).
* Metadata: :func:`read_photo_meta` (:class:`PhotoMeta`: exposure, ISO, aperture,
  orientation, transfer curve).
* All of it: :func:`photos_to_capture` with :class:`CaptureOptions` writes a capture that
  :func:`jaxrefl.io.load_capture` reads, a ``calibration.json`` record and previews
  (``jaxrefl capture``); :class:`PhoneCaptureError` for what cannot be made into one.
* Tests and benchmarks: :func:`render_photo` (rendered phone photos with known cameras),
  :class:`PhoneCamera`, :func:`write_jpeg`.

OpenCV is the optional extra ``jaxrefl[capture]``, imported on first use.
"""

from ._calibrate import Calibration as Calibration
from ._calibrate import CalibrationOptions as CalibrationOptions
from ._calibrate import Intrinsics as Intrinsics
from ._calibrate import Pose as Pose
from ._calibrate import calibrate as calibrate
from ._calibrate import locate as locate
from ._capture import CaptureOptions as CaptureOptions
from ._capture import PhoneCapture as PhoneCapture
from ._capture import list_photos as list_photos
from ._capture import photos_to_capture as photos_to_capture
from ._detect import Detection as Detection
from ._detect import DetectorOptions as DetectorOptions
from ._detect import Refinement as Refinement
from ._detect import detect_markers as detect_markers
from ._edges import refine_corners as refine_corners
from ._errors import PhoneCaptureError as PhoneCaptureError
from ._exif import PhotoMeta as PhotoMeta
from ._exif import read_photo_meta as read_photo_meta
from ._frame import SAMPLE_FRACTION as SAMPLE_FRACTION
from ._frame import TAG_FAMILY as TAG_FAMILY
from ._frame import TAG_IDS as TAG_IDS
from ._frame import FrameLayout as FrameLayout
from ._rectify import Rectified as Rectified
from ._rectify import rectify as rectify
from ._sheet import write_frame_sheet as write_frame_sheet
from ._synthetic import PhoneCamera as PhoneCamera
from ._synthetic import SyntheticSample as SyntheticSample
from ._synthetic import corner_pixels as corner_pixels
from ._synthetic import default_sample as default_sample
from ._synthetic import render_photo as render_photo
from ._synthetic import render_sample as render_sample
from ._synthetic import write_jpeg as write_jpeg
from ._tags import tag_cells as tag_cells

__all__ = [
    "SAMPLE_FRACTION",
    "TAG_FAMILY",
    "TAG_IDS",
    "Calibration",
    "CalibrationOptions",
    "CaptureOptions",
    "Detection",
    "DetectorOptions",
    "FrameLayout",
    "Intrinsics",
    "PhoneCamera",
    "PhoneCapture",
    "PhoneCaptureError",
    "PhotoMeta",
    "Pose",
    "Rectified",
    "Refinement",
    "SyntheticSample",
    "calibrate",
    "default_sample",
    "detect_markers",
    "list_photos",
    "locate",
    "photos_to_capture",
    "read_photo_meta",
    "rectify",
    "render_photo",
    "render_sample",
    "write_frame_sheet",
    "write_jpeg",
]

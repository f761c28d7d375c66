"""Finding the frame's tags in a photo: OpenCV's ArUco detector with the AprilTag 36h11
dictionary, corners in the layout's order.

:func:`detect_markers` runs ``cv2.aruco.ArucoDetector`` (``DICT_APRILTAG_36h11``) on an
8-bit grey image and keeps the frame's ids 0-15. Each kept tag's four corners are pixel
positions (x to the right, y down, the centre of pixel (row i, column j) at (j, i): OpenCV's
convention), listed top-left, top-right, bottom-right, bottom-left *as printed*
(:class:`~jaxrefl.phone.FrameLayout`), whatever the tag's rotation in the photo.

OpenCV numbers a marker's corners from the top-left of its own drawing of the marker, and
that drawing is the AprilTag one turned by 180 degrees in some versions
(:mod:`jaxrefl.phone._tags`); :func:`corner_order` therefore detects one upright tag drawn
by :func:`~jaxrefl.phone._tags.tag_cells` once per process and maps OpenCV's corner
numbers onto the printed ones.

Corner refinement is an option (:class:`Refinement`): one of OpenCV's four
(``CORNER_REFINE_*``), or ``EDGES``: OpenCV's unrefined corners, then the ring's four edges
located in linear intensity and intersected (:mod:`jaxrefl.phone._edges`). The default is
the one with the smallest corner error on rendered photos of the frame, measured by
``benchmarks/marker_detection.py`` (table in ``docs/benchmarks.md``): ``EDGES``; OpenCV's
own refinements leave every tag too small by about half a pixel per corner.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from ._edges import refine_corners
from ._errors import PhoneCaptureError, require_cv2
from ._frame import TAG_IDS, FrameLayout
from ._tags import tag_cells

__all__ = ["Detection", "DetectorOptions", "Refinement", "corner_order", "detect_markers"]


class Refinement(enum.Enum):
    """Corner refinement (module docstring)."""

    NONE = "none"  # OpenCV: the corners of the fitted quadrilateral
    SUBPIX = "subpix"  # OpenCV: cv2.cornerSubPix on each corner
    CONTOUR = "contour"  # OpenCV: lines fitted to the contour's pixels, intersected
    APRILTAG = "apriltag"  # OpenCV: the AprilTag library's edge refinement
    EDGES = "edges"  # NONE, then jaxrefl.phone._edges.refine_corners in linear intensity

    @property
    def opencv_code(self) -> int:
        """OpenCV's ``CORNER_REFINE_*`` value run by the detector."""
        return {"none": 0, "subpix": 1, "contour": 2, "apriltag": 3, "edges": 0}[self.value]


@dataclass(frozen=True)
class DetectorOptions:
    """How tags are found: the corner ``refinement`` and the fewest tags (``min_markers``)
    a photo needs to be used (4 tags give 16 corners: a pose and a share of the
    intrinsics)."""

    # Smallest corner error on rendered frames (benchmarks/marker_detection.py).
    refinement: Refinement = Refinement.EDGES
    min_markers: int = 4

    def __post_init__(self):
        if not isinstance(self.refinement, Refinement):
            raise PhoneCaptureError(
                f"refinement must be a Refinement, got {self.refinement!r}; one of "
                f"{[r.name for r in Refinement]}"
            )
        if not 1 <= self.min_markers <= len(TAG_IDS):
            raise PhoneCaptureError(
                f"min_markers must be in 1..{len(TAG_IDS)}, got {self.min_markers}"
            )


@dataclass(frozen=True)
class Detection:
    """The frame's tags found in one photo: ``ids`` (n,) ascending, ``corners`` (n, 4, 2)
    pixels in the layout's corner order; ``other_ids``: decoded tags that are not the
    frame's; ``candidates``: square outlines that decoded to no tag."""

    ids: np.ndarray
    corners: np.ndarray
    other_ids: tuple[int, ...] = ()
    candidates: int = 0
    image_size: tuple[int, int] = field(default=(0, 0))  # (width, height)

    @property
    def count(self) -> int:
        return int(self.ids.size)

    def object_points(self, layout: FrameLayout) -> np.ndarray:
        """(4n, 3) float32 corners on the marker plane (z = 0), cm, matching
        :meth:`image_points`."""
        return layout.corners()[self.ids].reshape(-1, 3).astype(np.float32)

    def image_points(self) -> np.ndarray:
        """(4n, 2) float32 detected corners, pixels."""
        return self.corners.reshape(-1, 2).astype(np.float32)

    def describe(self) -> str:
        """What was found, in words: ``5 of 16 tags (ids 0, 1, 2, 14, 15)``."""
        ids = ", ".join(str(int(i)) for i in self.ids) or "none"
        text = f"{self.count} of {len(TAG_IDS)} tags (ids {ids})"
        if self.other_ids:
            text += f", other tag36h11 ids {list(self.other_ids)}"
        if self.candidates:
            text += f", {self.candidates} undecoded square outlines"
        return text


def _detector(refinement: Refinement):
    cv2 = require_cv2()
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = refinement.opencv_code
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    return cv2.aruco.ArucoDetector(dictionary, params)


@lru_cache(maxsize=1)
def corner_order() -> tuple[int, int, int, int]:
    """For the printed corners TL, TR, BR, BL, the index of each in OpenCV's corner list
    (module docstring): found by detecting one upright tag drawn at 20 pixels per cell."""
    cell, margin = 20, 2
    img = np.full(((8 + 2 * margin) * cell,) * 2, 255, np.uint8)
    tag = np.kron(tag_cells(0).astype(np.uint8) * 255, np.ones((cell, cell), np.uint8))
    img[margin * cell : (margin + 8) * cell, margin * cell : (margin + 8) * cell] = tag
    corners, ids, _ = _detector(Refinement.NONE).detectMarkers(img)
    if ids is None or 0 not in ids.ravel():
        raise PhoneCaptureError(
            "this OpenCV's DICT_APRILTAG_36h11 does not decode an upright tag36h11 marker"
        )
    found = np.asarray(corners[int(np.flatnonzero(ids.ravel() == 0)[0])]).reshape(4, 2)
    lo, hi = margin * cell - 0.5, (margin + 8) * cell - 0.5  # outer edges of the black ring
    printed = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]])
    order = tuple(int(np.argmin(np.linalg.norm(found - p, axis=1))) for p in printed)
    if sorted(order) != [0, 1, 2, 3]:
        raise PhoneCaptureError(f"cannot match OpenCV's tag corners {found.tolist()} to a tag")
    return order  # type: ignore[return-value]


def detect_markers(
    gray: np.ndarray,
    options: DetectorOptions = DetectorOptions(),
    linear: np.ndarray | None = None,
) -> Detection:
    """The frame's tags in ``gray``, an (H, W) uint8 image (module docstring); ``linear``:
    its (H, W) linear intensity for ``Refinement.EDGES`` (default: ``gray`` decoded as
    sRGB)."""
    gray = np.asarray(gray)
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise PhoneCaptureError(f"detect_markers needs an (H, W) uint8 image, got {gray.shape}")
    corners, ids, rejected = _detector(options.refinement).detectMarkers(gray)
    order = list(corner_order())
    found: dict[int, np.ndarray] = {}
    other: list[int] = []
    for c, i in zip(corners, [] if ids is None else ids.ravel(), strict=True):
        i = int(i)
        if i in TAG_IDS and i not in found:
            found[i] = np.asarray(c, np.float64).reshape(4, 2)[order]
        elif i not in TAG_IDS:
            other.append(i)
    keys = sorted(found)
    if options.refinement is Refinement.EDGES and keys:
        if linear is None:
            from jaxrefl.scene import SRGBResponse

            linear = np.asarray(SRGBResponse().invert(gray / 255.0))
        refined, _ = refine_corners(linear, np.stack([found[k] for k in keys]))
        found = dict(zip(keys, refined, strict=True))
    return Detection(
        ids=np.array(keys, int),
        corners=np.stack([found[k] for k in keys]) if keys else np.zeros((0, 4, 2)),
        other_ids=tuple(sorted(set(other))),
        candidates=len(rejected),
        image_size=(int(gray.shape[1]), int(gray.shape[0])),
    )

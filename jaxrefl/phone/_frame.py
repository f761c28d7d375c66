"""The printed marker frame: where each AprilTag and the sample square lie, in cm.

The layout is svbrdf-diff-renderer's (Guo, ``tflsguoyu/svbrdf-diff-renderer``,
``src/capture.py``), so a frame printed for that tool works here and the other way round.
Frame coordinates: origin at the centre of the frame, x to the right of the printed page,
y to its top, z out of the paper (towards the camera); lengths in cm.

With ``side`` S the distance between the outer edges of opposite tags, one layout unit is
u = S / 18. Sixteen upright tags of side 2u (their black ring) sit on a 5 x 5 grid of
centres at x, y in {-8u, -4u, 0, 4u, 8u}, the ring of the grid only, numbered clockwise
from the top-left one:

    ids 0-4    top row,      y = +8u, x = -8u ... +8u
    ids 5-7    right column, x = +8u, y = +4u, 0, -4u
    ids 8-12   bottom row,   y = -8u, x = +8u ... -8u
    ids 13-15  left column,  x = -8u, y = -4u, 0, +4u

so white gaps of 2u lie between tags, and the free square inside the ring is 14u = 7S/9
wide. Corners of each tag are listed top-left, top-right, bottom-right, bottom-left (as
printed: clockwise on the page).

The *sample square* is the central SAMPLE_FRACTION x S square: svbrdf-diff-renderer
rectifies the whole frame to 1600 pixels and keeps the central 1024 (0.64 S, about 1.8u
clear of the tags' inner edges). Its pixel (i, j) of an N x N photo lies at
x = ((j + 0.5)/N - 0.5) s, y = -((i + 0.5)/N - 0.5) s with s = 0.64 S
(:func:`jaxrefl.scene.planar_points`), on the sample's surface: at z = -depth when the
sample lies ``depth`` cm below the marker plane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ._errors import PhoneCaptureError

__all__ = ["SAMPLE_FRACTION", "TAG_FAMILY", "TAG_IDS", "FrameLayout"]

TAG_FAMILY = "tag36h11"
TAG_IDS = tuple(range(16))
#: The sample square's side over the frame's: svbrdf-diff-renderer's 1024 of 1600 pixels.
SAMPLE_FRACTION = 1024 / 1600

# Grid positions (column, row) of ids 0-15 on the 5 x 5 grid, row 0 at the top.
_GRID = (
    [(c, 0) for c in range(5)]
    + [(4, r) for r in (1, 2, 3)]
    + [(c, 4) for c in range(4, -1, -1)]
    + [(0, r) for r in (3, 2, 1)]
)
# Corner offsets of a tag in units of u: top-left, top-right, bottom-right, bottom-left.
_CORNERS = np.array([[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]])


@dataclass(frozen=True)
class FrameLayout:
    """The frame of side ``side`` cm (module docstring for the geometry)."""

    side: float

    def __post_init__(self):
        if not (isinstance(self.side, (int, float)) and math.isfinite(self.side)) or self.side <= 0:
            raise PhoneCaptureError(
                f"frame side must be a positive length in cm, got {self.side!r}"
            )

    @property
    def unit(self) -> float:
        """u = S / 18, cm."""
        return self.side / 18.0

    @property
    def tag_size(self) -> float:
        """Side of a tag's black ring, 2u, cm."""
        return 2.0 * self.unit

    @property
    def sample_side(self) -> float:
        """Side of the sample square, SAMPLE_FRACTION * S, cm."""
        return SAMPLE_FRACTION * self.side

    @property
    def inner_side(self) -> float:
        """Side of the free square inside the ring of tags, 14u, cm."""
        return 14.0 * self.unit

    def centers(self) -> np.ndarray:
        """(16, 2) tag centres (x, y), cm, in id order."""
        g = np.array(_GRID, float)
        return np.stack([(g[:, 0] - 2.0) * 4.0, (2.0 - g[:, 1]) * 4.0], -1) * self.unit

    def corners(self, depth: float = 0.0) -> np.ndarray:
        """(16, 4, 3) tag corners (TL, TR, BR, BL as printed), cm; z = -depth."""
        xy = self.centers()[:, None, :] + _CORNERS[None] * self.unit
        z = np.full((*xy.shape[:2], 1), -float(depth))
        return np.concatenate([xy, z], -1)

    def sample_corners(self, depth: float = 0.0) -> np.ndarray:
        """(4, 3) corners of the sample square (TL, TR, BR, BL), at z = -depth, cm."""
        h = self.sample_side / 2
        return np.array([[-h, h, -depth], [h, h, -depth], [h, -h, -depth], [-h, -h, -depth]])

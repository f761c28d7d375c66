"""AprilTag 36h11 marker patterns, ids 0-15, without OpenCV.

A tag36h11 marker (Olson 2011; AprilTag 3, Krogius et al. 2019) is an 8 x 8 grid of cells
whose outer ring is black; its 6 x 6 interior carries a 36-bit code word, 1 = white cell.
The printed tag is surrounded by a white quiet zone (one cell or more). The *tag corners*
that detectors report, and that :mod:`jaxrefl.phone._frame` places, are the outer corners of
the black ring.

Cell layout of the code word (AprilTag 3's ``tag36h11`` family): bit 35 (the most
significant) is read first. The first nine bits fill the upper quarter of the interior,
at (column, row) = (1, 1) ... (5, 1), (2, 2), (3, 2), (4, 2), (3, 3) in the 8 x 8 grid
(row 0 at the top); bits 9-17, 18-26 and 27-35 are the same nine cells turned by 90, 180
and 270 degrees clockwise, (c, r) -> (7 - r, c). A tag printed this way is *upright*: the
AprilTag library reports its corners counter-clockwise from the bottom-left one
(svbrdf-diff-renderer's ``src/capture.py`` relies on that order).

OpenCV's ``DICT_APRILTAG_36h11`` holds the same code words, but some OpenCV versions draw
(and number the corners of) the marker turned by 180 degrees (opencv-python issue #1195,
opencv PR #28823), so :mod:`jaxrefl.phone._detect` learns the corner order of the
installed OpenCV from a tag drawn here rather than trusting either convention.
"""

from __future__ import annotations

from functools import cache

import numpy as np

__all__ = ["TAG36H11_CODES", "tag_cells"]

#: Code words of tag36h11 ids 0-15 (AprilTag 3, ``tag36h11.c``), 36 bits each.
TAG36H11_CODES: tuple[int, ...] = (
    0xD7E00984B,
    0xDDA664CA7,
    0xDC4A1C821,
    0xE17B470E9,
    0xEF91D01B1,
    0xF429CDD73,
    0x005DA29225,
    0x1106CBA43,
    0x223BED79D,
    0x21F51213C,
    0x33EB19CA6,
    0x3F76EB0F8,
    0x469A97414,
    0x45DCFE0B0,
    0x4A6465F72,
    0x51801DB96,
)

# The upper quarter of the interior: (column, row) of bits 0-8 in the 8 x 8 grid.
_QUARTER = ((1, 1), (2, 1), (3, 1), (4, 1), (5, 1), (2, 2), (3, 2), (4, 2), (3, 3))


def _bit_cells() -> list[tuple[int, int]]:
    cells, quarter = [], list(_QUARTER)
    for _ in range(4):
        cells += quarter
        quarter = [(7 - r, c) for c, r in quarter]  # 90 degrees clockwise
    return cells


@cache
def tag_cells(tag_id: int) -> np.ndarray:
    """The upright 8 x 8 cells of tag36h11 ``tag_id`` (0-15): True = white, row 0 at the top."""
    if not 0 <= tag_id < len(TAG36H11_CODES):
        from ._errors import PhoneCaptureError

        raise PhoneCaptureError(f"tag id {tag_id}: the frame uses tag36h11 ids 0-15")
    code = TAG36H11_CODES[tag_id]
    cells = np.zeros((8, 8), bool)
    for i, (c, r) in enumerate(_bit_cells()):
        cells[r, c] = bool((code >> (35 - i)) & 1)
    cells.flags.writeable = False
    return cells

"""Write the printable marker frame for ``jaxrefl capture``.

    jaxrefl frame [--side CM] [--out FILE.pdf|FILE.png] [--dpi N]

Sixteen AprilTag 36h11 tags (ids 0-15) in a ring, the layout of svbrdf-diff-renderer's
capture script, so a frame printed for either tool works with both. ``--side`` is the
distance in cm between the outer edges of opposite tags; the sample goes in the middle,
under the central square of 0.64 x side marked by corner ticks. The page (A4 where the
frame fits) names the tag family, the ids and the side, and carries a 10 cm scale bar:
print at 100 % and check it with a ruler, since a print scaled alike in both directions
cannot be told from the photos. See :func:`jaxrefl.phone.write_frame_sheet`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ._main import positive_float, positive_int

HELP = "write the printable AprilTag marker frame (PDF or PNG)"
COMPILES = False


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--side", type=positive_float, default=17.0, help="frame side in cm (outer tag edges)"
    )
    p.add_argument("--out", type=Path, default=Path("frame.pdf"), help="output file, .pdf or .png")
    p.add_argument("--dpi", type=positive_int, default=300, help="resolution of a PNG")


def run(args: argparse.Namespace) -> int:
    from jaxrefl.phone import FrameLayout, write_frame_sheet

    layout = FrameLayout(args.side)
    path = write_frame_sheet(layout, args.out, dpi=args.dpi)
    print(
        f"wrote {path}: tag36h11 ids 0-15, side {layout.side:g} cm, sample square "
        f"{layout.sample_side:.2f} cm; print at 100 % and check the scale bar"
    )
    return 0

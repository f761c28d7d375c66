"""The printable frame: a PDF or PNG page with the tags at their true size.

The page is A4 portrait (21 x 29.7 cm) when the frame fits with 1.5 cm margins, otherwise
a page of the frame's side plus margins. Drawing units are cm on the page: the axes fill
the whole figure, whose size in inches is the page's, so a print at 100 % (no "fit to
page") reproduces every length. Tags are vector rectangles (a black 8 x 8 square, white
cells on top, merged along rows), so the PDF has no resampled image in it. Below the
frame: the tag family and ids, the side, the sample square, and a scale bar in cm to check
the print with a ruler. Thin marks show the corners of the sample square.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._errors import PhoneCaptureError
from ._frame import TAG_FAMILY, TAG_IDS, FrameLayout
from ._tags import tag_cells

__all__ = ["write_frame_sheet"]

_A4 = (21.0, 29.7)
_MARGIN = 1.5  # cm of white around the frame: the tags' quiet zone and the printer's edge
_CM_PER_INCH = 2.54


def _page(layout: FrameLayout) -> tuple[float, float]:
    if layout.side + 2 * _MARGIN <= _A4[0]:
        return _A4
    return (layout.side + 2 * _MARGIN, layout.side + 2 * _MARGIN + 5.0)


def _draw_tag(ax, tag_id: int, x0: float, y0: float, size: float) -> None:
    """Tag ``tag_id`` with its black ring's bottom-left corner at (x0, y0), side ``size``."""
    from matplotlib.patches import Rectangle

    cell = size / 8.0
    ax.add_patch(Rectangle((x0, y0), size, size, facecolor="black", edgecolor="none"))
    cells = tag_cells(tag_id)
    for r in range(8):
        c = 0
        while c < 8:
            if not cells[r, c]:
                c += 1
                continue
            run = c
            while run < 8 and cells[r, run]:
                run += 1
            y = y0 + (7 - r) * cell  # row 0 is the top row of the tag
            ax.add_patch(
                Rectangle((x0 + c * cell, y), (run - c) * cell, cell, facecolor="white", lw=0)
            )
            c = run


def write_frame_sheet(layout: FrameLayout, path: str | Path, dpi: int = 300) -> Path:
    """Write the printable frame of ``layout`` to ``path`` (``.pdf`` or ``.png``, ``dpi``
    for PNG); returns the path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    if path.suffix.lower() not in (".pdf", ".png"):
        raise PhoneCaptureError(f"{path}: the frame is written as .pdf or .png")
    if dpi < 72:
        raise PhoneCaptureError(f"dpi must be >= 72 for a printable PNG, got {dpi}")
    w, h = _page(layout)
    fig = Figure(figsize=(w / _CM_PER_INCH, h / _CM_PER_INCH))
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0, w)
    ax.set_ylim(0, h)
    ax.set_axis_off()
    # frame centre on the page: centred across, its top _MARGIN below the page's top
    cx, cy = w / 2, h - _MARGIN - layout.side / 2
    half = layout.tag_size / 2
    for tag_id, (x, y) in zip(TAG_IDS, layout.centers(), strict=True):
        _draw_tag(ax, tag_id, cx + x - half, cy + y - half, layout.tag_size)
    s, mark = layout.sample_side / 2, 0.4
    for sx, sy in ((-1, 1), (1, 1), (1, -1), (-1, -1)):
        px, py = cx + sx * s, cy + sy * s
        ax.plot([px, px - sx * mark], [py, py], color="0.6", lw=0.5)
        ax.plot([px, px], [py, py - sy * mark], color="0.6", lw=0.5)
    top = cy - layout.side / 2 - 1.0
    lines = [
        f"AprilTag {TAG_FAMILY}, ids {TAG_IDS[0]}-{TAG_IDS[-1]}, clockwise from the top left",
        f"frame side {layout.side:g} cm (outer tag edges); sample square "
        f"{layout.sample_side:.2f} cm (corner marks)",
        f"print at 100 % (no fit to page); then: jaxrefl capture PHOTOS --side {layout.side:g}",
    ]
    for i, text in enumerate(lines):
        ax.text(_MARGIN, top - 0.6 * i, text, fontsize=8, va="top", ha="left")
    bar = float(min(10, int(np.floor(w - 2 * _MARGIN))))
    y_bar = top - 0.6 * len(lines) - 0.8
    ax.plot([_MARGIN, _MARGIN + bar], [y_bar, y_bar], color="black", lw=1.5)
    for k in range(int(bar) + 1):
        tick = 0.3 if k % 5 == 0 else 0.15
        ax.plot([_MARGIN + k, _MARGIN + k], [y_bar, y_bar + tick], color="black", lw=0.8)
    ax.text(_MARGIN, y_bar - 0.2, "0", fontsize=7, va="top", ha="center")
    ax.text(_MARGIN + bar, y_bar - 0.2, f"{bar:g} cm", fontsize=7, va="top", ha="center")
    ax.text(_MARGIN + bar + 0.5, y_bar, "scale bar: check with a ruler", fontsize=7, va="center")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path

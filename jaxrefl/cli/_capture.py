"""Turn phone photos of a sample in the printed frame into a capture.

    jaxrefl capture RAW_DIR --side CM --out CAPTURE_DIR [--depth CM] [--size N]
                    [--intrinsics FILE] [--max-error PX] [--flash-power P]

Reads the photos of RAW_DIR (JPEG or PNG, 8-bit, all of one size), finds the frame's
AprilTag 36h11 tags in each (``jaxrefl frame`` prints the frame), calibrates the camera
over the photos (or takes ``--intrinsics``), rectifies each photo to the sample square
(0.64 x side, at ``--depth`` cm below the marker plane) at N x N pixels and writes a
capture that ``jaxrefl fit`` reads: ``capture.json`` with the photos (16-bit PNG, sRGB),
the camera and flash positions (flash at the lens), ``calibration.json`` (intrinsics,
distortion, reprojection error, camera position and orientation and EXIF exposure of every
photo, the photos left out and why) and ``preview/NN.png`` (detected and reprojected tag
corners). Photos with too few tags, or whose reprojection error exceeds ``--max-error``,
are left out and named; fewer than 3 usable photos writes nothing. See
:func:`jaxrefl.phone.photos_to_capture`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ._main import check_out_dir, non_negative_float, positive_float, positive_int

HELP = "turn phone photos of a sample in the marker frame into a capture"
COMPILES = False


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("raw_dir", type=Path, metavar="RAW_DIR", help="folder of the photos")
    p.add_argument(
        "--side", type=positive_float, required=True, help="frame side in cm (outer tag edges)"
    )
    p.add_argument("--out", type=Path, required=True, help="capture folder to write (new or empty)")
    p.add_argument(
        "--depth",
        type=non_negative_float,
        default=0.0,
        help="cm the sample's surface lies below the marker plane",
    )
    p.add_argument("--size", type=positive_int, default=1024, help="rectified photo side in pixels")
    p.add_argument(
        "--intrinsics",
        type=Path,
        default=None,
        help="JSON of known intrinsics (e.g. an earlier capture's calibration.json); "
        "default: calibrate over these photos",
    )
    p.add_argument(
        "--max-error",
        type=positive_float,
        default=1.0,
        help="largest reprojection error (pixels, RMS) a photo may have",
    )
    p.add_argument(
        "--flash-power",
        type=positive_float,
        default=1500.0,
        help="flash power written in the capture (the public flash captures' convention)",
    )


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from jaxrefl.phone import CaptureOptions, Intrinsics, photos_to_capture

    check_out_dir(args.out)
    options = CaptureOptions(
        side=args.side,
        depth=args.depth,
        size=args.size,
        flash_power=args.flash_power,
        intrinsics=None if args.intrinsics is None else Intrinsics.read(args.intrinsics),
        max_error=args.max_error,
    )
    result = photos_to_capture(args.raw_dir, args.out, options)
    for path, why in result.left_out:
        print(f"left out {path.name}: {why}")
    cal = result.calibration
    k = cal.intrinsics.camera_matrix
    source = "calibrated" if cal.estimated else "given"
    print(
        f"camera ({source}): f {k[0, 0]:.1f} px, centre ({k[0, 2]:.1f}, {k[1, 2]:.1f}), "
        f"distortion {np.round(cal.intrinsics.distortion[:2], 4).tolist()}"
    )
    print(f"{'photo':<24} {'tags':>4} {'error px':>8}  camera position (cm)")
    for i, path in enumerate(result.photos):
        rec = result.record["photos"][i]
        pos = ", ".join(f"{v:6.2f}" for v in result.positions[i])
        print(f"{path.name:<24} {len(rec['tags']):>4} {cal.errors[i]:>8.3f}  ({pos})")
    print(
        f"wrote {len(result.photos)} rectified photos, capture.json, calibration.json and "
        f"preview/ to {result.out}"
    )
    return 0

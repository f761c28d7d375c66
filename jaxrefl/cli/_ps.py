"""Photometric stereo on a capture folder: normals, albedo, depth and errors.

    jaxrefl ps CAPTURE_DIR --out OUT_DIR [--method ls|robust|brdf] [--calibrate-lights CHROME_DIR]

CAPTURE_DIR is in the DiLiGenT layout (``filenames.txt``, ``light_directions.txt``,
``light_intensities.txt``, ``mask.png``, 16-bit PNGs, optional ``Normal_gt.mat``/``.png``)
or the UW psm layout (``OBJ/OBJ.<k>.tga``, ``OBJ.mask.tga``, ``lights.txt`` in or beside
the folder). Methods: ``ls`` (Woodham least squares), ``robust`` (shadows and highlights
rejected), ``brdf`` (normal + Cook-Torrance GGX BRDF per pixel). ``--calibrate-lights``
re-estimates the light directions from a chrome sphere captured under the same lights.
``--reference sphere`` evaluates against the ideal sphere fitted to the mask (for a sphere
without ground truth).

Writes OUT_DIR/normals.exr (+ .png), albedo.exr (+ .png), depth.exr (+ .png), error.exr
(+ .png) when there is a reference, and report.json (mean_angular_error_deg,
median_angular_error_deg, method, status counts, timings). Frame: x right, y up, z towards
the camera.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ._main import check_out_dir, positive_int

HELP = "photometric stereo: normals, albedo and depth from a capture folder"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", metavar="CAPTURE_DIR", type=Path, help="capture folder")
    p.add_argument("--out", required=True, type=Path, help="output folder (created)")
    p.add_argument(
        "--method",
        choices=("ls", "robust", "brdf"),
        default="ls",
        help="ls: Woodham least squares; robust: shadows and highlights rejected; brdf: normal "
        "and Cook-Torrance GGX BRDF per pixel",
    )
    p.add_argument(
        "--calibrate-lights",
        type=Path,
        default=None,
        metavar="CHROME_DIR",
        help="chrome-sphere capture under the same lights: calibrate the directions from it "
        "(default: the capture's own light directions)",
    )
    p.add_argument(
        "--reference",
        choices=("sphere",),
        default=None,
        help="evaluate against the ideal sphere fitted to the mask (default: the capture's "
        "ground-truth normals, when it has them)",
    )
    p.add_argument(
        "--downsample", type=positive_int, default=1, help="keep every n-th pixel (>= 1)"
    )


def run(args: argparse.Namespace) -> int:
    from jaxrefl.ps import METHODS, run_ps

    if not args.path.is_dir():
        raise FileNotFoundError(f"{args.path}: capture folder not found")
    if args.calibrate_lights is not None and not args.calibrate_lights.is_dir():
        raise FileNotFoundError(f"{args.calibrate_lights}: chrome-sphere folder not found")
    check_out_dir(args.out)
    r = run_ps(
        args.path,
        args.out,
        method=METHODS[args.method](),
        calibrate_lights=args.calibrate_lights,
        reference=args.reference,
        downsample=args.downsample,
    )
    print(f"{r['name']}: {r['n_pixels']} pixels, {r['n_images']} images, method {r['method']}")
    if "light_calibration" in r:
        e = r["light_calibration"]["mean_error_vs_capture_lights_deg"]
        print(f"chrome-sphere lights: mean {e:.2f} deg from the capture's own lights")
    if r["mean_angular_error_deg"] is not None:
        print(
            f"angular error vs {r['reference']}: mean {r['mean_angular_error_deg']:.2f} deg, "
            f"median {r['median_angular_error_deg']:.2f} deg"
        )
    print(f"solve {r['timings']['solve_s']:.2f} s, total {r['timings']['total_s']:.2f} s")
    print(f"wrote {args.out}")
    return 0

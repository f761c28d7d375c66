"""Export a fit for renderers: textures, a Mitsuba 3 scene or a glTF 2.0 material.

    jaxrefl export FIT_DIR --format mitsuba|gltf|textures [--out OUT_DIR] [--bits 8|16]

FIT_DIR is the output folder of ``jaxrefl fit`` or ``jaxrefl demo`` (its ``maps.exr``).
``textures`` writes the maps in the conventions renderers expect
(:func:`jaxrefl.svbrdf.write_textures`): ``base_color.png`` (sRGB), ``roughness.png``
(perceptual, sqrt(alpha)), ``metallic.png``, ``metallic_roughness.png`` (glTF's packing),
``normal.png`` (tangent space, when normals were fitted) and linear single-layer EXRs
(channels R, G, B or Y). ``mitsuba`` adds ``scene.xml``
(:func:`jaxrefl.svbrdf._export.mitsuba_xml`: the sample as a rectangle with a ``principled``
BSDF, a camera and a flash beside it; render with ``mitsuba scene.xml``); ``gltf`` adds
``material.gltf`` (:func:`jaxrefl.svbrdf._export.gltf_document`: a textured square with one
metallic-roughness material). The conversions (alpha to roughness, F0 to metallic or to
principled's ``specular``) are stated in :mod:`jaxrefl.svbrdf._export`. OUT_DIR defaults
to FIT_DIR/export_FORMAT.
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "export a fit's maps as textures, a Mitsuba 3 scene or a glTF 2.0 material"

FORMATS = ("mitsuba", "gltf", "textures")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("fit_dir", metavar="FIT_DIR", type=Path, help="a `jaxrefl fit` output folder")
    p.add_argument("--format", required=True, choices=FORMATS, help="what to write")
    p.add_argument(
        "--out", type=Path, default=None, help="output folder (default: FIT_DIR/export_FORMAT)"
    )
    p.add_argument(
        "--bits", type=int, choices=(8, 16), default=8, help="PNG sample depth (default: 8)"
    )


def run(args: argparse.Namespace) -> int:
    from jaxrefl import svbrdf

    out = args.out if args.out is not None else args.fit_dir / f"export_{args.format}"
    if args.format == "mitsuba":
        paths = svbrdf.write_mitsuba(args.fit_dir, out, bits=args.bits)
    elif args.format == "gltf":
        paths = svbrdf.write_gltf(args.fit_dir, out, bits=args.bits)
    else:
        tex = svbrdf.write_textures(args.fit_dir, out, bits=args.bits)
        paths = [tex.path(role) for role in tex.files]
    print(f"wrote {len(paths)} files to {out}/: {', '.join(p.name for p in paths)}")
    return 0

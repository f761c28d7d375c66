"""Where to take the next photo: candidate positions ranked by what a photo there teaches.

    jaxrefl plan FIT_DIR --out PLAN_DIR [--candidates-from CAPTURE --photos 1,2,4,7]
                 [--positions FILE] [--criterion variance|log_variance|information] [--max-pixels N]
                 [--top N] [--no-censoring]

FIT_DIR is the output folder of ``jaxrefl fit`` (its maps.exr and report.json; the capture
is read again from the path, photo subset, resolution and downsampling report.json
records: :func:`jaxrefl.svbrdf.read_fit`). Each candidate camera-and-flash position is
scored (:func:`jaxrefl.svbrdf.plan_next`, the linearised Fisher information of the new photo
with censoring at saturation added to the fit's Laplace precision, ``pooled``'s shared
width counted once) by the expected reduction of the predictive variance of renderings at
the candidates (``--criterion variance``, the default: how much better the fit would
predict a photo taken at any of them) or by the expected information gain about the
parameters (``--criterion information``). Where the fit estimated the flash (``jaxrefl fit
--light``), the candidates' flash gets the estimated offset. Candidates: by default a grid
over the hemisphere at the capture's distance; ``--positions FILE`` a text file of camera
positions, one ``x,y,z`` per line (capture units, the sample frame: origin its centre, +z
its normal); ``--candidates-from CAPTURE --photos 1,2,4,7`` the camera and flash positions
of those photos of a capture (sequential use: fit with ``jaxrefl fit CAPTURE --photos
0,3,5,6,8``, plan over the others, take the best, fit again).

Writes PLAN_DIR/plan.json (``ranking``: one entry per candidate, best first, with ``photo``
for photos of a capture or ``position`` for grid and listed ones, ``gain`` (the criterion's:
the share of the predictive variance removed, or nats), ``variance_reduction``,
``information`` in nats and ``share_informed``, the share of pixels whose posterior volume
it shrinks by 10% or more), PLAN_DIR/highlights.png (the sample with where the highlight of
the best candidates would fall) and PLAN_DIR/positions.png (the candidates seen from above,
coloured by gain).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxrefl._errors import JaxreflError
from jaxrefl._names import PLAN_CRITERIA

from ._main import check_out_dir, photo_indices, positive_int

HELP = "rank candidate positions for the next photo by what a photo there teaches the fit"


def _photos(text: str) -> tuple[int, ...]:
    return photo_indices(text, "--photos", "1,2,4,7")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("fit_dir", metavar="FIT_DIR", type=Path, help="a `jaxrefl fit` output folder")
    p.add_argument("--out", type=Path, required=True, help="output folder (created)")
    p.add_argument(
        "--candidates-from",
        type=Path,
        default=None,
        help="a capture whose photos' camera and flash positions are the candidates (default: "
        "a grid over the hemisphere at the capture's distance)",
    )
    p.add_argument(
        "--photos",
        type=_photos,
        default=None,
        help="with --candidates-from: which of its photos, e.g. 1,2,4,7 (default: all)",
    )
    p.add_argument(
        "--positions",
        type=Path,
        default=None,
        help="text file of candidate camera positions, one x,y,z per line in capture units "
        "(default: the hemisphere grid); the flash keeps the capture's offset from the lens",
    )
    p.add_argument(
        "--max-pixels",
        type=positive_int,
        default=4096,
        help="pixels sampled to score each candidate",
    )
    p.add_argument(
        "--criterion",
        choices=PLAN_CRITERIA,
        default=PLAN_CRITERIA[0],
        help="rank by the expected reduction of the predictive variance of renderings at the "
        "candidates (variance, the default; log_variance: the mean over pixels of its log) or "
        "by the expected information gain about the parameters (information)",
    )
    p.add_argument("--top", type=positive_int, default=3, help="candidates drawn in highlights.png")
    p.add_argument(
        "--no-censoring",
        action="store_true",
        help="score every new observation as uncensored (default: a saturating one is censored)",
    )


def _positions(path: Path):
    import numpy as np

    try:
        pos = np.loadtxt(path, delimiter=",", ndmin=2)
    except ValueError as e:
        raise JaxreflError(f"--positions {path}: not lines of x,y,z numbers ({e})") from None
    if pos.shape[-1] != 3:
        raise JaxreflError(
            f"--positions {path}: each line needs 3 numbers x,y,z, got {pos.shape[-1]}"
        )
    return pos


def run(args: argparse.Namespace) -> int:
    from jaxrefl import svbrdf

    if args.photos is not None and args.candidates_from is None:
        raise JaxreflError("--photos needs --candidates-from CAPTURE (whose photos they are)")
    if args.positions is not None and args.candidates_from is not None:
        raise JaxreflError("give --positions or --candidates-from, not both")
    check_out_dir(args.out)
    result, capture = svbrdf.read_fit(args.fit_dir)
    if args.candidates_from is not None:
        from jaxrefl.io import load_capture

        other = load_capture(args.candidates_from)
        candidates = svbrdf.photo_candidates(other, args.photos)
    elif args.positions is not None:
        candidates = svbrdf.listed_candidates(capture, _positions(args.positions))
    else:
        candidates = svbrdf.hemisphere_candidates(capture)
    options = svbrdf.PlanOptions(
        max_pixels=args.max_pixels, censoring=not args.no_censoring, criterion=args.criterion
    )
    plan = svbrdf.plan_next(result, capture, candidates, options)
    files = svbrdf.write_plan(plan, capture, args.out, top=args.top, fit_dir=args.fit_dir)
    print(
        f"{len(candidates)} candidates scored on {plan.pixels_sampled} of {plan.pixels} pixels"
        + (f"; shared: {', '.join(plan.shared)}" if plan.shared else "")
        + (f"; flash placed by the fit's light ({plan.light})" if plan.light != "fixed" else "")
    )
    for rank, row in enumerate(plan.ranking()[: args.top], start=1):
        where = (
            f"photo {row['photo']}"
            if "photo" in row
            else "position " + ", ".join(f"{v:.1f}" for v in row["position"])
        )
        print(
            f"{rank}. {where}: removes {row['variance_reduction']:.1%} of the predictive "
            f"variance, {row['information']:.2f} nats, informs "
            f"{row['share_informed']:.0%} of pixels, highlight at "
            f"({row['highlight'][0]:.1f}, {row['highlight'][1]:.1f})"
            + ("" if row["highlight_on_sample"] else " (beside the sample)")
        )
    print(f"wrote {files['plan']}, {files['highlights']} and {files['positions']}")
    return 0

"""Fit a photographed planar capture: per-pixel reflectance maps with uncertainty.

    jaxrefl fit CAPTURE_DIR --out OUT_DIR [--model auto|ggx|ggx_rgb|pooled|lambert|...]
                [--auto-candidates a,b,...] [--auto-pixels N] [--auto-seed N]
                [--holdout i,j,...|all] [--photos i,j,...] [--tile-pixels N] [--downsample F]
                [--noise-level auto|flat] [--restart] [--keep-tiles]

CAPTURE_DIR is in one of the layouts :func:`jaxrefl.io.load_capture` reads (the
svbrdf-diff-renderer ``parameters.json`` or ``optim.json`` layouts, MaterialGAN's text
files, or the generic JSON). ``--holdout all`` fits every photo out in turn and reports each
one's held-out RMSE beside Lambert's (:func:`jaxrefl.svbrdf.leave_one_out`), then writes the
maps of the fit on all photos. ``--photos 0,3,5`` fits with those photos only (the others are
neither fitted nor held out; ``--holdout`` then names photos among them, by their numbers in
the capture; the report numbers photos by their place in the subset, ``capture.selected``
lists the subset): the first step of sequential capture planning (``jaxrefl plan``).
``--model auto`` (the default) fits the model that best predicts
held-out training photos (:func:`jaxrefl.svbrdf.choose_model`); the report says which and why.
``--auto-candidates``, ``--auto-pixels`` and ``--auto-seed`` set that choice's
:class:`~jaxrefl.svbrdf.AutoOptions` (the models scored, the selection's size and seed; the
last two also size a named model's check of an estimated ``--light``), each flag not given
keeping AutoOptions' default; report.json records them (``job.auto``, and ``auto`` where
the model was chosen). ``--noise-level auto`` (the default) replaces the flat noise model of
a per-pixel model by the capture's noise-level function where its residuals support it
(:func:`jaxrefl.svbrdf.estimate_noise_level`; report.json ``noise_level`` says what and why).

Writes OUT_DIR/maps.exr (parameters, their Laplace std, correlations, status and
reliability flags), OUT_DIR/report.json (timings with compile apart, pixel counts by status,
the model, and with --holdout the held-out RMSE in linear radiance, overall and per photo)
and PNG previews. The tiles of the fit are kept in OUT_DIR/tiles while it runs: an interrupted
run resumes from them when run again (--restart to start over); after a successful run the
folder is removed unless --keep-tiles.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

from jaxrefl._errors import JaxreflError
from jaxrefl._names import CAPTURE_MODELS, LIGHT_CHOICES, LIGHT_DEFAULT, canonical

from ._distributed import add_distributed_arguments, distributed_from_args
from ._main import check_out_dir, photo_indices, positive_float, positive_int
from ._options import (
    BACKENDS,
    DTYPES,
    LOSSES,
    NOISES,
    SHOT_GAIN,
    SHOT_READ,
    add_auto_arguments,
    add_noise_level_argument,
    auto_options,
    fit_config,
)

if TYPE_CHECKING:
    from jaxrefl import svbrdf

HELP = "fit a capture: per-pixel maps, uncertainty, held-out error"


def _indices(text: str) -> tuple[int, ...] | str:
    if text.strip().lower() == "all":
        return "all"
    return photo_indices(text, "--holdout", "0,4 or 'all'")


def _photos(text: str) -> tuple[int, ...]:
    return photo_indices(text, "--photos")


def _subset_holdout(photos: tuple[int, ...] | None, holdout: tuple[int, ...]) -> tuple[int, ...]:
    """``--holdout`` as positions in the ``--photos`` subset (its indices name photos of the
    capture, which must be among those selected)."""
    if photos is None:
        return holdout
    missing = [i for i in holdout if i not in photos]
    if missing:
        raise JaxreflError(
            f"--holdout photo(s) {missing} are not among --photos {list(photos)}: hold out "
            "photos of the subset (the others are neither fitted nor held out)"
        )
    return tuple(photos.index(i) for i in holdout)


def _alpha(text: str) -> float:
    value = positive_float(text)
    if value > 1.0:
        raise argparse.ArgumentTypeError(f"must be in (0, 1] (a GGX width), got {value:g}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", type=Path, help="capture folder (or generic JSON file)")
    p.add_argument("--out", type=Path, required=True, help="output folder (created)")
    p.add_argument(
        "--model",
        default="auto",
        type=canonical,
        choices=["auto", *sorted(CAPTURE_MODELS)],
        help="capture model (jaxrefl models NAME describes one); auto: the candidate with the "
        "lowest leave-one-photo-out error over the training photos",
    )
    add_auto_arguments(p)
    p.add_argument(
        "--holdout",
        type=_indices,
        default=(),
        help="photos to leave out, e.g. 0,4; 'all': leave-one-out over every photo against "
        "Lambert, then the maps from all photos (default: none)",
    )
    p.add_argument(
        "--photos",
        type=_photos,
        default=None,
        help="fit with these photos only, e.g. 0,3,5,6,8 (the others are neither fitted nor "
        "held out; default: all)",
    )
    p.add_argument("--tile-pixels", type=positive_int, default=4096, help="pixels per tile")
    p.add_argument(
        "--resolution",
        type=positive_int,
        default=None,
        help="image folder to read, by its size (default: the largest)",
    )
    p.add_argument(
        "--downsample", type=positive_int, default=1, help="box-filter factor (>= 1) before fitting"
    )
    p.add_argument(
        "--max-photos",
        type=positive_int,
        default=None,
        help="read at most this many photos (default: all)",
    )
    p.add_argument(
        "--backend",
        default="lean",
        choices=BACKENDS,
        help="least-squares solver: lean (jaxrefl's own Levenberg-Marquardt), optimistix or "
        "jaxopt (pip install 'jaxrefl[backends]')",
    )
    p.add_argument(
        "--dtype", default="float32", choices=DTYPES, help="floating-point type of the fit"
    )
    p.add_argument(
        "--noise",
        default="gaussian",
        choices=NOISES,
        help=f"noise model: gaussian (sigma estimated) or shot (read {SHOT_READ}, "
        f"gain {SHOT_GAIN}, linear radiance units)",
    )
    p.add_argument(
        "--loss",
        default=None,
        choices=LOSSES,
        help="robust loss on the residuals (default: huber for pooled, robust to glints; l2 for "
        "the others)",
    )
    p.add_argument(
        "--alpha-min",
        type=_alpha,
        default=None,
        help="lower bound of alpha, in (0, 1] (default: the narrowest lobe the capture resolves)",
    )
    p.add_argument(
        "--tilt-std",
        type=positive_float,
        default=0.1,
        help="ggx_normal: std of the zero-mean prior on the normal's slopes",
    )
    p.add_argument(
        "--light",
        default=LIGHT_DEFAULT,
        choices=LIGHT_CHOICES,
        help=f"the flash (default {LIGHT_DEFAULT}): fixed (as the capture states it), offset "
        "(its offset from the lens estimated), offset+gains (and a gain per photo), auto: "
        "what held-out observations support",
    )
    add_noise_level_argument(p)
    p.add_argument("--restart", action="store_true", help="ignore tiles of an earlier run")
    p.add_argument(
        "--keep-tiles",
        action="store_true",
        help="keep OUT/tiles after a successful run (removed otherwise; an interrupted run "
        "keeps them and resumes from them)",
    )
    p.add_argument("--no-previews", action="store_true", help="skip the PNG previews")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_distributed_arguments(p)


def resume_hint(args: argparse.Namespace) -> str:
    """What to type after Ctrl-C: the same command resumes from OUT/tiles."""
    return f"the tiles done so far are in {args.out / 'tiles'}; run the same command to resume"


def fit_job(args: argparse.Namespace) -> svbrdf.FitJob:
    """The :class:`~jaxrefl.svbrdf.FitJob` the flags give (``--holdout all``: none held out,
    :func:`jaxrefl.svbrdf.leave_one_out` holds out each photo in turn)."""
    from jaxrefl.svbrdf import FitJob

    return FitJob(
        model=args.model,
        holdout=() if args.holdout == "all" else _subset_holdout(args.photos, args.holdout),
        tile_pixels=args.tile_pixels,
        config=fit_config(args.backend, args.dtype, args.noise, args.loss),
        alpha_min=args.alpha_min,
        tilt_std=args.tilt_std,
        light=args.light,
        auto=auto_options(args.auto_candidates, args.auto_pixels, args.auto_seed),
        noise_level=args.noise_level,
    )


def run(args: argparse.Namespace) -> int:
    from jaxrefl.io import load_capture
    from jaxrefl.svbrdf import fit_capture, write_outputs

    dist = distributed_from_args(args)
    if dist is not None:
        if args.holdout == "all":
            raise JaxreflError("--holdout all runs in one process: drop --distributed")
        dist.initialize()  # before any JAX computation
    if args.dtype == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)
    check_out_dir(args.out)
    loo_all = args.holdout == "all"
    job = fit_job(args)  # options are checked before any file is read
    capture = load_capture(args.capture, resolution=args.resolution, max_photos=args.max_photos)
    if args.photos is not None:
        bad = [i for i in args.photos if i >= capture.n_photos]
        if bad:
            raise JaxreflError(
                f"--photos {bad} out of range: the capture has {capture.n_photos} photos"
            )
        capture = capture.select(list(args.photos))
    if args.downsample > 1:
        capture = capture.downsample(args.downsample)
    print(f"{capture}")
    loo = None
    if loo_all:
        from jaxrefl.svbrdf import leave_one_out

        loo = leave_one_out(capture, job, progress=None if args.quiet else print)
    result = fit_capture(
        capture, job, args.out, restart=args.restart, progress=not args.quiet, distributed=dist
    )
    if loo is not None:
        result.report.update(loo.report)
    # How the capture was read, so that `jaxrefl plan` can read the same photos again.
    result.report.setdefault("capture", {}).update(
        path=str(Path(args.capture).resolve()),
        selected=None if args.photos is None else list(args.photos),
        resolution=args.resolution,
        downsample=args.downsample,
        max_photos=args.max_photos,
    )
    if dist is not None and not dist.is_main:
        return 0  # process 0 writes the outputs
    files = write_outputs(result, capture, args.out, previews=not args.no_previews)
    if not args.keep_tiles:
        remove_tiles(args.out)
    print_summary(result.report)
    print(
        f"wrote {files['maps']}, {files['report']}" + ("" if args.no_previews else " and previews")
    )
    return 0


def remove_tiles(out: Path) -> None:
    """Remove OUT/tiles (the resume state of :func:`jaxrefl.svbrdf.fit_capture`) once the
    maps are written."""
    shutil.rmtree(out / "tiles", ignore_errors=True)


def noise_level_line(level: dict) -> str:
    """The noise model the fit used, and why (the report's ``noise_level``)."""
    if level["kept"]:
        return (
            f"noise: level function sqrt(1 + {level['gain']:.3g} y + ({level['rel']:.3g} y)^2) "
            f"x each pixel's scale ({level['why']})"
        )
    return f"noise: {level['why']}"


def light_line(light: dict) -> str:
    """What was estimated of the flash, and why (the report's ``light``)."""
    if light["mode"] == "fixed":
        return f"light: fixed as the capture states it ({light['why']})"
    d = ", ".join(
        f"{v:+.2f} +- {s:.2f}"
        for v, s in zip(light["offset_cm"], light["offset_std_cm"], strict=True)
    )
    text = f"light: estimated {light['mode']}: flash offset ({d}) cm"
    if light["mode"] == "offset+gains":
        g = light["photo_gain"]
        text += f", photo gains {min(g):.3f}-{max(g):.3f}"
    return f"{text} ({light['why']})"


def print_summary(report: dict) -> None:
    t = report["timings"]
    counts = ", ".join(f"{k} {v}" for k, v in report["status_counts"].items() if v)
    print(f"model {report['model']}: {report['pixels']} pixels ({counts})")
    rate = t["pixels_per_s"]
    rate_s = f", {rate:,.0f} pixels/s" if rate else ""
    print(
        f"time: compile {t['compile_s']:.1f} s, run {t['run_s']:.2f} s{rate_s} "
        f"({t['tiles']} tiles, {t['tiles_loaded']} resumed, {t['devices']} device(s))"
    )
    flags = report["laplace_flag_counts"]
    print(f"Laplace uncertainty reliable on {flags['reliable']} of {report['pixels']} pixels")
    counts = report.get("misspecified_counts", {})
    bad = counts.get("misspecified")
    if bad:
        print(
            f"misspecified (the model cannot be right; intervals not calibrated): {bad} of "
            f"{report['pixels']} pixels (map 'misspecified')"
        )
        floor = counts.get("ALPHA_AT_FLOOR")
        if floor and report.get("alpha_min") is not None:
            print(
                f"  of them {floor} with alpha at its floor {report['alpha_min']:.3f} (the "
                "capture's resolvable width unless --alpha-min was given): the surface's lobe "
                "may be narrower than the model allows"
            )
    if report.get("train_rmse") is not None:
        print(f"fit RMSE (linear radiance, fitted photos): {report['train_rmse']:.5f}")
    if "heldout_rmse" in report and report["heldout_rmse"] is not None:
        per = ", ".join(
            f"{k}: " + ("-" if v is None else f"{v:.5f}")
            for k, v in report["heldout_rmse_per_photo"].items()
        )
        print(f"held-out RMSE: {report['heldout_rmse']:.5f} ({per})")
        med, p99 = report.get("heldout_pixel_rmse_median"), report.get("heldout_pixel_rmse_p99")
        if med is not None:
            print(f"held-out RMSE per pixel: median {med:.5f}, 99th percentile {p99:.5f}")
        base = report.get("baseline")
        if base and report.get(f"{base}_heldout_rmse") is not None:
            b_p99 = report.get(f"{base}_heldout_pixel_rmse_p99")
            print(
                f"{base} (same photos held out): {report[f'{base}_heldout_rmse']:.5f}, "
                f"per-pixel 99th percentile {b_p99:.5f}; photos predicted worse than "
                f"{base}: {report['photos_worse_than_baseline'] or 'none'}"
            )
    if report.get("light"):
        print(light_line(report["light"]))
    if report.get("noise_level"):
        print(noise_level_line(report["noise_level"]))
    if report.get("auto"):
        print(f"auto: chose {report['auto']['model']}: {report['auto']['why']}")
    for a in report.get("auto_per_fold", []):
        print(f"auto (fold): chose {a['model']}")
    if report.get("pooled"):
        pc = report["pooled"]
        alpha = f" (alpha {pc['alpha']:.4f})" if pc["alpha"] else ""
        print(f"pooled: chose {pc['model']}{alpha}: {pc['why']}")

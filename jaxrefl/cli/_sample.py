"""Posterior sampling: uncertainty maps of a capture, or the posterior of a measured BRDF.

    jaxrefl sample CAPTURE_DIR --out OUT_DIR [--pixels R0:R1,C0:C1] [--downsample F]
                   [--model auto] [--auto-candidates a,b,...] [--auto-pixels N]
                   [--auto-seed N] [--mcmc flagged|all|none] [--audit SHARE]
                   [--warmup N] [--samples N] [--chains N] [--gibbs-sweeps N]
                   [--rerun-rhat R] [--priors population|default] [--seed S]
                   [--time-limit SECONDS] [--restart] [--keep-work] [--quiet]
    jaxrefl sample BRDF_FILE --out OUT_DIR [--brdf-model ggx]
                   [--sampler emcee|hmc] [--max-steps N] [--walkers N] [--seed S]

A capture (any layout :func:`jaxrefl.io.load_capture` reads; ``--downsample`` first, then
the ``--pixels`` crop: rows R0:R1, columns C0:C1) goes through
:func:`jaxrefl.svbrdf.uncertainty_maps`: the capture job's float64 fit (``--model auto``,
the default, chooses the model by held-out photos as ``jaxrefl fit`` does, under the
:class:`~jaxrefl.svbrdf.AutoOptions` of ``--auto-candidates``, ``--auto-pixels`` and
``--auto-seed``), its Laplace std,
then :func:`jaxrefl.posterior.adaptive_uncertainty` with the
:class:`~jaxrefl.posterior.AdaptiveOptions` the flags give; every default is the library's
(:mod:`jaxrefl._map_defaults`: ``AdaptiveOptions()`` and this command make the same map)
(``--mcmc``, ``--audit``,
``--warmup``/``--samples``/``--chains`` as its :class:`~jaxrefl.posterior.HMCOptions`,
``--gibbs-sweeps`` as its :class:`~jaxrefl.posterior.GibbsOptions`: where the posterior
allows, Gibbs sampling instead
of HMC, exact for ``pooled``, with the lobe width from its collapsed marginal for the
per-pixel models (:mod:`jaxrefl.posterior._width_gibbs`),
``--rerun-rhat``: the max R-hat above which a pixel runs the longer second pass (and,
still above it, a third), 0 for none, ``--seed``). The noise scale is unknown (sampled
per pixel, Jeffreys prior). The lobe's priors (``--priors``) are by default estimated
from the population of fitted pixels (:func:`jaxrefl.svbrdf.population_priors`);
``default`` takes the model's own.
Writes OUT_DIR/uncertainty.exr (mean, std, q05, q95 per parameter, method, R-hat, ESS) and
OUT_DIR/posterior.nc (ArviZ InferenceData of the MCMC pixels, with observed data and
posterior predictive draws) by :func:`jaxrefl.svbrdf.write_uncertainty`, and
OUT_DIR/report.json (:meth:`jaxrefl.svbrdf.CaptureUncertainty.report` with the input,
crop and downsampling: counts by method, R-hat/ESS distributions, divergences,
Laplace/MCMC std ratios on the audit pixels, timings of each stage).

Progress: one line per stage on stderr (the fit and the model it chose, the priors, each
MCMC pass with its pixel count, writing), each with the seconds since the start, and during
MCMC a line every 30 s with the chunks done and the time left; with stderr a terminal,
progress bars too. ``--quiet`` silences both. The fit's tiles and the MCMC chunks are
written under OUT_DIR (``fit``, ``mcmc``; a pooled map's per-pixel widths: ``fit_widths``)
as they finish: a stopped command says so, and the same command run again resumes there
(``--restart`` discards them and starts over). They are removed once the map is whole,
unless ``--keep-work``. ``--time-limit``: no MCMC chunk is started that would end past that
many seconds from the start; the pixels left keep their Laplace summary (method
``laplace_time_limit`` in uncertainty.exr, counted in report.json's ``time_limit``), the
exit status is 3, and the same command run again samples them.

A measured BRDF file (Cornell .astm, MERL .binary, CURET; spectra converted to RGB) goes
through :func:`jaxrefl.measured.sample_posterior`: the least-squares fit of
``--brdf-model`` (f_r cos theta_i residuals, 80 degree limit), then emcee
(:class:`~jaxrefl.posterior.EmceeOptions` from ``--max-steps``, ``--walkers``, ``--seed``;
the default) or HMC (``--warmup``/``--samples``/``--chains``, ``--seed`` as
``HMCOptions.seed``), the noise scale unknown. emcee runs until
its chain is at least 50 integrated autocorrelation times long with split R-hat <= 1.01
and bulk ESS >= 400 for every parameter (:func:`jaxrefl.posterior.sample_emcee`), or
``--max-steps``. Writes OUT_DIR/posterior.nc and OUT_DIR/corner.png
(:func:`jaxrefl.measured.write_posterior`) and OUT_DIR/report.json
(:meth:`jaxrefl.measured.BRDFPosterior.report`).

Exit status 3 (outputs written): the draws missed a convergence target (``converged:
false`` in report.json, with the reasons, tau, chain length, R-hat and ESS, and one line
on stderr saying what to raise).
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from jaxrefl._errors import JaxreflError
from jaxrefl._map_defaults import MAP_AUDIT, MAP_CHUNK, MAP_GIBBS, MAP_SAMPLER, RERUN_RHAT
from jaxrefl._names import (
    CAPTURE_MODELS,
    LIGHT_CHOICES,
    LIGHT_DEFAULT,
    MEASURED_MODELS,
    PRIOR_SOURCES,
    canonical,
)

from ._distributed import add_distributed_arguments, distributed_from_args
from ._main import (
    check_out_dir,
    fraction,
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
)
from ._options import add_auto_arguments, add_noise_level_argument, auto_options, fit_config

NOT_CONVERGED = 3  # exit status: outputs written, but the draws missed a convergence target
# resumable state under OUT_DIR: the fit's tiles, the MCMC chunks, the per-pixel widths' fit
# of a pooled map (and fit_<model>: a widened model's fit)
WORK_DIRS = ("fit", "mcmc", "fit_widths")
HELP = "posterior sampling: uncertainty maps with diagnostics (capture or BRDF file)"


def _crop(text: str) -> tuple[int, int, int, int]:
    try:
        rows, cols = text.split(",")
        r0, r1 = (int(v) for v in rows.split(":"))
        c0, c1 = (int(v) for v in cols.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--pixels takes a crop ROW0:ROW1,COL0:COL1 (e.g. 0:16,8:24), not {text!r}"
        ) from None
    if not (0 <= r0 < r1 and 0 <= c0 < c1):
        raise argparse.ArgumentTypeError(f"--pixels crop {text!r} is empty")
    return r0, r1, c0, c1


def _rhat(text: str) -> float:
    value = non_negative_float(text)
    if 0 < value <= 1:
        raise argparse.ArgumentTypeError(
            f"R-hat is >= 1: give a limit above 1, or 0; got {value:g}"
        )
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", type=Path, help="capture folder, or a measured BRDF file")
    p.add_argument("--out", type=Path, required=True, help="output folder (created)")
    p.add_argument(
        "--pixels", type=_crop, default=None, help="crop ROW0:ROW1,COL0:COL1 (default: all)"
    )
    p.add_argument("--downsample", type=positive_int, default=1, help="box-filter factor first")
    p.add_argument(
        "--model",
        default="auto",
        type=canonical,
        choices=["auto", *sorted(CAPTURE_MODELS)],
        help="capture model (jaxrefl models NAME describes one); auto (default): the "
        "candidate that best predicts held-out training photos, as jaxrefl fit",
    )
    add_auto_arguments(p)
    p.add_argument(
        "--light",
        default=LIGHT_DEFAULT,
        choices=LIGHT_CHOICES,
        help=f"a capture's flash, as jaxrefl fit --light (default {LIGHT_DEFAULT}): the "
        "posterior is sampled under the light the fit estimated",
    )
    add_noise_level_argument(p)
    p.add_argument(
        "--mcmc",
        default="flagged",
        choices=("flagged", "all", "none"),
        help="pixels sampled by HMC: those whose Laplace std is flagged unreliable, all, or none",
    )
    p.add_argument(
        "--audit",
        type=fraction,
        default=MAP_AUDIT,
        help="fraction of reliable pixels also sampled, to check the Laplace std, in [0, 1]",
    )
    p.add_argument(
        "--warmup",
        type=non_negative_int,
        default=None,
        help=f"warm-up steps per chain (default: {MAP_SAMPLER['num_warmup']} for a capture, "
        "HMCOptions().num_warmup for a BRDF file's HMC)",
    )
    p.add_argument(
        "--samples",
        type=positive_int,
        default=None,
        help=f"draws per chain (default: {MAP_SAMPLER['num_samples']} for a capture, "
        "HMCOptions().num_samples for a BRDF file's HMC)",
    )
    p.add_argument(
        "--chains",
        type=positive_int,
        default=None,
        help=f"chains per pixel (default: {MAP_SAMPLER['num_chains']} for a capture, "
        "HMCOptions().num_chains for a BRDF file's HMC)",
    )
    p.add_argument(
        "--gibbs-sweeps",
        type=non_negative_int,
        default=MAP_GIBBS["sweeps"],
        help="scans between kept draws where a capture's posterior allows Gibbs sampling "
        "(pooled, per-pixel lobes under a co-located flash; --warmup scaled by "
        "GibbsOptions.warmup_fraction); 0: HMC everywhere",
    )
    p.add_argument(
        "--rerun-rhat",
        type=_rhat,
        default=None,
        help=f"rerun pixels above this max R-hat, longer (0: no second pass; default {RERUN_RHAT})",
    )
    p.add_argument(
        "--priors",
        default=PRIOR_SOURCES[0],
        choices=PRIOR_SOURCES,
        help="a capture's lobe priors: estimated from its reliably fitted pixels "
        "(population), or the model's defaults",
    )
    p.add_argument(
        "--chunk",
        type=positive_int,
        default=MAP_CHUNK,
        help="MCMC pixels per compiled sampler call",
    )
    p.add_argument(
        "--time-limit",
        type=positive_float,
        default=None,
        metavar="SECONDS",
        help="start no MCMC chunk that would end past this many seconds: the pixels left "
        "keep their Laplace summary (method laplace_time_limit; exit status 3; the same "
        "command run again samples them); default: no limit",
    )
    p.add_argument(
        "--restart",
        action="store_true",
        help="discard the resumable work of an earlier run in OUT (its fit's tiles and MCMC "
        "chunks) and start over",
    )
    p.add_argument(
        "--keep-work",
        action="store_true",
        help="keep the fit's tiles and the MCMC chunks (OUT/fit, OUT/mcmc) after a whole map",
    )
    p.add_argument(
        "--brdf-model",
        default="ggx",
        type=canonical,
        choices=list(MEASURED_MODELS),
        help="model for a BRDF file (jaxrefl models NAME describes one)",
    )
    p.add_argument(
        "--sampler", default="emcee", choices=("emcee", "hmc"), help="sampler for a BRDF file"
    )
    p.add_argument(
        "--max-steps",
        type=positive_int,
        default=None,
        help="emcee's cap on steps (default: EmceeOptions().max_steps); it stops earlier once "
        "converged (exit status 3 if not)",
    )
    p.add_argument(
        "--walkers",
        type=positive_int,
        default=None,
        help="emcee walkers (default: max(32, 2 D + 2) for D parameters)",
    )
    p.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="MCMC chunks sampled at once, in threads (default: 2 on a CPU, 1 on a GPU); "
        "the map does not depend on it",
    )
    p.add_argument("--seed", type=non_negative_int, default=0, help="random seed (>= 0)")
    p.add_argument("--quiet", action="store_true", help="no progress bars or stage lines")
    add_distributed_arguments(p)


def work_dirs(out: Path) -> list[Path]:
    """The folders of resumable work under ``out`` (:data:`WORK_DIRS` and a widened model's
    ``fit_<model>``) that exist."""
    if not out.is_dir():
        return []
    names = {*WORK_DIRS, *(f"fit_{m}" for m in CAPTURE_MODELS)}
    return sorted(d for d in out.iterdir() if d.is_dir() and d.name in names)


def _json(path: Path, obj: Any) -> None:
    from jaxrefl._jsonsafe import report_json

    tmp = path.with_suffix(".tmp")
    tmp.write_text(report_json(obj, default=_default))
    tmp.replace(path)


def _default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def run(args: argparse.Namespace) -> int:
    import jax

    # Posteriors are computed in float64: log densities of thousands of observations
    # differ by less than float32's resolution between nearby draws.
    jax.config.update("jax_enable_x64", True)
    path = Path(args.path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such capture folder or BRDF file")
    check_out_dir(args.out)
    brdf_file = path.is_file() and path.suffix.lower() != ".json"
    dist = distributed_from_args(args)
    if dist is not None:
        if brdf_file:
            raise JaxreflError("--distributed splits a capture's tiles and chunks, not a BRDF file")
        dist.initialize()  # before any JAX computation
    if args.restart and (dist is None or dist.is_main):
        for d in work_dirs(args.out):
            shutil.rmtree(d)
    if dist is not None and args.restart:
        from jaxrefl.fit import process_barrier

        process_barrier("restart")  # no process reads OUT_DIR's work before it is cleared
    args.out.mkdir(parents=True, exist_ok=True)
    opts = _options(args, brdf_file)
    if brdf_file:
        report = _run_brdf(args, path, opts)
    else:
        try:
            report = _run_capture(args, path, opts, dist)
        except KeyboardInterrupt:
            work = ", ".join(str(d) for d in work_dirs(args.out))
            where = f": the work done so far is in {work}" if work else ""
            print(
                f"jaxrefl sample: stopped{where}; the same command run again resumes there",
                file=sys.stderr,
            )
            raise
    if dist is not None and not dist.is_main:
        return 0  # process 0 writes the outputs
    _json(args.out / "report.json", report)
    print(f"wrote {', '.join(report['files'])} and report.json to {args.out}/")
    limit = report.get("time_limit")
    if limit and limit["reached"]:
        print(
            f"jaxrefl sample: the time limit ({limit['limit_s']:g} s) left "
            f"{limit['pixels_left_laplace']} MCMC pixels their Laplace summary and "
            f"{limit['second_pass_pixels_left']} their first pass; the MCMC chunks done are "
            f"in {args.out / 'mcmc'}: the same command run again (or with a higher "
            "--time-limit) samples the rest",
            file=sys.stderr,
        )
        return NOT_CONVERGED
    if report.get("converged") is False:
        why = "; ".join(report["convergence"]["reasons"])
        print(f"jaxrefl sample: not converged: {why}{_raise_hint(args)}", file=sys.stderr)
        return NOT_CONVERGED
    return 0


def _raise_hint(args) -> str:
    if args.sampler == "emcee":
        return f" (raise --max-steps, now {args.max_steps})"
    return " (raise --samples or --warmup)"


def _progress(args) -> bool:
    """Progress bars go to stderr: shown unless --quiet or stderr is not a terminal."""
    return not args.quiet and sys.stderr.isatty()


def _options(args, brdf_file: bool):
    """The chains and HMC: the map's (:data:`jaxrefl.posterior.UNCERTAINTY_MAP_HMC`) for a
    capture, :class:`~jaxrefl.posterior.HMCOptions`' own for a BRDF file's HMC, with the
    flags given."""
    from jaxrefl.posterior import UNCERTAINTY_MAP_HMC, HMCOptions

    base = HMCOptions() if brdf_file else UNCERTAINTY_MAP_HMC
    given = {"num_warmup": args.warmup, "num_samples": args.samples, "num_chains": args.chains}
    return dataclasses.replace(base, **{k: v for k, v in given.items() if v is not None})


def _emcee(args):
    """emcee for a BRDF file: :class:`~jaxrefl.posterior.EmceeOptions`' own defaults, with
    the flags given (one default, said once)."""
    from jaxrefl.posterior import EmceeOptions

    cap = {} if args.max_steps is None else {"max_steps": args.max_steps}
    return EmceeOptions(n_walkers=args.walkers, seed=args.seed, **cap)


def _gibbs(args):
    """The map's Gibbs sampling (:data:`jaxrefl.posterior.UNCERTAINTY_MAP_GIBBS`) with
    ``--gibbs-sweeps``; None (HMC everywhere) for 0."""
    from jaxrefl.posterior import UNCERTAINTY_MAP_GIBBS

    if args.gibbs_sweeps == 0:
        return None
    return dataclasses.replace(UNCERTAINTY_MAP_GIBBS, sweeps=args.gibbs_sweeps)


def _job(args):
    """A capture's fit (:class:`~jaxrefl.svbrdf.FitJob`): float64, with the flags' model,
    model choice and light."""
    from jaxrefl import svbrdf

    return svbrdf.FitJob(
        model=args.model,
        config=fit_config(dtype="float64"),
        light=args.light,
        auto=auto_options(args.auto_candidates, args.auto_pixels, args.auto_seed),
        noise_level=args.noise_level,
    )


class _Stages:
    """Stage lines on stderr, each with the seconds since the command started."""

    def __init__(self, quiet: bool) -> None:
        import time

        self.quiet, self.t0, self.clock = quiet, time.perf_counter(), time.perf_counter

    def __call__(self, line: str) -> None:
        if not self.quiet:
            print(f"[{self.clock() - self.t0:7.1f} s] {line}", file=sys.stderr, flush=True)


def _run_capture(args, path: Path, opts, dist) -> dict:
    from jaxrefl import posterior as jp
    from jaxrefl import svbrdf
    from jaxrefl.io import load_capture

    stages = _Stages(args.quiet)
    job = _job(args)
    options = jp.AdaptiveOptions(
        mcmc=args.mcmc,
        audit=args.audit,
        hmc=opts,
        gibbs=_gibbs(args),
        rerun_rhat=(
            RERUN_RHAT
            if args.rerun_rhat is None
            else (args.rerun_rhat if args.rerun_rhat > 0 else None)
        ),
        chunk=args.chunk,
        seed=args.seed,
        workers=args.workers,
        time_limit_s=args.time_limit,
        priors=args.priors,
    )
    cap = load_capture(path)
    if args.downsample > 1:
        cap = cap.downsample(args.downsample)
    if args.pixels is not None:
        r0, r1, c0, c1 = args.pixels
        _k, h, w, _c = cap.shape
        if r1 > h or c1 > w:
            raise JaxreflError(f"--pixels {r0}:{r1},{c0}:{c1} exceeds the {h} x {w} capture")
        cap = cap.crop(r0, r1, c0, c1)
    res = svbrdf.uncertainty_maps(
        cap,
        job,
        options,
        progress=_progress(args),
        out_dir=args.out,  # the fit's tiles and MCMC chunks as they finish (resume)
        distributed=dist,
        log=stages,
    )
    if dist is not None and not dist.is_main:
        return {}
    t0 = time.perf_counter()
    stages("writing uncertainty.exr, posterior.nc and previews")
    files = [p.name for p in svbrdf.write_uncertainty(res, args.out)]
    res.timings["write_s"] = time.perf_counter() - t0
    stages(f"writing: done in {res.timings['write_s']:.1f} s")
    limit = res.time_limit_report()
    if not args.keep_work and not (limit and limit["reached"]):
        for d in work_dirs(args.out):
            shutil.rmtree(d)
    rep = res.report()
    head = {k: rep.pop(k) for k in ("model", "height", "width")}
    report = {
        "input": str(path),
        "kind": "capture",
        **head,
        "crop": list(args.pixels) if args.pixels else None,
        "downsample": args.downsample,
        **rep,
        "files": files,
    }
    m = rep["uncertainty"]
    above = f"pixels_rhat_above_{RERUN_RHAT:g}"  # the map's threshold's counts in the report
    print(
        f"{res.height} x {res.width} pixels: {m['method_counts']}; MCMC pixels with R-hat > "
        f"1.01: {m['mcmc']['pixels_rhat_above_1.01']}, > {RERUN_RHAT:g}: "
        f"{m['mcmc'][above]}, > 1.1: "
        f"{m['mcmc']['pixels_rhat_above_1.1']}, with divergences: "
        f"{m['mcmc']['pixels_with_divergences']}"
    )
    sp = m["mcmc"]["second_pass"]
    if sp["pixels"]:
        print(
            f"second pass on {sp['pixels']} pixels: max R-hat median "
            f"{sp['max_rhat_before']['median']:.3f} -> {sp['max_rhat_after']['median']:.3f}, "
            f"still above {RERUN_RHAT:g}: {sp[above + '_after']}"
        )
    tp = m["mcmc"]["third_pass"]
    if tp["pixels"]:
        print(
            f"third pass on the {tp['pixels']} still above: "
            f"{tp[above + '_after']} above {RERUN_RHAT:g} after it"
        )
    return report


def _run_brdf(args, path: Path, opts) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    from jaxrefl import measured
    from jaxrefl import posterior as jp

    sampler: jp.EmceeOptions | jp.HMCOptions
    if args.sampler == "emcee":
        sampler = _emcee(args)
    else:  # --sampler hmc: HMC, as asked, its chains seeded by --seed
        sampler = dataclasses.replace(opts, seed=args.seed)
    res = measured.sample_posterior(path, args.brdf_model, sampler, progress=_progress(args))
    files = [p.name for p in measured.write_posterior(res, args.out)]
    rep = res.report()
    print(f"{path.name} ({args.brdf_model}, {args.sampler}):")
    cert = res.fit.certificate
    if cert is not None:
        print(f"  started from the best of {cert.n_starts} starts ({cert.short()} agree)")
    for lab, v in rep["posterior"].items():
        print(
            f"  {lab:12s} {v['mean']:.4g} +- {v['std']:.2g}  "
            f"R-hat {v['rhat']:.3f}  ESS {v['ess_bulk']:.0f}"
        )
    c = rep["convergence"]
    chain = f"chain of {c['chain_length']} steps"
    if c["max_tau"]:
        chain += f" = {c['chain_length'] / c['max_tau']:.0f} x max tau ({c['max_tau']:.0f})"
    verdict = "converged" if c["converged"] else "NOT converged"
    print(
        f"  {verdict}: {chain}, max R-hat {c['max_rhat']:.3f}, min bulk ESS {c['min_ess_bulk']:.0f}"
    )
    return {"input": str(path), "kind": "brdf", **rep, "files": files}

"""Posterior sampling: uncertainty maps of a capture, or the posterior of a measured BRDF.

    jaxrefl sample CAPTURE_DIR --out OUT_DIR [--pixels R0:R1,C0:C1] [--downsample F]
                   [--model ggx] [--mcmc flagged|all|none] [--audit 0.02]
                   [--warmup N] [--samples N] [--chains N] [--rerun-rhat R] [--seed S]
    jaxrefl sample BRDF_FILE --out OUT_DIR [--brdf-model cook_torrance_ggx]
                   [--sampler emcee|hmc] [--steps N] [--walkers N]

A capture (any layout :func:`jaxrefl.io.load_capture` reads) is first fitted by the capture
job (:func:`jaxrefl.svbrdf.fit_capture`, float64: the LM optimum and Laplace covariance of
every pixel), then :func:`jaxrefl.posterior.adaptive_uncertainty` keeps Laplace where it is
flagged reliable and runs vmapped HMC on the flagged pixels and a random audit sample;
the pixels whose chains then disagree (max R-hat above ``--rerun-rhat``, 1.1; 0 turns it
off) run a second, longer pass (:func:`jaxrefl.posterior.longer_options`: twice the
warm-up, four steps per kept draw).
``--pixels`` restricts everything to a crop (rows R0:R1, columns C0:C1, after
``--downsample``). The noise scale is unknown (sampled per pixel, Jeffreys prior).
Writes OUT_DIR/uncertainty.exr (mean, std, q05, q95 per parameter, method, R-hat, ESS),
OUT_DIR/posterior.nc (ArviZ InferenceData of the MCMC pixels, with observed data and
posterior predictive draws) and OUT_DIR/report.json (counts by method, R-hat/ESS
distributions, divergences, Laplace/MCMC std ratios on the audit pixels, timings).

A measured BRDF file (Cornell .astm, MERL .binary, CURET; spectra converted to RGB) is
fitted with :func:`jaxrefl.measured.fit_model` (f_r cos theta_i residuals, 80 degree
limit) and its posterior sampled with emcee (default) or HMC, the noise scale unknown.
Writes OUT_DIR/posterior.nc, OUT_DIR/corner.png and OUT_DIR/report.json.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from ._main import positive_int

_EMCEE_KEYS = ("tau", "burn", "thin", "tau_reliable", "n_steps", "n_walkers")
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


def add_arguments(p: argparse.ArgumentParser) -> None:
    from jaxrefl.svbrdf import CAPTURE_MODELS

    p.add_argument("path", type=Path, help="capture folder, or a measured BRDF file")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--pixels", type=_crop, default=None, help="crop ROW0:ROW1,COL0:COL1")
    p.add_argument("--downsample", type=positive_int, default=1, help="box-filter factor first")
    p.add_argument("--model", default="ggx", choices=sorted(CAPTURE_MODELS), help="capture model")
    p.add_argument("--mcmc", default="flagged", choices=("flagged", "all", "none"))
    p.add_argument("--audit", type=float, default=0.02, help="fraction of reliable pixels audited")
    p.add_argument("--warmup", type=int, default=300, help="HMC warm-up steps per chain")
    p.add_argument("--samples", type=positive_int, default=500, help="HMC draws per chain")
    p.add_argument("--chains", type=positive_int, default=4, help="chains per pixel")
    p.add_argument(
        "--rerun-rhat",
        type=float,
        default=1.1,
        help="rerun pixels above this max R-hat, longer (0: no second pass)",
    )
    p.add_argument("--brdf-model", default="cook_torrance_ggx", help="model for a BRDF file")
    p.add_argument("--sampler", default="emcee", choices=("emcee", "hmc"), help="for a BRDF file")
    p.add_argument("--steps", type=positive_int, default=3000, help="emcee steps")
    p.add_argument("--walkers", type=positive_int, default=None, help="emcee walkers")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true", help="no progress bar")


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
    args.out.mkdir(parents=True, exist_ok=True)
    opts = _options(args)
    if path.is_file() and path.suffix.lower() != ".json":
        report = _run_brdf(args, path, opts)
    else:
        report = _run_capture(args, path, opts)
    _json(args.out / "report.json", report)
    print(f"wrote {', '.join(report['files'])} and report.json to {args.out}/")
    return 0


def _options(args):
    from jaxrefl.posterior import HMCOptions

    return HMCOptions(num_warmup=args.warmup, num_samples=args.samples, num_chains=args.chains)


def _run_capture(args, path: Path, opts) -> dict:
    import jax
    import numpy as np

    from jaxrefl import fit
    from jaxrefl import posterior as jp
    from jaxrefl.io import load_capture
    from jaxrefl.svbrdf import FitJob, capture_model, fit_capture, pixel_block

    cap = load_capture(path)
    if args.downsample > 1:
        cap = cap.downsample(args.downsample)
    if args.pixels is not None:
        r0, r1, c0, c1 = args.pixels
        _k, h, w, _c = cap.shape
        if r1 > h or c1 > w:
            raise ValueError(f"--pixels {r0}:{r1},{c0}:{c1} exceeds the {h} x {w} capture")
        cap = cap.crop(r0, r1, c0, c1)
    _k, h, w, c = cap.shape
    # one tile of the crop's size (a 4096-pixel default tile would fit mostly padding)
    job = FitJob(model=args.model, dtype="float64", tile_pixels=min(4096, h * w))
    t0 = time.perf_counter()
    cf = fit_capture(cap, job, progress=not args.quiet)
    t_fit = time.perf_counter() - t0
    model, space = capture_model(args.model, channels=c, alpha_min=cf.extra["alpha_min"])
    lp = jp.log_posterior(model, space, fit.GaussianNoise(None))
    data = pixel_block(cap, 0, h * w, dtype=np.float64)
    theta = np.asarray(cf.theta, np.float64)
    std = np.stack([_map(cf, lab, "_std").reshape(-1) for lab in space.labels], -1)
    ok = np.all(np.isfinite(theta), -1)
    dn = np.asarray(space.dnatural(jax.numpy.asarray(np.where(ok[:, None], theta, 0.0))))
    theta_std = std / np.abs(dn)  # exact for elementwise bijections (delta method reversed)
    flag = cf.maps["laplace_flag"].reshape(-1)
    noise0 = cf.maps["noise_std"].reshape(-1)
    noise0 = np.where(np.isfinite(noise0) & (noise0 > 0), noise0, 1e-2)
    t1 = time.perf_counter()
    aopts = jp.AdaptiveOptions(
        mcmc=args.mcmc,
        audit=args.audit,
        hmc=opts,
        rerun_rhat=args.rerun_rhat if args.rerun_rhat > 0 else None,
        seed=args.seed,
    )
    umap = jp.adaptive_uncertainty(lp, data, theta, theta_std, flag, aopts, noise_scale=noise0)
    t_post = time.perf_counter() - t1
    files = ["uncertainty.exr"]
    jp.write_uncertainty_exr(
        args.out / "uncertainty.exr", umap, h, w, metadata={"model": args.model}
    )
    if umap.samples is not None:
        idx = umap.mcmc_pixels
        sub = jax.tree.map(lambda a: a[idx], data)
        ppc = jp.posterior_predictive(lp, umap.samples, sub, n_draws=50, seed=args.seed)
        rows, cols = np.divmod(idx, w)
        idata = jp.to_inference_data(
            umap.samples,
            sub,
            pixels=idx,
            predictive=ppc,
            attrs={"rows": rows.tolist(), "cols": cols.tolist(), "width": w, "height": h},
        )
        jp.save_netcdf(idata, args.out / "posterior.nc")
        files.append("posterior.nc")
    report = {
        "input": str(path),
        "kind": "capture",
        "model": args.model,
        "height": h,
        "width": w,
        "crop": list(args.pixels) if args.pixels else None,
        "downsample": args.downsample,
        "noise": "Gaussian, unknown scale per pixel (Jeffreys prior)",
        "priors": {b.name: repr(p) for b, p in zip(space.blocks, lp.priors, strict=True)},
        "sampler": {**vars(opts)},
        "second_pass": {
            "rerun_rhat": args.rerun_rhat if args.rerun_rhat > 0 else None,
            "options": {**vars(jp.longer_options(opts))},
        },
        "fit_report": {k: cf.report[k] for k in ("status_counts", "laplace_flag_counts")},
        "uncertainty": umap.report(),
        "timings": {"fit_s": t_fit, "posterior_s": t_post},
        "files": files,
    }
    m = umap.report()
    print(
        f"{h} x {w} pixels: {m['method_counts']}; MCMC pixels with R-hat > 1.01: "
        f"{m['mcmc']['pixels_rhat_above_1.01']}, > 1.1: {m['mcmc']['pixels_rhat_above_1.1']}, "
        "with divergences: "
        f"{m['mcmc']['pixels_with_divergences']}"
    )
    sp = m["mcmc"]["second_pass"]
    if sp["pixels"]:
        print(
            f"second pass on {sp['pixels']} pixels: max R-hat median "
            f"{sp['max_rhat_before']['median']:.3f} -> {sp['max_rhat_after']['median']:.3f}, "
            f"still above 1.1: {sp['pixels_rhat_above_1.1_after']}"
        )
    return report


def _map(cf, label: str, suffix: str):
    """The capture job's map of ``label`` (``albedo.R`` -> ``albedo_std.R``, ``alpha`` ->
    ``alpha.std``), as :class:`jaxrefl.svbrdf.CaptureFit` names them."""
    if "." in label:
        base, ch = label.rsplit(".", 1)
        return cf.maps[f"{base}{suffix}.{ch}"]
    return cf.maps[f"{label}.{suffix[1:]}"]


def _run_brdf(args, path: Path, opts) -> dict:
    import jax
    import jax.numpy as jnp
    import matplotlib

    matplotlib.use("Agg")
    import numpy as np

    from jaxrefl import fit
    from jaxrefl import posterior as jp
    from jaxrefl.measured import build_model, fit_model, load_measured, restrict, to_rgb

    m = load_measured(path)
    if m.wavelengths_nm is not None:
        m = to_rgb(m)
    m = restrict(m, 80.0)
    model = build_model(args.brdf_model)
    t0 = time.perf_counter()
    mf = fit_model(model, m, name=args.brdf_model, cosine=True, dtype="float64", timing=False)
    t_fit = time.perf_counter() - t0
    res = mf.result
    space = res.space
    wi, wo, vals = np.asarray(m.wi), np.asarray(m.wo), np.asarray(m.values)
    cos = np.maximum(wi[:, 2], 0.0)[:, None] * np.ones_like(vals)
    good = np.isfinite(vals) & (wi[:, 2:3] > 0) & (wo[:, 2:3] > 0)
    data = fit.pixel_data(
        np.where(good, vals * cos, 0.0), wi, wo, scale=cos, weight=good.astype(float)
    )
    lp = jp.log_posterior(model, space, fit.GaussianNoise(None))
    theta = np.asarray(res.theta, np.float64)
    n_used = float(np.sum(good))
    s0 = float(np.sqrt(2 * mf.cost / max(n_used - space.size, 1.0)))
    th0 = np.asarray(lp.init_theta(jnp.asarray(theta), noise_scale=s0))
    if args.sampler == "emcee":
        s = jp.sample_emcee(
            lp,
            th0,
            (data,),
            natural=lp.natural,
            labels=lp.labels,
            n_walkers=args.walkers,
            n_steps=args.steps,
            progress=not args.quiet,
            seed=args.seed,
        )
    else:
        batch = jax.tree.map(lambda a: a[None], data)
        s = jp.sample_pixels(lp, batch, th0[None], options=opts, seed=args.seed)
    dg = jp.diagnostics(s)
    idata = jp.to_inference_data(s, jax.tree.map(lambda a: a[None], data))
    jp.save_netcdf(idata, args.out / "posterior.nc")
    fig = jp.plot_corner(s, 0)
    fig.savefig(args.out / "corner.png", dpi=80)
    x = s.flat(0)
    summary = {
        lab: {
            "mean": float(np.mean(x[:, j])),
            "std": float(np.std(x[:, j], ddof=1)),
            "q05": float(np.quantile(x[:, j], 0.05)),
            "q95": float(np.quantile(x[:, j], 0.95)),
            "rhat": float(dg["rhat"][0, j]),
            "ess_bulk": float(dg["ess_bulk"][0, j]),
            "ess_tail": float(dg["ess_tail"][0, j]),
        }
        for j, lab in enumerate(s.labels)
    }
    print(f"{path.name} ({args.brdf_model}, {args.sampler}):")
    for lab, v in summary.items():
        print(
            f"  {lab:12s} {v['mean']:.4g} +- {v['std']:.2g}  "
            f"R-hat {v['rhat']:.3f}  ESS {v['ess_bulk']:.0f}"
        )
    return {
        "input": str(path),
        "kind": "brdf",
        "model": args.brdf_model,
        "sampler": args.sampler,
        "samples_used": int(n_used),
        "fit": {"params": mf.to_dict()["params"], "cost": mf.cost, "status": mf.status},
        "noise": "Gaussian on f_r cos(theta_i), unknown scale (Jeffreys prior)",
        "posterior": summary,
        "diagnostics": {
            "max_rhat": float(np.max(dg["rhat"])),
            "min_ess_bulk": float(np.min(dg["ess_bulk"])),
            "min_ess_tail": float(np.min(dg["ess_tail"])),
            "divergences": int(dg["divergences"][0]),
            "acceptance": float(dg["acceptance"][0]),
            **({k: s.extra[k] for k in _EMCEE_KEYS} if args.sampler == "emcee" else {}),
        },
        "timings": {"fit_s": t_fit, "compile_s": s.compile_s, "sample_s": s.run_s},
        "files": ["posterior.nc", "corner.png"],
    }

"""Calibration on real photos: do 50% and 90% predictive intervals cover what they claim?

For ``bath_tile`` and ``yellow_box`` (``../shared/data/svbrdf_flash``, read at ``--size``),
every photo is held out in turn: the job (``--model``, ``pooled`` by default: the model
``auto`` chose in every fold of ``benchmarks/real_captures.py``) is fitted on the other
photos, the model-discrepancy term is estimated from those training photos alone
(:func:`jaxrefl.svbrdf.estimate_discrepancy`), and the posterior predictive distribution of
the held-out photo's pixels (:func:`jaxrefl.svbrdf.predictive`: Laplace parameter
uncertainty + the noise + the discrepancy; for ``pooled`` the noise and discrepancy are one
variance function of the radiance, by default) gives central 50% and 90% intervals. The
table gives, per held-out photo, the share of its uncensored observations inside them: with
the default terms, without the discrepancy term, over the pixels not flagged as
misspecified (:class:`jaxrefl.svbrdf.ModelCheck`), and with the other noise term.

Then a synthetic capture (the demo's flash rig, ``--synthetic-size`` pixels a side, GGX +
Lambert, grey F0 drawn up to 0.5, Gaussian noise of std 0.004) is fitted with photo 8 held
out by ``ggx`` (grey F0 up to 0.25: half the pixels lie beyond its range) and by
``ggx_rgb`` (coloured F0 up to 1, the real captures' material model): coverage of the true
parameters by the Laplace 50% and 90% intervals (:func:`jaxrefl.svbrdf.laplace_interval`:
Student t with n_used - P degrees of freedom in the unconstrained space, the noise scale
being estimated per pixel, mapped to natural units), and of the held-out photo by the
predictive intervals, split by the flag. Then the same with the intervals a user gets from
``jaxrefl sample CAPTURE`` with its default settings: the uncertainty map's q05-q95 (the
Laplace marginals where its flags call them reliable, MCMC on the other pixels under the
population priors; :func:`jaxrefl.svbrdf.uncertainty_maps`).

    python benchmarks/predictive_coverage.py [--size 256] [--captures bath_tile,yellow_box]
        [--model pooled] [--synthetic-size 32] [--no-posterior] [--no-write]

It prints the tables and writes them, dated and with the machine, to the section
``predictive_coverage`` of ``docs/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _common import flash_capture, run_and_record, table  # noqa: E402
from capture_family import demo_rig_capture  # noqa: E402

LEVELS = (0.5, 0.9)
SYN_SIGMA = 0.004
SYN_HELD = 8


def _pct(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{100 * x:.1f}"


BLOCK = 32  # pixels on a side of the blocks whose median ratios measure the spread


def _photo_gain(pred, photo: int, shape: tuple[int, int]) -> tuple[float, float, dict]:
    """(the held-out photo's median ratio of observed to predicted radiance over its
    uncensored values, the interquartile range of that ratio's medians over BLOCK x BLOCK
    blocks of the image, {level: coverage of the intervals scaled by the photo's ratio}).
    A ratio far from 1 with a small spread is a photo-wide offset (flash power, exposure)
    shared by all of the photo's pixels; a large spread is a misfit that varies over the
    image. The scaled coverage says how much of a miss the offset explains: a diagnostic
    only, it uses the held-out photo itself."""
    m, y = pred.mean[:, photo], pred.obs[:, photo]
    use = pred.value[:, photo] & np.isfinite(m) & (m > 0)
    gain = float(np.median(y[use] / m[use]))
    h, w = shape
    ratio = np.where(use, y / np.where(use, m, 1.0), np.nan).reshape(h, w, -1)
    blocks = [
        np.nanmedian(ratio[a : a + BLOCK, b : b + BLOCK])
        for a in range(0, h, BLOCK)
        for b in range(0, w, BLOCK)
        if np.any(np.isfinite(ratio[a : a + BLOCK, b : b + BLOCK]))
    ]
    q25, q75 = np.percentile(blocks, [25, 75])
    cov = {}
    for lv in LEVELS:
        lo, hi = pred.interval(lv)
        inside = (y >= gain * lo[:, photo]) & (y <= gain * hi[:, photo])
        cov[lv] = float(np.mean(inside[use]))
    return gain, float(q75 - q25), cov


def real_capture(name: str, size: int, model: str) -> None:
    from jaxrefl.svbrdf import (
        DiscrepancyOptions,
        FitJob,
        estimate_discrepancy,
        fit_capture,
        predictive,
    )

    cap = flash_capture(name, size)
    k = cap.n_photos
    rows = []
    tot = {key: [0.0, 0] for key in ("all50", "all90", "ok50", "ok90", "fn50", "fn90")}
    fit_s = disc_s = pred_s = compile_s = 0.0
    for i in range(k):
        t0 = time.perf_counter()
        cf = fit_capture(cap, FitJob(model=model, holdout=(i,)))
        t1 = time.perf_counter()
        disc = estimate_discrepancy(cap, cf)
        t2 = time.perf_counter()
        pred = predictive(cap, cf, disc)
        alt = not disc.replaces_noise
        other = DiscrepancyOptions(replace_noise=alt)
        vfn = predictive(cap, cf, estimate_discrepancy(cap, cf, other))
        t3 = time.perf_counter()
        compile_s += cf.report["timings"]["compile_s"]
        fit_s += t1 - t0 - cf.report["timings"]["compile_s"]
        disc_s += t2 - t1
        pred_s += t3 - t2
        ok = ~pred.misspecified
        c = {}
        for lv in LEVELS:
            c[f"all{lv}"], n_all = pred.coverage(i, lv)
            c[f"nod{lv}"], _ = pred.coverage(i, lv, terms=("param", "noise"))
            c[f"ok{lv}"], n_ok = pred.coverage(i, lv, ok)
            c[f"fn{lv}"], _ = vfn.coverage(i, lv)
        for tag, n in (("all", n_all), ("ok", n_ok), ("fn", n_all)):
            for lv in LEVELS:
                key = f"{tag}{round(100 * lv)}"
                if np.isfinite(c[f"{tag}{lv}"]):
                    tot[key][0] += c[f"{tag}{lv}"] * n
                    tot[key][1] += n
        med = float(np.nanmedian(pred.mean[:, i]))
        gain, spread, at_gain = _photo_gain(pred, i, cap.shape[1:3])
        rows.append(
            [
                str(i),
                _pct(c["all0.5"]),
                _pct(c["all0.9"]),
                _pct(c["nod0.5"]),
                _pct(c["nod0.9"]),
                _pct(c["ok0.5"]),
                _pct(c["ok0.9"]),
                _pct(c["fn0.5"]),
                _pct(c["fn0.9"]),
                f"{100 * np.mean(pred.misspecified):.1f}",
                f"{np.sqrt(float(disc(med))):.4f}",
                f"{np.sqrt(np.nanmedian(pred.noise_var[:, i])):.4f}",
                f"{np.sqrt(np.nanmedian(pred.param_var[:, i])):.4f}",
                f"{gain:.3f}",
                f"{spread:.3f}",
                _pct(at_gain[0.5]),
                _pct(at_gain[0.9]),
                str(n_all),
            ]
        )
        print(f"  {name}: photo {i} held out ({t3 - t0:.0f} s)", file=sys.stderr, flush=True)

    def pooled(key):
        s, n = tot[key]
        return s / n if n else float("nan")

    rows.append(
        [
            "all",
            _pct(pooled("all50")),
            _pct(pooled("all90")),
            "",
            "",
            _pct(pooled("ok50")),
            _pct(pooled("ok90")),
            _pct(pooled("fn50")),
            _pct(pooled("fn90")),
            "",
            "",
            "",
            "",
            "",
            "",
            "",
            "",
            "",
        ]
    )
    print(f"### {name}, {size} x {size}, model `{model}`, each of {k} photos held out in turn")
    print()
    print(
        table(
            [
                "held-out photo",
                "50% cover",
                "90% cover",
                "50% no disc.",
                "90% no disc.",
                "50% unflagged",
                "90% unflagged",
                "50% other noise",
                "90% other noise",
                "flagged %",
                "disc. std at median",
                "noise std",
                "param std (median)",
                "obs / pred",
                "its spread",
                "50% at its gain",
                "90% at its gain",
                "values",
            ],
            rows,
        )
    )
    print()
    print(
        f"Coverage in %, of the held-out photo's uncensored observations (target 45-55 and "
        f"85-95). Seconds over the {k} folds: fit {fit_s:.0f} (compile {compile_s:.0f} apart), "
        f"discrepancy {disc_s:.0f}, both predictives {pred_s:.0f}. Columns: all three terms; "
        "parameter + noise only; all three over the pixels not flagged; 'other noise': the other "
        "noise term (for `pooled`, whose default replaces its one noise scale by a variance "
        "function of the radiance measured on held-out training photos, the fit's own scale "
        "plus the discrepancy: `DiscrepancyOptions(replace_noise=False)`); 'obs / pred': "
        "the held-out photo's median ratio of observed to predicted radiance; 'its spread': the "
        f"interquartile range of that ratio's medians over {BLOCK} x {BLOCK}-pixel blocks. A "
        "ratio far from 1 with a small spread is a photo-wide offset (flash power, exposure) "
        "that all the photo's pixels share, which no variance of the radiance alone can "
        "centre; a large spread, a misfit that varies over the image. 'at its gain': the "
        "coverage with the intervals scaled by the photo's ratio (a diagnostic that uses the "
        "held-out photo itself)."
    )
    print()


# The synthetic capture's models: the dielectric one whose grey F0 stops at 0.25, and the
# coloured-specular one whose F0 reaches 1 (the material model of the real captures).
SYN_MODELS = {"ggx": 0.25, "ggx_rgb": 1.0}


def synthetic(size: int, model: str) -> None:
    from jaxrefl.svbrdf import FitJob, estimate_discrepancy, fit_capture, laplace_interval
    from jaxrefl.svbrdf import predictive as predict

    cap, truth = demo_rig_capture(size, SYN_SIGMA)
    t0 = time.perf_counter()
    cf = fit_capture(cap, FitJob(model=model, holdout=(SYN_HELD,)))
    pred = predict(cap, cf, estimate_discrepancy(cap, cf))
    wall = time.perf_counter() - t0
    _model, space = cf.model()
    n = cf.theta.shape[0]
    boxes = {lv: laplace_interval(cf, lv, space) for lv in LEVELS}
    want = {
        "albedo.R": truth["albedo"][..., 0],
        "albedo.G": truth["albedo"][..., 1],
        "albedo.B": truth["albedo"][..., 2],
        "alpha": truth["alpha"],
    }
    for c, lab in enumerate("RGB"):
        want["specular." + lab] = truth["specular"][..., c]
    want["specular"] = truth["specular"][..., 0]
    spec = "specular" if "specular" in space.labels else "specular.R"
    true = np.stack([want[lab].reshape(-1) for lab in space.labels], -1)
    flag = pred.misspecified
    cap_f0 = SYN_MODELS[model]
    in_range = truth["specular"][..., 0].reshape(-1) <= cap_f0
    groups = {
        "unflagged": ~flag,
        "flagged": flag,
        "all": np.ones(n, bool),
        "F0 in model range": in_range,
        "F0 beyond 0.25": truth["specular"][..., 0].reshape(-1) > 0.25,
    }
    rows = []
    for gname, sel in groups.items():
        cells = [gname, str(int(np.sum(sel)))]
        for lab in ("albedo.R", spec, "alpha"):
            j = space.labels.index(lab)
            for lv in LEVELS:
                lo, hi = boxes[lv][lab]
                ok = sel & np.isfinite(lo) & np.isfinite(hi)
                inside = (true[:, j] >= lo) & (true[:, j] <= hi)
                cells.append(_pct(float(np.mean(inside[ok]))) if ok.any() else "-")
        for lv in LEVELS:
            cov, _n = pred.coverage(SYN_HELD, lv, sel)
            cells.append(_pct(cov))
        rows.append(cells)
    print(
        f"### Synthetic capture, {size} x {size}, grey F0 uniform in [0, 0.5], model `{model}` "
        f"(F0 <= {cap_f0:g}), noise std {SYN_SIGMA}, photo {SYN_HELD} held out"
    )
    print()
    heads = ["pixels", "count"]
    for lab in ("albedo.R", "F0" if spec == "specular" else "F0.R", "alpha"):
        heads += [f"{lab} 50%", f"{lab} 90%"]
    heads += ["photo 50%", "photo 90%"]
    print(table(heads, rows))
    print()
    counts = pred.check_counts()
    print(
        "Coverage in % of the true parameter by its Laplace interval, and of the held-out "
        "photo by the predictive interval. Flags: "
        + ", ".join(f"{k} {v}" for k, v in counts.items())
        + f" of {n} pixels; {wall:.0f} s with compilation."
    )
    print()


def _prior_line(summary: dict) -> str:
    """The map's priors in a few words (``CaptureUncertainty.prior_summary``)."""
    if summary.get("source") != "population":
        return f"{summary.get('source', '-')} ({summary.get('why', '')})".replace(" ()", "")
    f0 = summary["specular"]
    sd = np.sqrt(np.diag(np.asarray(f0["cov"])))
    return (
        f"population of {summary['pixels']} fitted pixels: F0 mean "
        f"{np.round(f0['mean'], 3).tolist()}, std {np.round(sd, 3).tolist()}; alpha median "
        f"{summary['alpha']['median']:.3f}, log std {summary['alpha']['log_std']:.2f}"
    )


def synthetic_map(size: int, model: str) -> None:
    """The 90% intervals a user gets from ``jaxrefl sample CAPTURE`` on the synthetic
    capture (the uncertainty map's q05-q95: the Laplace Gaussian where its flags call it
    reliable, MCMC elsewhere and on an audit sample), split as in :func:`synthetic`.
    Needs ``jax_enable_x64`` (the map's fit is float64)."""
    from jaxrefl import fit
    from jaxrefl import posterior as jp
    from jaxrefl.posterior import MCMC_METHODS
    from jaxrefl.svbrdf import FitJob, predictive, uncertainty_maps

    cap, truth = demo_rig_capture(size, SYN_SIGMA)
    t0 = time.perf_counter()
    job = FitJob(model=model, holdout=(SYN_HELD,), config=fit.FitConfig(dtype=np.float64))
    # the sampler settings of `jaxrefl sample`'s defaults (4 chains of 500 draws; the Gibbs
    # samplers where the posterior allows), its default priors (population_priors)
    opts = jp.AdaptiveOptions(hmc=jp.HMCOptions(), gibbs=jp.GibbsOptions(sweeps=2))
    cu = uncertainty_maps(cap, job, opts)
    wall = time.perf_counter() - t0
    flag = predictive(cap, cu.fit).misspecified
    m = cu.map
    true = {
        "albedo.R": truth["albedo"][..., 0],
        "specular": truth["specular"][..., 0],
        "specular.R": truth["specular"][..., 0],
        "alpha": truth["alpha"],
    }
    spec = "specular" if "specular" in m.labels else "specular.R"
    groups = {
        "unflagged": ~flag,
        "flagged": flag,
        "all": np.ones(flag.size, bool),
        "F0 in model range": truth["specular"][..., 0].reshape(-1) <= SYN_MODELS[model],
    }
    mcmc = np.isin(m.method, MCMC_METHODS)
    rows = []
    for gname, sel in groups.items():
        cells = [gname, str(int(np.sum(sel))), str(int(np.sum(sel & mcmc)))]
        for lab in ("albedo.R", spec, "alpha"):
            j = m.labels.index(lab)
            t = true[lab].reshape(-1)
            ok = sel & np.isfinite(m.q05[:, j]) & np.isfinite(m.q95[:, j])
            inside = (t >= m.q05[:, j]) & (t <= m.q95[:, j])
            cells.append(_pct(float(np.mean(inside[ok]))) if ok.any() else "-")
        rows.append(cells)
    print(
        f"### Synthetic capture, {size} x {size}, model `{model}`: the uncertainty map's 90% "
        "intervals (`uncertainty_maps`)"
    )
    print()
    f0 = "F0" if spec == "specular" else "F0.R"
    heads = ["pixels", "count", "MCMC", "albedo.R 90%", f"{f0} 90%", "alpha 90%"]
    print(table(heads, rows))
    print()
    print(
        "Coverage in % of the true parameter by the map's q05-q95 (Laplace where reliable, "
        f"MCMC on the other pixels and an audit sample), the same capture and held-out photo "
        f"as above; methods: {m.method_counts()}; sampler {m.timings.get('sampler', '-')}; "
        f"priors: {_prior_line(cu.prior_summary)}; {wall:.0f} s with compilation."
    )
    print()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--captures", default="bath_tile,yellow_box")
    ap.add_argument("--model", default="pooled")
    ap.add_argument("--synthetic-size", type=int, default=32)
    ap.add_argument(
        "--no-posterior",
        dest="posterior",
        action="store_false",
        help="skip the uncertainty map's intervals on the synthetic capture",
    )
    ap.add_argument(
        "--only-family",
        action="store_true",
        help="only the uncertainty maps of the capture family and the real captures "
        "(_family_maps.py: the coverage of the truth per generated capture)",
    )
    ap.add_argument("--members", default=None, help="family members, comma-separated (all)")
    ap.add_argument(
        "--cli",
        action="store_true",
        help="with --only-family: also jaxrefl sample per capture, cold and warm compile cache",
    )
    args = ap.parse_args()
    if args.only_family:
        from _family_maps import run_family

        members = None if args.members is None else args.members.split(",")
        run_family(members)
        if args.cli:
            from _family_maps import run_family_cli

            run_family_cli(members)
        return 0
    print(
        "Noise model: additive Gaussian, independent between photos and channels. The "
        "per-pixel models: each pixel's residual variance plus a discrepancy variance "
        "tau^2(radiance); `pooled` (one noise scale for the capture): a variance function "
        "v(radiance) in its place, and its Laplace parameter variance (formed with the one "
        "scale) rescaled to the errors' own variance at the pixel's radiances. Both are "
        "estimated from the training photos' leave-one-photo-out errors only "
        "(median-matched per radiance bin)."
    )
    print()
    for name in [c for c in args.captures.split(",") if c]:
        real_capture(name, args.size, args.model)
    if args.synthetic_size > 0:
        for model in SYN_MODELS:
            synthetic(args.synthetic_size, model)
        if args.posterior:
            import jax

            jax.config.update("jax_enable_x64", True)
            for model in SYN_MODELS:
                synthetic_map(args.synthetic_size, model)
    return 0


if __name__ == "__main__":
    if "--only-family" in sys.argv:
        sys.exit(
            run_and_record("posterior_speed_family", "Uncertainty maps of a capture family", main)
        )
    sys.exit(run_and_record("predictive_coverage", "Predictive coverage", main))

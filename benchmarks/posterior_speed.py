"""Posterior sampling speed and Laplace calibration, GGX + Lambert, K = 32, float64.

    python benchmarks/posterior_speed.py [--pixels 200] [--emcee-pixels 4] [--map-size 256]

1. Batched HMC (vmapped over pixels, per-chain adaptation, 16 leapfrog steps) on N
   simulated flash pixels against emcee (32 walkers, vectorised jitted log-prob) on a
   subset of the same pixels, in the same run: effective samples per second per pixel,
   the minimum over parameters of ArviZ's bulk ESS divided by the pixel's share of the wall
   time (compilation excluded and printed apart). Target: batched >= 5x emcee.
2. Laplace vs NUTS: ratio of marginal standard deviations on the pixels Laplace flags
   reliable (identifiable), median and 5-95% range per parameter.
3. Wall time of an adaptive uncertainty map (Laplace everywhere, ``UNCERTAINTY_MAP_HMC`` on the
   flagged pixels and a 2% audit: HMC, or the Gibbs samplers where the posterior allows;
   fixed-size chunks of at most ``--map-chunk`` pixels, the default number at once; the
   second pass on the pixels left above R-hat 1.05; the priors and Laplace marginals of
   ``svbrdf.uncertainty_maps``) of a synthetic ``jaxrefl demo``
   capture of ``--map-size`` squared, first, in a fresh process (every program compiled),
   then of the real captures bath_tile and yellow_box at that size (needs
   $JAXREFL_SHARED_DATA); ``--map-rows R`` crops the first R rows and extrapolates
   (labelled EXTRAPOLATED); ``--map-size 0`` skips it.
4. emcee SBC with ``--emcee-sbc`` simulations (the test runs 24).

    python benchmarks/posterior_speed.py --only-map --map-size 256 --map-rows 4
    python benchmarks/posterior_speed.py --only-emcee-sbc --emcee-sbc 200
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import demo_capture, run_and_record, table  # noqa: E402

from jaxrefl import fit, svbrdf  # noqa: E402
from jaxrefl import posterior as jp  # noqa: E402

K = 32
F64 = fit.FitConfig(dtype=np.float64)
SIGMA = 0.01


def simulate(n: int, seed: int = 0):
    """n pixels: albedo U(0.05, 0.8), specular U(0.02, 0.12), alpha = r^2 with r U(0.2, 0.7);
    co-located flash within 45 degrees of the normal; Gaussian noise SIGMA."""
    model, space = svbrdf.capture_model("ggx", channels=3, alpha_min=0.01)
    rng = np.random.default_rng(seed)
    params = {
        "albedo": rng.uniform(0.05, 0.8, (n, 3)),
        "specular": rng.uniform(0.02, 0.12, (n, 1)),
        "alpha": rng.uniform(0.2, 0.7, n) ** 2,
    }
    theta = np.asarray(space.from_natural(params, dtype=jnp.float64))
    th = np.arccos(rng.uniform(np.cos(np.radians(45)), 1.0, (n, K)))
    ph = rng.uniform(0, 2 * np.pi, (n, K))
    wi = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    scale = np.repeat(wi[..., 2:3], 3, -1) * 1.5
    lp = jp.log_posterior(model, space, fit.GaussianNoise(SIGMA))
    d0 = fit.pixel_data(np.zeros((n, K, 3)), wi, None, scale=scale)
    pred = np.asarray(jax.jit(jax.vmap(lp.predict))(jnp.asarray(theta), d0))
    data = fit.pixel_data(pred + SIGMA * rng.normal(size=pred.shape), wi, None, scale=scale)
    return model, space, lp, theta, data


def ess_per_s(samples: jp.Samples, n_pixels: int) -> np.ndarray:
    """(N,) min-over-parameters bulk ESS per second of the pixel's share of the run."""
    dg = jp.diagnostics(samples)
    return dg["min_ess_bulk"] / (samples.run_s / n_pixels)


def part_speed(args, model, space, lp, theta, data):
    n = data.obs.shape[0]
    r = fit.fit_pixels(model, data, space=space, noise=fit.GaussianNoise(SIGMA))
    res = fit.make_residual(model, space, fit.GaussianNoise(SIGMA))
    lap = fit.laplace(r, data, residual=res, options=fit.LaplaceOptions(noise="known"))
    th0 = np.asarray(r.theta)
    tsd = np.asarray(lap.theta_std)
    opts = jp.HMCOptions(num_warmup=300, num_samples=500, num_chains=2, batch_size=100)
    s = jp.sample_pixels(lp, data, th0, theta_std=tsd, options=opts, timing=True)
    hmc = ess_per_s(s, n)
    rows = [
        [
            "batched HMC (16 leapfrog, dense metric)",
            n,
            f"{s.compile_s:.1f}",
            f"{s.run_s:.2f}",
            f"{np.median(hmc):,.0f}",
            f"{np.quantile(hmc, 0.05):,.0f}",
        ]
    ]
    em = []
    t_em, c_em = 0.0, 0.0
    for i in range(args.emcee_pixels):
        d = jax.tree.map(lambda a, i=i: a[i], data)
        e = jp.sample_emcee(lp, th0[i], (d,), jp.EmceeOptions(32, 2000), theta_std=tsd[i])
        em.append(ess_per_s(e, 1)[0])
        t_em += e.run_s
        c_em = max(c_em, e.compile_s)
    em = np.asarray(em)
    rows.append(
        [
            "emcee (32 walkers x 2000 steps)",
            args.emcee_pixels,
            f"{c_em:.1f}",
            f"{t_em:.2f}",
            f"{np.median(em):,.0f}",
            f"{np.quantile(em, 0.05):,.0f}",
        ]
    )
    same = hmc[: args.emcee_pixels]
    print(
        table(
            [
                "sampler",
                "pixels",
                "compile s",
                "run s",
                "ESS/s/pixel median",
                "ESS/s/pixel 5%",
            ],
            rows,
        )
    )
    print(
        f"\nratio batched / emcee (median ESS/s per pixel): {np.median(hmc) / np.median(em):.1f}x; "
        f"on the same {args.emcee_pixels} pixels: {np.median(same) / np.median(em):.1f}x "
        f"(target >= 5x)"
    )
    return r, lap, s


def part_window(args) -> None:
    """The warm-up's metric window: end at 90% of warm-up (Stan) against 75% (the default).

    Same pixels, keys, starts and gradients; per pixel the mean acceptance during sampling
    (target 0.8) and the min-over-parameters bulk and tail ESS."""
    model, space, lp, _, data = simulate(args.window_pixels, seed=1)
    r = fit.fit_pixels(model, data, space=space, noise=fit.GaussianNoise(SIGMA))
    res = fit.make_residual(model, space, fit.GaussianNoise(SIGMA))
    lap = fit.laplace(r, data, residual=res, options=fit.LaplaceOptions(noise="known"))
    rows = []
    for end in (0.9, 0.75):
        opts = jp.HMCOptions(num_chains=2, batch_size=100, metric_window_end=end)
        s = jp.sample_pixels(
            lp, data, np.asarray(r.theta), theta_std=np.asarray(lap.theta_std), options=opts
        )
        dg = jp.diagnostics(s)
        acc = np.asarray(dg["acceptance"])
        bulk, tail = np.asarray(dg["min_ess_bulk"]), np.asarray(dg["min_ess_tail"])
        rows.append(
            [
                f"{end:.2f}",
                f"{np.median(acc):.3f}",
                f"{np.quantile(bulk, 0.05):.0f}",
                f"{np.median(bulk):.0f}",
                f"{np.quantile(tail, 0.05):.0f}",
                f"{np.median(tail):.0f}",
            ]
        )
    print(f"\n## Metric window end, {args.window_pixels} pixels, 2 chains x (300 + 500) steps")
    heads = ["window end", "acceptance (median)", "ESS bulk 5%", "bulk median", "ESS tail 5%"]
    print(table([*heads, "tail median"], rows))


def part_laplace(args, lp, data, r, lap):
    ok = np.flatnonzero(np.asarray(lap.reliable))[: args.nuts_pixels]
    sub = jax.tree.map(lambda a: a[ok], data)
    opts = jp.HMCOptions(num_warmup=300, num_samples=400, num_chains=2, kernel="nuts")
    th0 = np.asarray(r.theta)[ok]
    s = jp.sample_pixels(lp, sub, th0, theta_std=np.asarray(lap.theta_std)[ok], options=opts)
    dg = jp.diagnostics(s)
    good = dg["min_ess_bulk"] > 100
    nuts_std = s.natural.reshape(len(ok), -1, lp.size).std(axis=1, ddof=1)
    ratio = np.asarray(lap.std)[ok] / nuts_std
    rows = []
    for j, lab in enumerate(lp.labels):
        v = ratio[good, j]
        q = np.quantile(v, [0.05, 0.5, 0.95])
        inside = np.mean((v > 0.8) & (v < 1.25))
        rows.append([lab, f"{q[1]:.3f}", f"{q[0]:.3f} - {q[2]:.3f}", f"{100 * inside:.0f}%"])
    print(f"\nLaplace std / NUTS std on {good.sum()} reliable pixels with NUTS ESS > 100:")
    print(table(["parameter", "median", "5-95% range", "within [0.8, 1.25]"], rows))


def part_map(args):
    """The maps of the synthetic demo capture, then of the real ones. The demo runs first:
    its time is that of a first run in a fresh process, every program compiled (its target
    is the tightest); the real captures after it may reuse some of its compiled programs."""
    from jaxrefl.io import load_capture

    if "synthetic" in args.map_captures:
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            d = demo_capture(Path(tmp) / "demo", args.map_size)
            map_run(args, load_capture(d), "synthetic (jaxrefl demo)")
    root = Path(os.environ.get("JAXREFL_SHARED_DATA", "../shared/data"))
    for real in ("bath_tile", "yellow_box"):
        if real not in args.map_captures:
            continue
        src = root / "svbrdf_flash" / real
        if not src.exists():
            print(f"\n(no {src}: skipping the {real} uncertainty map timing)")
            continue
        cap = load_capture(src, resolution=args.map_size)
        map_run(args, cap, f"{real} at {cap.shape[1]} x {cap.shape[2]}")


def map_run(args, cap, name):
    """Adaptive uncertainty map (UNCERTAINTY_MAP_HMC, fixed-size chunks) of a capture. The fit is
    of the whole capture, once, compile included (the model choice is made once per capture
    on a fixed-size sample of pixels, so its time does not scale with the rows). With
    ``--map-rows R`` the posterior is of the first R rows only, run twice (the first run's
    extra time is its compilation), and its compiled time is extrapolated to the whole map
    by the ratio of rows (printed as such), the compilation counted once."""
    _k, h_full, w, _c = cap.shape
    t0 = time.perf_counter()
    job = svbrdf.FitJob(model=args.map_model, config=F64, tile_pixels=min(4096, h_full * w))
    cf = svbrdf.fit_capture(cap, job)
    t_fit = time.perf_counter() - t0
    rows = h_full if args.map_rows <= 0 else min(h_full, args.map_rows)
    n = rows * w
    # the posterior and Laplace marginals of svbrdf.uncertainty_maps: the lobe's priors from
    # the reliably fitted pixels, Student t marginals where the noise was estimated
    lp, _ = svbrdf.map_posterior(cf)
    dof = svbrdf.laplace_dof(cf)[:n]
    theta = svbrdf.fit_theta(cf, lp.space)[:n]
    noise0 = np.nan_to_num(cf.maps["noise_std"].reshape(-1)[:n], nan=1e-2)
    flag = cf.maps["laplace_flag"].reshape(-1)[:n]
    theta_std = svbrdf.laplace_theta_std(cf, lp.space)[:n]
    data = svbrdf.pixel_block(cap, 0, n, dtype=np.float64)

    def posterior():
        return jp.adaptive_uncertainty(
            lp,
            data,
            theta,
            theta_std,
            flag,
            jp.AdaptiveOptions(chunk=args.map_chunk, keep_samples=False),
            noise_scale=np.where(noise0 > 0, noise0, 1e-2),
            dof=dof,
            progress=True,
        )

    t1 = time.perf_counter()
    u = posterior()
    t_post = time.perf_counter() - t1
    t_post_warm = t_post
    if rows < h_full:  # a second, compiled run: its time is what scales with the rows
        t1 = time.perf_counter()
        posterior()
        t_post_warm = time.perf_counter() - t1
    m = u.report()
    tm = u.timings
    n_mc = m["mcmc"]["pixels"]
    from jaxrefl._threads import default_workers

    workers = default_workers()
    o, g = jp.UNCERTAINTY_MAP_HMC, jp.UNCERTAINTY_MAP_GIBBS
    print(
        f"\nadaptive uncertainty map, {name}, rows 0-{rows - 1} of {h_full} x {w} "
        f"(K = {cap.shape[0]}), float64, {o.num_chains} chains of {o.num_samples} draws: "
        f"HMC ({o.num_warmup} warm-up, {o.num_integration_steps} leapfrog) or, where the "
        f"posterior allows, Gibbs ({g.warmup(o.num_warmup)} warm-up intervals; exact Gibbs "
        f"{g.sweeps} sweeps, the width sampler {g.scans} "
        f"scan(s) between draws); chunks of {tm.get('mcmc_chunk_size', 0)} pixels, "
        f"{workers} at once; sampler: {tm.get('sampler', '-')}:"
    )
    body = [
        [
            f"fit_capture, all {h_full} rows (model choice, LM, Laplace, compile incl.)",
            f"{t_fit:.1f}",
        ],
        [f"adaptive posterior ({n_mc} MCMC pixels)", f"{t_post:.1f}"],
        ["  MCMC compile (first chunk - median chunk)", f"{tm.get('mcmc_compile_s', 0.0):.1f}"],
        ["  MCMC median chunk", f"{tm.get('mcmc_chunk_s_median', float('nan')):.1f}"],
        ["  MCMC first pass, wall (compile incl.)", f"{tm.get('mcmc_wall_s', 0.0):.1f}"],
        [
            f"  second pass, wall ({tm.get('rerun_pixels', 0)} pixels, compile incl.)",
            f"{tm.get('rerun_wall_s', 0.0):.1f}",
        ],
    ]
    total = t_fit + t_post
    if rows < h_full:
        f = h_full / rows
        post_c = max(0.0, t_post - t_post_warm)
        body.insert(2, ["  of which compile (first run - second run)", f"{post_c:.1f}"])
        est = t_fit + post_c + t_post_warm * f  # the fit whole; the posterior's run scales
        body.append([f"EXTRAPOLATED total, {h_full} x {w} (x{f:.0f} rows)", f"{est:.0f}"])
    else:
        body.append(["total", f"{total:.1f}"])
        est = total
    print(table(["step", "wall s"], body))
    goal = 120.0 if name.startswith("synthetic") else 300.0  # issue targets, compile incl.
    verdict = "MET" if est <= goal else f"MISSED by {100 * (est / goal - 1):.0f}%"
    print(f"target: the whole map within {goal:.0f} s, compile included: {est:.0f} s -> {verdict}")
    print("methods:", m["method_counts"])
    mc = m["mcmc"]
    if mc["max_rhat"]:
        print(
            f"MCMC: max R-hat median {mc['max_rhat']['median']:.3f}, q95 "
            f"{mc['max_rhat']['q95']:.3f}; min bulk ESS median {mc['min_ess_bulk']['median']:.0f}"
            f", q05 {mc['min_ess_bulk']['q05']:.0f}; pixels with divergences "
            f"{mc['pixels_with_divergences']}; R-hat > 1.1 on {mc['pixels_rhat_above_1.1']} "
            f"of {mc['pixels']}"
        )
        ok = 1.0 - (mc["pixels_rhat_above_1.05"] + mc["pixels_rhat_nan"]) / mc["pixels"]
        print(
            f"max R-hat <= 1.05 on {100 * ok:.2f}% of the MCMC pixels ({mc['pixels_rhat_nan']} "
            f"without an R-hat; target >= 99%: "
            f"{'MET' if ok >= 0.99 else 'MISSED'})"
        )
        sp = mc["second_pass"]
        if sp["pixels"]:
            print(
                f"second pass ({tm.get('rerun_wall_s', 0.0):.1f} s, compile incl.) on "
                f"{sp['pixels']} pixels: max R-hat median {sp['max_rhat_before']['median']:.3f} -> "
                f"{sp['max_rhat_after']['median']:.3f}; still above 1.1: "
                f"{sp['pixels_rhat_above_1.1_after']}"
            )


def part_emcee_sbc(args):
    """SBC of emcee as in tests/test_posterior_sbc.py (1-channel GGX + Lambert, K = 16,
    truth from the truncated prior, 12 walkers x 400 steps, draws thinned to 19), with
    ``--emcee-sbc`` simulations instead of the test's 24."""
    n, k, sigma = args.emcee_sbc, 16, 0.01
    model, space = svbrdf.capture_model("ggx", channels=1, alpha_min=0.05)
    lp = jp.log_posterior(model, space, fit.GaussianNoise(sigma))
    rng = np.random.default_rng(11)
    lo, hi = space.lower, space.upper
    cols = []
    for blk, prior in zip(space.blocks, lp.priors, strict=True):
        for j in range(blk.start, blk.stop):
            cols.append(jp.sample_truncated(prior, rng, (n,), lo[j], hi[j]))
    nat = np.stack(cols, -1)
    params = {b.name: nat[:, b.start : b.stop] for b in space.blocks}
    params["alpha"] = params["alpha"][:, 0]
    theta = np.asarray(space.from_natural(params, dtype=jnp.float64))
    th = np.arccos(rng.uniform(np.cos(np.radians(45)), 1.0, (n, k)))
    ph = rng.uniform(0, 2 * np.pi, (n, k))
    wi = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    scale = wi[..., 2:3] * 1.5
    d0 = fit.pixel_data(np.zeros((n, k, 1)), wi, None, scale=scale)
    pred = np.asarray(jax.jit(jax.vmap(lp.predict))(jnp.asarray(theta), d0))
    data = fit.pixel_data(pred + sigma * rng.normal(size=pred.shape), wi, None, scale=scale)
    t0 = time.perf_counter()
    draws = []
    for i in range(n):
        d = jax.tree.map(lambda a, i=i: a[i], data)
        e = jp.sample_emcee(lp, theta[i], (d,), jp.EmceeOptions(12, 400, seed=i))
        draws.append(jp.thin(e.theta, 19)[0])
    wall = time.perf_counter() - t0
    res = jp.sbc_summary(theta, np.stack(draws), labels=lp.labels, bins=10)
    rows = []
    for j, lab in enumerate(lp.labels):
        rows.append(
            [
                lab,
                f"{res.tests['chi2_p'][j]:.3f}",
                f"{res.coverage_z(0.5)[j]:+.2f}",
                f"{res.coverage_z(0.9)[j]:+.2f}",
            ]
        )
    print(f"\nemcee SBC, {n} simulations (12 walkers x 400 steps), {wall:.0f} s, 10 rank bins:")
    print(table(["parameter", "rank chi2 p", "50% coverage z", "90% coverage z"], rows))


def part_gradient(args) -> None:
    """Cost of one log-posterior gradient (value_and_grad, vmapped over pixels), with the
    censored branch evaluated on every observation (the general posterior, as for data
    with censoring) and without it (``LogPosterior.for_data`` on uncensored data)."""
    n = args.gradient_pixels
    _model, _space, lp, theta, data = simulate(n)
    rows = []
    for dtype in (jnp.float64, jnp.float32):
        d = data.astype(dtype)
        t = jnp.asarray(theta, dtype)
        us = {}
        for name, post in (("general", lp), ("for_data", lp.for_data(d))):
            f = jax.jit(jax.vmap(jax.value_and_grad(lambda x, dd, post=post: post(x, dd))))
            jax.block_until_ready(f(t, d))
            best = min(_timed_call(f, t, d) for _ in range(5))
            us[name] = 1e6 * best / n
        rows.append(
            [
                jnp.dtype(dtype).name,
                f"{us['general']:.2f}",
                f"{us['for_data']:.2f}",
                f"{us['general'] / us['for_data']:.1f}x",
            ]
        )
    print(f"\none log-posterior gradient, K = {K}, GGX + Lambert RGB, {n} pixels (us per pixel):")
    print(table(["dtype", "with censored branch", "for_data (none)", "ratio"], rows))


def _timed_call(f, *a) -> float:
    t0 = time.perf_counter()
    jax.block_until_ready(f(*a))
    return time.perf_counter() - t0


def part_mixing(args) -> None:
    """MCMC mixing on the Laplace-flagged pixels of a small demo capture under variants of
    ``UNCERTAINTY_MAP_HMC`` (same pixels, same seed): in the fit's coordinates does a longer or
    wider run, or a start clipped into [-4, 4], fix the R-hat of the map's MCMC pixels? And
    in the non-centred coordinates (``reparam``, :mod:`jaxrefl.posterior._reparam`), at
    which trajectory length?"""
    import dataclasses
    import tempfile

    from jaxrefl.io import load_capture

    with tempfile.TemporaryDirectory() as tmp:
        cap = load_capture(demo_capture(Path(tmp) / "demo", args.mixing_size))
    cf = svbrdf.fit_capture(cap, svbrdf.FitJob(model="ggx", config=F64, tile_pixels=4096))
    model, space = cf.model()
    lp = jp.log_posterior(model, space, fit.GaussianNoise(None))
    theta = np.asarray(cf.theta, np.float64)
    n = theta.shape[0]
    ok = np.all(np.isfinite(theta), -1)
    flag = cf.maps["laplace_flag"].reshape(-1)
    sel = np.flatnonzero(ok & (flag != 0))[: args.mixing_pixels]
    tsd = svbrdf.laplace_theta_std(cf, space)[sel]
    noise0 = np.nan_to_num(cf.maps["noise_std"].reshape(-1)[sel], nan=1e-2)
    s0 = np.where(noise0 > 0, noise0, 1e-2)
    sub = jax.tree.map(lambda v: v[sel], svbrdf.pixel_block(cap, 0, n, dtype=np.float64))
    sd = np.concatenate([tsd, np.ones((sel.size, 1))], -1)
    m, gibbs = jp.UNCERTAINTY_MAP_HMC, jp.UNCERTAINTY_MAP_GIBBS
    rep = dataclasses.replace
    # The reference variant: the fit's theta (no reparametrisation) and 8 leapfrog steps.
    fit8 = rep(m, reparam="none", num_integration_steps=8)
    variants = [
        ("fit's theta, 8 leapfrog", theta[sel], fit8),
        ("fit's theta, start clipped to [-4, 4]", np.clip(theta[sel], -4, 4), fit8),
        ("fit's theta, 4 chains", theta[sel], rep(fit8, num_chains=4)),
        ("fit's theta, 300 warm-up steps", theta[sel], rep(fit8, num_warmup=300)),
        ("fit's theta, 16 leapfrog", theta[sel], rep(fit8, num_integration_steps=16)),
        ("fit's theta, 32 leapfrog", theta[sel], rep(m, reparam="none")),
        ("non-centred albedo, 8 leapfrog", theta[sel], rep(m, num_integration_steps=8)),
        ("non-centred albedo, 16 leapfrog", theta[sel], rep(m, num_integration_steps=16)),
        ("non-centred albedo, 32 leapfrog (UNCERTAINTY_MAP_HMC)", theta[sel], m),
    ]
    rows = []
    first = None
    for name, th, opts in variants:
        x0 = lp.init_theta(jnp.asarray(th), noise_scale=s0)
        smp = jp.sample_pixels(
            lp, sub, x0, theta_std=sd, options=opts, gibbs=gibbs, seed=1, timing=True
        )
        dg = jp.diagnostics(smp)
        r = dg["max_rhat"]
        if opts is m:
            first = (x0, smp, r)
        ess = np.nanmedian(dg["min_ess_bulk"])
        rows.append(
            [
                name,
                f"{np.nanmedian(r):.3f}",
                f"{np.nanquantile(r, 0.9):.2f}",
                f"{np.mean(r < 1.1):.2f}",
                f"{ess:.0f}",
                str(int(np.sum(dg["divergences"] > 0))),
                f"{smp.run_s:.1f}",
                f"{ess * sel.size / smp.run_s:.0f}",
                f"{smp.compile_s:.1f}",
            ]
        )
    vals, counts = np.unique(flag[sel], return_counts=True)
    flags = {int(v): int(k) for v, k in zip(vals, counts, strict=True)}
    print(
        f"\nMCMC mixing on {sel.size} Laplace-flagged pixels of a {args.mixing_size} x "
        f"{args.mixing_size} demo capture (Laplace flags: pixels {flags}):"
    )
    cols = ["variant", "max R-hat median", "q90", "share < 1.1", "min bulk ESS median"]
    cols += ["px w/ div.", "run s", "median ESS x px / s", "compile s"]
    print(table(cols, rows))
    _second_pass(lp, sub, sd, *first, m)


def _second_pass(lp, sub, sd, x0, smp, r, m) -> None:
    """The second pass of ``adaptive_uncertainty`` on the pixels that UNCERTAINTY_MAP_HMC left
    above R-hat 1.1: restarted from the LM optimum or from first-pass draws (chain c from
    first-pass chain c, the draws' std as the initial metric), at which length."""
    import dataclasses

    from jaxrefl.posterior._adaptive import _restarts

    bad = np.flatnonzero(~(r <= 1.1))
    if bad.size == 0:
        print("\n(no pixel above R-hat 1.1 after UNCERTAINTY_MAP_HMC: no second pass)")
        return
    rng = np.random.default_rng(0)
    rs = [_restarts(smp, int(j), m.num_chains, rng) for j in bad]
    draws_x0 = jnp.asarray(np.stack([a for a, _ in rs]))
    draws_sd = np.stack([b for _, b in rs])
    sub_b = jax.tree.map(lambda v: v[bad], sub)
    rep = dataclasses.replace
    variants = [
        ("LM optimum, Laplace std, 2x warm-up, thin 2", x0[bad], sd[bad], 2, 2),
        ("first-pass draws, 1x warm-up, thin 2", draws_x0, draws_sd, 1, 2),
        ("first-pass draws, 2x warm-up, thin 2", draws_x0, draws_sd, 2, 2),
        ("first-pass draws, 2x warm-up, thin 4 (longer_options)", draws_x0, draws_sd, 2, 4),
    ]
    rows = []
    for name, xx, ss, wf, thin in variants:
        o = rep(m, num_warmup=wf * m.num_warmup, thin=thin, init_jitter=0.0)
        if (wf, thin) == (2, 4):
            assert o == jp.longer_options(m)
        t0 = time.perf_counter()
        s2 = jp.sample_pixels(
            lp, sub_b, xx, theta_std=ss, options=o, gibbs=jp.UNCERTAINTY_MAP_GIBBS, seed=2
        )
        wall = time.perf_counter() - t0
        g = jp.diagnostics(s2)
        rr = g["max_rhat"]
        rows.append(
            [
                name,
                f"{np.median(rr):.3f}",
                f"{np.quantile(rr, 0.9):.2f}",
                f"{np.mean(rr < 1.1):.2f}",
                f"{np.median(g['min_ess_bulk']):.0f}",
                str(int(np.sum(g["divergences"] > 0))),
                f"{wall:.1f}",
            ]
        )
    print(
        f"\nsecond pass on the {bad.size} of {r.size} pixels above R-hat 1.1 after "
        "UNCERTAINTY_MAP_HMC (wall s includes compilation):"
    )
    cols = ["restart", "max R-hat median", "q90", "share < 1.1", "min bulk ESS median"]
    print(table([*cols, "px w/ div.", "wall s"], rows))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pixels", type=int, default=200)
    p.add_argument("--emcee-pixels", type=int, default=4)
    p.add_argument("--nuts-pixels", type=int, default=200)
    p.add_argument("--map-size", type=int, default=256)
    p.add_argument("--map-rows", type=int, default=0, help="rows with a posterior (0: all)")
    p.add_argument("--map-chunk", type=int, default=2048, help="MCMC pixels per call")
    p.add_argument("--map-captures", default="bath_tile,yellow_box,synthetic")
    p.add_argument("--map-model", default="auto", help="the fit's model (auto: the default)")
    p.add_argument("--only-map", action="store_true", help="skip parts 1 and 2")
    p.add_argument(
        "--only-family",
        action="store_true",
        help="only the maps of the capture family and the real captures (_family_maps.py)",
    )
    p.add_argument("--members", default=None, help="family members, comma-separated (all)")
    p.add_argument(
        "--light",
        default=None,
        help="with --only-family: the maps' FitJob.light (default: the library's); a light "
        "other than the default is recorded in its own section, posterior_speed_family_light",
    )
    p.add_argument(
        "--cli",
        action="store_true",
        help="with --only-family: also jaxrefl sample per capture, cold and warm compile cache",
    )
    p.add_argument(
        "--only-family-cli",
        action="store_true",
        help="only jaxrefl sample per capture (--members, and the real captures), cold and warm",
    )
    p.add_argument("--emcee-sbc", type=int, default=200, help="emcee SBC simulations (0: skip)")
    p.add_argument("--only-emcee-sbc", action="store_true")
    p.add_argument("--window-pixels", type=int, default=100)
    p.add_argument("--only-window", action="store_true", help="only the metric-window part")
    p.add_argument("--only-gradient", action="store_true", help="only the gradient-cost part")
    p.add_argument("--gradient-pixels", type=int, default=4096)
    p.add_argument("--only-mixing", action="store_true", help="only the map-mixing part")
    p.add_argument("--mixing-size", type=int, default=64)
    p.add_argument("--mixing-pixels", type=int, default=512)
    args = p.parse_args()

    if args.only_family_cli:
        from _family_maps import run_family_cli

        run_family_cli(None if args.members is None else args.members.split(","))
        return
    if args.only_family:
        from _family_maps import run_family

        members = None if args.members is None else args.members.split(",")
        run_family(members, light=args.light)
        if args.cli:
            from _family_maps import run_family_cli

            run_family_cli(members)
        return
    if args.only_window:
        part_window(args)
        return
    if args.only_gradient:
        part_gradient(args)
        return
    if args.only_mixing:
        part_mixing(args)
        return
    if args.only_emcee_sbc:
        part_emcee_sbc(args)
        return
    if not args.only_map:
        model, space, lp, theta, data = simulate(args.pixels)
        r, lap, _ = part_speed(args, model, space, lp, theta, data)
        part_laplace(args, lp, data, r, lap)
        if args.emcee_sbc > 0:
            part_emcee_sbc(args)
    if args.map_size > 0:
        part_map(args)


if __name__ == "__main__":
    if "--only-family-cli" in sys.argv:
        sys.exit(
            run_and_record(
                "posterior_speed_family_cli", "jaxrefl sample on captures of the family", main
            )
        )
    if "--only-family" in sys.argv and "--light" in sys.argv:
        sys.exit(
            run_and_record(
                "posterior_speed_family_light",
                "Uncertainty maps of a capture family, the light estimated",
                main,
            )
        )
    if "--only-family" in sys.argv:
        sys.exit(
            run_and_record("posterior_speed_family", "Uncertainty maps of a capture family", main)
        )
    sys.exit(run_and_record("posterior_speed", "Posterior speed", main))

"""Posterior outputs: ArviZ InferenceData round-trip through NetCDF, uncertainty EXR maps,
adaptive method selection, and `jaxrefl sample` end to end on tiny cases."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import FrozenInstanceError, replace

import jax
import numpy as np
import pytest

from jaxrefl import brdf, fit, svbrdf
from jaxrefl import measured as jm
from jaxrefl import posterior as jp
from jaxrefl._jsonsafe import NULLS_KEY, jsonable
from jaxrefl.cli import main
from jaxrefl.io import load_capture, map_name, read_exr
from jaxrefl.posterior._adaptive_options import MCMCPixels
from jaxrefl.posterior._laplace_summary import laplace_summary
from jaxrefl.posterior._maps import uncertainty_channels

with warnings.catch_warnings():
    warnings.simplefilter("ignore", FutureWarning)
    import arviz as az

SIGMA = 0.02


@pytest.fixture(scope="module")
def lambert():
    """Lambertian RGB pixels seen from K = 6 directions (a cheap model to compile)."""
    m = brdf.get("lambert")
    space = fit.ParamSpace(m, channels=3)
    lp = jp.log_posterior(m, space, fit.GaussianNoise(SIGMA))
    rng = np.random.default_rng(0)
    n, k = 6, 6
    alb = rng.uniform(0.1, 0.9, size=(n, 3))
    alb[0] = [0.999, 0.5, 0.5]  # albedo.R at the bound: Laplace flags AT_BOUND there
    wi = np.tile(np.array([0.0, 0.0, 1.0]), (n, k, 1))
    obs = alb[:, None, :] / math.pi + SIGMA * rng.normal(size=(n, k, 3))
    data = fit.pixel_data(obs, wi)
    r = fit.fit_pixels(m, data, config=fit.FitConfig(noise=fit.GaussianNoise(SIGMA)), space=space)
    lap = fit.laplace(r, data, residual=fit.make_residual(m, space, fit.GaussianNoise(SIGMA)))
    return lp, data, r, lap


@pytest.fixture(scope="module")
def demo_cap(tmp_path_factory):
    """`jaxrefl demo` (8 x 8, no fit): the capture the command-line tests sample a crop of
    (one crop shape, so the fit's programs compiled by one test are loaded by the next)."""
    cap = tmp_path_factory.mktemp("demo") / "cap"
    assert main(["demo", "--out", str(cap), "--size", "8", "--no-fit"]) == 0
    return cap


def test_inference_data_netcdf_round_trip(lambert, tmp_path):
    lp, data, r, _ = lambert
    d0 = jax.tree.map(lambda a: a[1], data)
    s = jp.sample_emcee(
        lp,
        np.asarray(r.theta[1]),
        (d0,),
        jp.EmceeOptions(n_walkers=8, max_steps=1500, seed=1),
        natural=lp.natural,
        labels=lp.labels,
    )
    one = jax.tree.map(lambda a: a[1:2], data)
    ppc = jp.posterior_predictive(lp, s, one, n_draws=20)
    assert ppc.shape == (1, 20, 6, 3)
    idata = jp.to_inference_data(s, one, predictive=ppc, attrs={"note": "test"})
    path = jp.save_netcdf(idata, tmp_path / "post.nc")
    back = az.from_netcdf(str(path))
    for group in ("posterior", "sample_stats", "observed_data", "posterior_predictive"):
        assert group in back.groups(), back.groups()
    np.testing.assert_array_equal(
        back.posterior["albedo_R"].values, idata.posterior["albedo_R"].values
    )
    np.testing.assert_array_equal(back.observed_data["obs"].values, np.asarray(one.obs))
    assert back.posterior.attrs["method"] == "emcee"
    assert list(back.posterior.attrs["labels"]) == list(lp.labels)
    assert set(back.sample_stats.data_vars) >= {"acceptance_rate", "diverging", "lp"}
    dg = jp.diagnostics(s)
    assert dg["rhat"].shape == (1, 3) and np.all(dg["ess_bulk"] > 10)
    assert np.all(np.abs(dg["rhat"] - 1) < 0.1)
    fig = jp.plot_corner(s, 0)
    assert len(fig.axes) == 6  # the lower triangle of 3 parameters
    jp.plot_ppc(ppc, one, 0)


def test_adaptive_method_map_and_exr(lambert, tmp_path):
    """With MCMC off every estimated pixel is Laplace (method 1); the EXR carries mean,
    std, q05, q95 per parameter and the method channel; q05 < mean < q95."""
    lp, data, r, lap = lambert
    theta_std = np.asarray(lap.theta_std)
    flag = np.asarray(lap.flag)
    assert flag[0] & fit.LaplaceFlag.AT_BOUND
    none = jp.AdaptiveOptions(mcmc="none")
    u = jp.adaptive_uncertainty(lp, data, np.asarray(r.theta), theta_std, flag, none)
    assert np.all(u.method == 1)
    assert np.all(u.q05 <= u.mean) and np.all(u.mean <= u.q95)
    np.testing.assert_allclose(u.std, np.asarray(lap.std), rtol=1e-8)
    path = jp.write_uncertainty_exr(tmp_path / "u.exr", u, 2, 3)
    im = read_exr(path)
    for name in ("albedo_mean.R", "albedo_std.G", "albedo_q05.B", "albedo_q95.R", "method.Y"):
        assert name in im.channels, sorted(im.channels)
    assert im.pixel_types["method.Y"] == "UINT"
    np.testing.assert_allclose(im.channels["albedo_mean.G"].reshape(-1), u.mean[:, 1], rtol=1e-6)
    assert im.metadata["method_codes"]["1"] == "laplace"


def test_laplace_summaries_are_student_t_where_the_noise_was_estimated(lambert):
    """With ``dof`` per pixel the Laplace quantiles are theta* +- t_{0.95, dof} theta_std
    pushed through the bijection and the std is scaled by sqrt(dof / (dof - 2)); dof = inf
    gives the Gaussian ones; a finite dof <= 2 (no variance) sends the pixel to MCMC."""
    from scipy import stats

    lp, data, r, lap = lambert
    theta_std, flag = np.asarray(lap.theta_std), np.asarray(lap.flag)
    theta = np.asarray(r.theta)
    g = laplace_summary(lp, theta, theta_std)
    dof = np.array([np.inf, 15.0, 4.0, 15.0, 30.0, 2.0])
    t = laplace_summary(lp, theta, theta_std, dof)
    np.testing.assert_array_equal(t[0][0], g[0][0])  # dof inf: the Gaussian summary
    np.testing.assert_array_equal(t[2][0], g[2][0])
    sp = lp.space
    for j in (1, 2, 4):
        q = stats.t.ppf(0.95, dof[j])
        lo = np.asarray(sp.natural_vector(theta[j] - q * theta_std[j]))
        hi = np.asarray(sp.natural_vector(theta[j] + q * theta_std[j]))
        np.testing.assert_allclose(t[2][j], lo, rtol=1e-12)
        np.testing.assert_allclose(t[3][j], hi, rtol=1e-12)
        np.testing.assert_allclose(t[1][j], g[1][j] * np.sqrt(dof[j] / (dof[j] - 2)), rtol=1e-12)
        assert np.all(t[3][j] - t[2][j] > g[3][j] - g[2][j])  # wider than the Gaussian's
    assert np.all(np.isnan(t[1][5]))
    none = jp.AdaptiveOptions(mcmc="none")
    u = jp.adaptive_uncertainty(lp, data, theta, theta_std, flag, none, dof=dof)
    np.testing.assert_array_equal(u.q95[:, :3], np.asarray(t[3]))
    assert np.all(u.method == 1)  # mcmc="none": the dof-2 pixel keeps its (NaN) summary
    some = jp.AdaptiveOptions(
        mcmc="flagged", audit=0.0, hmc=jp.HMCOptions(num_warmup=20, num_samples=20, num_chains=2)
    )
    u2 = jp.adaptive_uncertainty(lp, data, theta, theta_std, flag, some, dof=dof)
    assert u2.method[5] == 2 and u2.method[0] == 2  # dof 2, and the AT_BOUND pixel
    assert np.all(u2.method[1:5] == 1) and np.all(np.isfinite(u2.std[5, :3]))


def test_cli_sample_capture_end_to_end(demo_cap, tmp_path):
    """`jaxrefl demo` (8 x 8) then `jaxrefl sample` on a 4 x 4 crop, Lambert model, MCMC on
    every pixel: the EXR, the NetCDF and report.json with diagnostics; then
    :func:`jaxrefl.svbrdf.uncertainty_maps` with the same settings returns exactly what the
    command wrote, as a typed result."""
    cap = demo_cap
    out = tmp_path / "out"
    argv = ["sample", str(cap), "--out", str(out), "--model", "lambert", "--pixels", "2:6,2:6"]
    argv += ["--mcmc", "all", "--warmup", "60", "--samples", "60", "--chains", "2", "--quiet"]
    assert main([*argv, "--workers", "1"]) == 0  # the library call below: the default workers
    rep = json.loads((out / "report.json").read_text())
    assert rep["height"] == 4 and rep["width"] == 4
    # --priors population (default): Lambert has no lobe to pool, its defaults stay
    assert rep["prior_source"]["source"] == "default" and "lobe" in rep["prior_source"]["why"]
    u = rep["uncertainty"]
    assert u["method_counts"]["mcmc"] + u["method_counts"]["mcmc_audit"] == 16
    assert u["mcmc"]["max_rhat"]["median"] < 1.2
    # --gibbs-sweeps 2 by default: Lambert's posterior is linear-Gaussian, drawn by Gibbs
    assert u["timings"]["sampler"] == "gibbs" and rep["sampler"]["gibbs"]["sweeps"] == 2
    n_above = u["mcmc"]["pixels_rhat_above_1.1"]
    assert n_above <= u["mcmc"]["pixels_rhat_above_1.01"] and n_above < 8
    im = read_exr(out / "uncertainty.exr")
    assert {"albedo_mean.R", "noise_scale_mean.Y", "rhat.Y", "ess_bulk.Y", "method.Y"} <= set(
        im.channels
    )
    assert np.all(np.isfinite(im.channels["rhat.Y"]))
    # the second pass: the pixels it reran are those above 1.05 after the first
    sp = u["mcmc"]["second_pass"]
    assert rep["second_pass"]["rerun_rhat"] == 1.05 and rep["second_pass"]["options"]["thin"] == 4
    passes = im.channels["mcmc_pass.Y"]
    assert set(np.unique(passes)) <= {1, 2} and int(np.sum(passes == 2)) == sp["pixels"]
    if sp["pixels"]:
        assert sp["max_rhat_before"]["min"] > 1.05
    post = az.from_netcdf(str(out / "posterior.nc"))
    assert post.posterior["albedo_R"].shape[-1] == 16
    # named coordinates: each MCMC pixel's row and column, photos, channels R/G/B
    idx = post.posterior["pixel"].values
    np.testing.assert_array_equal(post.posterior["row"].values, idx // 4)
    np.testing.assert_array_equal(post.posterior["col"].values, idx % 4)
    assert list(post.constant_data["censored"].dims) == ["pixel", "photo", "channel"]
    assert post.log_likelihood["obs"].shape[2:] == post.observed_data["obs"].shape
    assert list(post.posterior_predictive["channel"].values) == ["R", "G", "B"]
    # the PNGs a user looks at: std maps, R-hat map, pair plots of three MCMC pixels
    pngs = [f for f in rep["files"] if f.endswith(".png")]
    assert pngs[:2] == ["posterior_std.png", "rhat.png"] and len(pngs) == 5
    assert all(f.startswith("pair_r") for f in pngs[2:])
    from PIL import Image

    for f in pngs:
        with Image.open(out / f) as png:
            png.verify()
            assert png.format == "PNG" and min(png.size) > 100, f
    assert main(["sample", str(tmp_path / "missing"), "--out", str(out)]) == 1

    # The library call behind it gives the same maps and report as a typed result.
    # the command's sampler is the library's map default with the flags given
    hmc = replace(jp.UNCERTAINTY_MAP_HMC, num_warmup=60, num_samples=60, num_chains=2)
    options = jp.AdaptiveOptions(mcmc="all", hmc=hmc)
    job = svbrdf.FitJob(model="lambert", config=fit.FitConfig(dtype=np.float64))
    res = svbrdf.uncertainty_maps(load_capture(cap).crop(2, 6, 2, 6), job, options)
    assert isinstance(res, svbrdf.CaptureUncertainty) and (res.height, res.width) == (4, 4)
    assert res.fit.job.tile_pixels == 16  # one tile of the crop's size
    assert isinstance(res.map, jp.UncertaintyMap) and res.map.labels == res.posterior.labels
    assert res.theta_std.shape == (16, 3) and np.all(res.theta_std > 0)
    for name, ch in uncertainty_channels(res.map, 4, 4).items():
        np.testing.assert_array_equal(im.channels[name], ch, err_msg=name)
    lib = jsonable(res.report())[0]  # as report.json holds it (NaN: null)
    assert set(rep) - {NULLS_KEY} == set(lib) | {"input", "kind", "crop", "downsample", "files"}
    assert list(rep["bounds"]) == list(res.posterior.space.labels)
    for key in ("model", "height", "width", "noise", "priors", "bounds", "sampler", "second_pass"):
        assert rep[key] == lib[key], key
    assert rep["fit_report"] == lib["fit_report"]
    mine, cli = lib["uncertainty"], rep["uncertainty"]
    assert set(mine.pop("timings")) == set(cli.pop("timings"))
    assert cli == mine
    assert rep["files"][:2] == ["uncertainty.exr", "posterior.nc"]
    again = [p.name for p in svbrdf.write_uncertainty(res, tmp_path / "lib")]
    assert again == rep["files"]
    back = az.from_netcdf(str(tmp_path / "lib" / "posterior.nc"))
    np.testing.assert_array_equal(back.posterior["albedo_R"].values, post.posterior["albedo_R"])
    assert list(back.posterior.attrs["rows"]) == list(post.posterior.attrs["rows"])
    # theta_std is the job's std maps through the bijections' slopes (delta method reversed)
    lab = res.posterior.labels[0]
    slope = np.asarray(res.posterior.space.dnatural(jax.numpy.asarray(res.fit.theta)))[:, 0]
    std_map = res.fit.maps[map_name(lab, "_std")].reshape(-1)
    np.testing.assert_allclose(res.theta_std[:, 0] * np.abs(slope), std_map, rtol=1e-12)
    # A held-out photo stays out of the posterior as it stayed out of the fit: the data
    # the map's posterior holds (what its MCMC samples, with or without pixels to sample)
    crop = load_capture(cap).crop(2, 6, 2, 6)
    laplace_only = replace(options, mcmc="none")
    held = svbrdf.uncertainty_maps(crop, replace(job, holdout=(0,)), laplace_only)
    w = np.asarray(held.data.weight)
    assert np.all(w[:, 0] == 0) and np.all(np.any(w[:, 1:] > 0, axis=(1, 2)))
    with pytest.raises(ValueError, match="float64"):
        svbrdf.uncertainty_maps(cap, svbrdf.FitJob(model="lambert"), options)


def test_cli_sample_brdf_file(shared_data, tmp_path, capsys):
    """A Cornell BRDF, Lambert model (cheap), emcee: posterior.nc, corner.png, report."""
    src = shared_data / "brdf" / "cornell" / "acryl_blue.astm"
    out = tmp_path / "brdf"
    argv = ["sample", str(src), "--out", str(out), "--brdf-model", "lambert"]
    argv += ["--max-steps", "400", "--walkers", "10", "--quiet"]
    # 400 steps are fewer than 50 autocorrelation times: outputs written, exit status 3
    assert main(argv) == 3
    assert "not converged: chain of 400 steps" in capsys.readouterr().err
    rep = json.loads((out / "report.json").read_text())
    assert rep["kind"] == "brdf" and set(rep["posterior"]) >= {"albedo.R", "noise_scale"}
    assert rep["converged"] is False and rep["convergence"]["chain_length"] == 400
    assert "tau" in rep["convergence"]["reasons"][0]
    c = rep["convergence"]
    assert c["max_rhat"] == rep["diagnostics"]["max_rhat"] and len(c["tau"]) == 4
    assert rep["diagnostics"]["min_ess_bulk"] > 20
    assert (out / "corner.png").stat().st_size > 1000
    post = az.from_netcdf(str(out / "posterior.nc"))
    assert post.posterior.attrs["method"] == "emcee"
    assert "pixel" not in post.posterior.dims  # one material
    assert list(post.log_likelihood["obs"].dims) == ["chain", "draw", "sample", "channel"]
    assert list(post.constant_data["weight"].dims) == ["sample", "channel"]
    assert list(post.observed_data["channel"].values) == ["R", "G", "B"]

    # The library call behind it: the same draws and report, typed.
    sampler = jp.EmceeOptions(n_walkers=10, max_steps=400)
    res = jm.sample_posterior(src, "lambert", sampler)
    assert isinstance(res, jm.BRDFPosterior) and res.sampler_name == "emcee"
    for j, lab in enumerate(res.samples.labels):
        drawn = post.posterior[lab.replace(".", "_")].values  # (walkers, draws)
        np.testing.assert_array_equal(res.samples.natural[0, ..., j], drawn, err_msg=lab)
    lib = jsonable(res.report())[0]
    assert list(rep) == ["input", "kind", *lib, "files"]
    assert rep["files"] == ["posterior.nc", "corner.png"]
    for key in ("model", "sampler", "samples_used", "fit", "noise", "posterior", "diagnostics"):
        assert rep[key] == lib[key], key
    # What ran: the sampler's settings (seed included), the fit's options and starts.
    ran = rep["settings"]
    assert ran == lib["settings"] and ran["options"] == jm.MeasuredOptions().to_json()
    assert ran["sampler"]["type"] == "emcee" and ran["sampler"]["seed"] == 0
    assert ran["sampler"]["n_walkers"] == 10 and ran["sampler"]["max_steps"] == 400
    assert ran["starts"] == jm.MultiStart().to_json()
    assert res.n_used == int(np.sum(np.asarray(res.data.weight) > 0)) > 0
    with pytest.raises(TypeError, match="EmceeOptions or HMCOptions"):
        jm.sample_posterior(src, "lambert", jp.AdaptiveOptions())


def _draws_at_start(lp, th0, options, seed):
    """A stand-in sampler's draws: each pixel's (N, D) start plus noise 1e-3, seeded."""
    rng = np.random.default_rng(seed)
    n, c, m = th0.shape[0], options.num_chains, options.num_samples
    x = th0[:, None, None, :] + 1e-3 * rng.normal(size=(n, c, m, th0.shape[1]))
    st = {"acceptance_rate": np.ones((n, c, m)), "diverging": np.zeros((n, c, m), bool)}
    return jp.Samples(x, x, lp.labels, st, "hmc", run_s=1.0, no_estimate=np.zeros(n, bool))


def test_adaptive_chunks_have_one_shape_and_map_back(lambert, monkeypatch):
    """MCMC on 5 pixels (the 6th has no estimate) in chunks of at most 4: two balanced
    chunks of 3, every sampler call the same shape (the last chunk padded by repeating
    pixels, one compiled program for the map), and each pixel's summary comes from its own
    draws (the sampler is replaced by a stand-in whose draws sit at the start point: no
    compilation)."""
    from jaxrefl.posterior import _chunks

    lp, data, r, lap = lambert
    calls = []

    def fake(lp_, sub, th0, *, theta_std, normals, options, gibbs, seed):
        th0 = np.asarray(th0)
        calls.append((sub.obs.shape, th0.copy(), seed))
        return _draws_at_start(lp_, th0, options, seed)

    monkeypatch.setattr(_chunks, "sample_pixels", fake)
    opts = jp.HMCOptions(num_warmup=5, num_samples=30, num_chains=2)
    th, sd, flag = np.asarray(r.theta), np.asarray(lap.theta_std), np.asarray(lap.flag)
    th = th.copy()
    th[5] = np.nan
    # No second pass: the stand-in's 60 draws a pixel are noise, whose R-hat can pass 1.05.
    o = jp.AdaptiveOptions(mcmc="all", hmc=opts, chunk=4, seed=7, rerun_rhat=None, workers=1)
    u = jp.adaptive_uncertainty(lp, data, th, sd, flag, o)
    assert [c[0] for c in calls] == [(3, 6, 3), (3, 6, 3)] and [c[2] for c in calls] == [7, 8]
    np.testing.assert_array_equal(calls[1][1], np.asarray(lp.init_theta(th[[3, 4, 3]])))
    start = np.asarray(lp.init_theta(th[:5]))  # where the stand-in's draws sit
    np.testing.assert_allclose(u.mean[:5], start, atol=2e-3)  # each pixel its own draws
    assert np.all(np.isnan(u.mean[5])) and u.method[5] == 0
    assert u.samples.theta.shape == (5, 2, 30, lp.size)
    assert u.timings["mcmc_chunks"] == 2 and u.timings["mcmc_s"] == 2.0
    assert u.timings["mcmc_chunk_size"] == 3
    assert np.all(np.isfinite(u.rhat[:5])) and np.all(np.isin(u.method[:5], (2, 3)))
    lean = jp.adaptive_uncertainty(lp, data, th, sd, flag, replace(o, keep_samples=False))
    assert lean.samples is None
    np.testing.assert_array_equal(lean.std, u.std)
    with pytest.raises(ValueError, match="chunk"):
        jp.AdaptiveOptions(mcmc="all", chunk=0)


def test_chunks_sampled_in_threads_give_the_map_of_a_loop(lambert, monkeypatch):
    """workers > 1 runs chunks at once in threads; each chunk's seed is its index's, so the
    map equals the one-at-a-time loop's, the chunks come back in order, and every chunk
    runs in the pool's threads, the first ones included (they share one compilation:
    test_threads_share_one_compilation)."""
    import threading

    from jaxrefl.posterior import _chunks

    lp, data, r, lap = lambert
    where: dict[int, list] = {}

    def fake(lp_, sub, th0, *, theta_std, normals, options, gibbs, seed):
        where[workers].append((seed, threading.current_thread()))
        return _draws_at_start(lp_, np.asarray(th0), options, seed)

    monkeypatch.setattr(_chunks, "sample_pixels", fake)
    th, sd, flag = np.asarray(r.theta), np.asarray(lap.theta_std), np.asarray(lap.flag)
    maps = {}
    opts = jp.HMCOptions(num_warmup=5, num_samples=20, num_chains=2)
    for workers in (1, 3):
        where[workers] = []
        o = jp.AdaptiveOptions(
            mcmc="all", hmc=opts, chunk=1, seed=3, workers=workers, rerun_rhat=None
        )
        maps[workers] = jp.adaptive_uncertainty(lp, data, th, sd, flag, o)
    one, three = where[1], where[3]
    assert sorted(s for s, _ in three) == [s for s, _ in one] == list(range(3, 3 + th.shape[0]))
    assert all(t is not threading.main_thread() for _, t in three)
    # the same draws per pixel, whatever thread sampled them
    np.testing.assert_array_equal(maps[1].samples.theta, maps[3].samples.theta)
    for name in ("mean", "std", "q05", "q95", "rhat", "ess_bulk", "method"):
        np.testing.assert_array_equal(getattr(maps[1], name), getattr(maps[3], name), name)
    with pytest.raises(ValueError, match="workers"):
        jp.AdaptiveOptions(workers=0)


def test_chunk_count_fills_whole_rounds_of_workers():
    """A pass's chunk count is rounded up to an even number, so two workers never leave a
    core idle, a pass of one chunk's pixels included; the partition does not depend on
    the number of workers."""
    from jaxrefl.posterior._chunks import chunk_size as _chunk_size

    assert _chunk_size(22979, 2048, 128) == 1920  # 12 chunks
    assert _chunk_size(22000, 2048, 128) == 1920  # 12, not 11 with a core idle
    assert _chunk_size(3078, 2048, 128) == 1664  # 2 chunks, not 2 of 2048
    assert _chunk_size(1000, 2048, 128) == 512  # two at once
    assert _chunk_size(100, 2048, 128) == 50  # two single batches
    assert _chunk_size(1, 1, 128) == 1  # never more chunks than pixels


def test_threads_share_one_compilation():
    """Items that need the same program, run at once in threads from the first on
    (in_order), compile it once: the premise of running a pass's first chunks together."""
    import logging

    import jax.numpy as jnp

    from jaxrefl._threads import in_order

    def f(x):
        for i in range(200):  # a program whose compilation takes a while
            x = jnp.sin(x) * (i + 1.0)
        return x

    program = jax.jit(f)
    xs = [jnp.full((8,), float(i)) for i in range(4)]
    lines: list[str] = []

    class Lines(logging.Handler):
        def emit(self, record):
            lines.append(record.getMessage())

    log = logging.getLogger("jax._src.dispatch")
    handler, level = Lines(), log.level
    log.addHandler(handler)
    log.setLevel(logging.DEBUG)
    try:
        with jax.log_compiles(True):
            out = list(in_order(lambda i: program(xs[i]).block_until_ready(), range(4), 2))
    finally:
        log.removeHandler(handler)
        log.setLevel(level)
    assert sum("XLA compilation of jit(f)" in m for m in lines) == 1, lines
    np.testing.assert_allclose(out[3], f(xs[3]), rtol=1e-5)


def test_in_order_raises_at_the_failing_item():
    from jaxrefl._threads import in_order

    def f(i):
        if i == 4:
            raise RuntimeError("item 4")
        return i * i

    got = []
    with pytest.raises(RuntimeError, match="item 4"):
        for v in in_order(f, range(9), 2):
            got.append(v)
    assert got == [0, 1, 4, 9]
    assert list(in_order(f, range(4), 1)) == list(in_order(f, range(4), 3)) == [0, 1, 4, 9]


def test_second_pass_reruns_the_pixels_whose_chains_disagree(lambert, monkeypatch):
    """Pixels whose first-pass chains disagree (R-hat above ``rerun_rhat``) run a second,
    longer pass (longer_options: twice the warm-up, thin 4, no jitter) from first-pass draws,
    chain c from first-pass chain c, with the draws' std as the initial metric; its summaries and
    draws replace the first's and the report says what it changed (stand-in sampler)."""
    from jaxrefl.posterior import _chunks

    lp, data, r, lap = lambert
    th, sd, flag = np.asarray(r.theta), np.asarray(lap.theta_std), np.asarray(lap.flag)
    start = np.asarray(lp.init_theta(th))
    apart = [1, 4]  # these pixels' first-pass chains sit 1 apart
    calls = []

    def fake(lp_, sub, th0, *, theta_std, normals, options, gibbs, seed):
        th0, theta_std = np.asarray(th0), np.asarray(theta_std)
        calls.append((th0.copy(), theta_std.copy(), options))
        rng = np.random.default_rng(seed)
        c, m = options.num_chains, options.num_samples
        if th0.ndim == 2:  # first pass: one start per pixel
            x = np.repeat(th0[:, None, None, :], c, 1).repeat(m, 2)
            px = [int(np.flatnonzero(np.all(start == t, -1))[0]) for t in th0]
            x[np.isin(px, apart), 1] += 1.0
        else:  # second pass: the chains agree, about their starts' mean
            x = np.repeat(th0.mean(1)[:, None, None, :], c, 1).repeat(m, 2)
        x = x + 1e-2 * rng.normal(size=x.shape)
        st = {"acceptance_rate": np.ones(x.shape[:3]), "diverging": np.zeros(x.shape[:3], bool)}
        n = x.shape[0]
        return jp.Samples(x, x, lp_.labels, st, "hmc", run_s=1.0, no_estimate=np.zeros(n, bool))

    monkeypatch.setattr(_chunks, "sample_pixels", fake)
    opts = jp.HMCOptions(num_warmup=5, num_samples=30, num_chains=2)
    # Threshold 1.1: the agreeing stand-in chains are 60 noise draws a pixel, whose R-hat
    # can pass 1.05 by chance; the chains 1 apart are far above either.
    o = jp.AdaptiveOptions(mcmc="all", hmc=opts, chunk=4, seed=7, rerun_rhat=1.1, workers=1)
    assert o.second_pass == jp.longer_options(opts)
    u = jp.adaptive_uncertainty(lp, data, th, sd, flag, o)
    assert len(calls) == 4  # two first-pass chunks (6 pixels), two second-pass chunks
    x0, sd0 = (np.concatenate([calls[2][k], calls[3][k]]) for k in (0, 1))
    o2 = calls[2][2]
    assert calls[3][2] == o2
    assert (o2.num_warmup, o2.thin, o2.init_jitter) == (10, 4, 0.0)
    assert (o2.num_chains, o2.num_samples) == (opts.num_chains, opts.num_samples)
    assert x0.shape[:2] == (2, 2)  # the 2 pixels, one start per chain
    np.testing.assert_allclose(x0[:2, 0], start[apart], atol=0.05)
    np.testing.assert_allclose(x0[:2, 1], start[apart] + 1.0, atol=0.05)
    np.testing.assert_allclose(sd0[:2], 0.5, rtol=0.05)  # the std of chains 1 apart
    np.testing.assert_array_equal(np.flatnonzero(u.rerun), apart)
    assert np.all(u.rhat_first[apart] > 1.5) and np.all(np.isnan(u.rhat_first[[0, 2, 3, 5]]))
    assert np.all(u.rhat < 1.1)
    at = [int(np.flatnonzero(u.mcmc_pixels == i)[0]) for i in apart]
    # about the mean of the two restarts (first-pass draws, each with the stand-in's 1e-2
    # noise: the mean's std is about 0.007), halfway between chains 1 apart
    np.testing.assert_allclose(u.samples.theta[at].mean((1, 2)), start[apart] + 0.5, atol=0.03)
    np.testing.assert_allclose(u.mean[apart], u.samples.natural[at].mean((1, 2)))
    sp = u.report()["mcmc"]["second_pass"]
    assert sp["pixels"] == 2 and sp["pixels_rhat_above_1.1_after"] == 0
    assert sp["max_rhat_before"]["min"] > 1.5 and sp["max_rhat_after"]["max"] < 1.1
    ch = uncertainty_channels(u, 2, 3)["mcmc_pass.Y"].reshape(-1)
    np.testing.assert_array_equal(ch, [1, 2, 1, 1, 2, 1])
    lean = jp.adaptive_uncertainty(lp, data, th, sd, flag, replace(o, keep_samples=False))
    np.testing.assert_array_equal(lean.std, u.std)  # the same without keeping the draws
    # Draws kept for 3 of the 6 MCMC pixels: the same summaries, and each kept pixel's
    # draws (second pass included) are the full run's.
    capped = jp.adaptive_uncertainty(lp, data, th, sd, flag, replace(o, max_kept_pixels=3))
    np.testing.assert_array_equal(capped.std, u.std)
    kept = capped.kept_pixels
    assert kept.size == 3 and capped.samples.n_pixels == 3 and set(apart) & set(kept)
    order = [int(np.flatnonzero(u.mcmc_pixels == i)[0]) for i in kept]
    assert order == sorted(order)  # in the MCMC pixels' order
    np.testing.assert_array_equal(capped.samples.theta, u.samples.theta[order])
    assert capped.report()["mcmc"]["pixels_with_draws"] == 3
    assert u.report()["mcmc"]["pixels_with_draws"] == 6 and u.kept_pixels is None
    calls.clear()
    off = jp.adaptive_uncertainty(lp, data, th, sd, flag, replace(o, rerun_rhat=None))
    assert len(calls) == 2 and not off.rerun.any() and np.all(off.rhat[apart] > 1.5)
    assert replace(o, rerun_rhat=None).second_pass is None
    with pytest.raises(ValueError, match="num_chains and num_samples"):
        bad = jp.HMCOptions(num_warmup=5, num_samples=30, num_chains=4)
        replace(o, rerun_hmc=bad)


def test_adaptive_options_are_one_checked_immutable_object():
    """AdaptiveOptions: defaults as documented, strings become MCMCPixels, out-of-range
    settings are refused when the object is built, and it cannot be changed in place."""
    o = jp.AdaptiveOptions()
    assert (o.mcmc, o.audit, o.hmc, o.rerun_rhat, o.chunk, o.seed) == (
        MCMCPixels.FLAGGED,
        0.02,
        jp.UNCERTAINTY_MAP_HMC,
        1.05,
        2048,
        0,
    )
    assert o.keep_samples and o.second_pass == jp.longer_options(jp.UNCERTAINTY_MAP_HMC)
    # one map default, said once (jaxrefl._map_defaults) for the library and the command
    from jaxrefl._map_defaults import MAP_GIBBS, MAP_SAMPLER

    assert all(getattr(o.hmc, k) == v for k, v in MAP_SAMPLER.items())
    assert o.gibbs == jp.UNCERTAINTY_MAP_GIBBS == jp.GibbsOptions(**MAP_GIBBS)
    assert (o.hmc.num_warmup, o.hmc.num_samples, o.hmc.num_chains) == (100, 100, 2)
    assert jp.AdaptiveOptions(mcmc="all").mcmc is MCMCPixels.ALL
    for bad, match in (
        (dict(mcmc="some"), "mcmc must be one of"),
        (dict(audit=1.5), "audit"),
        (dict(audit=-0.1), "audit"),
        (dict(rerun_rhat=0.0), "rerun_rhat"),
        (dict(rerun_rhat=math.nan), "rerun_rhat"),
        (dict(chunk=0), "chunk"),
    ):
        with pytest.raises(ValueError, match=match):
            jp.AdaptiveOptions(**bad)
    with pytest.raises(FrozenInstanceError):
        o.seed = 1  # type: ignore[misc]


def test_vectorised_diagnostics_match_arviz():
    """``diagnostics`` (vectorised R-hat, bulk and tail ESS) equals ArviZ's per-element
    estimators on mixed, autocorrelated, tied (rejected HMC steps), unmixed and NaN chains."""
    rng = np.random.default_rng(4)
    n, c, m, d = 12, 2, 60, 2
    x = np.cumsum(rng.normal(size=(n, c, m, d)), 2) * 0.3 + rng.normal(size=(n, c, m, d))
    x[:3] = np.round(x[:3], 1)  # ties
    x[3, 1] += 4.0  # chains apart: R-hat >> 1
    x[4, 0, 7, 1] = np.nan
    s = jp.Samples(
        theta=x,
        natural=x,
        labels=("a", "b"),
        stats={"acceptance_rate": np.ones((n, c, m)), "diverging": np.zeros((n, c, m), bool)},
        method="hmc",
    )
    dg = jp.diagnostics(s)
    ds = az.convert_to_dataset({"x": np.moveaxis(x, 0, 2)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = {
            "rhat": np.array(az.rhat(ds)["x"]),
            "ess_bulk": np.array(az.ess(ds, method="bulk")["x"]),
            "ess_tail": np.array(az.ess(ds, method="tail")["x"]),
        }
    ref = {k: np.where(np.isnan(x).any(axis=(1, 2, 3))[:, None], np.nan, v) for k, v in ref.items()}
    for k, v in ref.items():
        np.testing.assert_allclose(dg[k], v, rtol=1e-8, err_msg=k)
    assert dg["max_rhat"][3] > 1.5 and np.isnan(dg["max_rhat"][4])
    # the shared rank normalisation gives the separate estimators' values
    from jaxrefl.posterior._fastdiag import ess_bulk, ess_tail, rank_diagnostics, rhat_rank

    flat = np.moveaxis(x, -1, 1).reshape(n * d, c, m)
    for a, b in zip(rank_diagnostics(flat), (rhat_rank, ess_bulk, ess_tail), strict=True):
        np.testing.assert_array_equal(a, b(flat))


def test_third_pass_reruns_the_pixels_still_apart(lambert, monkeypatch):
    """Pixels whose chains still disagree after the second pass run a third, with twice
    its scans between kept draws, from second-pass draws; the others keep the second
    pass's numbers, and the report counts them. rerun_passes=1 stops after the second
    (stand-in sampler: chains 1 apart until thin 8)."""
    from jaxrefl.posterior import _chunks

    lp, data, r, lap = lambert
    th, sd, flag = np.asarray(r.theta), np.asarray(lap.theta_std), np.asarray(lap.flag)
    start = np.asarray(lp.init_theta(th))
    apart = [1, 4]  # chains apart in the first pass
    stubborn = [4]  # ... and in the second
    calls = []

    def fake(lp_, sub, th0, *, theta_std, normals, options, gibbs, seed):
        th0 = np.asarray(th0)
        calls.append((options.thin, th0.copy()))
        rng = np.random.default_rng(seed)
        c, m = options.num_chains, options.num_samples
        base = th0 if th0.ndim == 2 else th0[:, 0]
        px = [int(np.argmin(np.abs(start - t).sum(-1))) for t in base]
        x = np.repeat(base[:, None, None, :], c, 1).repeat(m, 2)
        x = x + 1e-2 * rng.normal(size=x.shape)
        for k, p in enumerate(px):
            if (p in apart and options.thin == 1) or (p in stubborn and options.thin == 4):
                x[k, 1] += 1.0
        st = {"acceptance_rate": np.ones(x.shape[:3]), "diverging": np.zeros(x.shape[:3], bool)}
        n = x.shape[0]
        return jp.Samples(x, x, lp_.labels, st, "hmc", run_s=1.0, no_estimate=np.zeros(n, bool))

    monkeypatch.setattr(_chunks, "sample_pixels", fake)
    opts = jp.HMCOptions(num_warmup=5, num_samples=30, num_chains=2)
    o = jp.AdaptiveOptions(mcmc="all", hmc=opts, chunk=4, seed=7, rerun_rhat=1.1, workers=1)
    u = jp.adaptive_uncertainty(lp, data, th, sd, flag, o)
    thins = [t for t, _ in calls]
    assert thins == [1, 1, 4, 4, 8]  # 2 first-pass chunks, 2 second-pass, 1 third-pass
    assert calls[4][1].shape[0] == 1  # the one stubborn pixel
    assert np.all(u.rhat < 1.1) and list(np.flatnonzero(u.rerun)) == apart
    tp = u.report()["mcmc"]["third_pass"]
    assert tp == {"pixels": 1, "skipped": "", "pixels_rhat_above_1.05_after": 0}
    calls.clear()
    once = jp.adaptive_uncertainty(lp, data, th, sd, flag, replace(o, rerun_passes=1))
    assert [t for t, _ in calls] == [1, 1, 4, 4] and once.rhat[4] > 1.1
    assert once.report()["mcmc"]["third_pass"]["pixels"] == 0
    np.testing.assert_array_equal(once.std[[0, 1, 2, 3, 5]], u.std[[0, 1, 2, 3, 5]])
    assert "rerun_passes is 1" in once.report()["mcmc"]["third_pass"]["skipped"]
    # A second pass that leaves most of its pixels apart runs no third: both stay apart.
    calls.clear()
    stubborn[:] = [1, 4]
    both = jp.adaptive_uncertainty(lp, data, th, sd, flag, o)
    assert [t for t, _ in calls] == [1, 1, 4, 4] and np.all(both.rhat[apart] > 1.1)
    assert "2 of the second pass's 2 pixels" in both.report()["mcmc"]["third_pass"]["skipped"]
    with pytest.raises(ValueError, match="rerun_passes"):
        replace(o, rerun_passes=3)


def test_chunk_folder_resumes_without_sampling_again(lambert, monkeypatch, tmp_path):
    """With ``chunk_dir`` every chunk's draws (both passes) are written as they finish; a
    rerun reads them and samples nothing, with the same map; another seed, another box of
    the parameters, or other priors match none of them (stand-in sampler whose chains
    disagree on some pixels: a second pass runs)."""
    from jaxrefl.posterior import _chunks

    lp, data, r, lap = lambert
    th, sd, flag = np.asarray(r.theta), np.asarray(lap.theta_std), np.asarray(lap.flag)
    calls = []

    def fake(lp_, sub, th0, *, theta_std, normals, options, gibbs, seed):
        calls.append(seed)
        th0 = np.asarray(th0)
        rng = np.random.default_rng(seed)
        c, m = options.num_chains, options.num_samples
        x = th0[:, None, None, :] if th0.ndim == 2 else th0.mean(1)[:, None, None, :]
        x = np.repeat(np.repeat(x, c, 1), m, 2) + 1e-2 * rng.normal(size=(th0.shape[0], c, m, 1))
        if th0.ndim == 2:
            x[[0, 2], 1] += 1.0  # in each chunk (3 pixels), two pixels' chains disagree
        st = {"acceptance_rate": np.ones(x.shape[:3]), "diverging": np.zeros(x.shape[:3], bool)}
        tuning = {"step_size": np.ones(x.shape[:2])}
        n = x.shape[0]
        return jp.Samples(
            x, x, lp_.labels, st, "hmc", tuning, run_s=1.0, no_estimate=np.zeros(n, bool)
        )

    monkeypatch.setattr(_chunks, "sample_pixels", fake)
    opts = jp.HMCOptions(num_warmup=5, num_samples=30, num_chains=2)
    o = jp.AdaptiveOptions(mcmc="all", hmc=opts, chunk=4, seed=7, workers=1)
    folder = tmp_path / "mcmc"
    first = jp.adaptive_uncertainty(lp, data, th, sd, flag, o, chunk_dir=folder)
    assert len(calls) == 4 and first.rerun.any()  # two first-pass chunks, two second-pass
    assert len(list(folder.glob("first_*/chunk_*.npz"))) == 2
    assert len(list(folder.glob("second_*/chunk_*.npz"))) == 2
    calls.clear()
    again = jp.adaptive_uncertainty(lp, data, th, sd, flag, o, chunk_dir=folder)
    assert calls == []
    for name in ("mean", "std", "q05", "q95", "rhat", "rerun", "rhat_first", "method"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name), err_msg=name)
    np.testing.assert_array_equal(again.samples.theta, first.samples.theta)
    assert again.timings["mcmc_s"] == first.timings["mcmc_s"] == 2.0
    jp.adaptive_uncertainty(lp, data, th, sd, flag, replace(o, seed=8), chunk_dir=folder)
    assert len(calls) == 4  # another seed: other chunks
    # another parameter box (theta's coordinates differ): other chunks
    calls.clear()
    m = lp.space.model
    narrow = fit.ParamSpace(m, channels=3, bounds={"albedo": (0.0, 0.99)})
    lp_narrow = jp.log_posterior(m, narrow, fit.GaussianNoise(SIGMA))
    jp.adaptive_uncertainty(lp_narrow, data, th, sd, flag, o, chunk_dir=folder)
    assert len(calls) == 4
    # other priors (another posterior): other chunks
    calls.clear()
    lp_prior = jp.log_posterior(
        m, lp.space, fit.GaussianNoise(SIGMA), priors={"albedo": jp.Normal(0.5, 0.3)}
    )
    assert repr(lp_prior.priors) != repr(lp.priors)
    jp.adaptive_uncertainty(lp_prior, data, th, sd, flag, o, chunk_dir=folder)
    assert len(calls) == 4


def test_second_pass_of_an_untuned_sampler_reuses_the_first_pass_program(lambert, monkeypatch):
    """Where every first-pass chunk came from the width sampler, the second pass runs the
    first pass's settings with twice the scans between draws (untuned_rerun: an argument of
    the width sampler's program, not a constant) and a new seed, in chunks padded to the
    first pass's size: the same compiled program (stand-in sampler). HMC and exact Gibbs
    keep longer_options."""
    from jaxrefl.posterior import _chunks

    lp, data, r, lap = lambert
    th, sd, flag = np.asarray(r.theta), np.asarray(lap.theta_std), np.asarray(lap.flag)
    start = np.asarray(lp.init_theta(th))
    calls = []

    def fake(lp_, sub, th0, *, theta_std, normals, options, gibbs, seed):
        th0 = np.asarray(th0)
        calls.append((th0.shape, options, seed))
        rng = np.random.default_rng(seed)
        c, m = options.num_chains, options.num_samples
        if th0.ndim == 2:  # first pass: pixel 1's chains 1 apart
            x = np.repeat(th0[:, None, None, :], c, 1).repeat(m, 2)
            px = [int(np.flatnonzero(np.all(start == t, -1))[0]) for t in th0]
            x[np.isin(px, [1]), 1] += 1.0
        else:
            x = np.repeat(th0.mean(1)[:, None, None, :], c, 1).repeat(m, 2)
        x = x + 1e-2 * rng.normal(size=x.shape)
        st = {"acceptance_rate": np.ones(x.shape[:3]), "diverging": np.zeros(x.shape[:3], bool)}
        return jp.Samples(
            x,
            x,
            lp_.labels,
            st,
            "gibbs_mh",
            run_s=1.0,
            no_estimate=np.zeros(x.shape[0], bool),
        )

    monkeypatch.setattr(_chunks, "sample_pixels", fake)
    opts = jp.HMCOptions(num_warmup=5, num_samples=30, num_chains=2)
    o = jp.AdaptiveOptions(mcmc="all", hmc=opts, chunk=4, seed=7, rerun_rhat=1.1, workers=1)
    u = jp.adaptive_uncertainty(lp, data, th, sd, flag, o)
    assert len(calls) == 3 and u.timings["sampler"] == "gibbs_mh"
    (s1, o1, seed1), (_s, _o, seed2), (s3, o3, seed3) = calls
    assert o1 == opts and o3 == jp.untuned_rerun(opts) == replace(opts, thin=2)
    assert seed3 not in (seed1, seed2)
    assert s3[0] == s1[0] == 3  # the rerun's one pixel padded to the first chunks' 3
    assert u.timings["rerun_settings"] == "untuned" and u.rerun.sum() == 1
    for method in ("hmc", "gibbs"):  # these keep longer_options for the second pass
        calls.clear()
        monkeypatch.setattr(
            _chunks,
            "sample_pixels",
            lambda *a, method=method, **k: replace(fake(*a, **k), method=method),
        )
        u = jp.adaptive_uncertainty(lp, data, th, sd, flag, o)
        assert calls[2][1] == jp.longer_options(opts) and calls[2][0][0] == 1
        assert "rerun_settings" not in u.timings


def test_time_limit_leaves_laplace_pixels_marked_and_a_pass_says_what_it_does(lambert, monkeypatch):
    """A deadline: a chunk is not started where the last chunk's time would carry it past
    the deadline; its pixels keep their Laplace summaries with method
    ``laplace_time_limit`` (4), counted in the timings, and are not among the MCMC pixels.
    ``log`` hears each pass's start, its progress every HEARTBEAT_S and its end."""
    import time

    from jaxrefl.posterior import _chunks

    lp, data, r, lap = lambert
    theta, theta_std = np.asarray(r.theta), np.asarray(lap.theta_std)
    flag = np.asarray(lap.flag)
    opts = jp.AdaptiveOptions(
        mcmc="all",
        hmc=replace(jp.UNCERTAINTY_MAP_HMC, num_warmup=20, num_samples=20, batch_size=2),
        chunk=2,
        rerun_rhat=None,
        workers=1,
    )
    lines: list[str] = []
    monkeypatch.setattr(_chunks, "HEARTBEAT_S", 0.01)
    # past already: nothing is sampled, every pixel keeps its Laplace summary
    u0 = jp.adaptive_uncertainty(
        lp, data, theta, theta_std, flag, opts, deadline=time.perf_counter() - 1.0, log=lines.append
    )
    assert np.all(u0.method == jp.Method.LAPLACE_TIME_LIMIT) and u0.mcmc_pixels.size == 0
    assert u0.samples is None or u0.samples.theta.shape[0] == 0
    assert u0.timings["time_limit_pixels_left"] == 6
    assert u0.report()["method_counts"]["laplace_time_limit"] == 6
    # why they were chosen: pixel 0 for its AT_BOUND flag, the others as mcmc="all" asked
    assert u0.report()["mcmc_reasons"]["AT_BOUND"] == 1 and u0.reasons["audit"] == 5
    np.testing.assert_allclose(u0.std[:, :3], np.asarray(lap.std), rtol=1e-8)
    assert lines[0].startswith("MCMC first pass: 6 pixels in 3 chunks")
    assert "3 left by the time limit" in lines[-1]
    # ahead: the first chunk runs; it is timed as a slow one, so the next, which would end
    # past the deadline, is not started
    lines.clear()

    def slow(self, s):  # a compiled chunk can end before a heartbeat: wait for one
        time.sleep(5 * _chunks.HEARTBEAT_S)
        self.last_s = 1e6

    monkeypatch.setattr(_chunks._Pace, "took", slow)
    u1 = jp.adaptive_uncertainty(
        lp,
        data,
        theta,
        theta_std,
        flag,
        opts,
        deadline=time.perf_counter() + 600.0,
        log=lines.append,
    )
    sampled = np.isin(u1.method, (jp.Method.MCMC, jp.Method.MCMC_AUDIT))
    assert sampled.sum() == 2 and np.sum(u1.method == jp.Method.LAPLACE_TIME_LIMIT) == 4
    np.testing.assert_array_equal(np.sort(u1.mcmc_pixels), np.flatnonzero(sampled))
    assert u1.samples is not None and u1.samples.theta.shape[0] == 2
    assert np.all(np.isfinite(u1.rhat[sampled])) and np.all(np.isnan(u1.rhat[~sampled]))
    assert any("chunks done" in ln for ln in lines), lines  # the heartbeat
    # without a deadline the same options sample every pixel
    u2 = jp.adaptive_uncertainty(lp, data, theta, theta_std, flag, opts)
    assert np.all(np.isin(u2.method, (jp.Method.MCMC, jp.Method.MCMC_AUDIT)))
    # the limit as a setting, AdaptiveOptions.time_limit_s (counted from the call): a
    # nanosecond is over before the first chunk
    u3 = jp.adaptive_uncertainty(lp, data, theta, theta_std, flag, replace(opts, time_limit_s=1e-9))
    assert np.all(u3.method == jp.Method.LAPLACE_TIME_LIMIT)
    with pytest.raises(ValueError, match="time_limit_s must be a positive number"):
        replace(opts, time_limit_s=0.0)


def test_cli_sample_prints_its_stages_without_a_terminal_and_stops_at_its_time_limit(
    demo_cap, tmp_path
):
    """`jaxrefl sample` in a subprocess (stderr a pipe, not a terminal): one line per stage
    with the seconds since the start; --time-limit: exit status 3, the MCMC pixels left
    marked ``laplace_time_limit`` in uncertainty.exr and counted in report.json, the fit's
    work kept and named for a rerun."""
    import subprocess
    import sys

    cap = demo_cap
    out = tmp_path / "out"
    argv = ["sample", str(cap), "--out", str(out), "--model", "lambert", "--pixels", "2:6,2:6"]
    argv += ["--mcmc", "all", "--time-limit", "0.001"]
    code = "import sys; from jaxrefl.cli import main; sys.exit(main(sys.argv[1:]))"
    r = subprocess.run(
        [sys.executable, "-c", code, *argv],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 3, r.stderr
    stages = [ln for ln in r.stderr.splitlines() if ln.startswith("[")]
    for want in (
        "fit: 4 x 4 pixels",
        "fit: model lambert (given)",
        "priors:",
        "MCMC first pass: 16 pixels",
        "writing",
    ):
        assert any(want in ln for ln in stages), (want, r.stderr)
    assert all(ln.split("]")[0].strip("[ s").replace(".", "").isdigit() for ln in stages)
    assert "left 16 MCMC pixels their Laplace summary" in r.stderr and str(out / "mcmc") in r.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["time_limit"] == {
        "limit_s": 0.001,
        "pixels_left_laplace": 16,
        "second_pass_pixels_left": 0,
        "reached": True,
    }
    assert rep["model_choice"]["model"] == "lambert" and rep["model_choice"]["why"] == "given"
    assert rep["nonfinite_counts"] == {"SUMMARY": 0, "DIAGNOSTIC": 0}
    assert {"fit_s", "priors_s", "posterior_s", "total_s", "write_s"} <= set(rep["timings"])
    im = read_exr(out / "uncertainty.exr")
    assert np.all(im.channels["method.Y"] == int(jp.Method.LAPLACE_TIME_LIMIT))
    assert (out / "fit").is_dir()  # the resumable work stays for the rerun


def test_map_widens_grey_ggx_where_pixels_pile_at_its_f0_cap():
    """uncertainty_maps: a ggx fit of a metal (F0 up to 0.9) piles pixels at the 0.25 cap
    (more than WIDEN_SHARE of them), so the map is fitted and sampled with ggx_rgb and
    model_choice says why; a dielectric keeps the ggx it was given."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import capture_family as cfam

    jax.config.update("jax_enable_x64", True)
    # the light as stated: the light is not what this tests (tests/test_light*.py)
    job = svbrdf.FitJob(model="ggx", config=fit.FitConfig(dtype=np.float64), light="fixed")
    none = jp.AdaptiveOptions(mcmc="none")
    by_name = {m.name: m for m in cfam.FAMILY}
    metal = replace(by_name["gold_foil"], size=8)
    res = svbrdf.uncertainty_maps(cfam.render_member(metal).capture(), job, none)
    mc = res.model_choice
    assert res.model == "ggx_rgb" and res.posterior.labels[3:6] == (
        "specular.R",
        "specular.G",
        "specular.B",
    )
    assert mc["requested"] == "ggx" and mc["widened"]["from"] == "ggx"
    assert mc["capped_share"] > svbrdf._uncertainty.WIDEN_SHARE > mc["capped_share_after"]
    assert "cap" in mc["widened"]["why"] and res.report()["model_choice"] == mc
    plastic = replace(by_name["colocated_tiles"], size=8, photos=metal.photos)
    kept = svbrdf.uncertainty_maps(cfam.render_member(plastic).capture(), job, none)
    assert kept.model == "ggx" and "widened" not in kept.model_choice
    assert kept.model_choice["capped_share"] <= svbrdf._uncertainty.WIDEN_SHARE

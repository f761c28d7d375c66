"""Every setting that changes a result is a field of an option object, and what ran records
it: a capture fit's job (its report and the tiles' resume manifest) and a measured fit's
report settings."""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest

from jaxrefl import measured as jm
from jaxrefl import svbrdf
from jaxrefl.io import MeasuredBRDF
from jaxrefl.svbrdf._job_types import COMPACT_MIN_PIXELS


def test_every_field_of_a_capture_job_is_recorded():
    """``FitJob.to_json`` is the manifest's fingerprint: a field it leaves out would let a
    resumed fit mix tiles of two settings."""
    job = svbrdf.FitJob(model="ggx", compact=True, alpha_min=0.01, tilt_std=0.2)
    rec = job.to_json()
    assert set(rec) == {f.name for f in dataclasses.fields(svbrdf.FitJob)}
    assert rec["compact"] is True and rec["alpha_min"] == 0.01 and rec["tilt_std"] == 0.2
    with pytest.raises(ValueError, match="compact must be True, False or None"):
        svbrdf.FitJob(compact="yes")


def test_the_model_choice_settings_are_the_jobs_and_recorded():
    """The candidates, the selection's pixel count and its seed change which model ``auto``
    picks (and ``pooled``'s width): they are the job's ``auto``, in its record (the
    manifest's fingerprint) and checked when built."""
    auto = svbrdf.AutoOptions(candidates=("lambert", "GGX"), max_pixels=512, seed=3)
    assert auto.candidates == ("lambert", "ggx")  # canonical names
    rec = svbrdf.FitJob(auto=auto).to_json()["auto"]
    assert rec == {"candidates": ["lambert", "ggx"], "max_pixels": 512, "seed": 3}
    assert svbrdf.FitJob().to_json()["auto"]["candidates"] == list(svbrdf.AUTO_CANDIDATES)
    assert svbrdf.FitJob(auto=auto).to_json() != svbrdf.FitJob().to_json()
    with pytest.raises(ValueError, match="unknown model 'phong'"):
        svbrdf.AutoOptions(candidates=("lambert", "phong"))
    with pytest.raises(ValueError, match="names a model twice"):
        svbrdf.AutoOptions(candidates=("ggx", "ggx"))
    with pytest.raises(ValueError, match="max_pixels must be >= 1"):
        svbrdf.AutoOptions(max_pixels=0)
    with pytest.raises(ValueError, match="seed must be an integer"):
        svbrdf.AutoOptions(seed=0.5)
    with pytest.raises(ValueError, match=r"FitJob\.auto must be an AutoOptions"):
        svbrdf.FitJob(auto={"seed": 1})


def test_the_size_rule_decides_compaction_where_the_job_does_not():
    size_rule = svbrdf.FitJob()
    assert size_rule.compacts(COMPACT_MIN_PIXELS) and not size_rule.compacts(COMPACT_MIN_PIXELS - 1)
    assert svbrdf.FitJob(compact=False).compacts(10 * COMPACT_MIN_PIXELS) is False
    assert svbrdf.FitJob(compact=True).compacts(1) is True


def _lambert_material(k: int = 64, spectral: bool = False) -> MeasuredBRDF:
    rng = np.random.default_rng(0)

    def hemi():
        u = rng.uniform(0.05, 1.0, k)
        phi = rng.uniform(0.0, 2 * np.pi, k)
        s = np.sqrt(1 - u * u)
        return np.stack([s * np.cos(phi), s * np.sin(phi), u], -1)

    if spectral:  # four bands, reflectance falling with wavelength
        nm = np.array([450.0, 500.0, 550.0, 600.0])
        values = np.full((k, 4), 0.5 / np.pi) * np.array([1.0, 0.9, 0.8, 0.7])
        return MeasuredBRDF(hemi(), hemi(), values, tuple(f"{w:g}nm" for w in nm), nm, "matte")
    values = np.full((k, 3), 0.5 / np.pi) * np.array([1.0, 0.8, 0.6])
    return MeasuredBRDF(hemi(), hemi(), values, ("R", "G", "B"), name="matte")


def test_every_measured_option_is_in_the_report_settings():
    m = _lambert_material()
    opts = jm.MeasuredOptions(max_theta_deg=70.0, cosine=False, retry_float64=False)
    rep = jm.fit_brdf(m, ["lambert"], options=opts, timing=False, starts=None)
    fields = {f.name for f in dataclasses.fields(jm.MeasuredOptions)}
    # RGB data: the spectral choice and the illuminant do not apply, and say so.
    assert {k: rep.settings[k] for k in fields} == {
        "max_theta_deg": 70.0,
        "cosine": False,
        "retry_float64": False,
        "spectral": None,
        "illuminant": None,
    }
    # The angle limit is the one applied: every sample kept is within it.
    cos_lim = np.cos(np.radians(70.0))
    assert np.all(rep.measured.wi[:, 2] >= cos_lim) and np.all(rep.measured.wo[:, 2] >= cos_lim)
    assert len(rep.measured) < len(m)
    with pytest.raises(ValueError, match="max_theta_deg in \\(0, 90\\]"):
        jm.MeasuredOptions(max_theta_deg=95.0)
    with pytest.raises(ValueError, match="cosine True or False"):
        jm.MeasuredOptions(cosine=1)


def test_the_spectral_choice_and_illuminant_are_options_and_recorded():
    """How spectral data are fitted (RGB under an illuminant, or a problem a band) is a field
    of :class:`MeasuredOptions`, which fit_brdf, fit_model and the report follow alike."""
    m = _lambert_material(spectral=True)
    kw = {"timing": False, "starts": None}
    e = jm.MeasuredOptions(illuminant="E", retry_float64=False)
    rgb = jm.fit_brdf(m, ["lambert"], options=e, **kw)
    assert (rgb.settings["spectral"], rgb.settings["illuminant"]) == ("rgb", "E")
    assert rgb.settings["channels"] == "joint" and rgb.measured.channels == ("R", "G", "B")
    # Equal energy maps a flat spectrum to equal channels: these fall with wavelength, so red
    # (long) is below blue (short), the fit's albedo too, and D65 gives other colours.
    albedo = rgb.fits["lambert"].params["albedo"]
    assert albedo[0] < albedo[2]
    d65 = jm.fit_brdf(m, ["lambert"], options=jm.MeasuredOptions(retry_float64=False), **kw)
    assert d65.settings["illuminant"] == "D65"
    assert not np.allclose(d65.fits["lambert"].params["albedo"], albedo, rtol=1e-3)
    # fit_model takes the same options: the same RGB fit.
    one = jm.fit_model(jm.build_model("lambert"), m, options=e, **kw)
    np.testing.assert_allclose(one.params["albedo"], albedo, rtol=1e-6)

    bands = jm.MeasuredOptions(spectral="bands", retry_float64=False)
    per_band = jm.fit_brdf(m, ["lambert"], options=bands, **kw)
    assert (per_band.settings["spectral"], per_band.settings["illuminant"]) == ("bands", None)
    assert per_band.settings["channels"] == "separate"
    assert per_band.fits["lambert"].params["albedo"].shape == (4,)
    with pytest.raises(ValueError, match="spectral one of 'rgb', 'bands'"):
        jm.MeasuredOptions(spectral="xyz")
    with pytest.raises(ValueError, match="illuminant one of 'D65', 'E'"):
        jm.MeasuredOptions(illuminant="A")


def test_the_entry_points_take_their_settings_as_option_objects():
    """The keyword arguments (with defaults) of the job-level entry points are option
    objects, data, the subject of the call, or how it runs (progress, folders, processes,
    logging): a new keyword that changes a result belongs in an option object, or here with
    its reason."""
    from jaxrefl import fit, ps
    from jaxrefl import posterior as jp

    allowed = {
        # option objects: job, options, config, starts, sampler, method, discrepancy
        # data: space, init, bounds, fixed, prior, weight, mask, labels, intensities,
        #   saturated, theta_std, normals, noise_scale, dof, args, natural, nested, cache,
        #   candidates, reference, calibrate_lights, models, name, seed (a caller's seed,
        #   refused where it disagrees with HMCOptions.seed)
        # the subject: which light (estimate_light), which baseline model (leave_one_out),
        #   the capture's downsampling (run_ps, as load_capture's resolution)
        # how it runs: out_dir, restart, progress, on_tile, distributed, log, chunk_dir,
        #   deadline (the caller's clock; its limit is AdaptiveOptions.time_limit_s),
        #   timing, devices
        svbrdf.fit_capture: {"job", "out_dir", "restart", "progress", "on_tile", "distributed"},
        svbrdf.uncertainty_maps: {"job", "options", "progress", "out_dir", "distributed", "log"},
        svbrdf.leave_one_out: {"job", "baseline", "progress"},
        svbrdf.predictive: {"discrepancy"},
        svbrdf.estimate_discrepancy: {"options"},
        svbrdf.estimate_light: {"light", "options"},
        svbrdf.plan_next: {"candidates", "options", "reference"},
        jp.adaptive_uncertainty: {
            *("options", "noise_scale", "normals", "dof"),
            *("progress", "chunk_dir", "deadline", "log"),
        },
        jp.sample_pixels: {"theta_std", "normals", "options", "gibbs", "seed", "timing", "devices"},
        jp.sample_emcee: {"args", "options", "natural", "labels", "theta_std", "progress"},
        jm.fit_brdf: {"models", "options", "config", "timing", "progress", "starts"},
        jm.fit_model: {"name", "options", "config", "weight", "timing", "starts", "nested"},
        jm.sample_posterior: {"sampler", "options", "progress", "starts"},
        jm.prune: {"options", "mask", "labels", "config", "cache"},
        fit.fit_pixels: {"config", "space", "init", "bounds", "fixed", "devices", "prior"},
        fit.fit_samples: {"options", "config", "space", "init", "bounds", "fixed"},
        # laplace: the residual whose curvature is wanted is the problem (data); noise and
        #   thresholds are LaplaceOptions
        fit.laplace: {"residual", "options", "devices"},
        ps.run_ps: {"method", "calibrate_lights", "reference", "downsample"},
        ps.fit_normal_brdf: {"intensities", "weight", "saturated", "options"},
        ps.robust: {"intensities", "weight", "options"},
    }
    for f, names in allowed.items():
        params = inspect.signature(f).parameters.values()
        given = {p.name for p in params if p.default is not inspect.Parameter.empty}
        assert given == names, f"{f.__qualname__}: {sorted(given ^ names)}"


def test_the_laplace_settings_are_an_option_object_that_reaches_the_result():
    """The noise scale and the thresholds of ``NOT_IDENTIFIED`` are fields of
    :class:`jaxrefl.fit.LaplaceOptions`: recorded, checked when built, and followed."""
    from jaxrefl import brdf, fit

    rec = fit.LaplaceOptions().to_json()
    assert rec == {
        "type": "laplace",
        "noise": "estimate",
        "max_theta_std": 1.0,
        "cond_max": None,
        "unroll_max": 8,
    }
    for bad, name in (
        ({"noise": "guess"}, "noise"),
        ({"max_theta_std": 0.0}, "max_theta_std"),
        ({"cond_max": -1.0}, "cond_max"),
        ({"unroll_max": -1}, "unroll_max"),
    ):
        with pytest.raises(ValueError, match=f"LaplaceOptions needs .*{name}"):
            fit.LaplaceOptions(**bad)

    k = 6
    ang = np.linspace(0.1, 0.9, k)
    wi = np.stack([np.sin(ang), np.zeros(k), np.cos(ang)], -1)
    wo = np.stack([-0.5 * np.sin(ang), np.zeros(k), np.sqrt(1 - 0.25 * np.sin(ang) ** 2)], -1)
    obs = np.random.default_rng(0).uniform(0.1, 0.5, (4, k, 3)).astype(np.float32)
    data = fit.pixel_data(obs, wi, wo)
    r = fit.fit_pixels(brdf.get("lambert"), data)
    with pytest.raises(ValueError, match=r"options=LaplaceOptions"):
        fit.laplace(r, data, options={"noise": "known"})
    est = fit.laplace(r, data)
    known = fit.laplace(r, data, options=fit.LaplaceOptions(noise="known"))
    assert np.all(np.asarray(known.noise_var) == 1.0)
    assert not np.allclose(np.asarray(est.noise_var), 1.0)
    loose = fit.laplace(r, data, options=fit.LaplaceOptions(max_theta_std=1e9))
    strict = fit.laplace(r, data, options=fit.LaplaceOptions(max_theta_std=1e-9))
    assert np.all(np.asarray(loose.identified)) and not np.any(np.asarray(strict.identified))
    assert np.all(np.asarray(strict.flag) & fit.LaplaceFlag.NOT_IDENTIFIED)
    singular = fit.laplace(r, data, options=fit.LaplaceOptions(cond_max=1.0 + 1e-6))
    assert np.all(np.isnan(np.asarray(singular.std)))
    assert np.all(np.asarray(singular.flag) & fit.LaplaceFlag.SINGULAR)

"""The capture's noise-level function: :class:`jaxrefl.fit.LevelNoise` and its estimate
(:func:`jaxrefl.svbrdf.estimate_noise_level`)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import fit, svbrdf
from jaxrefl._errors import JaxreflError
from jaxrefl.demo import demo_scene, photograph_maps
from jaxrefl.svbrdf._noise_level import MAX_LEVERAGE, fit_noise_level
from jaxrefl.svbrdf._uncertainty import laplace_interval, map_posterior

SIZE = 16
REL = 0.03  # relative noise of the heteroscedastic capture
FLOOR = 0.05  # its floor, in the capture's radiance units (std REL * (y + FLOOR))


def test_level_noise_std_scale_and_checks():
    obs = jnp.asarray([[-0.5, 0.0, 0.25], [1.0, 2.0, 4.0]])
    noise = fit.LevelNoise(gain=2.0, rel=3.0)
    y = np.maximum(np.asarray(obs), 0.0)
    np.testing.assert_allclose(noise.std(obs), np.sqrt(1.0 + 2.0 * y + 9.0 * y * y), rtol=1e-6)
    assert noise.scale_unknown and not fit.ShotNoise().scale_unknown
    assert fit.GaussianNoise(None).scale_unknown and not fit.GaussianNoise(0.1).scale_unknown
    known = noise.with_scale(0.5)
    assert not known.scale_unknown
    np.testing.assert_allclose(known.std(obs), 0.5 * np.asarray(noise.std(obs)), rtol=1e-6)
    # gain = rel = 0 is the flat model of unknown scale
    np.testing.assert_allclose(fit.LevelNoise().std(obs), fit.GaussianNoise(None).std(obs))
    with pytest.raises(JaxreflError, match="gain"):
        fit.LevelNoise(gain=-1.0)
    with pytest.raises(JaxreflError, match="scale"):
        fit.LevelNoise(scale=0.0)
    with pytest.raises(JaxreflError, match="known scale"):
        known.with_scale(2.0)
    assert noise.to_json() == {"type": "level", "gain": 2.0, "rel": 3.0, "scale": None}


def test_the_shape_is_recovered_from_residuals_and_a_flat_noise_gains_nothing():
    """Squared residuals drawn with sd = s_i sqrt(1 + gain y + (rel y)^2), each pixel its own
    s_i: the profile likelihood finds the shape; with flat noise it finds no gain worth a
    parameter."""
    rng = np.random.default_rng(3)
    n, m = 3000, 27
    y = rng.exponential(0.3, (n, m))
    s = rng.uniform(0.5, 2.0, (n, 1))
    use = np.ones((n, m), bool)
    g2 = 1.0 + 10.0 * y + (5.0 * y) ** 2
    z2 = (s * s * g2) * rng.standard_normal((n, m)) ** 2
    gain, rel, gain_ll = fit_noise_level(z2, y, use)
    assert gain_ll > 100
    # the shape's std at the bright end within 15% (gain and rel trade off at low y)
    g2_hat = 1.0 + gain * 2.0 + (rel * 2.0) ** 2
    assert abs(np.sqrt(g2_hat / (1.0 + 20.0 + 100.0)) - 1.0) < 0.15, (gain, rel)
    flat = (s * s) * rng.standard_normal((n, m)) ** 2
    _g, _r, flat_ll = fit_noise_level(flat, y, use)
    assert flat_ll < np.log(use.sum())


@pytest.fixture(scope="module")
def captures():
    """A co-located capture of coloured lobes photographed with noise that grows with the
    signal (std REL (y + FLOOR)) and the same with flat noise (std REL FLOOR): (hetero,
    flat, truth)."""
    scene = demo_scene(size=SIZE)
    rng = np.random.default_rng(11)
    truth = {
        "albedo": rng.uniform(0.05, 0.6, (SIZE, SIZE, 3)),
        "specular": rng.uniform(0.1, 0.9, (SIZE, SIZE, 3)),
        "alpha": rng.uniform(0.25, 0.6, (SIZE, SIZE)) ** 2,
    }
    clean = photograph_maps(scene, truth)
    y = np.asarray(clean.images, np.float64)
    scale = float(np.quantile(y, 0.99))
    floor = FLOOR * scale
    noisy = y + REL * (y + floor) * rng.standard_normal(y.shape)
    flat = y + REL * floor * rng.standard_normal(y.shape)
    het = dataclasses.replace(clean, images=noisy.astype(np.float32))
    hom = dataclasses.replace(clean, images=flat.astype(np.float32))
    return het, hom, truth


JOB = svbrdf.FitJob(model="ggx_rgb", light="fixed", config=fit.FitConfig(dtype=np.float64))


@pytest.fixture(scope="module")
def het_level(captures):
    """The noise-level estimate of the heteroscedastic capture under JOB (one estimate for
    the tests that read it)."""
    return svbrdf.estimate_noise_level(captures[0], JOB)


def test_a_capture_whose_noise_grows_with_the_signal_keeps_a_level_function(captures, het_level):
    _het, hom, _truth = captures
    level = het_level
    assert level.kept and isinstance(level.noise, fit.LevelNoise), level.why
    assert "grow with the signal" in level.why and level.loglik_gain > level.penalty
    assert level.n_pixels == SIZE * SIZE
    flat = svbrdf.estimate_noise_level(hom, JOB)
    assert not flat.kept and flat.noise == JOB.config.noise, flat.why
    assert "flat noise model" in flat.why


def test_the_leverage_correction_is_what_sees_the_bright_noise(captures, het_level, monkeypatch):
    """Without it (every leverage taken as 0) the highlights' short residuals hide the
    growth: the estimated bright-end std falls well below the corrected estimate's."""
    het, _hom, _truth = captures
    with_lev = het_level
    import jaxrefl.svbrdf._noise_level as nl

    real = nl._corrected

    def no_leverage(residual, theta, data):
        z2, lev, y, use = real(residual, theta, data)
        return z2 * (1.0 - jnp.minimum(lev, MAX_LEVERAGE)), jnp.zeros_like(lev), y, use

    monkeypatch.setattr(nl, "_corrected", no_leverage)
    without = svbrdf.estimate_noise_level(het, JOB)
    y = float(np.quantile(np.asarray(het.images), 0.99))

    def bright(lv):
        return np.sqrt(1.0 + lv.gain * y + (lv.rel * y) ** 2)

    assert bright(without) < 0.85 * bright(with_lev), (without.as_dict(), with_lev.as_dict())


def test_the_level_function_calibrates_the_laplace_intervals_and_the_map_samples_it(captures):
    """90% Laplace intervals of F0 and alpha on the heteroscedastic capture: with the
    estimated noise-level function they cover the truth near the nominal rate (0.82: 3.5
    binomial standard errors below 90% on 256 pixels), with the flat noise model clearly
    less (about 75% here); the map's posterior samples the same noise model."""
    het, _hom, truth = captures
    cover = {}
    for name, job in (("level", JOB), ("flat", dataclasses.replace(JOB, noise_level="flat"))):
        cf = svbrdf.fit_capture(het, job)
        iv = laplace_interval(cf, 0.9)
        got = []
        for lab, true in (("specular.R", truth["specular"][..., 0]), ("alpha", truth["alpha"])):
            lo, hi = iv[lab]
            t = true.reshape(-1)
            got.append(float(np.mean((lo <= t) & (t <= hi))))
        cover[name] = got
        if name == "level":
            assert cf.report["noise_level"]["kept"]
            assert cf.report["job"]["config"]["noise"]["type"] == "level"
            lp, _ = map_posterior(cf)
            assert isinstance(lp.residual.noise, fit.LevelNoise) and lp.noise_scale is not None
        else:
            assert not cf.report["noise_level"]["kept"]
            assert "noise_level='flat'" in cf.report["noise_level"]["why"]
    assert min(cover["level"]) >= 0.82, cover
    assert max(cover["flat"]) < min(cover["level"]) - 0.05, cover


def test_jobs_that_keep_their_noise_model_and_a_bad_setting():
    scene = demo_scene(size=4)
    cap = photograph_maps(
        scene,
        {
            "albedo": np.full((4, 4, 3), 0.3),
            "specular": np.full((4, 4, 3), 0.04),
            "alpha": np.full((4, 4), 0.1),
        },
    )
    given = dataclasses.replace(JOB, config=JOB.config.replace(noise=fit.ShotNoise(0.01, 0.01)))
    assert "gives its noise model (shot)" in svbrdf.estimate_noise_level(cap, given).why
    pooled = dataclasses.replace(JOB, model="pooled")
    assert "pooled" in svbrdf.estimate_noise_level(cap, pooled).why
    with pytest.raises(JaxreflError, match="noise_level"):
        svbrdf.FitJob(noise_level="shaped")


def test_the_command_line_sets_the_noise_level_and_fit_prints_it():
    from jaxrefl.cli import _fit as fit_cmd
    from jaxrefl.cli import _sample as sample_cmd
    from jaxrefl.cli._main import build_parser

    for command, job_of in (("fit", fit_cmd.fit_job), ("sample", sample_cmd._job)):
        base = [command, "capture", "--out", "out"]
        assert job_of(build_parser().parse_args(base)).noise_level == svbrdf.FitJob().noise_level
        flat = job_of(build_parser().parse_args([*base, "--noise-level", "flat"]))
        assert flat.noise_level == "flat"
    kept = {"kept": True, "gain": 7.9, "rel": 4.0, "why": "the residuals grow"}
    assert "sqrt(1 + 7.9 y + (4 y)^2)" in fit_cmd.noise_level_line(kept)
    assert fit_cmd.noise_level_line({"kept": False, "why": "flat: x"}) == "noise: flat: x"

"""The main job: capture -> tiled fit -> Laplace maps -> files; recovery, calibration of the
Laplace standard deviations, held-out error on the real capture, bad input, resume."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import brdf, fit, svbrdf
from jaxrefl.cli import main
from jaxrefl.demo import demo_capture, demo_scene, render_demo
from jaxrefl.io import load_capture, read_exr
from jaxrefl.io._capture import ObsStatus
from jaxrefl.scene import render

BATH = "svbrdf_flash/bath_tile"
GGX = dict(distribution="ggx", shadowing="smith_height_correlated", fresnel="schlick")


def _demo_capture(size=16, seed=0, noise=0.0):
    """The demo scene as an in-memory float capture (no 8-bit quantisation)."""
    scene = demo_scene(size=size, seed=seed, dtype=jnp.float64)
    lin = np.asarray(render_demo(scene, encode=False), np.float64)
    if noise:
        lin = lin + noise * np.random.default_rng(seed).standard_normal(lin.shape)
    cap = demo_capture(scene, lin)
    return cap, scene


# ----------------------------------------------------------------------------- recovery
# The synthetic-pixel fits: one configuration (1500 pixels of 32 observations, known noise
# scale 0.01, 80 iterations), shared by the noise-free recovery test and the Laplace
# calibration tests, so that they run one compiled solver. On noise-free pixels the noise
# scale only rescales the residuals (the LM's tolerances and damping are relative).
_SIGMA = 0.01
_N_PIXELS = 1500


def _fit_synthetic(model, space, data):
    config = fit.FitConfig(solver=fit.LMOptions(max_iters=80), noise=fit.GaussianNoise(_SIGMA))
    return fit.fit_pixels(model, data, config=config, space=space)


def test_noise_free_pixels_recover_parameters_to_1e4():
    model, space, data, truth = _synthetic_pixels(_N_PIXELS, 32, 0.0, seed=2, dtype=jnp.float64)
    r = _fit_synthetic(model, space, data)
    assert (np.asarray(r.status) < fit.Status.MASKED).all()
    for name, v in truth.items():
        e = np.abs(np.asarray(r.params[name]).reshape(v.shape) / v - 1)
        assert np.quantile(e, 0.99) < 1e-4, (name, np.quantile(e, [0.5, 0.99]))


# The float64 capture jobs (noise-free demo pixels): one flat GGX configuration, shared by
# test_noise_free_capture_recovers_the_maps and both fits of the tilted-normals test (the
# first stage of ggx_normal and the flat comparison), so they run one compiled tile program.
# A known noise scale of 1e-6 only rescales the residuals of a noise-free fit (the LM's
# tolerances and damping are relative); the tilted test needs it for its prior.
_F64_JOB = dict(
    model="ggx",
    tile_pixels=64,
    alpha_min=1e-3,
    config=fit.FitConfig(
        solver=fit.LMOptions(max_iters=60), noise=fit.GaussianNoise(sigma=1e-6), dtype=np.float64
    ),
)


def test_noise_free_capture_recovers_the_maps():
    """Through the capture path (images stored as float32, so 1e-3 rather than 1e-4), on the
    8 x 8 demo: one tile of the job's 64 pixels."""
    cap, scene = _demo_capture(size=8)
    job = svbrdf.FitJob(**_F64_JOB)
    r = svbrdf.fit_capture(cap, job)
    p = r.params()
    assert (r.maps["status"] < fit.Status.MASKED).all()
    for name in ("albedo", "specular", "alpha"):
        e = np.abs(p[name] / np.asarray(scene.params[name]) - 1)
        assert np.median(e) < 1e-5 and np.quantile(e, 0.99) < 1e-3, (
            name,
            np.quantile(e, [0.5, 0.99]),
        )
    assert r.report["train_rmse"] < 1e-5


def test_normal_tilt_model_identities():
    """NormalTilt: the base model at tilt 0; otherwise the base in the rotated frame times
    cos_n / cos_z; finite values and gradients at the tilt bounds and grazing directions."""
    base = brdf.get("cook_torrance", diffuse="lambert", **GGX)
    m = brdf.NormalTilt(base)
    p = {"albedo": jnp.array([0.5, 0.4, 0.3]), "specular": jnp.array([0.04]), "alpha": 0.1}
    rng = np.random.default_rng(3)
    wi = rng.normal(size=(64, 3)) * [1, 1, 0] + [0, 0, 1.0]
    wo = rng.normal(size=(64, 3)) * [1, 1, 0] + [0, 0, 1.0]
    wi, wo = (jnp.asarray(w / np.linalg.norm(w, axis=-1, keepdims=True)) for w in (wi, wo))
    ev = jax.jit(lambda q, a, b: m.eval(q, a, b))  # one compile, not op-by-op dispatch
    flat = ev({**p, "tilt_x": 0.0, "tilt_y": 0.0}, wi, wo)
    np.testing.assert_allclose(flat, jax.jit(base.eval)(p, wi, wo), rtol=1e-12, atol=0)
    tx, ty = 0.3, -0.2
    t, b, n = brdf.tilt_frame(jnp.asarray(tx), jnp.asarray(ty))
    rot = np.stack([t, b, n])
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    assert abs(float(n[0] / n[2]) - tx) < 1e-12 and abs(float(n[1] / n[2]) - ty) < 1e-12
    got = ev({**p, "tilt_x": tx, "tilt_y": ty}, wi, wo)
    want = jax.jit(base.eval)(p, wi @ rot.T, wo @ rot.T) * np.asarray((wi @ n) / wi[:, 2])[:, None]
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-14)
    assert not m.reciprocal and m.param_names[-2:] == ("tilt_x", "tilt_y")
    # Edges: tilt at its bounds, a direction at the geometric horizon, in float32.
    graze = jnp.asarray([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8]], jnp.float32)

    def total(tilts):
        q = {k: jnp.asarray(v, jnp.float32) for k, v in p.items()}
        return jnp.sum(m.eval({**q, "tilt_x": tilts[0], "tilt_y": tilts[1]}, graze, graze[::-1]))

    vg = jax.jit(jax.value_and_grad(total))
    for tilts in ([1.0, 1.0], [-1.0, 0.0], [0.0, 0.0]):
        v, g = vg(jnp.asarray(tilts, jnp.float32))
        assert np.isfinite(v) and np.all(np.isfinite(g)), (tilts, v, g)


def test_gaussian_prior_residual_is_the_map_estimate():
    """A prior appends (x - mean)/std: on a linear-Gaussian pixel (Lambert albedo, known
    sigma) the fit is the exact posterior mode and the Laplace std the posterior std."""
    model = brdf.get("lambert")
    space = fit.ParamSpace(model, channels=1, transforms={"albedo": fit.Identity()})
    rng = np.random.default_rng(0)
    k, sigma, m0, s0 = 6, 0.05, 0.3, 0.02
    wi = np.tile([0.0, 0.0, 1.0], (1, k, 1))
    obs = (0.5 / np.pi + sigma * rng.standard_normal((1, k, 1))).astype(np.float64)
    data = fit.pixel_data(obs, wi)
    prior = fit.gaussian_prior(space, {"albedo.c0": (m0, s0)})
    noise = fit.GaussianNoise(sigma=sigma)
    # Tolerances far below the defaults: this checks the MAP identity, not the stopping rule
    # (which stops a damped first step short by up to ~1e-4 posterior std).
    tight = fit.LMOptions(xtol=1e-13, ftol=1e-15)
    config = fit.FitConfig(solver=tight, noise=noise)
    r = fit.fit_pixels(model, data, config=config, space=space, prior=prior, init="defaults")
    # obs = a/pi + e: precision k/(pi sigma)^2 + 1/s0^2, mean weighted by the precisions.
    prec_d, prec_0 = k / (np.pi * sigma) ** 2, 1 / s0**2
    mode = (prec_d * np.pi * obs.mean() + prec_0 * m0) / (prec_d + prec_0)
    assert abs(float(r.params["albedo"][0, 0]) - mode) < 1e-10 * mode
    res = fit.make_residual(model, space, noise, prior=prior)
    lap = fit.laplace(r, data, residual=res, options=fit.LaplaceOptions(noise="known"))
    assert abs(float(lap.std[0, 0]) - (prec_d + prec_0) ** -0.5) < 1e-9
    with pytest.raises(KeyError, match="no free parameters"):
        fit.gaussian_prior(space, {"alpha": (0.1, 0.1)})
    with pytest.raises(ValueError, match="std"):
        fit.gaussian_prior(space, {"albedo.c0": (0.1, 0.0)})


def test_capture_with_tilted_normals_is_recovered_by_ggx_normal():
    """Noise-free demo pixels with shading normals tilted by up to 0.25 (14 degrees): the
    two-stage ``ggx_normal`` fit recovers the slopes and the flat model cannot explain them.
    A known noise scale of 1e-6 makes the slopes' prior (std 0.1) negligible against the data."""
    size = 8
    scene = demo_scene(size=size, seed=0, dtype=jnp.float64)
    rng = np.random.default_rng(1)
    tilt = rng.uniform(-0.25, 0.25, (2, size, size))
    model = brdf.NormalTilt(scene.model)
    params = {**scene.params, "tilt_x": jnp.asarray(tilt[0]), "tilt_y": jnp.asarray(tilt[1])}
    lin = np.asarray(
        render(model, params, scene.lights, scene.cameras, points=scene.points, cos4=False)
    )
    cap, _ = _demo_capture(size=size)
    cap = replace(cap, images=lin)
    job = svbrdf.FitJob(**{**_F64_JOB, "model": "ggx_normal"})
    r = svbrdf.fit_capture(cap, job)
    p = r.params()
    err = np.abs(np.stack([p["tilt_x"], p["tilt_y"]]) - tilt)
    assert np.median(err) < 1e-5 and np.mean(err < 1e-3) >= 0.85, np.quantile(err, [0.5, 0.85])
    e_alpha = np.abs(p["alpha"] / np.asarray(scene.params["alpha"]) - 1)
    assert np.median(e_alpha) < 1e-4
    n = np.stack([r.maps[f"normal.{a}"] for a in "XYZ"], -1)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, rtol=1e-6)
    assert {"tilt_x", "tilt_y_std", "corr_tilt_x_tilt_y"} <= set(r.maps)
    flat = svbrdf.fit_capture(cap, replace(job, model="ggx"))
    assert r.report["train_rmse"] < 0.5 * flat.report["train_rmse"]


def _tilted_capture(amplitude, size=8, noise=0.0, seed=1):
    """The demo scene with shading normals tilted by uniform slopes in +-amplitude, plus
    Gaussian noise of std ``noise`` (float64 photos)."""
    scene = demo_scene(size=size, seed=0, dtype=jnp.float64)
    rng = np.random.default_rng(seed)
    tilt = rng.uniform(-amplitude, amplitude, (2, size, size))
    params = {**scene.params, "tilt_x": jnp.asarray(tilt[0]), "tilt_y": jnp.asarray(tilt[1])}
    model = brdf.NormalTilt(scene.model)
    lin = np.asarray(
        render(model, params, scene.lights, scene.cameras, points=scene.points, cos4=False)
    )
    cap, _ = _demo_capture(size=size)
    return replace(cap, images=lin + noise * rng.standard_normal(lin.shape))


@pytest.mark.parametrize("amplitude", [0.0, 0.01])
def test_score_test_of_the_slopes_sees_a_tilt_and_nothing_else(amplitude):
    """The score test ``auto`` runs before fitting ``ggx_normal`` (svbrdf._score_test), on
    the 8 x 8 demo with noise of a known std 1e-6 (the float64 jobs' noise scale). On a flat
    surface T is a chi-square draw of mean E (within 4 null std); slopes of at most 0.01
    (0.6 degrees) put it far above. T / 2 is also checked against an independent algebra:
    the cost drop of one Gauss-Newton step in every parameter, less that of a step in the
    flat parameters alone (block inversion of J^T J)."""
    from jaxrefl.svbrdf._score_test import score_test
    from jaxrefl.svbrdf._tile_fitter import STAGE2_ITERS, TileFitter, extend_start

    cap = _tilted_capture(amplitude, noise=1e-6)
    flat = TileFitter(cap, svbrdf.FitJob(**_F64_JOB))
    data = flat.data(0, 64)
    train = np.ones((64, cap.n_photos), bool)
    _, _, r1, fit_data = flat.score(data, train)
    tilted = TileFitter(cap, svbrdf.FitJob(**{**_F64_JOB, "model": "ggx_normal"}))
    assert tilted.settings()["tilted_solver"]["max_iters"] == STAGE2_ITERS
    t, e, v = tilted.tilt_evidence(r1, fit_data)
    assert 120 < e <= 128  # about 2 a pixel: the prior is weak against noise of 1e-6
    if amplitude == 0.0:
        assert abs(t - e) < 4 * np.sqrt(v), (t, e, v)
    else:
        assert t > e + 50 * np.sqrt(v), (t, e, v)
    res = fit.make_residual(
        tilted.model, tilted.space, tilted.noise, tilted.loss, tilted._tilt_prior()
    )
    theta = jnp.asarray(extend_start(r1, tilted.space, np.float64, np.zeros(2)))
    extra = (tilted.space.index("tilt_x").start, tilted.space.index("tilt_y").start)
    ones = jnp.ones(64)
    t_px = np.asarray(score_test(res, theta, fit_data, extra, ones)[0])
    flat_idx = [i for i in range(theta.shape[1]) if i not in extra]
    for i in range(0, 64, 9):
        d = jax.tree.map(lambda a, i=i: a[i], fit_data)
        jac = np.asarray(jax.jacfwd(res)(theta[i], d))
        g = jac.T @ np.asarray(res(theta[i], d))
        h = jac.T @ jac
        full = g @ np.linalg.solve(h, g)
        part = g[flat_idx] @ np.linalg.solve(h[np.ix_(flat_idx, flat_idx)], g[flat_idx])
        assert t_px[i] == pytest.approx(full - part, rel=1e-6, abs=1e-9 * max(1.0, full))


def _synthetic_pixels(n, k, sigma, seed, dtype):
    """GGX + Lambert pixels (C = 1, free albedo, specular, alpha) under K spiral lights."""
    rng = np.random.default_rng(seed)
    model = brdf.get("cook_torrance", diffuse="lambert", **GGX)
    space = fit.ParamSpace(model, channels=1)
    t = (np.arange(k) + 0.5) / k
    theta_l = np.arccos(1 - 0.9 * t)  # up to ~84 degrees
    phi = 2.399963 * np.arange(k)  # golden-angle spiral
    wi = np.stack(
        [np.sin(theta_l) * np.cos(phi), np.sin(theta_l) * np.sin(phi), np.cos(theta_l)], -1
    )
    wo = np.array([0.0, 0.0, 1.0])
    truth = {
        "albedo": rng.uniform(0.1, 0.7, (n, 1)),
        "specular": rng.uniform(0.05, 0.3, (n, 1)),
        "alpha": np.exp(rng.uniform(np.log(0.08), np.log(0.5), n)),
    }
    wi_b = np.broadcast_to(wi, (n, k, 3))
    wo_b = np.broadcast_to(wo, (n, k, 3))
    p = {key: jnp.asarray(v[:, None], dtype) for key, v in truth.items()}
    scale = wi[:, 2:3]
    clean = np.asarray(model.eval(p, jnp.asarray(wi_b, dtype), jnp.asarray(wo_b, dtype))) * scale
    obs = clean + sigma * rng.standard_normal(clean.shape)
    data = fit.pixel_data(obs, wi_b, wo_b, scale=np.broadcast_to(scale, obs.shape), dtype=dtype)
    return model, space, data, truth


@pytest.fixture(scope="module")
def noisy_fit():
    """One fit of 1500 noisy pixels, shared by both noise settings of the Laplace step."""
    model, space, data, truth = _synthetic_pixels(_N_PIXELS, 32, _SIGMA, seed=3, dtype=jnp.float64)
    return model, space, data, truth, _fit_synthetic(model, space, data)


@pytest.mark.parametrize("noise", ["known", "estimate"])
def test_laplace_std_is_calibrated_on_noisy_pixels(noisy_fit, noise):
    model, space, data, truth, r = noisy_fit
    res = fit.make_residual(model, space, fit.GaussianNoise(_SIGMA))
    lap = fit.laplace(r, data, residual=res, options=fit.LaplaceOptions(noise=noise))
    true_theta = np.asarray(space.from_natural({k: v for k, v in truth.items()}))
    z = (np.asarray(r.theta) - true_theta) / np.asarray(lap.theta_std)
    use = np.asarray(lap.reliable)
    # With one view at the normal, broad lobes (alpha ~ 0.5) are nearly collinear with the
    # diffuse term: those pixels are NOT_IDENTIFIED (~18% here); the rest must be calibrated.
    assert use.mean() > 0.75
    for j, label in enumerate(space.labels):
        s = np.std(z[use, j])
        assert 0.8 <= s <= 1.25, (label, s)
    # Natural std = |d natural / d theta| * theta std (elementwise bijections).
    dnat = np.abs(np.asarray(space.dnatural(r.theta)))
    np.testing.assert_allclose(np.asarray(lap.std), dnat * np.asarray(lap.theta_std), rtol=1e-6)
    if noise == "estimate":
        # The residuals were whitened by the true sigma: the estimated scale factor is ~1.
        s_hat = np.sqrt(np.asarray(lap.noise_var))
        assert abs(np.median(s_hat) - 1) < 0.05


def test_laplace_flags_unidentified_roughness():
    """No highlight observed (all lights far from the mirror direction): roughness is not
    identified and the flag says so, while a pixel with a highlight is reliable."""
    model = brdf.get("cook_torrance", diffuse="lambert", **GGX)
    space = fit.ParamSpace(model, channels=1)
    k = 16
    ang = np.linspace(0.9, 1.3, k)  # 52-75 degrees from the normal, viewer at the normal
    wi_far = np.stack([np.sin(ang), np.zeros(k), np.cos(ang)], -1)
    ang2 = np.linspace(0.0, 1.2, k)
    wi_near = np.stack([np.sin(ang2), np.zeros(k), np.cos(ang2)], -1)
    wi = np.stack([wi_far, wi_near])
    wo = np.broadcast_to([0.0, 0.0, 1.0], wi.shape)
    p = {"albedo": jnp.array([[[0.4]], [[0.4]]]), "specular": jnp.array([[[0.1]], [[0.1]]])}
    p["alpha"] = jnp.array([[0.02], [0.02]])
    scale = wi[..., 2:3]
    obs = np.asarray(model.eval(p, jnp.asarray(wi), jnp.asarray(wo))) * scale
    rng = np.random.default_rng(0)
    obs = obs + 1e-3 * rng.standard_normal(obs.shape)
    data = fit.pixel_data(obs, wi, wo, scale=np.broadcast_to(scale, obs.shape))
    r = fit.fit_pixels(model, data, space=space)
    lap = fit.laplace(r, data)
    flag = np.asarray(lap.flag)
    assert flag[0] != 0 and flag[1] == 0, flag


def test_laplace_of_masked_pixels_is_nan_and_flagged():
    # Two pixels of 16 observations, the shapes of test_laplace_flags_unidentified_roughness
    # (same model, space and defaults): its compiled fit and Laplace step are reused.
    model, space, data, _ = _synthetic_pixels(2, 16, 0.01, seed=1, dtype=jnp.float64)
    w = np.asarray(data.weight).copy()
    w[0] = 0.0
    data = replace_weight(data, w)
    r = fit.fit_pixels(model, data, space=space)
    lap = fit.laplace(r, data)
    assert np.all(np.isnan(np.asarray(lap.std)[0]))
    assert int(lap.flag[0]) & fit.LaplaceFlag.NO_ESTIMATE
    assert np.all(np.isfinite(np.asarray(lap.std)[1:]))


def test_laplace_reuses_the_fits_curvature_with_censored_and_masked_pixels():
    """The Laplace step takes J^T J and the active row count from the fit's last
    linearisation; it equals a fresh linearisation at theta, including a pixel with
    satisfied censored observations (not counted in n) and a masked one. (The shapes of
    test_laplace_of_masked_pixels_is_nan_and_flagged: one compiled fit.)"""
    model, space, data, _ = _synthetic_pixels(2, 16, 0.01, seed=2, dtype=jnp.float64)
    obs = np.asarray(data.obs).copy()
    cens = np.zeros(obs.shape, np.int8)
    top = np.argsort(obs[0, :, 0])[-3:]  # pixel 0: its three brightest saturate at 90%
    sat = 0.9 * obs[0, top, 0].min()
    obs[0, top, 0], cens[0, top, 0] = sat, 1
    data = fit.pixel_data(obs, data.wi, data.wo, scale=data.scale, censored=cens)
    w = np.asarray(data.weight).copy()
    w[1] = 0.0  # pixel 1: masked
    data = replace_weight(data, w)
    r = fit.fit_pixels(model, data, space=space)
    assert r.linearisation is not None
    act = np.asarray(r.linearisation.active)
    # The saturated observations end satisfied (the fit predicts above 90% of them).
    assert act[1] == 0 and act[0] == 13, act
    reused = fit.laplace(r, data)
    fresh = fit.laplace(replace(r, linearisation=None), data)  # linearised here
    for name in ("std", "corr", "theta_std", "noise_var"):
        a, b = np.asarray(getattr(reused, name)), np.asarray(getattr(fresh, name))
        np.testing.assert_allclose(a, b, rtol=1e-7, atol=0, equal_nan=True, err_msg=name)
    np.testing.assert_array_equal(np.asarray(reused.flag), np.asarray(fresh.flag))
    assert int(reused.flag[1]) & fit.LaplaceFlag.NO_ESTIMATE
    # Another residual is not the fit's: it is linearised afresh (noise scale 0.5 halves
    # the whitened residual, so J^T J is 4x larger and the known-noise std half).
    half = fit.make_residual(model, space, fit.GaussianNoise(0.5))
    known = fit.LaplaceOptions(noise="known")
    a = np.asarray(fit.laplace(r, data, residual=half, options=known).std)
    b = np.asarray(fit.laplace(r, data, options=known).std)
    np.testing.assert_allclose(a[0], 0.5 * b[0], rtol=1e-6)


def test_laplace_of_a_numerically_singular_jtj_does_not_follow_a_rounding_pivot():
    """Two J^T J equal but for one unit in the last place: singular, so the last Cholesky
    pivot is 0 in one and 2^-52 in the other. Neither is inverted; both get the same flag and
    NaN stds (a layout that rounds differently gets the same answer; see ``_laplace``).
    (The shapes of test_laplace_of_masked_pixels_is_nan_and_flagged: one compiled fit.)"""
    model, space, data, _ = _synthetic_pixels(2, 16, 0.01, seed=1, dtype=jnp.float64)
    r = fit.fit_pixels(model, data, space=space)
    singular = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0], [0.0, 1.0, 1.0]])
    jtj = np.stack([singular, singular])
    jtj[1, 2, 2] += 2.0**-52  # a positive last pivot: the factorisation would succeed
    lin = replace(r.linearisation, jtj=jnp.asarray(jtj))
    lap = fit.laplace(replace(r, linearisation=lin), data)
    flag = np.asarray(lap.flag) & ~fit.LaplaceFlag.AT_BOUND
    assert flag.tolist() == [fit.LaplaceFlag.NOT_IDENTIFIED | fit.LaplaceFlag.SINGULAR] * 2, flag
    assert np.all(np.isnan(np.asarray(lap.std))) and np.all(np.isnan(np.asarray(lap.corr)))
    assert not np.any(np.asarray(lap.identified))


def replace_weight(data, w):
    import equinox as eqx

    return eqx.tree_at(lambda d: d.weight, data, jnp.asarray(w, data.weight.dtype))


def test_grey_parameter_space_shares_one_value():
    model = brdf.get("cook_torrance", diffuse="lambert", **GGX)
    space = fit.ParamSpace(model, channels=3, grey=("specular",))
    assert space.labels == ("albedo.R", "albedo.G", "albedo.B", "specular", "alpha")
    theta = space.from_natural(
        {"albedo": jnp.array([0.2, 0.3, 0.4]), "specular": 0.05, "alpha": 0.1}
    )
    nat = space.to_natural(theta)
    np.testing.assert_allclose(nat["specular"], [0.05] * 3, rtol=1e-6)
    with pytest.raises(KeyError, match="colour parameter"):
        fit.ParamSpace(model, grey=("alpha",))


# ----------------------------------------------------------------------------- the job
# Every float32 job test on the 8 x 8 demo uses this tile size: one compiled tile program.
_TILE = 16


def test_capture_job_status_censoring_and_bad_pixels():
    cap, _ = _demo_capture(size=8, noise=1e-3)
    st = cap.status.copy()
    img = cap.images.copy()
    st[:, 0, 0] = ObsStatus.NONFINITE  # a pixel with no usable observation at all
    img[:, 0, 0] = 0.0
    st[:4, 0, 1] = ObsStatus.NEGATIVE  # some bad observations: fitted from the rest
    st[:, 0, 2] = ObsStatus.SATURATED  # all saturated: censored only
    cap = replace(cap, images=img, status=st, saturation_level=0.5)
    r = svbrdf.fit_capture(cap, svbrdf.FitJob(model="ggx", tile_pixels=_TILE))
    s = r.maps["status"]
    assert s[0, 0] == fit.Status.MASKED
    assert np.isnan(r.maps["alpha"][0, 0]) and r.maps["laplace_flag"][0, 0] & 1
    assert s[0, 1] < fit.Status.MASKED and np.isfinite(r.maps["alpha"][0, 1])
    assert r.maps["n_used"][0, 1] == (9 - 4) * 3
    # All-censored pixel: a prediction at or above the bound everywhere, never a crash.
    p = r.params()
    assert np.all(np.isfinite(p["albedo"][0, 2]))
    assert sum(r.report["status_counts"].values()) == 64


def test_holdout_and_bad_job_arguments():
    cap, _ = _demo_capture(size=8, noise=1e-3)
    r = svbrdf.fit_capture(cap, svbrdf.FitJob(model="ggx", holdout=(2,), tile_pixels=_TILE))
    assert r.report["holdout"] == [2]
    assert r.report["heldout_rmse"] < 5e-3
    assert set(r.report["heldout_rmse_per_photo"]) == {"2"}
    med, p99 = r.report["heldout_pixel_rmse_median"], r.report["heldout_pixel_rmse_p99"]
    # Noise 1e-3 per observation: a pixel's RMSE over 3 channels is about that.
    assert 3e-4 < med <= p99 < 5e-3
    with pytest.raises(ValueError, match="tilt_std"):
        svbrdf.FitJob(model="ggx_normal", tilt_std=0.0)
    with pytest.raises(ValueError, match="out of range"):
        svbrdf.fit_capture(cap, svbrdf.FitJob(holdout=(9,)))
    with pytest.raises(ValueError, match="unknown capture model"):
        svbrdf.FitJob(model="nope")
    with pytest.raises(ValueError, match="every photo is held out"):
        svbrdf.fit_capture(cap, svbrdf.FitJob(holdout=tuple(range(9))))


class _Interrupt(Exception):
    pass


def test_interrupted_run_resumes_without_recomputing(tmp_path):
    cap, _ = _demo_capture(size=8, noise=1e-3)
    job = svbrdf.FitJob(model="ggx", tile_pixels=_TILE)  # 4 tiles
    full = svbrdf.fit_capture(cap, job)

    def stop_after_two(i, n):
        if i == 1:
            raise _Interrupt

    with pytest.raises(_Interrupt):
        svbrdf.fit_capture(cap, job, tmp_path, on_tile=stop_after_two)
    assert len(list((tmp_path / "tiles").glob("tile_*.npz"))) == 2
    seen = []
    resumed = svbrdf.fit_capture(cap, job, tmp_path, on_tile=lambda i, n: seen.append(i))
    assert resumed.tiles_loaded == 2 and resumed.tiles_computed == 2 and seen == [2, 3]
    for name in ("alpha", "albedo.G", "alpha_std", "status"):
        np.testing.assert_array_equal(resumed.maps[name], full.maps[name])
    # A corrupt tile is recomputed; another job in the same folder is refused.
    (tmp_path / "tiles" / "tile_00001.npz").write_bytes(b"truncated")
    again = svbrdf.fit_capture(cap, job, tmp_path)
    assert again.tiles_computed == 1
    # A tile file of another size (a copy of another tile's arrays, cut) is recomputed too.
    with np.load(tmp_path / "tiles" / "tile_00002.npz") as z:
        cut = {k: z[k][:3] for k in z.files}
    np.savez(tmp_path / "tiles" / "tile_00002.npz", **cut)
    again = svbrdf.fit_capture(cap, job, tmp_path)
    assert again.tiles_computed == 1
    np.testing.assert_array_equal(again.maps["alpha"], full.maps["alpha"])
    with pytest.raises(ValueError, match="different job"):
        svbrdf.fit_capture(cap, svbrdf.FitJob(tile_pixels=_TILE, model="lambert"), tmp_path)
    # So is the same model with another noise model, solver or loss: the manifest records
    # each option object (its type and every field), so a changed field counts as well.
    shot = fit.ShotNoise(read=0.002, gain=0.002)
    changes = (
        {"noise": shot},
        {"noise": fit.GaussianNoise(sigma=0.01)},
        {"loss": fit.Huber()},
        {"solver": fit.LMOptions(max_iters=41)},
    )
    for change in changes:
        other = replace(job, config=job.config.replace(**change))
        with pytest.raises(ValueError, match="different job"):
            svbrdf.fit_capture(cap, other, tmp_path)
    manifest = json.loads((tmp_path / "tiles" / "manifest.json").read_text())
    assert manifest["job"]["config"]["noise"] == {"type": "gaussian", "sigma": None}
    assert manifest["job"]["config"]["loss"] == {"type": "l2"}
    assert manifest["job"]["config"]["dtype"] == "float32"
    # Beside the job, the settings that ran: this small job's lean LM is one plain loop.
    assert manifest["job"]["config"]["solver"]["compact_stages"]
    assert manifest["ran"]["config"]["solver"]["compact_stages"] == []
    # The job's compaction left to the size rule is recorded as decided (none, for this
    # size): the same value resumes, the other one is another job.
    assert manifest["job"]["compact"] is False and manifest["ran"]["compact"] is False
    same = svbrdf.fit_capture(cap, replace(job, compact=False), tmp_path)
    assert same.tiles_loaded == 4 and same.tiles_computed == 0 and same.job.compact is False
    with pytest.raises(ValueError, match="different job"):
        svbrdf.fit_capture(cap, replace(job, compact=True), tmp_path)
    # So are the model choice's settings (FitJob.auto), which the job records whatever its
    # model: pooled's width where it wins is the selection's.
    assert manifest["job"]["auto"] == svbrdf.AutoOptions().to_json()
    with pytest.raises(ValueError, match="different job"):
        svbrdf.fit_capture(cap, replace(job, auto=svbrdf.AutoOptions(seed=1)), tmp_path)
    # A job with shot noise resumes its own tiles, and refuses the same job with another gain.
    shot_dir = tmp_path / "shot"
    shot_job = replace(job, config=job.config.replace(noise=shot))
    with pytest.raises(_Interrupt):
        svbrdf.fit_capture(cap, shot_job, shot_dir, on_tile=stop_after_two)
    resumed = svbrdf.fit_capture(cap, shot_job, shot_dir)
    assert resumed.tiles_loaded == 2 and resumed.tiles_computed == 2
    assert resumed.report["job"]["config"]["noise"] == {
        "type": "shot",
        "read": 0.002,
        "gain": 0.002,
    }
    brighter = replace(job, config=job.config.replace(noise=replace(shot, gain=0.004)))
    with pytest.raises(ValueError, match="different job"):
        svbrdf.fit_capture(cap, brighter, shot_dir)
    # A corrupt manifest is named as such, with the way out.
    (tmp_path / "tiles" / "manifest.json").write_text('{"job": ')
    with pytest.raises(ValueError, match=r"manifest\.json: unreadable resume manifest.*--restart"):
        svbrdf.fit_capture(cap, job, tmp_path)
    assert svbrdf.fit_capture(cap, replace(job, model="lambert"), tmp_path, restart=True)


def test_outputs_exr_report_previews(tmp_path):
    cap, _ = _demo_capture(size=8, noise=1e-3)
    r = svbrdf.fit_capture(cap, svbrdf.FitJob(model="ggx", holdout=(0,), tile_pixels=_TILE))
    files = svbrdf.write_outputs(r, cap, tmp_path)
    exr = read_exr(tmp_path / "maps.exr")
    for name in (
        "albedo.R",
        "specular.Y",
        "roughness.Y",
        "roughness_std.Y",
        "status.Y",
        "laplace_flag.Y",
    ):
        assert name in exr.channels, name
    assert exr.metadata["model"] == "ggx"
    np.testing.assert_array_equal(exr.channels["status.Y"], r.maps["status"])
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["heldout_rmse"] == pytest.approx(r.report["heldout_rmse"])
    assert report["timings"]["compile_s"] >= 0 and report["timings"]["run_s"] > 0
    for p in files["previews"]:
        assert Path(p).stat().st_size > 1000
    # every layer of a real fit's maps.exr splits into an RGB or a Y image in Mitsuba 3
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    layers = dict(mi.Bitmap(str(tmp_path / "maps.exr")).split())
    formats = {lay.pixel_format() for lay in layers.values()}
    assert formats == {mi.Bitmap.PixelFormat.RGB, mi.Bitmap.PixelFormat.Y}, formats
    assert {"albedo", "albedo_std", "corr_albedo_R_alpha", "status", "roughness"} <= set(layers)
    assert main(["export", str(tmp_path), "--format", "mitsuba"]) == 0
    mi.load_file(str(tmp_path / "export_mitsuba" / "scene.xml"))


def test_resolvable_alpha_from_photo_spacing(shared_data):
    bath = load_capture(shared_data / BATH, max_photos=9)
    a = svbrdf.resolvable_alpha(bath)
    assert 0.03 < a < 0.07  # half of a ~5.5 degree spacing of the half vectors
    assert svbrdf.resolvable_alpha(bath.select([0])) == 1e-3


def test_sharded_fit_equals_one_device():
    """Two forced host devices (a fresh process: the flag must precede JAX's start)."""
    code = """
import numpy as np, jax
jax.config.update("jax_enable_x64", True)
from jaxrefl import fit, brdf
import tests.test_svbrdf as t
assert jax.device_count() == 2
# float64: in float32 the rounding of a differently laid-out batch moves poorly determined
# parameters along flat valleys (seen: 0.02 in theta on 9% of pixels, equal costs).
model, _, data, _ = t._synthetic_pixels(65, 16, 0.01, seed=5, dtype=np.float64)
# A small model keeps the two compilations short; the solver path is the same for all.
model = brdf.get("blinn_phong")
space = fit.ParamSpace(model, channels=1)
a = fit.fit_pixels(model, data, space=space)
# Under shard_map the LM runs as one compiled program: the one-device fit runs the same
# (test_fit_lm compares it with the host-driven steps).
one = fit.FitConfig(solver=fit.LMOptions(host_loop=False))
b = fit.fit_pixels(model, data, space=space, devices=1, config=one)
np.testing.assert_array_equal(np.asarray(a.status), np.asarray(b.status))
# Rounding of a differently laid-out batch moves a flat valley's point a little even in
# float64 (seen: one value of 195, 3e-6 relative, with tight tolerances too); costs agree.
np.testing.assert_allclose(np.asarray(a.theta), np.asarray(b.theta), rtol=1e-5, atol=1e-8)
np.testing.assert_allclose(np.asarray(a.cost), np.asarray(b.cost), rtol=1e-10)
la, lb = fit.laplace(a, data), fit.laplace(b, data, devices=1)
np.testing.assert_array_equal(np.asarray(la.flag), np.asarray(lb.flag))
np.testing.assert_allclose(np.asarray(la.std), np.asarray(lb.std), rtol=1e-5)
print("ok")
"""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=root, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr[-3000:]


# ----------------------------------------------------------------------------- the CLI
def test_bath_tile_beats_lambert_on_a_held_out_photo(shared_data, tmp_path):
    """The real capture end to end through the CLI (downsampled 8x: 128 x 128)."""
    rmse = {}
    for model in ("ggx", "lambert"):
        out = tmp_path / model
        args = ["fit", str(shared_data / BATH), "--out", str(out), "--model", model]
        args += ["--holdout", "4", "--downsample", "8", "--quiet", "--no-previews"]
        # the models compared under one light, as the capture states it (tests/test_light.py
        # covers estimating it)
        args += ["--light", "fixed"]
        assert main(args) == 0
        report = json.loads((out / "report.json").read_text())
        rmse[model] = report["heldout_rmse"]
        assert report["heldout_observations"] > 0.9 * 128 * 128 * 3
        assert sum(report["status_counts"].values()) == 128 * 128
    assert rmse["ggx"] < rmse["lambert"], rmse


def test_cli_errors_name_the_problem(tmp_path, capsys):
    assert main(["fit", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "missing" in err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["fit", str(empty), "--out", str(tmp_path / "o")]) == 1
    assert "empty" in capsys.readouterr().err


def test_demo_fits_and_reports_against_the_truth(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--size", "16"]) == 0
    text = capsys.readouterr().out
    assert "roughness       median relative error" in text
    report = json.loads((tmp_path / "fit" / "report.json").read_text())
    assert report["holdout"] == [0] and report["heldout_rmse"] < 0.05
    assert (tmp_path / "fit" / "maps.exr").exists()
    assert (tmp_path / "fit" / "heldout.png").exists()  # photo 0 held out: its error map
    assert not (tmp_path / "fit" / "tiles").exists()  # removed after a successful run
    truth = np.load(tmp_path / "truth" / "params.npz")
    exr = read_exr(tmp_path / "fit" / "maps.exr").channels
    err = np.abs(exr["albedo.G"] - truth["albedo"][..., 1])
    assert np.median(err) < 0.02

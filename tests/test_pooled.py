"""Pooling across pixels (``jaxrefl.svbrdf._pooled``) and the metallic-roughness view.

The synthetic capture below is one basis material -- a narrow GGX lobe with a gold F0 --
over a diffuse albedo that varies per pixel. Nine co-located flash photos like the demo's
(half vectors about 5 degrees apart) see the peak of that lobe on few pixels, so per pixel
the lobe is not identified, while the capture as a whole sees every part of it.
"""

from __future__ import annotations

from dataclasses import replace

import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import brdf, fit
from jaxrefl.demo import demo_capture, demo_scene
from jaxrefl.io import ObsStatus
from jaxrefl.io._capture import Capture
from jaxrefl.svbrdf import AutoOptions, FitJob, fit_capture, leave_one_out
from jaxrefl.svbrdf._pooled import choose_pooled

ALPHA = 0.03
F0 = (0.5, 0.35, 0.1)
SIZE = 24
# Most tests fit six of the nine photos: one photo count (and one tile size) for every fit
# of the same model, so each program compiles once for the whole file.
SIX = (0, 1, 2, 3, 4, 5)
# Every fit of the whole capture runs in one tile of its 576 pixels (the default 4096 rows
# would be mostly padding), and the model selection in tiles of the same shape.
TILE = SIZE * SIZE
# JAX's monitoring events: a program lowered (new to the process), and compiled by XLA.
_LOWER_EVENT = "/jax/core/compile/jaxpr_to_mlir_module_duration"
_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"


@pytest.fixture(scope="module")
def shared_lobe_capture():
    """(capture, truth): every pixel GGX alpha = ALPHA and F0 = F0, albedo in [0.05, 0.6]
    per pixel and channel; linear photos with 1% Gaussian noise."""
    scene = demo_scene(size=SIZE)
    rng = np.random.default_rng(3)
    truth = {
        "albedo": rng.uniform(0.05, 0.6, (SIZE, SIZE, 3)),
        "specular": np.broadcast_to(np.asarray(F0), (SIZE, SIZE, 3)),
        "alpha": np.full((SIZE, SIZE), ALPHA),
    }
    model = scene.model  # Cook-Torrance GGX, height-correlated Smith, Schlick, Lambert base
    k = len(scene.positions)
    cap = demo_capture(scene, np.zeros((k, SIZE, SIZE, 3), np.float32))
    geo = cap.per_pixel_geometry(dtype=np.float64)
    p = {n: jnp.asarray(v) for n, v in truth.items()}
    f = np.asarray(model.eval(p, jnp.asarray(geo["wi"]), jnp.asarray(geo["wo"])))
    img = f * geo["irradiance"] * geo["cos_i"][..., None]
    img = img * (1.0 + 0.01 * rng.standard_normal(img.shape))
    cap = Capture(**{**cap.__dict__, "images": img.astype(np.float32)})
    return cap, truth


def test_pooling_identifies_a_shared_lobe_the_pixels_do_not(shared_lobe_capture):
    cap, truth = shared_lobe_capture
    cap = cap.select(SIX)  # the photo count of the other pooled fits: their programs
    choice = choose_pooled(cap, np.ones(cap.n_photos, bool), alpha_min=1e-3)
    assert choice.model == "lobe"
    assert choice.alpha == pytest.approx(ALPHA, rel=0.1)
    np.testing.assert_allclose(choice.prior_mean, F0, atol=0.03)
    assert choice.cv_rmse[f"{choice.alpha:.4g}"] < 0.5 * choice.cv_rmse["lambert"]

    # the light as stated: the light is not what this tests (tests/test_light*.py)
    job = FitJob(model="pooled", alpha_min=1e-3, light="fixed", tile_pixels=TILE)
    pooled = fit_capture(cap, job)
    per_px = fit_capture(cap, replace(job, model="ggx_rgb"))
    f0_true = truth["specular"]
    f0_pool = np.stack([pooled.maps[f"specular.{c}"] for c in "RGB"], -1)
    f0_px = np.stack([per_px.maps[f"specular.{c}"] for c in "RGB"], -1)
    err_pool = np.abs(f0_pool - f0_true).max(-1)
    err_px = np.abs(f0_px - f0_true).max(-1)
    alpha_px_err = np.abs(per_px.maps["alpha"] / ALPHA - 1.0)
    # The per-pixel fit does not identify the lobe on many pixels ...
    assert np.mean(alpha_px_err > 0.25) > 0.1
    assert np.mean(err_px > 0.05) > 0.2
    # ... the pooled fit gets F0 on nearly all of them.
    assert np.mean(err_pool > 0.05) < 0.02
    assert np.median(err_pool) < 0.3 * np.median(err_px)
    np.testing.assert_allclose(pooled.maps["alpha"], choice.alpha)
    assert pooled.report["pooled"]["model"] == "lobe"
    assert "leave-one-photo-out" in pooled.report["pooled"]["why"]


def test_pooling_chooses_lambert_for_a_matte_capture(shared_lobe_capture):
    cap, truth = shared_lobe_capture
    geo = cap.per_pixel_geometry(dtype=np.float64)
    img = truth["albedo"][None] / np.pi * geo["irradiance"] * geo["cos_i"][..., None]
    img = img * (1.0 + 0.005 * np.random.default_rng(1).standard_normal(img.shape))
    matte = Capture(**{**cap.__dict__, "images": img.astype(np.float32)}).select(SIX)
    choice = choose_pooled(matte, np.ones(matte.n_photos, bool), alpha_min=1e-3)
    assert choice.model == "lambert" and choice.alpha is None
    res = fit_capture(matte, FitJob(model="pooled", holdout=(4,), tile_pixels=TILE))
    assert res.report["pooled"]["model"] == "lambert"
    assert list(res.labels) == ["albedo.R", "albedo.G", "albedo.B"]
    np.testing.assert_allclose(res.maps["albedo.G"], truth["albedo"][..., 1], rtol=0.03)


def test_metallic_view_round_trip():
    rng = np.random.default_rng(0)
    base = rng.uniform(0.0, 1.0, (500, 3))
    metal = rng.uniform(0.0, 1.0, 500)
    albedo, f0 = brdf.metallic_to_specular(base, metal)
    # glTF 2.0 by hand: the dielectric end and the metal end.
    a0, s0 = brdf.metallic_to_specular(base[:1], np.zeros(1))
    np.testing.assert_allclose(a0, base[:1] * 0.96)
    np.testing.assert_allclose(s0, np.full((1, 3), 0.04))
    a1, s1 = brdf.metallic_to_specular(base[:1], np.ones(1))
    np.testing.assert_allclose(a1, 0.0)
    np.testing.assert_allclose(s1, base[:1])
    back_base, back_metal = brdf.specular_to_metallic(albedo, f0)
    np.testing.assert_allclose(back_metal, metal, atol=1e-5)
    np.testing.assert_allclose(back_base, base, atol=1e-4)
    # A dielectric's grey F0 at 0.04 or below reads as metallic 0.
    _, m = brdf.specular_to_metallic(np.full((1, 3), 0.5), np.full((1, 3), 0.03))
    assert float(m[0]) == 0.0


def test_leave_one_out_reuses_one_compile(shared_lobe_capture, tmp_path):
    import jax

    cap, _ = shared_lobe_capture
    cap = cap.select(SIX)
    compiles: list[tuple[int, str]] = []
    fold = {"i": -1}

    def listener(event, duration, **kw):
        # Lowering happens for every program new to this process, even when the persistent
        # compilation cache then serves the compiled code (which skips the backend compile).
        if event in (_LOWER_EVENT, _COMPILE_EVENT):
            compiles.append((fold["i"], event))

    def progress(line):
        fold["i"] += 1

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        fold["i"] = -2
        jax.jit(lambda x: x + 1.0)(1.0)  # a new program: the listener must see it
        fold["i"] = -1
        job = FitJob(model="pooled", alpha_min=1e-3, tile_pixels=TILE)
        loo = leave_one_out(cap, job, progress=progress)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    k = cap.n_photos
    # Folds 1..K-1 of the model and 1..K-1 of the baseline compile nothing: progress is
    # called after each fold, so events tagged i were compiled during fold i + 1.
    model_later = [c for c in compiles if 0 <= c[0] < k - 1]
    base_later = [c for c in compiles if k <= c[0] < 2 * k - 1]
    assert any(c[0] == -2 for c in compiles)
    assert not model_later and not base_later
    assert np.all(np.isfinite(loo.per_photo)) and np.all(np.isfinite(loo.baseline_per_photo))
    # The shared lobe predicts every unseen photo far better than Lambert.
    assert np.all(loo.per_photo < 0.5 * loo.baseline_per_photo)
    r = loo.report
    assert r["heldout_rmse"] == pytest.approx(np.mean(loo.per_photo))
    assert r["lambert_heldout_rmse"] == pytest.approx(np.mean(loo.baseline_per_photo))
    assert set(r["heldout_rmse_per_photo"]) == {str(i) for i in range(k)}
    assert r["heldout_pixel_rmse_p99"] <= r["lambert_heldout_pixel_rmse_p99"]
    assert r["photos_worse_than_baseline"] == []
    assert len(r["pooled_per_fold"]) == k


def test_cli_holdout_all(shared_lobe_capture, tmp_path):
    import json

    from jaxrefl.cli import main
    from jaxrefl.io import save_generic_capture

    cap, _ = shared_lobe_capture
    cap = cap.select(SIX)
    folder = save_generic_capture(
        tmp_path / "cap",
        cap.images,
        side=cap.side,
        light_pos=cap.light_pos,
        light_power=cap.light_power[0],
        camera_pos=cap.camera_pos,
    ).parent
    out = tmp_path / "out"
    argv = ["fit", str(folder), "--out", str(out), "--holdout", "all"]  # the default model
    opts = ["--quiet", "--no-previews", "--alpha-min", "0.001", "--tile-pixels", str(TILE)]
    opts += ["--light", "fixed"]  # the light is not what this tests (tests/test_light*.py)
    assert main([*argv, *opts]) == 0

    def refuse(name):
        raise ValueError(f"non-finite number {name} in report.json")

    report = json.loads((out / "report.json").read_text(), parse_constant=refuse)
    assert report["holdout"] == "all" and report["baseline"] == "lambert"
    for key in ("heldout_rmse", "lambert_heldout_rmse", "heldout_pixel_rmse_p99"):
        assert isinstance(report[key], float)
    assert len(report["heldout_rmse_per_photo"]) == 6
    assert report["heldout_rmse"] < report["lambert_heldout_rmse"]
    # auto chose the shared lobe in every fold and for the final maps, and says why.
    assert [a["model"] for a in report["auto_per_fold"]] == ["pooled"] * 6
    assert report["model"] == "pooled" and report["auto"]["model"] == "pooled"
    assert report["pooled"]["model"] == "lobe"


def _corrupt(cap, k):
    """``cap`` with photo k's values replaced by noise ten times their scale."""
    img = cap.images.copy()
    img[k] = np.random.default_rng(9).uniform(0.0, 10.0 * float(img.max()), img[k].shape)
    return Capture(**{**cap.__dict__, "images": img.astype(np.float32)})


@pytest.fixture(scope="module")
def auto_fit(shared_lobe_capture):
    """(6-photo capture, its default fit with photo 5 held out)."""
    cap, _ = shared_lobe_capture
    cap = cap.select(SIX)
    job = FitJob(holdout=(5,), alpha_min=1e-3, tile_pixels=TILE)
    assert job.model == "auto" and job.config.loss is None
    return cap, fit_capture(cap, job)


def test_auto_chooses_the_shared_coloured_lobe_and_never_sees_held_out_photos(auto_fit):
    from jaxrefl.svbrdf import AUTO_CANDIDATES, choose_model

    cap, res = auto_fit
    choice = res.auto
    assert set(choice.cv_rmse) | set(choice.skipped) == set(AUTO_CANDIDATES)
    # The per-pixel normal refines the per-pixel dielectric, which is not the best here.
    assert "ggx_normal" in choice.skipped
    # A gold F0 of 0.5 is outside the dielectric range, and per pixel the narrow lobe is not
    # identified: the pooled coloured lobe predicts unseen photos best, by a wide margin
    # over Lambert.
    assert choice.model == "pooled"
    assert choice.cv_rmse["pooled"] < 0.5 * choice.cv_rmse["lambert"]
    assert choice.cv_rmse["pooled"] < choice.cv_rmse["ggx"]
    assert choice.folds == (0, 1, 2, 3, 4)
    # Photo 5 is held out: replacing it by noise changes no score.
    again = choose_model(_corrupt(cap, 5), FitJob(holdout=(5,), alpha_min=1e-3, tile_pixels=TILE))
    assert again.cv_rmse == choice.cv_rmse
    # The fit resolves the model and its loss and reports the choice.
    assert res.job.model == "pooled" and res.job.config.loss == fit.Huber()
    assert res.pooled is choice.pooled  # the selection's width, not chosen again
    assert res.report["model"] == "pooled"
    assert res.report["auto"]["model"] == "pooled"
    assert res.report["auto"]["cv_rmse"] == pytest.approx(choice.cv_rmse)
    assert "leave-one-photo-out" in res.report["auto"]["why"]
    lam = fit_capture(cap, FitJob(model="lambert", holdout=(5,), tile_pixels=TILE))
    assert res.report["heldout_rmse"] < 0.5 * lam.report["heldout_rmse"]


def test_the_pooled_fit_runs_and_records_its_own_settings(auto_fit):
    """The pooled fit runs with the selection's noise scale, its Huber loss and fused LM
    rounds: what the resume manifest records (``TileFitter.settings``), not the job's."""
    from jaxrefl.svbrdf._tile_fitter import TileFitter

    cap, cf = auto_fit
    ran = TileFitter(cap, cf.job, pooled=cf.pooled).settings()
    assert ran["compact"] is cf.job.compact is False  # a small capture: no compaction
    assert cf.job.config.noise.sigma is None
    sigma = pytest.approx(cf.pooled.sigma, rel=1e-6)
    assert ran["config"]["noise"] == {"type": "gaussian", "sigma": sigma}
    assert ran["config"]["loss"]["type"] == "huber"
    assert ran["config"]["solver"]["host_fused"] and not ran["config"]["solver"]["compact_stages"]
    assert "tilted_solver" not in ran


def test_auto_leaves_out_what_a_matte_capture_does_not_need(shared_lobe_capture):
    from jaxrefl.svbrdf import choose_model

    cap, truth = shared_lobe_capture
    geo = cap.per_pixel_geometry(dtype=np.float64)
    img = truth["albedo"][None] / np.pi * geo["irradiance"] * geo["cos_i"][..., None]
    img = img * (1.0 + 0.005 * np.random.default_rng(1).standard_normal(img.shape))
    matte = Capture(**{**cap.__dict__, "images": img.astype(np.float32)}).select(SIX)
    three = AutoOptions(candidates=("lambert", "pooled", "ggx"))
    choice = choose_model(matte, FitJob(alpha_min=1e-3, auto=three, tile_pixels=TILE))
    assert choice.model == "lambert"
    assert set(choice.cv_rmse) == {"lambert", "pooled", "ggx"}
    assert choice.as_dict()["candidates"] == ["lambert", "pooled", "ggx"]
    with pytest.raises(ValueError, match="other than 'auto'"):
        AutoOptions(candidates=("auto",))


def test_tilted_model_compiles_once_for_every_tile(shared_lobe_capture):
    """ggx_normal estimates the noise scale per tile: as an array, so the second tile's fit
    reuses the first's programs (a float would be static under equinox's jit)."""
    import jax

    cap, _ = shared_lobe_capture
    cap = cap.select([0, 1, 2, 3]).crop(0, 12, 0, 12)  # three tiles of 48 pixels
    n_px = cap.shape[1] * cap.shape[2]
    events: list[int] = []
    tiles = {"done": 0}

    def listener(event, duration, **kw):
        if event in (_LOWER_EVENT, _COMPILE_EVENT):
            events.append(tiles["done"])

    def on_tile(i, n):
        tiles["done"] += 1

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        res = fit_capture(cap, FitJob(model="ggx_normal", tile_pixels=n_px // 3), on_tile=on_tile)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert res.report["timings"]["tiles"] == 3
    # The first tile runs twice (warm-up, then timed); tiles 1 and 2 compile nothing (the
    # maps and the report after the last tile may).
    assert events and [e for e in events if 1 <= e < 3] == []


def test_auto_keeps_a_per_pixel_lobe_where_roughness_varies(shared_lobe_capture):
    """The demo's surface (grey dielectric F0, perceptual roughness 0.3-0.75 by patch), all
    nine photos: no one width fits every pixel, so the per-pixel dielectric wins (with five
    training photos the pooled width still predicts better), and its refinement with a
    per-pixel normal is not fitted: the surface is flat, and the score test of the slopes
    at the dielectric's optimum finds no more than noise."""
    from jaxrefl.svbrdf import choose_model
    from jaxrefl.svbrdf._auto import EVIDENCE_RATIO

    cap, _ = shared_lobe_capture
    scene = demo_scene(size=SIZE)
    geo = cap.per_pixel_geometry(dtype=np.float64)
    f = np.asarray(scene.model.eval(scene.params, jnp.asarray(geo["wi"]), jnp.asarray(geo["wo"])))
    img = f * geo["irradiance"] * geo["cos_i"][..., None]
    img = img * (1.0 + 0.01 * np.random.default_rng(5).standard_normal(img.shape))
    demo = Capture(**{**cap.__dict__, "images": img.astype(np.float32)})
    # 256 pixels a fold in one tile of 2048 rows: half the default rows, the same choice.
    job = FitJob(holdout=(8,), tile_pixels=2048, auto=AutoOptions(max_pixels=2048))
    choice = choose_model(demo, job)
    assert choice.model == "ggx", choice.as_dict()["why"]
    assert set(choice.cv_rmse) == {"lambert", "pooled", "ggx", "ggx_rgb"}
    assert "no sign of it" in choice.skipped["ggx_normal"]
    # The statistic over its null expectation: near 1 (the noise estimates bias it up a
    # little), well below the gate.
    assert 0.9 < choice.evidence["ggx_normal"] < EVIDENCE_RATIO
    assert choice.as_dict()["evidence"] == choice.evidence
    assert choice.cv_rmse["ggx"] < choice.cv_rmse["pooled"] < choice.cv_rmse["lambert"]


def test_held_out_photo_is_re_rendered_with_coloured_highlights(auto_fit, tmp_path):
    """compare.png shows ``predict_photos`` of the held-out photo: with the default model its
    gold highlight stays gold; the grey-F0 dielectric paints it whiter."""
    from jaxrefl.svbrdf import predict_photos, write_outputs

    cap, res = auto_fit
    assert res.job.model == "pooled"
    shot, pred = predict_photos(res, cap, [5])
    shot, pred = shot[0], pred[0]
    # The highlight: the brightest 3% of the held-out photo's pixels.
    lum = shot.mean(-1)
    hi = lum >= np.quantile(lum, 0.97)

    def chroma(img):  # R / B of the highlight's mean colour above the diffuse level
        return float(img[hi][:, 0].mean() / img[hi][:, 2].mean())

    assert chroma(shot) > 1.8  # the photo's highlight is gold
    assert chroma(pred) == pytest.approx(chroma(shot), rel=0.15)
    grey = fit_capture(cap, FitJob(model="ggx", holdout=(5,), alpha_min=1e-3, tile_pixels=TILE))
    _, g = predict_photos(grey, cap, [5])
    assert abs(chroma(g[0]) - chroma(shot)) > 2 * abs(chroma(pred) - chroma(shot))
    files = write_outputs(res, cap, tmp_path / "out")
    assert any(p.endswith("compare.png") for p in files["previews"])


def test_leave_one_out_compacts_by_the_work_of_all_folds(shared_lobe_capture, monkeypatch):
    """fit_capture compacts the LM's slow pixels by the capture's size unless the job says
    (``FitJob.compact``), and its job records what ran; the K fits of leave_one_out share
    their programs, so they compact by K x H x W, and the model selection's per-pixel fits
    follow the fit's choice (the same tile shape)."""
    from jaxrefl.svbrdf import _auto, _job, _job_types, _tile_fitter

    cap, _ = shared_lobe_capture
    cap = cap.select([0, 1, 2, 3]).crop(0, 8, 0, 8)  # K = 4 folds of 64 pixels
    seen: list[tuple[str, bool]] = []

    class Recording(_tile_fitter.TileFitter):
        def __init__(self, capture, job, pooled=None, *, width_terms=True):
            super().__init__(capture, job, pooled, width_terms=width_terms)
            seen.append((job.model, self.compact))

    monkeypatch.setattr(_job, "TileFitter", Recording)
    monkeypatch.setattr(_auto, "TileFitter", Recording)
    job = FitJob(model="lambert", tile_pixels=64)
    res = fit_capture(cap, job)
    assert seen == [("lambert", False)]  # 64 pixels: far below COMPACT_MIN_PIXELS
    assert res.job.compact is False and res.report["job"]["compact"] is False
    seen.clear()
    monkeypatch.setattr(_job_types, "COMPACT_MIN_PIXELS", 4 * 64)  # K x H x W reaches it
    leave_one_out(cap, job)
    assert seen == [("lambert", True)] * 8
    seen.clear()
    monkeypatch.setattr(_job_types, "COMPACT_MIN_PIXELS", 4 * 64 + 1)
    leave_one_out(cap, job)
    assert seen == [("lambert", False)] * 8
    seen.clear()
    # The default model: fit_capture hands the job's choice to the selection (here of one
    # candidate, which keeps the test to one compiled model) and to the chosen model's fit.
    one = AutoOptions(candidates=("lambert",))
    res = fit_capture(cap, FitJob(tile_pixels=64, holdout=(3,), compact=True, auto=one))
    assert res.job.model == "lambert" and res.job.compact is True
    assert res.report["auto"]["candidates"] == ["lambert"] and res.job.auto == one
    assert seen == [("lambert", True), ("lambert", True)]


def test_pixel_take_reads_the_pixels_pixel_block_reads(shared_lobe_capture):
    """The model selection's random pixels, read alone (geometry for them only), equal the
    same rows of the capture read in one block, censoring and weights included."""
    import jax

    from jaxrefl.svbrdf import pixel_block
    from jaxrefl.svbrdf._data import pixel_take

    cap, _ = shared_lobe_capture
    st = cap.status.copy()
    st[0, 3, 4, 1] = ObsStatus.SATURATED
    st[2, 5, 6, 0] = ObsStatus.DARK
    st[1, 7, 7, :] = ObsStatus.MASKED
    cap = replace(cap, status=st)
    n = SIZE * SIZE
    pick = np.sort(np.random.default_rng(3).choice(n, 40, replace=False))
    pick = np.union1d(pick, [3 * SIZE + 4, 5 * SIZE + 6, 7 * SIZE + 7])
    whole = pixel_block(cap, 0, n, dtype=np.float64)
    took = pixel_take(cap, pick, dtype=np.float64)
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(took), strict=True):
        np.testing.assert_array_equal(np.asarray(a)[pick], np.asarray(b))
    assert took.colocated == whole.colocated
    with pytest.raises(ValueError, match="pixel indices"):
        pixel_take(cap, np.array([n]))

"""Captures that are well-formed and physically impossible, or degenerate: refused where they
enter (naming the file and line or key), or fitted into outputs in which every non-finite
number carries a flag that says why.

Families: a camera below the sample, a flash in the plane, zero and tiny flash power, a camera
or light 1e30 away, a camera on the sample, every photo saturated or black or half of each,
an all-zero mask or alpha channel (all refused at load, and the CLI exits 1); the same
degenerate geometry and photos built in Python, where no loader stands guard, fitted on a
4 x 4 crop of the 8 x 8 demo in one of test_svbrdf's tiles (one compiled program); negative
and infinite observations in one pixel of a ``fit_pixels`` call; a pixel fitted exactly (std
0, undefined correlations); one and two photos under ``auto``.
"""

from __future__ import annotations

import json
import shutil
import warnings
from dataclasses import replace

import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import JaxreflError, brdf, fit, svbrdf
from jaxrefl.cli._main import main
from jaxrefl.demo import demo_capture, demo_scene, render_demo
from jaxrefl.fit._laplace import CORR_NAN_FLAGS, STD_NAN_FLAGS, undefined_correlations
from jaxrefl.io import CaptureError, CaptureWarning, ObsStatus, load_capture
from jaxrefl.io._photos import write_png
from jaxrefl.svbrdf._auto import ModelChoice, choose_model

K = 3  # photos of the MaterialGAN folders
_TILE = 16  # test_svbrdf's tile size on the 8 x 8 demo: one compiled tile program


# ----------------------------------------------------------------------------- refused at load
def _materialgan(d, *, value=128, cam=None, light=None, power=1500.0):
    """A MaterialGAN folder of K 4x4 photos of one grey ``value`` (or (K,) values), flash
    beside the camera about 24 cm above the sample."""
    d.mkdir()
    values = np.broadcast_to(np.asarray(value), (K,))
    for i in range(K):
        write_png(d / f"{i:02d}.png", np.full((4, 4, 3), values[i], np.uint8))
    cam = np.tile([0.0, 2.0, 24.0], (K, 1)) if cam is None else np.asarray(cam, float)
    light = cam + np.array([1.0, 0.0, 0.0]) if light is None else np.asarray(light, float)
    np.savetxt(d / "camera_pos.txt", cam, delimiter=",")
    np.savetxt(d / "light_pos.txt", light, delimiter=",")
    np.savetxt(d / "light_power.txt", [[power] * 3], delimiter=",")
    (d / "image_size.txt").write_text("10.0\n")
    return d


def _row(k, xyz):
    """K rows of a sane camera with row ``k`` replaced by ``xyz``."""
    rows = np.tile([0.0, 2.0, 24.0], (K, 1))
    rows[k] = xyz
    return rows


REFUSED = {
    "camera below the sample": (
        {"cam": _row(1, [0.0, 2.0, -5.0])},
        "camera_pos.txt",
        "line 2",
        "camera is at z = -5 cm, not above",
    ),
    "camera on the sample": (
        {"cam": _row(0, [0.0, 0.0, 0.0])},
        "camera_pos.txt",
        "line 1",
        "camera is at z = 0 cm",
    ),
    "camera 1e30 away": (
        {"cam": _row(2, [0.0, 0.0, 1e30])},
        "camera_pos.txt",
        "line 3",
        "from the sample, more than",
    ),
    "camera 1e200 away (its square overflows)": (
        {"cam": _row(2, [1e200, 0.0, 1e200])},
        "camera_pos.txt",
        "line 3",
        "camera is inf cm from the sample",
    ),
    "flash in the plane": (
        {"light": _row(1, [1.0, 2.0, 0.0])},
        "light_pos.txt",
        "line 2",
        "light is at z = 0 cm, not above",
    ),
    "light 1e30 away": (
        {"light": _row(0, [0.0, 0.0, 1e30])},
        "light_pos.txt",
        "line 1",
        "give it as a directional light",
    ),
    "zero flash power": ({"power": 0.0}, "light_power.txt", "line 1", "must be > 0"),
    "flash power below float32": (
        {"power": 1e-40},
        "light_power.txt",
        "line 1",
        "outside float32's normal range",
    ),
    "every photo saturated": (
        {"value": 255},
        "mg",
        "00.png ... 02.png",
        "every observation is saturated .* lower the exposure",
    ),
    "every photo black": (
        {"value": 0},
        "mg",
        "00.png ... 02.png",
        "every observation is black .* raise the exposure",
    ),
    "half black, half saturated": (
        {"value": [0, 255, 0]},
        "mg",
        "00.png ... 02.png",
        r"saturated \(48\) or black \(96\)",
    ),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_impossible_capture_is_refused_naming_file_and_line(tmp_path, case):
    kw, fname, field, msg = REFUSED[case]
    d = _materialgan(tmp_path / "mg", **kw)
    with pytest.raises(CaptureError, match=msg) as e:
        load_capture(d)
    assert e.value.path.name == fname and e.value.field == field, str(e.value)
    assert f"{fname}: {field}: " in str(e.value)


def test_masks_that_exclude_everything_are_refused(tmp_path):
    """An all-zero mask file (generic layout) and an all-transparent alpha channel."""
    img = np.full((2, 4, 4, 3), 0.3)
    cj = svbrdf_capture_json(tmp_path / "g", img, mask=np.zeros((4, 4), bool))
    with pytest.raises(CaptureError, match=r"the mask mask\.png excludes every pixel"):
        load_capture(cj)
    d = _materialgan(tmp_path / "mg")
    for i in range(K):
        write_png(d / f"{i:02d}.png", np.zeros((4, 4, 4), np.uint8))  # RGBA, alpha 0
    with pytest.raises(CaptureError, match="alpha channel excludes every pixel"):
        load_capture(d)


def svbrdf_capture_json(folder, img, **kw):
    from jaxrefl.io import save_generic_capture

    return save_generic_capture(
        folder, img, side=4.0, light_pos=[0.0, 1.0, 20.0], light_power=400.0,
        camera_pos=[0.0, 0.0, 20.0], transfer="gamma2.2", file_format="png8", **kw,
    )  # fmt: skip


def test_python_capture_without_photos_or_with_overflowing_geometry_is_refused():
    cap = _demo(size=8)
    with pytest.raises(CaptureError, match="holds no photo") as e:
        replace(cap, images=cap.images[:0], status=cap.status[:0])
    assert e.value.field == "images"
    far = cap.camera_pos.copy()
    far[4] = [0.0, 1e200, 1e200]
    with pytest.raises(CaptureError, match="squared distance overflows") as e:
        replace(cap, camera_pos=far)
    assert e.value.field == "camera_pos" and "(4,)" in str(e.value)


def test_odd_captures_load_with_a_warning_naming_the_file(tmp_path):
    # A flash 15 cm from the camera of a phone layout, 24 cm above the sample.
    d = _materialgan(tmp_path / "far", light=np.tile([15.0, 2.0, 24.0], (K, 1)))
    with pytest.warns(CaptureWarning, match=r"light_pos\.txt: line 1: the flash is 15 cm .*3 of 3"):
        load_capture(d)
    # Photos 1e4 times darker than a white surface under 1.5e7 (a power in the wrong unit).
    d = _materialgan(tmp_path / "dark", power=1.5e7, value=40)
    with pytest.warns(CaptureWarning, match=r"light_power\.txt: line 1: .* much darker"):
        cap = load_capture(d)
    assert cap.n_photos == K
    # One photo all saturated among measured ones.
    d = _materialgan(tmp_path / "one", value=[128, 255, 128])
    with pytest.warns(CaptureWarning, match=r"01\.png: every pixel is saturated"):
        load_capture(d)


def test_real_captures_and_the_demo_load_without_warnings(shared_data, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error", CaptureWarning)
        for name in ("bath_tile", "yellow_box"):
            cap = load_capture(shared_data / "svbrdf_flash" / name, resolution=64)
            assert cap.n_photos == 9
        assert main(["demo", "--out", str(tmp_path / "demo"), "--size", "8", "--no-fit"]) == 0
        assert load_capture(tmp_path / "demo").shape == (9, 8, 8, 3)


def test_cli_fit_exits_1_on_a_refused_capture(tmp_path, capsys):
    d = _materialgan(tmp_path / "black", value=0)
    out = tmp_path / "out"
    assert main(["fit", str(d), "--out", str(out), "--quiet", "--no-previews"]) == 1
    err = capsys.readouterr().err
    assert "every observation is black" in err and "raise the exposure" in err
    assert not (out / "report.json").exists()


# ----------------------------------------------------------------------------- flagged outputs
def _demo(size=8):
    scene = demo_scene(size=size, seed=0, dtype=jnp.float64)
    lin = np.asarray(render_demo(scene, encode=False), np.float64)
    lin = lin + 1e-3 * np.random.default_rng(0).standard_normal(lin.shape)
    return demo_capture(scene, lin)


def _why(name: str) -> int:
    """The flag bits that may explain a non-finite value of map ``name`` (docs/outputs.md)."""
    if name.startswith("corr_"):
        return int(CORR_NAN_FLAGS)
    if "_std" in name:
        return int(STD_NAN_FLAGS)
    return int(fit.LaplaceFlag.NO_ESTIMATE)


def _assert_every_nonfinite_is_flagged(maps, report):
    flag = maps["laplace_flag"].astype(np.int64)
    floats = [k for k, v in maps.items() if v.dtype.kind == "f"]
    assert len(floats) > 10
    for name in floats:
        bad = ~np.isfinite(maps[name]) & ((flag & _why(name)) == 0)
        assert not np.any(bad), (name, int(bad.sum()))
    # report.json counts every bit of the map
    for b in fit.LaplaceFlag:
        assert report["laplace_flag_counts"][b.name] == int(np.sum((flag & b) != 0)), b.name


def _degenerate(cap):
    ones = np.ones_like(cap.status)
    half = np.where(np.arange(cap.n_photos)[:, None, None, None] % 2 == 0, 1, 2) * ones
    return {
        "zero power": replace(cap, light_power=np.zeros_like(cap.light_power)),
        "tiny power": replace(cap, light_power=np.full_like(cap.light_power, 1e-30)),
        "light 1e30 away": replace(cap, light_pos=cap.light_pos * 1e30),
        "camera on the sample": replace(cap, camera_pos=np.zeros_like(cap.camera_pos)),
        "all saturated": replace(cap, status=ones * np.uint8(ObsStatus.SATURATED)),
        "all black": replace(
            cap, status=ones * np.uint8(ObsStatus.DARK), images=np.zeros_like(cap.images)
        ),
        "half black, half saturated": replace(cap, status=half.astype(np.uint8)),
        "all masked": cap.apply_mask(np.zeros(cap.shape[1:3], bool)),
    }


def test_fits_of_degenerate_captures_flag_every_nonfinite_value():
    """Built in Python (no loader checks them), fitted with ggx: every channel of the maps is
    finite wherever the Laplace flag gives no reason, and report.json counts every bit."""
    cap = _demo().crop(0, 4, 0, 4)  # 16 pixels: one tile of _TILE
    job = svbrdf.FitJob(model="ggx", tile_pixels=_TILE)
    n = cap.shape[1] * cap.shape[2]
    for case, bad in _degenerate(cap).items():
        r = svbrdf.fit_capture(bad, job)
        _assert_every_nonfinite_is_flagged(r.maps, r.report)
        flag = r.maps["laplace_flag"]
        if case in ("zero power", "light 1e30 away"):
            # no irradiance: J^T J is zero, never inverted, every std NaN for that reason
            assert np.all(flag & fit.LaplaceFlag.SINGULAR), case
            assert np.all(np.isnan(r.maps["alpha_std"])), case
            assert r.report["laplace_flag_counts"]["SINGULAR"] == n
        if case == "all masked":
            assert np.all(flag == fit.LaplaceFlag.NO_ESTIMATE)
            assert r.report["status_counts"]["MASKED"] == n


def test_one_bad_observation_in_a_fit_pixels_call_is_flagged_where_nonfinite():
    """16 pixels of 6 photos; one pixel holds a negative, +-inf or NaN observation, or a whole
    pixel does: every non-finite std or correlation carries a flag that says why."""
    k = 6
    ang = np.linspace(0.1, 0.9, k)
    wi = np.stack([np.sin(ang), np.zeros(k), np.cos(ang)], -1)
    wo = np.stack([-0.5 * np.sin(ang), np.zeros(k), np.sqrt(1 - 0.25 * np.sin(ang) ** 2)], -1)
    model = brdf.get("cook_torrance")
    rng = np.random.default_rng(0)
    for bad in (-1.0, np.inf, -np.inf, np.nan):
        obs = rng.uniform(0.1, 0.5, (16, k, 3)).astype(np.float32)
        obs[3, 2, 1] = bad
        obs[5] = bad
        data = fit.pixel_data(obs, wi, wo)
        r = fit.fit_pixels(model, data)
        lap = fit.laplace(r, data)
        flag = np.asarray(lap.flag)
        std, corr = np.asarray(lap.std), np.asarray(lap.corr)
        assert np.all((flag & STD_NAN_FLAGS)[~np.all(np.isfinite(std), -1)])
        assert np.all((flag & CORR_NAN_FLAGS)[~np.all(np.isfinite(corr), (-2, -1))])
        # a finite std and correlations where no such bit is set
        ok = (flag & CORR_NAN_FLAGS) == 0
        assert np.all(np.isfinite(std[ok])) and np.all(np.isfinite(corr[ok]))
        if not np.isfinite(bad):  # every observation of pixel 5 non-finite: no estimate
            assert flag[5] & fit.LaplaceFlag.NO_ESTIMATE


def test_a_zero_std_makes_correlations_undefined_nan_and_flagged():
    """A pixel fitted exactly (cost 0, estimated noise 0) has std 0: its correlations are NaN
    with CORR_UNDEFINED, not 0 and not unflagged; widening (a shared parameter's share)
    gives the std back, and the correlations are formed again."""
    k = 6
    ang = np.linspace(0.1, 0.9, k)
    wi = np.stack([np.sin(ang), np.zeros(k), np.cos(ang)], -1)
    obs = np.random.default_rng(1).uniform(0.1, 0.5, (16, k, 3)).astype(np.float32)
    data = fit.pixel_data(obs, wi)
    r = fit.fit_pixels(brdf.get("lambert"), data)
    exact = replace(r, cost=jnp.zeros_like(r.cost).at[0].set(r.cost[0]))
    lap = fit.laplace(exact, data)
    flag, std, corr = np.asarray(lap.flag), np.asarray(lap.std), np.asarray(lap.corr)
    formed = np.all(np.isfinite(std), -1)
    assert formed[1:].all() and np.all(std[1:] == 0)
    assert np.all(np.isnan(corr[1:]))
    assert np.all(flag[1:] & fit.LaplaceFlag.CORR_UNDEFINED)
    assert not flag[0] & fit.LaplaceFlag.CORR_UNDEFINED and np.all(np.isfinite(corr[0]))
    # The helper the capture job applies after widening decides again from the stds.
    wider = std + np.where(np.arange(3) == 0, 0.1, 0.0)  # parameter 0 gets a std
    c2, f2 = undefined_correlations(wider, np.where(np.isnan(corr), 0.0, corr), flag)
    assert np.all(f2[1:] & fit.LaplaceFlag.CORR_UNDEFINED)  # parameters 1, 2 still std 0
    assert np.all(np.isnan(c2[1:, 1:, :])) and np.all(np.isnan(c2[1:, :, 1:]))
    assert np.all(np.isfinite(c2[1:, 0, 0]))
    c3, f3 = undefined_correlations(std + 0.1, np.where(np.isnan(corr), 0.0, corr), flag)
    assert not np.any(f3 & fit.LaplaceFlag.CORR_UNDEFINED) and np.all(np.isfinite(c3))


# ----------------------------------------------------------------------------- too few photos
def test_auto_on_one_and_two_photos_says_what_is_possible():
    cap = _demo()
    one = svbrdf.fit_capture(cap.select([4]), svbrdf.FitJob(tile_pixels=_TILE))
    auto = one.report["auto"]
    assert one.report["model"] == auto["model"] == "lambert" and auto["cv_rmse"] == {}
    assert "too few training photos (1)" in auto["why"] and "lambert can be fitted" in auto["why"]
    assert auto["skipped"]["ggx"] == "needs 2 training photos, the capture has 1 photo"
    assert auto["skipped"]["pooled"].startswith("needs 2")
    _assert_every_nonfinite_is_flagged(one.maps, one.report)
    assert np.all(np.isfinite(one.maps["albedo.R"]))

    two = choose_model(cap.select([2, 6]), svbrdf.FitJob(tile_pixels=_TILE))
    assert two.model == "lambert" and set(two.cv_rmse) == {"lambert"}
    assert "not scored" in two.skipped["ggx"] and "needs 3" in two.skipped["ggx_rgb"]
    two_models = svbrdf.AutoOptions(candidates=("ggx_rgb", "ggx"))
    with pytest.raises(JaxreflError, match=r"1 photo of .*: ggx_rgb needs 3, ggx needs 2; add"):
        choose_model(cap.select([2]), svbrdf.FitJob(auto=two_models))
    with pytest.raises(JaxreflError, match="pooled needs at least two training photos"):
        svbrdf.fit_capture(cap.select([2]), svbrdf.FitJob(model="pooled", tile_pixels=_TILE))


def test_auto_report_says_why_no_candidate_was_scored():
    choice = ModelChoice("lambert", {"lambert": float("inf"), "ggx": float("inf")}, 64, (0, 1), {})
    why = choice.as_dict()["why"]
    assert why.startswith("no candidate could be scored") and "chose the simplest, lambert" in why
    json.dumps(choice.as_dict())  # plain JSON values (inf is written as Infinity, not a crash)


def test_materialgan_template_folder_is_sane(tmp_path):
    """The folders above differ from a capture that loads only where each case says."""
    d = _materialgan(tmp_path / "ok")
    with warnings.catch_warnings():
        warnings.simplefilter("error", CaptureWarning)
        cap = load_capture(d)
    assert cap.shape == (K, 4, 4, 3) and np.all(cap.valid)
    shutil.rmtree(d)

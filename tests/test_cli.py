"""The command line: the demo writes a readable capture; errors are messages, not tracebacks."""

from __future__ import annotations

import json

import numpy as np
from PIL import Image

from jaxrefl.cli import main


def test_demo_writes_a_capture(tmp_path, capsys):
    out = tmp_path / "demo"
    # --no-fit: the capture is what this test reads (test_svbrdf runs the demo with its fit)
    assert main(["demo", "--out", str(out), "--size", "32", "--no-fit"]) == 0
    text = capsys.readouterr().out
    assert "9 flash photos" in text and "compile" in text
    params = json.loads((out / "parameters.json").read_text())
    assert len(params["light_pos"]) == len(params["camera_pos"]) == 9
    imgs = sorted((out / "images" / "reference" / "32").glob("*.png"))
    assert len(imgs) == 9
    a = np.asarray(Image.open(imgs[0]))
    assert a.shape == (32, 32, 3) and a.dtype == np.uint8
    assert 20 < a.mean() < 235  # exposed, neither black nor white
    truth = np.load(out / "truth" / "params.npz")
    assert truth["albedo"].shape == (32, 32, 3)
    np.testing.assert_allclose(truth["roughness"] ** 2, truth["alpha"], rtol=1e-5)


def test_demo_highlight_follows_the_flash(tmp_path):
    """The brightest spot of each photo lies under its flash (the mirror configuration)."""
    from jaxrefl.demo import demo_scene, render_demo

    scene = demo_scene(size=64)
    scene.params["albedo"] = scene.params["albedo"] * 0 + 0.2  # uniform, so only the lobe moves
    scene.params["alpha"] = scene.params["alpha"] * 0 + 0.04
    scene.params["specular"] = scene.params["specular"] * 0 + 0.05
    imgs = np.asarray(render_demo(scene, encode=False))
    pts = np.asarray(scene.points)
    for k in range(imgs.shape[0]):
        i, j = np.unravel_index(np.argmax(imgs[k].sum(-1)), imgs[k].shape[:2])
        under = scene.positions[k, :2]
        under = np.clip(under, pts[..., :2].min((0, 1)), pts[..., :2].max((0, 1)))
        assert np.linalg.norm(pts[i, j, :2] - under) < 0.6, (k, pts[i, j], under)


def test_bad_size_is_a_clear_error(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--size", "30"]) == 2
    assert "argument --size: must be a multiple of 4" in capsys.readouterr().err


def test_models_lists_every_model(capsys):
    assert main(["models"]) == 0
    text = capsys.readouterr().out
    for name in ("lambert", "cook_torrance", "lafortune", "ward", "dichromatic"):
        assert name in text


def test_fit_flags_map_to_the_option_objects():
    """--backend, --dtype, --noise, --loss and --max-iters become the fit's objects."""
    from jaxrefl import fit
    from jaxrefl.cli._options import fit_config

    default = fit_config()
    assert default == fit.FitConfig(dtype=np.float32)
    assert default.loss is None and default.noise == fit.GaussianNoise()
    cfg = fit_config("optimistix", "float64", "shot", "huber", max_iters=7)
    assert cfg.solver == fit.OptimistixLM(max_iters=7)
    assert cfg.noise == fit.ShotNoise(read=0.002, gain=0.002)
    assert cfg.loss == fit.Huber() and cfg.dtype == np.float64
    assert isinstance(fit_config("jaxopt").solver, fit.JaxoptLM)
    assert fit_config("lean", max_iters=12).solver == fit.LMOptions(max_iters=12)
    assert fit_config(loss="cauchy").loss == fit.Cauchy()
    assert fit_config(loss="l2").loss == fit.L2()

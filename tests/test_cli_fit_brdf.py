"""`jaxrefl fit-brdf`: the report and the lobe plots, and errors as messages."""

from __future__ import annotations

import json

import numpy as np
from PIL import Image

from jaxrefl.cli import main


def test_fit_brdf_writes_report_and_plots(shared_data, tmp_path, capsys):
    out = tmp_path / "fit"
    path = shared_data / "brdf/curet/abrdf.dat"
    rc = main(
        ["fit-brdf", str(path), "--sample", "15", "--models", "lambert,ward", "--out", str(out)]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "| ward |" in text and "report.json" in text
    rep = json.loads((out / "report.json").read_text())
    assert list(rep["models"]) == ["lambert", "ward"]
    assert rep["data"]["sample"] == 15 and rep["n_samples"] == 189  # 16 beyond 80 degrees
    for name, n_params in (("lambert", 1), ("ward", 3)):
        entry = rep["models"][name]
        assert entry["n_params"] == n_params
        assert set(entry["metrics"]) == {"cosine_weighted_l2", "log_l2", "relative_l2"}
        assert entry["fit_time_s"] > 0 and entry["compile_time_s"] >= 0
        assert entry["status"] in ("CONVERGED", "MAX_ITERATIONS", "AT_BOUND")
    # The shiny CURET sample 15 needs the lobe (measured: 0.025 against 0.087 /sr).
    m = {k: v["metrics"]["cosine_weighted_l2"] for k, v in rep["models"].items()}
    assert m["ward"] < 0.5 * m["lambert"]
    assert rep["best"]["cosine_weighted_l2"] == "ward"
    img = np.asarray(Image.open(out / "lobes.png"))
    assert img.ndim == 3 and img.shape[0] > 200 and img.std() > 5  # a drawn figure


def test_fit_brdf_errors_are_messages(shared_data, tmp_path, capsys):
    curet = str(shared_data / "brdf/curet/abrdf.dat")
    out = str(tmp_path / "o")
    assert main(["fit-brdf", curet, "--out", out]) == 1
    assert "choose one" in capsys.readouterr().err
    assert main(["fit-brdf", curet, "--sample", "1", "--models", "phong_9", "--out", out]) == 1
    assert "unknown model" in capsys.readouterr().err
    assert main(["fit-brdf", str(tmp_path / "none.astm"), "--out", out]) == 1
    assert "no such file" in capsys.readouterr().err

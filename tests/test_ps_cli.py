"""``jaxrefl ps`` end to end: a small synthetic DiLiGenT capture and the UW chrome sphere."""

from __future__ import annotations

import json

import numpy as np
import pytest

import jaxrefl
from jaxrefl import ps
from jaxrefl.cli._main import main
from jaxrefl.io import read_exr


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    _, n, m = ps.sphere_surface(20, 24)
    lights = ps.spiral_lights(12, 50.0)
    e = np.ones((12, 3))
    img = ps.render(jaxrefl.brdf.get("lambert"), {"albedo": np.full(3, 0.7)}, n, m, lights, e)
    return ps.save_diligent(tmp_path_factory.mktemp("cli") / "ball", img, lights, e, m, n)


def test_cli_writes_maps_and_report(capture, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["ps", str(capture), "--out", str(out), "--method", "robust"]) == 0
    for f in ("normals", "albedo", "depth", "error"):
        assert (out / f"{f}.exr").is_file() and (out / f"{f}.png").is_file()
    r = json.loads((out / "report.json").read_text())
    assert r["method"] == "robust" and r["reference"] == "ground_truth"
    assert 0 <= r["mean_angular_error_deg"] < 0.5 and r["median_angular_error_deg"] < 0.5
    assert {"load_s", "solve_s", "integrate_s", "write_s", "total_s"} <= set(r["timings"])
    exr = read_exr(out / "normals.exr")
    n = exr.stack(["normal.X", "normal.Y", "normal.Z"])
    mask = np.asarray(ps.load_diligent(capture).mask)
    assert np.all(np.isfinite(n[mask])) and np.all(n[mask][:, 2] > 0)
    assert "angular error vs ground_truth" in capsys.readouterr().out


def test_cli_bad_input_is_a_clear_error(capture, tmp_path, capsys):
    assert main(["ps", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 1
    assert "capture folder not found" in capsys.readouterr().err
    np.savetxt(capture / "light_intensities.txt", np.ones((11, 3)))
    try:
        assert main(["ps", str(capture), "--out", str(tmp_path / "o")]) == 1
    finally:
        np.savetxt(capture / "light_intensities.txt", np.ones((12, 3)), fmt="%.8f")
    err = capsys.readouterr().err
    assert "11 light intensities for 12 images" in err


def test_cli_chrome_calibration_on_uw(shared_data, tmp_path):
    uw = shared_data / "photometric_stereo" / "uw_psm"
    out = tmp_path / "gray"
    args = ["ps", str(uw / "gray"), "--out", str(out), "--calibrate-lights", str(uw / "chrome")]
    assert main([*args, "--reference", "sphere", "--downsample", "4"]) == 0
    r = json.loads((out / "report.json").read_text())
    assert r["lights"] == "chrome_sphere" and r["reference"] == "fitted_sphere"
    assert r["light_calibration"]["mean_error_vs_capture_lights_deg"] < 4.0
    assert r["mean_angular_error_deg"] < 7.0

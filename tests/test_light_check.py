"""A job that names its model keeps ``auto``'s light only where that model predicts the
training photos held out in turn no worse under it than under the stated flash
(:mod:`jaxrefl.svbrdf._light_check`)."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxrefl import svbrdf
from jaxrefl.svbrdf import _job
from jaxrefl.svbrdf._light_check import check_light

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import capture_family as cf

SIZE, HALF = 16, 128  # the compiled shape of tests/test_light.py
TILE = 256


def _capture(offset: float):
    m = next(x for x in cf.FAMILY if x.name == "grey_gloss")
    return cf.render_member(dataclasses.replace(m, size=SIZE, photos=9, flash_offset_cm=offset))


def _wrong_auto(cap) -> svbrdf.LightEstimate:
    """An ``auto`` estimate that moved the flash 2.5 cm from where it was (as a score under a
    shared width can, where that width's misfit is what the move explains)."""
    return svbrdf.LightEstimate(
        "offset",
        "auto",
        np.array([-2.5, 0.5, 0.0]),
        np.ones(cap.n_photos),
        cv_rmse={"fixed": 0.1, "offset": 0.09, "offset+gains": 0.095},
        why="offset beats fixed",
        prior=svbrdf.gain_prior(cap),
    )


@pytest.fixture(scope="module")
def at_lens():
    return _capture(0.0).capture()


def test_named_model_vetoes_a_light_that_worsens_it_and_keeps_one_that_helps(at_lens):
    job = svbrdf.FitJob(model="ggx", tile_pixels=TILE)
    wrong = _wrong_auto(at_lens)
    out = check_light(at_lens, wrong, job)
    assert out.mode == "fixed" and out.asked == "auto"
    assert out.model_cv_rmse["offset"] > out.model_cv_rmse["fixed"]
    assert "the stated light instead" in out.why and "ggx" in out.why
    assert out.cv_rmse == wrong.cv_rmse
    assert out.as_dict()["model_cv_rmse"] == out.model_cv_rmse
    # the flash truly 1 cm from the lens: its estimate helps ggx, and is kept
    cap = _capture(1.0).capture()
    est = dataclasses.replace(
        svbrdf.estimate_light(cap, "offset", svbrdf.LightOptions(n_pixels=HALF)), asked="auto"
    )
    kept = check_light(cap, est, job)
    assert kept.mode == "offset" and kept.offset_cm is est.offset_cm
    assert kept.model_cv_rmse["offset"] <= kept.model_cv_rmse["fixed"]
    assert "kept by ggx" in kept.why
    # nothing to check: auto's model (scored under the light kept), a light asked by name
    for other in (dataclasses.replace(job, model="auto"), job):
        asked = other.model == "auto"
        e = wrong if asked else dataclasses.replace(wrong, asked="offset")
        assert check_light(at_lens, e, other) is e


def test_fit_capture_with_a_named_model_applies_the_checked_light(at_lens, monkeypatch):
    """fit_capture checks auto's light with the named model before fitting: where auto's
    estimate makes the model predict held-out photos worse, the fit is the fixed light's."""
    job = svbrdf.FitJob(model="ggx", tile_pixels=TILE, holdout=(4,))
    fixed = svbrdf.fit_capture(at_lens, dataclasses.replace(job, light="fixed"))
    monkeypatch.setattr(_job, "estimate_light", lambda cap, *a, **k: _wrong_auto(cap))
    fit = svbrdf.fit_capture(at_lens, job)
    assert fit.light.mode == "fixed" and fit.report["light"]["model_cv_rmse"]
    assert fit.report["heldout_rmse"] == pytest.approx(fixed.report["heldout_rmse"], rel=1e-6)

"""The uncertainty map under an estimated flash (``FitJob.light``): the posterior sees the
light the fit estimated, the report says which, and ``jaxrefl sample --light`` asks for it."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxrefl import fit, svbrdf
from jaxrefl import posterior as jp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import capture_family as cf

SIZE = 10


@pytest.fixture(scope="module")
def offset_capture():
    m = next(x for x in cf.FAMILY if x.name == "grey_gloss")
    return cf.render_member(dataclasses.replace(m, size=SIZE, flash_offset_cm=1.0))


def test_map_is_sampled_under_the_fit_light(offset_capture):
    jax.config.update("jax_enable_x64", True)
    cap = offset_capture.capture()  # the files' light: at the lens
    job = svbrdf.FitJob(model="lambert", config=fit.FitConfig(dtype=np.float64), light="offset")
    res = svbrdf.uncertainty_maps(cap, job, jp.AdaptiveOptions(mcmc="none"))
    light = res.fit.light
    assert light is not None and light.mode == "offset"
    rep = res.report()
    assert rep["light"]["mode"] == "offset"
    assert rep["light"]["offset_cm"] == pytest.approx(list(light.offset_cm))
    # the estimate moved the flash away from the lens, towards its true place
    true_off = (offset_capture.light_pos - offset_capture.camera_pos)[0]
    assert np.linalg.norm(light.offset_cm[:2] - true_off[:2]) < 0.5 * np.linalg.norm(true_off)
    # the posterior's data are the estimated light's, not the stated light's
    want = svbrdf.pixel_block(light.apply(cap), 0, SIZE * SIZE, dtype=np.float64)
    stated = svbrdf.pixel_block(cap, 0, SIZE * SIZE, dtype=np.float64)
    np.testing.assert_array_equal(np.asarray(res.data.wi), np.asarray(want.wi))
    np.testing.assert_array_equal(np.asarray(res.data.scale), np.asarray(want.scale))
    assert np.max(np.abs(np.asarray(res.data.wi) - np.asarray(stated.wi))) > 1e-3
    # a fixed light leaves the data as the capture states it
    fixed = svbrdf.uncertainty_maps(
        cap, dataclasses.replace(job, light="fixed"), jp.AdaptiveOptions(mcmc="none")
    )
    assert fixed.report()["light"]["mode"] == "fixed"
    np.testing.assert_array_equal(np.asarray(fixed.data.wi), np.asarray(stated.wi))

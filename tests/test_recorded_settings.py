"""Every setting that changes a result is a field of an option object, and what ran records
it: a capture fit's job (its report and the tiles' resume manifest) and a measured fit's
report settings."""

from __future__ import annotations

import dataclasses

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


def _lambert_material(k: int = 64) -> MeasuredBRDF:
    rng = np.random.default_rng(0)

    def hemi():
        u = rng.uniform(0.05, 1.0, k)
        phi = rng.uniform(0.0, 2 * np.pi, k)
        s = np.sqrt(1 - u * u)
        return np.stack([s * np.cos(phi), s * np.sin(phi), u], -1)

    values = np.full((k, 3), 0.5 / np.pi) * np.array([1.0, 0.8, 0.6])
    return MeasuredBRDF(hemi(), hemi(), values, ("R", "G", "B"), name="matte")


def test_every_measured_option_is_in_the_report_settings():
    m = _lambert_material()
    opts = jm.MeasuredOptions(max_theta_deg=70.0, cosine=False, retry_float64=False)
    rep = jm.fit_brdf(m, ["lambert"], options=opts, timing=False, starts=None)
    fields = {f.name for f in dataclasses.fields(jm.MeasuredOptions)}
    assert {k: rep.settings[k] for k in fields} == {
        "max_theta_deg": 70.0,
        "cosine": False,
        "retry_float64": False,
    }
    # The angle limit is the one applied: every sample kept is within it.
    cos_lim = np.cos(np.radians(70.0))
    assert np.all(rep.measured.wi[:, 2] >= cos_lim) and np.all(rep.measured.wo[:, 2] >= cos_lim)
    assert len(rep.measured) < len(m)
    with pytest.raises(ValueError, match="max_theta_deg in \\(0, 90\\]"):
        jm.MeasuredOptions(max_theta_deg=95.0)
    with pytest.raises(ValueError, match="cosine True or False"):
        jm.MeasuredOptions(cosine=1)

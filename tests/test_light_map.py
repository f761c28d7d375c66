"""Which light term an uncertainty map carries (:mod:`jaxrefl.svbrdf._light_map`): where
``auto`` kept the stated light after scoring an estimate, the lens-position spread; where
the user stated the light (``FitJob.light="fixed"``), none; and the term's size follows
the covariance it is drawn from."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxrefl import fit, svbrdf
from jaxrefl import posterior as jp
from jaxrefl.svbrdf import _light, _light_map
from jaxrefl.svbrdf._light import fixed_light
from jaxrefl.svbrdf._uncertainty import fit_theta

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import capture_family as cfam

SIZE = 8


@pytest.fixture(scope="module")
def stated_map():
    """A small capture whose true flash is 1 cm from the lens, its files saying it is at
    the lens, mapped with the light the user stated (``fixed``): the map, the capture and
    the ``offset`` estimate of it."""
    jax.config.update("jax_enable_x64", True)
    m = next(x for x in cfam.FAMILY if x.name == "grey_gloss")
    cap = cfam.render_member(dataclasses.replace(m, size=SIZE, flash_offset_cm=1.0)).capture()
    job = svbrdf.FitJob(model="lambert", config=fit.FitConfig(dtype=np.float64), light="fixed")
    res = svbrdf.uncertainty_maps(cap, job, jp.AdaptiveOptions(mcmc="none"))
    offset = svbrdf.estimate_light(cap, "offset", svbrdf.LightOptions.of_job(job))
    return res, cap, offset


def _kept_fixed(res, cap):
    """``res``'s fit as ``auto`` leaves it when it scores the candidates and keeps fixed."""
    kept = dataclasses.replace(
        fixed_light(cap, "auto", "offset does not beat fixed"),
        cv_rmse={"fixed": 0.02, "offset": 0.02, "offset+gains": 0.02},
    )
    return dataclasses.replace(res.fit, light=kept)


def _spread(cf, res, cap, **kw):
    theta = fit_theta(res.fit, res.posterior.space)
    return _light_map.light_spread(cf, res.posterior, res.data, cap, theta, **kw)


def test_user_stated_light_carries_no_term(stated_map):
    res, cap, _offset = stated_map
    assert res.fit.light.asked == "fixed"
    assert res.light_std is None
    assert res.report()["light"]["map_term"] == "none"
    assert _light_map.map_term(res.fit.light) == "none"
    assert _spread(res.fit, res, cap) is None
    # auto's fixed without a score (directional lights, too few photos): nothing either
    bare = dataclasses.replace(res.fit, light=fixed_light(cap, "auto", "no flash to place"))
    assert _light_map.map_term(bare.light) == "none"


def test_fixed_kept_by_auto_carries_the_lens_position_spread(stated_map):
    res, cap, offset = stated_map
    cf = _kept_fixed(res, cap)
    assert _light_map.map_term(cf.light) == "fixed: lens-position spread"
    # the estimate this capture's photos give lies well away from the lens
    assert np.linalg.norm(offset.offset_cm[:2]) > 0.5
    var = _spread(cf, res, cap, n_draws=8)
    assert var is not None and var.shape == (SIZE * SIZE, 3)
    assert np.nanmedian(np.sqrt(var)) > 1e-3
    # the map's intervals widen by it: std in quadrature, the report names the term
    umap, light_std = _light_map.widen_for_light(
        res.map, var, res.posterior.space.lower, res.posterior.space.upper
    )
    wide = dataclasses.replace(res, fit=cf, map=umap, light_std=light_std)
    assert wide.report()["light"]["map_term"] == "fixed: lens-position spread"
    np.testing.assert_allclose(
        umap.std[:, :3] ** 2, res.map.std[:, :3] ** 2 + light_std**2, rtol=1e-9, equal_nan=True
    )
    assert np.all((umap.q95 - umap.q05)[:, :3] >= (res.map.q95 - res.map.q05)[:, :3] - 1e-12)


def test_term_size_follows_the_covariance(stated_map, monkeypatch):
    """Four times the covariance doubles the light's std, for the lens-position spread
    (offset estimate placed at the lens: its mixture is then N(0, C) and the lens) and for
    an estimate's term."""
    res, cap, offset = stated_map
    cf = _kept_fixed(res, cap)

    def stds(scale, term_cf, lens):
        at_lens = dataclasses.replace(offset, offset_cm=np.zeros(3), cov=scale * offset.cov)
        monkeypatch.setattr(_light_map, "estimate_light", lambda *a, **k: at_lens)
        if not lens:
            term_cf = dataclasses.replace(term_cf, light=at_lens)
        return np.sqrt(_spread(term_cf, res, cap, n_draws=8))

    for lens in (True, False):
        one, four = stds(1.0, cf, lens), stds(4.0, cf, lens)
        ok = np.isfinite(one) & (one > 1e-12)
        assert ok.sum() > one.size // 2
        np.testing.assert_allclose(four[ok] / one[ok], 2.0, rtol=0.05)


def test_lens_spread_reuses_autos_problem(stated_map, monkeypatch):
    """Where ``auto`` scored the light (its problem kept on the light it returns), the map's
    lens-position spread draws from the ``offset`` estimate of that problem: no second
    estimate, the same term as the one computed afresh, the estimate computed once."""
    res, cap, _offset = stated_map
    job = res.fit.job
    scored = svbrdf.estimate_light(cap, "auto", svbrdf.LightOptions.of_job(job))
    source = scored.offset_source
    assert source is not None and source.serves(cap, job.holdout, job.alpha_min)
    assert not source.serves(cap, (0,), job.alpha_min)
    kept = dataclasses.replace(
        fixed_light(cap, "auto", "the stated light instead"),
        cv_rmse=scored.cv_rmse,
        offset_source=source,
    )
    cf = dataclasses.replace(res.fit, light=kept)
    afresh = _spread(_kept_fixed(res, cap), res, cap, n_draws=8)
    finals = []
    real_final = _light._final
    monkeypatch.setattr(
        _light, "_final", lambda *a, **k: finals.append(a[1]) or real_final(*a, **k)
    )

    def refuse(*_a, **_k):
        raise AssertionError("the map estimated the light again")

    monkeypatch.setattr(_light_map, "estimate_light", refuse)
    first = _spread(cf, res, cap, n_draws=8)
    again = _spread(cf, res, cap, n_draws=8)
    assert len(finals) <= 1  # computed on first use (or by auto, where it kept offset), then kept
    np.testing.assert_allclose(first, afresh, rtol=1e-10, atol=1e-15, equal_nan=True)
    np.testing.assert_array_equal(first, again)
    # a fit with other held-out photos does not take it
    other = dataclasses.replace(cf, job=dataclasses.replace(job, holdout=(0,)))
    with pytest.raises(AssertionError, match="estimated the light again"):
        _light_map._lens_estimate(other, cap)

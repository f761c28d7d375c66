"""The light's reported covariance (:mod:`jaxrefl.svbrdf._light_cov`): near the Laplace's on a
capture the model describes, widened to the spread of the leave-one-photo-out estimates on one
it does not (each photo's flash beam tilted its own way, which no offset explains)."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import svbrdf
from jaxrefl.svbrdf import _light_cov, _light_problem

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import capture_family as cf

SIZE, HALF = 16, 128  # the compiled shape of tests/test_light.py
HALF_OPTIONS = svbrdf.LightOptions(n_pixels=HALF)


@pytest.fixture(scope="module")
def rendered() -> cf.RenderedMember:
    m = next(x for x in cf.FAMILY if x.name == "grey_gloss")
    return cf.render_member(dataclasses.replace(m, size=SIZE, photos=9, flash_offset_cm=1.0))


def _beam_tilted(r: cf.RenderedMember, tilt: float) -> cf.RenderedMember:
    """Each photo's radiance times 1 + tilt (u_k . x), x in units of the side: a flash beam
    brighter towards a direction u_k of its own (a photo-level misfit the model has no term
    for)."""
    k = r.radiance.shape[0]
    t = (np.arange(SIZE) + 0.5) / SIZE - 0.5
    x, y = np.meshgrid(t, -t)
    ang = np.random.default_rng(7).uniform(0, 2 * np.pi, k)
    field = 1.0 + tilt * (np.cos(ang)[:, None, None] * x + np.sin(ang)[:, None, None] * y)
    rad = r.radiance * field[..., None]
    return dataclasses.replace(r, radiance=rad.astype(r.radiance.dtype)).with_noise(11)


def _jackknife_se(cap) -> np.ndarray:
    """The leave-one-photo-out jackknife's standard error of the offset's x and y."""
    offs = np.stack(
        [
            svbrdf.estimate_light(
                cap, "offset", svbrdf.LightOptions(holdout=(i,), n_pixels=HALF)
            ).offset_cm[:2]
            for i in range(cap.n_photos)
        ]
    )
    k = offs.shape[0]
    return np.sqrt((k - 1) / k * np.sum((offs - offs.mean(0)) ** 2, 0))


def test_reported_std_follows_the_photos_spread_where_the_model_misses(rendered):
    lap, rep = [], []
    for seed in range(11, 16):
        good = svbrdf.estimate_light(rendered.with_noise(seed).capture(), "offset", HALF_OPTIONS)
        lap.append(np.sqrt(np.diag(good.cov_laplace)[:2]))
        rep.append(good.offset_std_cm[:2])
    ratio = np.asarray(rep) / np.asarray(lap)
    # never narrower than the Laplace; where the model holds, near it on average over noise
    # draws (one draw's jackknife variance from 9 photos is noisy, about 50% relative, and
    # floored at the Laplace, so its mean lies above the Laplace's by a fraction of that)
    assert np.all(ratio >= 1.0 - 1e-9), ratio
    assert np.all(ratio.mean(0) < 1.75), ratio
    d = good.as_dict()
    assert d["offset_std_cm_laplace"][:2] == pytest.approx(list(lap[-1]))
    assert d["covariance"] == _light_cov.COVARIANCE

    bad_cap = _beam_tilted(rendered, 0.2).capture()
    bad = svbrdf.estimate_light(bad_cap, "offset", HALF_OPTIONS)
    jack = _jackknife_se(bad_cap)
    lap_bad = np.sqrt(np.diag(bad.cov_laplace)[:2])
    # the Laplace misses the photos' disagreement by a wide margin, the reported std does not
    assert np.all(lap_bad < 0.4 * jack), (lap_bad, jack)
    assert np.all(bad.offset_std_cm[:2] > 0.6 * jack), (bad.offset_std_cm, jack)
    assert np.all(bad.offset_std_cm[:2] < 2.0 * jack), (bad.offset_std_cm, jack)
    # the draws the maps' light term propagates come from the reported covariance
    xs = np.stack([o for o, _g in svbrdf.light_draws(bad, 2000, seed=1)])[:, :2]
    np.testing.assert_allclose(xs.std(0), bad.offset_std_cm[:2], rtol=0.1)


def test_widen_keeps_the_laplace_where_wider_and_the_gains_law_given_the_offset():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((5, 5))
    lap = a @ a.T + 0.5 * np.eye(5)
    # a spread narrower than the Laplace in every direction: the Laplace stands
    np.testing.assert_allclose(_light_cov.widen(lap, 0.5 * lap[:2, :2], 2), lap, atol=1e-12)
    # a wider one: the offset's block becomes it, the gains keep their regression on the
    # offset and their conditional covariance
    wide = 9.0 * lap[:2, :2] + 0.1 * np.eye(2)
    cov = _light_cov.widen(lap, wide, 2)
    np.testing.assert_allclose(cov[:2, :2], wide, rtol=1e-10)
    b_lap = np.linalg.solve(lap[:2, :2], lap[:2, 2:])
    np.testing.assert_allclose(np.linalg.solve(cov[:2, :2], cov[:2, 2:]), b_lap, atol=1e-10)

    def cond(c):
        return c[2:, 2:] - c[2:, :2] @ np.linalg.solve(c[:2, :2], c[:2, 2:])

    np.testing.assert_allclose(cond(cov), cond(lap), atol=1e-10)
    assert np.all(np.linalg.eigvalsh(cov - lap) > -1e-10)
    # only one direction wider: widened along it alone
    vals, vecs = np.linalg.eigh(lap[:2, :2])
    one = lap[:2, :2] + 4.0 * vals[0] * np.outer(vecs[:, 0], vecs[:, 0])
    got = _light_cov.widen(lap, one, 2)[:2, :2]
    np.testing.assert_allclose(got, one, rtol=1e-10)


def test_jackknife_folds_are_the_re_estimates_without_each_photo(rendered):
    """Each jackknife fold is the optimum of the profiled cost without its photo, as a full
    re-solve finds it: its steps use the cost's own gradient, not the projected one, which
    vanishes short of that optimum where the pixels' widths are off their exact stationary
    point (on this capture, by about a Laplace std)."""
    cap = _beam_tilted(rendered, 0.2).capture()
    both = [0, 1]
    with jax.enable_x64(True):
        problem = _light_problem.light_problem(cap, np.ones(cap.n_photos, bool), n_pixels=HALF)
        theta = problem.solve("offset", both, problem.unit_weights(both))[0]
        weights, _noise = problem.noise_weights(theta, "offset", both)
        theta, _r, jac, _it = problem.solve("offset", both, weights, theta0=theta)
        rc = _light_cov.robust_cov(problem, "offset", theta, jac, weights, 2)
        full = []
        for k in range(cap.n_photos):
            drop = jnp.asarray(np.arange(cap.n_photos) != k, jnp.float64)[None, :, None]
            w_k = [w * drop for w in weights]
            full.append(problem.solve("offset", both, w_k, theta0=theta)[0][:2])
    lap = np.sqrt(np.diag(rc.laplace)[:2])
    err = np.abs(rc.folds - np.asarray(full)) / lap
    assert rc.folds.shape == (cap.n_photos, 2)
    assert np.all(err < 0.1), err

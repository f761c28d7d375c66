"""Capture planning for a flash capture (jaxrefl.svbrdf._plan): the Fisher information of a
new photo against finite differences of its log-likelihood (uncensored and censored), the
predictive variance with a shared parameter against the inverse of the joint precision, a
highlight on the sample against one beside it (both criteria), censoring at saturation, the
fit's estimated flash moving the candidates', and ``jaxrefl fit --photos`` followed by
``jaxrefl plan`` writing plan.json."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import log_ndtr

from jaxrefl import svbrdf
from jaxrefl.cli import main
from jaxrefl.demo import demo_scene, photograph_maps
from jaxrefl.svbrdf._plan import CRITERIA

MODEL, SPACE = svbrdf.capture_model("ggx")
SIZE = 8
SIGMA = 0.002


# ----------------------------------------------------------------- Fisher information
def _pixel_prediction():
    """(theta (P,), y(theta) (C,)) of one pixel under one oblique flash photo, float64."""
    theta = SPACE.from_natural(
        {"albedo": np.array([0.3, 0.5, 0.2]), "specular": np.array([0.08]), "alpha": np.array(0.1)},
        dtype=jnp.float64,
    )
    wi = jnp.asarray([[0.2, 0.1, 0.97]]) / jnp.linalg.norm(jnp.asarray([0.2, 0.1, 0.97]))
    scale = 2.0

    def y(t):
        return MODEL.eval(SPACE.to_natural(t[None]), wi, wi)[0] * scale

    return theta, y


def _loglik(mu, obs, sd, sat):
    """log p(obs | mu) of normal observations (any shape) recorded censored at ``sat``
    (obs >= sat: the censored outcome)."""
    censored = log_ndtr((mu - sat) / sd)
    plain = -0.5 * ((obs - mu) / sd) ** 2 - np.log(sd * np.sqrt(2 * np.pi))
    return np.where(obs >= sat, censored, plain)


def test_fisher_information_matches_finite_differences_of_the_log_likelihood():
    """Uncensored: minus the finite-difference Hessian of the log-likelihood at y = mean is
    J^T J / var. Censored at a level inside the spread of two channels: the expected outer
    product of the finite-difference score (quadrature over the uncensored values, plus the
    censored outcome's probability) equals photo_information's Tobit information."""
    theta, y = _pixel_prediction()
    theta = np.asarray(theta)
    y_jit = jax.jit(y)

    def mu(t):
        return np.asarray(y_jit(jnp.asarray(t)))

    mean = mu(theta)
    jac = np.asarray(jax.jacfwd(y)(jnp.asarray(theta)))
    sd = 0.02 * mean
    var = sd * sd
    p = theta.size
    e = np.eye(p)

    # Uncensored: the central-difference Hessian of sum_c log p(mean_c | mu_c(theta)).
    h = 1e-4
    inf = np.full(3, np.inf)

    def ll(t):
        return float(np.sum(_loglik(mu(t), mean, sd, inf)))

    hess = np.array(
        [
            [
                (
                    ll(theta + h * (e[j] + e[k]))
                    - ll(theta + h * (e[j] - e[k]))
                    - ll(theta - h * (e[j] - e[k]))
                    + ll(theta - h * (e[j] + e[k]))
                )
                / (4 * h * h)
                for k in range(p)
            ]
            for j in range(p)
        ]
    )
    f_plain = svbrdf.photo_information(jac, mean, var)
    np.testing.assert_allclose(-hess, f_plain, rtol=2e-3, atol=1e-6 * np.abs(f_plain).max())

    # Censored: channels 0 and 1 saturate at 0.5 and 1 std above their means, channel 2 not.
    sat = mean + np.array([0.5, 1.0, np.inf]) * sd
    hs = 1e-5
    mu_plus = np.array([mu(theta + hs * e[j]) for j in range(p)])  # (P, C)
    mu_minus = np.array([mu(theta - hs * e[j]) for j in range(p)])
    nodes, weights = np.polynomial.legendre.leggauss(80)
    expected = np.zeros((p, p))
    for c in range(3):
        lo = mean[c] - 9 * sd[c]
        hi = min(sat[c], mean[c] + 9 * sd[c])
        ys = 0.5 * (hi - lo) * nodes + 0.5 * (hi + lo)
        ws = 0.5 * (hi - lo) * weights
        outcomes = np.append(ys, sat[c]) if np.isfinite(sat[c]) else ys
        # (P, outcomes): the finite-difference score of channel c's log-likelihood
        score = (
            _loglik(mu_plus[:, c, None], outcomes, sd[c], sat[c])
            - _loglik(mu_minus[:, c, None], outcomes, sd[c], sat[c])
        ) / (2 * hs)
        prob = ws * np.exp(-0.5 * ((ys - mean[c]) / sd[c]) ** 2) / (sd[c] * np.sqrt(2 * np.pi))
        if np.isfinite(sat[c]):
            prob = np.append(prob, np.exp(log_ndtr((mean[c] - sat[c]) / sd[c])))
        expected += (score * prob) @ score.T
    f_cens = svbrdf.photo_information(jac, mean, var, saturation_level=sat)
    np.testing.assert_allclose(f_cens, expected, rtol=5e-3, atol=1e-6 * np.abs(expected).max())
    # Censoring loses information: the uncensored minus the censored is positive semi-definite.
    assert np.linalg.eigvalsh(f_plain - f_cens).min() > -1e-9 * np.abs(f_plain).max()
    # albedo.R is seen by channel 0 alone, censored half a std above its mean: lambda ~ 0.92
    assert f_cens[0, 0] < 0.95 * f_plain[0, 0]


# ----------------------------------------------------------------- planning a capture
def _truth_fit(saturation_level=np.inf):
    """(CaptureFit at the true maps, capture): a narrow-lobe sample photographed by the demo
    rig; the plan is evaluated at the fit's optimum, here the truth."""
    scene = demo_scene(size=SIZE)
    rng = np.random.default_rng(0)
    truth = {
        "albedo": rng.uniform(0.1, 0.6, (SIZE, SIZE, 3)),
        "specular": np.full((SIZE, SIZE, 3), 0.06),
        "alpha": rng.uniform(0.03, 0.06, (SIZE, SIZE)),
    }
    cap = photograph_maps(scene, truth, SIGMA, rng)
    cap = dataclasses.replace(cap, saturation_level=saturation_level)
    theta = np.asarray(
        SPACE.from_natural(
            {k: v.reshape(SIZE * SIZE, *v.shape[2:]) for k, v in truth.items()},
            dtype=jnp.float64,
        )
    )
    fit = svbrdf.CaptureFit(
        maps={
            "status": np.zeros((SIZE, SIZE), np.uint32),
            "noise_std": np.full((SIZE, SIZE), SIGMA),
            "alpha": truth["alpha"],
        },
        report={},
        labels=SPACE.labels,
        theta=theta,
        job=svbrdf.FitJob(model="ggx"),
        alpha_min=1e-3,
        channels=3,
    )
    return fit, cap


# A camera (flash at the lens) whose highlight crosses the sample, and one whose highlight
# falls 30 cm beside it, both 24 cm up.
ON, OFF = [1.0, -1.0, 24.0], [30.0, 0.0, 24.0]


@pytest.fixture(scope="module")
def truth_fit():
    return _truth_fit()


@pytest.mark.parametrize("criterion", CRITERIA)
def test_highlight_beside_the_sample_scores_below_one_crossing_it(truth_fit, criterion):
    fit, cap = truth_fit
    options = svbrdf.PlanOptions(criterion=criterion)
    plan = svbrdf.plan_next(fit, cap, svbrdf.listed_candidates(cap, [ON, OFF]), options)
    rows = {tuple(r["position"]): r for r in plan.ranking()}
    on, off = rows[tuple(ON)], rows[tuple(OFF)]
    assert on["highlight_on_sample"] and not off["highlight_on_sample"]
    assert plan.best == 0 and plan.criterion == criterion
    assert on["gain"] > 2 * off["gain"] > 0
    assert 0 < on["variance_reduction"] < 1 and on["information"] > off["information"]
    assert on["share_informed"] > off["share_informed"]
    # No shared parameter in the per-pixel ggx model: the gain is the pixels'.
    assert plan.shared == () and np.all(plan.gain_shared == 0)
    assert plan.light == "fixed"


def test_predictive_variance_with_a_shared_parameter_matches_the_joint_inverse():
    """The block-arrow form (pixels' blocks, their coupling to one shared parameter, the
    Schur complement) against the dense joint precision inverted, scale_up 1 and 2: the
    sum over pixels and each pixel's own terms (the log_variance criterion's)."""
    from jaxrefl.svbrdf._plan_info import pixel_predictive_variance, predictive_variance

    rng = np.random.default_rng(1)
    n, p, s = 5, 3, 1
    q = p + s
    blocks = []
    for _ in range(n):
        x = rng.standard_normal((6, q))
        blocks.append(x.T @ x)
    prec = np.stack(blocks)
    g = rng.standard_normal((n, 4, q))
    moment = np.einsum("ncp,ncq->npq", g, g)
    tau = 0.3
    for scale_up in (1.0, 2.0):
        # The dense joint precision of scale_up copies of every pixel.
        copies = int(scale_up)
        size = n * copies * p + s
        joint = np.zeros((size, size))
        joint[-s:, -s:] = tau * np.eye(s)
        for c in range(copies):
            for i in range(n):
                o = (c * n + i) * p
                joint[o : o + p, o : o + p] = prec[i, :p, :p] + tau * np.eye(p)
                joint[o : o + p, -s:] = prec[i, :p, p:]
                joint[-s:, o : o + p] = prec[i, p:, :p]
                joint[-s:, -s:] += prec[i, p:, p:]
        cov = np.linalg.inv(joint)
        per_pixel = np.zeros((copies, n))
        for c in range(copies):
            for i in range(n):
                idx = [*range((c * n + i) * p, (c * n + i + 1) * p), *range(size - s, size)]
                per_pixel[c, i] = np.trace(cov[np.ix_(idx, idx)] @ moment[i])
        want = float(np.sum(per_pixel))
        # Each pixel's own terms (every copy of a pixel has the same).
        blocks_args = (prec[:, :p, :p] + tau * np.eye(p), prec[:, :p, p:], prec[:, p:, p:])
        got_px = pixel_predictive_variance(*blocks_args, moment, tau, scale_up)
        for c in range(copies):
            np.testing.assert_allclose(got_px, per_pixel[c], rtol=1e-10)
        got = predictive_variance(*blocks_args, moment, tau, scale_up)
        np.testing.assert_allclose(got, want, rtol=1e-10)


def test_the_fits_estimated_flash_moves_the_candidates_flash(truth_fit):
    """A fit whose report's light has an offset (the sample frame): stated candidates get
    it, placed ones keep theirs; the plan scores with the moved flash."""
    fit, cap = truth_fit
    offset = [1.5, -0.5, 0.2]
    light = {"mode": "offset", "asked": "offset", "frame": "sample", "offset_cm": offset}
    light["photo_gain"] = [1.0] * cap.n_photos
    moved = dataclasses.replace(fit, report={"light": light})
    cands = svbrdf.listed_candidates(cap, [ON, OFF])
    plan = svbrdf.plan_next(moved, cap, cands)
    assert plan.light == "offset"
    np.testing.assert_allclose(plan.candidates.light_pos, cands.light_pos + np.asarray(offset))
    # The same flash given as placed: the same scores.
    placed = svbrdf.listed_candidates(cap, [ON, OFF], cands.light_pos + np.asarray(offset))
    again = svbrdf.plan_next(moved, cap, placed)
    np.testing.assert_allclose(again.candidates.light_pos, placed.light_pos)
    np.testing.assert_allclose(again.gain, plan.gain, rtol=1e-9)
    # A fixed light leaves the stated flash where it is, and scores differ.
    fixed = svbrdf.plan_next(fit, cap, cands)
    np.testing.assert_allclose(fixed.candidates.light_pos, cands.light_pos)
    assert not np.allclose(fixed.gain, plan.gain, rtol=1e-6)


def test_censoring_lowers_the_gain_of_a_candidate_that_saturates(truth_fit):
    fit, cap = truth_fit
    cands = svbrdf.listed_candidates(cap, [ON, OFF])
    free = svbrdf.plan_next(fit, cap, cands, svbrdf.PlanOptions(censoring=False))
    # Saturation far above every prediction: censoring changes nothing.
    same = svbrdf.plan_next(fit, cap, cands)
    np.testing.assert_allclose(same.gain, free.gain, rtol=1e-9)
    # Saturation at a tenth of the brightest observation of the capture: the highlight of
    # ON saturates, OFF (diffuse only, below the level) does not.
    level = 0.1 * float(np.max(cap.images))
    fit_s, cap_s = fit, dataclasses.replace(cap, saturation_level=level)
    cens = svbrdf.plan_next(fit_s, cap_s, cands)
    assert cens.gain[0] < 0.9 * free.gain[0]
    assert cens.information[0] < 0.9 * free.information[0]
    # OFF's photo is recorded uncensored: its information is the uncensored one (its
    # variance share is not: the reference renderings include ON's, recorded saturated).
    np.testing.assert_allclose(cens.information[1], free.information[1], rtol=1e-6)


def test_recorded_slope_is_the_derivative_of_the_censored_mean():
    """Phi(b) - Phi(a) against central differences of the closed-form mean of a normal
    recorded censored at both levels (a Tobit observation)."""
    from scipy.stats import norm

    from jaxrefl.svbrdf._plan_info import recorded_slope

    def censored_mean(mu, sd, lo, hi):
        a, b = (lo - mu) / sd, (hi - mu) / sd
        inner = mu * (norm.cdf(b) - norm.cdf(a)) + sd * (norm.pdf(a) - norm.pdf(b))
        return lo * norm.cdf(a) + hi * norm.sf(b) + inner

    sd, lo, hi, h = 0.05, 0.0, 1.0, 1e-6
    for mu in (-0.1, 0.02, 0.5, 0.97, 1.2):
        want = (censored_mean(mu + h, sd, lo, hi) - censored_mean(mu - h, sd, lo, hi)) / (2 * h)
        np.testing.assert_allclose(recorded_slope(mu, sd, hi, lo), want, rtol=1e-6, atol=1e-9)
    assert recorded_slope(0.5, sd) == 1.0


def test_a_reference_recorded_saturated_has_no_variance_to_reduce(truth_fit):
    """The variance criterion scores renderings as the camera records them: a reference
    photo saturated everywhere is recorded the same whatever the parameters."""
    fit, cap = truth_fit
    cands = svbrdf.listed_candidates(cap, [ON, OFF])
    ref = svbrdf.listed_candidates(cap, [ON])
    # A level far below every pixel's predicted radiance in the reference photo.
    low = dataclasses.replace(cap, saturation_level=1e-9)
    cens = svbrdf.plan_next(fit, low, cands, reference=ref)
    free = svbrdf.plan_next(fit, low, cands, svbrdf.PlanOptions(censoring=False), reference=ref)
    assert np.all(free.variance_reduction > 0)
    np.testing.assert_array_equal(cens.variance_reduction, 0.0)


# ----------------------------------------------------------------- command line
def test_fit_photos_then_plan_writes_plan_json(tmp_path, capsys):
    """``jaxrefl fit --photos`` fits the subset (report.json records it); ``jaxrefl plan
    --candidates-from`` ranks the other photos, best first, with the documented keys."""
    demo, fit_dir, plan_dir = tmp_path / "demo", tmp_path / "fit", tmp_path / "plan"
    assert main(["demo", "--out", str(demo), "--size", str(SIZE), "--no-fit"]) == 0
    fit_args = ["fit", str(demo), "--out", str(fit_dir), "--model", "lambert", "--quiet"]
    assert main([*fit_args, "--photos", "0,3,5,6,8", "--no-previews", "--no-compile-cache"]) == 0
    report = json.loads((fit_dir / "report.json").read_text())
    assert report["capture"]["selected"] == [0, 3, 5, 6, 8]
    assert report["capture"]["photos"] == 5
    plan_args = ["plan", str(fit_dir), "--out", str(plan_dir), "--no-compile-cache"]
    assert main([*plan_args, "--candidates-from", str(demo), "--photos", "1,2,4,7"]) == 0
    doc = json.loads((plan_dir / "plan.json").read_text())
    ranking = doc["ranking"]
    assert sorted(r["photo"] for r in ranking) == [1, 2, 4, 7]
    for row in ranking:
        assert {"photo", "gain", "share_informed", "position", "highlight"} <= set(row)
        assert 0.0 <= row["share_informed"] <= 1.0
    gains = [r["gain"] for r in ranking]
    assert gains == sorted(gains, reverse=True) and gains[-1] > 0
    assert (plan_dir / "highlights.png").stat().st_size > 0
    assert (plan_dir / "positions.png").stat().st_size > 0
    out = capsys.readouterr().out
    assert f"photo {ranking[0]['photo']}" in out
    # Grid candidates: positions, no photo numbers.
    assert main(["plan", str(fit_dir), "--out", str(tmp_path / "grid"), "--no-compile-cache"]) == 0
    grid = json.loads((tmp_path / "grid" / "plan.json").read_text())
    assert grid["candidates"] == "grid" and len(grid["ranking"]) > 20
    assert all("photo" not in r and len(r["position"]) == 3 for r in grid["ranking"])

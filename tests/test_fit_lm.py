"""The lean batched Levenberg-Marquardt (jaxrefl/fit/_lm.py): the unrolled Cholesky against
LAPACK, conditioning, recovery of synthetic GGX + Lambert pixels in float64 and float32 from
the automatic start, and failures as values (masked and NaN pixels never touch their
neighbours)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from fit_zoo import make_problem, problem_zoo

import jaxrefl
from jaxrefl import fit
from jaxrefl.fit._linalg import cho_solve_unrolled, cholesky_unrolled
from jaxrefl.fit._status import equilibrated_condition

_GGX = jaxrefl.brdf.get("cook_torrance", distribution="ggx", diffuse="lambert")


@pytest.mark.parametrize("p", [1, 2, 3, 5, 7, 8])
def test_unrolled_cholesky_matches_lapack(p):
    rng = np.random.default_rng(p)
    j = rng.normal(size=(4, 3 * p, p))
    a = jnp.asarray(np.einsum("nmp,nmq->npq", j, j) + 1e-3 * np.eye(p))
    b = jnp.asarray(rng.normal(size=(4, p)))
    l, ok = cholesky_unrolled(a)
    assert np.all(ok)
    np.testing.assert_allclose(l, jnp.linalg.cholesky(a), rtol=1e-10, atol=1e-12)
    x = cho_solve_unrolled(l, b)
    np.testing.assert_allclose(jnp.einsum("npq,nq->np", a, x), b, rtol=1e-8, atol=1e-10)
    # not positive definite -> flagged, never NaN
    bad = a.at[:, p - 1, p - 1].set(-1.0)
    l_bad, ok_bad = cholesky_unrolled(bad)
    assert not np.any(ok_bad) and np.all(np.isfinite(l_bad))


def test_equilibrated_condition():
    assert float(equilibrated_condition(jnp.diag(jnp.asarray([1e-6, 1.0, 1e6])))) == 1.0
    j = jnp.asarray([[1.0, 2.0, 0.0], [1.0, 2.0 + 1e-9, 1.0], [0.0, 0.0, 1.0]])
    assert float(equilibrated_condition(j.T @ j)) > 1e12  # two nearly parallel columns
    z = jnp.asarray([[1.0, 0.0], [0.0, 0.0]])
    assert float(equilibrated_condition(z)) == np.inf  # a zero column


def _errors(result, truth):
    space = result.space
    t = space.from_natural({k: jnp.asarray(v) for k, v in truth.items()}, dtype=result.theta.dtype)
    x, xt = space.natural_vector(result.theta), space.natural_vector(t)
    return np.max(np.abs(np.asarray(x) / np.asarray(xt) - 1.0), axis=1)


def test_recovers_exact_pixels_float64():
    pr = problem_zoo()[0]  # GGX + Lambert, flash, exact data, float64
    r = fit.fit_pixels(pr.model, pr.data)
    err = _errors(r, pr.truth)
    assert r.theta.dtype == jnp.float64
    # every well-posed pixel to 1e-4 relative (measured: max 3e-8); all pixels converge
    assert np.all(err[pr.well_posed] < 1e-4), err[pr.well_posed].max()
    assert np.mean(err < 1e-4) >= 0.98
    assert r.status_counts()["CONVERGED"] == len(err)
    assert np.all(np.asarray(r.iterations) <= 40)


def test_recovers_exact_pixels_float32():
    m = jaxrefl.brdf.get("cook_torrance", distribution="ggx", diffuse="lambert")
    pr = make_problem("ggx32", m, n=64, seed=1, dtype=jnp.float32)
    r = fit.fit_pixels(m, pr.data)
    assert r.theta.dtype == jnp.float32 and r.params["alpha"].dtype == jnp.float32
    err = _errors(r, pr.truth)
    # measured on 256 pixels: median 4e-6, well-posed max 4e-5, 96% of all pixels < 1e-4
    assert np.median(err) < 1e-4
    assert np.all(err[pr.well_posed] < 1e-3), err[pr.well_posed].max()
    assert np.all(np.isin(np.asarray(r.status), [fit.Status.CONVERGED, fit.Status.MAX_ITERATIONS]))


def test_masked_and_nan_pixels_do_not_touch_neighbours():
    pr = problem_zoo()[0]
    d = pr.data
    clean = fit.fit_pixels(pr.model, d)
    obs = np.array(d.obs)
    weight = np.array(d.weight)
    weight[3] = 0.0  # pixel 3: no usable observation
    weight[4, :5] = 0.0  # pixel 4: 5 * 3 = 15 masked, 81 left
    obs[7] = np.nan  # pixel 7: every observation NaN (weights left at 1)
    obs[8, 2] = np.nan  # pixel 8: one direction NaN, the rest fine
    wi = np.array(d.wi)
    wi[9, 0] = np.inf  # pixel 9: one non-finite direction
    bad = fit.PixelData(
        jnp.asarray(obs),
        jnp.asarray(wi),
        jnp.asarray(wi),
        d.scale,
        jnp.asarray(weight),
        d.censored,
        d.colocated,  # same static flag as the clean batch: the compiled solver is reused
    )
    r = fit.fit_pixels(pr.model, bad)
    st = np.asarray(r.status)
    assert st[3] == fit.Status.MASKED and st[7] == fit.Status.NONFINITE_INPUT
    for i in (3, 7):
        assert np.all(np.isnan(np.asarray(r.theta[i]))) and np.isnan(float(r.cost[i]))
        assert np.all(np.isnan(np.asarray(r.params["alpha"][i])))
    assert int(r.n_used[3]) == 0 and int(r.n_used[4]) == 81 and int(r.n_used[8]) == 93
    assert not r.has_estimate[3] and r.has_estimate[4]
    # partially masked pixels are still fitted, exactly (the data are exact)
    err = _errors(r, pr.truth)
    for i in (4, 8, 9):
        if pr.well_posed[i]:
            assert err[i] < 1e-4
    # every other pixel: the same result as in the clean batch
    others = np.setdiff1d(np.arange(len(st)), [3, 4, 7, 8, 9])
    np.testing.assert_allclose(r.theta[others], clean.theta[others], rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(st[others], np.asarray(clean.status)[others])


def test_pure_state_functions_and_status_codes():
    m = jaxrefl.brdf.get("lambert")
    space = fit.ParamSpace(m, channels=1)
    res = fit.make_residual(m, space)
    k = 6
    d = fit.pixel_data(
        jnp.linspace(0.1, 0.2, k)[:, None],
        jnp.tile(jnp.asarray([0.0, 0.0, 1.0]), (k, 1)),
        scale=jnp.pi,
    )
    opts = fit.LMOptions(max_iters=25)
    state = fit.lm_init(res, jnp.asarray([2.0]), d, opts)
    step = jax.jit(lambda s: fit.lm_step(res, s, d, opts))
    costs = [float(state.cost)]
    for _ in range(25):
        state, info = step(state)
        costs.append(float(state.cost))
        assert info.pd
    assert np.all(np.diff(costs) <= 0.0)  # accepted steps only ever lower the cost
    assert bool(state.converged)
    # the least-squares albedo is the mean observation (pred = albedo); the stop test
    # (predicted cost reduction <= 1e-8 cost) leaves ~sqrt(1e-8) relative in the parameter
    np.testing.assert_allclose(space.natural_vector(state.theta), [0.15], rtol=1e-5)
    # a converged state is frozen
    again, info = step(state)
    assert not bool(info.accepted) and int(again.iterations) == int(state.iterations)
    np.testing.assert_array_equal(again.theta, state.theta)
    # lm_solve: same answer; a non-finite start is reported, not propagated
    theta, result = fit.lm_solve(res, jnp.asarray([2.0]), d, opts, space=space)
    np.testing.assert_allclose(theta, state.theta, rtol=1e-10)
    assert int(result.status) == fit.Status.CONVERGED
    _, result_nan = fit.lm_solve(res, jnp.asarray([jnp.nan]), d, opts)
    assert int(result_nan.status) == fit.Status.NONFINITE_INPUT and np.isnan(float(result_nan.cost))
    # a one-iteration budget from far away: MAX_ITERATIONS; fewer observations than P: MASKED
    _, r1 = fit.lm_solve(res, jnp.asarray([6.0]), d, fit.LMOptions(max_iters=1))
    assert int(r1.status) == fit.Status.MAX_ITERATIONS and int(r1.iterations) == 1
    _, r0 = fit.lm_solve(res, jnp.asarray([0.0]), d, opts, n_usable=jnp.asarray(0))
    assert int(r0.status) == fit.Status.MASKED
    assert fit.describe([0, 0, 4, 5, 9]) == {
        "CONVERGED": 2,
        "MAX_ITERATIONS": 0,
        "AT_BOUND": 0,
        "ILL_CONDITIONED": 0,
        "MASKED": 1,
        "NONFINITE_INPUT": 1,
        "UNKNOWN": 1,
    }
    assert set(fit.STATUS_MEANINGS) == set(fit.Status)


@pytest.fixture(scope="module")
def ggx_256():
    """256 noisy GGX pixels in float64 with a small parameter space (P = 3: grey albedo and
    F0, alpha), their residual and start, and the reference: lm_solve on each pixel alone
    (vmap), 25 steps. lm_solve reads only the step's options (max_iters, damping, tolerances,
    step cap, bound tolerance), none of batched_lm's batching fields (compact_*, chunk,
    host_*): one reference serves every batching compared with it below."""
    pr = make_problem("ggx_noisy_256", _GGX, n=256, noise=0.02, seed=7)
    space = fit.ParamSpace(pr.model, channels=3, grey=("albedo", "specular"))
    res = fit.make_residual(pr.model, space)
    theta0 = jnp.broadcast_to(space.from_natural({}, dtype=jnp.float64), (256, space.size))
    step = fit.LMOptions(max_iters=25)
    plain = jax.vmap(lambda t, d: fit.lm_solve(res, t, d, step, space=space))
    theta_ref, r_ref = plain(theta0, pr.data)
    return pr, space, res, theta0, theta_ref, r_ref


def test_compaction_stages_give_each_pixel_its_own_lm_solve(monkeypatch, ggx_256):
    """batched_lm's staged compaction (gather the unconverged pixels into ever smaller
    sub-batches) must not change any pixel's result: the same steps in the same order as
    lm_solve on that pixel alone, here against vmap(lm_solve) in float64."""
    # Blocks below _MIN_BLOCK pixels take one plain scan; this block of 256 must compact.
    monkeypatch.setattr(fit._lm, "_MIN_BLOCK", 0)
    # A small problem (P = 3) keeps the five compiled copies of the step cheap.
    pr, space, res, theta0, theta_ref, r_ref = ggx_256
    staged = fit.LMOptions(
        max_iters=25,
        compact_after=6,
        compact_stages=((9, 0.5), (13, 0.25)),
        chunk=256,
        host_loop=False,
    )
    theta, r = fit.batched_lm(res, theta0, pr.data, staged, space=space)
    it = np.asarray(r.iterations)
    # The stages were exercised: pixels stopped in each of them.
    assert np.any(it <= 6) and np.any((it > 9) & (it <= 13)) and np.any(it > 13), np.bincount(it)
    np.testing.assert_array_equal(it, np.asarray(r_ref.iterations))
    np.testing.assert_array_equal(np.asarray(r.status), np.asarray(r_ref.status))
    # Equal up to float64 rounding: XLA vectorises a sub-batch of another width differently
    # (remainder loops, fused multiply-adds), measured up to 1.2e-9 relative in theta.
    np.testing.assert_allclose(np.asarray(theta), np.asarray(theta_ref), rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(np.asarray(r.cost), np.asarray(r_ref.cost), rtol=1e-9)


@pytest.mark.parametrize("fused", [False, True])
def test_host_driven_steps_give_each_pixel_its_own_lm_solve(monkeypatch, fused, ggx_256):
    """batched_lm called outside a trace drives its steps from Python and gathers the
    unconverged pixels into ever fewer slots every host_round steps (``host_fused``: each
    round one program, and the last few pixels in one round of all their remaining steps):
    every pixel takes the steps lm_solve takes on it alone (float64), and the result equals
    the one-program path's; under jit the one-program path runs."""
    monkeypatch.setattr(fit._lm, "_MIN_BLOCK", 0)  # gather in a block of 256 as well
    pr, space, res, theta0, theta_ref, r_ref = ggx_256
    host = fit.LMOptions(max_iters=25, compact_after=2, host_round=3, host_fused=fused)
    gathered: list[int] = []  # live slots of each gathered round
    steps: list[int] = []  # host_fused: the steps each round may take
    real_gather, real_round = fit._lm_host._gather, fit._lm_host._round

    def recording(states, data, idx, live):
        if not isinstance(live, jax.core.Tracer):  # not inside a fused round's program
            gathered.append(int(np.sum(np.asarray(live))))
        return real_gather(states, data, idx, live)

    def recording_round(residual_fn, states, data, idx, n, options):
        live = int(np.sum(np.asarray(idx) < states.theta.shape[0]))
        if live:
            gathered.append(live)
            steps.append(int(n))
        return real_round(residual_fn, states, data, idx, n, options)

    monkeypatch.setattr(fit._lm_host, "_gather", recording)
    monkeypatch.setattr(fit._lm_host, "_round", recording_round)
    theta, r = fit.batched_lm(res, theta0, pr.data, host, space=space)
    it = np.asarray(r.iterations)
    # Pixels stopped early and late, and the late ones were gathered in fewer slots.
    assert gathered and min(gathered) < 64 and np.any(it <= 5) and np.any(it > 12), gathered
    if fused:  # rounds of host_round steps, then one round of every step left
        assert steps[:-1] and set(steps[:-1]) == {3} and steps[-1] > 3, steps
    np.testing.assert_array_equal(it, np.asarray(r_ref.iterations))
    np.testing.assert_array_equal(np.asarray(r.status), np.asarray(r_ref.status))
    np.testing.assert_allclose(np.asarray(theta), np.asarray(theta_ref), rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(np.asarray(r.cost), np.asarray(r_ref.cost), rtol=1e-9)
    # In blocks of 100 pixels (the last one padded): the same steps for every pixel.
    blocks = fit.LMOptions(max_iters=25, compact_after=2, host_round=3, chunk=100)
    theta_b, r_b = fit.batched_lm(res, theta0, pr.data, blocks, space=space)
    np.testing.assert_array_equal(np.asarray(r_b.iterations), it)
    np.testing.assert_allclose(np.asarray(theta_b), np.asarray(theta), rtol=1e-7, atol=1e-10)
    # Under a trace the same call runs as one program, with the same results.
    gathered.clear()
    theta_j, r_j = jax.jit(lambda t: fit.batched_lm(res, t, pr.data, host, space=space))(theta0)
    assert not gathered
    np.testing.assert_array_equal(np.asarray(r_j.iterations), it)
    np.testing.assert_allclose(np.asarray(theta_j), np.asarray(theta), rtol=1e-7, atol=1e-10)

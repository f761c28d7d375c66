"""The automatic start (:func:`jaxrefl.fit.initial_theta`) against a plain reference.

The reference is the variable projection written per pixel in the simplest way: for every
grid value the model is evaluated at zero colour scales and at each unit scale (basis
functions by differences), the box-constrained colour scales come from ``_box_ls`` and the
cost from the residual itself; grid values are the 12 coarse ones and 8 between the
neighbours of the best, ends included (the same points as the default's 12 + 6 interior
ones plus two repeats). The batched start must give the same fits: in float64, on a
synthetic capture (the demo's GGX + Lambert surface, nine flash photos, noisy), the LM from
either start ends at the same parameters within its tolerance and with the same statuses,
except where the new start reaches a lower cost.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from test_svbrdf import _demo_capture

from jaxrefl import fit
from jaxrefl.fit._affine import grid_values, linear_params
from jaxrefl.fit._box_ls import _box_ls
from jaxrefl.fit._init import _fit_weights, _inset, _natural_base
from jaxrefl.svbrdf._data import pixel_block
from jaxrefl.svbrdf._models import capture_model


def _reference_start(res, data, grid):
    """theta0 (N, P) by the per-pixel variable projection of the module docstring."""
    space, model = res.space, res.model
    lin = linear_params(model, space)
    assert lin == ("albedo", "specular")
    lo = np.array([space.lower[space.index(n).start] for n in lin])
    hi = np.array([space.upper[space.index(n).start] for n in lin])

    def one(d):
        dtype = d.obs.dtype
        c = d.obs.shape[-1]
        base = _natural_base(space, dtype)
        w, obs = _fit_weights(res, d)
        scale = jnp.where(w > 0, d.scale, 0.0)

        def project(g):
            def pred(x):
                p = dict(base)
                p["alpha"] = g
                p["albedo"], p["specular"] = jnp.full((c,), x[0]), jnp.full((c,), x[1])
                return model.eval(p, d.wi, d.wo) * scale

            f0 = pred(jnp.zeros(2, dtype))
            fs = [pred(jnp.eye(2, dtype=dtype)[j]) - f0 for j in range(2)]
            y = obs - f0
            a = jnp.stack(
                [
                    jnp.stack([jnp.sum(w * fs[i] * fs[j], 0) for j in range(2)], -1)
                    for i in range(2)
                ],
                -2,
            )
            b = jnp.stack([jnp.sum(w * fs[i] * y, 0) for i in range(2)], -1)
            x = _box_ls(a, b, lo, hi)  # (C, 2)
            r = y - x[None, :, 0] * fs[0] - x[None, :, 1] * fs[1]
            return x, jnp.sum(w * r * r)

        coarse = jnp.asarray(grid, dtype)
        x, cost = jax.vmap(project)(coarse)
        i = jnp.argmin(cost)
        g_lo, g_hi = coarse[jnp.maximum(i - 1, 0)], coarse[jnp.minimum(i + 1, len(grid) - 1)]
        t = jnp.linspace(0.0, 1.0, 8, dtype=dtype)
        fine = jnp.exp(jnp.log(g_lo) + t * (jnp.log(g_hi) - jnp.log(g_lo)))
        x2, cost2 = jax.vmap(project)(fine)
        vals = jnp.concatenate([coarse, fine])
        x, cost = jnp.concatenate([x, x2]), jnp.concatenate([cost, cost2])
        best = jnp.argmin(cost)
        nat = {n: _inset(space, n, x[best, :, j]) for j, n in enumerate(lin)}
        nat["alpha"] = vals[best]
        return space.from_natural(nat, dtype=dtype)

    return jax.jit(jax.vmap(one))(data)


def test_batched_start_fits_like_the_reference_start():
    with jax.enable_x64(True):
        cap, _ = _demo_capture(size=16, noise=3e-3)
        n = 16 * 16
        data = pixel_block(cap, 0, n, dtype=np.float64)
        model, space = capture_model("ggx", channels=3, alpha_min=0.01)
        res = fit.make_residual(model, space)
        theta_new = fit.initial_theta(res, data)
        theta_ref = _reference_start(res, data, grid_values("alpha", space, 12))
        # The same grid points: the same start wherever the cost has one clear minimum.
        same0 = np.all(np.abs(np.asarray(theta_new) - np.asarray(theta_ref)) < 1e-6, axis=1)
        assert same0.mean() >= 0.98, same0.mean()

        r_new = fit.fit_pixels(model, data, space=space, init=theta_new)
        r_ref = fit.fit_pixels(model, data, space=space, init=theta_ref)
        c_new, c_ref = np.asarray(r_new.cost), np.asarray(r_ref.cost)
        lower = c_new < c_ref * (1 - 1e-6)  # the new start found a better optimum
        keep = ~lower
        np.testing.assert_array_equal(
            np.asarray(r_new.status)[keep], np.asarray(r_ref.status)[keep]
        )
        # The LM's float64 tolerance (xtol 1e-8 on theta, ftol 1e-8 on the cost) leaves
        # parameters equal to a few 1e-5 along poorly determined directions.
        np.testing.assert_allclose(c_new[keep], c_ref[keep], rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(
            np.asarray(r_new.theta)[keep], np.asarray(r_ref.theta)[keep], rtol=0, atol=1e-3
        )
        assert lower.mean() <= 0.02, lower.mean()


def test_start_options_and_coarse_grid_only():
    model, space = capture_model("ggx", channels=3, alpha_min=0.01)
    res = fit.make_residual(model, space)
    cap, _ = _demo_capture(size=8, noise=1e-3)
    data = pixel_block(cap, 0, 64, dtype=np.float32)
    t0 = np.asarray(fit.initial_theta(res, data, refine=0))
    assert t0.shape == (64, space.size) and np.isfinite(t0).all()
    # Without the second grid alpha is one of the coarse values.
    alpha = np.asarray(space.to_natural(jnp.asarray(t0))["alpha"])
    coarse = grid_values("alpha", space, 12)
    assert np.min(np.abs(alpha[:, None] / coarse[None] - 1), axis=1).max() < 1e-5


def test_model_without_a_nonlinear_parameter_starts_at_its_optimum():
    """The pooled model (alpha fixed: affine in albedo and F0) with what makes its optimum
    more than one linear solve: a Huber loss, a Gaussian prior on F0 and saturated
    observations. The start is (close to) the LM's optimum: from it the LM ends where it
    ends from the model's defaults (float64: the same parameters within its tolerance, the
    same statuses), in fewer than half the steps."""
    with jax.enable_x64(True):
        cap, _ = _demo_capture(size=16, noise=3e-3)
        data = pixel_block(cap, 0, 16 * 16, dtype=np.float64)
        # The brightest 5% of observations saturated: one-sided rows, left out of a plain
        # linear solve.
        level = np.quantile(np.asarray(data.obs), 0.95)
        sat = np.asarray(data.obs) >= level
        data = eqx.tree_at(
            lambda d: (d.obs, d.censored),
            data,
            (jnp.minimum(data.obs, level), jnp.asarray(np.where(sat, 1, 0), data.censored.dtype)),
        )
        model, space = capture_model("pooled", channels=3, alpha=0.2)
        prior = fit.gaussian_prior(space, {f"specular.{c}": (0.05, 0.03) for c in ("R", "G", "B")})
        config = fit.FitConfig(
            solver=fit.LMOptions(max_iters=60),
            noise=fit.GaussianNoise(sigma=3e-3),
            loss=fit.Huber(),
        )
        res = fit.make_residual(model, space, config.noise, config.loss, prior)
        start = fit.initial_theta(res, data)
        r_start = fit.fit_pixels(model, data, config=config, space=space, init=start, prior=prior)
        r_ref = fit.fit_pixels(
            model, data, config=config, space=space, init="defaults", prior=prior
        )
        assert sat.any(axis=(1, 2)).mean() > 0.05  # the censored rows matter
        st, st_ref = np.asarray(r_start.status), np.asarray(r_ref.status)
        c_start, c_ref = np.asarray(r_start.cost), np.asarray(r_ref.cost)
        # A few pixels end at the iteration limit from either start: their saturated rows
        # switch on and off between steps (the one-sided residual has a kink). Elsewhere
        # both runs stop at the same optimum, with the same status.
        done = np.isin(st, (fit.Status.CONVERGED, fit.Status.AT_BOUND))
        both = done & np.isin(st_ref, (fit.Status.CONVERGED, fit.Status.AT_BOUND))
        assert both.mean() > 0.9 and done.mean() >= np.isin(st_ref, (0, 2)).mean()
        assert (st == fit.Status.CONVERGED).mean() > 0.3  # interior optima, not only bounds
        np.testing.assert_array_equal(st[both], st_ref[both])
        np.testing.assert_allclose(c_start[both], c_ref[both], rtol=1e-6)
        for name in ("albedo", "specular"):
            np.testing.assert_allclose(
                np.asarray(r_start.params[name])[both],
                np.asarray(r_ref.params[name])[both],
                rtol=0,
                atol=1e-4,
            )
        assert np.all(c_start <= c_ref * (1 + 1e-3))
        # The start itself is near the optimum: the reweighted passes bring it there, the LM
        # the rest of the way.
        nat = space.to_natural(start)
        err = np.zeros(int(both.sum()))
        for name in ("albedo", "specular"):
            e = np.abs(np.asarray(nat[name])[both] - np.asarray(r_ref.params[name])[both])
            err = np.maximum(err, np.max(e, axis=-1))
        # (Without the passes, the plain linear solve: median 2e-3, 90th percentile 8e-3.)
        assert np.median(err) < 1e-3 and np.quantile(err, 0.9) < 1e-2, np.quantile(err, [0.5, 0.9])
        it, it_ref = np.asarray(r_start.iterations), np.asarray(r_ref.iterations)
        # float64 tolerances (1e-8): the median pixel takes 8 steps from the start, 19 from
        # the defaults.
        assert np.median(it) <= 0.5 * np.median(it_ref), (np.median(it), np.median(it_ref))

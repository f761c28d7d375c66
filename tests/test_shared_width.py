"""The pooled model's Laplace uncertainty accounts for the shared width (svbrdf._width_laplace): the
per-pixel covariance plus each pixel's rank-one share equals the marginal of the joint
Gauss-Newton covariance of every pixel's parameters and log alpha, computed by brute force."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import fit
from jaxrefl.demo import demo_scene, photograph_maps
from jaxrefl.io import map_name
from jaxrefl.svbrdf import FitJob, fit_capture
from jaxrefl.svbrdf._data import pixel_block
from jaxrefl.svbrdf._tile_fitter import TileFitter

SIZE = 8  # 64 pixels: the joint problem has 64 x 6 + 1 unknowns


def _capture():
    """Diffuse albedo and coloured F0 well inside their ranges, one GGX width for all."""
    scene = demo_scene(size=SIZE)
    rng = np.random.default_rng(3)
    truth = {
        "albedo": rng.uniform(0.2, 0.6, (SIZE, SIZE, 3)),
        "specular": rng.uniform(0.2, 0.6, (SIZE, SIZE, 3)),
        "alpha": np.full((SIZE, SIZE), 0.15),
    }
    return photograph_maps(scene, truth, 0.003, rng)


@pytest.fixture(scope="module")
def pooled_fit():
    """The capture and its float64 pooled fit with photo 8 held out, in one tile of its 64
    pixels (the default 4096 rows would be mostly padding)."""
    cap = _capture()
    with jax.enable_x64(True):
        config = fit.FitConfig(dtype=np.float64)
        job = FitJob(
            model="pooled", holdout=(8,), light="fixed", config=config, tile_pixels=SIZE * SIZE
        )
        return cap, fit_capture(cap, job)


def test_width_share_equals_the_joint_laplace(pooled_fit):
    cap, cf = pooled_fit
    with jax.enable_x64(True):
        n = SIZE * SIZE
        fitter = TileFitter(cap, cf.job, pooled=cf.pooled)
        res, space = fitter.residual, fitter.space
        data = pixel_block(cap, 0, n, dtype=np.float64)
        train = jnp.asarray(fitter.train, jnp.float64)[None, :, None]
        data = eqx.tree_at(lambda d: d.weight, data, data.weight * train)
        theta = jnp.asarray(cf.theta, jnp.float64)
        assert np.all(cf.maps["laplace_flag"] & 0b110011 == 0)  # every covariance formed
        p = theta.shape[1]
        alpha = float(space.fixed["alpha"])

        def joint(z):
            th, log_a = z[:-1].reshape(n, p), z[-1]
            r = eqx.tree_at(lambda q: q.space.fixed["alpha"], res, jnp.exp(log_a))
            return jax.vmap(r)(th, data).reshape(-1)

        z = jnp.concatenate([theta.reshape(-1), jnp.log(jnp.asarray([alpha]))])
        jac = jax.jacfwd(joint)(z)
        cov = np.linalg.inv(np.asarray(jac.T @ jac))
        var_t = np.diagonal(cov)[:-1].reshape(n, p)
        per_pixel = np.stack(
            [
                np.diagonal(np.linalg.inv(np.asarray(jac[:, i * p : (i + 1) * p].T)
                                          @ np.asarray(jac[:, i * p : (i + 1) * p])))
                for i in range(n)
            ]
        )  # fmt: skip
        dn = np.abs(np.asarray(space.dnatural(theta)))
    want = dn * np.sqrt(var_t)
    got = np.stack([cf.maps[map_name(lab, "_std")].reshape(-1) for lab in space.labels], -1)
    np.testing.assert_allclose(got, want, rtol=1e-5)
    # The width's own std, by the delta method from log alpha.
    alpha_std = alpha * np.sqrt(cov[-1, -1])
    np.testing.assert_allclose(cf.maps["alpha_std"], alpha_std, rtol=1e-5)
    assert cf.report["pooled"]["width_laplace"]["alpha_std"] == pytest.approx(alpha_std, rel=1e-8)
    assert cf.report["pooled"]["width_laplace"]["pixels"] == n
    # The share is not negligible here (64 pixels share the width): the per-pixel covariance
    # alone understates some pixel's F0 std by more than 1%.
    alone = dn * np.sqrt(per_pixel)
    spec = [j for j, lab in enumerate(space.labels) if lab.startswith("specular.")]
    assert np.max(want[:, spec] / alone[:, spec]) > 1.01
    assert np.all(want >= alone * (1 - 1e-9))


def test_a_pixel_without_a_covariance_takes_no_part(pooled_fit):
    """width_terms leaves out a pixel whose per-pixel std is not finite (its curvature was
    not inverted): v NaN, s 0; the others are unchanged."""
    from jaxrefl.svbrdf._width_laplace import width_terms

    cap, cf = pooled_fit
    with jax.enable_x64(True):
        fitter = TileFitter(cap, cf.job, pooled=cf.pooled)
        n = SIZE * SIZE
        data = pixel_block(cap, 0, n, dtype=np.float64)
        train = jnp.asarray(fitter.train, jnp.float64)[None, :, None]
        data = eqx.tree_at(lambda d: d.weight, data, data.weight * train)
        theta = np.asarray(cf.theta, np.float64)
        std = np.ones_like(theta)
        v, s = width_terms(fitter.residual, theta, data, std)
        std[5, 2] = np.nan
        v2, s2 = width_terms(fitter.residual, theta, data, std)
    assert np.all(np.isfinite(v)) and np.all(s > 0)
    assert np.all(np.isnan(v2[5])) and s2[5] == 0.0
    keep = np.arange(n) != 5
    np.testing.assert_array_equal(v2[keep], v[keep])
    np.testing.assert_array_equal(s2[keep], s[keep])

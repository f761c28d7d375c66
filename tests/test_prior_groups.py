"""Population priors of a capture of two materials (svbrdf._prior_groups): the split of the
fitted F0 into materials, each material's core, the maps joined, and the map of a
two-material capture against its truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from jaxrefl import fit, svbrdf
from jaxrefl import posterior as jp
from jaxrefl.demo import demo_scene, photograph_maps
from jaxrefl.posterior._methods import MCMC_METHODS
from jaxrefl.svbrdf import _prior_groups
from jaxrefl.svbrdf._prior_groups import (
    CORE_SHARE,
    SEPARATION,
    _core,
    material_cores,
    merge_maps,
    two_materials,
)

COPPER = np.array([0.95, 0.64, 0.54])


def _two(rng, n_diel=600, n_metal=400, scatter=0.15):
    """Fitted F0 of a dielectric (grey 0.04, a share ``scatter`` of its fits spread along
    an unidentified lobe's ridge) and a copper."""
    diel = 0.04 + 0.01 * rng.standard_normal((n_diel, 1)) + 0.003 * rng.standard_normal((n_diel, 3))
    ridge = rng.random(n_diel) < scatter
    diel[ridge] = rng.uniform(0.0, 0.6, (int(ridge.sum()), 1))
    metal = COPPER + 0.03 * rng.standard_normal((n_metal, 3))
    return np.concatenate([diel, metal]), np.r_[np.zeros(n_diel, int), np.ones(n_metal, int)]


def test_two_clusters_are_split_and_labelled():
    f0, truth = _two(np.random.default_rng(0))
    label, info = two_materials(f0)
    assert label is not None, info
    assert info["separation"] > SEPARATION and info["bic_gain"] > 0
    assert "two materials" in info["why"]
    # components are numbered by the data; compare up to the swap
    agree = max(np.mean(label == truth), np.mean(label != truth))
    assert agree > 0.9
    metal = label[truth == 1][0]
    # the ridge's stray fits may join either; the material's core is the copper
    core = _core(f0, label == metal)
    np.testing.assert_allclose(np.mean(f0[core], 0), COPPER, atol=0.01)


@pytest.mark.parametrize("kind", ["skewed", "uniform", "tiny"])
def test_one_material_is_not_split(kind):
    """A skewed continuum of grey F0 (which beats one Gaussian by BIC), a uniform one, and
    a second cluster of 1% of the pixels stay one population."""
    rng = np.random.default_rng(1)
    if kind == "skewed":
        g = np.exp(rng.normal(np.log(0.1), 0.6, (3000, 1)))
        f0 = g + 0.005 * rng.standard_normal((3000, 3))
    elif kind == "uniform":
        f0 = np.repeat(rng.uniform(0.04, 0.5, (3000, 1)), 3, 1)
        f0 += 0.003 * rng.standard_normal(f0.shape)
    else:
        f0, _ = _two(rng, n_diel=2970, n_metal=30, scatter=0.0)
    label, info = two_materials(f0)
    assert label is None, info
    assert info["why"].startswith("one material")
    if kind == "tiny":
        assert "smaller component has" in info["why"]


def test_a_materials_core_leaves_out_the_ridge_scatter():
    f0, truth = _two(np.random.default_rng(2), scatter=0.2)
    diel = truth == 0
    core = _core(f0, diel)
    assert not np.any(core & ~diel)
    far = diel & (np.abs(f0[:, 0] - 0.04) > 0.1)
    assert far.sum() > 50 and not np.any(core & far)
    near = diel & np.all(np.abs(f0 - 0.04) < 0.015, axis=1)
    assert np.mean(core[near]) > 0.97


def test_a_material_whose_fits_do_not_agree_keeps_one_population(monkeypatch):
    """Each material's core is its tight cluster; where a material's core holds fewer than
    CORE_SHARE of its fits (they do not agree on its F0) the population is not split."""
    rng = np.random.default_rng(4)
    f0, truth = _two(rng, scatter=0.0)
    ok = np.ones(len(f0), bool)
    means = np.array([[0.04] * 3, COPPER])
    cores, why = material_cores(f0, truth, ok, means)
    assert cores is not None and why == ""
    assert np.mean(cores[0][truth == 0]) > 0.95 and not np.any(cores[1][truth == 0])

    def small_core(x, mask):  # a core of 40% of the material's pixels
        keep = mask & (np.cumsum(mask) % 5 < 2)
        return keep

    monkeypatch.setattr(_prior_groups, "_core", small_core)
    cores, why = material_cores(f0, truth, ok, means)
    assert cores is None and "not identified" in why
    assert f"fewer than {CORE_SHARE:.0%}" in why and "[0.04, 0.04, 0.04]" in why


def _map(n, d, offset, mcmc_local):
    """A small map whose values are ``offset`` + the pixel's local index; the pixels
    ``mcmc_local`` sampled (one draw each)."""
    v = offset + np.arange(n, dtype=np.float64)[:, None] * np.ones((1, d))
    method = np.zeros(n, np.uint8)
    method[mcmc_local] = MCMC_METHODS[0]
    m = len(mcmc_local)
    samples = jp.Samples(
        theta=np.full((m, 1, 1, d), offset),
        natural=np.full((m, 1, 1, d), offset),
        labels=("a", "b"),
        stats={"lp": np.zeros((m, 1, 1))},
        method="hmc",
        extra={"no_estimate": np.zeros(m, bool)},
        run_s=1.0,
    )
    return jp.UncertaintyMap(
        labels=("a", "b"),
        mean=v,
        std=v + 0.5,
        q05=v - 1,
        q95=v + 1,
        method=method,
        rhat=v[:, 0],
        ess_bulk=v[:, 0],
        ess_tail=v[:, 0],
        divergences=np.arange(n, dtype=np.int32),
        mcmc_pixels=np.asarray(mcmc_local, np.int64),
        samples=samples,
        laplace_std=v,
        rerun=np.zeros(n, bool),
        rhat_first=v[:, 0],
        timings={"mcmc_wall_s": 2.0, "mcmc_chunk_size": 8, "sampler": "gibbs"},
        reasons={"AT_BOUND": 1, "audit": 0},
    )


def test_merged_maps_put_each_pixel_back_in_its_place():
    masks = [np.array([1, 0, 0, 1, 1, 0], bool)]
    masks.append(~masks[0])
    a = _map(3, 2, 100.0, [0, 2])
    b = _map(3, 2, 200.0, [1])
    b.timings["sampler"] = "hmc"
    out = merge_maps([a, b], masks)
    np.testing.assert_array_equal(out.mean[:, 0], [100, 200, 201, 101, 102, 202])
    np.testing.assert_array_equal(out.divergences, [0, 0, 1, 1, 2, 2])
    # the sampled pixels' global indices, in the order of the joined draws
    np.testing.assert_array_equal(out.mcmc_pixels, [0, 4, 2])
    np.testing.assert_array_equal(out.samples.natural[:, 0, 0, 0], [100, 100, 200])
    assert np.all(np.isin(out.method[out.mcmc_pixels], MCMC_METHODS))
    assert out.timings["mcmc_wall_s"] == 4.0 and out.timings["mcmc_chunk_size"] == 8
    assert out.timings["sampler"] == "gibbs+hmc"
    assert out.reasons == {"AT_BOUND": 2, "audit": 0}


SIZE = 16


@pytest.fixture(scope="module")
def inlay():
    """A co-located capture of copper (left half) beside a grey dielectric, 1% noise:
    (capture, truth, metal (N,) bool)."""
    scene = demo_scene(size=SIZE)
    rng = np.random.default_rng(5)
    metal = np.zeros((SIZE, SIZE), bool)
    metal[:, : SIZE // 2] = True
    f0 = np.where(metal[..., None], COPPER, 0.04)
    truth = {
        "albedo": np.where(metal[..., None], 0.03, rng.uniform(0.2, 0.5, (SIZE, SIZE, 3))),
        "specular": f0 * rng.uniform(0.97, 1.03, (SIZE, SIZE, 1)),
        "alpha": np.where(metal, 0.15, rng.uniform(0.2, 0.5, (SIZE, SIZE))),
    }
    clean = photograph_maps(scene, truth)
    y = np.asarray(clean.images, np.float64)
    noisy = y + 0.01 * np.quantile(y, 0.99) * rng.standard_normal(y.shape)
    return dataclasses.replace(clean, images=noisy.astype(np.float32)), truth, metal.reshape(-1)


def test_a_two_material_map_samples_each_material_under_its_own_population(inlay, monkeypatch):
    """The map splits the population into the copper and the dielectric, and the
    dielectric's sampled pixels cover their F0 and alpha at the nominal rate where under
    the one population over both (whose mean F0 sits between them) they do not (about
    97 / 94% against 56 / 48% here)."""
    cap, truth, metal = inlay
    job = svbrdf.FitJob(model="ggx_rgb", light="fixed", config=fit.FitConfig(dtype=np.float64))
    opts = jp.AdaptiveOptions(mcmc="all")
    res = svbrdf.uncertainty_maps(cap, job, opts)
    split = res.prior_summary["split"]
    assert "two materials" in split["why"], split
    means = sorted(g["specular"]["mean"][0] for g in split["groups"])
    assert means[0] < 0.1 and means[1] > 0.8, means
    assert sum(g["map_pixels"] for g in split["groups"]) == SIZE * SIZE

    def cover(r):
        u, out = r.map, []
        for lab, t in (("specular.R", truth["specular"][..., 0]), ("alpha", truth["alpha"])):
            j = list(u.labels).index(lab)
            t = t.reshape(-1)
            hit = (u.q05[:, j] <= t) & (t <= u.q95[:, j])
            out.append(float(np.mean(hit[~metal])))
        return np.array(out)

    monkeypatch.setattr(
        _prior_groups, "population_groups", lambda cf, space: (None, {"why": "one (test)"})
    )
    one = svbrdf.uncertainty_maps(cap, job, opts)
    assert "split" in one.prior_summary and one.prior_summary["split"]["why"] == "one (test)"
    split_cover, one_cover = cover(res), cover(one)
    assert np.all(split_cover >= 0.85), (split_cover, one_cover)
    assert np.all(one_cover < split_cover - 0.2), (split_cover, one_cover)

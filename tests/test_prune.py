"""Pruning (jaxrefl.measured._prune) and leaving out unneeded pixels (._compact).

Synthetic pixels from two known simpler models (diffuse + GGX lobe, and diffuse alone) at
moderate noise (2% of each pixel's mean signal), pruned from a richer model with a second
lobe: the pruned model must be the true one in >= 90% of the trials, by BIC and by the
Laplace evidence. Every fit is shared between the criteria and groupings (``cache``).
"""

from __future__ import annotations

from collections import Counter

import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl.fit import FitConfig, LMOptions, Status, pixel_data
from jaxrefl.measured import Components, PruneOptions, prune
from jaxrefl.measured._compact import compact

TRIALS = 20  # per true model
K = 48
NOISE = 0.02
GLOSSY = Components(lobe="ggx", fresnel=False)
MATTE = GLOSSY.without("lobe")
RICH = Components(lobe="ggx", fresnel=False, second_lobe=True)
LM = LMOptions(unroll_max=0)


def _hemi(rng, shape, theta_max_deg=75.0):
    u = rng.uniform(np.cos(np.radians(theta_max_deg)), 1.0, shape)
    phi = rng.uniform(0.0, 2 * np.pi, shape)
    s = np.sqrt(1 - u * u)
    return np.stack([s * np.cos(phi), s * np.sin(phi), u], -1)


def _scene(seed: int = 0):
    """TRIALS glossy and TRIALS matte pixels, then 4 pixels a fit does not need."""
    rng = np.random.default_rng(seed)
    n = 2 * TRIALS
    wi, wo = _hemi(rng, (n, K)), _hemi(rng, (n, K))
    m = K // 3  # a third of the views near the mirror direction: the highlight is seen
    wo[:, :m] = wi[:, :m] * np.array([-1.0, -1.0, 1.0]) + 0.08 * rng.normal(size=(n, m, 3))
    wo[..., 2] = np.abs(wo[..., 2]) + 0.05
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    p = {
        "albedo": rng.uniform(0.2, 0.7, (n, 1, 1)),
        "specular": rng.uniform(0.04, 0.2, (n, 1, 1)),
        "alpha": np.exp(rng.uniform(np.log(0.08), np.log(0.4), (n, 1))),
    }
    f = np.array(GLOSSY.build().eval(p, wi, wo))
    lam = MATTE.build().eval({"albedo": p["albedo"][TRIALS:]}, wi[TRIALS:], wo[TRIALS:])
    f[TRIALS:] = np.asarray(lam)
    obs = f + NOISE * np.mean(f, axis=(1, 2), keepdims=True) * rng.normal(size=f.shape)
    # Four extra pixels: masked, shadowed (no light reaches it), saturated, no signal.
    extra = 4
    obs = np.concatenate([obs, np.repeat(obs[:1], extra, 0)])
    wi = np.concatenate([wi, np.repeat(wi[:1], extra, 0)])
    wo = np.concatenate([wo, np.repeat(wo[:1], extra, 0)])
    scale = np.ones_like(obs)
    censored = np.zeros(obs.shape, np.int8)
    mask = np.ones(obs.shape[0], bool)
    mask[n] = False
    scale[n + 1] = 0.0
    censored[n + 2] = 1
    obs[n + 3] = 0.0
    # One more observation column that no pixel can use (a light behind the surface).
    data = pixel_data(
        jnp.asarray(np.concatenate([obs, np.full_like(obs[:, :1], 0.1)], 1)),
        jnp.asarray(np.concatenate([wi, np.broadcast_to([0.0, 0.0, -1.0], wi[:, :1].shape)], 1)),
        jnp.asarray(np.concatenate([wo, np.broadcast_to([0.0, 0.0, 1.0], wo[:, :1].shape)], 1)),
        scale=jnp.asarray(np.concatenate([scale, np.ones_like(scale[:, :1])], 1)),
        censored=jnp.asarray(np.concatenate([censored, np.zeros_like(censored[:, :1])], 1)),
    )
    truth = np.array([GLOSSY.label] * TRIALS + [MATTE.label] * TRIALS + [""] * extra)
    return data, mask, truth


@pytest.fixture(scope="module")
def pruned():
    data, mask, truth = _scene()
    # P <= 5: the LAPACK Cholesky compiles faster than the unrolled one and costs nothing here.
    bic = prune(data, RICH, PruneOptions(criterion="bic"), mask=mask, config=FitConfig(solver=LM))
    ev = prune(data, RICH, PruneOptions(criterion="evidence"), mask=mask, cache=bic.fits)
    return data, mask, truth, bic, ev


def test_left_out_pixels_are_removed_and_counted(pruned):
    bic = pruned[3]
    c = bic.compacted.counts
    assert c == {
        "pixels_in": 2 * TRIALS + 4,
        "kept": 2 * TRIALS,
        "masked": 1,
        "shadowed": 1,
        "saturated": 1,
        "no_signal": 1,
        "columns_in": K + 1,
        "columns_kept": K,
    }
    # Removed, not down-weighted: the solver saw only the kept pixels and columns.
    for _, r, _ in bic.fits.values():
        assert r.theta.shape[0] == 2 * TRIALS
    assert bic.compacted.data.obs.shape == (2 * TRIALS, K, 1)
    full = bic.compacted.expand(bic.fits[RICH.label][1])
    st = np.asarray(full.status)
    assert np.all(st[2 * TRIALS :] == Status.MASKED)
    assert np.all(np.isnan(np.asarray(full.theta)[2 * TRIALS :]))
    assert np.all(st[: 2 * TRIALS] < Status.MASKED)
    assert "masked 1, shadowed 1, saturated 1, no_signal 1" in bic.summary()


def test_compact_reasons_and_options():
    data, mask, _ = _scene(1)
    out = compact(data, mask, min_obs=K + 2)  # more than any pixel has: all shadowed
    assert out.counts["kept"] == 0 and out.counts["shadowed"] == 2 * TRIALS + 3
    out = compact(data, saturation=0.0)  # every positive observation saturates
    assert out.counts["saturated"] >= 2 * TRIALS


@pytest.mark.parametrize("which", ["bic", "evidence"])
def test_pruned_model_is_the_true_one(pruned, which):
    _, _, truth, bic, ev = pruned
    rep = bic if which == "bic" else ev
    chosen = rep.chosen_per_pixel()
    fitted = truth != ""
    rate = float(np.mean(chosen[fitted] == truth[fitted]))
    print(f"{which}: pruned = true model in {rate:.3f} of {fitted.sum()} trials;", Counter(chosen))
    assert rate >= 0.9, Counter(zip(truth[fitted], chosen[fitted], strict=True))
    # The report says what was dropped and why (criterion before and after).
    g = rep.groups[0]
    assert g.dropped and g.dropped[0].component == "second_lobe"
    s = g.dropped[0]
    assert (s.after <= s.before) if which == "bic" else (s.after >= s.before)
    assert "removing second_lobe" in s.why


def test_per_cluster_pruning(pruned):
    """k-means on the fitted colours separates matte from glossy pixels; each cluster is
    pruned as a whole."""
    data, mask, truth, bic, _ = pruned
    kmeans2 = PruneOptions(groups="kmeans", n_clusters=2)
    rep = prune(data, RICH, kmeans2, mask=mask, cache=bic.fits)
    assert set(rep.fits) == set(bic.fits)  # nothing refitted
    assert len(rep.groups) == 2
    chosen = rep.chosen_per_pixel()
    fitted = truth != ""
    assert {g.chosen.label for g in rep.groups} == {GLOSSY.label, MATTE.label}
    assert np.mean(chosen[fitted] == truth[fitted]) >= 0.9
    d = rep.to_dict()
    assert d["pixels"]["kept"] == 2 * TRIALS and len(d["groups"]) == 2
    assert d["options"] == kmeans2.to_json() and d["criterion"] == "bic"
    # The clusters given as labels make the same groups and choices (nothing refitted).
    given = prune(data, RICH, PruneOptions(groups="labels"), mask=mask, labels=rep.labels,
                  cache=bic.fits)  # fmt: skip
    assert [g.chosen.label for g in given.groups] == [g.chosen.label for g in rep.groups]
    np.testing.assert_array_equal(given.chosen_per_pixel(), chosen)


def test_prune_options_are_checked_and_labels_go_with_their_grouping():
    data, mask, _ = _scene(1)
    for bad, match in (
        (dict(criterion="aic"), "criterion one of 'bic', 'evidence'"),
        (dict(groups="cluster"), "groups one of"),
        (dict(noise="guess"), "noise one of"),
        (dict(n_clusters=0), "integer n_clusters >= 1"),
        (dict(seed=-1), "integer seed >= 0"),
        (dict(prior_width=0.0), "prior_width > 0"),
        (dict(noise_floor=-1.0), "noise_floor >= 0"),
    ):
        with pytest.raises(ValueError, match=match):
            PruneOptions(**bad)
    with pytest.raises(ValueError, match='groups="labels"'):
        prune(data, RICH, mask=mask, labels=np.zeros(data.obs.shape[0], int))
    with pytest.raises(ValueError, match='groups="labels"'):
        prune(data, RICH, PruneOptions(groups="labels"), mask=mask)

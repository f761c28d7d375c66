"""Capture planning (jaxrefl.measured._plan): a candidate at the specular peak is worth more
for roughness than one far from it, and sequential D-optimal choice beats random choice."""

from __future__ import annotations

import numpy as np
import pytest

from jaxrefl.measured import Components, greedy_design, information, rank_candidates
from jaxrefl.measured._components import param_space
from jaxrefl.measured._plan import posterior_std

MODEL = Components(lobe="ggx", fresnel=False).build()
SPACE = param_space(MODEL, 1)
TRUTH = {"albedo": np.array([0.4]), "specular": np.array([0.1]), "alpha": np.array(0.1)}
SIGMA = 0.005


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _hemi(rng, n, theta_max_deg=70.0):
    u = rng.uniform(np.cos(np.radians(theta_max_deg)), 1.0, n)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    s = np.sqrt(1 - u * u)
    return np.stack([s * np.cos(phi), s * np.sin(phi), u], -1)


@pytest.fixture(scope="module")
def theta():
    return SPACE.from_natural(TRUTH)


def test_peak_beats_far_for_roughness(theta):
    rng = np.random.default_rng(0)
    # What was measured: 8 pairs, none near the mirror direction (diffuse only).
    wi = _hemi(rng, 8, 60.0)
    wo = _unit(wi * np.array([1.0, 1.0, 1.0]) + np.array([0.0, 0.0, 0.2]))  # back-scatter side
    light = _unit(np.array([[0.5, 0.0, 0.8], [0.5, 0.0, 0.8]]))
    peak = light * np.array([-1.0, -1.0, 1.0])  # mirror direction: the highlight
    far = _unit(np.array([[0.5, 0.1, 0.8]]))  # next to the light, far from the highlight
    r = rank_candidates(
        MODEL,
        SPACE,
        theta,
        light,
        np.concatenate([peak[:1], far]),
        measured_wi=wi,
        measured_wo=wo,
        sigma=SIGMA,
    )
    assert r.best == 0 and r.gain[0] > r.gain[1] > 0
    s_alpha = r.std_of("alpha")
    assert s_alpha[0] < 0.5 * s_alpha[1], s_alpha
    assert s_alpha[1] <= r.std_now[SPACE.labels.index("alpha")]


def test_sequential_d_optimal_beats_random(theta):
    rng = np.random.default_rng(1)
    m = 80
    cand_wi, cand_wo = _hemi(rng, m), _hemi(rng, m)
    half = m // 4  # some candidates near the highlight, as a real candidate grid has
    jitter = 0.1 * rng.normal(size=(half, 3)) * np.array([1.0, 1.0, 0.0])
    cand_wo[:half] = _unit(cand_wi[:half] * np.array([-1.0, -1.0, 1.0]) + jitter)
    info = information(MODEL, SPACE, theta, cand_wi, cand_wo, sigma=SIGMA)
    prior = np.eye(SPACE.size) / 9.0
    ia = SPACE.labels.index("alpha")
    target = 0.05  # std of ln alpha: 5% roughness uncertainty

    def needed(order):
        a = prior.copy()
        for n, k in enumerate(order, start=1):
            a = a + info[k]
            if posterior_std(a)[ia] <= target:
                return n
        return len(order) + 1

    n_opt = needed(greedy_design(info, 40))
    n_rand = np.mean([needed(np.random.default_rng(s).permutation(m)[:40]) for s in range(10)])
    print(f"measurements to std(ln alpha) <= {target}: D-optimal {n_opt}, random {n_rand:.1f}")
    assert n_opt <= 40 and n_opt < n_rand

"""Error metrics of jaxrefl.measured against values computed by hand, their sample
selection, weights and gradients."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import measured as jm
from jaxrefl.measured._metrics import (
    cosine_weighted_l2,
    log_l2,
    relative_l2,
    sample_weights,
    usable_samples,
)

LN2 = np.log(2.0)


def test_hand_computed_values():
    # Two samples, one channel: f = (1, 2), f̂ = (2, 2), cos_i = (1, 0.5), weights 1.
    f = np.array([[1.0], [2.0]])
    g = np.array([[2.0], [2.0]])
    c = np.array([1.0, 0.5])
    # E_cos = sqrt(((2-1)*1)^2 + 0) / 2) = sqrt(1/2)
    assert float(cosine_weighted_l2(f, g, c)) == pytest.approx(np.sqrt(0.5), rel=1e-12)
    # E_log = sqrt((ln 3 - ln 2)^2 / 2): ln(1 + 2*1) - ln(1 + 1*1), then ln(1+1) - ln(1+1)
    want = abs(np.log(3.0) - LN2) / np.sqrt(2.0)
    assert float(log_l2(f, g, c)) == pytest.approx(want, rel=1e-12)
    # E_rel = sqrt(1 / (1 + 4))
    assert float(relative_l2(f, g)) == pytest.approx(np.sqrt(0.2), rel=1e-12)
    # Weights 3 and 1: E_cos = sqrt(3 * 1 / 4); E_rel = sqrt(3 / (3 + 4))
    w = np.array([3.0, 1.0])
    assert float(cosine_weighted_l2(f, g, c, w)) == pytest.approx(np.sqrt(0.75), rel=1e-12)
    assert float(relative_l2(f, g, w)) == pytest.approx(np.sqrt(3 / 7), rel=1e-12)


def test_channels_average_and_negative_values():
    # Two channels on one sample: the mean over channels, C in the denominator.
    f = np.array([[1.0, 0.0]])
    g = np.array([[1.0, 2.0]])
    assert float(cosine_weighted_l2(f, g, np.array([0.5]))) == pytest.approx(np.sqrt(0.5))
    # A negative measured value counts as 0 in the log metric (sensor noise), not as NaN:
    # ln(1 + 1*1) - ln(1 + 0) = ln 2 over one sample and one channel.
    val = float(log_l2(np.array([[-0.3]]), np.array([[1.0]]), np.array([1.0])))
    assert val == pytest.approx(LN2, rel=1e-12)


def test_selection_nonfinite_and_angle_limit():
    th = np.radians([10.0, 40.0, 85.0, 30.0])
    wi = np.stack([np.sin(th), 0 * th, np.cos(th)], -1)
    wo = wi * np.array([-1.0, -1.0, 1.0])
    f = np.array([[1.0], [2.0], [5.0], [np.nan]])
    g = np.array([[1.5], [2.0], [0.0], [1.0]])
    # 85 degrees is beyond the 80 degree limit of Ngan et al., the NaN sample is dropped:
    # only samples 0 and 1 count, E_rel = sqrt(0.25 / (1 + 4)).
    e = jm.error_metrics(f, g, wi, wo)
    assert e["relative_l2"] == pytest.approx(np.sqrt(0.25 / 5), rel=1e-12)
    want_cos = np.sqrt((0.5 * np.cos(th[0])) ** 2 / 2)
    assert e["cosine_weighted_l2"] == pytest.approx(want_cos, rel=1e-12)
    # No limit: the grazing sample is back in.
    e_all = jm.error_metrics(f, g, wi, wo, max_theta_deg=None)
    assert e_all["relative_l2"] == pytest.approx(np.sqrt((0.25 + 25) / 30), rel=1e-12)
    assert usable_samples(wi, wo, f).tolist() == [True, True, False, False]
    # Nothing usable: NaN, not an exception or a 0 that would look perfect.
    assert np.isnan(float(relative_l2(np.zeros((2, 1)), np.zeros((2, 1)))))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_exact_fit_is_zero_with_finite_gradient(dtype):
    rng = np.random.default_rng(0)
    f = jnp.asarray(rng.uniform(0.1, 3.0, (20, 3)), dtype)
    c = jnp.asarray(rng.uniform(0.05, 1.0, 20), dtype)
    for metric in (
        lambda g: cosine_weighted_l2(f, g, c),
        lambda g: log_l2(f, g, c),
        lambda g: relative_l2(f, g),
    ):
        assert float(metric(f)) == 0.0
        grad = jax.grad(metric)(f)
        assert bool(jnp.all(jnp.isfinite(grad)))
        # Away from the exact fit the gradient matches a central difference (float64).
        if dtype == jnp.float64:
            g0 = f * 1.1
            d = jnp.zeros_like(f).at[3, 1].set(1e-6)
            fd = (metric(g0 + d) - metric(g0 - d)) / 2e-6
            assert float(jax.grad(metric)(g0)[3, 1]) == pytest.approx(float(fd), rel=1e-6)


def test_merl_solid_angle_weights():
    from jaxrefl.io import MeasuredBRDF

    cells = np.array([[0, 45, 0], [89, 45, 0], [10, 0, 5], [10, 89, 5]])
    m = MeasuredBRDF(
        wi=np.tile([0.0, 0.0, 1.0], (4, 1)),
        wo=np.tile([0.0, 0.0, 1.0], (4, 1)),
        values=np.ones((4, 3)),
        channels=("R", "G", "B"),
        meta={"format": "MERL binary", "cell": cells},
    )
    w = sample_weights(m)
    assert np.mean(w) == pytest.approx(1.0)

    def raw(i, j):
        u = i + 0.5
        th, td = (u / 90) ** 2 * np.pi / 2, (j + 0.5) / 90 * np.pi / 2
        return np.cos(td) * np.sin(td) * np.sin(th) * u

    # Ratios follow cos(td) sin(td) sin(th) (i + 1/2); the near-normal cell weighs least.
    assert w[1] / w[0] == pytest.approx(raw(89, 45) / raw(0, 45), rel=1e-12)
    assert w[2] / w[3] == pytest.approx(raw(10, 0) / raw(10, 89), rel=1e-12)
    assert w[0] < 1e-3 * w[1]
    # Any other source: weight 1 per sample.
    other = MeasuredBRDF(m.wi, m.wo, m.values, m.channels)
    assert sample_weights(other).tolist() == [1.0] * 4

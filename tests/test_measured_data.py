"""Measured f_r samples as fitting data: one builder (:func:`jaxrefl.fit._problem.sample_arrays`)
for :func:`jaxrefl.fit.fit_samples` and :func:`jaxrefl.measured.measured_pixel_data`."""

from __future__ import annotations

import numpy as np
import pytest

from jaxrefl.fit._problem import sample_arrays
from jaxrefl.io import MeasuredBRDF
from jaxrefl.measured import measured_pixel_data

S = np.sqrt(0.5)
WI = np.array([[0.0, 0.0, 1.0], [S, 0.0, S], [0.6, 0.0, -0.8], [0.0, 0.6, 0.8], [1.0, 0.0, 0.0]])
WO = np.array([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.0, 0.0, 1.0], [0.0, -0.6, -0.8], [0, 0, 1.0]])
F = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0], [7.0, 8.0], [9.0, 10.0]])
ABOVE = np.array([1.0, 1.0, 0.0, 0.0, 0.0])  # wi below, wo below, wi on the horizon


@pytest.mark.parametrize("cosine", [True, False])
def test_sample_arrays_weights_and_cosine(cosine):
    obs, scale, weight = sample_arrays(WI, WO, F, cosine=cosine)
    np.testing.assert_array_equal(weight, np.repeat(ABOVE[:, None], 2, axis=1))
    if cosine:
        cos = ABOVE * WI[:, 2]
        np.testing.assert_array_equal(scale, np.repeat(cos[:, None], 2, axis=1))
        np.testing.assert_array_equal(obs, F * cos[:, None])
    else:
        assert scale is None
        np.testing.assert_array_equal(obs, F)
    # keep= drops samples besides the horizon test; a 1-D values array is one channel
    obs, _, weight = sample_arrays(WI, WO, F[:, 0], cosine=cosine, keep=[False, 1, 1, 1, 1])
    np.testing.assert_array_equal(weight[:, 0], [0.0, 1.0, 0.0, 0.0, 0.0])
    assert obs.shape == (5, 1)


def test_sample_arrays_converts_first_then_scales():
    obs, scale, weight = sample_arrays(WI, WO, F, cosine=True, dtype=np.float32)
    assert obs.dtype == scale.dtype == weight.dtype == np.float32
    np.testing.assert_array_equal(obs[1], F[1].astype(np.float32) * np.float32(S))


@pytest.mark.parametrize("cosine", [True, False])
def test_measured_pixel_data_masks_non_finite_samples(cosine):
    f = F.copy()
    f[1, 1] = np.nan  # a non-finite channel drops the whole sample
    m = MeasuredBRDF(WI, WO, f, ("R", "G"))
    d = measured_pixel_data(m, cosine=cosine)
    assert d.obs.shape == (1, 5, 2)
    w = ABOVE.copy()
    w[1] = 0.0
    np.testing.assert_array_equal(np.asarray(d.weight[0]), np.repeat(w[:, None], 2, axis=1))
    assert np.all(np.isfinite(np.asarray(d.obs)))
    if cosine:
        np.testing.assert_array_equal(np.asarray(d.scale[0, :, 0]), w * WI[:, 2])
        np.testing.assert_array_equal(np.asarray(d.obs[0]), F * (w * WI[:, 2])[:, None])
    else:
        np.testing.assert_array_equal(np.asarray(d.scale), 1.0)
        np.testing.assert_array_equal(np.asarray(d.obs[0, 0]), F[0])
        assert float(d.obs[0, 1, 1]) == 0.0 and float(d.obs[0, 1, 0]) == F[1, 0]

"""The censored observations a Gibbs scan draws latent values for, gathered per pixel
(jaxrefl.posterior._conjugate.censored_slots), and the exact Gibbs sampler's latent terms
built from them."""

from __future__ import annotations

import numpy as np

from jaxrefl.posterior._conjugate import CENSORED_GROWTH, CENSORED_SLOTS, censored_slots
from jaxrefl.posterior._gibbs import latent_terms


def _random_flags(rng, n, m, rate):
    flags = np.zeros((n, m), np.int8)
    hit = rng.uniform(size=(n, m)) < rate
    flags[hit] = rng.choice(np.array([-1, 1], np.int8), size=int(hit.sum()))
    return flags


def test_slots_hold_each_pixels_censored_observations_in_order_then_padding():
    rng = np.random.default_rng(3)
    cens = _random_flags(rng, 200, 27, 0.15)
    idx, sign = censored_slots(cens)
    count = np.sum(cens != 0, axis=1)
    r = idx.shape[1]
    sizes = [CENSORED_SLOTS * CENSORED_GROWTH**k for k in range(4)]
    # the smallest compiled size, at most the observations a pixel has
    assert r == min(27, min(s for s in sizes if s >= count.max()))
    for i in range(cens.shape[0]):
        where = np.flatnonzero(cens[i])
        k = where.size
        np.testing.assert_array_equal(idx[i, :k], where)
        np.testing.assert_array_equal(sign[i, :k], cens[i, where])
        assert np.all(sign[i, k:] == 0) and np.all(idx[i, k:] == 0)


def test_no_censoring_and_never_more_slots_than_observations():
    idx, sign = censored_slots(np.zeros((5, 9), np.int8))
    assert idx.shape == (5, CENSORED_SLOTS) and not np.any(sign) and not np.any(idx)
    # 5 of 6 observations censored: past CENSORED_SLOTS, but 6 rows are all there are
    cens = np.array([[1, -1, 1, 0, -1, 1], [0, 0, 0, 0, 0, -1]], np.int8)
    assert CENSORED_SLOTS < 5 < CENSORED_SLOTS * CENSORED_GROWTH
    idx, sign = censored_slots(cens)
    assert idx.shape == (2, 6)
    np.testing.assert_array_equal(idx[0], [0, 1, 2, 4, 5, 0])
    np.testing.assert_array_equal(sign[0], [1, -1, 1, -1, 1, 0])
    np.testing.assert_array_equal(idx[1], [5, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(sign[1], [-1, 0, 0, 0, 0, 0])
    # fewer observations than CENSORED_SLOTS
    idx, sign = censored_slots(np.array([[0, -1, 0]], np.int8))
    np.testing.assert_array_equal(idx, [[1, 0, 0]])
    np.testing.assert_array_equal(sign, [[-1, 0, 0]])


def test_gathered_latent_terms_equal_the_dense_ones():
    """r = A'^T W y* and y*^T W y* with latent values y* on the censored rows, from the
    observed rows' sums plus the gathered rows (as the exact Gibbs scan forms them), equal
    the sums over every row."""
    rng = np.random.default_rng(5)
    n, m, p = 50, 27, 6
    cens = _random_flags(rng, n, m, 0.2)
    aw = rng.normal(size=(n, m, p))
    yw = rng.normal(size=(n, m))
    w = rng.integers(0, 2, size=(n, m)).astype(float)
    latent = rng.normal(size=(n, m))
    y = np.where(cens != 0, latent, yw)
    r_dense = np.einsum("nmp,nm,nm->np", aw, w, y)
    yy_dense = np.einsum("nm,nm,nm->n", y, w, y)

    r_obs, yy_obs, aw_c, yw_c, w_c, sign_c = (np.asarray(v) for v in latent_terms(aw, yw, w, cens))
    idx, _ = censored_slots(cens)
    np.testing.assert_array_equal(yw_c, np.take_along_axis(yw, idx, axis=1))
    # the padding's latent draws are arbitrary: weight 0 must cancel them
    y_c = np.where(sign_c != 0, np.take_along_axis(latent, idx, axis=1), 1e3)
    wy = w_c * y_c  # as the scan forms them
    np.testing.assert_allclose(r_obs + np.einsum("nr,nrp->np", wy, aw_c), r_dense, rtol=1e-12)
    np.testing.assert_allclose(yy_obs + np.sum(wy * y_c, axis=1), yy_dense, rtol=1e-12)

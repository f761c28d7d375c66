"""``auto``'s choice of the light (:func:`jaxrefl.svbrdf._light.choose_light`): a candidate's
gain is weighed against its noise over the training photos, not over pixels."""

from __future__ import annotations

import numpy as np

from jaxrefl.svbrdf import _light

K, N = 8, 500  # training photos, pixels per half


class _Scores:
    """A stand-in for :class:`jaxrefl.svbrdf.LightProblem` whose held-out squared errors
    (K, N) per half are given per candidate."""

    def __init__(self, per_photo: dict[str, np.ndarray], seed: int = 0):
        self.train = np.ones(K, bool)
        rng = np.random.default_rng(seed)
        self.sse = {
            m: [v[:, None] + 0.05 * rng.standard_normal((K, N)) for _ in range(2)]
            for m, v in per_photo.items()
        }

    def unit_weights(self, halves):
        return [None for _ in halves]

    def solve(self, mode, halves, weights):
        return np.zeros(2), None, None, 0

    def loo_sse(self, theta, mode, fit_half, score_half):
        return self.sse[mode][score_half], np.ones((K, N))


def test_a_gain_one_photo_pays_for_is_not_kept():
    fixed = np.ones(K)
    # every photo but one predicted 10% better, the last 40% worse: the sum gains more than
    # the tolerance and every pixel gains alike (the per-pixel spread is the noise's alone),
    # while over the photos the gain is well within its noise
    lopsided = np.r_[np.full(K - 1, 0.9), 1.4]
    problem = _Scores({"fixed": fixed, "offset": lopsided, "offset+gains": fixed})
    chosen, cv, why = _light.choose_light(problem)
    assert cv["offset"] < cv["fixed"] / (1.0 + 0.01)
    assert chosen == "fixed", why
    assert "offset does not beat fixed" in why
    # the same total gain, shared by every photo: kept
    even = np.full(K, lopsided.mean())
    problem = _Scores({"fixed": fixed, "offset": even, "offset+gains": even + 0.01})
    chosen, _cv, why = _light.choose_light(problem)
    assert chosen == "offset", why
    assert "offset beats fixed" in why and "offset+gains does not beat offset" in why

"""Pooling across pixels: one lobe shape for the whole capture, chosen by held-out photos.

A flash capture sees each pixel's BRDF at one half vector per photo. With eight photos most
pixels never see their own highlight's peak, so a per-pixel lobe width is not identified: a
needle aimed between the photos fits the training photos as well as a broad lobe and lands
wherever the held-out photo looks. The capture as a whole, though, sees every half-vector
angle somewhere. The pooled model therefore shares what single pixels cannot identify:

    f_r(x) = albedo(x) / pi + F0(x) D(h; alpha) G(wi, wo; alpha) / (4 cos_i cos_o)

with GGX D, height-correlated Smith G (Walter et al. 2007; Heitz 2014) and one ``alpha`` for
every pixel, a per-pixel diffuse ``albedo`` (RGB) and a per-pixel coloured specular ``F0``
(RGB, in [0, 1]: metals included) -- the exemplar form of Gardner et al. 2003 (linear light
source reflectometry: a measured pixel as a non-negative blend of a diffuse term and a
chart lobe) with the chart reduced to the one lobe the capture supports. Fresnel is Schlick's
F0 + (1 - F0)(1 - cos theta_d)^5, so the lobe is linear in F0 up to the (1 - cos theta_d)^5
term, which vanishes for a co-located flash (theta_d = 0) and is below 1e-6 for light-view
separations under 30 degrees; the selection below uses the linear form, the fit the exact one.

Choosing the capture's model (:func:`choose_pooled`), on a random subsample of pixels:

1. Given alpha, each pixel and channel is a non-negative least-squares problem in
   (albedo, F0) (two unknowns: solved exactly by comparing the feasible supports), with
   censored observations as one-sided rows (active where the prediction breaks the bound).
2. Every candidate -- Lambert (no lobe) and the lobe at each alpha of a log grid from the
   capture's resolvable width (:func:`jaxrefl.svbrdf.resolvable_alpha`) to 1, refined around
   the best -- is scored by leave-one-photo-out over the training photos: fit on all but one,
   predict that one's uncensored observations, sum the squared errors over photos.
3. The lowest held-out error wins; the report lists every candidate's, so a reader sees why.

Pixels share more than alpha: the population of F0 values. Given alpha, the fit puts an
empirical-Bayes Gaussian prior on each pixel's F0 channel, N(mu_c, tau_c^2), with mu_c the
median and tau_c the scaled median absolute deviation (1.4826 MAD) of the per-pixel
non-negative least-squares F0 over all pixels, in noise units sigma (the median per-pixel
residual RMS of that fit). A pixel whose observations pin F0 down ignores the prior; one that
never saw its lobe keeps the population's F0, so its prediction for an unseen direction is
the pooled material's, never a lobe the data do not support. The per-pixel fit is then the
ordinary MAP fit of :func:`jaxrefl.fit.fit_pixels` with alpha fixed at its selected value
(Laplace uncertainty included: the prior is part of its curvature, and
:mod:`jaxrefl.svbrdf._width_laplace` adds each pixel's share of the shared alpha's own
uncertainty).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl import brdf
from jaxrefl._errors import JaxreflError

from ._data import subsample

__all__ = ["PoolChoice", "choose_pooled"]

_LOBE = brdf.get(
    "cook_torrance", distribution="ggx", shadowing="smith_height_correlated", fresnel="none"
)


@dataclass(frozen=True)
class PoolChoice:
    """What :func:`choose_pooled` chose, and the evidence.

    model:       ``"lambert"`` or ``"lobe"`` (diffuse + the shared GGX lobe)
    alpha:       the shared GGX width (None for Lambert)
    cv_rmse:     leave-one-photo-out RMSE of every candidate: ``{"lambert": r, "0.1234": r}``
    prior_mean, prior_std: the empirical-Bayes prior on F0 per channel (natural units)
    sigma:       the noise scale the prior is expressed in (radiance units)
    pixels:      how many pixels the selection used
    """

    model: str
    alpha: float | None
    cv_rmse: dict[str, float]
    prior_mean: tuple[float, ...] = ()
    prior_std: tuple[float, ...] = ()
    sigma: float | None = None
    pixels: int = 0

    def as_dict(self) -> dict[str, Any]:
        best = min(self.cv_rmse.values()) if self.cv_rmse else None
        lam = self.cv_rmse.get("lambert")
        why = (
            f"leave-one-photo-out RMSE {best:.5f} against Lambert's {lam:.5f}"
            if best is not None and lam is not None
            else None
        )
        return {
            "model": self.model,
            "alpha": self.alpha,
            "why": why,
            "cv_rmse": self.cv_rmse,
            "prior_mean_F0": list(self.prior_mean),
            "prior_std_F0": list(self.prior_std),
            "sigma": self.sigma,
            "selection_pixels": self.pixels,
        }


def _lobe_basis(alpha, data):
    """(N, K, C) radiance of a unit-F0 lobe (Fresnel factor 1) for every observation."""
    n, k, _c = data.obs.shape
    one = jnp.ones((n, k, 1), data.obs.dtype)
    a = jnp.full((n, k), alpha, data.obs.dtype)
    wo = data.wi if data.colocated else data.wo
    return _LOBE.eval({"specular": one, "alpha": a}, data.wi, wo) * data.scale


def _obs_major(x):
    """(N, K, C) -> (K, C * N): the photos first, so that the sums over photos below run
    across contiguous vectors of pixels (a CPU vectorises those; summing the short middle
    axis of (N, K, C) it does not)."""
    n, k, c = x.shape
    return jnp.moveaxis(x, 0, -1).reshape(k, c * n)


def _nnls2(b0, b1, y, w):
    """Per (channel, pixel) column: min_{a, u >= 0} sum_k w (y - a b0 - u b1)^2, exactly.

    The optimum is the best of the feasible supports {both, a only, u only, none}. Inputs
    (K, M) (:func:`_obs_major`); returns a, u (M,)."""
    s00 = jnp.sum(w * b0 * b0, 0)
    s01 = jnp.sum(w * b0 * b1, 0)
    s11 = jnp.sum(w * b1 * b1, 0)
    t0 = jnp.sum(w * b0 * y, 0)
    t1 = jnp.sum(w * b1 * y, 0)
    tiny = jnp.finfo(y.dtype).tiny
    det = s00 * s11 - s01 * s01
    # A singular 2x2 system (the lobe indistinguishable from the diffuse term, or no
    # observation) leaves only the one-parameter supports: det <= eps * scale rejects it.
    ok2 = det > 1e-6 * s00 * s11 + tiny
    safe = jnp.where(ok2, det, 1.0)
    a2 = (s11 * t0 - s01 * t1) / safe
    u2 = (s00 * t1 - s01 * t0) / safe
    feas2 = ok2 & (a2 >= 0) & (u2 >= 0)
    a1 = jnp.maximum(t0, 0.0) / jnp.maximum(s00, tiny)
    u1 = jnp.maximum(t1, 0.0) / jnp.maximum(s11, tiny)
    # Gains over the empty support (sum w y^2 - SSE): both-free t.x, one-parameter t^2/s.
    g2 = jnp.where(feas2, a2 * t0 + u2 * t1, -jnp.inf)
    ga = a1 * t0
    gu = u1 * t1
    best2 = (g2 >= ga) & (g2 >= gu)
    besta = ~best2 & (ga >= gu)
    a = jnp.where(best2, a2, jnp.where(besta, a1, 0.0))
    u = jnp.where(best2, u2, jnp.where(besta, 0.0, u1))
    return a, u


def _censored_nnls(b0, b1, y, cens, w):
    """:func:`_nnls2` with censored observations (``cens`` +1 saturated, -1 dark, 0 not) as
    one-sided rows: a saturated row (true >= obs) counts where the prediction falls below
    it, a dark one where it rises above; two passes from the uncensored solution."""
    unc = (cens == 0).astype(y.dtype)
    a, u = _nnls2(b0, b1, y, w * unc)
    for _ in range(2):
        pred = a[None] * b0 + u[None] * b1
        viol = ((cens == 1) & (pred < y)) | ((cens == -1) & (pred > y))
        a, u = _nnls2(b0, b1, y, w * (unc + viol.astype(y.dtype)))
    return a, u


def _columns(data):
    """(obs, censored, usable, diffuse basis) of ``data`` as (K, C * N) columns."""
    y, cens = _obs_major(data.obs), _obs_major(data.censored)
    base = _obs_major(data.weight) > 0
    return y, cens, base, _obs_major(data.scale) / jnp.pi


@jax.jit
def _cv_sse(alpha, lobe_on, data, train):
    """Leave-one-photo-out squared error and count over the training photos ``train`` (K,)
    for the lobe at ``alpha`` (``lobe_on`` 0: Lambert)."""
    y, cens, base, b0 = _columns(data)
    b1 = _obs_major(_lobe_basis(alpha, data)) * lobe_on
    k = train.shape[0]

    def fold(j):
        tr = train & (jnp.arange(k) != j)
        w = (base & tr[:, None]).astype(y.dtype)
        a, u = _censored_nnls(b0, b1, y, cens, w)
        pred = a[None] * b0 + u[None] * b1
        held = base & (cens == 0) & (jnp.arange(k) == j)[:, None] & train[j]
        e = jnp.where(held, pred - y, 0.0)
        return jnp.sum(e * e), jnp.sum(held)

    s, n = jax.lax.map(fold, jnp.arange(k))
    return jnp.sum(s), jnp.sum(n)


@jax.jit
def _population(alpha, data, train):
    """Per-pixel F0 (N, C) and residual mean square (N,) of the non-negative fit at alpha."""
    n_px, k, c = data.obs.shape
    y, cens, base, b0 = _columns(data)
    b1 = _obs_major(_lobe_basis(alpha, data))
    w = (base & train[:, None]).astype(y.dtype)
    a, u = _censored_nnls(b0, b1, y, cens, w)
    pred = a[None] * b0 + u[None] * b1
    use = w * (cens == 0)
    e = ((pred - y) * use).reshape(k, c, n_px)
    n = jnp.sum(use.reshape(k, c, n_px), (0, 1))
    return u.reshape(c, n_px).T, jnp.sum(e * e, (0, 1)) / jnp.maximum(n, 1.0), n


def choose_pooled(
    capture,
    train: np.ndarray,
    alpha_min: float,
    *,
    n_pixels: int = 4096,
    grid: int = 12,
    refine: int = 6,
    seed: int = 0,
    dtype=np.float32,
) -> PoolChoice:
    """Choose Lambert or the shared-alpha lobe for ``capture`` by leave-one-photo-out over
    the photos marked in ``train`` (K,) bool, and the empirical-Bayes F0 prior (module
    docstring). Needs at least two training photos for a held-out score. ``grid`` log-spaced
    widths, then ``refine`` golden-section steps between the best one's neighbours (the
    defaults bracket alpha to a few percent: the held-out error is flat near its optimum)."""
    train = np.asarray(train, bool)
    if train.sum() < 2:
        raise JaxreflError(
            f"pooled needs at least two training photos to choose its shared width by held-out "
            f"error; {capture.source or 'the capture'} has {int(train.sum())}: fit it with "
            "lambert (or model auto, which chooses among the models its photos allow)"
        )
    data = subsample(capture, n_pixels, seed, dtype)
    tr = jnp.asarray(train)

    def score(alpha: float, on: float) -> float:
        s, n = _cv_sse(
            jnp.asarray(alpha, data.obs.dtype), jnp.asarray(on, data.obs.dtype), data, tr
        )
        n = float(n)
        return float(np.sqrt(float(s) / n)) if n > 0 else float("inf")

    lo = max(float(alpha_min), 1e-3)
    cv: dict[str, float] = {"lambert": score(lo, 0.0)}
    alphas = list(np.geomspace(lo, 1.0, grid)) if lo < 1.0 else [1.0]
    scores = [score(a, 1.0) for a in alphas]
    i = int(np.argmin(scores))
    # Golden-section search in log alpha between the grid neighbours of the best (the
    # held-out error is smooth there); every point tried is kept in the report.
    lo_t, hi_t = np.log(alphas[max(i - 1, 0)]), np.log(alphas[min(i + 1, len(alphas) - 1)])
    g = (np.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = hi_t - g * (hi_t - lo_t), lo_t + g * (hi_t - lo_t)
    f1, f2 = score(float(np.exp(x1)), 1.0), score(float(np.exp(x2)), 1.0)
    alphas += [float(np.exp(x1)), float(np.exp(x2))]
    scores += [f1, f2]
    for _ in range(refine):
        if f1 <= f2:
            hi_t, x2, f2 = x2, x1, f1
            x1 = hi_t - g * (hi_t - lo_t)
            f1 = score(float(np.exp(x1)), 1.0)
            alphas.append(float(np.exp(x1)))
            scores.append(f1)
        else:
            lo_t, x1, f1 = x1, x2, f2
            x2 = lo_t + g * (hi_t - lo_t)
            f2 = score(float(np.exp(x2)), 1.0)
            alphas.append(float(np.exp(x2)))
            scores.append(f2)
    for a, s in zip(alphas, scores, strict=True):
        cv[f"{a:.4g}"] = s
    j = int(np.argmin(scores))
    if not scores[j] < cv["lambert"]:
        return PoolChoice("lambert", None, cv, pixels=int(data.obs.shape[0]))
    alpha = float(alphas[j])
    f0, ms, n = _population(jnp.asarray(alpha, data.obs.dtype), data, tr)
    f0, ms, n = np.asarray(f0, np.float64), np.asarray(ms, np.float64), np.asarray(n)
    seen = n > 0
    mu = np.median(f0[seen], axis=0)
    mad = 1.4826 * np.median(np.abs(f0[seen] - mu), axis=0)
    sigma = float(np.sqrt(np.median(ms[seen])))
    # A population without spread (every pixel the same F0) would pin each pixel to it; the
    # floor keeps the prior a prior: 1% of the F0 range.
    tau = np.maximum(mad, 0.01)
    mu = np.clip(mu, 0.0, 1.0)
    return PoolChoice(
        "lobe",
        alpha,
        cv,
        prior_mean=tuple(float(v) for v in mu),
        prior_std=tuple(float(v) for v in tau),
        sigma=max(sigma, 1e-6),
        pixels=int(data.obs.shape[0]),
    )

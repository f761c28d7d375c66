"""Posterior predictive intervals of a capture's photos, and where the model cannot be right.

For pixel x, photo k and channel c, a fit (:class:`CaptureFit`) predicts the radiance
mu = L_kc(x; theta*) at its optimum theta*. The posterior predictive distribution of a new
observation y of that radiance is taken Gaussian,

    y ~ N(mu, v_param + v_noise + tau^2(mu)),

with three variances, all in the capture's linear radiance units squared:

* ``v_param = g^T Sigma_theta g``: parameter uncertainty, the Laplace covariance
  Sigma_theta of the unconstrained parameters (the fit's ``*_std`` and ``corr_*`` maps,
  :func:`laplace_theta_std`) pushed through the prediction's gradient g = d mu / d theta
  (the delta method). Where the fit formed no covariance (Laplace ``NOT_IDENTIFIED`` by an
  ill-conditioned J^T J, ``NO_ESTIMATE``) the term is missing: 0, and the pixel is counted in
  :attr:`Predictive.no_covariance`.
* ``v_noise``: the fit's noise model. With :class:`jaxrefl.fit.GaussianNoise` of unknown
  scale (the default of the per-pixel models), the pixel's residual variance s^2 = 2 cost /
  (n - P) (:func:`jaxrefl.fit.laplace`); with ``pooled``, the capture's one noise scale
  sigma^2 (:mod:`jaxrefl.svbrdf._pooled`). Either way the noise is assumed additive,
  Gaussian, independent between photos and channels and of one variance per pixel (not
  growing with the radiance): what the fits assume.
* ``tau^2(mu)``: model discrepancy (:class:`Discrepancy`): what the photos show beyond the
  model and its noise (misregistration, a lobe shape or Fresnel the model does not have,
  8-bit quantisation of dark values). It is estimated from the *training* photos only
  (:func:`estimate_discrepancy`): on a random subsample of pixels, each training photo j is
  held out in turn, the fit on the other training photos predicts it, and per bin of
  predicted radiance tau^2 is the smallest variance >= 0 that makes the median of the
  standardised squared errors e^2 / (v_param + v_noise + tau^2) equal to a chi-square(1)'s
  median, 0.455 (a median, not a mean: a few wild highlights must not set the width of every
  interval). Between bin centres tau^2 is interpolated linearly, constant beyond. A held-out
  photo of the job is never looked at.
* With ``DiscrepancyOptions(replace_noise=True)`` the same median-matched estimate is
  made against the parameter variance alone, and v(mu) *replaces* the fit's noise term: a
  heteroscedastic noise model measured on held-out training photos. It is the default for a
  fit whose noise is one known scale for the whole capture (``pooled``'s: too wide for dark
  pixels and too narrow for bright ones, where photon noise and misregistration grow with
  the radiance); a per-pixel model keeps its own per-pixel noise estimate plus tau^2(mu).
  The Laplace covariance of such a fit was formed with that one noise scale too, so the
  parameter term is rescaled to the noise measured at the pixel's own radiances:
  v_param * f with 1 / f = the mean over the pixel's usable training observations of
  v_fit / e^2(mu) (the precision-weighted average, exact where every observation informs
  the parameters alike), e^2(mu) the held-out errors' own median-matched variance per bin
  (:attr:`Discrepancy.error_var`: the parameter term not taken out, so a bound from above
  on the noise, and never 0 where the errors are not). Without it, dark pixels, whose
  errors are a few times smaller than the capture's noise scale, get parameter intervals
  wider than all of their errors.

The central interval of level p is mu +- z_p sqrt(v), z_p the standard normal's
(1 + p)/2 quantile. :meth:`Predictive.coverage` counts the share of a photo's uncensored,
valid observations inside it (censored observations are bounds, not values, and are left
out).

Where the model cannot be right: :attr:`Predictive.check` holds the bits of
:class:`ModelCheck` (:mod:`jaxrefl.svbrdf._check`), its posterior predictive check
evaluated with the discrepancy term (v = the capture's noise variance + tau^2(mu)).

The intervals of a flagged pixel are not calibrated: its model is wrong there, so neither its
parameter intervals nor its predictive intervals mean what their level says. Reports count
flagged pixels apart (:meth:`Predictive.coverage` takes a pixel mask).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from jaxrefl._errors import JaxreflError
from jaxrefl.io import corr_name, map_name

from ._check import PPC_ALPHA, ModelCheck, bound_bits, check_counts, ppc_failed
from ._data import pixel_block, stack_folds, subsample
from ._discrepancy_options import DiscrepancyOptions
from ._job_types import CaptureFit
from ._tile_fitter import TileFitter

__all__ = [
    "LEVELS",
    "Discrepancy",
    "Predictive",
    "estimate_discrepancy",
    "model_check",
    "predictive",
]

LEVELS: tuple[float, ...] = (0.5, 0.9)
# The median of a chi-square of one degree of freedom: the median of e^2 / v for a Gaussian e
# of variance v (stats.chi2.ppf(0.5, 1)).
_CHI2_1_MEDIAN = float(stats.chi2.ppf(0.5, 1))
_DISCREPANCY = DiscrepancyOptions()


@dataclass(frozen=True)
class Discrepancy:
    """Model-discrepancy variance tau^2 as a function of predicted radiance mu.

    radiance: (B,) bin centres (median predicted radiance of each bin), increasing
    var:      (B,) tau^2 there (radiance units squared, >= 0)
    rows:     held-out training observations the estimate used
    folds:    the training photos held out in turn
    replaces_noise: tau^2 is the whole variance beyond the parameter term: the fit's noise
              term is replaced by it (``DiscrepancyOptions.replace_noise``)
    error_var: (B,) with ``replaces_noise``, the held-out errors' own variance per bin, by
              which the parameter term is rescaled (module docstring); else None
    """

    radiance: np.ndarray
    var: np.ndarray
    rows: int = 0
    folds: tuple[int, ...] = ()
    replaces_noise: bool = False
    error_var: np.ndarray | None = None

    @classmethod
    def zero(cls) -> Discrepancy:
        """No discrepancy term: tau^2 = 0 everywhere."""
        return cls(np.zeros(1), np.zeros(1))

    def __call__(self, mu) -> np.ndarray:
        """tau^2 at predicted radiance ``mu`` (any shape): linear between bin centres."""
        return np.interp(np.asarray(mu, np.float64), self.radiance, self.var)

    def as_dict(self) -> dict[str, Any]:
        return {
            "radiance": self.radiance.tolist(),
            "std": np.sqrt(self.var).tolist(),
            "rows": self.rows,
            "folds": list(self.folds),
            "replaces_noise": self.replaces_noise,
            "error_std": None if self.error_var is None else np.sqrt(self.error_var).tolist(),
        }


@dataclass
class Predictive:
    """Posterior predictive moments of every pixel, photo and channel (N = H x W row-major).

    mean:       (N, K, C) predicted radiance at the optimum
    param_var, noise_var, disc_var: (N, K, C) the three variances (module docstring)
    obs:        (N, K, C) the observations
    value:      (N, K, C) bool: the observation is an uncensored value (valid, not clipped)
    train:      (K,) bool: photos the fit used
    check:      (N,) :class:`ModelCheck` bits
    chi2, dof:  (N,) the posterior predictive check's statistic and degrees of freedom
    no_covariance: (N,) bool: no Laplace covariance (the parameter term is missing)
    discrepancy: the :class:`Discrepancy` used
    noise_ref_var: the check's reference noise variance (the median)
    """

    mean: np.ndarray
    param_var: np.ndarray
    noise_var: np.ndarray
    disc_var: np.ndarray
    obs: np.ndarray
    value: np.ndarray
    train: np.ndarray
    check: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    no_covariance: np.ndarray
    discrepancy: Discrepancy
    noise_ref_var: float = float("nan")

    def std(self, terms: tuple[str, ...] = ("param", "noise", "disc")) -> np.ndarray:
        """(N, K, C) predictive std from the named variance terms (all three by default)."""
        parts = {"param": self.param_var, "noise": self.noise_var, "disc": self.disc_var}
        bad = [t for t in terms if t not in parts]
        if bad:
            raise JaxreflError(f"unknown variance terms {bad}; choose from {sorted(parts)}")
        return np.sqrt(sum((parts[t] for t in terms), np.zeros_like(self.mean)))

    def interval(self, level: float, terms=("param", "noise", "disc")):
        """(lower, upper), each (N, K, C): the central Gaussian interval of ``level``."""
        if not 0.0 < level < 1.0:
            raise JaxreflError(f"level must be in (0, 1), got {level}")
        z = float(stats.norm.ppf(0.5 + 0.5 * level))
        s = self.std(terms)
        return self.mean - z * s, self.mean + z * s

    def coverage(
        self,
        photo: int,
        level: float,
        pixels: np.ndarray | None = None,
        terms=("param", "noise", "disc"),
    ) -> tuple[float, int]:
        """(share of photo ``photo``'s uncensored values inside the ``level`` interval,
        number of values) over the pixels of the (N,) boolean mask ``pixels`` (all: None)."""
        lo, hi = self.interval(level, terms)
        use = self.value[:, photo] & np.isfinite(self.mean[:, photo])
        if pixels is not None:
            use = use & np.asarray(pixels, bool).reshape(-1)[:, None]
        y = self.obs[:, photo]
        inside = (y >= lo[:, photo]) & (y <= hi[:, photo])
        n = int(np.sum(use))
        return (float(np.sum(inside & use)) / n if n else float("nan")), n

    @property
    def misspecified(self) -> np.ndarray:
        """(N,) bool: some :class:`ModelCheck` bit is set."""
        return self.check != 0

    def check_counts(self) -> dict[str, int]:
        """Pixels per :class:`ModelCheck` bit, and ``misspecified`` (any bit)."""
        return check_counts(self.check)


# ----------------------------------------------------------------------------- moments
def _theta_cov(space, theta, std, corr):
    """(N, P, P) Laplace covariance in the unconstrained space from natural std (N, P) and
    correlation (N, P, P): the bijections act entry by entry, so std_theta = std_x / |g'|
    and the correlation is the same in both spaces; and (N,) whether it was formed."""
    ok_t = jnp.all(jnp.isfinite(theta), -1)
    t = jnp.where(ok_t[:, None], theta, 0.0)
    dn = jnp.abs(space.dnatural(t))
    s = std / jnp.where(dn > 0, dn, jnp.nan)
    cov = s[:, :, None] * s[:, None, :] * corr
    formed = ok_t & jnp.all(jnp.isfinite(cov), axis=(-2, -1))
    return jnp.where(formed[:, None, None], cov, 0.0), formed


@eqx.filter_jit
def _moments(res, theta, std, corr, data):
    """Per pixel: prediction (K, C) at theta, its parameter variance g^T Sigma g (K, C),
    and whether the covariance exists; NaN theta gives NaN predictions."""
    cov, formed = _theta_cov(res.space, theta, std, corr)
    ok_t = jnp.all(jnp.isfinite(theta), -1)
    t = jnp.where(ok_t[:, None], theta, 0.0)

    def one(ti, ci, di):
        mu = res.predict(ti, di)
        g = jax.jacfwd(res.predict)(ti, di)  # (K, C, P)
        return mu, jnp.einsum("kcp,pq,kcq->kc", g, ci, g)

    mu, pv = jax.vmap(one)(t, cov, data)
    nan = jnp.where(ok_t, 0.0, jnp.nan)[:, None, None]
    return mu + nan, jnp.maximum(pv, 0.0) + nan, formed


def _fit_arrays(cf: CaptureFit, space) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """theta (N, P), natural std (N, P) and correlation (N, P, P) from a fit's maps."""
    labels = space.labels
    std = np.stack([cf.maps[map_name(lab, "_std")].reshape(-1) for lab in labels], -1)
    p = len(labels)
    corr = np.zeros((std.shape[0], p, p))
    for a in range(p):
        corr[:, a, a] = 1.0
        for b in range(a + 1, p):
            v = cf.maps[corr_name(labels[a], labels[b])].reshape(-1)
            corr[:, a, b] = corr[:, b, a] = v
    return np.asarray(cf.theta, np.float64), std, corr


def _noise_var(fitter: TileFitter, noise_map: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """(N, K, C) noise variance of each prediction: the fit's noise model at the predicted
    radiance, times the pixel's estimated scale s^2 (or the known variance itself)."""
    s2 = np.asarray(noise_map, np.float64).reshape(-1, 1, 1) ** 2
    if fitter.known_noise is not None:  # the map holds the known variance itself
        return np.broadcast_to(s2, mu.shape).copy()
    unit = np.asarray(fitter.noise.std(jnp.asarray(np.nan_to_num(mu))), np.float64)
    return s2 * unit * unit


def predictive(capture, cf: CaptureFit, discrepancy: Discrepancy | None = None) -> Predictive:
    """Posterior predictive moments of every photo of ``capture`` from the fit ``cf``, and
    its :class:`ModelCheck` flags (module docstring; the predictive check at the level
    :data:`~jaxrefl.svbrdf._check.PPC_ALPHA`, as every check of a fit). ``discrepancy``: the
    model-discrepancy term (:func:`estimate_discrepancy`; None: none).

    Every photo is predicted, the fit's own training photos and its held-out ones; only the
    held-out ones give an honest coverage (:meth:`Predictive.coverage`)."""
    disc = Discrepancy.zero() if discrepancy is None else discrepancy
    _k, h, w, _c = capture.shape
    if cf.theta.shape[0] != h * w:
        raise JaxreflError(
            f"the fit has {cf.theta.shape[0]} pixels and the capture {h * w}: predict the "
            "capture the fit was made of"
        )
    fitter = TileFitter(
        capture, replace(cf.job, compact=False), pooled=cf.pooled, width_terms=False
    )
    space = fitter.space
    theta, std, corr = _fit_arrays(cf, space)
    size = cf.job.tile_pixels
    dt = cf.job.dtype
    mus, pvs, forms, datas = [], [], [], []
    for s in range(0, h * w, size):
        e = min(s + size, h * w)
        d = pixel_block(capture, s, e, size, dtype=dt)

        def pad(a, e=e, s=s):
            out = np.full((size, *a.shape[1:]), np.nan, dt)
            out[: e - s] = a[s:e]
            return jnp.asarray(out)

        mu, pv, formed = _moments(fitter.residual, pad(theta), pad(std), pad(corr), d)
        mus.append(np.asarray(mu, np.float64)[: e - s])
        pvs.append(np.asarray(pv, np.float64)[: e - s])
        forms.append(np.asarray(formed)[: e - s])
        datas.append(jax.tree.map(lambda a, n=e - s: np.asarray(a)[:n], d))
    mean, pvar = np.concatenate(mus), np.concatenate(pvs)
    formed = np.concatenate(forms)
    obs = np.concatenate([d.obs for d in datas]).astype(np.float64)
    value = np.concatenate([(d.weight > 0) & (d.censored == 0) for d in datas])
    nvar = _noise_var(fitter, cf.maps["noise_std"], mean)
    dvar = disc(mean)
    if disc.replaces_noise:  # a variance function of the radiance in place of the noise
        if disc.error_var is not None:  # the parameter term at the measured noise
            err = np.interp(mean, disc.radiance, disc.error_var)
            train_use = np.concatenate([d.weight > 0 for d in datas]) & fitter.train[None, :, None]
            pvar = pvar * _rescale(nvar, err, train_use)[:, None, None]
        nvar, dvar = dvar, np.zeros_like(dvar)
    # The posterior predictive check on the pixel's own training photos (module docstring).
    # The capture's noise variance (the median over pixels), or the variance function itself.
    ref: np.ndarray | float = nvar
    if not disc.replaces_noise:
        ref = float(np.nanmedian(nvar[:, fitter.train])) if np.any(fitter.train) else np.nan
    use = value & fitter.train[None, :, None] & np.isfinite(mean)
    r2 = np.where(use, (obs - np.nan_to_num(mean)) ** 2, 0.0)
    # Floored at the smallest normal: only a variance function that is 0 somewhere reaches it.
    chi2 = np.sum(r2 / np.maximum(ref + dvar, np.finfo(np.float64).tiny), axis=(1, 2))
    dof = np.sum(use, axis=(1, 2)) - space.size
    fail = ppc_failed(chi2, dof, PPC_ALPHA)
    with np.errstate(divide="ignore", invalid="ignore"):
        ok_t = np.all(np.isfinite(theta), -1)
        dn = np.asarray(space.dnatural(jnp.asarray(np.where(ok_t[:, None], theta, 0.0))))
        theta_std = std / np.abs(dn)  # the delta method reversed (laplace_theta_std)
    check = bound_bits(space, theta, theta_std) | np.where(fail, int(ModelCheck.PPC_FAILED), 0)
    return Predictive(
        mean=mean,
        param_var=np.where(formed[:, None, None], pvar, 0.0),
        noise_var=nvar,
        disc_var=dvar,
        obs=obs,
        value=value,
        train=fitter.train.copy(),
        check=check.astype(np.uint32),
        chi2=chi2,
        dof=dof,
        no_covariance=~formed & np.all(np.isfinite(theta), -1),
        discrepancy=disc,
        noise_ref_var=float(np.nanmedian(ref)),
    )


def model_check(capture, cf: CaptureFit, discrepancy: Discrepancy | None = None) -> np.ndarray:
    """(H, W) uint32 :class:`ModelCheck` bits of a fit: the ``misspecified`` map."""
    h, w = capture.shape[1:3]
    return predictive(capture, cf, discrepancy).check.reshape(h, w)


# ----------------------------------------------------------------------------- discrepancy
def _rescale(v_fit: np.ndarray, v_new: np.ndarray, use: np.ndarray) -> np.ndarray:
    """(N,) f = 1 / mean over each pixel's ``use`` entries of v_fit / v_new: the factor that
    turns a Laplace covariance formed with noise variances ``v_fit`` (N, K, C) into one
    formed with ``v_new``; 1 where a pixel has no such entry."""
    # Floored at the smallest normal: only errors that are all 0 in a bin reach it.
    ratio = v_fit / np.maximum(v_new, np.finfo(np.float64).tiny)
    ok = use & np.isfinite(ratio)
    n = np.sum(ok, axis=(1, 2))
    mean = np.sum(np.where(ok, ratio, 0.0), axis=(1, 2)) / np.maximum(n, 1)
    return np.where((n > 0) & (mean > 0), 1.0 / np.where(mean > 0, mean, 1.0), 1.0)


def _solve_tau2(e2: np.ndarray, v: np.ndarray) -> float:
    """The smallest t >= 0 with median(e2 / (v + t)) <= the chi-square(1) median (bisection
    on a monotone function; 0 where the model's own variance already suffices)."""

    def excess(t):
        # Floored at the smallest normal: only v = 0 (no parameter term) at t = 0 reaches it,
        # where a ratio may overflow to inf, which reads as "too narrow" as it should.
        with np.errstate(over="ignore"):
            ratio = e2 / np.maximum(v + t, np.finfo(np.float64).tiny)
        return float(np.median(ratio)) - _CHI2_1_MEDIAN

    if e2.size == 0 or excess(0.0) <= 0:
        return 0.0
    lo, hi = 0.0, max(float(np.median(e2)) / _CHI2_1_MEDIAN, 1e-30)
    while excess(hi) > 0:
        hi *= 2.0
    for _ in range(60):  # 2^-60 of the bracket: far below any variance that matters
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if excess(mid) > 0 else (lo, mid)
    return hi


def estimate_discrepancy(
    capture,
    cf: CaptureFit,
    options: DiscrepancyOptions = _DISCREPANCY,
) -> Discrepancy:
    """tau^2(mu) from the training photos of ``cf`` alone (module docstring), under
    ``options`` (:class:`DiscrepancyOptions`: rows, bins, seed, the noise model).

    ``max_pixels`` rows in all (pixels x training photos; at least 256 pixels a photo), drawn
    at random with ``seed``; ``bins`` quantile bins of predicted radiance. Each held-out
    training photo is predicted by the job's model fitted on the other training photos, in
    stacked rows of the job's tile size (the fit's compiled programs serve). For ``pooled``,
    the shared width and F0 prior are the job's (chosen on all its training photos), so each
    row's fit has seen its photo through them: slightly optimistic.

    ``replace_noise``: estimate the whole observation variance beyond the parameter term,
    v(mu), the same way (median-matched per bin, against the parameter variance alone) and
    use it in place of the fit's noise term: a heteroscedastic noise model measured on
    held-out training photos, for a fit whose one noise scale (``pooled``'s) is too wide for
    dark pixels and too narrow for bright ones. None (the default): True exactly when the
    fit's noise is one known variance for the capture (``pooled``), False where each pixel
    has its own estimate (the per-pixel models)."""
    max_pixels, bins, seed = options.max_pixels, options.bins, options.seed
    replace_noise = options.replace_noise
    k = capture.n_photos
    train = [i for i in range(k) if i not in cf.job.holdout]
    if len(train) < 2:
        return Discrepancy.zero()
    fitter = TileFitter(
        capture, replace(cf.job, compact=False), pooled=cf.pooled, width_terms=False
    )
    if replace_noise is None:
        replace_noise = fitter.known_noise is not None
    per = max(256, max_pixels // len(train))
    data = subsample(capture, per, seed, cf.job.dtype)
    size = cf.job.tile_pixels
    stacked, mask, held = stack_folds(data, train, k, size)
    e2s, vs, mus, rows_f = [], [], [], []
    for s in range(0, mask.shape[0], size):
        part = slice(s, s + size)
        d = jax.tree.map(lambda a, p=part: a[p], stacked)
        out = fitter(d, size, mask[part])
        mu, pv, formed = _moments(
            fitter.residual,
            jnp.asarray(out["theta"]),
            jnp.asarray(out["std"]),
            jnp.asarray(out["corr"]),
            d,
        )
        hk = held[part]
        rows = np.flatnonzero(hk >= 0)
        if rows.size == 0:
            continue
        mu_all = np.asarray(mu, np.float64)[rows]
        nv_all = _noise_var(fitter, np.sqrt(out["noise_var"])[rows], mu_all)
        mu = mu_all[np.arange(rows.size), hk[rows]]
        pv = np.asarray(pv, np.float64)[rows, hk[rows]]
        pv = np.where(np.asarray(formed)[rows, None], pv, 0.0)
        nv = nv_all[np.arange(rows.size), hk[rows]]
        y = np.asarray(d.obs, np.float64)[rows, hk[rows]]
        ok = (np.asarray(d.weight)[rows, hk[rows]] > 0) & (
            np.asarray(d.censored)[rows, hk[rows]] == 0
        )
        ok &= np.isfinite(mu) & np.isfinite(nv)
        e2s.append(((y - mu) ** 2)[ok])
        vs.append((pv if replace_noise else pv + nv)[ok])
        mus.append(mu[ok])
        if replace_noise:  # what the rescaling of this row's parameter term needs
            use = (np.asarray(d.weight)[rows] > 0) & mask[part][rows][:, :, None]
            rows_f.append((mu_all, nv_all, use, np.nonzero(ok)[0]))
    e2, v, m = (np.concatenate(x) if x else np.zeros(0) for x in (e2s, vs, mus))
    if e2.size == 0:
        return Discrepancy.zero()
    edges = np.quantile(m, np.linspace(0.0, 1.0, bins + 1))
    which = np.clip(np.searchsorted(edges, m, side="right") - 1, 0, bins - 1)
    live = [b for b in range(bins) if np.any(which == b)]
    centres = np.asarray([float(np.median(m[which == b])) for b in live])
    order = np.argsort(centres)

    def solve(v):
        return np.asarray([_solve_tau2(e2[which == b], v[which == b]) for b in live])[order]

    if not replace_noise:
        return Discrepancy(centres[order], solve(v), int(e2.size), tuple(train))
    # The errors' own variance function, then each held-out value's parameter term rescaled
    # by its row's factor under it (module docstring).
    err = Discrepancy(centres[order], solve(np.zeros_like(v)))
    f = np.concatenate([_rescale(nv, err(mu), use)[i] for mu, nv, use, i in rows_f])
    return Discrepancy(centres[order], solve(v * f), int(e2.size), tuple(train), True, err.var)

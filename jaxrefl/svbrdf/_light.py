"""The flash as a light to estimate: its offset from the lens, a gain per photo, their posterior.

Every capture layout states where the flash was (for a phone: at the lens) and one power for
every photo. A phone's flash sits 0.5-1.5 cm from its lens, and phones change exposure and
flash output from shot to shot. The capture-level light parameters are

    p_k = p_k^stated + R_k d        (cm)      the flash position of photo k
    I_kc = g_k I_kc^stated                    its intensity

* ``d`` (3,): the flash's offset from the stated position. Frame: the camera's (x right,
  y down, z forward) where the capture gives each photo's camera orientation R_k (the
  ``camera_orientation`` of ``calibration.json``, written by ``jaxrefl capture``: a phone
  turned between shots carries its flash with it); otherwise the sample's (x, y in the
  sample plane, z up: R_k = I), which assumes the phone is held the same way for every
  photo.
* ``g_k`` (K,): the photo's gain (flash output times exposure) relative to the stated power.
  Their geometric mean over the training photos is fixed at that of their prior means (a
  common factor of every gain is a common factor of every map, which the photos cannot
  tell apart). Prior from the photos' EXIF exposure (:mod:`jaxrefl.svbrdf._light_prior`).
  A held-out photo keeps its prior gain: estimating it would use the photo.
* Prior on ``d``: N(0, diag(``OFFSET_PRIOR_CM``)^2): a flash within a few cm of the lens in
  x and y, within a few mm of the lens's plane in z (the phone's normal in either frame,
  when the phone faces the sample). x and y are estimated; z is not: it changes every
  photo's irradiance nearly alike, which the maps absorb, so the photos pin it only through
  what the model misses, and it keeps its prior (mean 0, its std in the covariance).

Estimation: each pixel's albedo, F0 and GGX width profiled out on a pixel subsample,
Levenberg-Marquardt on the light, a noise scale linear in the prediction
(:mod:`jaxrefl.svbrdf._light_problem`). Laplace: the covariance of (d, log g) is
(J^T J + P)^-1 at the optimum, J the whitened profiled residual's Jacobian (its Gauss-Newton
curvature is the Schur complement of the per-pixel parameters: the light's marginal
curvature) and P the prior's precision. It holds where the residuals are the noise model's;
real photos' are not, and the reported covariance is the Laplace's with the offset widened,
direction by direction, to the spread of its delete-one-photo jackknife where that is wider
(:mod:`jaxrefl.svbrdf._light_cov`); gains' std by the delta method, g std(log g).
:func:`light_draws` samples that Gaussian, and the maps' light term
(:mod:`jaxrefl.svbrdf._light_map`) propagates it.

Kept only where held-out observations support it (``auto``, :func:`estimate_light`): the
subsample is split into two halves of pixels; for each candidate (``fixed``, ``offset``,
``offset+gains``) the light is estimated on one half and scored on the other by
leave-one-photo-out over the training photos under one shared width, the one that predicts
the first half's training photos best held out in turn (each pixel's coefficients fitted on
the other photos, photo j predicted at its prior gain), and the halves swap. The simplest
candidate within :data:`jaxrefl.svbrdf.TOLERANCE` (relative) of the lowest RMSE wins, as
``auto`` chooses models, and a candidate must also win by more than its margin's noise over
the photos (:func:`choose_light`). Everything is deterministic given the capture and the held-out
photos (a fixed subsample seed, a NumPy optimiser), so every process of a distributed fit
finds the same light.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import jax
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl._names import LIGHT_CHOICES

from ._light_cov import COVARIANCE, robust_cov
from ._light_options import LightOptions
from ._light_prior import GainPrior, gain_prior
from ._light_problem import (
    ESTIMATED_OFFSET,
    OFFSET_PRIOR_CM,
    SELECTION_PIXELS,
    LightProblem,
    light_problem,
)

__all__ = [  # the problem's and the prior's public names are re-exported from here
    "LIGHT_CHOICES",
    "LIGHT_MODES",
    "GainPrior",
    "LightEstimate",
    "LightProblem",
    "estimate_light",
    "gain_prior",
    "light_draws",
    "light_problem",
]

LIGHT_MODES: tuple[str, ...] = LIGHT_CHOICES[:3]  # the estimates; "auto" picks one
_Z90 = 1.6448536269514722  # the standard normal's 95% quantile: a central 90% interval
# A more complex light must lower the held-out squared error by this many standard errors of
# the paired difference over the training photos: a one-sided test at about 2.3%
# (:func:`choose_light`).
CHOICE_Z = 2.0


@dataclass(frozen=True)
class LightEstimate:
    """The capture's light (module docstring) and the evidence for it.

    mode:        what was estimated: ``fixed``, ``offset`` or ``offset+gains``
    asked:       the job's ``light`` (``auto`` or one of the modes)
    offset_cm:   d (3,), in ``frame``; offset_std_cm its std from ``cov`` (None: fixed)
    photo_gain:  g (K,); photo_gain_std (K,) (0 for a gain not estimated but known from
                 EXIF, its prior's std where held out, None when fixed)
    estimated:   (K,) whether each photo's gain was estimated
    corr:        correlation matrix over ``labels`` (offset x, y, z, then log gains)
    cov:         their covariance (3 + K, 3 + K) (a held-out photo's log gain: its prior
                 variance, independent of the rest): the Laplace's, its offset widened to
                 the delete-one-photo jackknife's where that is wider
                 (:mod:`jaxrefl.svbrdf._light_cov`); None when fixed
    cov_laplace: the Laplace covariance alone, the posterior's if the noise model held
    cv_rmse:     held-out RMSE per candidate (``auto``), under the shared width
    model_cv_rmse: held-out RMSE of the job's named model under the estimate ``auto`` kept
                 and under ``fixed`` (:mod:`jaxrefl.svbrdf._light_check`); empty where not
                 checked
    why:         one sentence, the form of ``auto``'s
    offset_source: where ``auto`` scored the candidates, its problem, for the ``offset``
                 estimate of the same pixels, seed and held-out photos (:class:`OffsetSource`)
    """

    mode: str
    asked: str
    offset_cm: np.ndarray
    photo_gain: np.ndarray
    offset_std_cm: np.ndarray | None = None
    photo_gain_std: np.ndarray | None = None
    estimated: np.ndarray | None = None
    labels: tuple[str, ...] = ()
    corr: np.ndarray | None = None
    cov: np.ndarray | None = None
    cov_laplace: np.ndarray | None = None
    cv_rmse: dict[str, float] = field(default_factory=dict)
    model_cv_rmse: dict[str, float] = field(default_factory=dict)
    why: str = ""
    frame: str = ""
    prior: GainPrior | None = None
    noise: tuple[float, float] | None = None
    pixels: int = 0
    iterations: int = 0
    rot: np.ndarray | None = None
    offset_source: OffsetSource | None = field(default=None, compare=False, repr=False)

    def apply(self, capture, offset_cm=None, photo_gain=None):
        """``capture`` (as its files state the light) with this light: flash at p + R d,
        power g I (module docstring); ``offset_cm`` (3,) and ``photo_gain`` (K,) in place of
        the estimate's, e.g. one of :func:`light_draws`."""
        off = self.offset_cm if offset_cm is None else np.asarray(offset_cm, np.float64)
        gain = self.photo_gain if photo_gain is None else np.asarray(photo_gain, np.float64)
        if np.all(off == 0.0) and np.all(gain == 1.0):
            return capture
        rot = np.broadcast_to(np.eye(3), (capture.n_photos, 3, 3)) if self.rot is None else self.rot
        return replace(
            capture,
            light_pos=capture.light_pos + np.einsum("kij,j->ki", rot, off),
            light_power=capture.light_power * gain[:, None],
        )

    def interval90(self) -> dict[str, list[list[float]]] | None:
        """Central 90% intervals of the offset (cm) and gains (log-normal) of ``cov``'s
        Gaussian."""
        if self.offset_std_cm is None or self.photo_gain_std is None:
            return None
        lo = self.offset_cm - _Z90 * self.offset_std_cm
        hi = self.offset_cm + _Z90 * self.offset_std_cm
        sl = self.photo_gain_std / self.photo_gain
        return {
            "offset_cm": [lo.tolist(), hi.tolist()],
            "photo_gain": [
                (self.photo_gain * np.exp(-_Z90 * sl)).tolist(),
                (self.photo_gain * np.exp(_Z90 * sl)).tolist(),
            ],
        }

    def as_dict(self) -> dict[str, Any]:
        def lst(a):
            return None if a is None else [float(v) for v in np.asarray(a).ravel()]

        return {
            "mode": self.mode,
            "asked": self.asked,
            "frame": self.frame,
            "offset_cm": lst(self.offset_cm),
            "offset_std_cm": lst(self.offset_std_cm),
            "offset_std_cm_laplace": None
            if self.cov_laplace is None
            else lst(np.sqrt(np.diag(self.cov_laplace)[:3])),
            "covariance": None if self.cov is None else COVARIANCE,
            "photo_gain": lst(self.photo_gain),
            "photo_gain_std": lst(self.photo_gain_std),
            "photo_gain_estimated": None
            if self.estimated is None
            else [bool(v) for v in self.estimated],
            "interval90": self.interval90(),
            "labels": list(self.labels),
            "corr": None if self.corr is None else np.asarray(self.corr).tolist(),
            "why": self.why,
            "cv_rmse": dict(self.cv_rmse),
            "model_cv_rmse": dict(self.model_cv_rmse),
            "gain_prior": None if self.prior is None else self.prior.as_dict(),
            "noise_model": None
            if self.noise is None
            else {"sigma0": self.noise[0], "sigma_per_radiance": self.noise[1]},
            "pixels": self.pixels,
            "iterations": self.iterations,
        }


@dataclass(eq=False)
class OffsetSource:
    """``auto``'s light problem (its pixel subsample, seed and held-out photos), kept with the
    light it chose, for the ``offset`` estimate of the capture: an uncertainty map whose fit
    kept the stated light after scoring an offset draws its lens-position spread from that
    estimate (:mod:`jaxrefl.svbrdf._light_map`). ``auto`` scores the offset on pixel halves
    and does not need the estimate on both, so it is computed on first use (about as long
    as ``auto``'s score), then kept; where ``auto`` kept ``offset``, it is that estimate.
    Either way it is what :func:`estimate_light` with ``light="offset"`` and ``on``'s
    arguments returns for the capture, with no second problem built and no second solve.

    on: what it is computed on: the capture's shape, the held-out photos, ``n_pixels``,
    ``seed`` and ``alpha_min`` of :func:`estimate_light`.
    """

    problem: LightProblem
    on: dict[str, Any]
    kept: LightEstimate | None = None

    def estimate(self) -> LightEstimate:
        if self.kept is None:
            with jax.enable_x64(True):
                self.kept = _final(self.problem, "offset", "offset", {}, _AS_ASKED.format("offset"))
        return self.kept

    def serves(self, capture, holdout, alpha_min) -> bool:
        """Whether the estimate is the one :func:`estimate_light` would give ``capture``
        with these held-out photos and ``alpha_min`` at its default pixels and seed."""
        return self.on == _basis(capture, holdout, SELECTION_PIXELS, 0, alpha_min)


_AS_ASKED = "as asked (light {}); not scored against fixed"


def _basis(capture, holdout, n_pixels, seed, alpha_min) -> dict[str, Any]:
    k = capture.n_photos
    return {
        "shape": tuple(capture.shape),
        "holdout": tuple(sorted({int(i) for i in holdout if 0 <= i < k})),
        "n_pixels": int(n_pixels),
        "seed": seed,
        "alpha_min": None if alpha_min is None else float(alpha_min),
    }


def fixed_light(capture, asked: str, why: str) -> LightEstimate:
    k = capture.n_photos
    return LightEstimate(
        "fixed",
        asked,
        np.zeros(3),
        np.ones(k),
        why=why,
        frame="as the capture states",
    )


def _tolerance() -> float:
    from ._auto import TOLERANCE

    return TOLERANCE


def _final(problem: LightProblem, mode: str, asked: str, cv: dict, why: str) -> LightEstimate:
    both = [0, 1]
    theta, _r, _j, it1 = problem.solve(mode, both, problem.unit_weights(both))
    weights, noise = problem.noise_weights(theta, mode, both)
    theta, _r, jac, it2 = problem.solve(mode, both, weights, theta0=theta)
    problem.weights = weights
    x0, a = problem.embed(mode)
    x = x0 + a @ theta
    # Laplace (the whitened J, prior rows included, gives the posterior precision), widened
    # where the photos scatter the estimate more than the noise model allows (._light_cov).
    rc = robust_cov(problem, mode, theta, jac, weights, ESTIMATED_OFFSET)
    k = problem.k
    held = 3 + np.flatnonzero(~problem.train)

    def natural(c_theta):
        cov = a @ c_theta @ a.T
        if mode == "offset+gains":
            cov[held, held] = problem.prior.log_std**2
        # The offset's components not estimated keep their prior (independent of the rest).
        for i in range(ESTIMATED_OFFSET, 3):
            cov[i, i] = OFFSET_PRIOR_CM[i] ** 2
        return cov

    cov, cov_laplace = natural(rc.cov), natural(rc.laplace)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    gain = np.exp(x[3:])
    est = np.zeros(k, bool) if mode != "offset+gains" else problem.train.copy()
    g_std = gain * std[3:] if mode == "offset+gains" else np.zeros(k)
    labels = ("offset_x", "offset_y", "offset_z", *[f"log_gain_{i}" for i in range(k)])
    return LightEstimate(
        mode,
        asked,
        x[:3],
        gain,
        offset_std_cm=std[:3],
        photo_gain_std=g_std,
        estimated=est,
        labels=labels,
        corr=corr,
        cov=cov,
        cov_laplace=cov_laplace,
        cv_rmse=cv,
        why=why,
        frame=problem.frame,
        prior=problem.prior,
        noise=noise,
        pixels=int(sum(h.obs.shape[0] for h in problem.halves)),
        iterations=it1 + it2,
        rot=np.asarray(problem.halves[0].rot),
    )


def choose_light(problem: LightProblem) -> tuple[str, dict[str, float], str]:
    """Score ``fixed``, ``offset`` and ``offset+gains`` by the cross-fitted held-out RMSE
    (module docstring). A candidate is kept over the simpler ones only where it wins by more
    than the tolerance and by more than :data:`CHOICE_Z` standard errors of its gain, the
    sum over the training photos of each photo's paired difference of held-out squared
    errors (both halves' pixels): the photos are the replicates, sqrt(G var) the standard
    error over G of them. What the model misses is correlated over a photo's pixels (a
    misplaced highlight spans many, a photo's own exposure or flash beam moves them all),
    so the pixels are not independent replicates: a light that helps some photos' pixels a
    great deal and costs another photo's as much wins by many per-pixel standard errors
    and by none over photos (the photo is the unit of misfit, as in the covariance's
    jackknife: :mod:`jaxrefl.svbrdf._light_cov`). Returns the choice, the RMSEs and the
    margins' account."""
    per: dict[str, np.ndarray] = {}
    cnt = np.zeros(0)
    for mode in LIGHT_MODES:
        parts, counts = [], []
        for fit_half, score_half in ((0, 1), (1, 0)):
            if mode == "fixed":
                theta = np.zeros(0)
            else:
                theta = problem.solve(mode, [fit_half], problem.unit_weights([fit_half]))[0]
            s, n = problem.loo_sse(theta, mode, fit_half, score_half)
            parts.append(s)
            counts.append(n)
        per[mode] = np.concatenate(parts, 1)  # (K, N): each photo's error at each pixel
        cnt = np.concatenate(counts, 1)
    total = float(cnt.sum())
    cv = {m: float(np.sqrt(v.sum() / total)) if total > 0 else float("inf") for m, v in per.items()}
    chosen = "fixed"
    notes = []
    for mode in LIGHT_MODES[1:]:
        # each training photo's gain (> 0 where the candidate predicts it better)
        diff = (per[chosen] - per[mode]).sum(1)[problem.train]
        se = float(np.sqrt(diff.size * np.var(diff, ddof=1)))
        gain = float(diff.sum())
        margin = max(CHOICE_Z * se, per[chosen].sum() * (1.0 - 1.0 / (1.0 + _tolerance()) ** 2))
        won = gain > margin
        verdict = "beats" if won else "does not beat"
        notes.append(f"{mode} {verdict} {chosen} by {gain / max(se, 1e-300):.1f} standard errors")
        if won:
            chosen = mode
    return chosen, cv, "; ".join(notes)


def estimate_light(
    capture, light: str = "auto", options: LightOptions | None = None
) -> LightEstimate:
    """The light of ``capture`` (module docstring): ``light`` one of :data:`LIGHT_CHOICES`;
    ``fixed`` returns the stated light. ``options``: the held-out photos (never looked at),
    the subsample's pixels and seed, and the narrowest lobe (:class:`LightOptions`; None:
    its defaults)."""
    o = LightOptions() if options is None else options
    holdout, n_pixels, seed, alpha_min = o.holdout, o.n_pixels, o.seed, o.alpha_min
    if light not in LIGHT_CHOICES:
        raise JaxreflError(f"light must be one of {', '.join(LIGHT_CHOICES)}, not {light!r}")
    if light == "fixed":
        return fixed_light(capture, light, "as asked (light fixed)")
    if capture.light_pos is None:
        return fixed_light(capture, light, "directional lights: there is no flash to place")
    train = np.ones(capture.n_photos, bool)
    train[[i for i in holdout if 0 <= i < capture.n_photos]] = False
    n_train = int(train.sum())
    # Each leave-one-out fold of the score fits a pixel's width and two columns per channel
    # on the other training photos (two at least) and predicts one.
    need = 3
    if light == "auto" and n_train < need:
        return fixed_light(
            capture,
            light,
            f"{n_train} training photos: scoring the light by leave-one-photo-out needs {need}",
        )
    with jax.enable_x64(True):
        problem = light_problem(capture, train, n_pixels=n_pixels, seed=seed, alpha_min=alpha_min)
        if light == "auto":
            chosen, cv, margins = choose_light(problem)
            why = (
                f"held-out RMSE over {n_train} training photos, light fitted on one half "
                "of the pixels and scored on the other: "
                + ", ".join(f"{m} {r:.5f}" for m, r in cv.items())
                + f"; {margins}"
            )
            if chosen != "fixed":
                why += f" ({cv[chosen] / cv['fixed']:.2f} x fixed's)"
            source = OffsetSource(problem, _basis(capture, holdout, n_pixels, seed, alpha_min))
            if chosen == "fixed":
                est = fixed_light(capture, light, why)
                return replace(est, cv_rmse=cv, prior=problem.prior, offset_source=source)
            est = _final(problem, chosen, light, cv, why)
            if chosen == "offset":
                why_offset = _AS_ASKED.format("offset")
                source.kept = replace(est, asked="offset", cv_rmse={}, why=why_offset)
            return replace(est, offset_source=source)
        return _final(problem, light, light, {}, _AS_ASKED.format(light))


def light_draws(estimate: LightEstimate, n: int, seed=0) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` draws (offset_cm (3,), photo_gain (K,)) of the light from its posterior:
    (d, log g) ~ N((offset_cm, log photo_gain), ``estimate.cov``) (module docstring), the
    gains log-normal; a held-out photo's gain from its prior. The covariance is singular
    where the gains' geometric mean is fixed (and in ``offset``, which estimates no gain):
    drawn through its eigendecomposition, the draws keep those constraints exactly. A
    ``fixed`` light has no covariance: every draw is the stated light. Each draw gives the
    capture that light through ``estimate.apply(capture, *draw)``, ``capture`` as its
    files state the light (not one the estimate was already applied to). ``seed``: an int
    or a NumPy ``Generator``."""
    if n < 0:
        raise JaxreflError(f"light_draws needs n >= 0, not {n}")
    off = np.asarray(estimate.offset_cm, np.float64)
    gain = np.asarray(estimate.photo_gain, np.float64)
    if estimate.cov is None:
        return [(off.copy(), gain.copy()) for _ in range(n)]
    mean = np.concatenate([off, np.log(gain)])
    vals, vecs = np.linalg.eigh(np.asarray(estimate.cov, np.float64))
    # Round-off leaves the constrained directions' eigenvalues a hair either side of 0: below
    # numpy's numerical-rank tolerance (largest x size x eps, as matrix_rank) they are 0, so
    # the draws keep the constraints to round-off.
    tol = max(vals.max(), 0.0) * vals.size * np.finfo(np.float64).eps
    root = vecs * np.sqrt(np.where(vals > tol, vals, 0.0))
    rng = np.random.default_rng(seed)
    xs = mean + rng.standard_normal((n, mean.size)) @ root.T
    return [(x[:3], np.exp(x[3:])) for x in xs]

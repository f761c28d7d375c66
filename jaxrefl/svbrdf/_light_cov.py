"""The light's reported covariance: the Laplace's, widened to the spread of the
leave-one-photo-out estimates where the photos disagree more than the noise model allows.

The Laplace covariance L = (J^T J + P)^-1 (:mod:`jaxrefl.svbrdf._light`: J the whitened
profiled residuals' Jacobian, P the prior's precision) is the posterior's when the whitened
residuals are the noise model's: independent, unit variance. On real photos they are not:
what the model misses (a flash beam that is not isotropic, a surface the BRDF does not
describe, a photo's own misregistration) is correlated over a photo's pixels, and each photo
pulls the light its own way by far more than its noise allows (on the real captures the
offsets of the leave-one-photo-out folds spread tens of times wider than the Laplace std:
``docs/benchmarks.md``, ``real_captures_light``). The photo is the unit that misfit comes
in, so the spread is measured over photos: the delete-one-photo jackknife (Quenouille 1956;
Tukey 1958; Efron & Tibshirani 1993, *An Introduction to the Bootstrap*, ch. 11; photos as
the deleted groups)

    V = (G - 1) / G  sum_k (d_(k) - mean) (d_(k) - mean)^T

over the G training photos, d_(k) the offset's x and y estimated without photo k. Each d_(k)
is at most :data:`JACKKNIFE_STEPS` steps of the estimate's own optimiser
(:meth:`jaxrefl.svbrdf.LightProblem.solve`: the profiled cost's own gradient with the
projected curvature, a step taken only where it lowers the cost) from the estimate on the
same pixels and weights with photo k's weight 0, every pixel's width and coefficients
profiled again without it. Steps on the projected gradient instead stop where that, not the
cost's slope, vanishes: each pixel's width sits off its exact stationary point by a fraction
of its search's spacing, and a fold's re-estimate would stop short of its optimum by an amount
that differs from fold to fold (on a real capture one step, the infinitesimal jackknife with
the pixels' refit, falls
well short of the full re-estimates' spread, and the clustered sandwich, which leaves the
pixels' refit out, falls shorter: with seven parameters a pixel and a handful of photos,
every photo is a point of high leverage). The cost: per training photo, at most
:data:`JACKKNIFE_STEPS` + 1 evaluations of the profiled cost and of its Jacobian.

The reported covariance is the wider of L and V in every direction of the offset: with
M = L_oo^-1/2 V L_oo^-1/2, its eigenvalues floored at 1, the offset's block becomes
W = L_oo^1/2 M' L_oo^1/2; the gains keep their Laplace law given the offset (their
regression on it and their conditional covariance), so cov_go = B W, cov_gg = B W B^T + E
with B = L_go L_oo^-1 and E = L_gg - B L_oo B^T. Where the model holds V equals L up to its
own noise (from G photos, about sqrt(2 / (G - 1)) relative in a variance; the jackknife's
is biased up, Efron & Stein 1981), and the floor keeps the Laplace, a little conservative.
A gain is pinned by its own photo alone, so deleting photos says nothing of it: its
misfit is not measured (the gains keep the Laplace's conditional law). With fewer than
:data:`JACKKNIFE_MIN_PHOTOS` training photos the Laplace stands.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

__all__ = ["COVARIANCE", "JACKKNIFE_MIN_PHOTOS", "JACKKNIFE_STEPS", "LightCov", "robust_cov"]

JACKKNIFE_STEPS = 3
JACKKNIFE_MIN_PHOTOS = 3  # the spread of two estimates is one difference: no covariance
COVARIANCE = (
    "Laplace, the offset widened to the delete-one-photo jackknife's covariance where that is wider"
)


@dataclass(frozen=True)
class LightCov:
    """cov: the reported covariance of theta (module docstring); laplace: (J^T J + P)^-1;
    jackknife: V of the offset's estimated components (None: too few photos); folds: each
    training photo's estimate d_(k) (G, n_offset)."""

    cov: np.ndarray
    laplace: np.ndarray
    jackknife: np.ndarray | None = None
    folds: np.ndarray | None = None


def _sym_pow(a: np.ndarray, power: float) -> np.ndarray:
    vals, vecs = np.linalg.eigh(a)
    return (vecs * vals**power) @ vecs.T


def widen(laplace: np.ndarray, spread: np.ndarray, n_off: int) -> np.ndarray:
    """``laplace`` (P, P) with its first ``n_off`` coordinates' block widened to ``spread``
    (n_off, n_off) where that is wider, the rest keeping its law given them (module
    docstring)."""
    o, g = slice(0, n_off), slice(n_off, None)
    l_oo = laplace[o, o]
    root, inv_root = _sym_pow(l_oo, 0.5), _sym_pow(l_oo, -0.5)
    m = inv_root @ spread @ inv_root
    vals, vecs = np.linalg.eigh(0.5 * (m + m.T))
    w = root @ ((vecs * np.maximum(vals, 1.0)) @ vecs.T) @ root
    b = np.linalg.solve(l_oo, laplace[o, g]).T  # (P - n_off, n_off)
    e = laplace[g, g] - b @ l_oo @ b.T
    cov = np.empty_like(laplace)
    cov[o, o] = w
    cov[g, o] = b @ w
    cov[o, g] = (b @ w).T
    cov[g, g] = b @ w @ b.T + e
    return 0.5 * (cov + cov.T)


def robust_cov(problem, mode: str, theta: np.ndarray, jac: np.ndarray, weights, n_off: int):
    """The light's covariance of theta (module docstring) at the estimate ``theta`` of
    ``problem`` (:class:`jaxrefl.svbrdf.LightProblem`) in ``mode``, ``jac`` the whitened
    Jacobian there (prior rows included), ``weights`` the fit's per half, ``n_off`` the
    offset's estimated components (the first of theta)."""
    laplace = np.linalg.inv(jac.T @ jac)
    photos = np.flatnonzero(problem.train)
    if n_off == 0 or photos.size < JACKKNIFE_MIN_PHOTOS:
        return LightCov(laplace, laplace)
    both = list(range(len(problem.halves)))
    folds = []
    for k in photos:
        drop = jnp.asarray(np.arange(problem.k) != k, jnp.float64)[None, :, None]
        w_k = [w * drop for w in weights]
        t = problem.solve(mode, both, w_k, theta0=theta, max_iter=JACKKNIFE_STEPS)[0]
        folds.append(t[:n_off])
    d = np.asarray(folds)
    g = d.shape[0]
    dev = d - d.mean(0)
    spread = (g - 1) / g * dev.T @ dev
    return LightCov(widen(laplace, spread, n_off), laplace, spread, d)

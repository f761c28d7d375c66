"""Capture planning: which light/view pair to measure next, by expected Fisher information.

For a material with current estimate theta (unconstrained parameters of a
:class:`~jaxrefl.fit.ParamSpace`; a fit, or a prior guess), observation k in channel c
predicts y_kc = f_r(x(theta); wi_k, wo_k)_c s_kc (``scale`` s: 1 for f_r samples, cos_i for
the cosine-weighted residual of :func:`jaxrefl.measured.fit_model`, E cos_i for radiance)
with Gaussian noise of std sigma_kc. Its Fisher information about theta is

    I_k = sum_c j_kc j_kc^T / sigma_kc^2,      j_kc = d y_kc / d theta      (P x P)

and the Gauss-Newton (Laplace) posterior after a set S of measurements has precision
A_S = Lambda_0 + sum_{k in S} I_k (Lambda_0: the prior precision, default I / tau^2 with
tau = 3 as in the pruning evidence). The D-optimal criterion (Chaloner & Verdinelli 1995,
Bayesian experimental design, section 2.2) ranks a candidate c by the expected information
gain

    gain_c = ln det(A_S + I_c) - ln det(A_S)       [nats]

i.e. how much the volume of the posterior shrinks. :func:`rank_candidates` computes it for
every candidate (with the std of every parameter after adding it, e.g. of log alpha, so a
roughness-only choice is possible too) and recommends the best; :func:`greedy_design`
repeats the choice n times at fixed theta (the information of a Gaussian model does not
depend on the yet unseen values). In a capture loop, refit after each measurement and rank
again (``benchmarks/capture_planning.py`` does that).
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF
from jaxrefl.fit import ParamSpace

__all__ = ["Ranking", "greedy_design", "information", "posterior_std", "rank_candidates"]

# Default prior width in theta units (the pruning evidence uses the same).
PRIOR_WIDTH = 3.0


@eqx.filter_jit
def _info(model: BRDF, space: ParamSpace, theta, wi, wo, scale, inv_var):
    def pred(t):
        p = space.to_natural(t)
        return model.eval(p, wi, wo) * scale  # (M, C)

    jac = jax.jacfwd(pred)(theta)  # (M, C, P)
    return jnp.einsum("mcp,mcq,mc->mpq", jac, jac, inv_var)


def information(
    model: BRDF,
    space: ParamSpace,
    theta: Float[Array, " P"],
    wi: Float[Array, "M 3"],
    wo: Float[Array, "M 3"],
    *,
    scale: Float[Array, "M C"] | None = None,
    sigma: float | np.ndarray = 1.0,
) -> np.ndarray:
    """(M, P, P) Fisher information I_k of each observation (module docstring).

    scale: per observation and channel (default 1); sigma: noise std, a number or (M, C).
    Observations below the horizon carry no information (the model is 0 there).
    """
    theta = jnp.asarray(theta)
    dt = theta.dtype
    wi = jnp.asarray(wi, dt)
    wo = jnp.asarray(wo, dt)
    m, c = wi.shape[0], space.channels
    s = jnp.ones((m, c), dt) if scale is None else jnp.broadcast_to(jnp.asarray(scale, dt), (m, c))
    sig = jnp.broadcast_to(jnp.asarray(sigma, dt), (m, c))
    return np.asarray(_info(model, space, theta, wi, wo, s, 1.0 / (sig * sig)), np.float64)


def _logdet(a: np.ndarray) -> np.ndarray:
    sign, ld = np.linalg.slogdet(a)
    # A precision matrix that lost positive definiteness to round-off has no volume.
    return np.where(sign > 0, ld, -np.inf)


def posterior_std(precision: np.ndarray) -> np.ndarray:
    """Per-parameter std (theta units) of a Gaussian with this precision (..., P, P)."""
    cov = np.linalg.inv(precision)
    return np.sqrt(np.maximum(np.diagonal(cov, axis1=-2, axis2=-1), 0.0))


@dataclass(frozen=True)
class Ranking:
    """Candidates ranked by expected information gain.

    order:     (M,) candidate indices, best first
    gain:      (M,) ln det(A + I_c) - ln det(A), nats
    std_after: (M, P) posterior std of every theta entry after adding the candidate
    std_now:   (P,) posterior std before
    labels:    names of the theta entries (``ParamSpace.labels``)
    """

    order: np.ndarray
    gain: np.ndarray
    std_after: np.ndarray
    std_now: np.ndarray
    labels: tuple[str, ...]

    @property
    def best(self) -> int:
        """The recommended next measurement (index into the candidates)."""
        return int(self.order[0])

    def std_of(self, label: str) -> np.ndarray:
        """(M,) std of the entry ``label`` (e.g. ``"alpha"``: the std of ln alpha, since
        alpha's theta is ln(alpha - 1e-4)) after each candidate."""
        return self.std_after[:, self.labels.index(label)]


def _prior(space: ParamSpace, prior_precision: np.ndarray | None) -> np.ndarray:
    if prior_precision is None:
        return np.eye(space.size) / PRIOR_WIDTH**2
    return np.asarray(prior_precision, np.float64)


def rank_candidates(
    model: BRDF,
    space: ParamSpace,
    theta: Float[Array, " P"],
    cand_wi: Float[Array, "M 3"],
    cand_wo: Float[Array, "M 3"],
    *,
    measured_wi: Float[Array, "K 3"] | None = None,
    measured_wo: Float[Array, "K 3"] | None = None,
    scale=None,
    cand_scale=None,
    sigma: float = 1.0,
    prior_precision: np.ndarray | None = None,
) -> Ranking:
    """Rank candidate pairs (cand_wi[m], cand_wo[m]) by D-optimal gain given what was
    already measured (``measured_*``; none = the prior alone) at estimate ``theta``."""
    a = _prior(space, prior_precision)
    if measured_wi is not None:
        if measured_wo is None:
            raise JaxreflError("give measured_wo together with measured_wi")
        info = information(model, space, theta, measured_wi, measured_wo, scale=scale, sigma=sigma)
        a = a + info.sum(axis=0)
    ic = information(model, space, theta, cand_wi, cand_wo, scale=cand_scale, sigma=sigma)
    after = a[None] + ic
    gain = _logdet(after) - _logdet(a)
    order = np.argsort(-gain, kind="stable")
    return Ranking(order, gain, posterior_std(after), posterior_std(a), space.labels)


def greedy_design(
    info: np.ndarray,
    n: int,
    *,
    start: np.ndarray | None = None,
    prior_precision: np.ndarray | None = None,
) -> np.ndarray:
    """Indices of ``n`` candidates chosen one at a time by D-optimal gain, from the
    per-candidate information ``info`` (M, P, P) (:func:`information`), after the
    precision ``start`` (default: the prior I / tau^2). A candidate may be chosen again
    (repeated measurements average noise)."""
    p = info.shape[-1]
    a = np.eye(p) / PRIOR_WIDTH**2 if prior_precision is None else np.asarray(prior_precision)
    if start is not None:
        a = a + start
    chosen = []
    for _ in range(n):
        gain = _logdet(a[None] + info) - _logdet(a)
        k = int(np.argmax(gain))
        chosen.append(k)
        a = a + info[k]
    return np.asarray(chosen, int)

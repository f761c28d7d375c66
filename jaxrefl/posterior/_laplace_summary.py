"""Laplace summaries in natural units of the Laplace marginals in theta.

``mean`` is the optimum x* = g(theta*), ``std`` the delta-method std theta_std |g'(theta*)|,
and the quantiles g(theta* + z_q theta_std) (exact quantiles of the pushed-forward marginal,
since g is monotone per entry). z_q is the normal quantile where the noise scale is known
and the Student t quantile of the pixel's degrees of freedom where the fit estimated it
(``dof``), whose std is then theta_std sqrt(dof / (dof - 2)).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from scipy import stats

from ._logpost import LogPosterior

__all__ = ["laplace_summary"]

_Z95 = 1.6448536269514722  # standard normal 95% quantile


def laplace_summary(
    lp: LogPosterior,
    theta_hat: np.ndarray,
    theta_std: np.ndarray,
    dof: np.ndarray | None = None,
):
    """(mean, std, q05, q95) in natural units of the Laplace marginals in theta (module
    docstring); the BRDF entries only (P of them).

    dof: (N,) degrees of freedom of each pixel's marginals, or None. Where the noise scale
    was estimated from the pixel's own residuals (n - P degrees of freedom), the marginal of
    theta_j under the Jeffreys prior on the scale is a Student t with scale theta_std, not a
    Gaussian (Gelman et al., *BDA3*, sec. 14.2): the quantiles are theta* +- t_{0.95, dof}
    theta_std and the std is theta_std sqrt(dof / (dof - 2)), pushed through the bijection
    as above. inf (or None): the Gaussian of a known scale. A finite dof <= 2 has no
    finite variance: those pixels get NaN here, and
    :func:`~jaxrefl.posterior.adaptive_uncertainty` samples
    them."""
    space = lp.space
    t = jnp.asarray(np.nan_to_num(theta_hat))
    n = np.shape(theta_hat)[0]
    nu = np.full(n, np.inf) if dof is None else np.asarray(dof, np.float64).reshape(n)
    t_ok = np.isfinite(nu) & (nu > 2)
    # Quantile and std factor per pixel: Student t where dof is finite, normal where inf.
    z = np.full(n, _Z95)
    z[t_ok] = stats.t.ppf(0.95, nu[t_ok])
    inflate = np.ones(n)
    inflate[t_ok] = np.sqrt(nu[t_ok] / (nu[t_ok] - 2.0))
    s = jnp.asarray(np.nan_to_num(theta_std))
    mean = np.array(space.natural_vector(t))
    std = np.array(s * jnp.abs(space.dnatural(t))) * inflate[:, None]
    q05 = np.array(space.natural_vector(t - z[:, None] * s))
    q95 = np.array(space.natural_vector(t + z[:, None] * s))
    bad = ~(np.all(np.isfinite(theta_hat), -1) & np.all(np.isfinite(theta_std), -1))
    bad |= ~(t_ok | np.isposinf(nu))
    for a in (mean, std, q05, q95):
        a[bad] = np.nan
    return mean, std, q05, q95

"""Where a capture's model cannot be right: the ``misspecified`` map's bits.

A pixel is flagged when its fit gives evidence that the model cannot represent it; its
intervals (Laplace parameter intervals, predictive intervals) are then not calibrated, since
they are computed as if the model were right. Bits of :class:`ModelCheck`:

* ``AT_MODEL_BOUND`` (1): the posterior piles against a bound that is a limit of the
  *model*, not of physics: its mode sits at the bound, or within :data:`NEAR` of the range
  from it with the Laplace 90% interval (Gaussian in the unconstrained space) reaching it.
  The bounds that count: the upper end of a reflectance (albedo or specular F0 at
  1, or at the dielectric cap 0.25 of the grey-F0 models: the photos ask for more than the
  model allows), or either end of the GGX width alpha (its floor is the capture's resolvable
  width, its ceiling 1) on a pixel with a specular lobe (some F0 channel above its lower
  bound: without a lobe alpha is not identified and its bound says nothing). A value at the
  lower end of a reflectance (0) is one a surface can have and is not flagged. "At" is
  :meth:`jaxrefl.fit.ParamSpace.at_bound`'s test (within 1e-3 of the range). An F0 fitted at
  0.249 with a std of 0.03 under the 0.25 cap is as misspecified as one at 0.25: a surface
  of F0 0.4 ends there.
* ``ALPHA_AT_FLOOR`` (4, always with ``AT_MODEL_BOUND``): of those, the width piles against
  its floor, the capture's resolvable width (:func:`jaxrefl.svbrdf.resolvable_alpha`, or
  the job's ``alpha_min``). The floor is a limit of what the photos resolve, not of
  physics: the lobe may be narrower than any width the model allows, and the pixel's
  Laplace alpha and F0 intervals then describe the nearest lobe the model has, not the
  surface's. The uncertainty maps sample such a pixel with alpha's floor at 1e-3 where the
  job gave none (:func:`jaxrefl.svbrdf._uncertainty.posterior_space`).
* ``PPC_FAILED`` (2): a posterior predictive check on the pixel's own training photos
  fails: T = sum over its uncensored training observations of r^2 / v, with r the residual
  at the optimum, exceeds the chi-square quantile of n - P degrees of freedom at
  1 - :data:`PPC_ALPHA`. v is the capture's noise variance, the median over pixels of the
  fit's (a pixel's own residual variance cannot test its own residuals), plus the
  model-discrepancy variance where one is given (:func:`jaxrefl.svbrdf.predictive`). The
  fit's map (:func:`jaxrefl.svbrdf.fit_capture`) checks against the noise alone and only
  for Gaussian noise models; :func:`jaxrefl.svbrdf.predictive` repeats the check with the
  discrepancy term.
"""

from __future__ import annotations

import enum

import jax.numpy as jnp
import numpy as np
from scipy import stats

from jaxrefl._errors import JaxreflError

__all__ = ["NEAR", "PPC_ALPHA", "ModelCheck", "bound_bits", "check_counts", "ppc_failed"]

# The posterior predictive check's false-alarm rate per pixel: of 65,536 well-modelled
# pixels about 66 are flagged by chance.
PPC_ALPHA = 1e-3
# A mode this close to a bound (share of the range) with its 90% interval reaching the bound
# piles against it; the normal quantile of that interval's end.
NEAR = 0.05
_Z90 = 1.6448536269514722


class ModelCheck(enum.IntFlag):
    """Bits of the ``misspecified`` map (module docstring); 0 = no evidence against the model.
    The numbers are stored in maps and reports and do not change."""

    AT_MODEL_BOUND = 1
    PPC_FAILED = 2
    ALPHA_AT_FLOOR = 4


def bound_bits(space, theta: np.ndarray, theta_std: np.ndarray | None = None) -> np.ndarray:
    """(N,) :class:`ModelCheck` bits ``AT_MODEL_BOUND`` and ``ALPHA_AT_FLOOR`` for theta
    (N, P) of ``space`` and its Laplace std in the unconstrained space (N, P; None: the mode
    alone is tested) (module docstring); 0 where a pixel has no estimate (NaN)."""
    theta = np.asarray(theta)
    ok = np.all(np.isfinite(theta), -1)
    t = jnp.asarray(np.where(ok[:, None], theta, 0.0))
    x = np.asarray(space.natural_vector(t))
    at = np.asarray(space.at_bound(t))
    lower, upper = np.asarray(space.lower), np.asarray(space.upper)
    # The upper side: closer to the upper bound than to the lower one.
    hi = np.isfinite(upper) & (upper - x <= x - lower)
    if theta_std is not None:
        # The 90% interval's end on the bound's side (the bijections are increasing).
        s = np.where(np.isfinite(theta_std), theta_std, 0.0)
        end_t = np.where(hi, 1.0, -1.0) * _Z90 * s + np.asarray(t)
        reach = np.asarray(space.at_bound(jnp.asarray(end_t, t.dtype)))
        near = np.asarray(space.at_bound(t, NEAR))
        at = at | (near & reach)
    kind = [lab.split(".")[0] for lab in space.labels]
    refl = np.array([k in ("albedo", "specular") for k in kind])
    spec = np.array([k == "specular" for k in kind])
    alpha = np.array([k == "alpha" for k in kind])
    flag = np.any(at & hi & refl, -1)
    floor = np.zeros_like(flag)
    if alpha.any() and spec.any():
        lobe = ~np.all(at[:, spec] & ~hi[:, spec], -1)
        flag |= np.any(at[:, alpha], -1) & lobe
        floor = np.any(at[:, alpha] & ~hi[:, alpha], -1) & lobe
    bits = np.where(flag & ok, int(ModelCheck.AT_MODEL_BOUND), 0)
    return bits | np.where(floor & ok, int(ModelCheck.ALPHA_AT_FLOOR), 0)


def ppc_failed(chi2: np.ndarray, dof: np.ndarray, alpha: float = PPC_ALPHA) -> np.ndarray:
    """(N,) bool: T = ``chi2`` above the chi-square(``dof``) quantile at 1 - ``alpha``
    (never where dof <= 0 or T is not finite)."""
    if not 0.0 < alpha < 1.0:
        raise JaxreflError(f"the check's false-alarm rate must be in (0, 1), got {alpha}")
    dof = np.asarray(dof)
    q = stats.chi2.isf(alpha, np.maximum(dof, 1))
    return (dof > 0) & np.isfinite(chi2) & (chi2 > q)


def check_counts(check: np.ndarray) -> dict[str, int]:
    """Pixels per :class:`ModelCheck` bit, and ``misspecified`` (any bit)."""
    c = np.asarray(check).reshape(-1).astype(np.int64)
    out = {b.name or str(int(b)): int(np.sum((c & b) != 0)) for b in ModelCheck}
    out["misspecified"] = int(np.sum(c != 0))
    return out

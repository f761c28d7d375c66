"""Detect a fit that float32 could not handle, and redo it in float64.

float32 (24-bit mantissa, eps = 6e-8) is the fast default, and the guarded models keep
values and gradients finite, but a stiff problem can still defeat it:

* a non-finite cost or parameter (overflow of a 1e5 exponent's lobe or a 1e-3 roughness's
  distribution somewhere on the path), reported as ``Status.NONFINITE_INPUT``;
* an ill-conditioned normal matrix: the lean solver flags ``Status.ILL_CONDITIONED`` when
  the equilibrated condition number of J^T J exceeds 1e7 in float32 (1e10 in float64).
  Above ~1/eps a float32 solve has no correct digit along the weakest direction, while
  float64 still resolves it (nearly collinear lights, grazing-only observations);
* a fit that float32 stopped short of the optimum with no flag at all (a normalised Blinn-Phong
  lobe of exponent 1e4: cos^n of a cosine known to 6e-8 is known to 6e-4, so the float32 cost
  surface is too rough to follow to the bottom): :func:`step_gain` takes one Gauss-Newton step in
  float64 from the float32 optimum, and when it lowers the float64 cost by more than
  :data:`GAIN_RTOL` the fit is redone (by :func:`fit_pixels_retry`, which has the data;
  :func:`float64_reasons` sees only the result and does not apply this test). A fit whose cost is
  within that fraction of its optimum's cannot gain more, so a healthy fit is never sent. On the
  stiff cases of ``benchmarks/_stiff_fits.py`` the threshold separates the float32 fits that
  reached the optimum (smaller gains) from those that stopped short (larger ones). Not caught: the
  collinear-lights fits that stop short (the step cannot move along the unresolved direction, so
  it gains nothing) unless flagged ILL_CONDITIONED. The float32 cost itself is no detector: its
  round-off at a stiff optimum is as large as the shortfall it would have to reveal.

:func:`float64_reasons` says which of these a result shows (empty: keep it);
:func:`choose` keeps the float64 redo where it is finite and at least as good (cost
re-evaluated in float64 for both, so round-off of the float32 cost does not decide).
``MASKED`` (no data) is not a precision problem and never triggers a retry.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF
from jaxrefl.fit import (
    FitConfig,
    FitResult,
    ParamSpace,
    PixelData,
    Residual,
    Status,
    fit_pixels,
    has_estimate,
    make_residual,
)

__all__ = [
    "RetryResult",
    "choose",
    "cost64",
    "fit_pixels_retry",
    "float64_enabled",
    "float64_reasons",
    "retry_mask",
    "step_gain",
    "x64",
]

#: Status codes that send a float32 fit to float64.
RETRY_STATUS = (Status.NONFINITE_INPUT, Status.ILL_CONDITIONED)
#: Relative float64 cost decrease of one Gauss-Newton step that sends a fit to float64
#: (the optimum tolerance of ``benchmarks/_stiff_fits.py``: a fit this far from its optimum
#: is not at it).
GAIN_RTOL = 1e-3
# Step lengths tried along the Gauss-Newton direction (the best is kept): a full step can
# overshoot on a lobe 0.6 degrees wide, a shorter one still shows the missing decrease.
_STEPS = (1.0, 0.5, 0.25)


def float64_reasons(result: FitResult) -> list[str]:
    """Why ``result`` (any leading shape) should be redone in float64; [] when it is fine.

    Reasons (each at most once): ``"non-finite cost"``, ``"non-finite parameters"``,
    ``"status NONFINITE_INPUT"``, ``"status ILL_CONDITIONED"``; problems with no estimate
    (MASKED) are left out.
    """
    status = np.atleast_1d(np.asarray(result.status))
    has = has_estimate(status)
    out = []
    cost = np.atleast_1d(np.asarray(result.cost))
    if np.any(has & ~np.isfinite(cost)):
        out.append("non-finite cost")
    theta = np.asarray(result.theta).reshape(status.shape[0], -1)
    if np.any(has & ~np.all(np.isfinite(theta), axis=-1)):
        out.append("non-finite parameters")
    for s in RETRY_STATUS:
        if np.any(status == s):
            out.append(f"status {s.name}")
    return out


def float64_enabled() -> bool:
    """Whether JAX is running with 64-bit floats by default."""
    return bool(jax.config.read("jax_enable_x64"))


@contextmanager
def x64():
    """Enable float64 inside the block (``jax.enable_x64``), restoring the setting after."""
    with jax.enable_x64(True):
        yield


def choose(cost32: float, cost64: float) -> Literal["float32", "float64"]:
    """``"float64"`` when the float64 cost is finite and not worse than the float32 one
    (relative slack 1e-6: equal optima within round-off keep the more precise answer),
    else ``"float32"``."""
    if not np.isfinite(cost64):
        return "float32"
    if not np.isfinite(cost32):
        return "float64"
    return "float64" if cost64 <= cost32 * (1.0 + 1e-6) + 1e-300 else "float32"


def retry_mask(result: FitResult, data: PixelData | None = None) -> np.ndarray:
    """(N,) bool: the problems of a batched ``result`` (leading axis N) that
    :func:`float64_reasons` would send to float64, and with ``data`` also those whose
    :func:`step_gain` exceeds ``GAIN_RTOL``."""
    status = np.atleast_1d(np.asarray(result.status))
    has = has_estimate(status)
    cost = np.atleast_1d(np.asarray(result.cost))
    theta = np.asarray(result.theta).reshape(status.shape[0], -1)
    bad = has & (~np.isfinite(cost) | ~np.all(np.isfinite(theta), axis=-1))
    bad = bad | np.isin(status, [int(s) for s in RETRY_STATUS])
    if data is not None:
        bad = bad | (has & (step_gain(result, data) > GAIN_RTOL))
    return bad


def _gain_one(res: Residual, th, d):
    r = res(th, d)
    jac = jax.jacfwd(res)(th, d)
    a = jac.T @ jac
    dg = jnp.sqrt(jnp.diagonal(a))
    # An unused parameter has a zero column: scale 1 instead of dividing by 0.
    dg = jnp.where(dg > 0, dg, 1.0)
    a_eq = a / (dg[:, None] * dg[None, :]) + 1e-12 * jnp.eye(a.shape[0])
    s = jnp.linalg.solve(a_eq, (jac.T @ r) / dg) / dg
    c0 = 0.5 * jnp.sum(r * r)
    c1 = jnp.stack([0.5 * jnp.sum(res(th - t * s, d) ** 2) for t in _STEPS])
    c1 = jnp.min(jnp.where(jnp.isfinite(c1), c1, jnp.inf))
    # Relative to c0; a zero cost (exact fit) has nothing to gain.
    gain = (c0 - c1) / jnp.where(c0 > 0, c0, 1.0)
    return jnp.where(jnp.isfinite(gain) & (c0 > 0), jnp.maximum(gain, 0.0), 0.0)


# filter_jit: one compilation per residual structure (model, space) and shape, reused.
@eqx.filter_jit
def _gains(res: Residual, theta, data):
    return jax.vmap(lambda th, d: _gain_one(res, th, d))(theta, data)


def _float64_inputs(result: FitResult, data: PixelData):
    """(residual, theta with non-finite rows set to 0, finite-row mask, data), all float64;
    call inside :func:`x64`. A NaN theta would poison any evaluation: it is evaluated at 0
    and the caller masks the result with the mask."""
    res = make_residual(result.model, result.space)
    theta = jnp.asarray(np.asarray(result.theta), jnp.float64)
    ok = jnp.all(jnp.isfinite(theta), axis=-1)
    return res, jnp.where(ok[:, None], theta, 0.0), ok, data.astype(jnp.float64)


def step_gain(result: FitResult, data: PixelData) -> np.ndarray:
    """(N,) relative decrease (c0 - c1) / c0 of the float64 cost 1/2 |r|^2 (L2 loss, unit
    sigma, as :func:`cost64`) by one Gauss-Newton step from each problem's theta.

    The step solves (D^-1 J^T J D^-1 + 1e-12 I) D s = D^-1 J^T r with D = sqrt(diag J^T J)
    (equilibrated; the 1e-12 ridge keeps the solve finite on a singular J^T J, e.g. an
    unused parameter) and the best of theta - t s, t in (1, 1/2, 1/4), is kept. 0 where the
    step does not lower the cost, theta or the cost is not finite, or the cost is 0.
    """
    with x64():
        res, t_safe, ok, d64 = _float64_inputs(result, data)
        g = _gains(res, t_safe, d64)
        return np.asarray(jnp.where(ok, g, 0.0), dtype=np.float64)


@eqx.filter_jit
def _costs(res: Residual, theta, data, ok):
    r = jax.vmap(res)(theta, data)
    c = 0.5 * jnp.sum(r * r, axis=-1)
    return jnp.where(ok & jnp.isfinite(c), c, jnp.inf)


def cost64(result: FitResult, data: PixelData) -> np.ndarray:
    """(N,) cost 1/2 |r|^2 of every problem of ``result`` re-evaluated in float64 on ``data``
    (L2 loss, unit sigma: the default residual); inf where theta is not finite."""
    with x64():
        res, t_safe, ok, d64 = _float64_inputs(result, data)
        # Jitted (one compilation per residual structure and shape): eager, the vmapped
        # residual compiled each of its primitives anew for every call.
        return np.asarray(_costs(res, t_safe, d64, ok), dtype=np.float64)


@dataclass(frozen=True, eq=False)
class RetryResult:
    """A batched fit after the float64 retry.

    result:       float64 arrays; each problem holds the kept result (float32's, or the
                  float64 redo where that was kept)
    retried:      (N,) bool, problems sent to float64 (:func:`retry_mask` with the data)
    kept_float64: (N,) bool, problems whose float64 redo was kept (:func:`choose`)
    result32:     the original float32 fit
    """

    result: FitResult
    retried: np.ndarray
    kept_float64: np.ndarray
    result32: FitResult

    @property
    def theta(self):
        return self.result.theta


def fit_pixels_retry(
    model: BRDF,
    data: PixelData,
    *,
    config: FitConfig = FitConfig(),
    space: ParamSpace | None = None,
) -> RetryResult:
    """:func:`jaxrefl.fit.fit_pixels` in float32, then the flagged problems again in float64.

    Only the problems of :func:`retry_mask` (with ``data``: flags and float64 step gain)
    are refitted (a batch of that size); per problem
    the float64 result is kept when :func:`choose` prefers it (costs re-evaluated in
    float64). ``config`` (solver, noise, loss) and ``space`` are those of both fits (each
    starts at :func:`jaxrefl.fit.initial_theta`); ``config.dtype`` must be None (the dtypes
    are float32, then float64).
    """
    if config.dtype is not None:
        raise JaxreflError("fit_pixels_retry chooses the dtypes itself (float32, then float64)")
    r32 = fit_pixels(model, data, config=config.replace(dtype=np.float32), space=space)
    retried = retry_mask(r32, data)
    kept = np.zeros_like(retried)
    with x64():
        merged = {
            "theta": np.array(r32.theta, np.float64),
            "status": np.array(r32.status),
            "cost": np.array(r32.cost, np.float64),
            "iterations": np.array(r32.iterations),
            "n_used": np.array(r32.n_used),
        }
        idx = np.flatnonzero(retried)
        if idx.size:
            sub = jax.tree.map(lambda x: x[idx], data.astype(jnp.float64))
            cfg64 = config.replace(dtype=np.float64)
            r64 = fit_pixels(model, sub, config=cfg64, space=space)
            c32 = cost64(r32, data)[idx]
            c64 = cost64(r64, sub)
            take = np.asarray([choose(a, b) == "float64" for a, b in zip(c32, c64, strict=True)])
            kept[idx[take]] = True
            for key in merged:
                merged[key][idx[take]] = np.asarray(getattr(r64, key))[take]
        theta = jnp.asarray(merged["theta"], jnp.float64)
        result = FitResult(
            r32.space.to_natural(theta),
            theta,
            jnp.asarray(merged["status"]),
            jnp.asarray(merged["cost"]),
            jnp.asarray(merged["iterations"]),
            jnp.asarray(merged["n_used"]),
            r32.space,
            model,
            r32.backend,
        )
    return RetryResult(result, retried, kept, r32)

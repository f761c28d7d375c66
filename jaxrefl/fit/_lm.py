"""A lean batched Levenberg–Marquardt for many small independent least-squares problems.

Minimises cost(theta) = 1/2 |r(theta)|^2 for one pixel (theta of length P ~ 3-10, r of
length K*C ~ 100) as pure functions over an explicit state (BlackJAX style):
``lm_init`` -> ``LMState``; ``lm_step(state) -> (state, LMInfo)``; ``lm_solve`` runs a
*fixed* number of steps with ``lax.scan``. :func:`~jaxrefl.fit.batched_lm` (:mod:`._lm_batched`)
is ``jit(vmap(lm_solve))`` up to rounding, organised in blocks by one of two schedulers
(:mod:`._lm_host`, :mod:`._lm_staged`).

One step (Madsen, Nielsen & Tingleff 2004, "Methods for non-linear least squares
problems", Alg. 3.16; Nielsen's damping update):

    (J^T J + lam I) delta = -g,  g = J^T r     small P x P system, Cholesky
    delta *= min(1, max_step / |delta|_inf)    step cap in the unconstrained space
    theta_t = theta + delta,   r_t, J_t by one forward-mode pass (jax.jacfwd, P tangents)
    rho = (cost - cost_t) / -(g.delta + delta^T J^T J delta / 2)          gain ratio
    accept if cost_t < cost:   lam *= max(1/3, 1 - (2 rho - 1)^3),  nu = 2
    otherwise reject:          lam *= nu,  nu *= 2

Design decisions:

* Damping is plain lam * I (isotropic), *not* Marquardt's diag(J^T J) scaling. Marquardt's
  scaling damps each parameter in proportion to its own curvature, so a parameter the data
  barely constrain yet (alpha, before a GGX pixel's highlight is matched) is barely damped;
  from a small start more GGX pixels then fall into the "alpha -> 0, highlight missed"
  local minimum than with lam * I. The start is relative, lam0 * mean(diag(J^T J(theta0))),
  so the same option works whatever the units of the data (radiance, f_r, whitened
  residuals); Madsen & Nielsen use tau * max(diag). The default ``lam0`` is small because
  the automatic start (:func:`~jaxrefl.fit.initial_theta`) is usually close to the optimum,
  where Gauss-Newton steps taken at once converge fastest.
* The number of iterations is fixed (``lax.scan``, no ``while_loop`` under ``vmap``, which
  would run every pixel until the slowest stops). Converged pixels are frozen (their state
  stops changing), so a pixel takes the same steps whatever batch it is in (up to the
  rounding of XLA's compilation for the batch shape; see ``_shard``). ``batched_lm`` then
  saves the work of frozen pixels by compacting the unconverged ones (see there).
* The step cap (``max_step``, in theta units) keeps a long Gauss-Newton step from
  throwing a sigmoid or exp parameter into its flat tail, where the solver would stall.
* Failures are values: a trial point with non-finite cost or Jacobian is a rejected step
  (NaN never enters the state); a system that is not positive definite in floating point
  (a non-positive Cholesky pivot) is a rejected step and lam grows.
* For P <= ``unroll_max`` the Cholesky factorisation and the two triangular solves are
  unrolled into scalar arithmetic (:mod:`._linalg`), vectorised across pixels by vmap.

Convergence is tested at the new point after each step, on the *undamped* model so
that heavy damping (tiny steps) is never mistaken for convergence: with the Gauss-Newton
step s = -(J^T J + mu I)^-1 g (mu = sqrt(eps) mean(diag J^T J), a ridge for singular
directions), the pixel has converged when |s| <= xtol (|theta| + xtol) (the parameters are
settled: the test that ends zero-residual problems) or when the predicted reduction
-g.s/2 <= ftol * cost (the cost cannot improve further: the test that ends noisy problems,
also along flat valleys where the parameters are poorly determined). A pixel also stops
when a rejected step predicted less than 10 eps * cost: no further reduction is possible
in the working precision (MINPACK's info = 6; common in float32 along flat valleys).
Defaults depend on the dtype (float32: xtol = 1e-5, ftol = 1e-4; float64: 1e-8, 1e-8):
float32's ``ftol`` is about the least its precision resolves, and far below statistical
relevance when the cost is at the noise level (it moves chi^2 by ftol times the number of
observations).

The final status per pixel (``_status.Status``) is computed by ``_status.classify``.
"""

from __future__ import annotations

import numbers
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from jaxrefl._errors import JaxreflError

from ._linalg import cho_solve_unrolled, cholesky_unrolled
from ._options import Option, check_number
from ._status import classify, default_cond_max
from ._transform import ParamSpace

__all__ = [
    "LMInfo",
    "LMOptions",
    "LMResult",
    "LMState",
    "lm_init",
    "lm_solve",
    "lm_step",
]

ResidualFn = Callable[[Array, Any], Array]

# The schedulers of batched_lm (_lm_host, _lm_staged) gather at least _MIN_COMPACT pixels
# per round, and only in a block of at least _MIN_BLOCK (else one plain loop of steps).
_MIN_COMPACT = 64
_MIN_BLOCK = 512


class LMOptions(Option):
    """The lean LM solver and its options (hashable; every field is static). It is the
    default ``solver`` of :func:`~jaxrefl.fit.solve` and :class:`~jaxrefl.fit.FitConfig`
    (kind ``"lean"``).

    max_iters:  fixed number of steps, >= 1; default 40.
    lam0:       initial damping relative to mean(diag(J^T J)) at theta0; default 0.01.
    lam_min, lam_max: absolute clamps of lam relative to the same scale (keep lam * I from
                underflowing to a singular system or overflowing to a zero step); defaults
                1e-12, 1e12.
    xtol, ftol: step and relative-cost tolerances; None = dtype default (module docstring).
    cond_max:   equilibrated condition number of J^T J above which a pixel is
                ILL_CONDITIONED; None = 1e7 (float32) / 1e10 (float64).
    bound_rtol: tolerance of :meth:`ParamSpace.at_bound`; default 1e-3.
    unroll_max: largest P for the unrolled Cholesky (:mod:`._linalg`; else
                jnp.linalg.cholesky); default 8.
    max_step:   cap on |delta|_inf per step; default 4 (a log-parametrised alpha moves by
                at most a factor e^max_step per step).
    compact_after: steps every pixel takes before the unconverged ones are gathered
                (either organisation below; results per pixel do not depend on it);
                default 1.
    compact_stages, chunk: how :func:`batched_lm` organises the work inside a trace
                (results per pixel do not depend on them). Each stage ``(until,
                fraction)`` gives the unconverged pixels ``fraction`` of a block's slots
                up to step ``until``; the default caps shrink gradually, because pixels of
                real flash captures converge over a spread of steps and a stage whose
                unconverged pixels overflow its cap runs another round as costly as the
                first. Stages narrower than ``_MIN_COMPACT`` slots merge into the one
                before, and blocks under ``_MIN_BLOCK`` pixels take one plain loop of steps
                that stops once all have converged (fewer compiled copies of the step).
    host_loop, host_round: called outside a trace, :func:`batched_lm` runs its steps from
                Python, each one compiled program, and every ``host_round`` steps (default
                2) gathers the unconverged pixels into rounds of 1/16 or 1/4 of a block
                (:func:`_solve_host`; ``compact_stages`` organises the other way;
                ``chunk`` both); inside a trace (``jit``, ``shard_map``) the steps are loops of one
                program. The same steps for every pixel either way: a step inside a
                compiled loop and a step as a program of its own cost differently on CPU
                (``benchmarks/fit_throughput.py`` times both). Default True.
    host_fused: with ``host_loop``, each gathered round is one program (gather, up to
                ``host_round`` steps in a loop that stops once the round has converged,
                scatter), and once the unconverged pixels fit in the smaller slots they take
                all their remaining steps in one such program: fewer program calls, for
                models whose steps are cheap and many (one linear in its free parameters
                started at its exact optimum). The same steps for every pixel either way.
                Default False.
    """

    kind: ClassVar[str] = "lean"
    max_iters: int = eqx.field(default=40, static=True)
    lam0: float = eqx.field(default=0.01, static=True)
    lam_min: float = eqx.field(default=1e-12, static=True)
    lam_max: float = eqx.field(default=1e12, static=True)
    xtol: float | None = eqx.field(default=None, static=True)
    ftol: float | None = eqx.field(default=None, static=True)
    cond_max: float | None = eqx.field(default=None, static=True)
    bound_rtol: float = eqx.field(default=1e-3, static=True)
    unroll_max: int = eqx.field(default=8, static=True)
    max_step: float = eqx.field(default=4.0, static=True)
    compact_after: int = eqx.field(default=1, static=True)
    compact_stages: tuple[tuple[int, float], ...] = eqx.field(
        default=((6, 1 / 2), (12, 1 / 4), (20, 1 / 8), (40, 1 / 32)), static=True
    )
    chunk: int = eqx.field(default=2048, static=True)
    host_loop: bool = eqx.field(default=True, static=True)
    host_round: int = eqx.field(default=2, static=True)
    host_fused: bool = eqx.field(default=False, static=True)

    def __check_init__(self):
        for name in ("max_iters", "chunk", "host_round"):
            v = getattr(self, name)
            if not isinstance(v, numbers.Integral) or v < 1:
                raise JaxreflError(f"LMOptions needs an integer {name} >= 1, got {v!r}")
        for name in ("unroll_max", "compact_after"):
            v = getattr(self, name)
            if not isinstance(v, numbers.Integral) or v < 0:
                raise JaxreflError(f"LMOptions needs an integer {name} >= 0, got {v!r}")
        for name in ("lam0", "lam_min", "lam_max", "bound_rtol", "max_step"):
            check_number("LMOptions", name, getattr(self, name), positive=True)
        for name in ("xtol", "ftol", "cond_max"):
            if getattr(self, name) is not None:
                check_number("LMOptions", name, getattr(self, name), positive=True)
        if self.lam_min >= self.lam_max:
            raise JaxreflError(
                f"LMOptions needs lam_min < lam_max, got {self.lam_min} and {self.lam_max}"
            )

    def tolerances(self, dtype) -> tuple[float, float, float]:
        """(xtol, ftol, cond_max) for ``dtype``."""
        single = jnp.finfo(dtype).bits <= 32
        xtol = self.xtol if self.xtol is not None else (1e-5 if single else 1e-8)
        ftol = self.ftol if self.ftol is not None else (1e-4 if single else 1e-8)
        return xtol, ftol, default_cond_max(dtype, self.cond_max)


class LMState(eqx.Module):
    """Carried state of one pixel (add a leading N axis under vmap)."""

    theta: Float[Array, " P"]
    cost: Float[Array, ""]
    jtj: Float[Array, "P P"]
    grad: Float[Array, " P"]  # J^T r
    active: Int[Array, ""]  # residual rows with r != 0 or a non-zero Jacobian row
    lam: Float[Array, ""]
    nu: Float[Array, ""]
    lam_scale: Float[Array, ""]  # mean(diag(J^T J(theta0))): the unit of lam
    converged: Bool[Array, ""]
    iterations: Int[Array, ""]  # steps taken before convergence
    valid: Bool[Array, ""]  # theta0 and its cost were finite


class LMInfo(eqx.Module):
    """Diagnostics of one step."""

    accepted: Bool[Array, ""]
    trial_cost: Float[Array, ""]
    step_norm: Float[Array, ""]
    gain_ratio: Float[Array, ""]
    pd: Bool[Array, ""]  # the damped system was positive definite


class LMResult(eqx.Module):
    """Per-pixel outcome (leading N axis when batched)."""

    cost: Float[Array, "*n"]
    iterations: Int[Array, "*n"]
    converged: Bool[Array, "*n"]
    status: Int[Array, "*n"]
    lam: Float[Array, "*n"]
    jtj: Float[Array, "*n P P"]  # J^T J at the returned theta (the Laplace precision)
    grad: Float[Array, "*n P"]
    active: Int[Array, "*n"]  # active residual rows there (the Laplace step's n)


def _damped_solve(jtj, grad, lam, unroll_max: int):
    """delta = -(J^T J + lam I)^-1 g, and whether the system was positive definite."""
    p = jtj.shape[-1]
    a = jtj + lam * jnp.eye(p, dtype=jtj.dtype)
    if p <= unroll_max:
        l, ok = cholesky_unrolled(a)
        delta = -cho_solve_unrolled(l, grad)
    else:
        l = jnp.linalg.cholesky(a)
        ok = jnp.all(jnp.isfinite(l))
        l = jnp.where(ok, l, jnp.eye(p, dtype=jtj.dtype))
        delta = -jax.scipy.linalg.cho_solve((l, True), grad)
    ok = ok & jnp.all(jnp.isfinite(delta))
    return jnp.where(ok, delta, 0.0), ok


# ---------------------------------------------------------------------------- the solver
def _linearise(residual_fn: ResidualFn, theta, data):
    def f(t):
        r = residual_fn(t, data)
        return r, r

    jac, r = jax.jacfwd(f, has_aux=True)(theta)
    cost = 0.5 * jnp.sum(r * r)
    # Products written as broadcast-multiply-sum: under vmap a batched (P x M)(M x P) matmul
    # is a slow small-matrix kernel on CPU, the elementwise form fuses into one loop.
    jtj = jnp.sum(jac[:, :, None] * jac[:, None, :], axis=0)
    grad = jnp.sum(jac * r[:, None], axis=0)
    # Rows that take part in the fit at theta: a satisfied censored observation (and a
    # masked one) has r = 0 and a zero Jacobian row. Counted here so that the Laplace step
    # can reuse the fit's last linearisation instead of a Jacobian of its own.
    active = jnp.sum(jnp.any(jac != 0.0, axis=-1) | (r != 0.0)).astype(jnp.int32)
    return cost, jtj, grad, active


def lm_init(
    residual_fn: ResidualFn, theta0: Float[Array, " P"], data: Any, options: LMOptions
) -> LMState:
    """State at theta0. A non-finite theta0 (or cost there) gives a frozen, invalid state."""
    finite0 = jnp.all(jnp.isfinite(theta0))
    theta = jnp.where(finite0, theta0, 0.0)
    cost, jtj, grad, active = _linearise(residual_fn, theta, data)
    valid = finite0 & jnp.isfinite(cost) & jnp.all(jnp.isfinite(jtj)) & jnp.all(jnp.isfinite(grad))
    cost = jnp.where(valid, cost, 0.0)
    jtj = jnp.where(valid, jtj, 0.0)
    grad = jnp.where(valid, grad, 0.0)
    diag_mean = jnp.mean(jnp.diagonal(jtj))
    # The unit of lam: mean curvature at theta0; floored at the dtype's tiny so a pixel
    # with an all-zero Jacobian (no usable data) still gets a positive definite system.
    lam_scale = jnp.maximum(diag_mean, jnp.finfo(theta.dtype).tiny)
    one = jnp.ones((), theta.dtype)
    return LMState(
        theta=theta,
        cost=cost,
        jtj=jtj,
        grad=grad,
        active=active,
        lam=options.lam0 * lam_scale * one,
        nu=2.0 * one,
        lam_scale=lam_scale,
        converged=~valid,
        iterations=jnp.zeros((), jnp.int32),
        valid=valid,
    )


def _converged(state: LMState, options: LMOptions) -> Bool[Array, ""]:
    """The convergence test at the current point (module docstring): the Gauss-Newton step
    (ridge mu = sqrt(eps) * mean diag) is small, or the cost reduction it predicts is."""
    xtol, ftol, _ = options.tolerances(state.theta.dtype)
    mu = jnp.sqrt(jnp.finfo(state.theta.dtype).eps) * state.lam_scale
    gn, pd = _damped_solve(state.jtj, state.grad, mu, options.unroll_max)
    decrement = -0.5 * jnp.dot(state.grad, gn)  # predicted reduction of the GN step
    small_step = jnp.sqrt(jnp.sum(gn * gn)) <= xtol * (jnp.sqrt(jnp.sum(state.theta**2)) + xtol)
    small_gain = decrement <= ftol * state.cost
    return pd & (small_step | small_gain)


def lm_step(
    residual_fn: ResidualFn, state: LMState, data: Any, options: LMOptions
) -> tuple[LMState, LMInfo]:
    """One damped Gauss-Newton step; a converged (or invalid) state is returned unchanged.

    The convergence test runs on the new point; a pixel that passes it is frozen from then on.
    """
    keep = state.converged
    delta, pd = _damped_solve(state.jtj, state.grad, state.lam, options.unroll_max)
    # Step cap in the unconstrained space: a longer step jumps a sigmoid or exp into its flat
    # saturated tail, where the gradient vanishes and the solver would stall at a bound.
    longest = jnp.max(jnp.abs(delta))
    delta = delta * jnp.minimum(1.0, options.max_step / jnp.maximum(longest, options.max_step))
    theta_t = state.theta + delta
    cost_t, jtj_t, grad_t, active_t = _linearise(residual_fn, theta_t, data)
    finite_t = jnp.isfinite(cost_t) & jnp.all(jnp.isfinite(jtj_t)) & jnp.all(jnp.isfinite(grad_t))
    actual = state.cost - cost_t
    # Reduction predicted by the Gauss-Newton model, -(g.d + d^T J^T J d / 2).
    hd = jnp.sum(state.jtj * delta[None, :], axis=-1)
    predicted = -(jnp.sum(state.grad * delta) + 0.5 * jnp.sum(delta * hd))
    accepted = pd & finite_t & (actual > 0)
    rho = jnp.where(predicted > 0, actual / jnp.where(predicted > 0, predicted, 1.0), 0.0)
    rho = jnp.where(accepted, rho, 0.0)
    shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
    lam = jnp.where(accepted, state.lam * shrink, state.lam * state.nu)
    # Clamps (relative to the curvature unit): lam -> 0 would leave a singular system for
    # rank-deficient J, lam -> inf a zero step; neither helps.
    lam = jnp.clip(lam, options.lam_min * state.lam_scale, options.lam_max * state.lam_scale)
    # nu doubles on every rejection; capped so that it cannot overflow over long rejections.
    nu = jnp.where(accepted, 2.0, jnp.minimum(state.nu * 2.0, 2.0**30))
    take = accepted & ~keep
    # Stall: a rejected step that predicted less than the float resolution of the cost; no
    # further reduction is possible in this precision (MINPACK's info = 6).
    eps = jnp.finfo(state.theta.dtype).eps
    stalled = pd & ~accepted & (predicted <= 10.0 * eps * state.cost)

    def pick(new, old):
        return jnp.where(take, new, old)

    new = LMState(
        theta=pick(theta_t, state.theta),
        cost=pick(cost_t, state.cost),
        jtj=pick(jtj_t, state.jtj),
        grad=pick(grad_t, state.grad),
        active=pick(active_t, state.active),
        lam=jnp.where(keep, state.lam, lam),
        nu=jnp.where(keep, state.nu, nu),
        lam_scale=state.lam_scale,
        converged=keep | stalled,
        iterations=state.iterations + jnp.where(keep, 0, 1).astype(jnp.int32),
        valid=state.valid,
    )
    new = eqx.tree_at(lambda s: s.converged, new, new.converged | _converged(new, options))
    step_norm = jnp.sqrt(jnp.sum(delta * delta))
    info = LMInfo(accepted=take, trial_cost=cost_t, step_norm=step_norm, gain_ratio=rho, pd=pd)
    return new, info


def _finish(state: LMState, theta0, options, space, n_usable) -> tuple[Array, LMResult]:
    """Status and result of one pixel."""
    _, _, cond_max = options.tolerances(state.theta.dtype)
    status = classify(
        state.theta,
        state.cost,
        state.jtj,
        state.converged,
        state.valid,
        cond_max=cond_max,
        space=space,
        n_usable=n_usable,
        bound_rtol=options.bound_rtol,
    )
    theta = jnp.where(state.valid, state.theta, theta0)
    cost = jnp.where(state.valid, state.cost, jnp.nan)
    result = LMResult(
        cost=cost,
        iterations=state.iterations,
        converged=state.converged & state.valid,
        status=status,
        lam=state.lam,
        jtj=state.jtj,
        grad=state.grad,
        active=state.active,
    )
    return theta, result


def lm_solve(
    residual_fn: ResidualFn,
    theta0: Float[Array, " P"],
    data: Any,
    options: LMOptions | None = None,
    *,
    space: ParamSpace | None = None,
    n_usable: Int[Array, ""] | None = None,
) -> tuple[Float[Array, " P"], LMResult]:
    """Run ``options.max_iters`` steps from theta0 (``lax.scan``); returns (theta, LMResult).

    ``space`` enables the AT_BOUND status, ``n_usable`` (number of usable observations) the
    MASKED status (fewer than P). A non-finite theta0 gives NONFINITE_INPUT and theta0 back.
    """
    options = LMOptions() if options is None else options
    state = lm_init(residual_fn, theta0, data, options)

    def body(s, _):
        s, _info = lm_step(residual_fn, s, data, options)
        return s, None

    state, _ = lax.scan(body, state, None, length=options.max_iters)
    return _finish(state, theta0, options, space, n_usable)

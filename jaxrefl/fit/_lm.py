"""A lean batched Levenberg–Marquardt for many small independent least-squares problems.

Minimises cost(theta) = 1/2 |r(theta)|^2 for one pixel (theta of length P ~ 3-10, r of
length K*C ~ 100) as pure functions over an explicit state (BlackJAX style):
``lm_init`` -> ``LMState``; ``lm_step(state) -> (state, LMInfo)``; ``lm_solve`` runs a
*fixed* number of steps with ``lax.scan``; ``batched_lm`` is ``jit(vmap(lm_solve))`` (up to
rounding; organised in blocks, see there).

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
  residuals); Madsen & Nielsen use tau * max(diag). The default lam0 = 0.01 is chosen for the
  automatic start (:func:`~jaxrefl.fit.initial_theta`), which is usually close to the
  optimum: there a small damping takes Gauss-Newton steps at once and needs about half the
  steps of lam0 = 1 for the same final costs; from a poor start (the model defaults) the
  two end equally often better and worse, while a smaller lam0 ends worse more often.
* The number of iterations is fixed (``lax.scan``, no ``while_loop`` under ``vmap``, which
  would run every pixel until the slowest stops). Converged pixels are frozen (their state
  stops changing), so a pixel takes the same steps whatever batch it is in (up to the
  rounding of XLA's compilation for the batch shape; see ``_shard``). ``batched_lm`` then
  saves the work of frozen pixels by compacting the unconverged ones (see there).
* The step cap (``max_step`` = 4 in theta units) keeps a long Gauss-Newton step from
  throwing a sigmoid or exp parameter into its flat tail, where the solver would stall.
* Failures are values: a trial point with non-finite cost or Jacobian is a rejected step
  (NaN never enters the state); a system that is not positive definite in floating point
  (a non-positive Cholesky pivot) is a rejected step and lam grows.
* For P <= ``unroll_max`` (default 8) the Cholesky factorisation and the two triangular
  solves are unrolled into scalar arithmetic (vectorised across pixels by vmap); batched
  LAPACK calls on 7 x 7 matrices cost more than the arithmetic itself.

Convergence is tested at the new point after each step, on the *undamped* model so
that heavy damping (tiny steps) is never mistaken for convergence: with the Gauss-Newton
step s = -(J^T J + mu I)^-1 g (mu = sqrt(eps) mean(diag J^T J), a ridge for singular
directions), the pixel has converged when |s| <= xtol (|theta| + xtol) (the parameters are
settled: the test that ends zero-residual problems) or when the predicted reduction
-g.s/2 <= ftol * cost (the cost cannot improve further: the test that ends noisy problems,
also along flat valleys where the parameters are poorly determined). A pixel also stops
when a rejected step predicted less than 10 eps * cost: no further reduction is possible
in the working precision (MINPACK's info = 6; common in float32 along flat valleys).
Defaults depend on the dtype (float32: xtol = 1e-5, ftol = 1e-4; float64: 1e-8, 1e-8). A
relative cost change of 1e-4 is far below statistical relevance when the cost is at the
noise level (it moves chi^2 by ~1e-4 * the number of observations), and float32 cannot
resolve much less.

The final status per pixel (``_status.Status``) is computed by ``_status.classify``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from jaxrefl._errors import JaxreflError

from ._options import Option, check_number
from ._status import classify, default_cond_max
from ._transform import ParamSpace

__all__ = [
    "LMInfo",
    "LMOptions",
    "LMResult",
    "LMState",
    "batched_lm",
    "cho_solve_unrolled",
    "cholesky_unrolled",
    "lm_init",
    "lm_solve",
    "lm_step",
]

ResidualFn = Callable[[Array, Any], Array]

# Compaction needs at least this many pixels per round, and a block at least _MIN_BLOCK
# (else one plain loop of steps is used).
_MIN_COMPACT = 64
_MIN_BLOCK = 512


class LMOptions(Option):
    """The lean LM solver and its options (hashable; every field is static). It is the
    default ``solver`` of :func:`~jaxrefl.fit.solve` and :class:`~jaxrefl.fit.FitConfig`
    (kind ``"lean"``).

    max_iters:  fixed number of steps, >= 1; default 40 (30-50 is plenty for P <= 10 from
                a good init).
    lam0:       initial damping relative to mean(diag(J^T J)) at theta0; default 0.01.
    lam_min, lam_max: absolute clamps of lam relative to the same scale (keep lam * I from
                underflowing to a singular system or overflowing to a zero step); defaults
                1e-12, 1e12.
    xtol, ftol: step and relative-cost tolerances; None = dtype default (module docstring).
    cond_max:   equilibrated condition number of J^T J above which a pixel is
                ILL_CONDITIONED; None = 1e7 (float32) / 1e10 (float64).
    bound_rtol: tolerance of :meth:`ParamSpace.at_bound`; default 1e-3.
    unroll_max: largest P for the unrolled Cholesky (else jnp.linalg.cholesky); default 8.
    max_step:   cap on |delta|_inf per step (4: alpha x e^4 = 55, a logit 0.5 -> 0.98).
    compact_after: steps every pixel takes before the unconverged ones are gathered
                (either organisation below; results per pixel do not depend on it);
                default 1.
    compact_stages, chunk: how :func:`batched_lm` organises the work inside a trace
                (results per pixel do not depend on them). The default stages halve the
                slots every few steps (1/2 of a block to step 6, 1/4 to 12, 1/8 to 20,
                1/32 to the end). They follow how pixels of real flash captures converge
                from the automatic start with lam0 = 0.01, which is slower and more
                spread out than on synthetic captures: many pixels still iterate after
                8 steps and some after 16. A stage whose unconverged pixels overflow its
                cap runs another round that costs as much as the first, so the caps
                shrink gradually rather than in one jump to a small tail.
                Stages narrower than 64 slots merge into the one before, and blocks under
                512 pixels take one plain loop of steps that stops once all have
                converged (fewer compiled copies of the step).
    host_loop, host_round: called outside a trace, :func:`batched_lm` runs its steps from
                Python, each one compiled program, and every ``host_round`` steps (default
                2) gathers the unconverged pixels into rounds of 1/16 or 1/4 of a block
                (:func:`_solve_host`; ``compact_stages`` organises the other way;
                ``chunk`` both); inside a trace (``jit``, ``shard_map``) the steps are loops of one
                program. The same steps for every pixel either way. On CPU a step inside a
                compiled loop costs more than the same step as a program of its own, while
                each program called from Python costs its dispatch
                (``benchmarks/fit_throughput.py`` times both).
                Default True.
    host_fused: with ``host_loop``, each gathered round is one program (gather, up to
                ``host_round`` steps in a loop that stops once the round has converged,
                scatter), and once the unconverged pixels fit in the smaller slots they take
                all their remaining steps in one such program. Fewer program calls, but a
                step inside a compiled loop runs slower on CPU than a step program of its own
                (whose operations XLA parallelises): it pays where steps are cheap and calls
                many, e.g. a model linear in its free parameters started at its exact optimum
                (the pooled capture model), and costs where steps are heavy (a GGX lobe with
                a free width). The same steps for every pixel either way. Default False.
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


# ---------------------------------------------------------------------------- linear algebra
def cholesky_unrolled(
    a: Float[Array, "*b P P"],
) -> tuple[Float[Array, "*b P P"], Bool[Array, "*b"]]:
    """Lower Cholesky factor of a symmetric matrix, unrolled for small static P.

    Returns (L, ok). Where a pivot is not positive (the matrix is not positive definite in
    floating point) ``ok`` is False and that pivot is replaced by 1 (gradient-safe; the
    factor is then meaningless and must not be used).
    """
    p = a.shape[-1]
    cols: list[list[Array]] = [[jnp.zeros_like(a[..., 0, 0])] * p for _ in range(p)]
    ok = jnp.ones(a.shape[:-2], dtype=bool)
    for j in range(p):
        s = a[..., j, j]
        for k in range(j):
            s = s - cols[j][k] * cols[j][k]
        pos = s > 0
        ok = ok & pos
        d = jnp.sqrt(jnp.where(pos, s, 1.0))
        cols[j][j] = d
        for i in range(j + 1, p):
            t = a[..., i, j]
            for k in range(j):
                t = t - cols[i][k] * cols[j][k]
            cols[i][j] = t / d
    rows = [jnp.stack(cols[i], axis=-1) for i in range(p)]
    return jnp.stack(rows, axis=-2), ok


def cho_solve_unrolled(l: Float[Array, "*b P P"], b: Float[Array, "*b P"]) -> Float[Array, "*b P"]:
    """Solve (L L^T) x = b by forward and back substitution, unrolled for small P."""
    p = l.shape[-1]
    y: list[Array] = []
    for i in range(p):
        t = b[..., i]
        for k in range(i):
            t = t - l[..., i, k] * y[k]
        y.append(t / l[..., i, i])
    x: list[Array] = [jnp.zeros_like(y[0])] * p
    for i in reversed(range(p)):
        t = y[i]
        for k in range(i + 1, p):
            t = t - l[..., k, i] * x[k]
        x[i] = t / l[..., i, i]
    return jnp.stack(x, axis=-1)


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


def _steps(residual_fn, states, data, options, n):
    """n steps of vmap(lm_step) over a block of pixels."""
    step = jax.vmap(lambda s, d: lm_step(residual_fn, s, d, options)[0])
    return lax.scan(lambda s, _: (step(s, data), None), states, None, length=n)[0]


def _steps_until_converged(residual_fn, states, data, options, n):
    """Up to n steps of vmap(lm_step), stopping once every pixel has converged (they are
    frozen then, so the steps skipped would change nothing): a round of stragglers costs
    its slowest pixel's steps, not the stage's."""
    step = jax.vmap(lambda s, d: lm_step(residual_fn, s, d, options)[0])

    def cond(carry):
        k, s = carry
        return (k < n) & ~jnp.all(s.converged)

    return lax.while_loop(cond, lambda c: (c[0] + 1, step(c[1], data)), (0, states))[1]


def _stages(b: int, options: LMOptions) -> tuple[int, list[tuple[int, int]]]:
    """(steps every pixel takes, [(until, slots)] of the compaction stages) for a block of
    b pixels; no stages means one plain loop of up to ``max_iters`` steps (see
    :func:`_solve_block`)."""
    done = min(options.compact_after, options.max_iters)
    stages = [
        (min(u, options.max_iters), max(1, math.ceil(b * f))) for u, f in options.compact_stages
    ]
    # Stages narrower than _MIN_COMPACT slots are not worth a compiled copy of the step:
    # the stage before them runs on to their end instead.
    stages = [(u, c) for u, c in stages if u > done and c >= _MIN_COMPACT]
    if stages:
        stages[-1] = (options.max_iters, stages[-1][1])
    if b < _MIN_BLOCK or not stages:
        # A small block is not worth more compiled copies of the step (compile time).
        return 0, []
    return done, stages


@eqx.filter_jit
def _init_all(residual_fn, theta0, data, options):
    return jax.vmap(lambda t, d: lm_init(residual_fn, t, d, options))(theta0, data)


@eqx.filter_jit
def _step_all(residual_fn, states, data, options):
    return jax.vmap(lambda s, d: lm_step(residual_fn, s, d, options)[0])(states, data)


@eqx.filter_jit
def _gather(states, data, idx, live):
    """The pixels ``idx`` of states and data; slots that are not ``live`` are frozen."""
    sub = jax.tree.map(lambda x: x[idx], states)
    sub = eqx.tree_at(lambda s: s.converged, sub, sub.converged | ~live)
    return sub, jax.tree.map(lambda x: x[idx], data)


@eqx.filter_jit
def _scatter(states, sub, idx):
    """states with pixels ``idx`` replaced by ``sub`` (an index of N or more is dropped)."""
    return jax.tree.map(lambda x, y: x.at[idx].set(y, mode="drop"), states, sub)


@eqx.filter_jit
def _round(residual_fn, states, data, idx, n, options):
    """A gathered round as one program (``host_fused``): the pixels ``idx`` take up to ``n``
    steps (a traced count: one program for any count), stopping once all of them have
    converged, and are scattered back."""
    b = states.theta.shape[0]
    sub, sub_data = _gather(states, data, jnp.minimum(idx, b - 1), idx < b)
    sub = _steps_until_converged(residual_fn, sub, sub_data, options, n)
    return _scatter(states, sub, idx)


@eqx.filter_jit
def _finish_all(states, theta0, n_usable, options, space):
    return jax.vmap(lambda s, t, n: _finish(s, t, options, space, n))(states, theta0, n_usable)


def _slot_sizes(b: int) -> tuple[int, int]:
    """The two slot counts of a gathered round for a block of b pixels: b/16 and b/4 (at
    least ``_MIN_COMPACT``). Two fixed sizes, not the tightest power of two, so the programs a
    block can use do not depend on how its pixels converge: they compile once, before they
    are needed (:func:`_warm`), and a later batch of the same shape compiles nothing."""
    return max(_MIN_COMPACT, b // 16), max(_MIN_COMPACT, b // 4)


def _rounds(todo: np.ndarray, b: int) -> list[np.ndarray] | None:
    """The unconverged pixels ``todo`` split into gathered rounds (slot indices, padded with
    b), or None where stepping the whole block costs no more."""
    small, big = _slot_sizes(b)
    cap = small if todo.size <= small else big
    if -(-todo.size // cap) * cap >= b:
        return None
    out = []
    for i in range(0, todo.size, cap):
        idx = np.full(cap, b, np.int32)
        part = todo[i : i + cap]
        idx[: part.size] = part
        out.append(idx)
    return out


# Blocks whose gathered-round programs have compiled (see _warm).
_WARMED: set = set()


def _warm(residual_fn, states, data, options) -> None:
    """Compile the gathered-round programs of both slot sizes the first time a block of
    this shape and residual is solved in the process: one step (``host_fused``: a round of
    none) on slots that are all padding (frozen, and dropped on the way back), which
    changes nothing."""
    leaves = jax.tree.leaves((residual_fn, data))
    key = (
        jax.tree.structure((residual_fn, data)),
        tuple((x.shape, str(x.dtype)) for x in leaves if hasattr(x, "shape")),
        states.theta.shape,
        str(states.theta.dtype),
        options,
    )
    if key in _WARMED:
        return
    b = states.theta.shape[0]
    for cap in _slot_sizes(b):
        idx = np.full(cap, b, np.int32)
        if options.host_fused:
            zero = jnp.asarray(0, np.int32)
            states = _round(residual_fn, states, data, jnp.asarray(idx), zero, options)
            continue
        sub, sub_data = _gather(
            states, data, jnp.asarray(np.minimum(idx, b - 1)), jnp.asarray(idx < b)
        )
        sub = _step_all(residual_fn, sub, sub_data, options)
        states = _scatter(states, sub, jnp.asarray(idx))
    jax.block_until_ready(states)
    _WARMED.add(key)


def _solve_host(residual_fn, theta0, data, n_usable, options, space):
    """:func:`batched_lm` for all N pixels, driven from Python, each step one compiled
    program. All pixels take the first ``compact_after`` steps; then, in rounds of
    ``host_round`` steps, the unconverged pixels are gathered into slots of one of two fixed
    sizes (:func:`_slot_sizes`), step, and are scattered back, or the whole block steps
    where that costs no more. Every unconverged pixel is in every round, so each takes the
    same steps in the same order as ``lm_solve`` alone. Fewer than ``_MIN_BLOCK`` pixels
    take plain steps (no gathering), until all have converged. ``host_fused``: each round
    is one program (:func:`_round`), and the pixels left when they fit in the smaller slots
    take all their remaining steps in one last round."""
    b = theta0.shape[0]
    states = _init_all(residual_fn, theta0, data, options)
    it = min(options.compact_after, options.max_iters) if b >= _MIN_BLOCK else 0
    for _ in range(it):  # every pixel, converged or not (frozen ones are unchanged)
        states = _step_all(residual_fn, states, data, options)
    if b >= _MIN_BLOCK and it < options.max_iters:
        _warm(residual_fn, states, data, options)
    while it < options.max_iters:
        todo = np.flatnonzero(~np.asarray(states.converged))
        if todo.size == 0:
            break
        n = min(options.host_round, options.max_iters - it)
        rounds = None if b < _MIN_BLOCK else _rounds(todo, b)
        if rounds is None:
            for _ in range(n):
                states = _step_all(residual_fn, states, data, options)
        elif options.host_fused:
            last = todo.size <= _slot_sizes(b)[0]  # the rest in one round
            steps = jnp.asarray(options.max_iters - it if last else n, np.int32)
            for idx in rounds:
                states = _round(residual_fn, states, data, jnp.asarray(idx), steps, options)
            if last:
                break
        else:
            for idx in rounds:
                # Padding slots repeat the last pixel, frozen, and are dropped on the way back.
                sub, sub_data = _gather(
                    states, data, jnp.asarray(np.minimum(idx, b - 1)), jnp.asarray(idx < b)
                )
                for _ in range(n):
                    sub = _step_all(residual_fn, sub, sub_data, options)
                states = _scatter(states, sub, jnp.asarray(idx))
        it += n
    return _finish_all(states, theta0, n_usable, options, space)


def _solve_block(residual_fn, theta0, data, n_usable, options, space):
    """lm_solve for a block of B pixels, organised to skip the work of converged pixels.

    All B pixels take the first ``compact_after`` steps. Then come the stages of
    ``compact_stages``, each ``(until, fraction)``: the pixels still unconverged are gathered
    ``cap = fraction * B`` at a time and take the steps up to iteration ``until`` (the last
    stage runs to ``max_iters``), and are scattered back (a while loop over rounds at the
    block level, never inside vmap). The caps shrink with the stages as pixels converge
    (the tail of slow pixels is short but long-running). A converged pixel is frozen, so
    each pixel's result equals ``lm_solve``'s: the same steps, in the same order."""
    b = theta0.shape[0]
    states = jax.vmap(lambda t, d: lm_init(residual_fn, t, d, options))(theta0, data)
    done, stages = _stages(b, options)
    if not stages:
        # One loop of up to max_iters steps for all pixels, stopping when all converged.
        states = _steps_until_converged(residual_fn, states, data, options, options.max_iters)
    else:
        states = _steps(residual_fn, states, data, options, done)
    for until, cap in stages:
        if until <= done:
            continue
        n_steps = until - done

        def todo(states, until=until):
            return ~states.converged & (states.iterations < until)

        def round_(states, until=until, cap=cap, n_steps=n_steps):
            idx = jnp.nonzero(todo(states), size=cap, fill_value=b)[0]
            live = idx < b
            get = jnp.minimum(idx, b - 1)
            sub = jax.tree.map(lambda x: x[get], states)
            # Padding slots (copies of the last pixel) are frozen and dropped on the way
            # back. Every live pixel has taken all ``done`` steps so far (it never
            # converged), so n_steps brings each exactly to ``until``.
            sub = eqx.tree_at(lambda s: s.converged, sub, sub.converged | ~live)
            sub_data = jax.tree.map(lambda x: x[get], data)
            sub = _steps_until_converged(residual_fn, sub, sub_data, options, n_steps)
            return jax.tree.map(lambda x, y: x.at[idx].set(y, mode="drop"), states, sub)

        def any_todo(states, todo=todo):
            return jnp.any(todo(states))

        states = lax.while_loop(any_todo, round_, states)
        done = until
    return jax.vmap(lambda s, t, n: _finish(s, t, options, space, n))(states, theta0, n_usable)


def batched_lm(
    residual_fn: ResidualFn,
    theta0: Float[Array, "N P"],
    data: Any,
    options: LMOptions | None = None,
    *,
    space: ParamSpace | None = None,
    n_usable: Int[Array, " N"] | None = None,
) -> tuple[Float[Array, "N P"], LMResult]:
    """``lm_solve`` over N independent pixels; ``data`` has a leading N axis on every leaf,
    ``n_usable`` is (N,) or None.

    Equivalent to ``jit(vmap(lm_solve))`` up to float rounding (which can move poorly
    determined parameters along flat valleys in float32), organised for speed: all pixels
    take the first ``options.compact_after`` steps, then only the still-unconverged pixels,
    gathered into fewer slots, take the remaining ones. Outside a trace, with
    ``options.host_loop``, each step is its own compiled program driven from Python
    (:func:`_solve_host`); inside one, the steps are loops of one program with the slots of
    ``options.compact_stages`` (:func:`_solve_block`). Either way pixels go in blocks of
    ``options.chunk``.
    """
    options = LMOptions() if options is None else options
    n = theta0.shape[0]
    nu = jnp.full((n,), jnp.iinfo(jnp.int32).max, jnp.int32) if n_usable is None else n_usable
    leaves = jax.tree.leaves((residual_fn, theta0, data, nu))
    if options.host_loop and not any(isinstance(x, jax.core.Tracer) for x in leaves):
        if n <= options.chunk:
            return _solve_host(residual_fn, theta0, data, nu, options, space)
        # One block after the other, each driven from Python.
        args = _blocks((theta0, data, nu), options.chunk)
        parts = []
        for i in range(args[0].shape[0]):
            t, d, u = jax.tree.map(lambda x, i=i: x[i], args)
            parts.append(_solve_host(residual_fn, t, d, u, options, space))
        out = jax.tree.map(lambda *xs: jnp.stack(xs), *parts)
    else:
        out = _batched_lm_graph(residual_fn, theta0, data, nu, options, space)
    return jax.tree.map(lambda x: x.reshape((-1, *x.shape[2:]))[:n], out)


def _blocks(args, chunk: int):
    """Every leaf of ``args`` (leading axis N) as (blocks, chunk', ...), chunk' = min(chunk,
    N): blocks of pixels whose working set stays in cache. The last block is padded with
    copies of pixel 0 (their results are cut off after), so every block runs the same
    compiled programs."""
    n = jax.tree.leaves(args)[0].shape[0]
    chunk = max(1, min(chunk, n))
    blocks = -(-n // chunk)
    pad = blocks * chunk - n

    def padded(x):
        x = jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad, *x.shape[1:]))]) if pad else x
        return x.reshape((blocks, chunk, *x.shape[1:]))

    return jax.tree.map(padded, args)


@eqx.filter_jit
def _batched_lm_graph(residual_fn, theta0, data, n_usable, options, space):
    """:func:`batched_lm` as one compiled program, block by block (``lax.map``), each
    solved by :func:`_solve_block`; results (blocks, chunk, ...)."""

    def block(a):
        theta_b, data_b, nu_b = a
        return _solve_block(residual_fn, theta_b, data_b, nu_b, options, space)

    return lax.map(block, _blocks((theta0, data, n_usable), options.chunk))

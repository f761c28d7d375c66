"""One interface to three batched least-squares solvers, each chosen by its object.

``solve(residual_fn, theta0 (N, P), data (leading N axis), solver)`` minimises
1/2 |r(theta, data_n)|^2 for every pixel n independently and returns ``(theta, FitInfo)``
with per-pixel :class:`~jaxrefl.fit.Status` codes, iteration counts and final costs. The
solver object carries its own iteration budget and tolerances:

* :class:`~jaxrefl.fit.LMOptions` (default, kind ``"lean"``): :func:`~jaxrefl.fit.batched_lm`,
  fixed iteration budget, lam * I damping, unrolled Cholesky, compaction of unconverged
  pixels (fastest by far under vmap).
* :class:`OptimistixLM` (``"optimistix"``): ``optimistix.least_squares`` with
  ``optimistix.LevenbergMarquardt`` (trust-region LM, QR solves) under ``vmap``,
  ``throw=False``; its ``RESULTS`` are mapped to our codes (successful -> CONVERGED, max
  steps -> MAX_ITERATIONS, nonfinite -> NONFINITE_INPUT, any other failure ->
  ILL_CONDITIONED).
* :class:`JaxoptLM` (``"jaxopt"``): ``jaxopt.LevenbergMarquardt`` under ``vmap`` with
  ``damping_parameter=1`` and ``solver="cholesky"`` (with its default damping of 1e-6 x max
  diag(J^T J), nearly undamped Gauss-Newton steps send more GGX pixels into the "highlight
  missed" local minimum; see :mod:`jaxrefl.fit._lm` on damping), Madsen-Nielsen stop test.
  jaxopt is no longer maintained: it is imported only when asked for, its import-time
  warnings are silenced, and a missing install raises an ImportError saying what to do.

Whatever the solver, the status is then completed the same way (``_status.classify``): the
AT_BOUND test with ``space``, MASKED with ``n_usable``, ILL_CONDITIONED from J^T J at the
solution. Library solvers run every pixel until the slowest one stops (a vmapped while
loop), so they are slow on big batches; they are here as cross-checks. optimistix and jaxopt
are optional dependencies (``pip install 'jaxrefl[backends]'``), imported when their solver
runs; a missing one raises an ImportError naming that command.
"""

from __future__ import annotations

import warnings
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jaxrefl._errors import JaxreflError

from ._lm import LMOptions, _linearise
from ._lm_batched import batched_lm
from ._options import Option
from ._status import Status, classify, default_cond_max, severity
from ._transform import ParamSpace

__all__ = ["FitInfo", "JaxoptLM", "OptimistixLM", "Solver", "solve"]


class _LibraryLM(Option):
    """The options common to the library solvers (hashable; every field is static).

    max_iters:  iteration budget, >= 1; default 256 (optimistix's default)
    rtol, atol: relative and absolute tolerances; None = dtype default (1e-4 / 1e-6 in
                float32, 1e-6 / 1e-8 in float64). optimistix: Cauchy termination on cost
                and step; jaxopt: step xtol = rtol and gradient gtol = atol
    cond_max:   equilibrated condition number of J^T J above which a pixel is
                ILL_CONDITIONED; None = 1e7 (float32) / 1e10 (float64)
    bound_rtol: tolerance of :meth:`ParamSpace.at_bound`; default 1e-3
    """

    max_iters: int = eqx.field(default=256, static=True)
    rtol: float | None = eqx.field(default=None, static=True)
    atol: float | None = eqx.field(default=None, static=True)
    cond_max: float | None = eqx.field(default=None, static=True)
    bound_rtol: float = eqx.field(default=1e-3, static=True)

    def __check_init__(self):
        if self.max_iters < 1:
            raise JaxreflError(f"{type(self).__name__} needs max_iters >= 1, got {self.max_iters}")

    def tolerances(self, dtype) -> tuple[float, float, float]:
        """(rtol, atol, cond_max) for ``dtype``."""
        single = jnp.finfo(dtype).bits <= 32
        rtol = (1e-4 if single else 1e-6) if self.rtol is None else float(self.rtol)
        atol = (1e-6 if single else 1e-8) if self.atol is None else float(self.atol)
        return rtol, atol, default_cond_max(dtype, self.cond_max)


class OptimistixLM(_LibraryLM):
    """``optimistix.LevenbergMarquardt`` under ``vmap`` (module docstring); a cross-check of
    the lean solver. Fields: ``max_iters`` (default 256), ``rtol``, ``atol``, ``cond_max``,
    ``bound_rtol`` as described on the library solvers' common base (``_LibraryLM``)."""

    kind: ClassVar[str] = "optimistix"


class JaxoptLM(_LibraryLM):
    """``jaxopt.LevenbergMarquardt`` under ``vmap`` (module docstring; needs the optional
    jaxopt package). Fields: ``max_iters`` (default 256), ``rtol`` (step xtol), ``atol``
    (gradient gtol), ``cond_max``, ``bound_rtol``, as for :class:`OptimistixLM`."""

    kind: ClassVar[str] = "jaxopt"


Solver = LMOptions | OptimistixLM | JaxoptLM
"""A batched least-squares solver: the lean LM or one of the library solvers."""


class FitInfo(eqx.Module):
    """Per-pixel outcome of :func:`solve` (leading N axis)."""

    status: Int[Array, " N"]
    iterations: Int[Array, " N"]
    cost: Float[Array, " N"]
    converged: Bool[Array, " N"]
    jtj: Float[Array, "N P P"]  # J^T J at the returned theta
    active: Int[Array, " N"]  # active residual rows there (``_lm._linearise``)


def _optional(package: str, solver: str):
    """The optional ``package`` a library ``solver`` needs, or an ImportError saying how to
    install it."""
    try:
        with warnings.catch_warnings():
            # jaxopt warns at import that it is unmaintained (DeprecationWarning), and a
            # package may emit others from its own imports; none is actionable for our users.
            warnings.simplefilter("ignore")
            return __import__(package)
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError(
            f"{solver} needs the {package} package, an optional dependency: "
            "pip install 'jaxrefl[backends]' (or use fit.LMOptions())"
        ) from err


def _import_jaxopt():
    return _optional("jaxopt", "JaxoptLM")


def _import_optimistix():
    return _optional("optimistix", "OptimistixLM")


def _status(residual_fn, theta, theta0, data, converged, valid, space, n_usable, cond_max, rtol):
    cost, jtj, _, active = _linearise(residual_fn, theta, data)
    status = classify(
        theta,
        cost,
        jtj,
        converged,
        valid & jnp.all(jnp.isfinite(theta0)),
        cond_max=cond_max,
        space=space,
        n_usable=n_usable,
        bound_rtol=rtol,
    )
    return status, cost, jtj, active


@eqx.filter_jit
def _solve_optimistix(residual_fn, theta0, data, n_usable, space, opts, tol_dtype):
    import optimistix as optx

    # The tolerances are those of the dtype asked for (``tol_dtype``), the condition limit
    # that of the dtype the solver runs in.
    rtol, atol, _ = opts.tolerances(tol_dtype)
    _, _, cond_max = opts.tolerances(theta0.dtype)
    max_iters = opts.max_iters

    def one(t0, d, n):
        solver: optx.LevenbergMarquardt[Array, Array, None]
        solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
        # A non-finite start is not sent to the solver (its result would be NaN anyway).
        ok0 = jnp.all(jnp.isfinite(t0))
        start = jnp.where(ok0, t0, 0.0)
        sol: optx.Solution[Array, None]
        sol = optx.least_squares(
            residual_fn, solver, start, args=d, max_steps=max_iters, throw=False
        )
        res = sol.result
        # An array at run time; equinox's stubs type the comparison of results as bool.
        converged = jnp.asarray(res == optx.RESULTS.successful)
        hit_max = res == optx.RESULTS.nonlinear_max_steps_reached
        nonfinite = res == optx.RESULTS.nonfinite
        theta = sol.value
        status, cost, jtj, active = _status(
            residual_fn,
            theta,
            t0,
            d,
            converged,
            ~nonfinite & ok0,
            space,
            n,
            cond_max,
            opts.bound_rtol,
        )
        other = ~(converged | hit_max | nonfinite) & (
            severity(status) <= severity(Status.MAX_ITERATIONS)
        )
        status = jnp.where(other, Status.ILL_CONDITIONED, status).astype(jnp.int32)
        theta = jnp.where(ok0, theta, t0)
        iters = sol.stats["num_steps"].astype(jnp.int32)
        return theta, FitInfo(status, iters, cost, converged, jtj, active)

    return jax.vmap(one)(theta0, data, n_usable)


@eqx.filter_jit
def _solve_jaxopt_jit(residual_fn, theta0, data, n_usable, space, opts):
    jaxopt = _import_jaxopt()
    rtol, atol, cond_max = opts.tolerances(theta0.dtype)
    max_iters = opts.max_iters

    def one(t0, d, n):
        solver = jaxopt.LevenbergMarquardt(
            residual_fun=residual_fn,
            maxiter=max_iters,
            damping_parameter=1.0,
            solver="cholesky",
            materialize_jac=True,
            stop_criterion="madsen-nielsen",
            xtol=rtol,
            gtol=atol,
            implicit_diff=False,
        )
        ok0 = jnp.all(jnp.isfinite(t0))
        start = jnp.where(ok0, t0, 0.0)
        theta, state = solver.run(start, d)
        iters = state.iter_num.astype(jnp.int32)
        converged = iters < max_iters
        valid = ok0 & jnp.all(jnp.isfinite(theta))
        status, cost, jtj, active = _status(
            residual_fn, theta, t0, d, converged, valid, space, n, cond_max, opts.bound_rtol
        )
        theta = jnp.where(ok0, theta, t0)
        return theta, FitInfo(status, iters, cost, converged, jtj, active)

    return jax.vmap(one)(theta0, data, n_usable)


def _solve_jaxopt(*args):
    _import_jaxopt()  # fail early, outside the trace, if it is missing
    with warnings.catch_warnings():
        # jaxopt's internals may warn while tracing (deprecated JAX APIs); not actionable.
        warnings.simplefilter("ignore")
        return _solve_jaxopt_jit(*args)


def solve(
    residual_fn: Any,
    theta0: Float[Array, "N P"],
    data: Any,
    solver: Solver = LMOptions(),
    *,
    space: ParamSpace | None = None,
    n_usable: Int[Array, " N"] | None = None,
) -> tuple[Float[Array, "N P"], FitInfo]:
    """Solve N independent least-squares problems with ``solver``.

    ``residual_fn(theta (P,), data_n) -> r`` for one pixel; ``data`` carries a leading N
    axis. ``solver``: :class:`~jaxrefl.fit.LMOptions` (the lean LM, default),
    :class:`OptimistixLM` or :class:`JaxoptLM`, each with its own iteration budget and
    tolerances. ``space`` and ``n_usable`` complete the status (AT_BOUND, MASKED).
    """
    theta0 = jnp.asarray(theta0)
    if theta0.ndim != 2:
        raise JaxreflError(f"theta0 must have shape (N, P), got {theta0.shape}")
    n = theta0.shape[0]
    nu = jnp.full((n,), jnp.iinfo(jnp.int32).max, jnp.int32) if n_usable is None else n_usable
    if isinstance(solver, LMOptions):
        theta, res = batched_lm(residual_fn, theta0, data, solver, space=space, n_usable=nu)
        info = FitInfo(res.status, res.iterations, res.cost, res.converged, res.jtj, res.active)
        return theta, info
    if isinstance(solver, OptimistixLM):
        _import_optimistix()  # fail early, outside the trace, if it is missing
        single = jnp.finfo(theta0.dtype).bits <= 32
        if single and jax.config.read("jax_enable_x64"):
            # optimistix's LM builds its damping term in the default float (float64 under
            # jax_enable_x64), and lineax then refuses the float32 system ("Vector and operator
            # structures do not match"). Solve in float64 with float32's tolerances and hand
            # back float32, the dtype asked for.
            d64 = jax.tree.map(
                lambda x: x.astype(jnp.float64) if jnp.issubdtype(x.dtype, jnp.floating) else x,
                data,
            )
            theta, info = _solve_optimistix(
                residual_fn, theta0.astype(jnp.float64), d64, nu, space, solver, theta0.dtype
            )
            return theta.astype(theta0.dtype), eqx.tree_at(
                lambda i: (i.cost, i.jtj),
                info,
                (info.cost.astype(theta0.dtype), info.jtj.astype(theta0.dtype)),
            )
        return _solve_optimistix(residual_fn, theta0, data, nu, space, solver, theta0.dtype)
    if isinstance(solver, JaxoptLM):
        return _solve_jaxopt(residual_fn, theta0, data, nu, space, solver)
    raise TypeError(
        f"solver must be fit.LMOptions, fit.OptimistixLM or fit.JaxoptLM, not {solver!r}"
    )

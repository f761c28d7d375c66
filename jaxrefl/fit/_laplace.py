"""Laplace (Gauss–Newton) uncertainty of every fitted pixel, in natural units.

At the least-squares optimum theta* of a pixel, the Gauss–Newton approximation of the
posterior of the unconstrained parameters (flat prior in theta) is Gaussian:

    theta ~ N(theta*, Sigma_theta),   Sigma_theta = s^2 (J^T J)^-1,   J = dr/dtheta at theta*

where r is the whitened, weighted residual of :class:`Residual` (so J^T J = J_pred^T W J_pred
for W = weight / std^2), and s^2 is the noise scale (:attr:`LaplaceOptions.noise`):

* ``noise="known"``: s^2 = 1 (the noise model's std is trusted; r is already whitened);
* ``noise="estimate"`` (default): s^2 = 2 cost / (n - P), the residual variance with n the
  number of active residuals (usable observations minus censored ones that are satisfied,
  since those contribute neither residual nor Jacobian) and P free parameters; pixels with
  n <= P keep s^2 = 1 and get ``NOT_IDENTIFIED``.

Natural parameters x = g(theta) (the bijections of :class:`ParamSpace`) get the delta-method
covariance Sigma_x = A Sigma_theta A^T with A = dx/dtheta: ``std`` (N, P) and ``corr``
(N, P, P) in the units of :attr:`ParamSpace.labels`. For log-scale parameters (alpha,
exponents) the Gaussian in theta is a log-normal in x; ``theta_std`` gives its log-width.

Reliability flags (bits of ``flag``; 0 = the Gaussian approximation is trusted):

=========================  ====  =====================================================
``NO_ESTIMATE``              1    the fit gave no estimate (MASKED / NONFINITE_INPUT)
``NOT_POSITIVE_DEFINITE``    2    J^T J has a non-finite entry, or a non-positive pivot
                                  although it passed the condition test: no covariance
                                  (std NaN)
``AT_BOUND``                 4    a parameter sits at a bound: the posterior is cut
                                  off there, a Gaussian is the wrong shape
``NOT_IDENTIFIED``           8    some parameter's theta-space std exceeds
                                  ``max_theta_std`` (:class:`LaplaceOptions`; default
                                  1: the data do not pin it down within a factor e of a
                                  log-scale parameter, or within ~one logit unit of an
                                  albedo; e.g. roughness where
                                  no highlight was observed), the equilibrated condition
                                  number of J^T J exceeds ``cond_max`` (then J^T J is not
                                  inverted: std NaN), or n <= P
``NONFINITE``               16    a std or correlation is not finite though J^T J was
                                  inverted (an overflow in the delta method)
``SINGULAR``                32    J^T J is numerically singular (the condition test
                                  behind ``NOT_IDENTIFIED``, which is set too) and is
                                  not inverted: std and corr NaN
``CORR_UNDEFINED``          64    some parameter's std is 0 (its natural parameter does
                                  not move to first order: a saturated bijection, or a
                                  noise estimate of 0): its correlations are undefined
                                  and NaN; the other entries are formed
=========================  ====  =====================================================

Every non-finite number of ``std`` and ``corr`` carries a flag that says why: ``std`` is NaN
only where ``NO_ESTIMATE``, ``NOT_POSITIVE_DEFINITE``, ``SINGULAR`` or ``NONFINITE`` is set
(:data:`STD_NAN_FLAGS`), ``corr`` also where ``CORR_UNDEFINED`` is (:data:`CORR_NAN_FLAGS`).

A numerically singular J^T J (equilibrated condition number above ``cond_max``, the test
behind the fit's ``ILL_CONDITIONED``; a zero column included) is never inverted. J^T J is a
Gram matrix, positive semi-definite; when it is singular to the working precision, whether
its Cholesky factorisation meets a pivot of +1e-17 or -1e-17, and what an inverse built on
such a pivot holds (stds of 1e15), is rounding noise, and rounding differs with the batch
shape XLA compiles for (``_shard``). The condition test decides at ``cond_max`` (1e10 in
float64), far below the rounding floor 1/eps ~ 4.5e15: rounding moves a condition number of
1e10 by ~1e-6 relative, so flags and the NaN pattern agree between device layouts except for
a pixel within that sliver of the threshold. (In float32 the default 1e7 is at the floor,
1/eps ~ 8.4e6: there the flags of nearly singular pixels can follow the layout.)

Cost: the solver's last linearisation (J^T J and the active row count at theta,
:class:`~jaxrefl.fit.Linearisation`) is reused, so a pixel costs P x P algebra only: an
equilibrated Cholesky, its inverse, the delta-method product and the condition test. A
result without one (or another residual) costs one forward-mode Jacobian per pixel, about
one LM iteration.
"""

from __future__ import annotations

import enum
import numbers
from dataclasses import dataclass
from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from jaxrefl._errors import JaxreflError

from ._linalg import cho_solve_unrolled, cholesky_unrolled
from ._lm import _linearise as lm_linearise
from ._options import Option, check_number
from ._residual import PixelData, Residual
from ._shard import device_count, map_sharded
from ._status import default_cond_max, has_estimate, ill_conditioned

__all__ = [
    "CORR_NAN_FLAGS",
    "STD_NAN_FLAGS",
    "LaplaceFlag",
    "LaplaceOptions",
    "LaplaceResult",
    "flag_counts",
    "laplace",
    "same_residual",
    "undefined_correlations",
]


class LaplaceFlag(enum.IntFlag):
    """Bits of :attr:`LaplaceResult.flag` (module docstring)."""

    NO_ESTIMATE = 1
    NOT_POSITIVE_DEFINITE = 2
    AT_BOUND = 4
    NOT_IDENTIFIED = 8
    NONFINITE = 16
    SINGULAR = 32
    CORR_UNDEFINED = 64


#: The bits of which one is set wherever a std is not finite (module docstring).
STD_NAN_FLAGS = (
    LaplaceFlag.NO_ESTIMATE
    | LaplaceFlag.NOT_POSITIVE_DEFINITE
    | LaplaceFlag.SINGULAR
    | LaplaceFlag.NONFINITE
)
#: The bits of which one is set wherever a correlation is not finite.
CORR_NAN_FLAGS = STD_NAN_FLAGS | LaplaceFlag.CORR_UNDEFINED

#: The noise settings of :class:`LaplaceOptions`.
NOISE_SETTINGS = ("estimate", "known")


class LaplaceOptions(Option):
    """How :func:`laplace` forms and judges each pixel's covariance (kind ``"laplace"``;
    hashable, every field static).

    noise:         ``"estimate"`` (default: s^2 from the residuals) or ``"known"`` (s^2 = 1:
                   the residual is already whitened by the right sigma); module docstring
    max_theta_std: a parameter whose theta-space std exceeds it is not identified
                   (``NOT_IDENTIFIED``; > 0, default 1)
    cond_max:      equilibrated condition number of J^T J above which it is not inverted
                   (``NOT_IDENTIFIED`` and ``SINGULAR``); None = 1e7 (float32) / 1e10
                   (float64), as the fit's ``ILL_CONDITIONED``
    unroll_max:    largest P for the unrolled Cholesky (:mod:`._linalg`; else
                   jnp.linalg.cholesky, the same factor to rounding); default 8, as
                   :class:`~jaxrefl.fit.LMOptions`
    """

    kind: ClassVar[str] = "laplace"
    noise: Literal["estimate", "known"] = eqx.field(default="estimate", static=True)
    max_theta_std: float = eqx.field(default=1.0, static=True)
    cond_max: float | None = eqx.field(default=None, static=True)
    unroll_max: int = eqx.field(default=8, static=True)

    def __check_init__(self):
        if self.noise not in NOISE_SETTINGS:
            raise JaxreflError(
                f"LaplaceOptions needs noise one of {', '.join(map(repr, NOISE_SETTINGS))}, "
                f"got {self.noise!r}"
            )
        check_number("LaplaceOptions", "max_theta_std", self.max_theta_std, positive=True)
        if self.cond_max is not None:
            check_number("LaplaceOptions", "cond_max", self.cond_max, positive=True)
        v = self.unroll_max
        if not isinstance(v, numbers.Integral) or isinstance(v, bool) or v < 0:
            raise JaxreflError(f"LaplaceOptions needs an integer unroll_max >= 0, got {v!r}")


def undefined_correlations(std: np.ndarray, corr: np.ndarray, flag: np.ndarray):
    """``corr`` (N, P, P) with NaN where a parameter's ``std`` (N, P) is 0 (the correlation
    of a parameter that does not vary is undefined), and ``flag`` (N,) with
    ``CORR_UNDEFINED`` set exactly on the pixels that have such an entry. For std and
    corr changed after :func:`laplace` (e.g. widened by a shared parameter's uncertainty);
    pixels without a covariance (a non-finite std) keep their NaN and lose the bit."""
    std = np.asarray(std)
    zero = std == 0
    pair = zero[:, :, None] | zero[:, None, :]
    formed = np.all(np.isfinite(std), axis=-1)
    pair &= formed[:, None, None]
    corr = np.where(pair, np.nan, corr)
    bit = int(LaplaceFlag.CORR_UNDEFINED)
    has = np.any(pair, axis=(-2, -1))
    flag = (np.asarray(flag) & ~bit) | np.where(has, bit, 0)
    return corr, flag.astype(np.asarray(flag).dtype)


def flag_counts(flag: ArrayLike) -> dict[str, int]:
    """Pixels per :class:`LaplaceFlag` bit (a pixel may count under several), plus
    ``reliable`` (flag 0): ``{"NO_ESTIMATE": 12, ..., "reliable": 9800}``."""
    f = np.asarray(flag).reshape(-1)
    out = {b.name or str(b.value): int(np.sum((f & b.value) != 0)) for b in LaplaceFlag}
    out["reliable"] = int(np.sum(f == 0))
    return out


@dataclass(frozen=True, eq=False)
class LaplaceResult:
    """Per-pixel Laplace covariance (leading axis N; P = ``len(labels)``).

    std:        (N, P) standard deviation of each natural parameter
    corr:       (N, P, P) correlation matrix of the natural parameters
    cov:        (N, P, P) natural-unit covariance
    theta_std:  (N, P) standard deviation in the unconstrained space
    noise_var:  (N,) s^2 used (estimated or 1)
    flag:       (N,) int32 bit set of :class:`LaplaceFlag`; 0 = reliable
    identified: (N, P) bool, per-parameter theta_std <= max_theta_std
    """

    labels: tuple[str, ...]
    std: Float[Array, "N P"]
    corr: Float[Array, "N P P"]
    cov: Float[Array, "N P P"]
    theta_std: Float[Array, "N P"]
    noise_var: Float[Array, " N"]
    flag: Int[Array, " N"]
    identified: Array

    @property
    def reliable(self) -> Array:
        """(N,) bool: flag == 0."""
        return self.flag == 0

    def flag_counts(self) -> dict[str, int]:
        """Pixels per flag bit (a pixel may count under several), plus ``reliable``
        (:func:`flag_counts`)."""
        return flag_counts(self.flag)

    def std_of(self, label: str) -> Array:
        """(N,) std of the entry named ``label`` (e.g. ``"alpha"``, ``"albedo.G"``)."""
        return self.std[:, self.labels.index(label)]


def _linearise(res: Residual, theta, data: PixelData):
    """J^T J, the active row count and the cost at theta, as the LM computes them (a pixel
    without an estimate is linearised at 0 and flagged; gradient-safe)."""
    t = jnp.where(jnp.all(jnp.isfinite(theta)), theta, 0.0)
    # A non-finite Jacobian entry makes the pixel NOT_POSITIVE_DEFINITE (through jtj).
    cost, jtj, _, active = lm_linearise(res, t, data)
    return jtj, active, cost


def _pixel(space, theta, jtj, active, cost, estimate: bool, unroll_max: int, cond_max):
    """The Laplace covariance of one pixel from J^T J, the active rows and the cost there."""
    p = theta.shape[-1]
    ok = jnp.all(jnp.isfinite(theta))
    t = jnp.where(ok, theta, 0.0)
    dof = active - p
    if estimate:
        s2 = jnp.where(dof > 0, 2.0 * cost / jnp.where(dof > 0, dof, 1), 1.0)
    else:
        s2 = jnp.ones((), theta.dtype)
    # Column scaling (equilibration) before the factorisation keeps float32 pivots sane when
    # albedo and log-alpha columns differ by orders of magnitude.
    d = jnp.diagonal(jtj)
    scale = 1.0 / jnp.sqrt(jnp.where(d > 0, d, 1.0))
    a = jtj * scale[:, None] * scale[None, :]
    eye = jnp.eye(p, dtype=theta.dtype)
    if p <= unroll_max:
        l_fac, pd = cholesky_unrolled(a)
        l_safe = jnp.where(pd, l_fac, eye)  # gradient-safe: a failed factor is not used
        inv_a = cho_solve_unrolled(l_safe[None], eye).T
    else:
        l_fac = jnp.linalg.cholesky(a)
        pd = jnp.all(jnp.isfinite(l_fac))
        l_safe = jnp.where(pd, l_fac, eye)
        inv_a = jax.scipy.linalg.cho_solve((l_safe, True), eye)
    pd = pd & jnp.all(jnp.isfinite(jtj)) & jnp.all(d > 0) & jnp.all(jnp.isfinite(inv_a))
    # The condition test (eigensolver-free, _status) decides whether J^T J is inverted: the
    # factorisation and inverse of a numerically singular one are rounding noise (module
    # docstring).
    finite = jnp.all(jnp.isfinite(jtj))
    ill = finite & ill_conditioned(jnp.where(finite, jtj, 0.0), cond_max)
    formed = pd & ~ill
    cov_t = s2 * inv_a * scale[:, None] * scale[None, :]
    cov_t = jnp.where(formed, cov_t, jnp.nan)
    amat = space.jacobian_natural(t)  # (P, P): dx/dtheta
    cov_x = amat @ cov_t @ amat.T
    std_t = jnp.sqrt(jnp.maximum(jnp.diagonal(cov_t), 0.0))
    std_x = jnp.sqrt(jnp.maximum(jnp.diagonal(cov_x), 0.0))
    # A zero std (a parameter that does not move) leaves its correlations undefined: NaN
    # there (flagged CORR_UNDEFINED); the division is guarded so its gradient stays finite.
    denom = std_x[:, None] * std_x[None, :]
    corr = jnp.where(denom > 0, cov_x / jnp.where(denom > 0, denom, 1.0), jnp.nan)
    corr = jnp.where(formed, corr, jnp.nan)
    undefined = formed & jnp.any(std_x == 0)
    return std_x, corr, cov_x, std_t, s2, formed, ill, dof, ok, undefined


@eqx.filter_jit
def _laplace_jit(space, res, theta, lin, cost, status, estimate, max_theta_std, cond_max, unroll):
    """``res`` None: ``lin`` = (jtj, active) from the fit, ``cost`` its cost; otherwise
    ``lin`` = (data,) and J^T J, the active rows and the cost come from ``res`` here."""
    if res is None:
        jtj, active = lin
    else:
        (data,) = lin
        jtj, active, cost = jax.vmap(lambda t, d: _linearise(res, t, d))(theta, data)

    def one(t, j, a, c):
        return _pixel(space, t, j, a, c, estimate, unroll, cond_max)

    std, corr, cov, std_t, s2, formed, ill, dof, ok, undefined = jax.vmap(one)(
        theta, jtj, active, cost
    )
    at_bound = jnp.any(space.at_bound(jnp.where(ok[:, None], theta, 0.0)), axis=-1)
    identified = std_t <= max_theta_std
    none = ~has_estimate(status) | ~ok
    flag = jnp.zeros(theta.shape[:1], jnp.int32)
    flag = flag | jnp.where(none, LaplaceFlag.NO_ESTIMATE, 0)
    flag = flag | jnp.where(~formed & ~ill & ~none, LaplaceFlag.NOT_POSITIVE_DEFINITE, 0)
    flag = flag | jnp.where(at_bound & ~none, LaplaceFlag.AT_BOUND, 0)
    not_id = (ill | (formed & (~jnp.all(identified, axis=-1) | (dof <= 0)))) & ~none
    flag = flag | jnp.where(not_id, LaplaceFlag.NOT_IDENTIFIED, 0)
    flag = flag | jnp.where(ill & ~none, LaplaceFlag.SINGULAR, 0)
    flag = flag | jnp.where(undefined & ~none, LaplaceFlag.CORR_UNDEFINED, 0)
    # Overflow in the delta method; the NaN of an undefined correlation is not one.
    zero = std == 0
    defined = ~(zero[:, :, None] | zero[:, None, :])
    corr_ok = jnp.all(jnp.isfinite(corr) | ~defined, axis=(-2, -1))
    finite = jnp.all(jnp.isfinite(std), axis=-1) & corr_ok
    flag = flag | jnp.where(~finite & formed & ~none, LaplaceFlag.NONFINITE, 0)
    nan = jnp.nan
    std = jnp.where(none[:, None], nan, std)
    std_t = jnp.where(none[:, None], nan, std_t)
    corr = jnp.where(none[:, None, None], nan, corr)
    cov = jnp.where(none[:, None, None], nan, cov)
    return std, corr, cov, std_t, s2, flag.astype(jnp.int32), identified & ~none[:, None]


def laplace(
    fit,
    data: PixelData,
    *,
    residual: Residual | None = None,
    options: LaplaceOptions = LaplaceOptions(),
    devices: int | None = None,
) -> LaplaceResult:
    """Laplace covariance of every pixel of a :class:`FitResult` from :func:`fit_pixels`.

    fit:       the result (its ``theta``, ``status``, ``space``, ``model``)
    data:      the :class:`PixelData` it was fitted to (leading N axis)
    residual:  the residual whose curvature is wanted (default: the fit's own, recorded in
               ``fit.linearisation``; Gaussian sigma 1, L2 for a result without one). When
               it is the fit's, the fit's J^T J at theta is reused and ``data`` is not
               read; another residual is linearised here (one Jacobian per pixel)
    options:   the noise scale (estimated or known) and the thresholds of
               ``NOT_IDENTIFIED`` (:class:`LaplaceOptions`)
    devices:   how many of JAX's devices share the pixels (default all)
    """
    from ._residual import make_residual

    theta = jnp.asarray(fit.theta)
    if theta.ndim != 2:
        raise JaxreflError(f"laplace expects a batch fit with theta (N, P); got {theta.shape}")
    if not isinstance(options, LaplaceOptions):
        raise JaxreflError(f"laplace takes options=LaplaceOptions(...), not {options!r}")
    cond_max = default_cond_max(theta.dtype, options.cond_max)
    lin = getattr(fit, "linearisation", None)
    if lin is not None and (residual is None or same_residual(residual, lin.residual)):
        # The fit's own J^T J at theta: no Jacobian to compute here.
        res = None
        cost = jnp.where(jnp.isfinite(fit.cost), fit.cost, 0.0).astype(theta.dtype)
        rest: tuple = (jnp.asarray(lin.jtj, theta.dtype), jnp.asarray(lin.active))
    else:
        res = make_residual(fit.model, fit.space) if residual is None else residual
        cost = jnp.zeros(theta.shape[:1], theta.dtype)  # recomputed from ``res``
        rest = (data.astype(theta.dtype),)
        if data.obs.shape[0] != theta.shape[0]:
            raise JaxreflError(f"data has {data.obs.shape[0]} pixels, the fit {theta.shape[0]}")

    def run(theta, cost, status, *rest):
        return _laplace_jit(
            fit.space,
            res,
            theta,
            rest,
            cost,
            status,
            options.noise == "estimate",
            float(options.max_theta_std),
            cond_max,
            int(options.unroll_max),
        )

    # Pixels are independent: spread them over every device, as the fit does (``_shard``).
    args = (theta, cost, jnp.asarray(fit.status), *rest)
    out = map_sharded(run, args, device_count(devices))
    std, corr, cov, std_t, s2, flag, identified = out
    return LaplaceResult(fit.space.labels, std, corr, cov, std_t, s2, flag, identified)


def same_residual(a: Residual, b: Residual) -> bool:
    """Whether two residuals are the same function (identical, or equal leaf by leaf): a
    linearisation taken with one serves the other."""
    return a is b or bool(eqx.tree_equal(a, b))

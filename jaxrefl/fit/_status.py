"""Per-pixel outcome codes of a fit: failures are values, never exceptions mid-batch.

Every solver in :mod:`jaxrefl.fit` returns one integer per problem (pixel), in the spirit of
optimistix's ``RESULTS``: a batch of a million pixels must finish even when some pixels have
no data, NaN inputs or an unidentifiable parameter. The codes are ordered by severity; where
several apply, the most severe (listed first below) wins. Severity does not follow the
numbers (AT_BOUND is more severe than ILL_CONDITIONED): compare codes by :func:`severity`,
never by value; the numbers are stored in EXR maps and report files and do not change.

=================  ====  ==========================================================
NONFINITE_INPUT     5    non-finite values that could not be masked (a non-finite
                         initial guess; every observation of the pixel non-finite),
                         or a non-finite result
MASKED              4    fewer usable observations (finite, weight > 0) than free
                         parameters: the problem is not posed; no estimate (NaN)
AT_BOUND            2    a parameter sits at (or beyond) a bound of its range; its
                         value is an extreme, not an interior optimum
ILL_CONDITIONED     3    J^T J at the solution is numerically singular after
                         scaling its columns to unit diagonal: some combination of
                         parameters is not identified by the data
MAX_ITERATIONS      1    the iteration limit was reached before the convergence test
                         passed (the value is the best one found, often fine)
CONVERGED           0    the convergence test passed
=================  ====  ==========================================================
"""

from __future__ import annotations

import enum
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from . import _eig

if TYPE_CHECKING:
    from ._transform import ParamSpace

__all__ = [
    "SEVERITY",
    "STATUS_MEANINGS",
    "Status",
    "classify",
    "describe",
    "equilibrated_condition",
    "has_estimate",
    "ill_conditioned",
    "most_severe",
    "severity",
]


class Status(enum.IntEnum):
    """Per-pixel outcome of a fit (see the module docstring for precedence)."""

    CONVERGED = 0
    MAX_ITERATIONS = 1
    AT_BOUND = 2
    ILL_CONDITIONED = 3
    MASKED = 4
    NONFINITE_INPUT = 5


STATUS_MEANINGS: dict[int, str] = {
    Status.CONVERGED: "converged: the relative cost change and step size fell below tolerance",
    Status.MAX_ITERATIONS: "stopped at the iteration limit before the convergence test passed",
    Status.AT_BOUND: "a parameter is at (or beyond) a bound of its range",
    Status.ILL_CONDITIONED: "J^T J is numerically singular: parameters not identified by the data",
    Status.MASKED: "fewer usable observations than free parameters: no estimate",
    Status.NONFINITE_INPUT: "non-finite input that could not be masked, or a non-finite result",
}

# Most severe first: where several conditions hold, the first one listed is reported.
SEVERITY: tuple[Status, ...] = (
    Status.NONFINITE_INPUT,
    Status.MASKED,
    Status.AT_BOUND,
    Status.ILL_CONDITIONED,
    Status.MAX_ITERATIONS,
    Status.CONVERGED,
)

# code -> rank: 0 for the least severe (CONVERGED), len(SEVERITY) - 1 for the most severe.
_RANK = np.zeros(max(Status) + 1, np.int32)
_RANK[np.array(SEVERITY[::-1])] = np.arange(len(SEVERITY))
_BY_RANK = np.array(SEVERITY[::-1], np.int32)  # rank -> code


def _is_jax(x: object) -> bool:
    return isinstance(x, jax.Array)


def severity(status: ArrayLike) -> Any:
    """The severity rank of each :class:`Status` code: 0 for ``CONVERGED`` up to 5 for
    ``NONFINITE_INPUT``, in the order of :data:`SEVERITY` (not the numeric order of the codes).

    A JAX array (or tracer) gives a JAX array; anything else a NumPy array (or scalar).
    Codes outside the table are clipped to it (below 0 as ``CONVERGED``, above 5 as
    ``NONFINITE_INPUT``), as a numeric comparison with ``MASKED`` would place them.
    """
    if _is_jax(status):
        return jnp.take(jnp.asarray(_RANK), status, mode="clip")
    return np.take(_RANK, np.asarray(status, np.int64), mode="clip")


def most_severe(a: ArrayLike, b: ArrayLike) -> Any:
    """Elementwise the more severe of two :class:`Status` codes (by :func:`severity`)."""
    if _is_jax(a) or _is_jax(b):
        return jnp.asarray(_BY_RANK)[
            jnp.maximum(severity(jnp.asarray(a)), severity(jnp.asarray(b)))
        ]
    return _BY_RANK[np.maximum(severity(a), severity(b))]


def has_estimate(status: ArrayLike) -> Any:
    """Where a fit gave parameters: the status is less severe than ``MASKED`` (neither
    ``MASKED`` nor ``NONFINITE_INPUT``). Boolean, JAX or NumPy like :func:`severity`."""
    return severity(status) < _RANK[Status.MASKED]


def describe(status_map: ArrayLike) -> dict[str, int]:
    """Count pixels per status: ``{"CONVERGED": 9812, "AT_BOUND": 170, ...}``.

    Every status name appears (with 0 where absent), in the order of :class:`Status`; codes
    that are not a :class:`Status` are counted under ``"UNKNOWN"`` (only if present).
    """
    s = np.asarray(status_map).reshape(-1).astype(np.int64)
    out = {st.name: int(np.sum(s == st.value)) for st in Status}
    unknown = int(s.size - sum(out.values()))
    if unknown:
        out["UNKNOWN"] = unknown
    return out


def _equilibrate(jtj: Float[Array, "*b P P"]) -> tuple[Float[Array, "*b P P"], Bool[Array, "*b"]]:
    """C = D^-1/2 J^T J D^-1/2 (identity where a column is numerically zero) and that mask."""
    d = jnp.diagonal(jtj, axis1=-2, axis2=-1)
    dmax = jnp.max(d, axis=-1, keepdims=True)
    # A column below eps^2 of the largest one is numerically zero (J's column below eps).
    tiny = jnp.finfo(jtj.dtype).eps ** 2
    zero_col = jnp.any(d <= tiny * dmax, axis=-1) | ~jnp.all(jnp.isfinite(jtj), axis=(-2, -1))
    s = 1.0 / jnp.sqrt(jnp.where(d > tiny * dmax, d, 1.0))
    c = jtj * s[..., :, None] * s[..., None, :]
    c = jnp.where(zero_col[..., None, None], jnp.eye(jtj.shape[-1], dtype=jtj.dtype), c)
    return c, zero_col


def equilibrated_condition(jtj: Float[Array, "*b P P"]) -> Float[Array, "*b"]:
    """Condition number of D^-1/2 J^T J D^-1/2 with D = diag(J^T J).

    Column scaling removes the units of the parameters (and the saturation of a sigmoid),
    so the number measures only how collinear the columns of J are: 1 for orthogonal
    columns, inf for a zero column or exact dependence.
    """
    c, zero_col = _equilibrate(jtj)
    ev = jnp.linalg.eigvalsh(c)
    lo, hi = ev[..., 0], ev[..., -1]
    cond = jnp.where(lo > 0, hi / jnp.where(lo > 0, lo, 1.0), jnp.inf)
    return jnp.where(zero_col, jnp.inf, cond)


def default_cond_max(dtype, cond_max: float | None = None) -> float:
    """``cond_max``, or where None the default for ``dtype``: 1e7 (float32 and narrower),
    1e10 (float64); the threshold of :func:`ill_conditioned` every solver applies."""
    if cond_max is not None:
        return float(cond_max)
    return 1e7 if jnp.finfo(dtype).bits <= 32 else 1e10


def ill_conditioned(jtj: Float[Array, "*b P P"], cond_max: float) -> Bool[Array, "*b"]:
    """``equilibrated_condition(jtj) > cond_max``, decided without an eigensolver.

    For P <= ``_eig.MAX_P`` by definiteness tests (:mod:`jaxrefl.fit._eig`: exact up to a
    relative threshold shift of (P - 1) 2^-12, 1e-3 for P = 5), elementwise arithmetic
    that vectorises over the batch instead of one LAPACK eigensolver call per matrix;
    beyond, by the eigenvalues.
    """
    if jtj.shape[-1] > _eig.MAX_P:
        return equilibrated_condition(jtj) > cond_max
    c, zero_col = _equilibrate(jtj)
    return zero_col | _eig.condition_exceeds(c, cond_max)


def classify(
    theta: Float[Array, " P"],
    cost: Float[Array, ""],
    jtj: Float[Array, "P P"],
    converged: Bool[Array, ""],
    valid: Bool[Array, ""],
    *,
    cond_max: float,
    space: ParamSpace | None = None,
    n_usable: Int[Array, ""] | None = None,
    bound_rtol: float = 1e-3,
) -> Int[Array, ""]:
    """The :class:`Status` of one pixel; the most severe condition wins (see ``_status``)."""
    status = jnp.where(converged, Status.CONVERGED, Status.MAX_ITERATIONS)
    ill = ill_conditioned(jtj, cond_max)
    status = jnp.where(ill, Status.ILL_CONDITIONED, status)
    if space is not None:
        status = jnp.where(jnp.any(space.at_bound(theta, bound_rtol)), Status.AT_BOUND, status)
    if n_usable is not None:
        status = jnp.where(n_usable < theta.shape[-1], Status.MASKED, status)
    finite = valid & jnp.isfinite(cost) & jnp.all(jnp.isfinite(theta))
    status = jnp.where(finite, status, Status.NONFINITE_INPUT)
    return status.astype(jnp.int32)

"""The shared unrolled Cholesky and triangular solves (jaxrefl/fit/_linalg.py) against NumPy's
LAPACK on random symmetric positive definite matrices, in float32 and float64."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl.fit._linalg import (
    cho_solve_unrolled,
    cholesky_unrolled,
    solve_lower_t_unrolled,
    solve_lower_unrolled,
)

# Relative tolerances of each dtype against float64 LAPACK: a few hundred ulps, for
# matrices whose condition number _spd keeps moderate.
_RTOL = {np.float32: 2e-4, np.float64: 1e-10}


def _spd(rng: np.random.Generator, n: int, p: int) -> np.ndarray:
    """n random SPD (p, p) matrices: Gram matrices of 3p random rows plus a small ridge."""
    j = rng.normal(size=(n, 3 * p, p))
    return np.einsum("nmp,nmq->npq", j, j) + 0.1 * np.eye(p)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("p", [1, 2, 4, 7, 9])
def test_cholesky_matches_numpy(p, dtype):
    rng = np.random.default_rng(100 + p)
    a = _spd(rng, 16, p)
    b = rng.normal(size=(16, p))
    l, ok = cholesky_unrolled(jnp.asarray(a, dtype))
    assert l.dtype == dtype and bool(np.all(ok))
    ref = np.linalg.cholesky(a)
    scale = np.max(np.abs(ref), axis=(-2, -1), keepdims=True)
    np.testing.assert_allclose(np.asarray(l, np.float64) / scale, ref / scale, atol=_RTOL[dtype])
    assert np.all(np.triu(np.asarray(l), 1) == 0)
    # The solves, each against NumPy's on the float64 factor.
    lf = jnp.asarray(ref, dtype)
    bf = jnp.asarray(b, dtype)
    fwd = np.linalg.solve(ref, b[..., None])[..., 0]
    back = np.linalg.solve(np.swapaxes(ref, -1, -2), b[..., None])[..., 0]
    full = np.linalg.solve(a, b[..., None])[..., 0]
    for got, want in (
        (solve_lower_unrolled(lf, bf), fwd),
        (solve_lower_t_unrolled(lf, bf), back),
        (cho_solve_unrolled(lf, bf), full),
    ):
        assert got.dtype == dtype
        tol = _RTOL[dtype] * np.linalg.cond(a)[:, None] * np.max(np.abs(want), -1, keepdims=True)
        assert np.all(np.abs(np.asarray(got, np.float64) - want) <= tol)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_cholesky_flags_a_matrix_that_is_not_positive_definite(dtype):
    rng = np.random.default_rng(3)
    a = _spd(rng, 4, 5)
    a[:, 4, 4] = -1.0
    l, ok = cholesky_unrolled(jnp.asarray(a, dtype))
    assert not np.any(ok) and np.all(np.isfinite(np.asarray(l)))

"""The eigensolver-free condition test of the per-pixel status (jaxrefl.fit._eig)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl.fit import _eig
from jaxrefl.fit._status import equilibrated_condition, ill_conditioned


def _near_dependent(rng, n, p, k=None):
    """Equilibrated J^T J whose last column is the first plus 10^-u noise, u in [0, 8]:
    condition numbers from 1 to about 1e16, spread over the cond_max used below."""
    j = rng.normal(size=(n, k or 2 * p, p))
    j[:, :, -1] = j[:, :, 0] + 10.0 ** rng.uniform(-8, 0, size=(n, 1)) * j[:, :, -1]
    a = np.einsum("nkp,nkq->npq", j, j)
    d = np.sqrt(np.einsum("npp->np", a))
    return a / d[:, :, None] / d[:, None, :]


@pytest.mark.parametrize("p", [2, 3, 5, 8])
def test_positive_definite_matches_numpy(p):
    rng = np.random.default_rng(p)
    a = _near_dependent(rng, 400, p)
    # Shift by s lambda_min, s in [0, 2]: about half of them pushed past singular.
    lam_min = np.linalg.eigvalsh(a)[:, 0]
    b = a - (rng.uniform(0.0, 2.0, 400) * lam_min)[:, None, None] * np.eye(p)
    lo = np.linalg.eigvalsh(b)[:, 0]
    got = np.asarray(jax.jit(_eig.positive_definite)(jnp.asarray(b)))
    clear = np.abs(lo) > 1e-9 * np.abs(np.linalg.eigvalsh(b)[:, -1])  # not within rounding
    assert 0.2 < np.mean(lo > 0) < 0.8
    np.testing.assert_array_equal(got[clear], (lo > 0)[clear])


@pytest.mark.parametrize("p", [2, 3, 5, 8])
def test_ill_conditioned_agrees_with_the_eigenvalues(p):
    """Same answer as eigvalsh wherever kappa is not within the documented threshold shift
    (P - 1) 2^-BISECTIONS (plus rounding) of cond_max; in float64 over kappa 1 .. 1e16."""
    rng = np.random.default_rng(10 + p)
    a = jnp.asarray(_near_dependent(rng, 2000, p))
    cond_max = 1e8
    kappa = np.linalg.cond(np.asarray(a))
    got = np.asarray(jax.jit(lambda x: ill_conditioned(x, cond_max))(a))
    ref = np.asarray(equilibrated_condition(a)) > cond_max
    band = (p - 1) * 2.0**-_eig.BISECTIONS + 1e-6
    clear = np.abs(kappa / cond_max - 1) > band
    assert 0.2 < ref.mean() < 0.8  # both answers are well represented
    np.testing.assert_array_equal(got[clear], ref[clear])
    np.testing.assert_array_equal(got[clear], kappa[clear] > cond_max)


def test_ill_conditioned_edge_cases_and_float32():
    eye = jnp.eye(4)
    zero_col = eye.at[2, 2].set(0.0)
    nan = eye.at[1, 0].set(jnp.nan).at[0, 1].set(jnp.nan)
    singular = jnp.ones((4, 4))  # rank 1: lambda_min = 0 exactly
    indefinite = jnp.asarray([[1.0, 2.0], [2.0, 1.0]])  # eigenvalues 3 and -1
    scaled = jnp.diag(jnp.asarray([1e-6, 1.0, 1e6, 3.0]))  # units only: kappa = 1
    for a, want in [(eye, False), (zero_col, True), (nan, True), (singular, True), (scaled, False)]:
        assert bool(ill_conditioned(a, 1e8)) is want
        assert bool(equilibrated_condition(a) > 1e8) is want
    assert bool(ill_conditioned(indefinite, 1e8))
    # float32 and a batch shape: the same answers as float64 away from the threshold.
    rng = np.random.default_rng(3)
    a = _near_dependent(rng, 500, 5)
    kappa = np.linalg.cond(a)
    got = np.asarray(ill_conditioned(jnp.asarray(a, jnp.float32).reshape(5, 100, 5, 5), 1e4))
    clear = np.abs(np.log10(kappa / 1e4)) > 0.3  # float32 rounding moves kappa ~1e4 by < 2x
    np.testing.assert_array_equal(got.reshape(-1)[clear], (kappa > 1e4)[clear])
    # Beyond MAX_P the status falls back to the eigenvalues (same answer).
    big = jnp.asarray(_near_dependent(rng, 50, _eig.MAX_P + 1))
    np.testing.assert_array_equal(
        np.asarray(ill_conditioned(big, 1e8)),
        np.asarray(equilibrated_condition(big)) > 1e8,
    )

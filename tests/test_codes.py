"""Stored codes (fit Status, observation ObsStatus): their numbers never change (they are
written to EXR maps and report.json files, and resuming reads them back), and their order of
severity is explicit, not the numeric order."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrefl
from jaxrefl.fit import (
    GaussianNoise,
    LaplaceFlag,
    Status,
    has_estimate,
    make_residual,
    most_severe,
    severity,
)
from jaxrefl.fit._laplace import flag_counts, same_residual
from jaxrefl.fit._status import SEVERITY
from jaxrefl.io._capture import OBS_STATUS, Capture, ObsStatus, geometry_status, obs_severity

# ----------------------------------------------------------------------------- fit Status
STORED_STATUS = {
    "CONVERGED": 0,
    "MAX_ITERATIONS": 1,
    "AT_BOUND": 2,
    "ILL_CONDITIONED": 3,
    "MASKED": 4,
    "NONFINITE_INPUT": 5,
}
# least severe first
STATUS_ORDER = ("CONVERGED", "MAX_ITERATIONS", "ILL_CONDITIONED", "AT_BOUND", "MASKED")
STATUS_ORDER = (*STATUS_ORDER, "NONFINITE_INPUT")


def test_status_numbers_are_the_stored_ones():
    assert {s.name: int(s) for s in Status} == STORED_STATUS


def test_status_severity_is_the_documented_order_not_the_numeric_one():
    ranks = [int(severity(Status[name])) for name in STATUS_ORDER]
    assert ranks == list(range(len(Status)))
    assert tuple(s.name for s in SEVERITY) == STATUS_ORDER[::-1]
    # the case that numeric comparison gets wrong
    assert Status.AT_BOUND < Status.ILL_CONDITIONED
    assert severity(Status.AT_BOUND) > severity(Status.ILL_CONDITIONED)


@pytest.mark.parametrize("kind", ["numpy", "jax", "jit"])
def test_severity_helpers_on_arrays(kind):
    codes = np.array([int(s) for s in Status], np.int32)
    want_rank = np.array([STATUS_ORDER.index(Status(c).name) for c in codes])
    want_has = np.array([Status(c) not in (Status.MASKED, Status.NONFINITE_INPUT) for c in codes])
    pairs = [(a, b) for a in codes for b in codes]
    a = np.array([p[0] for p in pairs], np.int32)
    b = np.array([p[1] for p in pairs], np.int32)
    want_worst = np.array([x if STATUS_ORDER.index(Status(x).name) >= STATUS_ORDER.index(
        Status(y).name) else y for x, y in pairs])  # fmt: skip

    def run(c, a, b):
        return severity(c), has_estimate(c), most_severe(a, b)

    if kind == "numpy":
        rank, has, worst = run(codes, a, b)
        assert isinstance(rank, np.ndarray) and isinstance(has, np.ndarray)
        assert isinstance(worst, np.ndarray)
    else:
        fn = jax.jit(run) if kind == "jit" else run
        rank, has, worst = fn(jnp.asarray(codes), jnp.asarray(a), jnp.asarray(b))
        assert isinstance(rank, jax.Array) and isinstance(worst, jax.Array)
    np.testing.assert_array_equal(np.asarray(rank), want_rank)
    np.testing.assert_array_equal(np.asarray(has), want_has)
    np.testing.assert_array_equal(np.asarray(worst), want_worst)
    # a scalar code against an array, as ps.fit_normal_brdf uses it
    np.testing.assert_array_equal(
        np.asarray(most_severe(jnp.asarray(codes), Status.MASKED)),
        [int(Status.MASKED)] * 5 + [int(Status.NONFINITE_INPUT)],
    )


# ----------------------------------------------------------------------------- ObsStatus
STORED_OBS = {
    "OK": 0,
    "SATURATED": 1,
    "DARK": 2,
    "NONFINITE": 3,
    "NEGATIVE": 4,
    "MASKED": 5,
    "LIGHT_BELOW_HORIZON": 6,
    "VIEW_BELOW_HORIZON": 7,
    "CENSORED_MIXED": 8,
}
# least severe first (the precedence of jaxrefl.io._capture's docstring, reversed)
OBS_ORDER = ("OK", "DARK", "SATURATED", "CENSORED_MIXED", "VIEW_BELOW_HORIZON")
OBS_ORDER = (*OBS_ORDER, "LIGHT_BELOW_HORIZON", "MASKED", "NEGATIVE", "NONFINITE")
ALL_OBS = np.array([int(s) for s in ObsStatus], np.uint8)


def test_obs_status_numbers_are_the_stored_ones():
    assert {s.name: int(s) for s in ObsStatus} == STORED_OBS
    assert OBS_STATUS == {v: k.lower() for k, v in STORED_OBS.items()}


def test_obs_severity_is_the_documented_precedence():
    ranks = obs_severity(np.array([ObsStatus[n] for n in OBS_ORDER], np.uint8))
    np.testing.assert_array_equal(ranks, np.arange(len(ObsStatus)))


def _capture(status, height=1):
    """One photo of ``height`` x n pixels, one channel, with the given status codes."""
    status = np.asarray(status, np.uint8).reshape(1, height, -1, 1)
    return Capture(
        images=np.ones(status.shape, np.float32),
        status=status,
        light_pos=np.array([[0.0, 0.0, 10.0]]),
        light_dir=None,
        light_power=np.ones((1, 1)),
        camera_pos=np.array([[0.0, 0.0, 10.0]]),
        side=1.0,
        points=np.zeros((height, status.shape[2], 3)),
    )


def test_mask_and_horizon_keep_the_more_severe_codes():
    invalid = (ObsStatus.NONFINITE, ObsStatus.NEGATIVE)
    # a mask marks every code masked but the invalid values
    masked = _capture(ALL_OBS).apply_mask(np.zeros((1, ALL_OBS.size), bool)).status.ravel()
    want = [c if c in invalid else ObsStatus.MASKED for c in ALL_OBS]
    np.testing.assert_array_equal(masked, want)
    # light and camera below the plane: 6 over everything but masked and invalid values
    st = ALL_OBS.reshape(1, 1, -1, 1)
    pts = np.zeros((1, ALL_OBS.size, 3))
    for light_pos, camera_z, code in (
        ([[0.0, 0.0, -1.0]], -1.0, ObsStatus.LIGHT_BELOW_HORIZON),
        ([[0.0, 0.0, 1.0]], -1.0, ObsStatus.VIEW_BELOW_HORIZON),
        ([[0.0, 0.0, -1.0]], 1.0, ObsStatus.LIGHT_BELOW_HORIZON),
    ):
        out = geometry_status(st, pts, np.asarray(light_pos), None, np.array([[0, 0, camera_z]]))
        want = [c if c in (*invalid, ObsStatus.MASKED) else code for c in ALL_OBS]
        np.testing.assert_array_equal(out.ravel(), want)


def test_downsample_takes_the_most_severe_code_of_a_block():
    censored = {ObsStatus.SATURATED, ObsStatus.DARK}
    for a in ObsStatus:
        for b in ObsStatus:
            got = _capture([a, b, 0, 0], height=2).downsample(2).status.ravel().tolist()
            if {a, b} == censored:
                want = ObsStatus.CENSORED_MIXED
            else:
                want = max(a, b, key=lambda s: OBS_ORDER.index(s.name))
            assert got == [want], (a, b)


def test_has_estimate_agrees_with_the_stored_numbers_everywhere():
    """``has_estimate`` is ``code < MASKED`` on every integer, inside the table or not (codes
    read back from older files), in NumPy and in JAX."""
    codes = np.arange(-3, 12, dtype=np.int32)
    want = codes < int(Status.MASKED)
    np.testing.assert_array_equal(has_estimate(codes), want)
    np.testing.assert_array_equal(np.asarray(jax.jit(has_estimate)(jnp.asarray(codes))), want)
    assert bool(has_estimate(Status.AT_BOUND)) and not bool(has_estimate(Status.MASKED))


# ----------------------------------------------------------------------------- Laplace flags
STORED_FLAGS = {
    "NO_ESTIMATE": 1,
    "NOT_POSITIVE_DEFINITE": 2,
    "AT_BOUND": 4,
    "NOT_IDENTIFIED": 8,
    "NONFINITE": 16,
    "SINGULAR": 32,
    "CORR_UNDEFINED": 64,
}


def test_laplace_flag_bits_are_the_stored_ones_and_counted_per_bit():
    assert {b.name: int(b) for b in LaplaceFlag} == STORED_FLAGS
    f = np.array([[0, 1, 3], [16, 24, 0], [40, 64, 96]], np.int32)
    want = {
        "NO_ESTIMATE": 2,
        "NOT_POSITIVE_DEFINITE": 1,
        "AT_BOUND": 0,
        "NOT_IDENTIFIED": 2,
        "NONFINITE": 2,
        "SINGULAR": 2,
        "CORR_UNDEFINED": 2,
        "reliable": 2,
    }
    assert flag_counts(f) == want
    assert flag_counts(jnp.asarray(f)) == want


def test_same_residual_is_identity_or_equal_leaves():
    model = jaxrefl.brdf.get("lambert")
    a = make_residual(model)
    assert same_residual(a, a)
    assert same_residual(a, make_residual(model))  # equal leaf by leaf
    assert not same_residual(a, make_residual(model, noise=GaussianNoise(0.5)))


def test_model_check_bits_are_the_stored_ones_and_counted_per_bit():
    from jaxrefl.svbrdf import ModelCheck
    from jaxrefl.svbrdf._check import check_counts

    assert {b.name: int(b) for b in ModelCheck} == {
        "AT_MODEL_BOUND": 1,
        "PPC_FAILED": 2,
        "ALPHA_AT_FLOOR": 4,
    }
    c = np.array([[0, 1, 3], [2, 5, 0]], np.uint32)
    want = {"AT_MODEL_BOUND": 3, "PPC_FAILED": 2, "ALPHA_AT_FLOOR": 1, "misspecified": 4}
    assert check_counts(c) == want


# ----------------------------------------------------------------------------- posterior methods
def test_method_codes_are_the_stored_ones_and_name_the_methods_table():
    from jaxrefl.posterior import METHODS, Method
    from jaxrefl.posterior._methods import MCMC_METHODS

    assert {m.name: int(m) for m in Method} == {
        "NONE": 0,
        "LAPLACE": 1,
        "MCMC": 2,
        "MCMC_AUDIT": 3,
        "LAPLACE_TIME_LIMIT": 4,
    }
    assert {int(m): m.name.lower() for m in Method} == METHODS
    assert set(MCMC_METHODS) == {Method.MCMC, Method.MCMC_AUDIT}

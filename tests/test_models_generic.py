"""Checks every model in the zoo must pass: the contract, reciprocity, non-negativity,
energy conservation, finite values and gradients (property-based), gradients against
finite differences, float32 and float64, jit and vmap."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _helpers import central_difference
from hypothesis import given
from hypothesis import strategies as st

import jaxrefl
from jaxrefl.brdf import directional_albedo, model_zoo, random_directions, random_params

ZOO = model_zoo()
IDS = [e.label for e in ZOO]
# One batch size for every eager (op-by-op) evaluation of a batch of random pairs: JAX
# compiles each primitive once per shape, so tests sharing the shape reuse those programs.
N = 2048


@pytest.fixture(scope="module", params=ZOO, ids=IDS)
def entry(request):
    return request.param


def test_contract_shapes_and_names(entry):
    m = entry.build()
    assert isinstance(m, jaxrefl.brdf.BRDF)
    assert len(set(m.param_names)) == len(m.param_names)
    p = random_params(m, jax.random.PRNGKey(0), (N,), channels=3)
    wi = random_directions(jax.random.PRNGKey(1), (N,))
    wo = random_directions(jax.random.PRNGKey(2), (N,))
    f = m.eval(p, wi, wo)
    assert f.shape == (N, 3) and f.dtype == jnp.float64
    # Unbatched parameters broadcast over a (4, 5) batch of directions.
    p0 = jax.tree_util.tree_map(lambda a: a[0], p)
    wi2 = random_directions(jax.random.PRNGKey(3), (4, 5))
    assert m.eval(p0, wi2, wi2[::-1]).shape == (4, 5, 3)
    # Missing and unknown parameters are refused with the names in the message.
    with pytest.raises(KeyError, match="missing"):
        m.eval({}, wi, wo)
    with pytest.raises(KeyError, match="unexpected"):
        m.eval({**p, "bogus": 1.0}, wi, wo)


def test_below_horizon_is_zero(entry):
    m = entry.build()
    p = m.default_params(jnp.float64)
    wi = jnp.array([[0.6, 0.0, -0.8], [1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])
    wo = jnp.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    f = m.eval(p, wi, wo)
    assert np.all(np.asarray(f) == 0.0)
    g = jax.grad(lambda q: m.eval(q, wi, wo).sum())(p)
    for leaf in jax.tree_util.tree_leaves(g):
        assert np.all(np.asarray(leaf) == 0.0)


def test_reciprocity(entry):
    m = entry.build()
    key = jax.random.PRNGKey(11)
    p = random_params(m, key, (N,))
    wi = random_directions(jax.random.PRNGKey(12), (N,))
    wo = random_directions(jax.random.PRNGKey(13), (N,))
    a, b = m.eval(p, wi, wo), m.eval(p, wo, wi)
    if m.reciprocal:
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    else:
        # Models documented as non-reciprocal must actually differ somewhere.
        assert float(jnp.max(jnp.abs(a - b) / (jnp.abs(a) + jnp.abs(b) + 1e-30))) > 1e-3


def test_non_negative(entry):
    m = entry.build()
    p = random_params(m, jax.random.PRNGKey(21), (N,))
    wi = random_directions(jax.random.PRNGKey(22), (N,))
    wo = random_directions(jax.random.PRNGKey(23), (N,))
    f = np.asarray(m.eval(p, wi, wo))
    assert np.all(np.isfinite(f)) and np.all(f >= 0.0)


def test_jit_vmap_agree(entry):
    m = entry.build()
    p = random_params(m, jax.random.PRNGKey(31), (N,))
    wi = random_directions(jax.random.PRNGKey(32), (N,))
    wo = random_directions(jax.random.PRNGKey(33), (N,))
    direct = m.eval(p, wi, wo)
    jitted = jax.jit(m.eval)(p, wi, wo)
    vmapped = jax.vmap(m.eval)(p, wi, wo)
    np.testing.assert_allclose(jitted, direct, rtol=1e-12)
    np.testing.assert_allclose(vmapped, direct, rtol=1e-12)


def _energy_params(m):
    """Parameters at their energy-critical ends: reflectance scales 1, roughness moderate."""
    p = {}
    for q in m.params:
        v = m.default_params(jnp.float64)[q.name]
        if q.kind == "color" and q.name in ("albedo", "specular"):
            v = jnp.ones_like(v)
        p[q.name] = v
    return p


ENERGY = [e for e in ZOO if e.build().energy_conserving]


@pytest.mark.parametrize("entry", ENERGY, ids=[e.label for e in ENERGY])
def test_energy_conservation(entry):
    """Models that claim energy conservation keep the directional albedo <= 1."""
    m = entry.build()
    p = _energy_params(m)
    th = jnp.deg2rad(jnp.array([0.0, 45.0, 75.0, 85.0]))
    wo = jnp.stack([jnp.sin(th), jnp.zeros_like(th), jnp.cos(th)], -1)
    rho = np.asarray(directional_albedo(m, p, wo, n_theta=384, n_phi=384))
    assert np.all(rho <= 1.0 + 5e-3), rho


def test_lambert_white_furnace_is_one():
    m = jaxrefl.brdf.get("lambert")
    wo = jnp.array([[0.0, 0.0, 1.0], [0.8, 0.0, 0.6]])
    rho = directional_albedo(m, {"albedo": jnp.ones(1)}, wo, 256, 64)
    np.testing.assert_allclose(rho, 1.0, rtol=1e-4)


def test_gradients_match_finite_differences(entry):
    m = entry.build()
    p = random_params(m, jax.random.PRNGKey(41), ())
    # Keep scale parameters away from their extremes so a central difference is meaningful.
    for q in m.params:
        if q.name in ("alpha", "alpha_u", "alpha_v"):
            p[q.name] = jnp.asarray(0.3)
        if q.name == "exponent":
            p[q.name] = jnp.asarray(12.0)
        if q.kind == "lobes":
            p[q.name] = p[q.name].at[..., 3].set(5.0)
    # Three pairs, as in test_below_horizon_is_zero: the same shapes reuse its primitives.
    wi = jnp.array([[0.3, 0.2, 0.9327379], [0.5, -0.4, 0.7681146], [-0.2, 0.4, 0.8944272]])
    wo = jnp.array([[-0.25, -0.1, 0.9630680], [0.1, 0.6, 0.7937254], [0.3, -0.3, 0.9055385]])
    wi = wi / jnp.linalg.norm(wi, axis=-1, keepdims=True)
    wo = wo / jnp.linalg.norm(wo, axis=-1, keepdims=True)

    def fn(q):
        return jnp.sum(m.eval(q, wi, wo))

    g = jax.grad(fn)(p)
    for name in m.param_names:
        num = central_difference(fn, p, name)
        np.testing.assert_allclose(np.asarray(g[name]), num, rtol=1e-5, atol=1e-7, err_msg=name)


unit = st.floats(0.0, 1.0, allow_nan=False)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["f32", "f64"])
@given(data=st.data())
def test_property_finite_values_and_gradients(dtype, data):
    """Over the whole parameter and direction domain (incl. the horizon), every model gives
    finite values and finite gradients with respect to every parameter."""
    entry = data.draw(st.sampled_from(ZOO), label="model")
    m = entry.build()
    seed = data.draw(st.integers(0, 2**31 - 1), label="seed")
    p = random_params(m, jax.random.PRNGKey(seed), (), channels=3, dtype=dtype)

    def direction(label):
        z = data.draw(
            st.one_of(st.just(0.0), st.just(1e-6), st.just(1.0), unit), label=f"{label}.z"
        )
        phi = data.draw(st.floats(0.0, 2 * np.pi), label=f"{label}.phi")
        r = np.sqrt(max(0.0, 1.0 - z * z))
        return jnp.asarray([r * np.cos(phi), r * np.sin(phi), z], dtype=dtype)

    wi = direction("wi")
    wo = wi if data.draw(st.booleans(), label="wi == wo") else direction("wo")
    f, g = _value_and_grad_jit(m, p, wi, wo)
    assert f.dtype == dtype
    assert np.all(np.isfinite(np.asarray(f))), (entry.label, p, wi, wo, f)
    for name, leaf in g.items():
        assert np.all(np.isfinite(np.asarray(leaf))), (entry.label, name, p, wi, wo, leaf)


_JIT_CACHE: dict = {}


def _value_and_grad_jit(m, p, wi, wo):
    """f and the gradient of sum(f) with respect to every parameter, from one compilation
    per model (and dtype): the VJP of f with a cotangent of ones is that gradient."""
    if m not in _JIT_CACHE:

        def value_and_grad(q, a, b):
            f, vjp = jax.vjp(lambda r: m.eval(r, a, b), q)
            return f, vjp(jnp.ones_like(f))[0]

        _JIT_CACHE[m] = jax.jit(value_and_grad)
    return _JIT_CACHE[m](p, wi, wo)


# ----------------------------------------------------------------------------- validation
@pytest.fixture
def validating():
    before = jaxrefl.brdf.set_validation(True)
    yield
    jaxrefl.brdf.set_validation(before)


def test_check_params_refuses_out_of_range_and_non_finite():
    for name in jaxrefl.brdf.available():
        m = jaxrefl.brdf.get(name)
        m.check_params(m.default_params())  # every default is in range
    ward = jaxrefl.brdf.get("ward")
    bad = {**ward.default_params(), "alpha": 0.0}
    with pytest.raises(
        ValueError, match=r"Ward parameter 'alpha' = 0\.0 is outside .*\[0\.0001, 1\]"
    ):
        ward.check_params(bad)
    ct = jaxrefl.brdf.get("cook_torrance", fresnel="dielectric")
    bad = {**ct.default_params(), "eta": jnp.zeros(3)}
    with pytest.raises(ValueError, match=r"parameter 'eta' .* outside its range \[1, 4\]"):
        ct.check_params(bad)
    with pytest.raises(ValueError, match=r"'alpha' = nan is not finite"):
        ward.check_params({**ward.default_params(), "alpha": jnp.nan})


def test_eval_validates_only_when_asked(validating):
    m = jaxrefl.brdf.get("blinn_phong")
    wi, wo = jnp.asarray([0.0, 0.6, 0.8]), jnp.asarray([0.0, -0.6, 0.8])
    p = m.default_params()
    assert np.all(np.isfinite(m.eval(p, wi, wo)))
    with pytest.raises(ValueError, match=r"wi must be unit vectors.*length 0\.001"):
        m.eval(p, 1e-3 * wi, wo)
    with pytest.raises(ValueError, match=r"'exponent'"):
        m.eval({**p, "exponent": -1.0}, wi, wo)
    # Inside jit the inputs are traced: no check, no error.
    f = jax.jit(m.eval)(p, 1e-3 * wi, wo)
    assert f.shape == (3,)
    jaxrefl.brdf.set_validation(False)
    m.eval(p, 1e-3 * wi, wo)  # off: evaluated as given

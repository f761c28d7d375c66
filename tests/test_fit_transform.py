"""Unconstrained parametrisations (jaxrefl/fit/_transform.py): bijections (round trips,
derivatives against autodiff, ranges and clipping) and ParamSpace (labels, defaults, user
bounds, fixed parameters, batched maps, bound detection)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrefl
from jaxrefl import fit

BIJECTIONS = [
    fit.Identity(),
    fit.Exp(0.0),
    fit.Exp(1e-4),
    fit.Softplus(1.0),
    fit.ScaledSigmoid(0.0, 1.0),
    fit.ScaledSigmoid(-2.0, 5.0),
]


def _ggx():
    return jaxrefl.brdf.get(
        "cook_torrance",
        distribution="ggx",
        shadowing="smith_height_correlated",
        fresnel="schlick",
        diffuse="lambert",
    )


@pytest.mark.parametrize("bij", BIJECTIONS, ids=lambda b: repr(b))
def test_round_trip_and_derivative(bij):
    u = jnp.linspace(-6.0, 6.0, 41)
    x = bij.forward(u)
    np.testing.assert_allclose(bij.inverse(x), u, rtol=1e-9, atol=1e-9)
    lo, hi = bij.range
    assert np.all((x > lo) & (x < hi))
    # dforward against autodiff, elementwise
    np.testing.assert_allclose(bij.dforward(u), jax.vmap(jax.grad(bij.forward))(u), rtol=1e-12)


@pytest.mark.parametrize("bij", BIJECTIONS[1:], ids=lambda b: repr(b))
def test_inverse_clips_into_the_open_range(bij):
    lo, hi = bij.range
    xs = jnp.asarray([lo - 1.0, lo, lo + 1e-12] + ([hi, hi + 1.0] if np.isfinite(hi) else []))
    u = bij.inverse(xs)
    assert np.all(np.isfinite(u))
    # clipped values map back strictly inside, within the documented epsilon of the bound
    x = bij.forward(u)
    assert np.all((x > lo) & (x <= (hi if np.isfinite(hi) else np.inf)))
    width = (hi - lo) if np.isfinite(hi) else 1.0 + abs(lo)
    assert np.all(np.minimum(np.abs(x - lo), np.abs(x - hi)) <= 2e-6 * width)
    # extreme u stay in range and finite (float32 too)
    for dt in (jnp.float32, jnp.float64):
        e = bij.forward(jnp.asarray([-80.0, 80.0], dt))
        assert e.dtype == dt and np.all(np.isfinite(e)) and np.all(e >= lo)


def test_unit_vector():
    uv = fit.UnitVector()
    u = jnp.asarray([[0.3, -2.0, 1.0], [0.0, 0.0, 0.0], [1e-3, 2e-3, 5.0]])
    x = uv.forward(u)
    np.testing.assert_allclose(jnp.linalg.norm(x, axis=-1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(x[1], [0.0, 0.0, 1.0])  # zero vector -> the normal
    # gauge freedom: every positive multiple of u is the same direction
    np.testing.assert_allclose(uv.forward(7.5 * u[0]), x[0], rtol=1e-12)
    np.testing.assert_allclose(uv.jacobian(u[0]), jax.jacfwd(uv.forward)(u[0]), rtol=1e-10)
    # singular along u itself: the null direction that LM's damping takes care of
    np.testing.assert_allclose(uv.jacobian(u[0]) @ u[0], 0.0, atol=1e-12)
    with pytest.raises(ValueError, match="not elementwise"):
        uv.dforward(u)


def test_param_space_defaults_labels_and_bounds():
    m = _ggx()
    s = fit.ParamSpace(m)
    assert s.size == 7
    assert s.labels == (
        "albedo.R",
        "albedo.G",
        "albedo.B",
        "specular.R",
        "specular.G",
        "specular.B",
        "alpha",
    )
    assert s.free_names == ("albedo", "specular", "alpha")
    kinds = {b.name: type(b.runs[0].bijection) for b in s.blocks}
    assert kinds == {"albedo": fit.ScaledSigmoid, "specular": fit.ScaledSigmoid, "alpha": fit.Exp}
    np.testing.assert_allclose(s.lower, [0, 0, 0, 0, 0, 0, 1e-4])
    np.testing.assert_allclose(s.upper, [1, 1, 1, 1, 1, 1, 1])
    # A finite user upper bound on a log-scale parameter switches it to ScaledSigmoid.
    s2 = fit.ParamSpace(m, bounds={"alpha": (0.01, 0.5)})
    bij = s2.blocks[2].runs[0].bijection
    assert isinstance(bij, fit.ScaledSigmoid) and (bij.lower, bij.upper) == (0.01, 0.5)
    x = s2.to_natural(jnp.asarray([[-50.0] * 7, [50.0] * 7]))["alpha"]
    assert 0.01 <= float(x[0]) and float(x[1]) <= 0.5
    # Other channel counts and names
    assert fit.ParamSpace(jaxrefl.brdf.get("lambert"), channels=1).labels == ("albedo.c0",)
    s4 = fit.ParamSpace(m, channels=2, channel_names=("450nm", "550nm"))
    assert s4.labels[:2] == ("albedo.450nm", "albedo.550nm") and s4.size == 5
    with pytest.raises(KeyError, match="not parameters"):
        fit.ParamSpace(m, bounds={"roughness": (0, 1)})
    with pytest.raises(ValueError, match="trailing axis"):
        s.to_natural(jnp.zeros((3, 6)))


def test_param_space_maps_batched_and_fixed():
    m = _ggx()
    rng = np.random.default_rng(0)
    nat = {
        "albedo": jnp.asarray(rng.uniform(0.05, 0.9, (5, 3))),
        "specular": jnp.asarray(rng.uniform(0.02, 0.5, (5, 3))),
        "alpha": jnp.asarray(rng.uniform(0.01, 0.9, 5)),
    }
    s = fit.ParamSpace(m)
    theta = s.from_natural(nat)
    assert theta.shape == (5, 7)
    back = s.to_natural(theta)
    for k, v in nat.items():
        np.testing.assert_allclose(back[k], v, rtol=1e-10)
    vec = s.natural_vector(theta)
    np.testing.assert_allclose(vec[:, 3:6], nat["specular"], rtol=1e-10)
    np.testing.assert_allclose(vec[:, 6], nat["alpha"], rtol=1e-10)
    # dnatural = diagonal of the full Jacobian (every default bijection is elementwise)
    jac = s.jacobian_natural(theta)
    np.testing.assert_allclose(s.dnatural(theta), jnp.diagonal(jac, axis1=-2, axis2=-1), rtol=1e-12)
    np.testing.assert_allclose(jac - jax.vmap(jnp.diag)(s.dnatural(theta)), 0.0, atol=1e-15)

    # Fixed parameters leave theta and come back as broadcast constants.
    sf = fit.ParamSpace(m, fixed={"specular": 0.04})
    assert sf.size == 4 and "specular" not in sf.free_names
    assert sf.labels == ("albedo.R", "albedo.G", "albedo.B", "alpha")
    pf = sf.to_natural(sf.from_natural(nat))
    assert pf["specular"].shape == (5, 3)
    np.testing.assert_allclose(pf["specular"], 0.04)
    np.testing.assert_allclose(pf["alpha"], nat["alpha"], rtol=1e-10)
    # the model evaluates with the dict as it comes
    wi = jnp.asarray([[0.0, 0.6, 0.8]] * 5)
    assert m.eval(pf, wi, wi).shape == (5, 3)

    # float32 stays float32
    t32 = s.from_natural(jax.tree.map(lambda v: v.astype(jnp.float32), nat))
    assert t32.dtype == jnp.float32 and s.to_natural(t32)["alpha"].dtype == jnp.float32


def test_at_bound():
    s = fit.ParamSpace(_ggx())
    nat = {
        "albedo": jnp.asarray([[0.5, 0.0005, 0.5], [0.5, 0.5, 0.9995], [0.5, 0.5, 0.5]]),
        "specular": jnp.full((3, 3), 0.2),
        "alpha": jnp.asarray([0.3, 2e-4, 1.5]),  # 1.5: beyond the model's range (Exp allows it)
    }
    flags = np.asarray(s.at_bound(s.from_natural(nat)))
    assert flags.shape == (3, 7)
    expected = np.zeros((3, 7), bool)
    expected[0, 1] = True  # albedo.G near 0
    expected[1, 2] = expected[1, 6] = True  # albedo.B near 1, alpha near its floor
    expected[2, 6] = True  # alpha beyond its upper bound
    np.testing.assert_array_equal(flags, expected)


def test_off_bounds_clips_only_sigmoid_entries():
    s = fit.ParamSpace(_ggx())
    nat = {
        "albedo": jnp.asarray([[0.5, 1e-6, 0.999999]]),
        "specular": jnp.full((1, 3), 0.2),
        "alpha": jnp.asarray([2e-4]),  # near its floor, but Exp-mapped: not clipped
    }
    theta = s.from_natural(nat)
    out = np.asarray(s.off_bounds(theta))
    assert np.isfinite([s.lower[6], s.upper[6]]).all()  # alpha's range is finite too
    np.testing.assert_allclose(out[0, :6], np.clip(np.asarray(theta)[0, :6], -3.0, 3.0))
    assert out[0, 6] == np.asarray(theta)[0, 6]
    assert abs(out[0, 1]) == 3.0 and abs(out[0, 2]) == 3.0 and out[0, 0] == 0.0
    # The clipped albedo lies 4.7% of the range from its edge.
    np.testing.assert_allclose(s.to_natural(jnp.asarray(out))["albedo"][0, 1], 0.0474, atol=1e-4)


def test_lafortune_lobes_and_log_scale_defaults():
    lf = jaxrefl.brdf.get("lafortune")
    s = fit.ParamSpace(lf, channels=1)
    assert s.labels == ("albedo.c0", "lobes[0].Cx", "lobes[0].Cy", "lobes[0].Cz", "lobes[0].n")
    p = s.to_natural(jnp.asarray([0.0, -3.0, 0.5, 2.0, -40.0]))
    assert p["lobes"].shape == (1, 4)
    assert float(p["lobes"][0, 3]) > 0.0  # the exponent stays positive (Exp)
    np.testing.assert_allclose(p["lobes"][0, :3], [-3.0, 0.5, 2.0])  # C's: identity
    # the other log-scale parameters get Exp with their model's lower bound
    for name, opts, param, lower in [
        ("phong", {}, "exponent", 0.0),
        ("oren_nayar", {}, "sigma", 0.0),
        ("cook_torrance", {"fresnel": "dielectric"}, "eta", 1.0),
        ("cook_torrance", {"fresnel": "conductor"}, "k", 0.0),
    ]:
        sp = fit.ParamSpace(jaxrefl.brdf.get(name, **opts))
        bij = sp.blocks[sp.free_names.index(param)].runs[0].bijection
        assert isinstance(bij, fit.Exp) and bij.lower == lower, (name, param, bij)

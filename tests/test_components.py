"""Models assembled from components (jaxrefl.measured._components): only the switched-on
parts are built and compiled, the sum equals the monolithic models, the retro lobe's
normalisation, and the parameter space of a second lobe."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl.brdf import CookTorrance, Lambert, Sum, directional_albedo
from jaxrefl.fit import Exp
from jaxrefl.measured import Components
from jaxrefl.measured._components import RetroLobe, param_space, start_from


def _dirs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(2, n, 3))
    v[..., 2] = np.abs(v[..., 2]) + 0.05
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    return v[0], v[1]


RICH = Components(anisotropic=True, second_lobe=True, retro=True)


def test_build_holds_only_the_switched_on_parts():
    assert isinstance(Components(lobe=None, fresnel=False).build(), Lambert)
    m = RICH.build()
    assert isinstance(m, Sum) and len(m.parts) == 4
    assert m.param_names == (
        "albedo",
        "specular",
        "alpha_u",
        "alpha_v",
        "specular_2",
        "alpha_2",
        "retro",
    )
    assert RICH.label == "diffuse+ggx+fresnel+anisotropic+second_lobe+retro"
    assert set(RICH.removals()) == set(RICH.active)
    assert RICH.without("lobe").active == ("diffuse", "retro")
    assert m.reciprocal
    with pytest.raises(ValueError, match="refine the specular lobe"):
        Components(lobe=None)
    with pytest.raises(ValueError, match="at least one component"):
        Components(diffuse=False, lobe=None, fresnel=False)
    with pytest.raises(ValueError, match="not switched on"):
        Components().without("retro")


def test_diffuse_only_compiles_to_less_than_a_zero_lobe():
    """The compiled diffuse-only model carries no lobe arithmetic: its jaxpr is a small
    fraction of that of a model whose lobe is switched off by a zero strength."""
    wi, wo = _dirs(8, 0)
    diffuse = Components(lobe=None, fresnel=False).build()
    plastic = Components(fresnel=False).build()  # F = specular: a zero lobe is exactly 0
    pd = {"albedo": jnp.full((3,), 0.5)}
    pp = {**pd, "specular": jnp.zeros(3), "alpha": jnp.asarray(0.2)}
    n_d = len(jax.make_jaxpr(lambda p: diffuse.eval(p, wi, wo))(pd).eqns)
    n_p = len(jax.make_jaxpr(lambda p: plastic.eval(p, wi, wo))(pp).eqns)
    assert n_d * 3 < n_p, (n_d, n_p)
    np.testing.assert_allclose(diffuse.eval(pd, wi, wo), plastic.eval(pp, wi, wo), rtol=1e-12)


def test_sum_equals_the_monolithic_models():
    wi, wo = _dirs(64, 1)
    p = {"albedo": jnp.asarray([0.3, 0.4, 0.5]), "specular": jnp.full(3, 0.06), "alpha": 0.15}
    # One jitted call per model (compiling once beats op-by-op dispatch).
    got = jax.jit(Components().build().eval)(p, wi, wo)
    ref = jax.jit(CookTorrance("ggx", diffuse="lambert").eval)(p, wi, wo)
    np.testing.assert_allclose(got, ref, rtol=1e-12)
    # A second lobe is a renamed copy: its contribution equals a CookTorrance lobe.
    two = Components(second_lobe=True).build()
    p2 = {**p, "specular_2": jnp.full(3, 0.02), "alpha_2": 0.5}
    lobe2 = jax.jit(CookTorrance("ggx").eval)({"specular": p2["specular_2"], "alpha": 0.5}, wi, wo)
    f_two = jax.jit(two.eval)
    np.testing.assert_allclose(f_two(p2, wi, wo), ref + lobe2, rtol=1e-12)
    np.testing.assert_allclose(f_two(p2, wo, wi), f_two(p2, wi, wo), rtol=1e-12)  # reciprocal


def test_retro_lobe_normalisation_and_edges():
    lobe = RetroLobe(8.0)
    # Albedo at normal incidence equals ``retro`` (module docstring): integrate numerically.
    a = directional_albedo(lobe, {"retro": jnp.ones(1)}, jnp.asarray([[0.0, 0.0, 1.0]]), 128, 64)
    np.testing.assert_allclose(np.asarray(a).ravel(), 1.0, rtol=2e-3)
    # Peak at wo = wi; zero with a finite gradient for back-facing pairs, in float32.
    w = jnp.asarray([0.6, 0.0, 0.8], jnp.float32)
    back = jnp.asarray([-0.8, 0.0, 0.6], jnp.float32)  # wi . wo = 0
    f = jax.jit(lambda r, wo: lobe.eval({"retro": r}, w, wo).sum())
    assert float(f(jnp.ones(1, jnp.float32), back)) == 0.0
    g = jax.jit(jax.grad(f))(jnp.ones(1, jnp.float32), back)
    assert np.all(np.isfinite(np.asarray(g)))
    np.testing.assert_allclose(float(f(jnp.ones(1, jnp.float32), w)), 10.0 / (2 * np.pi), rtol=1e-6)
    with pytest.raises(ValueError, match=">= 1"):
        RetroLobe(0.5)


def test_param_space_and_starts():
    m = Components(second_lobe=True).build()
    space = param_space(m, 3)
    blk = space.blocks[space.free_names.index("alpha_2")]
    assert isinstance(blk.runs[0].bijection, Exp)
    assert space.size == 3 + 3 + 1 + 3 + 1
    start = start_from(
        {
            "albedo": np.full((2, 3), 0.4),
            "specular": np.full((2, 3), 0.1),
            "alpha": np.full(2, 0.1),
        },
        RICH,
        2,
        3,
    )
    np.testing.assert_allclose(start["alpha_u"], 0.1)
    np.testing.assert_allclose(start["alpha_2"], 0.4)
    np.testing.assert_allclose(start["specular_2"], 0.025)
    assert start["retro"].shape == (2, 3)

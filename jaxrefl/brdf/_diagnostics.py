"""User-callable physics diagnostics: reciprocity, directional albedo, the white furnace.

Directional albedo (directional-hemispherical reflectance) for outgoing direction wo:

    rho(wo) = ∫_{H^2} f_r(wi, wo) cos(theta_i) dω_i
            = ∫_0^{2π} ∫_0^{π/2} f_r(wi(θ, φ), wo) cos θ sin θ dθ dφ,

evaluated with the midpoint rule on a (θ, φ) grid (deterministic, so tests are repeatable).
Grid resolution bounds what lobes it resolves: with ``n_theta`` cells the polar step is
π/(2 n_theta); a lobe must span several cells (alpha >~ 10 π/(2 n_theta)). For reciprocal
models rho(wo) is also the fraction of light from wo that is reflected (the white-furnace
test of a model lit by a uniform unit environment).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from ._base import BRDF, Params
from ._frame import spherical_direction
from ._zoo import random_directions

__all__ = ["directional_albedo", "furnace_test", "hemisphere_grid", "reciprocity_error"]


def hemisphere_grid(
    n_theta: int = 256, n_phi: int = 512, dtype=jnp.float64
) -> tuple[Float[Array, "N 3"], Float[Array, " N"]]:
    """Midpoint-rule directions and solid-angle weights sin θ dθ dφ over the hemisphere."""
    dth = (jnp.pi / 2) / n_theta
    dph = (2 * jnp.pi) / n_phi
    th = (jnp.arange(n_theta, dtype=dtype) + 0.5) * dth
    ph = (jnp.arange(n_phi, dtype=dtype) + 0.5) * dph
    tt, pp = jnp.meshgrid(th, ph, indexing="ij")
    w = spherical_direction(tt, pp).reshape(-1, 3)
    weights = (jnp.sin(tt) * dth * dph).reshape(-1)
    return w, weights


def directional_albedo(
    model: BRDF,
    params: Params,
    wo: Float[Array, "M 3"],
    n_theta: int = 256,
    n_phi: int = 512,
) -> Float[Array, "M C"]:
    """rho(wo) = ∫ f_r(wi, wo) cos θ_i dω_i for each row of ``wo`` (params unbatched)."""
    wo = jnp.asarray(wo)
    wi, weights = hemisphere_grid(n_theta, n_phi, wo.dtype)
    cos_i = wi[:, 2]

    def one(w_o):
        f = model.eval(params, wi, jnp.broadcast_to(w_o, wi.shape))
        return jnp.sum(f * (weights * cos_i)[:, None], axis=0)

    return jax.lax.map(one, wo)


def furnace_test(
    model: BRDF,
    params: Params,
    thetas_deg: Float[Array, " M"] | tuple[float, ...] = (0.0, 30.0, 60.0, 75.0, 85.0),
    n_theta: int = 256,
    n_phi: int = 512,
) -> dict[str, Array]:
    """Directional albedo at several incidence angles (phi = 0): ``{"theta_deg", "albedo"}``.

    A physically based model with unit reflectance parameters passes when every value is
    <= 1 (up to quadrature error); Lambert with albedo 1 gives exactly 1.
    """
    th = jnp.deg2rad(jnp.asarray(thetas_deg, dtype=jnp.float64))
    wo = spherical_direction(th, jnp.zeros_like(th))
    return {
        "theta_deg": jnp.asarray(thetas_deg),
        "albedo": directional_albedo(model, params, wo, n_theta, n_phi),
    }


def reciprocity_error(model: BRDF, params: Params, key: PRNGKeyArray, n: int = 4096) -> Array:
    """max |f(wi, wo) - f(wo, wi)| / max(|f|, tiny) over ``n`` random direction pairs."""
    k1, k2 = jax.random.split(key)
    wi = random_directions(k1, (n,))
    wo = random_directions(k2, (n,))
    a = model.eval(params, wi, wo)
    b = model.eval(params, wo, wi)
    scale = jnp.maximum(jnp.maximum(jnp.abs(a), jnp.abs(b)), 1e-300)
    return jnp.max(jnp.abs(a - b) / scale)

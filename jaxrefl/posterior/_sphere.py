"""A direction on the sphere as an unconstrained 3-vector: no pole, no wrap-around.

Angles (theta, phi) make a sampler's life hard: phi wraps around at 2 pi and the metric
collapses at the poles (a step of fixed size in phi moves the direction by sin(theta) times
as much). Instead the light direction is

    l = u / |u|,   u in R^3 unconstrained,

and the sampler works on u. The map forgets the radius r = |u|, so we give r a density of
its own: in polar coordinates du = r^2 dr dl, so a target p(r, l) = h(r) p(l) is the density

    p(u) = h(|u|) p(u / |u|) / |u|^2

on R^3. With h the chi distribution with 3 degrees of freedom, h(r) ∝ r^2 exp(-r^2 / 2),
the radial part is exp(-|u|^2 / 2): the density of u is a standard normal times the
direction prior, smooth everywhere except the single point u = 0, which carries
no mass and which a sampler only reaches at a density of about exp(0) p(l) <= the typical
one (no divergence). Marginally, l has exactly the prior p(l) (a von Mises–Fisher or
uniform, :class:`~jaxrefl.posterior.VonMisesFisher`) times the likelihood: the radius
never enters the likelihood, and r is independent of l a posteriori. Every direction is
treated alike: there is no special axis.

R-hat and ESS are computed on the components of l (``light.x``, ``light.y``,
``light.z``), never on u (whose radius is a nuisance). World directions are carried into
the local frame of each surface point with :func:`jaxrefl.scene.orthonormal_basis` and
:func:`jaxrefl.scene.to_local`.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._priors import VonMisesFisher

__all__ = [
    "SphereDirection",
    "angle_deg",
    "direction_summary",
    "lit_geometry",
]


class SphereDirection(eqx.Module):
    """A direction l = u / |u| with prior ``prior`` (module docstring)."""

    prior: VonMisesFisher = VonMisesFisher((0.0, 0.0, 1.0), 0.0)

    size = 3
    labels = ("light.x", "light.y", "light.z")

    def direction(self, u: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
        n2 = jnp.sum(u * u, axis=-1, keepdims=True)
        ok = n2 > 0
        # Gradient-safe: u = 0 (no direction, zero prior mass) is swapped for +z.
        u_safe = jnp.where(ok, u, jnp.asarray([0.0, 0.0, 1.0], dtype=u.dtype))
        return u_safe / jnp.sqrt(jnp.where(ok, n2, 1.0))

    def log_density(self, u: Float[Array, "*b 3"]) -> Float[Array, " *b"]:
        """log p(u) = -|u|^2 / 2 + log p_prior(u / |u|) (chi-3 radius, module docstring)."""
        return -0.5 * jnp.sum(u * u, axis=-1) + self.prior.log_prob(self.direction(u))

    def init(self, l: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
        """u for direction l at radius sqrt(2), the mode of the chi-3 radius."""
        l = jnp.asarray(l)
        return jnp.sqrt(2.0) * l / jnp.linalg.norm(l, axis=-1, keepdims=True)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between direction arrays (*b, 3) (not necessarily unit)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _vmf_radius_deg(kappa: float, level: float) -> float:
    """Angle about the mean holding ``level`` of a von Mises–Fisher's mass (inverse of the
    cosine's CDF, Wood 1994): cos = 1 + log(1 - level (1 - e^(-2 kappa))) / kappa."""
    if kappa < 1e-8:
        return float(np.degrees(np.arccos(1.0 - 2.0 * level)))
    w = 1.0 + np.log1p(-level * (-np.expm1(-2.0 * kappa))) / kappa
    return float(np.degrees(np.arccos(np.clip(w, -1.0, 1.0))))


def lit_geometry(normals: np.ndarray, weight: np.ndarray | None = None, tol: float = 0.05) -> dict:
    """Can shading pin a light direction down at all? A check on the geometry alone.

    For a Lambertian point, radiance = albedo E max(n . l, 0) / pi is linear in l where
    lit: three lit points with linearly independent normals fix l; with all normals in one
    plane (smallest singular value of the (K, 3) normal matrix below ``tol`` times the
    largest) the component of l out of that plane is seen only through its square, so l
    and its mirror image fit equally (two modes); fewer than 3 points leave a curve of
    solutions. Returns ``n_points``, ``rank`` (numerical) and ``identifiable`` (bool).
    """
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    w = np.ones(len(n)) if weight is None else np.asarray(weight, np.float64).reshape(len(n), -1)
    used = n[np.max(w.reshape(len(n), -1), axis=-1) > 0] if w.size else n
    if len(used) == 0:
        return {"n_points": 0, "rank": 0, "identifiable": False}
    sv = np.linalg.svd(used, compute_uv=False)
    rank = int(np.sum(sv > tol * sv[0]))
    return {"n_points": len(used), "rank": rank, "identifiable": len(used) >= 3 and rank == 3}


def direction_summary(
    draws: np.ndarray,
    prior: VonMisesFisher | None = None,
    *,
    level: float = 0.9,
    max_radius_deg: float = 15.0,
    rhat: float | None = None,
    geometry: dict | None = None,
) -> dict:
    """Is a direction identified by the data? Summary of posterior draws (M, 3).

    mean:        the mean direction (normalised resultant)
    resultant:   mean resultant length R in [0, 1] (1: all draws agree)
    radius_deg:  the angle about the mean holding ``level`` of the draws
    prior_radius_deg: the same for the prior (vMF closed form)
    identified:  radius_deg <= max_radius_deg, and below half the prior's radius, and
                 R-hat (if given) <= 1.05, and the geometry (if given, from
                 :func:`lit_geometry`) identifiable. Too few observations, or co-planar
                 normals (the light's component out of their plane is mirrored: two
                 modes, which chains started apart find) fail it.
    """
    x = np.asarray(draws, dtype=np.float64).reshape(-1, 3)
    x = x[np.all(np.isfinite(x), axis=-1)]
    if x.size == 0:
        return {"identified": False, "reason": "no finite draws"}
    r = x.mean(axis=0)
    rl = float(np.linalg.norm(r))
    mean = r / rl if rl > 0 else np.array([0.0, 0.0, 1.0])
    radius = float(np.quantile(angle_deg(x, mean[None, :]), level))
    prior_radius = _vmf_radius_deg(prior.kappa, level) if prior is not None else 180.0
    reasons = []
    if radius > max_radius_deg:
        reasons.append(f"{100 * level:.0f}% of the posterior spreads over {radius:.1f} deg")
    if radius > 0.5 * prior_radius:
        reasons.append(
            f"the posterior is not much narrower than the prior ({prior_radius:.1f} deg)"
        )
    if geometry is not None and not geometry["identifiable"]:
        reasons.append(
            f"{geometry['n_points']} points with normals of rank {geometry['rank']}: "
            "3 lit points with non-coplanar normals are needed"
        )
    if rhat is not None and not rhat <= 1.05:
        reasons.append(f"chains disagree (R-hat {rhat:.2f}): several modes")
    return {
        "mean": mean.tolist(),
        "resultant": rl,
        "radius_deg": radius,
        "prior_radius_deg": prior_radius,
        "level": level,
        "identified": not reasons,
        "reason": "; ".join(reasons) if reasons else "identified",
    }

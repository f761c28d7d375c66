"""A shared zoo of batched fitting problems (like optimistix's ``tests/helpers.py``).

Each :class:`ZooProblem` holds synthetic pixels made with the forward model: K light/view
directions per pixel, a known truth, and the :class:`~jaxrefl.fit.PixelData` to fit. Used by
the tests of ``jaxrefl.fit`` to check recovery and the agreement of the solver backends.

Directions: ``"flash"`` puts light and camera together (wi = wo, as for a phone flash):
a Fibonacci spiral of K directions within 60 degrees of a per-pixel random axis near the
normal, randomly rotated; ``"gonio"`` draws wi and wo independently (uniform in the
hemisphere above 5 degrees elevation), like a gonioreflectometer. Observations are
f_r * E * cos(theta_i) with irradiance E = 2 (flash) or f_r (gonio, scale 1).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import jaxrefl
from jaxrefl import fit

__all__ = ["ZooProblem", "directions", "make_problem", "problem_zoo"]


class ZooProblem(NamedTuple):
    name: str
    model: jaxrefl.brdf.BRDF
    data: fit.PixelData
    truth: dict[str, np.ndarray]  # natural parameters, leading axis N
    noisy: bool
    well_posed: np.ndarray  # (N,) bool, see :func:`well_posed`


def _rotation_to(axis: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) taking +z to the unit vectors ``axis`` (N, 3)."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, axis)
    c = axis[:, 2]
    vx = np.zeros((len(axis), 3, 3))
    vx[:, 0, 1], vx[:, 0, 2], vx[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    vx = vx - np.transpose(vx, (0, 2, 1))
    k = 1.0 / (1.0 + c)
    return np.eye(3)[None] + vx + (vx @ vx) * k[:, None, None]


def directions(kind: str, n: int, k: int, rng: np.random.Generator):
    """(wi, wo) of shape (n, k, 3): see the module docstring."""
    if kind == "flash":
        j = np.arange(k) + 0.5
        cos_t = 1.0 - (j / k) * (1.0 - np.cos(np.radians(60.0)))
        sin_t = np.sqrt(1.0 - cos_t**2)
        phi = j * np.pi * (3.0 - np.sqrt(5.0))
        rot = rng.uniform(0.0, 2.0 * np.pi, (n, 1))
        d = np.stack(
            [sin_t * np.cos(phi + rot), sin_t * np.sin(phi + rot), np.broadcast_to(cos_t, (n, k))],
            axis=-1,
        )
        tilt = np.radians(rng.uniform(0.0, 10.0, n))
        az = rng.uniform(0.0, 2.0 * np.pi, n)
        axis = np.stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)], -1)
        d = np.einsum("nij,nkj->nki", _rotation_to(axis), d)
        d[..., 2] = np.maximum(d[..., 2], 0.05)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return d, d
    if kind == "gonio":

        def hemi():
            u = rng.uniform(np.sin(np.radians(5.0)), 1.0, (n, k))
            phi = rng.uniform(0.0, 2.0 * np.pi, (n, k))
            s = np.sqrt(1.0 - u**2)
            return np.stack([s * np.cos(phi), s * np.sin(phi), u], axis=-1)

        return hemi(), hemi()
    raise ValueError(kind)


def random_truth(
    model, n: int, rng: np.random.Generator, channels: int = 3
) -> dict[str, np.ndarray]:
    """Albedo U(0.05, 0.8) per channel, grey specular U(0.02, 0.5), alpha log-U(0.05, 0.8)."""
    out = {}
    for q in model.params:
        if q.name == "albedo":
            out[q.name] = rng.uniform(0.05, 0.8, (n, channels))
        elif q.name == "specular":
            out[q.name] = np.repeat(rng.uniform(0.02, 0.5, (n, 1)), channels, axis=1)
        elif q.name == "alpha":
            out[q.name] = np.exp(rng.uniform(np.log(0.05), np.log(0.8), n))
        else:
            raise ValueError(f"no random truth for {q.name}")
    return out


def make_problem(
    name: str,
    model,
    *,
    n: int,
    k: int = 32,
    kind: str = "flash",
    noise: float = 0.0,
    seed: int = 0,
    dtype=jnp.float64,
) -> ZooProblem:
    """Synthetic pixels of ``model`` with multiplicative Gaussian noise of relative size
    ``noise`` (0 = exact)."""
    rng = np.random.default_rng(seed)
    truth = random_truth(model, n, rng)
    wi, wo = directions(kind, n, k, rng)
    p = {
        q.name: jnp.asarray(
            truth[q.name][:, None, ...] if q.kind == "color" else truth[q.name][:, None]
        )
        for q in model.params
    }
    f = np.asarray(jax.jit(model.eval)(p, jnp.asarray(wi), jnp.asarray(wo)))  # (n, k, 3)
    scale = np.broadcast_to((2.0 * wi[..., 2:3]) if kind == "flash" else 1.0, f.shape)
    obs = f * scale
    if noise:
        obs = obs * (1.0 + noise * rng.standard_normal(obs.shape))
    data = fit.pixel_data(
        jnp.asarray(obs, dtype),
        jnp.asarray(wi, dtype),
        None if kind == "flash" else jnp.asarray(wo, dtype),
        scale=jnp.asarray(scale, dtype),
    )
    return ZooProblem(name, model, data, truth, bool(noise), well_posed(model, data, truth))


def well_posed(model, data: fit.PixelData, truth, noise: float = 0.01, limit: float = 0.1):
    """(N,) bool: pixels whose parameters the data determine.

    The Cramer-Rao bound at the truth with Gaussian noise of ``noise`` times the pixel's RMS
    observation: every natural parameter's standard deviation must be below ``limit`` times
    its value. (Random gonio directions can miss a sharp highlight entirely; then specular
    and alpha are not determined even by exact data, and any solver may return any point of
    a flat valley.)
    """
    space = fit.ParamSpace(model, channels=data.obs.shape[-1])
    res = fit.make_residual(model, space)
    theta = space.from_natural({k: jnp.asarray(v) for k, v in truth.items()}, dtype=data.obs.dtype)

    def one(t, d):
        j = jax.jacfwd(res)(t, d)
        sigma = noise * jnp.sqrt(jnp.mean(d.obs**2))
        fisher = j.T @ j / sigma**2
        dx = space.dnatural(t)
        cov = jnp.linalg.inv(fisher) * dx[:, None] * dx[None, :]
        std = jnp.sqrt(jnp.maximum(jnp.diagonal(cov), 0.0))
        ok = jnp.all(jnp.isfinite(cov)) & (jnp.linalg.cond(fisher) < 1e12)
        return ok & jnp.all(std < limit * jnp.abs(space.natural_vector(t)))

    return np.asarray(jax.jit(jax.vmap(one))(theta, data))


@functools.cache
def problem_zoo(n: int = 64, dtype=jnp.float64) -> tuple[ZooProblem, ...]:
    """The named problems: GGX + Lambert (flash, exact), Beckmann + Lambert (gonio, exact),
    Lambert only (flash, exact), GGX + Lambert with 1% noise (flash). Cached: test modules
    share one zoo (and, having the same shapes, the compiled solvers)."""
    get = jaxrefl.brdf.get
    ggx = get("cook_torrance", distribution="ggx", diffuse="lambert")
    beckmann = get("cook_torrance", distribution="beckmann", diffuse="lambert")
    return (
        make_problem("ggx_lambert", ggx, n=n, seed=1, dtype=dtype),
        make_problem("beckmann_lambert_gonio", beckmann, n=n, kind="gonio", seed=2, dtype=dtype),
        make_problem("lambert", get("lambert"), n=n, seed=3, dtype=dtype),
        make_problem("ggx_lambert_noisy", ggx, n=n, noise=0.01, seed=4, dtype=dtype),
    )

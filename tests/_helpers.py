"""Shared test helpers for the BRDF model tests (like optimistix's ``tests/helpers.py``).

* Directions: :func:`unit`, :func:`sph` (degrees), :func:`mirror` (about the normal).
* Quadrature: :func:`lobe_grid` and :func:`albedo_on_grid` (a sphere grid centred on a lobe axis),
  :func:`hemisphere_quadrature` (a half-vector grid adapted to a lobe of width ``alpha``).
* Gradients: :func:`central_difference` and :func:`fd_check` (``jax.grad`` against it).
* Edges: :data:`EDGE_WI`/:data:`EDGE_WO` and :func:`assert_finite_edges` (finite values and
  gradients at the normal, at grazing angles, on and below the horizon, in float32/64).

Compiled evaluations are kept in one cache keyed by model (:data:`JIT`), so tests in different
modules that evaluate the same model share one compilation.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

JIT: dict[Any, Any] = {}


# ----------------------------------------------------------------------------- directions
def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def sph(theta_deg, phi_deg=0.0):
    t, p = np.deg2rad(theta_deg), np.deg2rad(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def mirror(w):
    return np.array([-w[0], -w[1], w[2]])


# ----------------------------------------------------------------------------- quadrature
def lobe_grid(axis, width, n_gl=32, n_phi=256, n_panels=6):
    """Directions and solid-angle weights on a sphere grid centred on ``axis``: Gauss-Legendre
    panels in the polar angle, the first of ``width`` and the rest growing geometrically,
    midpoint rule in azimuth. Centred on the normal it stops at the horizon (a panel edge).
    The grid size does not depend on ``width`` so that one compiled evaluation serves all."""
    a = unit(axis)
    t = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    t1 = unit(t - a * (t @ a))
    t2 = np.cross(a, t1)
    tmax = np.pi / 2 if a[2] > 1 - 1e-12 else np.pi
    edges = np.concatenate([[0.0], np.geomspace(min(width, tmax / 2), tmax, n_panels)])
    x, wt = np.polynomial.legendre.leggauss(n_gl)
    th = np.concatenate([(lo + hi) / 2 + (hi - lo) / 2 * x for lo, hi in itertools.pairwise(edges)])
    tw = np.concatenate([(hi - lo) / 2 * wt for lo, hi in itertools.pairwise(edges)])
    ph = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    T, P = np.meshgrid(th, ph, indexing="ij")
    W = np.sin(T) * tw[:, None] * (2 * np.pi / n_phi)
    d = (
        (np.sin(T) * np.cos(P))[..., None] * t1
        + (np.sin(T) * np.sin(P))[..., None] * t2
        + np.cos(T)[..., None] * a
    )
    return d.reshape(-1, 3), W.reshape(-1)


def albedo_on_grid(m, p, wi, axis, width, **kw):
    """rho(wi) = ∫ f(wi, wo) cos(theta_o) dω_o, by quadrature on a grid centred on ``axis``."""
    d, W = lobe_grid(axis, width, **kw)
    ev = JIT.setdefault(m, jax.jit(m.eval))
    p = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in p.items()}
    f = np.asarray(ev(p, jnp.asarray(np.broadcast_to(wi, d.shape)), jnp.asarray(d)))
    return np.sum(f * (W * np.maximum(d[:, 2], 0.0))[:, None], axis=0)


def hemisphere_quadrature(alpha, n_theta=128, n_phi=64):
    """Nodes h (M, 3) and weights (M,) (numpy) for ∫ over the hemisphere dω, adapted to a lobe
    of width alpha: tan(theta) = alpha tan(pi v / 2), Gauss-Legendre in v, midpoint in phi."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    v, wv = 0.5 * (x + 1), 0.5 * w
    t = alpha * np.tan(0.5 * np.pi * v)
    theta = np.arctan(t)
    dtheta = alpha * 0.5 * np.pi / np.cos(0.5 * np.pi * v) ** 2 / (1 + t * t)
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    T, P = np.meshgrid(theta, phi, indexing="ij")
    W = (wv * dtheta)[:, None] * np.sin(T) * (2 * np.pi / n_phi)
    h = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1)
    return h.reshape(-1, 3), W.reshape(-1)


# ----------------------------------------------------------------------------- gradients
def central_difference(fn: Callable[[dict], Any], p: dict, name: str):
    """The central difference of ``fn`` with respect to every element of ``p[name]`` (step
    1e-6 relative, 1e-6 absolute below 1), in float64."""
    x = np.asarray(p[name], dtype=np.float64)
    num = np.zeros_like(x)
    for idx in np.ndindex(x.shape):
        h = 1e-6 * max(1.0, abs(x[idx]))
        xp, xm = x.copy(), x.copy()
        xp[idx] += h
        xm[idx] -= h
        num[idx] = (fn({**p, name: jnp.asarray(xp)}) - fn({**p, name: jnp.asarray(xm)})) / (2 * h)
    return num


def fd_check(m, p, wi, wo, rtol=1e-6, atol=1e-9):
    """jax.grad against a central difference for every element of every parameter."""
    fn = jax.jit(lambda q: jnp.sum(m.eval(q, wi, wo) * jnp.arange(1.0, 4.0)[None, :]))
    g = jax.grad(fn)(p)
    for name in p:
        num = central_difference(fn, p, name)
        np.testing.assert_allclose(np.asarray(g[name]), num, rtol=rtol, atol=atol, err_msg=name)
        assert np.any(np.abs(num) > 1e-6), name  # the check must be able to fail


# ----------------------------------------------------------------------------- edges
_G = 1e-6
_S = np.sqrt(1 - _G * _G)
_C = np.sqrt(0.5)
EDGE_WI = np.array(
    [[0, 0, 1], [_C, 0, _C], [0.8660254037844386, 0, 0.5], [_S, 0, _G], [0, 0, 1],
     [_S, 0, _G], [_S, 0, _G], [1, 0, 1e-30], [1, 0, 1e-30], [1, 0, 0], [0.6, 0, -0.8],
     [_S, 0, _G]]
)  # fmt: skip
EDGE_WO = np.array(
    [[0, 0, 1], [_C, 0, _C], [-0.8660254037844386, 0, 0.5], [0, 0, 1], [0, _S, _G],
     [-_S, 0, _G], [_S, 0, _G], [-1, 0, 1e-30], [0, 0, 1], [0, 0, 1], [0, 0, 1],
     [-_S, 0, 0]]
)  # fmt: skip
# normal (wi = wo, wh = n); wi = wo at 45; mirror pair (wh = n); grazing wi; grazing wo;
# grazing mirror pair; wi = wo grazing; mirror pair and one direction at cos = 1e-30 (below
# every floor); wi on the horizon; wi below; wo exactly at cos 0. The last three rows must
# evaluate to exactly 0.


def assert_finite_edges(m, p, dtype, wi=EDGE_WI, wo=EDGE_WO):
    """Values and gradients (parameters and both directions) finite at the edge directions,
    in ``dtype``, and exactly 0 in the last three rows (cos = 0 and below the horizon)."""
    wi = jnp.asarray(wi, dtype=dtype)
    wo = jnp.asarray(wo, dtype=dtype)
    p = {k: jnp.asarray(v, dtype=dtype) for k, v in p.items()}
    ev = JIT.setdefault(m, jax.jit(m.eval))
    gr = JIT.setdefault(
        ("grad", m),
        jax.jit(jax.grad(lambda q, a, b: jnp.sum(m.eval(q, a, b)), argnums=(0, 1, 2))),
    )
    f = ev(p, wi, wo)
    assert f.dtype == dtype and np.all(np.isfinite(np.asarray(f))), f
    assert np.all(np.asarray(f)[-3:] == 0.0)  # cos = 0 and below the horizon are exactly 0
    for leaf in jax.tree_util.tree_leaves(gr(p, wi, wo)):
        assert np.all(np.isfinite(np.asarray(leaf))), (p, leaf)

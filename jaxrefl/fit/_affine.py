"""Which colour parameters a reflectance model is affine in, and the grid of its other
scalar parameter: the two facts the automatic start (:func:`~jaxrefl.fit.initial_theta`)
builds on.

:func:`linear_params` checks affinity numerically (the model at zero, unit and random colour
scales on random direction pairs, for several values of the other parameters), so a new
model needs no declaration. :func:`grid_values` gives natural grid values of a scalar
parameter (log-spaced for a width or exponent), inside the parameter's bounds by
``_EDGE_MARGIN`` of its range.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from jaxrefl.brdf import BRDF

from ._transform import ParamSpace

__all__ = ["grid_values", "linear_params"]

ALPHA_FAMILY = ("alpha", "alpha_u", "alpha_v")
# Start this fraction of a bounded range inside its edges (the sigmoid's slope is 0.01 there).
_EDGE_MARGIN = 1e-2


def grid_values(name: str, space: ParamSpace, size: int = 8) -> np.ndarray:
    """Natural grid values for a scalar parameter, inside its (user) bounds."""
    q = space.model.param_spec(name)
    if name in ALPHA_FAMILY:
        g = np.geomspace(0.01, 1.0, size)
    elif name == "exponent":
        g = np.geomspace(1.0, 1e4, size)
    elif name == "sigma":
        g = np.linspace(0.0, 1.2, size)
    elif float(np.asarray(q.default)) > 0:  # a scalar parameter's default is one number
        g = float(np.asarray(q.default)) * np.geomspace(0.1, 10.0, size)
    else:
        g = np.asarray([float(np.asarray(q.default))])
    s = space.index(name)
    lo, hi = float(space.lower[s.start]), float(space.upper[s.start])
    width = hi - lo if math.isfinite(hi - lo) else abs(lo) + 1.0
    return np.unique(np.clip(g, lo + _EDGE_MARGIN * width, hi - _EDGE_MARGIN * width))


def _test_directions(n: int = 24) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(12345)

    def hemi(k):
        v = rng.normal(size=(k, 3))
        v[:, 2] = np.abs(v[:, 2]) + 0.05
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    return hemi(n), hemi(n)


@eqx.filter_jit
def _eval(model, p, wi, wo):
    return model.eval(p, wi, wo)


def _is_affine(model: BRDF, space: ParamSpace, names: tuple[str, ...]) -> bool:
    """Numerically: is the model affine in the colour parameters ``names`` jointly?

    f(x) at x = 0, the unit vectors and two random points, for the defaults and 3 grid values
    of each other free scalar, on 24 random direction pairs (float32, one jitted call);
    affine when f(x) = f(0) + sum_j x_j (f(e_j) - f(0)) to 1e-4 of the largest value.
    """
    if not names:
        return True
    m = len(names)
    wi, wo = _test_directions()
    base = {q.name: np.asarray(q.default, dtype=np.float32) for q in model.params}
    for n, fixed in space.fixed.items():
        base[n] = np.asarray(fixed, dtype=np.float32)
    kinds = {q.name: q.kind for q in model.params}
    nonlin = [b.name for b in space.blocks if b.name not in names and b.kind == "scalar"]
    settings = [dict(base)]
    for n in nonlin:
        for v in grid_values(n, space, 3):
            settings.append({**base, n: np.asarray(v, np.float32)})
    rng = np.random.default_rng(7)
    xs = np.concatenate([np.zeros((1, m)), np.eye(m), rng.uniform(0.1, 0.9, (2, m))])
    rows = [(s, x) for s in settings for x in xs]
    p: dict[str, np.ndarray] = {}
    for k in base:
        vals = [np.asarray(s[k], np.float32) for s, _ in rows]
        v = np.stack(vals)  # (B, ...): colours (B,) or (B, C); scalars (B,); lobes (B, L, 4)
        if kinds[k] == "color" and v.ndim == 1:
            v = v[:, None]
        p[k] = v[:, None]  # a unit axis to meet the direction axis
    for j, n in enumerate(names):
        p[n] = np.asarray([x[j] for _, x in rows], np.float32)[:, None, None]
    f = _eval(model, p, jnp.asarray(wi[None], jnp.float32), jnp.asarray(wo[None], jnp.float32))
    f = np.asarray(f[..., 0], np.float64).reshape(len(settings), len(xs), -1)
    f0, units = f[:, :1], f[:, 1 : 1 + m] - f[:, :1]
    lin = f0 + np.einsum("rj,sjk->srk", xs[1 + m :], units)
    scale = np.max(np.abs(f0), axis=(1, 2)) + np.sum(np.max(np.abs(units), axis=2), axis=1)
    err = np.max(np.abs(f[:, 1 + m :] - lin), axis=(1, 2))
    return bool(np.all(err <= 1e-4 * scale + 1e-30))


def linear_params(model: BRDF, space: ParamSpace) -> tuple[str, ...]:
    """The free colour parameters (``albedo``, ``specular``) in which the model is affine
    (jointly), checked numerically; the largest such set, albedo first."""
    cands = tuple(
        b.name for b in space.blocks if b.kind == "color" and b.name in ("albedo", "specular")
    )
    if _is_affine(model, space, cands):
        return cands
    for n in cands:
        if _is_affine(model, space, (n,)):
            return (n,)
    return ()

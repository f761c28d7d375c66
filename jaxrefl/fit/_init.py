"""Starting points that need no user input: closed-form linear parameters on a roughness grid.

Most reflectance models are *affine* in their colour scales: with everything else fixed,

    pred_kc = f0_kc + sum_j x_jc F_jkc        (x = albedo, specular per channel c)

(Lambert: albedo/pi; Cook-Torrance with Schlick: F = F0 (1 - m) + m with m = (1 - cos)^5 is
affine in F0; Ward, Phong, dichromatic likewise). So for a *fixed* roughness the best colour
scales solve a small weighted linear least-squares problem per channel in closed form:
variable projection (Golub & Pereyra 1973) turns a P-dimensional search into a 1-D one.

:func:`initial_theta`:

1. Finds the free colour parameters in which the model is affine (:func:`linear_params`,
   checked numerically on random directions and several values of the other parameters).
2. Grids the remaining free scalar parameter (``alpha``: 12 log-spaced values in [0.01, 1];
   ``alpha_u``/``alpha_v`` tied together; ``exponent``: [1, 1e4]; ``sigma``: [0, 1.2] rad),
   solves the colour scales exactly within their bounds for every grid value (a box-
   constrained LS, exact for one or two parameters by enumerating the active sets; more
   than two: unconstrained LS then clipping, not exact), then grids again (8 values)
   between the neighbours of the best value, and keeps the value of lowest cost. The
   coarse grid is that fine because the cost minimum in alpha of a rough, strong lobe is
   only a few percent wide: a coarser grid starts more GGX pixels in the wrong basin, which
   the fit then keeps.
3. Otherwise (a parameter that is neither affine nor a gridable scalar, e.g. ``eta``,
   Lafortune lobes, a non-affine model) falls back to multi-start: the model defaults, with
   the closed-form diffuse albedo where there is one, and a few grid values of the first free
   scalar parameter; the candidate with the lowest residual cost wins.

Observations are whitened by the noise model and weighted; censored (saturated / dark)
observations are left out of the closed-form steps. The diffuse albedo of step 3 also
leaves out the brightest ``exclude_brightest`` fraction of observations (they likely hold
the highlight). Values on the edge of a bounded range are moved 1% of the range inside,
where the sigmoid still has slope (a start *at* a bound has none). Fixed parameters keep
their values; user bounds are respected.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxrefl.brdf import BRDF

from ._residual import PixelData, Residual
from ._transform import ParamSpace, ScaledSigmoid

__all__ = ["diffuse_albedo", "grid_values", "initial_theta", "linear_params"]

ALPHA_FAMILY = ("alpha", "alpha_u", "alpha_v")
# Start this fraction of a bounded range inside its edges (the sigmoid's slope is 0.01 there).
_EDGE_MARGIN = 1e-2
# Points of the refining grid between the neighbours of the best coarse value.
_REFINE = 8
# Pixels per chunk in the batched initialisation (bounds memory: G x (1 + m) x K x C each).
_CHUNK = 2048


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


# ---------------------------------------------------------------------------- linear algebra
def _quad(a, b, x):
    """x^T A x - 2 b^T x over the trailing axes."""
    ax = jnp.sum(a * x[..., None, :], axis=-1)
    return jnp.sum(x * ax, axis=-1) - 2.0 * jnp.sum(b * x, axis=-1)


def _box_ls(a: Array, b: Array, lo: ArrayLike, hi: ArrayLike) -> Array:
    """argmin x^T A x - 2 b^T x subject to lo <= x <= hi (A PSD (..., m, m), b (..., m)).

    m = 1, 2: exact (the optimum is interior or on an edge, where the 1-D problem is solved
    by clipping). m > 2: ridge-regularised LS, then clipping (not exact).
    """
    m = b.shape[-1]
    tiny = jnp.finfo(b.dtype).tiny
    lo = jnp.asarray(lo, b.dtype)
    hi = jnp.asarray(hi, b.dtype)
    lead = (1,) * (b.ndim - 1)
    if m == 1:
        a11 = a[..., 0, 0]
        # A basis function that is zero on every used observation: no information, lower bound.
        x = jnp.where(a11 > tiny, b[..., 0] / jnp.where(a11 > tiny, a11, 1.0), lo[0])
        return jnp.clip(x, lo[0], hi[0])[..., None]
    if m > 2:
        eye = jnp.eye(m, dtype=b.dtype)
        # A 1e-6 relative ridge keeps collinear basis functions from a singular solve.
        ridge = 1e-6 * jnp.mean(jnp.diagonal(a, axis1=-2, axis2=-1), axis=-1) + tiny
        x = jnp.linalg.solve(a + ridge[..., None, None] * eye, b[..., None])[..., 0]
        return jnp.clip(x, lo.reshape((*lead, m)), hi.reshape((*lead, m)))
    a11, a12, a22 = a[..., 0, 0], a[..., 0, 1], a[..., 1, 1]
    b1, b2 = b[..., 0], b[..., 1]
    det = a11 * a22 - a12 * a12
    # Interior solution only where the 2 x 2 system is well conditioned.
    ok = det > 1e-6 * a11 * a22 + tiny
    det_s = jnp.where(ok, det, 1.0)
    interior = jnp.stack([(a22 * b1 - a12 * b2) / det_s, (a11 * b2 - a12 * b1) / det_s], axis=-1)
    inside = ok & jnp.all(
        (interior >= lo.reshape((*lead, 2))) & (interior <= hi.reshape((*lead, 2))), axis=-1
    )
    cands, valid = [interior], [inside]
    for i, j, aii_, ajj, bj in ((0, 1, a11, a22, b2), (1, 0, a22, a11, b1)):
        del aii_
        for v in (lo[i], hi[i]):
            xj = jnp.where(ajj > tiny, (bj - a12 * v) / jnp.where(ajj > tiny, ajj, 1.0), lo[j])
            xj = jnp.clip(xj, lo[j], hi[j])
            pair = [xj, xj]
            pair[i] = jnp.broadcast_to(v, xj.shape)
            cands.append(jnp.stack(pair, axis=-1))
            valid.append(jnp.ones_like(inside))
    xs = jnp.stack(cands, axis=-2)  # (..., 5, 2)
    q = jax.vmap(_quad, in_axes=(None, None, -2), out_axes=-1)(a, b, xs)
    q = jnp.where(jnp.stack(valid, axis=-1), q, jnp.inf)
    best = jnp.argmin(q, axis=-1)
    return jnp.take_along_axis(xs, best[..., None, None], axis=-2)[..., 0, :]


# ---------------------------------------------------------------------------- per pixel
def _fit_weights(res: Residual, d: PixelData) -> tuple[Float[Array, "K C"], Float[Array, "K C"]]:
    """w / std^2 on usable, uncensored observations, 0 elsewhere, and the observations with
    the others set to 0; both (K, C)."""
    ok = res.usable(d) & (d.censored == 0)
    obs = jnp.where(ok, d.obs, 0.0)
    std = res.noise.std(obs)
    return jnp.where(ok, d.weight, 0.0) / (std * std), obs


def diffuse_albedo(
    res: Residual, d: PixelData, exclude_brightest: float = 0.2
) -> Float[Array, " C"]:
    """Weighted LS albedo of a Lambertian fit, pred = albedo * scale / pi, per channel, from
    the observations without the brightest fraction (ranked by mean obs/scale)."""
    w, obs = _fit_weights(res, d)
    s = jnp.where(w > 0, d.scale, 0.0) / jnp.pi
    ratio = jnp.mean(jnp.where(s > 0, obs / jnp.where(s > 0, s, 1.0), 0.0), axis=-1)  # (K,)
    used = jnp.any(w > 0, axis=-1)
    if exclude_brightest > 0:
        thresh = jnp.nanquantile(jnp.where(used, ratio, jnp.nan), 1.0 - exclude_brightest)
        keep = ~(ratio > thresh)  # NaN threshold (no usable data) keeps everything
        w = w * keep[:, None]
    num = jnp.sum(w * s * obs, axis=0)
    den = jnp.sum(w * s * s, axis=0)
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.5)


def _natural_base(space: ParamSpace, dtype) -> dict[str, Array]:
    out = {}
    for q in space.model.params:
        if q.name in space.fixed:
            out[q.name] = space.fixed[q.name].astype(dtype)
        else:
            v = jnp.asarray(q.default, dtype)
            if q.kind == "color" and v.shape != (space.channels,):
                # A default given per RGB channel (e.g. gold's eta) is averaged for other C.
                v = jnp.full((space.channels,), jnp.mean(v), dtype)
            out[q.name] = v
    return out


def _inset(space: ParamSpace, name: str, x: Array) -> Array:
    """Move a value 1% of its range inside a bounded range (see the module docstring)."""
    blk = space.blocks[space.free_names.index(name)]
    bij = blk.runs[0].bijection
    if isinstance(bij, ScaledSigmoid):
        w = bij.upper - bij.lower
        return jnp.clip(x, bij.lower + _EDGE_MARGIN * w, bij.upper - _EDGE_MARGIN * w)
    return x


def _varpro_pixel(res, lin, grid_names, grid, d):
    """theta0 of one pixel by variable projection over the grid (see the module doc)."""
    space, model = res.space, res.model
    dtype = d.obs.dtype
    c = d.obs.shape[-1]
    m = len(lin)
    b = 1 + m
    base = _natural_base(space, dtype)
    wi = d.wi.astype(dtype)[None, None]
    wo = wi if d.colocated else d.wo.astype(dtype)[None, None]
    w, obs = _fit_weights(res, d)
    scale = jnp.where(w > 0, d.scale, 0.0)
    lo = np.array([space.lower[space.index(n).start] for n in lin])
    hi = np.array([space.upper[space.index(n).start] for n in lin])

    def project(gvals):
        """Best linear parameters (G, C, m) and cost (G,) for each grid value."""
        g = gvals.shape[0]
        p = {}
        for q in model.params:
            v = base[q.name]
            p[q.name] = jnp.broadcast_to(v, (g, b, 1, *v.shape))
        for name in grid_names:
            p[name] = jnp.broadcast_to(gvals[:, None, None], (g, b, 1))
        for j, name in enumerate(lin):
            unit = (jnp.arange(b) == j + 1).astype(dtype)
            p[name] = jnp.broadcast_to(unit[None, :, None, None], (g, b, 1, c))
        pred = model.eval(p, wi, wo) * scale[None, None]  # (G, B, K, C)
        f0 = pred[:, 0]
        y = obs[None] - f0  # (G, K, C)
        if m:
            # Normal equations per grid value and channel, written out entry by entry as
            # sums over K (batched small matmuls and transposes are slow on CPU).
            fs = [pred[:, 1 + i] - f0 for i in range(m)]  # m x (G, K, C)
            wf = [w[None] * f for f in fs]
            rows = [[jnp.sum(wf[i] * fs[j], axis=1) for j in range(m)] for i in range(m)]
            a = jnp.stack([jnp.stack(row, -1) for row in rows], axis=-2)  # (G, C, m, m)
            bb = jnp.stack([jnp.sum(wf[i] * y, axis=1) for i in range(m)], axis=-1)  # (G, C, m)
            x = _box_ls(a, bb, lo, hi)  # (G, C, m)
            for i in range(m):
                y = y - x[:, None, :, i] * fs[i]
        else:
            x = jnp.zeros((g, c, 0), dtype)
        cost = jnp.sum(w[None] * y * y, axis=(-2, -1))
        return x, jnp.where(jnp.isfinite(cost), cost, jnp.inf)

    # No nonlinear parameter: one "grid value" (unused) and a single linear solve.
    coarse = jnp.asarray(grid if grid_names else [0.0], dtype).reshape(-1)
    x, cost = project(coarse)
    if grid_names:
        # Refine: a second grid between the neighbours of the best value.
        i = jnp.argmin(cost)
        n = coarse.shape[0]
        g_lo, g_hi = coarse[jnp.maximum(i - 1, 0)], coarse[jnp.minimum(i + 1, n - 1)]
        t = jnp.linspace(0.0, 1.0, _REFINE, dtype=dtype)
        if np.all(np.asarray(grid) > 0):
            fine = jnp.exp(jnp.log(g_lo) + t * (jnp.log(g_hi) - jnp.log(g_lo)))
        else:
            fine = g_lo + t * (g_hi - g_lo)
        x2, cost2 = project(fine)
        coarse = jnp.concatenate([coarse, fine])
        x = jnp.concatenate([x, x2])
        cost = jnp.concatenate([cost, cost2])
    best = jnp.argmin(cost)
    nat = {}
    for j, name in enumerate(lin):
        nat[name] = _inset(space, name, x[best, :, j])
    for name in grid_names:
        nat[name] = coarse[best]
    return space.from_natural(nat, dtype=dtype)


def _multistart_pixel(res, scalar_name, grid, exclude_brightest, d):
    """theta0 of one pixel: best of the defaults and a few grid values (module doc, step 3)."""
    space = res.space
    dtype = d.obs.dtype
    nat = {}
    if "albedo" in space.free_names:
        nat["albedo"] = _inset(space, "albedo", diffuse_albedo(res, d, exclude_brightest))
    cands = [space.from_natural(nat, dtype=dtype)]
    if scalar_name is not None:
        for v in grid:
            cand = {**nat, scalar_name: jnp.asarray(v, dtype)}
            cands.append(space.from_natural(cand, dtype=dtype))
    thetas = jnp.stack(cands)
    r = jax.vmap(res, in_axes=(0, None))(thetas, d)
    cost = jnp.sum(r * r, axis=-1)
    best = jnp.argmin(jnp.where(jnp.isfinite(cost), cost, jnp.inf))
    return thetas[best]


def _plan(res: Residual, grid_size: int):
    space = res.space
    lin = linear_params(res.model, space)
    rest = [b for b in space.blocks if b.name not in lin]
    names = tuple(b.name for b in rest)
    if all(b.kind == "scalar" for b in rest):
        if not names:
            return "varpro", lin, (), np.zeros(0)
        if set(names) == {"alpha_u", "alpha_v"}:
            return "varpro", lin, names, grid_values("alpha_u", space, grid_size)
        if len(names) == 1:
            return "varpro", lin, names, grid_values(names[0], space, grid_size)
    scalars = [b.name for b in space.blocks if b.kind == "scalar"]
    first = scalars[0] if scalars else None
    grid = grid_values(first, space, 6) if first else np.zeros(0)
    return "multistart", lin, first, grid


@eqx.filter_jit
def _initial_theta_jit(res, data, plan, exclude_brightest):
    how, lin, names, grid = plan
    grid = np.asarray(grid)
    if how == "varpro":

        def one(d):
            return _varpro_pixel(res, lin, names, grid, d)
    else:

        def one(d):
            return _multistart_pixel(res, names, grid, exclude_brightest, d)

    n = data.obs.shape[0]
    return jax.lax.map(one, data, batch_size=min(n, _CHUNK))


def initial_theta(
    res: Residual,
    data: PixelData,
    *,
    exclude_brightest: float = 0.2,
    grid_size: int = 12,
    devices: int | None = 1,
) -> Float[Array, "N P"]:
    """Unconstrained starting points (N, P) for the pixels of ``data`` (leading N axis).

    ``res`` supplies the model, the parameter space (bounds, fixed values) and the noise
    model used to whiten. See the module docstring for the method. ``devices``: how many of
    JAX's devices share the pixels (None: all; see ``_shard``).
    """
    from ._shard import device_count, map_sharded

    if data.obs.ndim != 3:
        raise ValueError(f"initial_theta expects batched data (N, K, C), got {data.obs.shape}")
    how, lin, names, grid = _plan(res, int(grid_size))  # eager: checks affinity numerically
    plan = (how, lin, names, tuple(float(v) for v in grid))
    run = lambda d: _initial_theta_jit(res, d, plan, float(exclude_brightest))  # noqa: E731
    return map_sharded(run, (data,), device_count(devices))

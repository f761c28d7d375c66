"""Starting points that need no user input: closed-form linear parameters on a roughness grid.

Most reflectance models are *affine* in their colour scales: with everything else fixed,

    pred_kc = f0_kc + sum_j x_jc F_jkc        (x = albedo, specular per channel c)

(Lambert: albedo/pi; Cook-Torrance with Schlick: F = F0 (1 - m) + m with m = (1 - cos)^5 is
affine in F0; Ward, Phong, dichromatic likewise). So for a *fixed* roughness the best colour
scales solve a small weighted linear least-squares problem per channel in closed form:
variable projection (Golub & Pereyra 1973) turns a P-dimensional search into a 1-D one.

:func:`initial_theta`:

1. Finds the free colour parameters in which the model is affine (:func:`linear_params`,
   checked numerically on random directions and several values of the other parameters;
   :mod:`._affine`).
2. Grids the remaining free scalar parameter (``alpha``: ``grid_size`` = 12 log-spaced
   values in [0.01, 1]; ``alpha_u``/``alpha_v`` tied together; ``exponent``: [1, 1e4];
   ``sigma``: [0, 1.2] rad), solves the colour scales exactly within their bounds for every
   grid value (a box-constrained LS, exact for one or two parameters by enumerating the
   active sets; more than two: unconstrained LS then clipping, not exact; :mod:`._box_ls`),
   then grids again (``refine`` = 6 values strictly between the neighbours of the best
   value, equally spaced in log alpha, so the fine spacing is 1/7 of the coarse one), and
   keeps the value of lowest cost. The grids are that fine because the cost minimum in
   alpha of a rough, strong lobe is only a few percent wide, and the profiled cost of a
   pixel seen from few directions can have several minima within one coarse step: a
   coarser search starts more GGX pixels in a different basin, which the fit then keeps.

   Cost per grid value: for alpha = a_g and zero colour scales the model gives f0 (K, C),
   and its derivative along each colour scale gives the basis functions F_j (exact, the
   model being affine in them), both from one forward-mode pass (``jax.linearize``) in
   which every term that does not depend on alpha (the geometry of the K directions) is
   computed once per pixel, not once per grid value. With y = obs - f0 and w the weights,
   the moments A_ij = sum_k w F_i F_j and b_i = sum_k w F_i y give the constrained
   solution x, and the cost is that of the residual y - sum_j x_j F_j (not the expanded
   form, a small difference of large sums in float32). Pixels are solved in blocks of
   ``_VARPRO_CHUNK`` as one array problem (pixel x grid value x observation x channel).
   Without a nonlinear parameter (every free parameter affine: Lambert, or a lobe whose
   width is fixed, as the pooled capture model's) there is no grid, and the one solve is
   made the fit's own problem: the prior's quadratic terms join the moments (a Gaussian
   prior N(m, s^2) on x_j adds 1/s^2 to A_jj and m/s^2 to b_j), and ``_EXACT_PASSES``
   reweighted passes (iteratively reweighted least squares: weights psi(z)/z of the robust
   loss at the current residuals; saturated or dark observations join where the current
   prediction violates their bound) move it towards the robust, censored optimum. A value
   on a bound starts ``_EXACT_MARGIN`` of the range inside it, within the LM's bound test,
   so the LM confirms it there instead of crawling towards it where the sigmoid has little
   slope.
3. Otherwise (a parameter that is neither affine nor a gridable scalar, e.g. ``eta``,
   Lafortune lobes, a non-affine model) falls back to multi-start: the model defaults, with
   the closed-form diffuse albedo where there is one, and a few grid values of the first free
   scalar parameter; the candidate with the lowest residual cost wins.

Observations are whitened by the noise model and weighted; censored (saturated / dark)
observations are left out of the closed-form steps. The diffuse albedo of step 3 also
leaves out the brightest ``exclude_brightest`` fraction of observations (they likely hold
the highlight). Values on the edge of a bounded range are moved ``_EDGE_MARGIN`` of the
range inside, where the sigmoid still has slope (a start *at* a bound has none). Fixed
parameters keep their values; user bounds are respected.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrefl._errors import JaxreflError

from ._affine import _EDGE_MARGIN, grid_values, linear_params
from ._box_ls import _box_ls, _box_ls2
from ._residual import L2, PixelData, Residual
from ._transform import ParamSpace, ScaledSigmoid

__all__ = ["diffuse_albedo", "initial_theta"]

# A model without a nonlinear parameter starts at its own problem's solution (module
# docstring): its robust loss and censored rows by this many reweighted passes, and a value
# on a bound of its range starts this fraction inside (within the LM's default bound test,
# ``LMOptions.bound_rtol``, so a pixel whose optimum is on the bound is found there, not
# crawled towards where the sigmoid has little slope).
_EXACT_PASSES = 2
_EXACT_MARGIN = 1e-4
# Pixels per block of the variable projection (its working set: G x K x C values a pixel);
# without a grid the working set is G = 1 value a pixel, and larger blocks spend less on
# the per-operation overhead of the reweighted passes.
_VARPRO_CHUNK = 256
_EXACT_CHUNK = 4096
# At most this many (pixel, grid value, observation, channel) entries in a block.
_VARPRO_ELEMS = 1 << 21
# Pixels per chunk in the multi-start initialisation (bounds memory: G x (1 + m) x K x C each).
_CHUNK = 2048


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


def _inset(space: ParamSpace, name: str, x: Array, margin: float = _EDGE_MARGIN) -> Array:
    """Move a value ``margin`` of its range inside a bounded range (module docstring)."""
    blk = space.blocks[space.free_names.index(name)]
    bij = blk.runs[0].bijection
    if isinstance(bij, ScaledSigmoid):
        w = bij.upper - bij.lower
        return jnp.clip(x, bij.lower + margin * w, bij.upper - margin * w)
    return x


def _prior_moments(res: Residual, lin: tuple[str, ...], c: int, dtype):
    """Per linear parameter j and channel, the precision 1/std^2 and precision-weighted mean
    mean/std^2 of ``res.prior`` on that entry (zeros where it has none): the prior's
    quadratic (x - mean)^2 / std^2 adds them to A_jj and b_j."""
    prec = [jnp.zeros((c,), dtype) for _ in lin]
    pb = [jnp.zeros((c,), dtype) for _ in lin]
    prior = res.prior
    if prior is None:
        return [v.reshape(1, 1, c) for v in prec], [v.reshape(1, 1, c) for v in pb]
    for i, idx in enumerate(prior.index):
        for j, name in enumerate(lin):
            s = res.space.index(name)
            if s.start <= idx < s.stop:
                inv = 1.0 / jnp.square(prior.std[i].astype(dtype))
                prec[j] = prec[j].at[idx - s.start].add(inv)
                pb[j] = pb[j].at[idx - s.start].add(prior.mean[i].astype(dtype) * inv)
    # (1, 1, C): aligned with the (pixel, grid value, channel) moments.
    return [v.reshape(1, 1, c) for v in prec], [v.reshape(1, 1, c) for v in pb]


def _irls_weight(loss, z):
    """psi(z) / z of the robust loss (1 for L2): the weight of iteratively reweighted least
    squares, whose fixed point is the loss's minimiser. rho''(0) = 1 for every loss here, so
    the weight is 1 at z = 0 (the division is guarded there)."""
    if isinstance(loss, L2):
        return jnp.ones_like(z)
    psi = jax.grad(lambda v: jnp.sum(loss.rho(v)))(z)
    small = jnp.abs(z) < 1e-6
    return jnp.where(small, 1.0, psi / jnp.where(small, 1.0, z))


def _varpro_block(res, lin, grid_names, grid, refine, d):
    """theta0 (n, P) of a block of n pixels by variable projection over the grid (module doc).

    Array axes: (n, G, K, C) = (pixel, grid value, observation, channel). Every parameter
    and direction enters ``model.eval`` with unit axes where it does not vary, so each term
    of the model is computed at the shape of what it depends on: the geometry once per
    pixel and observation (n, 1, K), the roughness-dependent lobe once per grid value.
    """
    space, model = res.space, res.model
    dtype = d.obs.dtype
    c = d.obs.shape[-1]
    m = len(lin)
    base = _natural_base(space, dtype)
    wi = d.wi.astype(dtype)[:, None]  # (n, 1, K, 3)
    wo = wi if d.colocated else d.wo.astype(dtype)[:, None]
    w, obs = jax.vmap(lambda dd: _fit_weights(res, dd))(d)  # (n, K, C)
    # Every usable observation (censored ones too) with its whitening weight w / std^2,
    # for the exact solve of a model without a nonlinear parameter (module docstring).
    usable = jax.vmap(res.usable)(d)
    obs_all = jnp.where(usable, d.obs, 0.0)
    std_all = jax.vmap(res.noise.std)(obs_all)
    w_all = jnp.where(usable, d.weight, 0.0) / (std_all * std_all)
    scale = jnp.where(usable, d.scale, 0.0)
    lo = np.array([space.lower[space.index(n).start] for n in lin])
    hi = np.array([space.upper[space.index(n).start] for n in lin])
    prec, pbias = _prior_moments(res, lin, c, dtype)
    exact = not grid_names
    kinds = {q.name: q.kind for q in model.params}
    p = {}
    for q in model.params:
        v = base[q.name]
        rank = 3 if kinds[q.name] == "scalar" else 4
        p[q.name] = v.reshape((1,) * (rank - v.ndim) + v.shape)

    def project(gvals):
        """Best linear parameters m x (n, G, C) and cost (n, G) for grid values (n | 1, G).

        With the basis f0 (the model at zero colour scales) and f_j (its derivative along
        colour scale j), y = obs - f0 and the moments A_ij = sum_k w f_i f_j,
        b_i = sum_k w f_i y (per channel, plus the prior's terms), the box-constrained
        solution x minimises x^T A x - 2 b^T x. Without a nonlinear parameter (``exact``)
        the solve is repeated ``_EXACT_PASSES`` times as iteratively reweighted least
        squares: each pass weighs the observations by the robust loss at the current
        residuals and adds the censored ones that the current prediction violates (the
        one-sided rows of :class:`~jaxrefl.fit.Residual`): towards the fit's own optimum,
        which the LM then reaches in a few steps."""
        pg = dict(p)
        for name in grid_names:
            pg[name] = gvals[:, :, None]

        def pred_at(xs):
            return model.eval({**pg, **dict(zip(lin, xs, strict=True))}, wi, wo) * scale[:, None]

        # The basis from one forward pass (exact: the model is affine in the colour
        # scales), sharing every term that does not depend on them.
        zero = tuple(jnp.zeros((1, 1, 1, c), dtype) for _ in lin)
        f0, tangent = jax.linearize(pred_at, zero)
        ones = jnp.ones((1, 1, 1, c), dtype)
        fs = [tangent(tuple(ones if i == j else z for i, z in enumerate(zero))) for j in range(m)]
        # The moments per pixel, grid value and channel, entry by entry, with K as the
        # minor axis (batched small matmuls are slow on CPU).
        vs = [jnp.swapaxes(v, -1, -2) for v in fs]  # (n, G, C, K)
        y = jnp.swapaxes((obs_all if exact else obs)[:, None] - f0, -1, -2)

        def solve(us, z):
            """The box-constrained x from the whitened basis u_j = sqrt(w) f_j and
            z = sqrt(w) y: A_ij = sum_k u_i u_j, b_i = sum_k u_i z."""
            a = {(i, j): jnp.sum(us[i] * us[j], axis=-1) for i in range(m) for j in range(i, m)}
            b = [jnp.sum(us[i] * z, axis=-1) + pbias[i] for i in range(m)]
            for i in range(m):
                a[i, i] = a[i, i] + prec[i]
            if m == 1:
                return [_box_ls(a[0, 0][..., None, None], b[0][..., None], lo, hi)[..., 0]]
            if m == 2:
                x1, x2, _ = _box_ls2(a[0, 0], a[0, 1], a[1, 1], b[0], b[1], lo, hi)
                return [x1, x2]
            if m:
                full = jnp.stack(
                    [jnp.stack([a[min(i, j), max(i, j)] for j in range(m)], -1) for i in range(m)],
                    -2,
                )
                x = _box_ls(full, jnp.stack(b, -1), lo, hi)  # (n, G, C, m)
                return [x[..., i] for i in range(m)]
            return []

        def residual(xs, us, z):
            r = z
            for j in range(m):
                r = r - xs[j][..., None] * us[j]
            return r  # sqrt(w) (obs - pred), (n, G, C, K)

        def whiten(wt):
            s = jnp.sqrt(wt)
            return [s * v for v in vs], s * y

        # The basis enters only whitened: each u_j is then one fused pass over the model
        # (a bare f_j read by several consumers would be evaluated again in each).
        us, z = whiten(jnp.swapaxes(w, -1, -2)[:, None])
        xs = solve(us, z)
        if exact:
            wa = jnp.swapaxes(w_all, -1, -2)[:, None]
            cens = jnp.swapaxes(d.censored, -1, -2)[:, None]
            std = jnp.swapaxes(std_all, -1, -2)[:, None]
            for _ in range(_EXACT_PASSES):
                r = residual(xs, vs, y)
                # A censored row counts where the prediction breaks its bound: below a
                # saturated value (r > 0) or above a dark one (r < 0).
                on = (cens == 0) | ((cens > 0) & (r > 0)) | ((cens < 0) & (r < 0))
                xs = solve(*whiten(wa * on * _irls_weight(res.loss, -r / std)))
        # The cost from the residual itself: the expanded form s + x^T A x - 2 b^T x loses
        # the digits of a good fit in float32 (it is a small difference of large sums), and
        # near-equal grid values would then be ranked by rounding.
        r = residual(xs, us, z)
        cost = jnp.sum(r * r, axis=(-2, -1))
        return xs, jnp.where(jnp.isfinite(cost), cost, jnp.inf)

    # No nonlinear parameter: one "grid value" (unused) and a single linear solve.
    coarse = jnp.asarray(grid if grid_names else [0.0], dtype).reshape(1, -1)
    xs, cost = project(coarse)
    vals = jnp.broadcast_to(coarse, cost.shape)
    ng = coarse.shape[1]
    positive = bool(np.all(np.asarray(grid) > 0))
    if grid_names and ng > 1 and refine > 0:
        i = jnp.argmin(cost, axis=-1)
        # A fine grid of ``refine`` values strictly between the neighbours of the best value
        # (equally spaced in log for a positive grid; the neighbours are grid values already).
        g_lo = coarse[0, jnp.maximum(i - 1, 0)][:, None]
        g_hi = coarse[0, jnp.minimum(i + 1, ng - 1)][:, None]
        t = (jnp.arange(1, refine + 1, dtype=dtype) / (refine + 1))[None]
        if positive:
            fine = jnp.exp(jnp.log(g_lo) + t * (jnp.log(g_hi) - jnp.log(g_lo)))
        else:
            fine = g_lo + t * (g_hi - g_lo)
        xs2, cost2 = project(fine)
        vals = jnp.concatenate([vals, fine], axis=1)
        xs = [jnp.concatenate([a, b], axis=1) for a, b in zip(xs, xs2, strict=True)]
        cost = jnp.concatenate([cost, cost2], axis=1)
    best = jnp.argmin(cost, axis=-1)
    nat = {}
    for j, name in enumerate(lin):
        xb = jnp.take_along_axis(xs[j], best[:, None, None], axis=1)[:, 0]  # (n, C)
        nat[name] = _inset(space, name, xb, _EXACT_MARGIN if exact else _EDGE_MARGIN)
    for name in grid_names:
        nat[name] = jnp.take_along_axis(vals, best[:, None], axis=1)[:, 0]
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


def _varpro_chunk(shape: tuple[int, ...], n_grid: int) -> int:
    """Pixels per block of the variable projection for data of shape (N, K, C)."""
    k, c = shape[-2:]
    cap = _VARPRO_CHUNK if n_grid > 1 else _EXACT_CHUNK
    return max(1, min(cap, _VARPRO_ELEMS // (max(1, n_grid) * k * c)))


def _bucket(n: int, chunk: int) -> int:
    """The batch size a varpro batch of n pixels is padded to before compilation, so that
    batches of different sizes share one compiled program: a power of two number of blocks
    of ``chunk`` pixels up to 16 blocks, a multiple of 16 blocks above (less than 16 blocks
    of padding on a large batch)."""
    blocks = -(-n // chunk)
    if blocks <= 16:
        return chunk * (1 << max(0, blocks - 1).bit_length())
    return chunk * 16 * -(-blocks // 16)


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
def _initial_theta_jit(res, data, plan, exclude_brightest, refine):
    how, lin, names, grid = plan
    grid = np.asarray(grid)
    n = data.obs.shape[0]
    if how == "varpro":
        # Blocks of pixels (lax.map), each solved as one array problem; the last block is
        # padded with copies of pixel 0, cut off after. The block size depends on K and C
        # only, never on N: every pixel then goes through the same compiled block, and its
        # start does not depend on the batch it came in (nor on how devices split it).
        chunk = _varpro_chunk(data.obs.shape, len(grid))
        blocks = -(-n // chunk)
        pad = blocks * chunk - n

        def padded(x):
            if pad:
                x = jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad, *x.shape[1:]))])
            return x.reshape((blocks, chunk, *x.shape[1:]))

        theta = jax.lax.map(
            lambda d: _varpro_block(res, lin, names, grid, refine, d), jax.tree.map(padded, data)
        )
        return theta.reshape((blocks * chunk, theta.shape[-1]))[:n]

    def one(d):
        return _multistart_pixel(res, names, grid, exclude_brightest, d)

    return jax.lax.map(one, data, batch_size=min(n, _CHUNK))


def initial_theta(
    res: Residual,
    data: PixelData,
    *,
    exclude_brightest: float = 0.2,
    grid_size: int = 12,
    refine: int = 6,
    devices: int | None = 1,
) -> Float[Array, "N P"]:
    """Unconstrained starting points (N, P) for the pixels of ``data`` (leading N axis).

    ``res`` supplies the model, the parameter space (bounds, fixed values) and the noise
    model used to whiten. See the module docstring for the method: ``grid_size`` coarse
    values of the gridded parameter, then ``refine`` values strictly between the
    neighbours of the best one (0: no second grid); the multi-start fallback uses neither.
    ``devices``: how many of JAX's devices share the pixels (None: all; see ``_shard``).
    """
    from ._shard import device_count, map_sharded

    if data.obs.ndim != 3:
        raise JaxreflError(f"initial_theta expects batched data (N, K, C), got {data.obs.shape}")
    how, lin, names, grid = _plan(res, int(grid_size))  # eager: checks affinity numerically
    plan = (how, lin, names, tuple(float(v) for v in grid))
    if int(refine) < 0:
        raise JaxreflError(f"refine must be >= 0, got {refine}")
    ex = float(exclude_brightest)
    run = lambda d: _initial_theta_jit(res, d, plan, ex, int(refine))  # noqa: E731
    n = data.obs.shape[0]
    if how != "varpro" or n == 0:
        return map_sharded(run, (data,), device_count(devices))
    # The varpro start of a pixel depends on that pixel alone; padding the batch with copies
    # of pixel 0 (cut off after) lets batches of different sizes use one compiled program.
    pad = _bucket(n, _varpro_chunk(data.obs.shape, len(grid))) - n
    if not pad or any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(data)):
        return map_sharded(run, (data,), device_count(devices))

    def padded(x):  # on the host: no small programs to compile per batch size
        a = np.asarray(x)
        return jax.device_put(np.concatenate([a, np.repeat(a[:1], pad, 0)]))

    theta = map_sharded(run, (jax.tree.map(padded, data),), device_count(devices))
    return jax.device_put(np.asarray(theta)[:n])

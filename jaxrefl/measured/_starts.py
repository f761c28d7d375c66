"""Multi-start fits of one measured material: starts that see the data, a batch of diverse
starts solved together, and a certificate of the optimum.

A fit of a specular lobe from one start can stop next to the Lambertian solution (a lobe too
narrow or too weak to reach the highlight has no gradient towards it), so a model ranking
would compare the optimiser's luck. :func:`fit_multistart` therefore solves S starts of the
same problem in one batched Levenberg-Marquardt call (:func:`jaxrefl.fit.fit_pixels` on the
problem repeated S times) and keeps the start of lowest cost. The starts are

* **data-driven** and **quasi-random** (:mod:`._seeds`): lobe widths and heights read off
  the samples, and scrambled Sobol points in a box of the unconstrained space;
* **the automatic start** of a single fit (:func:`jaxrefl.fit.initial_theta`: closed-form
  colours on a roughness grid), so that the kept result is never worse than the single
  start's (both get the same iteration budget).
* **nested** (:mod:`._nested`), for a model that contains a smaller one: the smaller
  model's optimum plus one new lobe.

**Continuation.** Every start gets the solver's iteration budget; a narrow Lafortune lobe
(exponent in the hundreds) can need several budgets to converge, so that the best start
found after one budget may still be descending. While one of the ``polish`` lowest-cost
starts of a problem has stopped at the budget (``MAX_ITERATIONS``), every start that did
continues from where it stopped, for up to ``rounds`` more budgets; a continued start keeps
its old result if the new one is not lower. The continuation runs the same batch through
the same compiled program (same shapes, same static solver settings), so it compiles
nothing.

**Perturbed generations.** Where the starts disagree (the certificate below is doubtful:
the landscape has many basins, as multi-lobe Lafortune fits often do), the ``polish`` best
results so far seed a new generation of as many starts: each best result plus a Gaussian
step in the unconstrained space of scale 0.25, 0.5, 1 or 2 (a basin-hopping step, Wales &
Doye 1997), solved and continued like the first. Generations follow one another, up to
``generations``, while the certificate stays doubtful and the last one lowered some
problem's best cost by more than ``agree_rtol``; the best over all generations is kept and
all of them are certified together. They run through the same compiled program.

The :class:`~jaxrefl.measured.Certificate` (:mod:`._certificate`) counts the starts that
agree on the best cost: a user then sees that the starts disagree, not only the best value
found.

Costs are the solver's own 1/2 |r|^2 (whitened and robust as the config says), compared in
float64. Problems: one for channels fitted jointly, C when every channel is its own problem
(results then have a leading axis C; the certificate reports the worst channel).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF
from jaxrefl.fit import (
    L2,
    FitConfig,
    FitResult,
    ParamSpace,
    PixelData,
    Status,
    fit_pixels,
    initial_theta,
    keep_lower,
    make_residual,
    pixel_data,
)
from jaxrefl.fit import sample_arrays as _sample_arrays
from jaxrefl.io import MeasuredBRDF

from ._certificate import Certificate, certify
from ._data import Channels, fit_channels, restrict
from ._fit_options import MeasuredOptions
from ._nested import nested_thetas
from ._seeds import start_thetas
from ._start_options import MultiStart

__all__ = ["fit_multistart"]

_DEFAULT_STARTS = MultiStart()
_OPTIONS = MeasuredOptions()
_FLOAT32_CONFIG = FitConfig(dtype=np.float32)


def _problem(
    wi: np.ndarray,
    wo: np.ndarray,
    values: np.ndarray,
    channels: Channels,
    cosine: bool,
    dtype: np.dtype,
) -> PixelData:
    """The samples as N problems (N = 1 joint, C separate), as :func:`jaxrefl.fit.fit_samples`
    builds them."""
    obs, scale, weight = _sample_arrays(wi, wo, values, cosine=cosine, dtype=dtype)
    k, c = obs.shape
    if channels == "joint":
        return pixel_data(
            obs[None],
            wi[None].astype(dtype),
            wo[None].astype(dtype),
            scale=None if scale is None else scale[None],
            weight=weight[None],
        )
    return pixel_data(
        obs.T[..., None],
        np.broadcast_to(wi.astype(dtype), (c, k, 3)),
        np.broadcast_to(wo.astype(dtype), (c, k, 3)),
        scale=None if scale is None else scale.T[..., None],
        weight=weight.T[..., None],
    )


def _nested_starts(
    space: ParamSpace,
    nested: FitResult,
    wi: np.ndarray,
    wo: np.ndarray,
    f: np.ndarray,
    n: int,
    cosine: bool,
) -> np.ndarray:
    """(N, S, P) :func:`nested_thetas` of each of the N problems from the fit ``nested``
    (theta (P',) for one problem, (N, P') for N)."""
    theta = np.asarray(nested.theta, np.float64)
    if theta.size != n * nested.space.size:
        raise JaxreflError(
            f"the nested fit has {theta.size // max(nested.space.size, 1)} problems, "
            f"this fit {n}: fit both with the same channels"
        )
    with jax.enable_x64(True):
        natural = nested.space.to_natural(jnp.asarray(theta.reshape(n, -1)))
        nat = {k: np.asarray(v, np.float64) for k, v in natural.items()}
    out = []
    for i in range(n):
        p = {k: v[i] for k, v in nat.items()}
        fi = f if n == 1 else f[:, i : i + 1]
        out.append(nested_thetas(space, nested.model, p, wi, wo, fi, cosine=cosine))
    return np.stack(out)


def _finite_costs(r: FitResult, n: int, s: int) -> np.ndarray:
    c = np.asarray(r.cost, np.float64).reshape(n, s)
    return np.where(np.isfinite(c), c, np.inf)


# Perturbation scales (unconstrained units) of the perturbed generations of starts.
_PERTURB_SCALES = (0.25, 0.5, 1.0, 2.0)


def _perturbed(
    theta: np.ndarray, costs: np.ndarray, starts: MultiStart, generation: int
) -> np.ndarray:
    """(N * S, P) starts of a perturbed generation from the results so far (N, G * S, P)
    and their costs (N, G * S): the ``starts.polish`` lowest-cost results of each problem,
    each perturbed by Gaussian steps of every scale in ``_PERTURB_SCALES`` in turn
    (module docstring). ``generation`` = G, the generations so far; each has S starts."""
    n, _, p = theta.shape
    s = theta.shape[1] // generation
    rng = np.random.default_rng([starts.seed, generation])
    top = np.argsort(costs, axis=1)[:, : min(starts.polish, s)]
    m = np.arange(s)
    base = theta[np.arange(n)[:, None], top[:, m % top.shape[1]]]
    step = np.asarray(_PERTURB_SCALES)[(m // top.shape[1]) % len(_PERTURB_SCALES)]
    out = base + step[None, :, None] * rng.standard_normal((n, s, p))
    return out.reshape(n * s, p)


def _stack(a: FitResult, b: FitResult) -> FitResult:
    """Two batched results as one, ``a``'s rows first."""

    def cat(x, y):
        return jnp.concatenate([jnp.asarray(x), jnp.asarray(y)])

    return FitResult(
        jax.tree.map(cat, a.params, b.params),
        cat(a.theta, b.theta),
        cat(a.status, b.status),
        cat(a.cost, b.cost),
        cat(a.iterations, b.iterations),
        cat(a.n_used, b.n_used),
        a.space,
        a.model,
        a.backend,
    )


def _continue(
    model: BRDF,
    batch: PixelData,
    config: FitConfig,
    space: ParamSpace,
    r: FitResult,
    n: int,
    s: int,
    starts: MultiStart,
) -> FitResult:
    """The continuation of the module docstring: up to ``starts.rounds`` more budgets for
    the starts that stopped at the iteration limit, while one of each problem's
    ``starts.polish`` best has."""
    for _ in range(starts.rounds):
        status = np.asarray(r.status).reshape(n, s)
        costs = _finite_costs(r, n, s)
        top = np.argsort(costs, axis=1)[:, : starts.polish]
        if not np.any(np.take_along_axis(status, top, axis=1) == Status.MAX_ITERATIONS):
            break
        more = fit_pixels(model, batch, config=config, space=space, init=r.theta)
        # A start that had stopped for another reason keeps its result, and so does one
        # whose continuation did not lower its cost (the LM restarts its damping).
        hit = np.asarray(r.status) == Status.MAX_ITERATIONS
        iters = np.asarray(r.iterations) + np.where(hit, np.asarray(more.iterations), 0)
        fields = lambda x: (x.params, x.theta, x.status, x.n_used)  # noqa: E731
        cost, (params, theta, status, n_used) = keep_lower(
            r.cost, fields(r), more.cost, fields(more), where=hit
        )
        r = FitResult(
            params, theta, status, cost, jnp.asarray(iters), n_used, space, model, r.backend
        )
    return r


def fit_multistart(
    model: BRDF,
    measured: MeasuredBRDF,
    *,
    options: MeasuredOptions = _OPTIONS,
    config: FitConfig = _FLOAT32_CONFIG,
    starts: MultiStart = _DEFAULT_STARTS,
    thetas: np.ndarray | None = None,
    nested: FitResult | None = None,
) -> tuple[FitResult, Certificate, np.ndarray]:
    """Fit ``model`` to the f_r samples of ``measured`` from many starts at once and keep
    the best per problem.

    options: the samples and channels fitted and the residual, as for
             :func:`~jaxrefl.measured.fit_model` (:class:`MeasuredOptions`: the angle limit,
             the cosine factor, spectral data as RGB or one problem a band); one run in
             ``config``'s dtype, so its ``retry_float64`` is :func:`fit_model`'s to apply
    config:  as for :func:`jaxrefl.fit.fit_samples` (dtype None: float32)
    The starts: the automatic one, then :func:`start_thetas`, then, with ``nested`` (the fit
    of :func:`nested_model` to the same samples under the same options; used when
    ``starts.nested``), :func:`nested_thetas`; ``thetas`` (S, P) replaces them all (the
    thresholds of ``starts`` still certify).
    Returns the best result shaped as :func:`jaxrefl.fit.fit_samples` returns it (no
    leading axis when joint, C when separate), its :class:`Certificate`, and the (N, S)
    costs of every start.
    """
    dtype = np.dtype(np.float32 if config.dtype is None else config.dtype)
    measured, channels = fit_channels(measured, options)
    measured = restrict(measured, options.max_theta_deg)
    if len(measured) == 0:
        raise JaxreflError(
            f"{measured.source}: no usable samples within {options.max_theta_deg} degrees"
        )
    cosine = options.cosine
    wi = np.asarray(measured.wi, np.float64)
    wo = np.asarray(measured.wo, np.float64)
    f = np.asarray(measured.values, np.float64)
    data = _problem(wi, wo, f, channels, cosine, dtype)
    n = data.obs.shape[0]
    names = tuple(measured.channels) if channels == "joint" else None
    space = ParamSpace(model, channels=data.obs.shape[-1], channel_names=names)
    if thetas is None:
        per = [
            start_thetas(space, wi, wo, f if n == 1 else f[:, i : i + 1], starts, cosine=cosine)
            for i in range(n)
        ]
        loss = L2() if config.loss is None else config.loss
        auto = np.asarray(initial_theta(make_residual(model, space, config.noise, loss), data))
        t0 = np.concatenate([auto[:, None].astype(np.float64), np.stack(per)], axis=1)
        if nested is not None and starts.nested:
            t0 = np.concatenate([t0, _nested_starts(space, nested, wi, wo, f, n, cosine)], axis=1)
    else:
        t0 = np.broadcast_to(np.asarray(thetas, np.float64), (n, *np.shape(thetas)))
    s = t0.shape[1]
    batch = jax.tree.map(lambda a: jnp.repeat(a, s, axis=0), data)
    r = fit_pixels(
        model,
        batch,
        config=config.replace(dtype=dtype),
        space=space,
        init=jnp.asarray(t0.reshape(n * s, -1), dtype),
    )
    cfg = config.replace(dtype=dtype)
    r = _continue(model, batch, cfg, space, r, n, s, starts)
    costs = _finite_costs(r, n, s)
    y = np.where(np.asarray(data.weight) > 0, np.asarray(data.obs, np.float64), 0.0)
    scale = float(0.5 * np.sum(y * y) / n)
    # Generations side by side: row g * n * s + i * s + j holds start j of problem i in
    # generation g; costs (n, G * s) in the same order along axis 1.
    thetas_all = np.asarray(r.theta, np.float64).reshape(n, s, -1)
    gen, improved = 1, True
    while (
        thetas is None
        and gen <= starts.generations
        and improved
        and certify(costs, starts.agree_rtol, starts.min_share, scale).doubtful
    ):
        t1 = _perturbed(thetas_all, costs, starts, gen)
        r1 = fit_pixels(model, batch, config=cfg, space=space, init=jnp.asarray(t1, dtype))
        r1 = _continue(model, batch, cfg, space, r1, n, s, starts)
        c1 = _finite_costs(r1, n, s)
        best = np.min(costs, axis=1)
        improved = bool(np.any(np.min(c1, axis=1) < best - starts.agree_rtol * np.abs(best)))
        r = _stack(r, r1)
        costs = np.concatenate([costs, c1], axis=1)
        thetas_all = np.concatenate(
            [thetas_all, np.asarray(r1.theta, np.float64).reshape(n, s, -1)], axis=1
        )
        gen += 1
    j = np.argmin(costs, axis=1)
    pick = (j // s) * n * s + np.arange(n) * s + j % s
    cert = certify(costs, starts.agree_rtol, starts.min_share, scale)

    def take(x):
        x = jnp.asarray(x)[pick]
        return x[0] if channels == "joint" else x

    theta = take(r.theta)
    params = space.to_natural(theta)
    if channels == "separate":
        kinds = {q.name: q.kind for q in model.params}
        params = {k: (v[:, 0] if kinds[k] == "color" else v) for k, v in params.items()}
    best = FitResult(
        params,
        theta,
        take(r.status),
        take(r.cost),
        take(r.iterations),
        take(r.n_used),
        space,
        model,
        r.backend,
    )
    return best, cert, costs

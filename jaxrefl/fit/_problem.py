"""The public fitting API: many pixels (:func:`fit_pixels`) or one measured material
(:func:`fit_samples`), returning a :class:`FitResult`.

Pipeline: a :class:`ParamSpace` (bounds, fixed values, unconstrained theta), a
:class:`Residual` (noise whitening, robust loss, censoring, defensive masking), a start
(:func:`initial_theta` by default: closed-form colours on a roughness grid), and a batched
least-squares solver (:func:`solve`: :class:`LMOptions`, :class:`OptimistixLM` or
:class:`JaxoptLM`). :class:`FitConfig` bundles the solver, noise model, loss and dtype of a
fit: every fitting entry point of the library takes one.

Failures are values (``Status``), never exceptions in the middle of a batch:

* a pixel with fewer usable observations (finite, weight > 0) than free parameters is
  MASKED; if non-finite values are what left it short, NONFINITE_INPUT. Such pixels still
  pass through the solver (their residual is identically 0, so they stop at once; shapes
  stay static) but get NaN ``params``, ``theta`` and ``cost``: no estimate, rather than a
  made-up one.
* non-finite observations in an otherwise usable pixel are masked out (weight 0) and the
  pixel is fitted from the rest; ``n_used`` counts what was used.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int
from numpy.typing import DTypeLike

from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF

from ._backends import Solver, solve
from ._init import initial_theta
from ._lm import LMOptions
from ._options import Option
from ._residual import (
    L2,
    GaussianNoise,
    GaussianPrior,
    Loss,
    NoiseModel,
    PixelData,
    Residual,
    make_residual,
    pixel_data,
)
from ._shard import device_count, map_sharded
from ._status import Status, describe, has_estimate
from ._transform import ParamSpace

__all__ = [
    "FitConfig",
    "FitResult",
    "Linearisation",
    "SamplesOptions",
    "fit_pixels",
    "fit_samples",
    "sample_arrays",
]

Init = Literal["auto", "defaults"] | ArrayLike | Mapping[str, ArrayLike]


def _as_dtype(dtype: Any) -> np.dtype | None:
    return None if dtype is None else np.dtype(dtype)


class FitConfig(Option):
    """How a fit is computed: solver, noise model, robust loss and dtype (immutable).

    Every fitting entry point takes one (:func:`fit_pixels`, :func:`fit_samples`,
    :class:`jaxrefl.svbrdf.FitJob`, :func:`jaxrefl.measured.fit_brdf` and the other
    measured fits, :func:`jaxrefl.ps.fit_normal_brdf`); :meth:`to_json` records it in
    reports and resume manifests.

    solver: :class:`LMOptions` (the lean LM, default), :class:`OptimistixLM` or
            :class:`JaxoptLM`; each carries its iteration budget and tolerances
    noise:  :class:`GaussianNoise` (default: sigma unknown, the fit uses 1) or
            :class:`ShotNoise`; robust-loss thresholds are in its units
    loss:   :class:`L2`, :class:`Huber` or :class:`Cauchy`; None (default): the entry
            point's default (:class:`L2` for :func:`fit_pixels`; the model's own for
            :class:`jaxrefl.svbrdf.FitJob`)
    dtype:  computation dtype, any form ``np.dtype`` accepts (``jnp.float32``), stored as a
            ``np.dtype``; None (default): the entry point's default (:func:`fit_pixels`:
            that of the data; :func:`fit_samples`: float64 if JAX has it enabled, else
            float32). float32 is the fast one.
    """

    kind: ClassVar[str] = "fit"
    solver: Solver = eqx.field(default_factory=LMOptions)
    noise: NoiseModel = eqx.field(default_factory=GaussianNoise)
    loss: Loss | None = None
    # Typed as what it accepts; the converter stores a ``np.dtype`` (or None).
    dtype: DTypeLike = eqx.field(default=None, static=True, converter=_as_dtype)

    def __check_init__(self):
        if self.dtype is not None and not np.issubdtype(self.dtype, np.floating):
            raise JaxreflError(f"FitConfig needs a floating dtype, got {self.dtype}")

    def replace(self, **changes: Any) -> FitConfig:
        """A copy with ``changes`` (field names as keywords)."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True, eq=False)
class Linearisation:
    """The solver's last linearisation, at the returned theta of every pixel.

    residual: the :class:`Residual` that was minimised
    jtj:      (N, P, P) J^T J of that residual at theta (the Gauss-Newton precision)
    active:   (N,) residual rows taking part there (r != 0 or a non-zero Jacobian row;
              satisfied censored and masked observations do not)

    :func:`laplace` reuses it instead of differentiating the residual again (the Jacobian is
    most of the Laplace step's cost).
    """

    residual: Residual
    jtj: Float[Array, "N P P"]
    active: Int[Array, " N"]


@dataclass(frozen=True, eq=False)
class FitResult:
    """Outcome of a fit.

    params:     natural parameters, leading axis N (pixels) for :func:`fit_pixels`; for
                :func:`fit_samples` none (joint channels) or C (channels fitted separately)
    theta:      (..., P) unconstrained vector (``space.labels`` names the entries)
    status:     (...) int32 :class:`Status` codes; ``status_counts()`` summarises them
    cost:       (...) final 1/2 |r|^2 (whitened, robust); NaN where there is no estimate
    iterations: (...) solver iterations
    n_used:     (...) usable observations (entries of the K x C grid)
    backend:    the kind of solver that ran (``"lean"``, ``"optimistix"``, ``"jaxopt"``)
    linearisation: the solver's J^T J at theta (:class:`Linearisation`), for
                :func:`laplace`; None where the result was assembled otherwise
    """

    params: dict[str, Array]
    theta: Float[Array, "*n P"]
    status: Int[Array, "*n"]
    cost: Float[Array, "*n"]
    iterations: Int[Array, "*n"]
    n_used: Int[Array, "*n"]
    space: ParamSpace
    model: BRDF
    backend: str = "lean"
    linearisation: Linearisation | None = None

    def status_counts(self) -> dict[str, int]:
        """``{"CONVERGED": ..., "MAX_ITERATIONS": ..., ...}`` (see :func:`describe`)."""
        return describe(self.status)

    @property
    def has_estimate(self) -> Array:
        """Where params are defined (not MASKED / NONFINITE_INPUT)."""
        return has_estimate(self.status)


def _theta0(res, data: PixelData, init: Any, dtype) -> Array:
    n = data.obs.shape[0]
    space = res.space
    if isinstance(init, str):
        if init == "auto":
            return initial_theta(res, data)
        if init == "defaults":
            return jnp.broadcast_to(space.default_theta(dtype), (n, space.size))
        raise JaxreflError(f"init must be 'auto', 'defaults', an array or a dict, not {init!r}")
    if isinstance(init, Mapping):
        t = space.from_natural(init, dtype=dtype)
    else:
        t = jnp.asarray(init, dtype=dtype)
    if t.shape[-1:] != (space.size,):
        raise JaxreflError(f"init theta must end in P = {space.size} {space.labels}; got {t.shape}")
    return jnp.broadcast_to(t, (n, space.size))


@eqx.filter_jit
def _data_checks(res, data):
    return res.n_usable(data), res.nonfinite_input(data)


@eqx.filter_jit
def _finalise(theta, status, cost, n_used, nonfinite, p):
    short = n_used < p
    status = jnp.where(short & nonfinite, Status.NONFINITE_INPUT, status).astype(jnp.int32)
    none = ~has_estimate(status)
    return jnp.where(none[:, None], jnp.nan, theta), status, jnp.where(none, jnp.nan, cost)


def _run(model, data, space, config, init, devices, prior):
    loss = L2() if config.loss is None else config.loss
    res = make_residual(model, space, config.noise, loss, prior)
    dtype = data.obs.dtype
    n_used, nonfinite = _data_checks(res, data)
    ndev = device_count(devices)
    if isinstance(init, str) and init == "auto":
        # The default start is per pixel too: spread it like the solver.
        theta0 = initial_theta(res, data, devices=ndev)
    else:
        theta0 = _theta0(res, data, init, dtype)

    def solve_batch(theta0, data, n_used):
        return solve(res, theta0, data, config.solver, space=space, n_usable=n_used)

    theta, info = map_sharded(solve_batch, (theta0, data, n_used), ndev)
    theta, status, cost = _finalise(theta, info.status, info.cost, n_used, nonfinite, space.size)
    lin = Linearisation(res, info.jtj, info.active)
    return theta, status, cost, info.iterations, n_used, lin


def fit_pixels(
    model: BRDF,
    data: PixelData,
    *,
    config: FitConfig = FitConfig(),
    space: ParamSpace | None = None,
    init: Init = "auto",
    bounds: Mapping[str, tuple[float, float]] | None = None,
    fixed: Mapping[str, ArrayLike] | None = None,
    devices: int | None = None,
    prior: GaussianPrior | None = None,
) -> FitResult:
    """Fit ``model`` to every pixel of ``data`` (:class:`PixelData` with a leading N axis).

    config:   solver, noise model, loss (None: :class:`L2`) and dtype (None: that of
              ``data.obs``) as a :class:`FitConfig`; the default is the lean LM, Gaussian
              noise of unknown sigma, L2
    space:    the parameter space (default ``ParamSpace(model, C, bounds, fixed)``)
    init:     ``"auto"`` (closed-form colours on a roughness grid), ``"defaults"`` (the
              model's defaults), a theta array ((P,) or (N, P)) or a dict of natural values
    prior:    a :class:`GaussianPrior` on natural parameters (MAP fit; see ``_residual``)
    devices:  how many of JAX's devices share the pixels (default all); results agree up
              to rounding (``_shard`` says how far)
    """
    if not isinstance(config, FitConfig):
        raise TypeError(f"config must be a fit.FitConfig, not {type(config).__name__}")
    if data.obs.ndim != 3:
        raise JaxreflError(f"fit_pixels expects data of shape (N, K, C); got {data.obs.shape}")
    if config.dtype is not None:
        data = data.astype(config.dtype)
    c = data.obs.shape[-1]
    if space is None:
        space = ParamSpace(model, channels=c, bounds=bounds, fixed=fixed)
    elif bounds is not None or fixed is not None:
        raise JaxreflError("give bounds/fixed through the ParamSpace when passing space")
    if space.channels != c:
        raise JaxreflError(f"space has {space.channels} channels, data has {c}")
    theta, status, cost, iters, n_used, lin = _run(model, data, space, config, init, devices, prior)
    kind = config.solver.kind
    return FitResult(
        space.to_natural(theta), theta, status, cost, iters, n_used, space, model, kind, lin
    )


def sample_arrays(
    wi: ArrayLike,
    wo: ArrayLike,
    values: ArrayLike,
    *,
    cosine: bool,
    keep: ArrayLike | None = None,
    dtype: Any = np.float64,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Measured f_r samples as the arrays of one fitting problem: ``(obs, scale, weight)``,
    each (K, C) in ``dtype`` (``scale`` is None without ``cosine``).

    wi, wo (K, 3) and values (K, C) or (K,) f_r in 1/sr, all first converted to ``dtype``.
    A sample takes part (weight 1) where both directions are above the horizon (z > 0) and
    ``keep`` (K,) allows it; weight 0 elsewhere. With ``cosine`` the observations and the
    predictions become f_r cos(theta_i) (``scale`` = cos_i, 0 where a sample does not take
    part), so the residual is (f̂ - f) cos(theta_i) (Ngan et al. 2005's cosine weighting).
    """
    wi = np.asarray(wi, dtype)
    wo = np.asarray(wo, dtype)
    obs = np.asarray(values, dtype)
    if obs.ndim == 1:
        obs = obs[:, None]
    k, c = obs.shape
    above = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    if keep is not None:
        above &= np.asarray(keep, bool)
    weight = np.broadcast_to(above[:, None], (k, c)).astype(dtype)
    scale = None
    if cosine:  # observations and predictions both become f_r cos(theta_i)
        scale = np.broadcast_to(np.where(above, wi[:, 2], 0.0)[:, None], (k, c))
        obs = obs * scale
    return obs, scale, weight


class SamplesOptions(Option):
    """How :func:`fit_samples` makes a problem of measured samples.

    channels: ``"joint"``: one problem, colour parameters per channel and shared scalars
              (results without a leading axis); ``"separate"``: every channel is its own
              problem with its own scalars (results with a leading axis C, colour
              parameters as (C,)).
    cosine:   fit f_r cos(theta_i) instead of f_r (scale = cos_i), which down-weights the
              noisy grazing samples.
    """

    kind: ClassVar[str] = "samples"
    channels: Literal["joint", "separate"] = "joint"
    cosine: bool = False

    def __check_init__(self) -> None:
        if self.channels not in ("joint", "separate"):
            raise JaxreflError(
                f"SamplesOptions.channels must be 'joint' or 'separate', not {self.channels!r}"
            )
        if not isinstance(self.cosine, bool):
            raise JaxreflError(f"SamplesOptions.cosine must be True or False, not {self.cosine!r}")


def fit_samples(
    model: BRDF,
    measured: Any,
    *,
    options: SamplesOptions | None = None,
    config: FitConfig = FitConfig(),
    space: ParamSpace | None = None,
    init: Init = "auto",
    bounds: Mapping[str, tuple[float, float]] | None = None,
    fixed: Mapping[str, ArrayLike] | None = None,
) -> FitResult:
    """Fit ``model`` to measured f_r samples: one problem with K = number of samples.

    measured: a :class:`jaxrefl.io.MeasuredBRDF` (``wi``, ``wo`` (K, 3), ``values`` (K, C)
              f_r in 1/sr) or a tuple ``(wi, wo, values)``. Non-finite values and samples at
              or below the horizon get weight 0.
    options:  the problem (:class:`SamplesOptions`: the channels joint or separate, f_r or
              f_r cos(theta_i); None: its defaults).
    config:   as for :func:`fit_pixels`; its dtype None means float64 if enabled in JAX,
              else float32.

    The other arguments are those of :func:`fit_pixels`; with the default L2 loss and
    sigma 1 the cost is in (1/sr)^2.
    """
    o = SamplesOptions() if options is None else options
    channels, cosine = o.channels, o.cosine
    if isinstance(measured, tuple):
        wi, wo, values = measured
        names = None
    else:
        wi, wo, values = measured.wi, measured.wo, measured.values
        names = tuple(measured.channels)
    dtype = jnp.asarray(0.0).dtype if config.dtype is None else np.dtype(config.dtype)
    values, scale, weight = sample_arrays(wi, wo, values, cosine=cosine, dtype=dtype)
    k, c = values.shape
    wi = jnp.asarray(wi, dtype)
    wo = jnp.asarray(wo, dtype)
    if channels == "joint":
        s1 = None if scale is None else scale[None]
        data = pixel_data(values[None], wi[None], wo[None], scale=s1, weight=weight[None])
        n_ch, ch_names = c, names
    else:  # "separate" (SamplesOptions admits no other value)
        obs = jnp.transpose(values)[..., None]  # (C, K, 1)
        data = pixel_data(
            obs,
            jnp.broadcast_to(wi, (c, k, 3)),
            jnp.broadcast_to(wo, (c, k, 3)),
            scale=None if scale is None else jnp.transpose(scale)[..., None],
            weight=jnp.transpose(weight)[..., None],
        )
        n_ch, ch_names = 1, None
    if space is None:
        if ch_names is not None and len(ch_names) != n_ch:
            ch_names = None
        space = ParamSpace(model, channels=n_ch, bounds=bounds, fixed=fixed, channel_names=ch_names)
    r = fit_pixels(model, data, config=config.replace(dtype=None), space=space, init=init)
    if channels == "joint":
        return FitResult(
            jax.tree.map(lambda x: x[0], r.params),
            r.theta[0],
            r.status[0],
            r.cost[0],
            r.iterations[0],
            r.n_used[0],
            r.space,
            model,
            r.backend,
        )
    kinds = {q.name: q.kind for q in model.params}
    params = {n: (v[:, 0] if kinds[n] == "color" else v) for n, v in r.params.items()}
    return FitResult(
        params,
        r.theta,
        r.status,
        r.cost,
        r.iterations,
        r.n_used,
        r.space,
        model,
        r.backend,
        r.linearisation,
    )

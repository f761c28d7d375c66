"""The per-pixel least-squares problem: data, noise models, robust losses, residuals.

One pixel (or one measured material) is K observations in C channels. For parameters x,

    pred_kc = f_r(x; wi_k, wo_k)_c * scale_kc                      (model.eval, 1/sr * scale)
    z_kc    = (pred_kc - obs_kc) / std_kc                           (whitening, noise model)
    r_kc    = sqrt(weight_kc) * sign(z) sqrt(2 rho(z_kc))           (robust loss, weights)
    cost    = 1/2 sum r^2 = sum_kc weight_kc rho(z_kc)

``scale`` turns f_r into what was observed: for a flash capture (light and camera together)
it is irradiance * cos(theta_i) (radiance = f_r E cos_i), for measured f_r samples it is 1.
Censored observations (``censored`` = +1: the sensor saturated, the true value is >= obs;
-1: clipped dark, the true value is <= obs) contribute only when the prediction is on the
wrong side: z is set to 0 where pred >= obs (saturated) or pred <= obs (dark). This is the
one-sided (hinge) residual of a Tobit-style likelihood's mode, keeping the problem a least
squares problem. Censored observations count as usable in :meth:`Residual.n_usable`.

A :class:`GaussianPrior` on some natural parameters appends (x_j - mean_j) / std_j to r
(in the whitened units of the data, so give the noise scale when using one): the least
squares optimum is then the MAP estimate, and J^T J the Laplace precision of the posterior.

Defensive masking: an observation is usable only where obs, scale, weight and both
directions are finite and weight > 0; everything else is swapped for harmless values
*before* any arithmetic (gradient-safe), so one NaN never poisons a pixel's residual or its
Jacobian. Callers should still zero-weight bad observations themselves.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF

from ._options import Option, check_number
from ._transform import ParamSpace

__all__ = [
    "L2",
    "Cauchy",
    "GaussianNoise",
    "GaussianPrior",
    "Huber",
    "LevelNoise",
    "Loss",
    "NoiseModel",
    "PixelData",
    "Residual",
    "ShotNoise",
    "gaussian_prior",
    "make_residual",
    "pixel_data",
    "replace_params",
]


class PixelData(eqx.Module):
    """Observations of one pixel (fields as below) or of N pixels (a leading N axis on every
    field). Build it with :func:`pixel_data`, which fills defaults and checks shapes.

    obs:      (K, C) observed linear radiance (or f_r values for measured BRDF samples)
    wi, wo:   (K, 3) unit directions in the local frame, away from the surface
    scale:    (K, C) factor such that prediction = model.eval(params, wi, wo) * scale
    weight:   (K, C) >= 0; 0 masks an observation out
    censored: (K, C) int8; 0 none, +1 saturated (true >= obs), -1 dark-clipped (true <= obs)
    colocated: static flag, True when wo == wi for every observation (a flash capture with
              the light at the camera). The residual then evaluates ``model.eval(p, wi, wi)``
              so the compiler can share the wi and wo halves of the BRDF (each
              direction-dependent term is computed once).
    """

    obs: Float[Array, "*n K C"]
    wi: Float[Array, "*n K 3"]
    wo: Float[Array, "*n K 3"]
    scale: Float[Array, "*n K C"]
    weight: Float[Array, "*n K C"]
    censored: Int[Array, "*n K C"]
    colocated: bool = eqx.field(default=False, static=True)

    @property
    def shape(self) -> tuple[int, ...]:
        """(*n, K, C)."""
        return tuple(self.obs.shape)

    def astype(self, dtype) -> PixelData:
        """The same data with floating fields cast to ``dtype``."""
        return PixelData(
            self.obs.astype(dtype),
            self.wi.astype(dtype),
            self.wo.astype(dtype),
            self.scale.astype(dtype),
            self.weight.astype(dtype),
            self.censored,
            self.colocated,
        )


def pixel_data(
    obs: ArrayLike,
    wi: ArrayLike,
    wo: ArrayLike | None = None,
    scale: ArrayLike | None = None,
    weight: ArrayLike | None = None,
    censored: ArrayLike | None = None,
    dtype=None,
) -> PixelData:
    """Build :class:`PixelData`, broadcasting ``scale`` (default 1), ``weight`` (default 1)
    and ``censored`` (default 0) to the shape of ``obs`` ((*n, K, C)); ``wi``/``wo`` are
    broadcast to (*n, K, 3). ``wo=None`` (or ``wo is wi``) means co-located light and view:
    wo = wi and ``colocated=True``. ``dtype`` defaults to the dtype of ``obs`` (float32 if it
    is not floating).

    Refused with a ValueError naming the argument: an argument that does not broadcast to
    its shape; a non-finite ``scale``; finite ``wi``/``wo`` that are not unit vectors
    (within 1e-3) where the observation has weight. Non-finite directions and observations
    are kept: the residual drops them and reports them as non-finite input. Value checks
    are skipped for traced arrays (inside ``jax.jit``)."""
    colocated = wo is None or wo is wi
    obs = jnp.asarray(obs)
    if dtype is None:
        dtype = obs.dtype if jnp.issubdtype(obs.dtype, jnp.floating) else jnp.float32
    obs = obs.astype(dtype)
    if obs.ndim < 2:
        raise JaxreflError(f"obs must have shape (*n, K, C), got {obs.shape}")
    lead = obs.shape[:-1]

    def lift(v, shape, name):
        if v.ndim > len(shape):
            raise JaxreflError(
                f"{name} has shape {v.shape}, more axes than {shape} (obs is (*n, K, C))"
            )
        try:
            return jnp.broadcast_to(v.reshape((1,) * (len(shape) - v.ndim) + v.shape), shape)
        except ValueError:
            raise JaxreflError(
                f"{name} has shape {v.shape}, which does not broadcast to {shape} "
                "(obs is (*n, K, C))"
            ) from None

    def full(v, default, name):
        return lift(jnp.asarray(default if v is None else v, dtype=dtype), obs.shape, name)

    def direction(w, name):
        w = jnp.asarray(w, dtype=dtype)
        if w.shape[-1:] != (3,):
            raise JaxreflError(f"{name} must have a trailing axis of 3, got {w.shape}")
        return lift(w, (*lead, 3), name)

    cens = jnp.zeros(obs.shape, jnp.int8) if censored is None else jnp.asarray(censored)
    cens = lift(cens.astype(jnp.int8), obs.shape, "censored")
    wi_b = direction(wi, "wi")
    wo_b = wi_b if colocated else direction(wo, "wo")
    scale_b, weight_b = full(scale, 1.0, "scale"), full(weight, 1.0, "weight")
    if _concrete(scale_b) and not bool(jnp.all(jnp.isfinite(scale_b))):
        raise JaxreflError(
            "scale holds a non-finite value; give finite scales (weight 0 drops an observation)"
        )
    for name, w in (("wi", wi_b), ("wo", None if colocated else wo_b)):
        if w is not None and _concrete(w) and _concrete(weight_b):
            _check_unit(name, w, weight_b)
    return PixelData(obs, wi_b, wo_b, scale_b, weight_b, cens, colocated)


# Largest accepted | |w| - 1 | of a direction given to :func:`pixel_data`.
_UNIT_TOL = 1e-3


def _concrete(a) -> bool:
    """Whether ``a`` holds values (not a JAX tracer inside a transformation)."""
    return not isinstance(a, jax.core.Tracer)


def _check_unit(name: str, w: Array, weight: Array) -> None:
    """Refuse finite directions off unit length where an observation has weight."""
    w64 = np.asarray(w, np.float64)
    used = np.any(np.asarray(weight) != 0, axis=-1)  # (*n, K)
    norm = np.sqrt(np.sum(w64 * w64, axis=-1))
    off = np.where(used & np.isfinite(norm), np.abs(norm - 1.0), 0.0)
    if off.size and np.max(off) > _UNIT_TOL:
        i = np.unravel_index(int(np.argmax(off)), off.shape)
        raise JaxreflError(
            f"{name} must be unit vectors (|{name}| = 1 within {_UNIT_TOL:g}); the worst, at "
            f"index {tuple(int(j) for j in i)}, has length {norm[i]:.6g}"
        )


# ---------------------------------------------------------------------------- noise models
class NoiseModel(Option):
    """Standard deviation of each observation, used to whiten residuals."""

    def std(self, obs: Float[Array, "K C"]) -> Float[Array, "K C"]:
        raise NotImplementedError

    @property
    def scale_unknown(self) -> bool:
        """Whether ``std`` is known only up to a common factor s per problem (pixel), which
        the Laplace step estimates from the residuals and a posterior samples (Jeffreys)."""
        return False

    def with_scale(self, sigma: float | Array) -> NoiseModel:
        """The known noise model whose std is ``sigma`` times this one's (for a scale that
        is estimated once and then held fixed, e.g. a prior in units of the noise)."""
        raise JaxreflError(f"{type(self).__name__} has a known scale: nothing to set")


def _lift(v: Array, like: Array) -> Array:
    return jnp.broadcast_to(v.reshape((1,) * (like.ndim - v.ndim) + v.shape), like.shape)


class GaussianNoise(NoiseModel):
    """Additive Gaussian noise of standard deviation ``sigma`` (scalar or per channel (C,)).

    ``sigma=None`` means unknown: the fit uses sigma = 1 (the optimum of an L2 fit does not
    depend on a common sigma) and sigma can be estimated afterwards from the residuals
    (:func:`jaxrefl.fit.laplace` with ``LaplaceOptions(noise="estimate")``). Robust-loss
    thresholds are in units of sigma, so give sigma when using Huber or Cauchy.

    sigma: noise std in the units of the observations, > 0 and finite (a number, or an
           array of one per channel (C,)); default None (unknown)
    """

    kind: ClassVar[str] = "gaussian"
    sigma: float | Array | None = None

    def __check_init__(self):
        check_number("GaussianNoise", "sigma", self.sigma, positive=True)

    def std(self, obs):
        if self.sigma is None:
            return jnp.ones_like(obs)
        return _lift(jnp.asarray(self.sigma, dtype=obs.dtype), obs)

    @property
    def scale_unknown(self) -> bool:
        return self.sigma is None

    def with_scale(self, sigma):
        if self.sigma is not None:
            return super().with_scale(sigma)
        return GaussianNoise(sigma=sigma)


class ShotNoise(NoiseModel):
    """Photon (shot) plus read noise: variance = read^2 + gain * max(obs, 0).

    The variance is computed from the *observations*, not from the prediction, and stays
    fixed during the fit: the problem remains a plain weighted least squares (a variance
    that moves with the prediction adds a log-determinant term and a second, competing
    gradient, and lets the solver "explain" residuals by inflating the predicted variance).
    For well-exposed pixels obs ~ pred, so the two differ by O(1/sqrt(counts)).

    read: read-noise std in the units of obs, finite and > 0 (it keeps the variance positive
          at obs <= 0); a number or one per channel (C,); default 0.01
    gain: units of obs per photo-electron, finite and >= 0; default 0
    """

    kind: ClassVar[str] = "shot"
    read: float | Array = 0.01
    gain: float | Array = 0.0

    def __check_init__(self):
        check_number("ShotNoise", "read", self.read, positive=True, why="the variance at obs = 0")
        check_number("ShotNoise", "gain", self.gain)

    def std(self, obs):
        read = _lift(jnp.asarray(self.read, dtype=obs.dtype), obs)
        gain = _lift(jnp.asarray(self.gain, dtype=obs.dtype), obs)
        var = read * read + gain * jnp.maximum(obs, 0.0)
        # Floor at the dtype's smallest normal: only a traced read = 0 reaches it.
        return jnp.sqrt(jnp.maximum(var, jnp.finfo(obs.dtype).tiny))


class LevelNoise(NoiseModel):
    """A noise-level function of unknown scale: std = s sqrt(1 + gain y + (rel y)^2),
    y = max(obs, 0), with s unknown per problem (pixel) unless ``scale`` is given.

    The brightness dependence of a camera's noise (Liu et al., "Automatic estimation and
    removal of noise from a single image", IEEE TPAMI 30(2), 2008, call it the noise level
    function): photon noise adds variance in proportion to the signal (``gain``), and what
    scales with the signal itself (flat-field, tone-curve and JPEG errors, a misfit that
    grows with the highlight) adds std in proportion to it (``rel``). The 1 is the floor
    (read noise), in units of which gain (1 / obs) and rel (1 / obs) are given; s carries
    the absolute level, so a capture-wide shape serves pixels of any noise level. As for
    :class:`ShotNoise`, the std is computed from the observations and fixed during a fit.
    :func:`jaxrefl.svbrdf.estimate_noise_level` estimates the shape from a capture's
    residuals. gain = rel = 0 is :class:`GaussianNoise`.

    gain:  variance per unit of y, in floor variances, finite and >= 0; default 0
    rel:   std per unit of y, in floor stds, finite and >= 0; default 0
    scale: s when known (a number > 0), None (default): unknown, estimated per problem
    """

    kind: ClassVar[str] = "level"
    gain: float | Array = 0.0
    rel: float | Array = 0.0
    scale: float | Array | None = None

    def __check_init__(self):
        check_number("LevelNoise", "gain", self.gain)
        check_number("LevelNoise", "rel", self.rel)
        check_number("LevelNoise", "scale", self.scale, positive=True)

    def std(self, obs):
        y = jnp.maximum(obs, 0.0)  # the sensor's dark level: no negative signal
        gain = _lift(jnp.asarray(self.gain, dtype=obs.dtype), obs)
        rel = _lift(jnp.asarray(self.rel, dtype=obs.dtype), obs)
        shape = jnp.sqrt(1.0 + gain * y + (rel * y) ** 2)
        if self.scale is None:
            return shape
        return shape * _lift(jnp.asarray(self.scale, dtype=obs.dtype), obs)

    @property
    def scale_unknown(self) -> bool:
        return self.scale is None

    def with_scale(self, sigma):
        if self.scale is not None:
            return super().with_scale(sigma)
        return LevelNoise(gain=self.gain, rel=self.rel, scale=sigma)


# ---------------------------------------------------------------------------- robust losses
class Loss(Option):
    """A robust loss rho(z) on whitened residuals, applied as r = sign(z) sqrt(2 rho(z))."""

    def rho(self, z: Float[Array, "*b"]) -> Float[Array, "*b"]:
        raise NotImplementedError

    def residual(self, z: Float[Array, "*b"]) -> Float[Array, "*b"]:
        """sign(z) sqrt(2 rho(z)), written so that it and its derivative are finite at 0."""
        raise NotImplementedError


class L2(Loss):
    """rho(z) = z^2 / 2: ordinary least squares (r = z)."""

    kind: ClassVar[str] = "l2"

    def rho(self, z):
        return 0.5 * z * z

    def residual(self, z):
        return z


class Huber(Loss):
    """rho(z) = z^2/2 for |z| <= delta, delta (|z| - delta/2) beyond (Huber 1964).

    r = z inside, sign(z) sqrt(2 delta |z| - delta^2) outside: quadratic near 0, the cost
    grows linearly beyond delta (r grows like sqrt|z|).

    delta: threshold in units of the noise std (whitened residual), > 0; default 1
    """

    kind: ClassVar[str] = "huber"
    delta: float = 1.0

    def __check_init__(self):
        check_number("Huber", "delta", self.delta, positive=True)

    def rho(self, z):
        a = jnp.abs(z)
        return jnp.where(a <= self.delta, 0.5 * z * z, self.delta * (a - 0.5 * self.delta))

    def residual(self, z):
        a = jnp.abs(z)
        inside = a <= self.delta
        # Gradient-safe: the outer branch is evaluated at |z| >= delta only (sqrt arg >= delta^2).
        a_out = jnp.where(inside, self.delta, a)
        outer = jnp.sign(z) * jnp.sqrt(2.0 * self.delta * a_out - self.delta * self.delta)
        return jnp.where(inside, z, outer)


class Cauchy(Loss):
    """rho(z) = c^2/2 log(1 + (z/c)^2) (Cauchy / Lorentzian loss).

    r = z sqrt(log1p(t)/t) with t = (z/c)^2, equal to sign(z) c sqrt(log1p(t)); the ratio
    log1p(t)/t -> 1 - t/2 is used for tiny t, so r and dr/dz are finite at z = 0.

    c: scale in units of the noise std (whitened residual), > 0; default 1
    """

    kind: ClassVar[str] = "cauchy"
    c: float = 1.0

    def __check_init__(self):
        check_number("Cauchy", "c", self.c, positive=True)

    def rho(self, z):
        return 0.5 * self.c * self.c * jnp.log1p((z / self.c) ** 2)

    def residual(self, z):
        t = (z / self.c) ** 2
        # Below 1e-6 the series 1 - t/2 is exact to O(t^2) ~ 1e-12 and avoids 0/0 at z = 0.
        small = t < 1e-6
        t_safe = jnp.where(small, 1.0, t)
        ratio = jnp.where(small, 1.0 - 0.5 * t, jnp.log1p(t_safe) / t_safe)
        return z * jnp.sqrt(ratio)


# ---------------------------------------------------------------------------- priors
class GaussianPrior(eqx.Module):
    """Independent Gaussian priors x_j ~ N(mean_j, std_j^2) on natural-vector entries
    ``index`` of a :class:`ParamSpace` (:func:`gaussian_prior` builds one by label)."""

    index: tuple[int, ...] = eqx.field(static=True)
    mean: Float[Array, " J"]
    std: Float[Array, " J"]

    def residual(self, natural: Float[Array, " P"]) -> Float[Array, " J"]:
        idx = jnp.asarray(self.index)
        return (natural[idx] - self.mean.astype(natural.dtype)) / self.std.astype(natural.dtype)


def gaussian_prior(space: ParamSpace, priors: dict[str, tuple[float, float]]) -> GaussianPrior:
    """A :class:`GaussianPrior` from ``{label: (mean, std)}`` (labels of ``space.labels``,
    natural units; std > 0)."""
    labels = space.labels
    bad = [k for k in priors if k not in labels]
    if bad:
        raise KeyError(f"no free parameters {bad} in the space; it has {labels}")
    for k, (_, sd) in priors.items():
        if not sd > 0:
            raise JaxreflError(f"prior std of {k!r} must be > 0, got {sd}")
    keys = list(priors)
    return GaussianPrior(
        tuple(labels.index(k) for k in keys),
        jnp.asarray([float(priors[k][0]) for k in keys]),
        jnp.asarray([float(priors[k][1]) for k in keys]),
    )


# ---------------------------------------------------------------------------- residual
def replace_params(params: dict[str, Array], replace: Mapping[str, Array]) -> dict[str, Array]:
    """``params`` with the named entries swapped for ``replace``'s (broadcast, same dtype)."""
    out = dict(params)
    for name, v in replace.items():
        if name not in out:
            raise KeyError(f"replace: {name!r} is not a parameter of the model ({tuple(out)})")
        old = out[name]
        out[name] = jnp.broadcast_to(jnp.asarray(v, old.dtype), old.shape)
    return out


class Residual(eqx.Module):
    """r(theta, data): the whitened, weighted, censored, robust residual of one pixel.

    Call with theta (P,) and unbatched :class:`PixelData` ((K, C) fields); returns (K*C,),
    ordered k-major (entry k*C + c), followed by the J entries of ``prior`` if there is one.
    """

    model: BRDF
    space: ParamSpace
    noise: NoiseModel
    loss: Loss
    prior: GaussianPrior | None = None

    def usable(self, data: PixelData) -> Bool[Array, "*n K C"]:
        """Observations that take part: finite inputs and weight > 0."""
        row_ok = jnp.all(jnp.isfinite(data.wi) & jnp.isfinite(data.wo), axis=-1)
        ok = jnp.isfinite(data.obs) & jnp.isfinite(data.scale) & jnp.isfinite(data.weight)
        return ok & (data.weight > 0) & row_ok[..., None]

    def n_usable(self, data: PixelData) -> Int[Array, "*n"]:
        """Number of usable observations (entries of the (K, C) grid) per pixel."""
        return jnp.sum(self.usable(data), axis=(-2, -1))

    def nonfinite_input(self, data: PixelData) -> Bool[Array, "*n"]:
        """Whether a pixel has a non-finite value in an observation that was not already
        masked by weight 0 (it is masked here; this says the caller did not do it)."""
        row_bad = ~jnp.all(jnp.isfinite(data.wi) & jnp.isfinite(data.wo), axis=-1)
        bad = ~(jnp.isfinite(data.obs) & jnp.isfinite(data.scale)) | row_bad[..., None]
        bad = (bad & (data.weight != 0)) | ~jnp.isfinite(data.weight)
        return jnp.any(bad, axis=(-2, -1))

    def predict(
        self,
        theta: Float[Array, " P"],
        data: PixelData,
        replace: Mapping[str, Array] | None = None,
    ) -> Float[Array, "K C"]:
        """model.eval(params, wi, wo) * scale with unusable observations swapped out;
        ``replace`` overrides natural parameters by name (e.g. ``{"albedo": zeros}``)."""
        ok = self.usable(data)
        row_ok = jnp.all(jnp.isfinite(data.wi) & jnp.isfinite(data.wo), axis=-1)
        up = jnp.asarray([0.0, 0.0, 1.0], dtype=theta.dtype)
        # Gradient-safe: non-finite directions are replaced by the normal before evaluation.
        wi = jnp.where(row_ok[..., None], data.wi.astype(theta.dtype), up)
        wo = wi if data.colocated else jnp.where(row_ok[..., None], data.wo.astype(theta.dtype), up)
        scale = jnp.where(ok, data.scale.astype(theta.dtype), 0.0)
        # Parameters get a leading unit axis so they align with the (K, 3) directions
        # without implicit rank promotion.
        params = self.space.to_natural(theta[None, :])
        if replace:
            params = replace_params(params, replace)
        return self.model.eval(params, wi, wo) * scale

    def __call__(self, theta: Float[Array, " P"], data: PixelData) -> Float[Array, " KC"]:
        dtype = theta.dtype
        ok = self.usable(data)
        obs = jnp.where(ok, data.obs.astype(dtype), 0.0)
        w = jnp.where(ok, data.weight.astype(dtype), 0.0)
        pred = self.predict(theta, data)
        z = (pred - obs) / self.noise.std(obs)
        sat = data.censored > 0
        dark = data.censored < 0
        # One-sided residuals of censored observations (see the module docstring).
        z = jnp.where((sat & (pred >= obs)) | (dark & (pred <= obs)), 0.0, z)
        r = (jnp.sqrt(w) * self.loss.residual(z)).reshape(-1)
        if self.prior is None:
            return r
        return jnp.concatenate([r, self.prior.residual(self.space.natural_vector(theta))])


def make_residual(
    model: BRDF,
    space: ParamSpace | None = None,
    noise: NoiseModel | None = None,
    loss: Loss | None = None,
    prior: GaussianPrior | None = None,
) -> Residual:
    """The residual function ``r(theta (P,), data: PixelData (unbatched)) -> (K*C [+ J],)``.

    Defaults: ``ParamSpace(model)`` (3 channels), ``GaussianNoise()`` (sigma 1), ``L2()``,
    no prior.
    """
    return Residual(
        model,
        ParamSpace(model) if space is None else space,
        GaussianNoise() if noise is None else noise,
        L2() if loss is None else loss,
        prior,
    )

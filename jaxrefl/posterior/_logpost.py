"""The log-posterior of one pixel (or one measured material) in unconstrained coordinates.

Built from the same parts as fitting (:mod:`jaxrefl.fit`): the model and its
:class:`~jaxrefl.fit.ParamSpace` (bijections x = g(theta)), :class:`~jaxrefl.fit.PixelData`
and a noise model (:class:`~jaxrefl.fit.GaussianNoise`, :class:`~jaxrefl.fit.ShotNoise`).
The unconstrained vector is

    theta = [theta_brdf (P),  u (3, if the light direction is sampled),  log s (1, if the
             noise scale is unknown)]

and, with pred_kc the prediction of :class:`~jaxrefl.fit.Residual` (f_r * scale) and
sd_kc = s * noise.std(obs_kc), the log density is

    log p(theta | y) = sum_b [log prior_b(g(theta_b)) + log |dg/dtheta_b|]         (priors)
                     + log p_light(u) + log prior_s(s) + log s                      (extras)
                     + sum_{uncensored} w_kc [-rho(z_kc) - log sd_kc]               (values)
                     + sum_{saturated} w_kc log Phi(z_kc)                            (y >= obs)
                     + sum_{dark} w_kc log Phi(-z_kc)                                (y <= obs)

with z = (pred - obs) / sd and rho the fit's loss (L2: z^2 / 2, the Gaussian; Huber and
Cauchy give the corresponding heavy-tailed likelihoods). Censored observations get the
exact Tobit likelihood here (the probability of exceeding the recorded bound), where the
least-squares fit uses its one-sided residual. ``weight`` acts as a likelihood power (0
masks an observation out), as in the fit.

Light direction (``light=``): the direction is a point on the sphere
(:class:`~jaxrefl.posterior.SphereDirection`, u unconstrained). Then the data's ``wi`` is
ignored: call with world-frame ``normals`` (K, 3) per observation, ``data.wo`` in the world
frame, and ``data.scale`` the irradiance *without* the cosine; the prediction is
f_r(wi, wo) max(cos theta_i, 0) scale with wi = l and wo carried into each normal's frame
(isotropic models only care about the relative azimuth, so any tangent frame serves).
:class:`SharedLight` is the posterior of N pixels sharing one light.

Unknown Gaussian noise scale (``noise_scale=``): sd = s * noise.std, s > 0 sampled as log s
with prior ``noise_scale`` (default :class:`~jaxrefl.posterior.Jeffreys` when the noise
model's scale is unknown: ``GaussianNoise(sigma=None)``, ``LevelNoise(scale=None)``).

Cost: log Phi (``log_ndtr``, an erfc with an asymptotic branch) is most of a gradient's
cost where it is evaluated on every observation. The censored terms go through one log Phi
on a selected argument (not one per side), and :meth:`LogPosterior.for_data` gives the
samplers a copy without the censored branch for data that have no censored observation
(``benchmarks/posterior_speed.py --only-gradient`` times one gradient with and without it).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import log_ndtr
from jaxtyping import Array, Float

from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF
from jaxrefl.fit import (
    Bijection,
    Exp,
    Identity,
    Loss,
    NoiseModel,
    ParamSpace,
    PixelData,
    Residual,
    ScaledSigmoid,
    Softplus,
    make_residual,
    replace_params,
)
from jaxrefl.scene import orthonormal_basis, to_local

from ._priors import Jeffreys, MultivariateNormal, Prior, resolve_priors
from ._sphere import SphereDirection

__all__ = ["LogPosterior", "SharedLight", "log_posterior"]


class LogPosterior(eqx.Module):
    """log p(theta | data) of one pixel (module docstring); build with :func:`log_posterior`.

    Call ``lp(theta (D,), data (unbatched PixelData), normals=None) -> scalar``.
    """

    residual: Residual
    priors: tuple[Prior, ...]  # one per block of residual.space, in block order
    light: SphereDirection | None
    noise_scale: Prior | None
    # False only in a copy made by :meth:`for_data` for data without censored observations:
    # the censored branch (log Phi on every observation) is then left out of the graph.
    censoring: bool = eqx.field(default=True, static=True)

    def for_data(self, data: PixelData) -> LogPosterior:
        """This posterior specialised to ``data`` (concrete arrays): without the censored
        branch where no observation is censored, else unchanged. Same values either way."""
        try:
            any_censored = bool(np.any(np.asarray(data.censored) != 0))
        except jax.errors.TracerArrayConversionError:  # traced data: keep the general graph
            return self
        return dataclasses.replace(self, censoring=any_censored)

    @property
    def space(self) -> ParamSpace:
        return self.residual.space

    @property
    def model(self) -> BRDF:
        return self.residual.model

    @property
    def size(self) -> int:
        """D, the length of theta."""
        extra = (3 if self.light is not None else 0) + (self.noise_scale is not None)
        return self.space.size + extra

    @property
    def labels(self) -> tuple[str, ...]:
        """Names of the *natural* quantities of :meth:`natural` (D of them)."""
        out = list(self.space.labels)
        if self.light is not None:
            out += list(SphereDirection.labels)
        if self.noise_scale is not None:
            out.append("noise_scale")
        return tuple(out)

    def split(self, theta: Float[Array, "*b D"]):
        """(theta_brdf (*b, P), u (*b, 3) or None, log s (*b,) or None)."""
        p = self.space.size
        u = theta[..., p : p + 3] if self.light is not None else None
        log_s = theta[..., -1] if self.noise_scale is not None else None
        return theta[..., :p], u, log_s

    def natural(self, theta: Float[Array, "*b D"]) -> Float[Array, "*b D"]:
        """Natural values in the order of :attr:`labels` (light as a unit vector)."""
        tb, u, log_s = self.split(theta)
        parts = [self.space.natural_vector(tb)]
        if u is not None and self.light is not None:
            parts.append(self.light.direction(u))
        if log_s is not None:
            parts.append(jnp.exp(log_s)[..., None])
        return jnp.concatenate(parts, axis=-1)

    def log_prior(self, theta: Float[Array, " D"]) -> Float[Array, ""]:
        """Log prior density of theta, Jacobians of the bijections included."""
        tb, u, log_s = self.split(theta)
        x = self.space.natural_vector(tb)
        total = jnp.zeros((), theta.dtype)
        for blk in self.space.blocks:
            for r in blk.runs:
                total = total + jnp.sum(_log_dforward(r.bijection, tb[r.start : r.stop]))
        # A prior in units of the noise (MultivariateNormal.noise_ref) takes the scale s
        # (1 where the noise is known).
        s = jnp.ones((), theta.dtype) if log_s is None else jnp.exp(log_s)
        for blk, prior in zip(self.space.blocks, self.priors, strict=True):
            xb = x[blk.start : blk.stop]
            if isinstance(prior, MultivariateNormal) and prior.noise_ref is not None:
                total = total + jnp.sum(prior.log_prob_scaled(xb, s))
            else:
                total = total + jnp.sum(prior.log_prob(xb))
        if u is not None and self.light is not None:
            total = total + self.light.log_density(u)
        if log_s is not None and self.noise_scale is not None:
            total = total + self.noise_scale.log_prob(jnp.exp(log_s)) + log_s
        return total

    def predict(
        self,
        theta: Float[Array, " D"],
        data: PixelData,
        normals: Array | None = None,
        replace: Mapping[str, Array] | None = None,
    ) -> Float[Array, "K C"]:
        """The predicted observations (K, C) at theta; ``replace`` overrides natural
        parameters by name (as in :meth:`jaxrefl.fit.Residual.predict`)."""
        tb, u, _ = self.split(theta)
        if u is None or self.light is None:
            return self.residual.predict(tb, data, replace)
        if normals is None:
            raise JaxreflError("a posterior over the light direction needs normals (K, 3)")
        dtype = theta.dtype
        n = jnp.asarray(normals, dtype)
        l = self.light.direction(u)
        t, b = orthonormal_basis(n)
        wi = to_local(jnp.broadcast_to(l, n.shape), n, t, b)
        wo = to_local(data.wo.astype(dtype), n, t, b)
        ok = self.residual.usable(data)
        scale = jnp.where(ok, data.scale.astype(dtype), 0.0)
        params = self.space.to_natural(tb[None, :])
        if replace:
            params = replace_params(params, replace)
        return self.model.eval_cos(params, wi, wo) * scale

    def log_likelihood(
        self,
        theta: Float[Array, " D"],
        data: PixelData,
        normals: Array | None = None,
        pred: Array | None = None,
    ) -> Float[Array, ""]:
        """log p(data | theta) (module docstring); ``pred``: :meth:`predict` at theta where
        the caller already has it."""
        return jnp.sum(self.pointwise_log_likelihood(theta, data, normals, pred))

    def pointwise_log_likelihood(
        self,
        theta: Float[Array, " D"],
        data: PixelData,
        normals: Array | None = None,
        pred: Array | None = None,
    ) -> Float[Array, "K C"]:
        """The terms of :meth:`log_likelihood`, one per observation (K, C): w_kc times its
        value or censored term (module docstring); 0 where masked out."""
        _, _, log_s = self.split(theta)
        dtype = theta.dtype
        ok = self.residual.usable(data)
        obs = jnp.where(ok, data.obs.astype(dtype), 0.0)
        w = jnp.where(ok, data.weight.astype(dtype), 0.0)
        if pred is None:
            pred = self.predict(theta, data, normals)
        sd = self.residual.noise.std(obs)
        if log_s is not None:
            sd = sd * jnp.exp(log_s)
        z = (pred - obs) / sd
        sat = data.censored > 0
        dark = data.censored < 0
        value = -self.residual.loss.rho(z) - jnp.log(sd)
        if not self.censoring:  # for_data saw no censored observation
            return w * value
        # One log Phi for both sides: log Phi(z) where saturated, log Phi(-z) where dark.
        ll = jnp.where(sat | dark, log_ndtr(jnp.where(sat, z, -z)), value)
        return w * ll

    def __call__(
        self, theta: Float[Array, " D"], data: PixelData, normals: Array | None = None
    ) -> Float[Array, ""]:
        lp = self.log_prior(theta) + self.log_likelihood(theta, data, normals)
        # NaN (a non-finite prediction) becomes -inf: a rejected proposal, never a crash.
        return jnp.where(jnp.isnan(lp), -jnp.inf, lp)

    def init_theta(
        self,
        theta_brdf: Float[Array, "*b P"],
        light: Array | None = None,
        noise_scale: Array | float | None = None,
    ) -> Float[Array, "*b D"]:
        """theta from a fit's theta (e.g. the LM optimum), a light direction and a scale.

        Bounded parameters start off their bounds (:meth:`ParamSpace.off_bounds`): a
        sampler's warm-up needs a usable gradient scale where it starts."""
        tb = self.space.off_bounds(theta_brdf)
        batch = tb.shape[:-1]
        parts = [tb]
        if self.light is not None:
            l0 = self.light.prior.mu if light is None else light
            parts.append(jnp.broadcast_to(self.light.init(jnp.asarray(l0, tb.dtype)), (*batch, 3)))
        if self.noise_scale is not None:
            s0 = 1.0 if noise_scale is None else noise_scale
            parts.append(jnp.broadcast_to(jnp.log(jnp.asarray(s0, tb.dtype)), batch)[..., None])
        return jnp.concatenate(parts, axis=-1)


def _log_dforward(bij: Bijection, u: Array) -> Array:
    """log |dx/du| of an elementwise bijection, in closed form where the product would
    underflow (a logistic's s (1 - s) is 0 in float32 beyond |u| ~ 88)."""
    if isinstance(bij, Identity):
        return jnp.zeros_like(u)
    if isinstance(bij, Exp):
        return u
    if isinstance(bij, Softplus):
        return jax.nn.log_sigmoid(u)
    if isinstance(bij, ScaledSigmoid):
        return jnp.log(bij.upper - bij.lower) + jax.nn.log_sigmoid(u) + jax.nn.log_sigmoid(-u)
    return jnp.log(jnp.abs(bij.dforward(u)))


def log_posterior(
    model: BRDF,
    space: ParamSpace | None = None,
    noise: NoiseModel | None = None,
    loss: Loss | None = None,
    priors: Mapping[str, Prior] | None = None,
    *,
    light: SphereDirection | None = None,
    noise_scale: Prior | str | None = "auto",
) -> LogPosterior:
    """The :class:`LogPosterior` of ``model`` (module docstring).

    space:       the fit's parameter space (default ``ParamSpace(model)``, 3 channels)
    noise, loss: as in :func:`jaxrefl.fit.make_residual` (default Gaussian sigma 1, L2)
    priors:      by parameter name; the others get :func:`default_priors`
    light:       a :class:`SphereDirection` to sample the light direction, else None
    noise_scale: prior of an unknown noise scale s, None for a known noise model;
                 ``"auto"``: :class:`Jeffreys` if ``noise``'s scale is unknown
                 (``GaussianNoise(sigma=None)``, the fit's default, or a
                 :class:`~jaxrefl.fit.LevelNoise` without a scale), else known
    """
    res = make_residual(model, space, noise, loss)
    if not res.space.elementwise:
        raise JaxreflError(
            "log_posterior needs elementwise bijections; sample directions via light="
        )
    pri = resolve_priors(res.space, priors)
    if isinstance(noise_scale, str):
        if noise_scale != "auto":
            raise JaxreflError(f"noise_scale must be a Prior, None or 'auto', not {noise_scale!r}")
        noise_scale = Jeffreys() if res.noise.scale_unknown else None
    return LogPosterior(res, tuple(pri[b.name] for b in res.space.blocks), light, noise_scale)


class SharedLight(eqx.Module):
    """N pixels with their own BRDF parameters and one light direction they all share.

    theta = [u (3), theta_1 (P'), ..., theta_N (P')] with P' the per-pixel length of
    ``pixel`` (a :class:`LogPosterior` with ``light`` set: its u entries are taken from the
    shared ones). Call ``lp(theta (3 + N P'), data (N, K, C), normals (N, K, 3))``.
    """

    pixel: LogPosterior
    n_pixels: int = eqx.field(static=True)

    def __check_init__(self):
        if self.pixel.light is None:
            raise JaxreflError("SharedLight needs a pixel posterior with light= set")

    @property
    def per_pixel(self) -> int:
        return self.pixel.size - 3

    def for_data(self, data: PixelData) -> SharedLight:
        """:meth:`LogPosterior.for_data` of the pixel posterior."""
        return dataclasses.replace(self, pixel=self.pixel.for_data(data))

    @property
    def size(self) -> int:
        return 3 + self.n_pixels * self.per_pixel

    def expand(self, theta: Float[Array, " D"]) -> Float[Array, "N Dp"]:
        """Each pixel's full theta (with the shared u inserted)."""
        u = theta[:3]
        rest = theta[3:].reshape(self.n_pixels, self.per_pixel)
        p = self.pixel.space.size
        ub = jnp.broadcast_to(u, (self.n_pixels, 3))
        return jnp.concatenate([rest[:, :p], ub, rest[:, p:]], axis=-1)

    def __call__(self, theta, data: PixelData, normals) -> Float[Array, ""]:
        light = self.pixel.light
        assert light is not None
        full = self.expand(theta)
        u = theta[:3]

        def one(t, d, n):
            # Each pixel's prior without the light's (counted once below).
            p = self.pixel.space.size
            return self.pixel(t, d, n) - light.log_density(t[p : p + 3])

        lp = jnp.sum(jax.vmap(one)(full, data, normals)) + light.log_density(u)
        return jnp.where(jnp.isnan(lp), -jnp.inf, lp)

"""Priors in natural units: bounded albedos, log-normal or half-Cauchy roughness, a
von Mises–Fisher light direction, and the default prior of every parameter of a model.

Every prior has ``log_prob(x)`` (JAX, elementwise for scalar priors, up to an additive
constant) and ``sample(rng, shape)`` (NumPy, for simulation-based calibration). A prior is
placed on the *natural* value x of a parameter (albedo in [0, 1], alpha > 0, a unit
direction l); the log-posterior adds the log-Jacobian of the bijection x = g(theta) so the
sampler sees the same distribution in its unconstrained coordinates
(:mod:`jaxrefl.posterior._logpost`).

A parameter's range in its :class:`~jaxrefl.fit.ParamSpace` truncates its prior: alpha with
bounds [1e-3, 1] under a log-normal prior has the log-normal density restricted to
[1e-3, 1]. The truncation constant does not depend on x, so MCMC ignores it;
:func:`sample_truncated` draws from the truncated prior by rejection (for SBC).

=====================  ================================================  ===============
prior                   log density (up to a constant)                     support
=====================  ================================================  ===============
``Uniform(lo, hi)``     0                                                  [lo, hi]
``Normal(mu, sd)``      -(x - mu)^2 / (2 sd^2)                             R
``LogNormal(med, s)``   -log x - (log x - log med)^2 / (2 s^2)             x > 0
``HalfCauchy(scale)``   -log(1 + (x / scale)^2)                            x >= 0
``Jeffreys()``          -log x  (improper; a noise scale)                  x > 0
``VonMisesFisher``      kappa mu . l + log(kappa / (4 pi sinh kappa))      |l| = 1
``MultivariateNormal``  -(x - mu)^T S^-1 (x - mu) / 2 over a whole block   R^k
=====================  ================================================  ===============

Default priors (:func:`default_priors`): a log-normal with median 0.1 and log sd 1.5 on the
log-scale widths (alpha, exponents: 0.005-2 at +-2 sd, polished to matte), truncated to
their range; a uniform prior on every other parameter with a finite range (albedo,
specular F0); a wide normal (sd 10) on unbounded parameters.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import ParamSpace

__all__ = [
    "HalfCauchy",
    "Jeffreys",
    "LogNormal",
    "MultivariateNormal",
    "Normal",
    "Prior",
    "Uniform",
    "VonMisesFisher",
    "default_priors",
    "sample_truncated",
]

_LOG_SCALE = frozenset({"alpha", "alpha_u", "alpha_v", "exponent", "sigma", "k", "eta"})


class Prior(eqx.Module):
    """A prior density on natural values (scalar priors act elementwise)."""

    def log_prob(self, x: Float[Array, "*b"]) -> Float[Array, "*b"]:
        raise NotImplementedError

    def sample(self, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
        raise NotImplementedError


class Uniform(Prior):
    """Flat on [lower, upper] (the bounded albedos and Fresnel F0)."""

    lower: float = 0.0
    upper: float = 1.0

    def log_prob(self, x):
        return jnp.zeros_like(x)

    def sample(self, rng, shape):
        return rng.uniform(self.lower, self.upper, size=shape)


class Normal(Prior):
    """Gaussian N(mean, std^2)."""

    mean: float = 0.0
    std: float = 1.0

    def log_prob(self, x):
        z = (x - self.mean) / self.std
        return -0.5 * z * z

    def sample(self, rng, shape):
        return rng.normal(self.mean, self.std, size=shape)


def _floats(v) -> tuple[float, ...]:
    return tuple(float(x) for x in np.asarray(v, np.float64).reshape(-1))


def _float_or_none(v) -> float | None:
    return None if v is None else float(v)


class MultivariateNormal(Prior):
    """Gaussian N(mean, cov) over a whole block of k entries (the channels of a coloured
    F0, say), correlated: ``log_prob`` takes (*b, k) and returns (*b,). ``mean`` (k,) and
    ``cov`` (k, k, symmetric positive definite) are tuples, so that the prior hashes (a
    static part of a compiled sampler). Truncated to the block's box by its bijections, as
    every prior here.

    noise_ref: None, or a noise scale s_ref > 0 in the units of the posterior's noise
    scale s (sd = s noise.std(obs), :mod:`jaxrefl.posterior._logpost`; s = 1 where the
    noise is known). Then the prior is in units of the noise, N(mean, (s / s_ref)^2 cov):
    the conjugate Normal-Inverse-Gamma prior of a linear model with an unknown noise scale
    (Gelman et al., *BDA3*, sec. 14.8), which equals N(mean, cov) where s = s_ref and which
    the linear-Gaussian samplers draw exactly (:mod:`jaxrefl.posterior._width_gibbs`).
    Its log density, normalising factor (s / s_ref)^-k included, is :meth:`log_prob_scaled`.
    """

    # Python floats whatever the caller gives (NumPy scalars would be traced as arrays)
    mean: tuple[float, ...] = eqx.field(converter=_floats)
    cov: tuple[tuple[float, ...], ...] = eqx.field(converter=lambda c: tuple(map(_floats, c)))
    noise_ref: float | None = eqx.field(default=None, converter=_float_or_none)

    def __check_init__(self):
        c = np.asarray(self.cov, np.float64)
        k = len(self.mean)
        if c.shape != (k, k) or not np.allclose(c, c.T):
            raise JaxreflError(f"MultivariateNormal needs a symmetric ({k}, {k}) cov, got {c}")
        if not np.all(np.linalg.eigvalsh(c) > 0):
            raise JaxreflError(f"MultivariateNormal needs a positive definite cov, got {c}")
        if self.noise_ref is not None and not self.noise_ref > 0:
            raise JaxreflError(f"noise_ref must be a positive noise scale, got {self.noise_ref}")

    @property
    def precision(self) -> np.ndarray:
        """cov^-1 (k, k), float64."""
        return np.linalg.inv(np.asarray(self.cov, np.float64))

    def log_prob(self, x):
        """log N(x; mean, cov) up to a constant; (*b, k) -> (*b,). With ``noise_ref`` this
        is the density where s = s_ref (see :meth:`log_prob_scaled`)."""
        d = x - jnp.broadcast_to(jnp.asarray(self.mean, x.dtype), x.shape)
        return -0.5 * jnp.einsum("...i,ij,...j->...", d, jnp.asarray(self.precision, x.dtype), d)

    def log_prob_scaled(self, x, s):
        """log N(x; mean, (s / s_ref)^2 cov) up to a constant free of s: (s_ref / s)^2 times
        :meth:`log_prob` minus k log(s / s_ref). Without ``noise_ref``, :meth:`log_prob`."""
        if self.noise_ref is None:
            return self.log_prob(x)
        ratio = self.noise_ref / s
        return ratio * ratio * self.log_prob(x) + len(self.mean) * jnp.log(ratio)

    def sample(self, rng, shape):
        """Draws of N(mean, cov) (with ``noise_ref``: at s = s_ref), shape (*shape, k)."""
        return rng.multivariate_normal(np.asarray(self.mean), np.asarray(self.cov), size=shape)


class LogNormal(Prior):
    """log x ~ N(log median, log_std^2): a roughness prior spanning decades."""

    median: float = 0.1
    log_std: float = 1.5

    def log_prob(self, x):
        # Gradient-safe: x <= 0 is outside the support (the bijections never produce it);
        # it is swapped for 1 before the log and given -inf.
        ok = x > 0
        xs = jnp.where(ok, x, 1.0)
        z = (jnp.log(xs) - math.log(self.median)) / self.log_std
        return jnp.where(ok, -jnp.log(xs) - 0.5 * z * z, -jnp.inf)

    def sample(self, rng, shape):
        return self.median * np.exp(self.log_std * rng.normal(size=shape))


class HalfCauchy(Prior):
    """Half-Cauchy on x >= 0 with ``scale``: heavy-tailed, for roughness or a noise scale
    (Gelman 2006, *Prior distributions for variance parameters in hierarchical models*)."""

    scale: float = 1.0

    def log_prob(self, x):
        t = x / self.scale
        return jnp.where(x >= 0, -jnp.log1p(t * t), -jnp.inf)

    def sample(self, rng, shape):
        return np.abs(self.scale * rng.standard_cauchy(size=shape))


class Jeffreys(Prior):
    """p(x) ∝ 1/x on x > 0 (flat in log x): the scale-invariant prior of an unknown noise
    scale (Jeffreys 1946). Improper: it cannot be sampled, the posterior is proper as soon
    as one observation is used."""

    def log_prob(self, x):
        ok = x > 0
        # Gradient-safe: x <= 0 (outside the support) is swapped for 1 before the log.
        return jnp.where(ok, -jnp.log(jnp.where(ok, x, 1.0)), -jnp.inf)

    def sample(self, rng, shape):
        raise JaxreflError("the Jeffreys prior is improper: it has no draws (give a proper prior)")


class VonMisesFisher(Prior):
    """von Mises–Fisher on the unit sphere S^2 about ``mean`` with concentration ``kappa``.

    p(l) = kappa / (4 pi sinh kappa) exp(kappa mean . l)  (Fisher 1953). kappa = 0 is the
    uniform distribution on the sphere; the angular spread about the mean is about
    1/sqrt(kappa) radians for large kappa. ``log_prob`` takes unit vectors (*b, 3).
    Sampling: Wood (1994), *Simulation of the von Mises Fisher distribution*, in 3-D where
    the cosine w to the mean has the closed form w = 1 + log(u + (1 - u) e^(-2 kappa)) / kappa.
    """

    mean: tuple[float, float, float] = (0.0, 0.0, 1.0)
    kappa: float = 0.0

    def __check_init__(self):
        if not self.kappa >= 0:
            raise JaxreflError(f"VonMisesFisher needs kappa >= 0, got {self.kappa}")
        if not np.linalg.norm(self.mean) > 0:
            raise JaxreflError("VonMisesFisher needs a non-zero mean direction")

    @property
    def mu(self) -> np.ndarray:
        m = np.asarray(self.mean, dtype=np.float64)
        return m / np.linalg.norm(m)

    def log_prob(self, x):
        mu = jnp.asarray(self.mu, dtype=x.dtype).reshape((1,) * (x.ndim - 1) + (3,))
        k = self.kappa
        # log(kappa / (4 pi sinh kappa)) written for large kappa without overflow; the
        # kappa -> 0 limit is log(1 / (4 pi)).
        if k < 1e-8:
            log_c = -math.log(4.0 * math.pi)
        else:
            log_c = math.log(k) - math.log(2.0 * math.pi) - k - math.log1p(-math.exp(-2.0 * k))
        return log_c + k * jnp.sum(x * mu, axis=-1)

    def sample(self, rng, shape):
        n = int(np.prod(shape, dtype=int))
        k = self.kappa
        u = rng.uniform(size=n)
        if k < 1e-8:
            w = 2.0 * u - 1.0
        else:
            w = 1.0 + np.log(u + (1.0 - u) * np.exp(-2.0 * k)) / k
        w = np.clip(w, -1.0, 1.0)
        phi = rng.uniform(0.0, 2.0 * np.pi, size=n)
        s = np.sqrt(1.0 - w * w)
        local = np.stack([s * np.cos(phi), s * np.sin(phi), w], axis=-1)
        # Rotate +z onto mu with an orthonormal basis (t, b, mu).
        mu = self.mu
        t = np.cross(mu, [1.0, 0.0, 0.0] if abs(mu[0]) < 0.9 else [0.0, 1.0, 0.0])
        t /= np.linalg.norm(t)
        b = np.cross(mu, t)
        out = local[:, :1] * t + local[:, 1:2] * b + local[:, 2:] * mu
        return out.reshape((*shape, 3))


def default_priors(space: ParamSpace) -> dict[str, Prior]:
    """The default prior of every free parameter of ``space`` (module docstring), by name."""
    out: dict[str, Prior] = {}
    for b in space.blocks:
        lo = min(r.lower for r in b.runs)
        hi = max(r.upper for r in b.runs)
        if b.name in _LOG_SCALE and lo >= 0:
            out[b.name] = LogNormal(0.1, 1.5)  # truncated to [lo, hi] by the bijection
        elif math.isfinite(lo) and math.isfinite(hi):
            out[b.name] = Uniform(float(lo), float(hi))
        else:
            out[b.name] = Normal(0.0, 10.0)
    return out


def resolve_priors(space: ParamSpace, priors: Mapping[str, Prior] | None) -> dict[str, Prior]:
    """Defaults overridden by ``priors`` (by parameter name); unknown names raise."""
    out = default_priors(space)
    for name, p in dict(priors or {}).items():
        if name not in out:
            raise KeyError(f"prior for {name!r}: not a free parameter; free: {tuple(out)}")
        if not isinstance(p, Prior):
            raise TypeError(f"prior for {name!r} must be a jaxrefl.posterior Prior, got {p!r}")
        out[name] = p
    return out


def sample_truncated(
    prior: Prior,
    rng: np.random.Generator,
    shape: tuple[int, ...],
    lower: float = -math.inf,
    upper: float = math.inf,
    max_rounds: int = 1000,
) -> np.ndarray:
    """Draws of a scalar ``prior`` restricted to [lower, upper] (rejection sampling)."""
    n = int(np.prod(shape, dtype=int))
    out = np.empty(0)
    for _ in range(max_rounds):
        x = np.asarray(prior.sample(rng, (max(2 * n, 64),)), dtype=np.float64)
        out = np.concatenate([out, x[(x >= lower) & (x <= upper)]])
        if out.size >= n:
            return out[:n].reshape(shape)
    raise JaxreflError(f"{prior} puts almost no mass on [{lower}, {upper}]: cannot sample it")

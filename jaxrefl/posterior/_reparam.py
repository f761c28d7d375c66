"""Conditional non-centring of the diffuse albedo: the coordinates in which map MCMC mixes.

Why: on a pixel where no highlight was observed, a broad specular lobe looks like diffuse
light, so the data pin down only albedo_c + (the lobe's diffuse-equivalent level), a
*curved* ridge through (albedo, specular F0, alpha) that is ~100 times longer than it is
wide (noise 0.5% of the signal, F0 free over [0, 0.25]). A constant (even dense) mass
matrix cannot follow a curved ridge: in the fit's coordinates HMC takes steps of the ridge's
width and the map's chains do not mix on the Laplace-flagged pixels of the demo capture
(``benchmarks/posterior_speed.py --only-mixing`` measures R-hat and ESS with and without it).

The map. The prediction of the capture models is affine in the diffuse albedo rho,
pred_kc = a_kc(rest) rho_c + r_kc(rest), with ``rest`` every other entry of theta (specular,
alpha, light, noise scale). Over the uncensored observations with W = weight / std(obs)^2
and s the noise scale (1 when known), the Gaussian part of the likelihood gives

    rho_c | rest  ~  N(m_c, v_c),   m_c = sum_k W a (y - r) / sum_k W a^2,
                                    v_c = s^2 / sum_k W a^2

(a grey albedo sums over channels too). The sampler moves in theta' with

    theta_rho = c(rest) + w(rest) * theta'_rho,    every other entry unchanged,
    c = g^-1(m~),   w = sqrt(v) / g'(c),

g the albedo's bijection (a scaled logistic) and m~ the mean softly clamped into the
albedo's range. In theta' the ridge is straight: the conditional of theta'_rho is ~N(0, 1)
wherever the other parameters are, and what is left is the low-dimensional (specular,
alpha, s) geometry, which the dense metric handles.

Exact for any c and w: the map is triangular with diagonal (w, 1, ..., 1), so the density in
theta' is p(T(theta')) * prod_c w_c (log-Jacobian sum log w), and the draws T(theta') are
draws of the same posterior. The approximations (censored rows and a robust loss left out
of m and v, the range ignored by the least squares) decide only how round the target looks,
never what it is. The prediction at theta comes from the same forward-mode pass as a and r
(r + a rho), so a gradient costs one JVP of the model instead of one evaluation.

This is the non-centred parameterisation of hierarchical models (Papaspiliopoulos, Roberts
& Skold 2007, *A general framework for the parametrization of hierarchical models*,
Statistical Science 22(1)) with the conditional moments of a linear sub-model, the way
variable projection treats linear parameters in least squares (Golub & Pereyra 2003).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrefl._errors import JaxreflError
from jaxrefl.fit import PixelData, ScaledSigmoid

from ._logpost import LogPosterior

__all__ = ["ConditionalAlbedo", "conditional_albedo"]

# The soft clamp keeps m~ inside [lo + d (hi - lo), hi - d (hi - lo)]: the least-squares
# mean ignores the range and may leave it (the posterior then sits against the bound); the
# clamp keeps g^-1 finite there. d = 2% and a softplus of width 2%: exact identity in the
# middle of the range, smooth (so the leapfrog's gradients are) where it bends.
_CLAMP = 0.02
# The prior alone (uniform on the range) is a logistic in theta with sd pi / sqrt(3): the
# conditional sd w never needs to be wider (that is where the data say nothing).
_W_MAX = math.pi / math.sqrt(3.0)


class ConditionalAlbedo(eqx.Module):
    """The log-posterior ``base`` in the coordinates theta' of the module docstring.

    Call ``t(theta', data, normals=None) -> log p(T(theta')) + log|dT/dtheta'|``;
    :meth:`to_theta` and :meth:`from_theta` map single points (vmap them for batches).
    Build with :func:`conditional_albedo`.
    """

    base: LogPosterior
    name: str = eqx.field(static=True)
    start: int = eqx.field(static=True)
    stop: int = eqx.field(static=True)
    grey: bool = eqx.field(static=True)
    lower: float = eqx.field(static=True)
    upper: float = eqx.field(static=True)

    @property
    def light(self):
        return self.base.light

    @property
    def size(self) -> int:
        return self.base.size

    @property
    def labels(self) -> tuple[str, ...]:
        return self.base.labels

    def for_data(self, data: PixelData) -> ConditionalAlbedo:
        return dataclasses.replace(self, base=self.base.for_data(data))

    def _parts(self, theta, data, normals):
        """(r, a, c, w): the affine pieces and the conditional moments given theta's rest
        (theta's own albedo entries do not enter)."""
        dtype = theta.dtype
        c_n = data.obs.shape[-1]
        shape = (1,) if self.grey else (c_n,)

        def pred(rho):
            return self.base.predict(theta, data, normals, replace={self.name: rho})

        r, a = jax.jvp(pred, (jnp.zeros(shape, dtype),), (jnp.ones(shape, dtype),))
        ok = self.base.residual.usable(data) & (data.censored == 0)
        obs = jnp.where(ok, data.obs.astype(dtype), 0.0)
        wgt = jnp.where(ok, data.weight.astype(dtype), 0.0) / self.base.residual.noise.std(obs) ** 2
        axes = (0, 1) if self.grey else (0,)
        n_rho = self.stop - self.start
        saa = jnp.sum(wgt * a * a, axis=axes).reshape(n_rho)
        has = saa > 0
        saa1 = jnp.where(has, saa, 1.0)  # gradient-safe: no information -> c = 0, w = w_max
        m = jnp.sum(wgt * a * (obs - r), axis=axes).reshape(n_rho) / saa1
        _, _, log_s = self.base.split(theta)
        s = jnp.exp(log_s) if log_s is not None else jnp.ones((), dtype)
        sd = s / jnp.sqrt(saa1)
        span = self.upper - self.lower
        z = (m - self.lower) / span
        d = _CLAMP
        z = z - d * jax.nn.softplus((z - (1.0 - d)) / d) + d * jax.nn.softplus((d - z) / d)
        # The softplus tails still leave z a hair outside (0, 1) far out: clip for the log.
        z = jnp.clip(z, 0.5 * d, 1.0 - 0.5 * d)
        c = jnp.log(z) - jnp.log1p(-z)
        w = jnp.minimum(sd / (span * z * (1.0 - z)), _W_MAX)
        # A zero sd (noise scale underflowed to 0) would make the map singular.
        w = jnp.maximum(w, jnp.finfo(dtype).tiny)
        c = jnp.where(has, c, 0.0)
        w = jnp.where(has, w, _W_MAX)
        return r, a, c, w

    def to_theta(self, theta_p: Float[Array, " D"], data: PixelData, normals=None):
        """(theta, log|dT/dtheta'|, prediction at theta) for one point theta'."""
        r, a, c, w = self._parts(theta_p, data, normals)
        u = c + w * theta_p[self.start : self.stop]
        theta = theta_p.at[self.start : self.stop].set(u)
        rho = self.lower + (self.upper - self.lower) * jax.nn.sigmoid(u)  # g(u), ScaledSigmoid
        return theta, jnp.sum(jnp.log(w)), r + a * rho[None, :]

    def from_theta(self, theta: Float[Array, " D"], data: PixelData, normals=None):
        """theta' for one point theta (the inverse of :meth:`to_theta`)."""
        _, _, c, w = self._parts(theta, data, normals)
        u = (theta[self.start : self.stop] - c) / w
        return theta.at[self.start : self.stop].set(u)

    def __call__(self, theta_p: Float[Array, " D"], data: PixelData, normals=None):
        theta, log_det, pred = self.to_theta(theta_p, data, normals)
        lp = self.base.log_prior(theta) + self.base.log_likelihood(theta, data, normals, pred)
        lp = lp + log_det
        return jnp.where(jnp.isnan(lp), -jnp.inf, lp)


def conditional_albedo(lp: LogPosterior, name: str = "albedo") -> ConditionalAlbedo:
    """``lp`` in the conditionally non-centred coordinates of the module docstring.

    Raises ValueError (saying why) when they do not apply: no free ``name`` block, a
    bijection other than the scaled logistic of a bounded albedo, or a model whose
    prediction is not affine in ``name`` (checked numerically on a few directions).
    """
    if not isinstance(lp, LogPosterior):
        raise JaxreflError(f"conditional_albedo needs a LogPosterior, got {type(lp).__name__}")
    blocks = {b.name: b for b in lp.space.blocks}
    if name not in blocks:
        raise JaxreflError(f"no free parameter {name!r} to non-centre (free: {tuple(blocks)})")
    blk = blocks[name]
    bijs = {r.bijection for r in blk.runs}
    bij = next(iter(bijs), None)
    if len(bijs) != 1 or not isinstance(bij, ScaledSigmoid):
        raise JaxreflError(f"{name!r} needs one bounded (scaled-logistic) bijection, got {bijs}")
    _check_affine(lp, name)
    return ConditionalAlbedo(
        lp, name, blk.start, blk.stop, blk.grey, float(bij.lower), float(bij.upper)
    )


def _check_affine(lp: LogPosterior, name: str) -> None:
    """pred(rho) must be affine in rho: the midpoint rule holds to rounding on a few lit
    directions at the parameters' default values."""
    space = lp.space
    dtype = jnp.zeros(()).dtype
    th = jnp.zeros((1, space.size), dtype)
    params = space.to_natural(th)
    ang = np.deg2rad(np.array([5.0, 30.0, 55.0, 75.0]))
    wi_np = np.stack([np.sin(ang), 0 * ang, np.cos(ang)], -1)
    wo_np = np.stack([-np.sin(ang[::-1]) * 0.7, np.sin(ang[::-1]) * 0.7, np.cos(ang[::-1])], -1)
    wo_np /= np.linalg.norm(wo_np, axis=-1, keepdims=True)
    wi, wo = jnp.asarray(wi_np, dtype), jnp.asarray(wo_np, dtype)

    def ev(v):
        p = {**params, name: jnp.full(params[name].shape, v, dtype)}
        return np.asarray(lp.model.eval(p, wi, wo), np.float64)

    lo, hi = ev(0.1), ev(0.9)
    mid = ev(0.5)
    tol = 1e3 * float(jnp.finfo(dtype).eps) * max(1.0, float(np.max(np.abs(mid))))
    if not np.all(np.abs(mid - 0.5 * (lo + hi)) <= tol):
        raise JaxreflError(
            f"the model's prediction is not affine in {name!r}: the conditional "
            "non-centring does not apply (sample in the fit's coordinates, reparam='none')"
        )

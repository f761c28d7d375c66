"""Which posteriors the width sampler (:mod:`._width_gibbs`) draws: one scalar lobe width
in a positive box, every other parameter in a finite box with a uniform or Gaussian prior,
and a prediction affine in those given the width (checked at two widths and two points).
The helpers here insert the width into, and drop it from, the natural vector, and form the
affine terms at a width.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl.fit import PixelData, ScaledSigmoid

from ._conjugate import censoring_failure, is_linear, likelihood_failure, theta_of
from ._logpost import LogPosterior
from ._priors import MultivariateNormal, Normal, Uniform

__all__ = [
    "WIDTH",
    "affine_terms",
    "drop_width",
    "general",
    "insert_width",
    "layout",
    "qualifies_width",
]

# The nonlinear parameter: a lobe width (GGX / Beckmann alpha), one scalar per pixel.
WIDTH = "alpha"


def layout(lp: LogPosterior):
    """(width index, lo (P,), hi (P,) over every natural entry, width prior, Gaussian prior)
    when the posterior has one scalar ``alpha`` in a finite positive box and every other
    entry is in a finite box with a uniform prior that covers it or a Gaussian prior
    (:class:`Normal` per entry, :class:`MultivariateNormal` over its block; truncated to
    the box); else None. The Gaussian prior is None where every such prior is uniform, else
    a hashable (mean (P,), precision (P, P) in units of s^-2, k, absolute): zeros in the
    uniform entries' and the width's rows and columns; a prior in units of the noise
    (``noise_ref``) has precision cov^-1 noise_ref^2 (module docstring), one in absolute
    units cov^-1, exact only where s = 1 (a known noise); k counts the entries of the
    former (their prior's normalising factor s^-k), ``absolute`` says whether any prior is
    of the latter kind."""
    width = None
    lo, hi = [], []
    p = lp.space.size
    mean, prec = np.zeros(p), np.zeros((p, p))
    k_scaled, absolute = 0, False
    for blk, prior in zip(lp.space.blocks, lp.priors, strict=True):
        at = slice(blk.start, blk.stop)
        for r in blk.runs:
            if not isinstance(r.bijection, ScaledSigmoid):
                return None
            if not (np.isfinite(r.lower) and np.isfinite(r.upper)):
                return None
            if blk.name == WIDTH:
                if r.stop - r.start != 1 or width is not None or not r.lower > 0:
                    return None
                width = (r.start, prior)
            elif isinstance(prior, Normal):
                idx = np.arange(r.start, r.stop)
                mean[idx] = float(prior.mean)
                prec[idx, idx] = 1.0 / float(prior.std) ** 2
                absolute = True
            elif isinstance(prior, MultivariateNormal):
                if len(prior.mean) != blk.stop - blk.start:
                    return None
                if r.start == blk.start:  # once per block
                    mean[at] = prior.mean
                    ref = 1.0 if prior.noise_ref is None else float(prior.noise_ref) ** 2
                    prec[at, at] = prior.precision * ref
                    k_scaled += 0 if prior.noise_ref is None else len(prior.mean)
                    absolute |= prior.noise_ref is None
            elif not isinstance(prior, Uniform) or not (
                float(prior.lower) <= r.lower and float(prior.upper) >= r.upper
            ):
                return None
            lo += [r.lower] * (r.stop - r.start)
            hi += [r.upper] * (r.stop - r.start)
    if width is None:
        return None
    gauss = None
    if np.any(prec != 0):
        gauss = tuple(mean.tolist()), tuple(map(tuple, prec.tolist())), k_scaled, absolute
    return width[0], np.asarray(lo, np.float64), np.asarray(hi, np.float64), width[1], gauss


def general(lp: LogPosterior) -> LogPosterior:
    """``lp`` with its censored branch whatever the data (the same values): chunks with
    and without censored observations then share one compiled program."""
    return dataclasses.replace(lp, censoring=True)


def insert_width(x, a, i):
    """The full natural vector: x (P - 1,) with the width a inserted at index i."""
    return jnp.concatenate([x[..., :i], jnp.asarray(a, x.dtype)[..., None], x[..., i:]], -1)


def drop_width(v, i):
    return jnp.concatenate([v[..., :i], v[..., i + 1 :]], -1)


def affine_terms(lp, d, i, x_c, a):
    """(A (M, P - 1), b (M,)) of pixel d's prediction at width a, exact for a model affine
    in x (one forward-mode Jacobian at x_c)."""

    def pred(x):
        return lp.residual.predict(theta_of(lp, insert_width(x, a, i)), d).reshape(-1)

    jac = jax.jacfwd(pred)(x_c)
    return jac, pred(x_c) - jac @ x_c


def qualifies_width(lp: LogPosterior, data: PixelData) -> tuple[bool, str]:
    """(True, "") when :func:`sample_width_gibbs` samples this posterior for every pixel of
    ``data`` (module docstring), else (False, the first condition that fails)."""
    if why := likelihood_failure(lp):
        return False, why
    lay = layout(lp)
    if lay is None:
        return False, (
            f"not one scalar {WIDTH!r} in a positive box with every other parameter in a "
            "finite box with a uniform or Gaussian prior"
        )
    if why := censoring_failure(data):
        return False, why
    i, lo, hi, _prior, gauss = lay
    if gauss is not None and gauss[3] and lp.noise_scale is not None:
        return False, (
            "a Gaussian prior in absolute units with an unknown noise scale (give a "
            "MultivariateNormal a noise_ref: a prior in units of the noise)"
        )
    ok = _linear_given_width(general(lp), data, i, jnp.asarray(lo), jnp.asarray(hi))
    if not bool(np.all(np.asarray(ok))):
        return False, f"the model is not linear in its parameters given {WIDTH!r}"
    return True, ""


@eqx.filter_jit
def _linear_given_width(lp, data, i, lo, hi):
    xl, xh = drop_width(lo, i), drop_width(hi, i)
    x_c, x_2 = 0.5 * (xl + xh), xl + 0.3 * (xh - xl)

    def one(d):
        ok = jnp.asarray(True)
        for f in (0.2, 0.7):  # two widths inside the interval
            a = lo[i] + f * (hi[i] - lo[i])
            jac, b = affine_terms(lp, d, i, x_c, a)
            p2 = lp.residual.predict(theta_of(lp, insert_width(x_2, a, i)), d).reshape(-1)
            ok = ok & is_linear(p2, b + jac @ x_2)
        return ok

    return jax.vmap(one)(data)

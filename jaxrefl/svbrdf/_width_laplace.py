"""Laplace uncertainty that accounts for the pooled model's shared lobe width.

The ``pooled`` model (:mod:`jaxrefl.svbrdf._pooled`) fits each pixel's parameters theta_i
with the GGX width alpha fixed at one value for the capture. A per-pixel Laplace covariance
H_i^-1 (H_i = J_i^T J_i, the Gauss-Newton curvature of pixel i's whitened residual r_i)
treats that alpha as known. Seen as one joint problem in (theta_1, ..., theta_N, t), with
t = log alpha shared, the Gauss-Newton curvature has an arrow shape:

    H = [[ H_1            h_1 ]          h_i = J_i^T j_i,    j_i = dr_i / dt
         [      ...       ... ]          c_i = j_i^T j_i
         [           H_N  h_N ]
         [ h_1^T ... h_N^T  C ]],        C = sum_i c_i

and its inverse follows from the Schur complement of the block-diagonal part (exact block
elimination):

    S = C - sum_i h_i^T H_i^-1 h_i = sum_i s_i,        s_i = c_i - h_i^T v_i,  v_i = H_i^-1 h_i
    Var(t) = 1 / S
    Cov(theta_i) = H_i^-1 + v_i v_i^T / S,    Cov(theta_i, t) = -v_i / S

so each pixel's covariance gains the rank-one term v_i v_i^T / S: its share of the width's
uncertainty, large where the pixel's parameters trade off against the width (F0 against
alpha, when a pixel sees only the lobe's flank), small where they do not or where many
pixels pin the width down (S grows with N). :func:`width_terms` computes (v_i, s_i) per
pixel, one tile at a time; :func:`widen` sums the s_i of the whole capture and applies the
rank-one terms to the natural-unit std and correlation maps (delta method:
x = g(theta), dx = g'(theta) dtheta entry by entry).

Pixels whose own curvature is not inverted (a NaN std from :func:`jaxrefl.fit.laplace`: no
estimate, not positive definite, or a condition number above its limit) take no part:
their v_i is NaN and their s_i 0, so the width's variance is that of the other pixels'
data, the same or larger than the joint problem's. The curvature is taken where the fit
stopped, with the width at the value chosen by held-out photos: the Gaussian approximation
of the joint posterior around that point, not at a joint optimum. Noise is the pooled fit's
known scale (the per-pixel Laplace uses the same, ``LaplaceOptions(noise="known")``).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl import fit
from jaxrefl.fit import PixelData, Residual

__all__ = ["WidthUncertainty", "widen", "width_terms"]


@eqx.filter_jit
def _terms(residual: Residual, theta, data: PixelData, formed):
    alpha = residual.space.fixed["alpha"]

    def one(t, d, ok):
        t = jnp.where(ok, t, 0.0)

        def r_of(th, log_a):
            res = eqx.tree_at(lambda r: r.space.fixed["alpha"], residual, jnp.exp(log_a))
            return res(th, d)

        log_a = jnp.log(alpha).astype(t.dtype)
        jac = jax.jacfwd(r_of, argnums=0)(t, log_a)  # (M, P)
        _, j_t = jax.jvp(lambda la: r_of(t, la), (log_a,), (jnp.ones_like(log_a),))  # (M,)
        h_mat = jac.T @ jac
        h = jac.T @ j_t
        c = j_t @ j_t
        # Column scaling before the solve, as the per-pixel Laplace does (float32 pivots).
        dg = jnp.diagonal(h_mat)
        sc = 1.0 / jnp.sqrt(jnp.where(dg > 0, dg, 1.0))
        a = h_mat * sc[:, None] * sc[None, :]
        l_fac, pd = fit.cholesky_unrolled(a)
        eye = jnp.eye(a.shape[0], dtype=a.dtype)
        v = sc * fit.cho_solve_unrolled(jnp.where(pd, l_fac, eye), sc * h)
        keep = ok & pd & jnp.all(jnp.isfinite(v))
        s = jnp.where(keep, c - h @ v, 0.0)
        return jnp.where(keep, v, jnp.nan), jnp.maximum(s, 0.0)

    return jax.vmap(one)(theta, data, formed)


def width_terms(residual: Residual, theta, data: PixelData, std) -> tuple[np.ndarray, np.ndarray]:
    """(v (N, P), s (N,)) of the module docstring for the pixels of one tile: ``residual``
    the pooled fit's (alpha in ``residual.space.fixed``), ``theta`` (N, P) where the fit
    stopped, ``data`` the tile's fitted data, ``std`` (N, P) the per-pixel Laplace std.
    A pixel whose std is not finite everywhere (no estimate, or a curvature that was not
    inverted: not positive definite, or above the condition limit) takes no part."""
    theta = jnp.asarray(theta)
    formed = np.all(np.isfinite(np.asarray(std)), axis=-1)
    formed &= np.all(np.isfinite(np.asarray(theta)), axis=-1)
    v, s = _terms(residual, theta, data, jnp.asarray(formed))
    return np.asarray(v, np.float64), np.asarray(s, np.float64)


class WidthUncertainty(eqx.Module):
    """The shared width's Laplace uncertainty (:func:`widen`).

    alpha:     the shared GGX width
    log_std:   std of log alpha, 1 / sqrt(S); inf where no pixel informs it
    alpha_std: its delta-method std in alpha, alpha * log_std
    pixels:    pixels whose curvature entered S
    """

    alpha: float
    log_std: float
    alpha_std: float
    pixels: int

    def as_dict(self) -> dict[str, float | int]:
        return {
            "alpha": self.alpha,
            "log_alpha_std": self.log_std,
            "alpha_std": self.alpha_std,
            "pixels": self.pixels,
        }


def widen(
    space: fit.ParamSpace,
    alpha: float,
    theta: np.ndarray,
    std: np.ndarray,
    corr: np.ndarray,
    v: np.ndarray,
    s: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, WidthUncertainty]:
    """The natural-unit ``std`` (N, P) and ``corr`` (N, P, P) of the per-pixel Laplace with
    each pixel's share of the width's uncertainty added (module docstring), from the
    per-pixel ``v`` (N, P) and ``s`` (N,) of every tile; and the width's own uncertainty."""
    s_tot = float(np.sum(s[np.isfinite(s)], dtype=np.float64))
    var_t = 1.0 / s_tot if s_tot > 0 else np.inf
    used = int(np.sum(np.isfinite(s) & (s > 0)))
    ok = np.all(np.isfinite(theta), axis=-1)
    dn = np.asarray(space.dnatural(jnp.asarray(np.where(ok[:, None], theta, 0.0))))
    # In the maps' own dtype, in place: the (N, P, P) arrays are the large ones.
    dtype = np.result_type(std.dtype, corr.dtype, np.float32)
    w = (dn * v).astype(dtype)  # the rank-one direction in natural units (NaN: no part)
    extra = np.where(np.isfinite(w), w, 0.0)
    cov = corr.astype(dtype) * std[:, :, None]
    cov *= std[:, None, :]
    if np.isfinite(var_t):
        rank1 = extra[:, :, None] * extra[:, None, :]
        rank1 *= dtype.type(var_t)
        cov += rank1
    new_std = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
    denom = new_std[:, :, None] * new_std[:, None, :]
    pos = denom > 0
    np.divide(cov, denom, out=cov, where=pos)
    cov[~pos] = 0.0
    cov[~np.isfinite(corr)] = np.nan
    new_corr = cov
    new_std = np.where(np.isfinite(std), new_std, np.nan)
    log_std = float(np.sqrt(var_t))
    return new_std, new_corr, WidthUncertainty(float(alpha), log_std, alpha * log_std, used)

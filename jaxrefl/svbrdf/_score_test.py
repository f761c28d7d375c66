"""Does a refinement's extra parameter have support in the data? A score test at the base optimum.

A refining model (``ggx_normal``: the dielectric plus a normal's slopes) nests its base
model: with the extra parameters e at their prior mean 0 it predicts what the base predicts.
Whether the training photos ask for e can be read at the base model's optimum, before
paying for the refinement's own fit (Rao's score test; Rao 1948, "Large sample tests of
statistical hypotheses", Proc. Cambridge Phil. Soc. 44):

    g  = J_e^T r - J_e^T J_o (J_o^T J_o)^+ J_o^T r       efficient score of e (others o profiled)
    S  = J_e^T J_e - J_e^T J_o (J_o^T J_o)^+ J_o^T J_e   efficient information of e
    T  = c g^T (S + P)^-1 g                              evidence, with the prior precision P
    E  = tr(S (S + P)^-1),  V = 2 tr((S (S + P)^-1)^2)   T's mean and variance under e = 0

with r and J the refinement's residual (whitened by the noise scale its fit uses, its prior
on e appended) and Jacobian at (base optimum, e = 0), per pixel. ``c`` = (scale the fit
whitens with / the pixel's own noise scale)^2 puts each pixel in units of its own noise
(a pixel twice as noisy as the median gives a score four times smaller than its residual
suggests). Under e = 0 and Gaussian noise, g ~ N(0, S / c) and E[T] = E exactly:
T / E near 1 means the photos show no more than noise in the directions e moves the
prediction, and the half of the objective that e would remove is about what e would fit to
the noise (E / 2, its effective number of parameters). The same quantities are the
expected drop of the cost, T / 2, from one Gauss-Newton step in e from the base optimum.

The test is local: it sees what a small e explains. A refinement that helps only from far
away (a normal tilted beyond the prior's few degrees) goes unseen; its prior makes such
tilts unlikely fits anyway.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxrefl.fit import PixelData, Residual

__all__ = ["score_test"]


@eqx.filter_jit
def score_test(
    res: Residual,
    theta: Float[Array, "N P"],
    data: PixelData,
    extra: tuple[int, ...],
    scale: Float[Array, " N"],
) -> tuple[Float[Array, " N"], Float[Array, " N"], Float[Array, " N"]]:
    """Per pixel (T, E, V) of the module docstring for the entries ``extra`` (indices) of
    theta, whose prior's rows ``res`` appends; ``scale`` = c. Pixels without more usable
    observations than parameters give 0, 0, 0."""
    p = theta.shape[-1]
    e_idx = jnp.asarray(extra)
    o_idx = jnp.asarray([i for i in range(p) if i not in extra])

    def one(t, d, c):
        r = res(t, d)
        jac = jax.jacfwd(res)(t, d)
        n_data = d.obs.size  # the data's rows come first (K * C), the prior's after
        jd, rd = jac[:n_data], r[:n_data]
        # Curvature and gradient of the data term; the prior's rows only add its precision
        # (its residual is 0 at e = 0).
        a = jd.T @ jd
        g = jd.T @ rd
        prior = jac[n_data:].T @ jac[n_data:]
        a_eo = a[e_idx][:, o_idx]
        # Pseudo-inverse: parameters at a bound (F0 at the dielectric cap) leave J_o rank
        # deficient; their directions carry no information to profile out.
        a_oo_inv = jnp.linalg.pinv(a[o_idx][:, o_idx], hermitian=True)
        s = a[e_idx][:, e_idx] - a_eo @ a_oo_inv @ a_eo.T
        geff = g[e_idx] - a_eo @ a_oo_inv @ g[o_idx]
        post = s + prior[e_idx][:, e_idx]
        m = jnp.linalg.solve(post, s)  # (S + P)^-1 S: its trace is E's
        t_stat = c * geff @ jnp.linalg.solve(post, geff)
        e_stat = jnp.trace(m)
        v_stat = 2.0 * jnp.sum(m * m.T)
        live = jnp.isfinite(t_stat) & jnp.isfinite(e_stat) & (res.n_usable(d) > p)
        zero = jnp.zeros((), t.dtype)
        return (
            jnp.where(live, t_stat, zero),
            jnp.where(live, e_stat, zero),
            jnp.where(live, v_stat, zero),
        )

    return jax.vmap(one)(theta, data, scale)

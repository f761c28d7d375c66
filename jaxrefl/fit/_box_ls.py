"""Box-constrained linear least squares of a few colour scales: argmin x^T A x - 2 b^T x
subject to lo <= x <= hi, vectorised over any leading axes.

One or two unknowns (the albedo, or albedo and specular, of the automatic start's variable
projection) are solved exactly by comparing the interior solution with the optimum on each
edge of the box; more unknowns by a ridge-regularised solve then clipping (not exact).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

__all__: list[str] = []


def _box_ls(a: Array, b: Array, lo: ArrayLike, hi: ArrayLike) -> Array:
    """argmin x^T A x - 2 b^T x subject to lo <= x <= hi (A PSD (..., m, m), b (..., m)).

    m = 1, 2: exact (the optimum is interior or on an edge, where the 1-D problem is solved
    by clipping). m > 2: ridge-regularised LS, then clipping (not exact).
    """
    m = b.shape[-1]
    tiny = jnp.finfo(b.dtype).tiny
    lo = jnp.asarray(lo, b.dtype)
    hi = jnp.asarray(hi, b.dtype)
    lead = (1,) * (b.ndim - 1)
    if m == 1:
        a11 = a[..., 0, 0]
        # A basis function that is zero on every used observation: no information, lower bound.
        x = jnp.where(a11 > tiny, b[..., 0] / jnp.where(a11 > tiny, a11, 1.0), lo[0])
        return jnp.clip(x, lo[0], hi[0])[..., None]
    if m > 2:
        eye = jnp.eye(m, dtype=b.dtype)
        # A 1e-6 relative ridge keeps collinear basis functions from a singular solve.
        ridge = 1e-6 * jnp.mean(jnp.diagonal(a, axis1=-2, axis2=-1), axis=-1) + tiny
        x = jnp.linalg.solve(a + ridge[..., None, None] * eye, b[..., None])[..., 0]
        return jnp.clip(x, lo.reshape((*lead, m)), hi.reshape((*lead, m)))
    x1, x2, _ = _box_ls2(a[..., 0, 0], a[..., 0, 1], a[..., 1, 1], b[..., 0], b[..., 1], lo, hi)
    return jnp.stack([x1, x2], axis=-1)


def _box_ls2(a11, a12, a22, b1, b2, lo, hi):
    """The m = 2 case of :func:`_box_ls` on separate arrays: (x1, x2, q) with q the minimum
    of x^T A x - 2 b^T x.

    The minimiser is the interior solution of the 2 x 2 normal equations where that is well
    conditioned and inside the box; otherwise it lies on an edge, where one coordinate is at
    a bound and the other solves its 1-D problem (clipped into its range). The five
    candidates (interior, four edges) are compared by q; elementwise arithmetic only (no
    stacking, gathers or small matrices, which are slow on CPU), vectorised over any
    leading axes.
    """
    dtype = b1.dtype
    tiny = jnp.finfo(dtype).tiny
    lo = [jnp.asarray(v, dtype) for v in (lo[0], lo[1])]
    hi = [jnp.asarray(v, dtype) for v in (hi[0], hi[1])]

    def quad(x1, x2):
        return a11 * x1 * x1 + 2.0 * a12 * x1 * x2 + a22 * x2 * x2 - 2.0 * (b1 * x1 + b2 * x2)

    det = a11 * a22 - a12 * a12
    # Interior solution only where the 2 x 2 system is well conditioned.
    ok = det > 1e-6 * a11 * a22 + tiny
    det_s = jnp.where(ok, det, 1.0)
    x1 = (a22 * b1 - a12 * b2) / det_s
    x2 = (a11 * b2 - a12 * b1) / det_s
    inside = ok & (x1 >= lo[0]) & (x1 <= hi[0]) & (x2 >= lo[1]) & (x2 <= hi[1])
    q = jnp.where(inside, quad(x1, x2), jnp.inf)
    # Edges: one coordinate at a bound, the other the clipped 1-D solution. A basis function
    # that is zero on every used observation carries no information: its lower bound.
    a11_s, a22_s = jnp.where(a11 > tiny, a11, 1.0), jnp.where(a22 > tiny, a22, 1.0)
    for first in (True, False):
        for v in (lo[0], hi[0]) if first else (lo[1], hi[1]):
            if first:
                e1 = v
                e2 = jnp.where(a22 > tiny, (b2 - a12 * v) / a22_s, lo[1])
                e2 = jnp.clip(e2, lo[1], hi[1])
            else:
                e2 = v
                e1 = jnp.where(a11 > tiny, (b1 - a12 * v) / a11_s, lo[0])
                e1 = jnp.clip(e1, lo[0], hi[0])
            qe = quad(e1, e2)
            better = qe < q  # strict: the first of equal candidates wins
            x1, x2, q = (
                jnp.where(better, e1, x1),
                jnp.where(better, e2, x2),
                jnp.where(better, qe, q),
            )
    return x1, x2, q

"""Normals to depth: Frankot-Chellappa (FFT) and a Poisson solver on the mask.

A surface z(x, y) seen orthographically (frame of :mod:`jaxrefl.ps`: x right, y up, z
towards the camera, pixel units) has normal n ∝ (-z_x, -z_y, 1), so

    z_x = -n_x / n_z,      z_y = -n_y / n_z,      and with rows downward  z_row = n_y / n_z.

* :func:`frankot_chellappa`: the integrable surface closest to (z_x, z_y) in the Fourier
  basis (Frankot & Chellappa, "A method for enforcing integrability in shape from shading
  algorithms", TPAMI 10(4), 1988): Z(w) = -i (w_x G_x + w_y G_y) / (w_x^2 + w_y^2), periodic
  on the whole image, gradients outside the mask set to 0.
* :func:`poisson`: least squares on the mask's own grid edges, min_z sum over pixel pairs
  (a, b) inside the mask of (z_b - z_a - t_ab)^2 with t the mean of the two pixels'
  gradients along the edge (Neumann condition at the silhouette, no periodicity); the
  normal equations L z = D^T t (L the graph Laplacian of the mask) are solved matrix-free
  by Jacobi-preconditioned conjugate gradients (``jax.scipy.sparse.linalg.cg``), started
  from the Frankot-Chellappa solution.

Both return z up to a constant: the mean over the mask is set to 0; NaN outside it.
Where n_z is small (the silhouette of a sphere) the gradients are unbounded; n_z is
floored at ``nz_min`` there (default 0.05: slopes up to 20).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["frankot_chellappa", "gradients", "poisson"]


def gradients(
    normals: np.ndarray, mask: np.ndarray, nz_min: float = 0.05
) -> tuple[np.ndarray, np.ndarray]:
    """(dz/dcol, dz/drow) of an (H, W, 3) normal map, 0 outside ``mask`` or where the
    normal is missing."""
    n = np.asarray(normals, np.float64)
    ok = np.asarray(mask, bool) & np.all(np.isfinite(n), axis=-1)
    # Floor n_z: a normal at (or beyond) the silhouette would give an infinite slope.
    nz = np.maximum(np.where(ok, n[..., 2], 1.0), nz_min)
    gc = np.where(ok, -n[..., 0] / nz, 0.0)
    gr = np.where(ok, n[..., 1] / nz, 0.0)
    return gc, gr


def _finish(z: np.ndarray, mask: np.ndarray) -> np.ndarray:
    z = np.asarray(z, np.float64)
    return np.where(mask, z - z[mask].mean(), np.nan)


def frankot_chellappa(normals: np.ndarray, mask: np.ndarray, nz_min: float = 0.05) -> np.ndarray:
    """Depth (H, W) in pixel units from a normal map (module docstring)."""
    mask = np.asarray(mask, bool)
    gc, gr = gradients(normals, mask, nz_min)
    h, w = mask.shape
    wc = 2 * np.pi * np.fft.fftfreq(w)[None, :]
    wr = 2 * np.pi * np.fft.fftfreq(h)[:, None]
    den = wc * wc + wr * wr
    den[0, 0] = 1.0  # the mean of z is free; set below
    zf = (-1j * wc * np.fft.fft2(gc) - 1j * wr * np.fft.fft2(gr)) / den
    zf[0, 0] = 0.0
    return _finish(np.real(np.fft.ifft2(zf)), mask)


def _dt_cols(u):
    """Adjoint of z -> z[:, 1:] - z[:, :-1]."""
    z = jnp.zeros((u.shape[0], u.shape[1] + 1), u.dtype)
    return z.at[:, 1:].add(u).at[:, :-1].add(-u)


def _dt_rows(u):
    """Adjoint of z -> z[1:] - z[:-1]."""
    z = jnp.zeros((u.shape[0] + 1, u.shape[1]), u.dtype)
    return z.at[1:].add(u).at[:-1].add(-u)


@partial(jax.jit, static_argnames=("maxiter",))
def _poisson_cg(gc, gr, mask, z0, tol, maxiter):
    m = mask.astype(gc.dtype)
    ec = m[:, 1:] * m[:, :-1]
    er = m[1:] * m[:-1]
    tc = 0.5 * (gc[:, 1:] + gc[:, :-1]) * ec
    tr = 0.5 * (gr[1:] + gr[:-1]) * er
    b = _dt_cols(tc) + _dt_rows(tr)
    outside = 1.0 - m

    def op(z):
        lz = _dt_cols(ec * (z[:, 1:] - z[:, :-1])) + _dt_rows(er * (z[1:] - z[:-1]))
        # Pixels outside the mask are decoupled and pinned to 0 (identity rows).
        return lz + outside * z

    deg = (
        jnp.pad(ec, ((0, 0), (1, 0)))
        + jnp.pad(ec, ((0, 0), (0, 1)))
        + jnp.pad(er, ((1, 0), (0, 0)))
        + jnp.pad(er, ((0, 1), (0, 0)))
    )
    # Jacobi preconditioner; an isolated pixel (degree 0) gets 1 (its row is identity or 0).
    diag = jnp.where(deg > 0, deg, 1.0)
    z, _ = jax.scipy.sparse.linalg.cg(
        op, b, x0=z0 * m, tol=tol, maxiter=maxiter, M=lambda x: x / diag
    )
    return z


def poisson(
    normals: np.ndarray,
    mask: np.ndarray,
    nz_min: float = 0.05,
    tol: float = 1e-7,
    maxiter: int = 3000,
) -> np.ndarray:
    """Depth (H, W) in pixel units on the mask (module docstring); each connected part of
    the mask gets its own constant (the global mean is 0)."""
    mask = np.asarray(mask, bool)
    gc, gr = gradients(normals, mask, nz_min)
    z0 = np.nan_to_num(frankot_chellappa(normals, mask, nz_min))
    dt = jnp.asarray(0.0).dtype
    args = (jnp.asarray(gc, dt), jnp.asarray(gr, dt), jnp.asarray(mask), jnp.asarray(z0, dt))
    z = _poisson_cg(*args, tol, maxiter)
    return _finish(np.asarray(z), mask)

"""Uncalibrated photometric stereo: rank-3 factorisation, the GBR ambiguity, and its
resolution by a calibration object of known shape in view.

Lambertian images without shadows form a rank-3 matrix (Hayakawa, "Photometric stereo
under a light source with arbitrary motion", JOSA A 11(11), 1994):

    M = S L^T,     M (N pixels x K images),  S = rho n  (N x 3),  L = E l  (K x 3).

The truncated SVD M ~ U3 W3 V3^T gives S^ = U3 W3^1/2 and L^ = V3 W3^1/2, and every
invertible 3 x 3 A gives an equally good pair S = S^ A, L = L^ A^-T: the *linear
ambiguity* (9 unknowns, 8 up to the global scale that trades albedo against intensity).
Requiring the normal field to be integrable leaves exactly the *generalized bas-relief*
(GBR) subgroup (Belhumeur, Kriegman & Yuille, "The bas-relief ambiguity", IJCV 35(1),
1999):

    G = [[1, 0, 0], [0, 1, 0], [mu, nu, lambda]],   b' = G^-T b,   l' = G l   (lambda != 0),

under which the surface z(x, y) becomes lambda z + mu x + nu y and every image (shadows
included) is unchanged: no image of a Lambertian object under distant lights can tell these
apart. :func:`gbr_matrix` and :func:`apply_gbr` make it explicit.

**Resolution used here: a calibration object in view.** Pixels whose normals are known
(e.g. a sphere in the scene, whose normals follow from its silhouette, :mod:`._sphere`)
fix the whole linear ambiguity, GBR included: each such pixel i with known n_i gives
n_i x (A^T s^_i) = 0, two independent linear equations in the 9 entries of A, so >= 4
pixels in general position determine A up to scale (the direct linear transform: the
right singular vector of the smallest singular value). The scale is fixed by the known
albedo of the calibration object (default: rho = 1 on average, i.e. albedos and
intensities come out relative to it) and the sign by n_z > 0 there. Light directions
then follow as L = L^ A^-T (normalised; |L| is the relative intensity).

Rows of M must be free of shadows and highlights: :func:`factorize` takes a mask of
pixels to use (e.g. pixels lit in every image) and :func:`uncalibrated` applies the
resolved A to all pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jaxrefl._errors import JaxreflError

from ._capture import PSInputError

__all__ = [
    "UncalibratedResult",
    "apply_gbr",
    "factorize",
    "gbr_matrix",
    "resolve_with_known_normals",
    "uncalibrated",
]


def gbr_matrix(mu: float, nu: float, lam: float) -> np.ndarray:
    """G of the module docstring (lambda != 0)."""
    if lam == 0:
        raise JaxreflError("a GBR transformation needs lambda != 0")
    return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [mu, nu, lam]])


def apply_gbr(b: np.ndarray, lights: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(b', l') = (G^-T b, G l) for scaled normals b (..., 3) and scaled lights (..., 3):
    b' . l' = b . l, so the images do not change."""
    g_inv_t = np.linalg.inv(g).T
    return b @ g_inv_t.T, lights @ g.T


def factorize(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(S^ (N, 3), L^ (K, 3), singular values) of the rank-3 SVD of M (N x K)."""
    m = np.asarray(m, np.float64)
    if m.ndim != 2 or min(m.shape) < 3:
        msg = f"rank-3 factorisation needs >= 3 pixels and images, got {m.shape}"
        raise PSInputError(None, msg)
    if not np.all(np.isfinite(m)):
        raise PSInputError("m", "holds NaN or Inf; leave such pixels out of the SVD (use)")
    u, w, vt = np.linalg.svd(m, full_matrices=False)
    r = np.sqrt(w[:3])
    return u[:, :3] * r, vt[:3].T * r, w


def resolve_with_known_normals(
    s_hat: np.ndarray, normals: np.ndarray, albedo: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """A (3 x 3) with s^_i A ∝ n_i for the calibration pixels (module docstring), and the
    singular values of the linear system (the last one near 0 when the data are consistent;
    its ratio to the second last measures how well A is determined)."""
    s_hat = np.asarray(s_hat, np.float64)
    n = np.asarray(normals, np.float64)
    if s_hat.shape[0] < 4:
        raise PSInputError(None, f"{s_hat.shape[0]} calibration pixels; need >= 4 known normals")
    # b = s A, b_m = sum_j s_j A[j, m]; cross(n, b) = 0 row by row, linear in vec(A) (row-major).
    rows = []
    for comp in range(3):
        p, q = (comp + 1) % 3, (comp + 2) % 3
        # (n x b)_comp = n_p b_q - n_q b_p
        coef = np.zeros((s_hat.shape[0], 3, 3))
        coef[:, :, q] += n[:, p : p + 1] * s_hat
        coef[:, :, p] -= n[:, q : q + 1] * s_hat
        rows.append(coef.reshape(-1, 9))
    d = np.concatenate(rows)
    _, sv, vt = np.linalg.svd(d, full_matrices=False)
    a = vt[-1].reshape(3, 3)
    b = s_hat @ a
    if np.mean(np.sum(b * n, axis=1)) < 0:
        a = -a
        b = -b
    scale = albedo / np.median(np.linalg.norm(b, axis=1))
    return a * scale, sv


@dataclass(frozen=True)
class UncalibratedResult:
    """normals (N, 3), albedo (N,), light directions (K, 3), relative intensities (K,),
    the matrix A, and the singular values of M (rank-3 check: w[3] / w[2] small)."""

    normals: np.ndarray
    albedo: np.ndarray
    lights: np.ndarray
    intensities: np.ndarray
    a: np.ndarray
    singular_values: np.ndarray


def uncalibrated(
    m: np.ndarray,
    use: np.ndarray,
    calib: np.ndarray,
    calib_normals: np.ndarray,
    calib_albedo: float = 1.0,
) -> UncalibratedResult:
    """Uncalibrated PS of N pixels (M: N x K grey values).

    use:   (N,) bool, pixels free of shadows and highlights that enter the SVD
    calib: (N,) bool, pixels with known normals ``calib_normals`` ((n_calib, 3), in the
           order of ``np.flatnonzero(calib)``), all of them inside ``use``
    """
    m = np.asarray(m, np.float64)
    use = np.asarray(use, bool)
    calib = np.asarray(calib, bool)
    if use.shape != m.shape[:1] or calib.shape != m.shape[:1]:
        raise PSInputError(
            "use" if use.shape != m.shape[:1] else "calib",
            f"must be (N,) = ({m.shape[0]},) booleans, got {use.shape} and {calib.shape}",
        )
    if np.any(calib & ~use):
        raise PSInputError(None, "calibration pixels must be among the pixels used in the SVD")
    cn = np.asarray(calib_normals, np.float64)
    if cn.shape != (int(calib.sum()), 3) or not np.all(np.isfinite(cn)):
        raise PSInputError(
            "calib_normals",
            f"must be ({int(calib.sum())}, 3) finite normals, one per calibration pixel; "
            f"got shape {cn.shape}",
        )
    if not np.all(np.isfinite(m[~use])):
        raise PSInputError(
            "m", "holds NaN or Inf outside the pixels used; every value must be finite"
        )
    s_use, l_hat, w = factorize(m[use])
    # S^ for every pixel: least-squares projection of its row onto L^ (exact for rows in use).
    s_all = np.linalg.lstsq(l_hat, m.T, rcond=None)[0].T
    s_all[use] = s_use
    a, _ = resolve_with_known_normals(s_all[calib], calib_normals, calib_albedo)
    b = s_all @ a
    rho = np.linalg.norm(b, axis=1)
    normals = b / np.where(rho > 0, rho, 1.0)[:, None]
    if not np.all(np.isfinite(a)) or np.linalg.cond(a) > 1e12:
        raise PSInputError(
            "calib_normals",
            "the known normals do not determine the 3 x 3 ambiguity (the system is singular); "
            "give >= 4 calibration pixels whose normals are not coplanar",
        )
    lights = l_hat @ np.linalg.inv(a).T
    e = np.linalg.norm(lights, axis=1)
    return UncalibratedResult(normals, rho, lights / e[:, None], e, a, w)

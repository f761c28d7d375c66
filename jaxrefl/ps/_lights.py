"""Light calibration: directions (and intensities) of distant lights from a mirror sphere's
highlights or from the shading of a Lambertian sphere, each with its uncertainty.

**Chrome sphere.** A mirror sphere reflects each distant light towards the orthographic
camera (view v = (0, 0, 1)) at the point whose normal bisects light and view. With the
sphere's circle (centre, radius r: :func:`jaxrefl.ps.fit_circle`) and the highlight's
centroid (row h_r, column h_c) in the frame of :mod:`jaxrefl.ps`:

    n = ((h_c - c_col) / r, -(h_r - c_row) / r, sqrt(1 - ...)),     l = 2 (n . v) n - v

(the law of reflection). The highlight is the set of mask pixels at >= ``threshold`` of the
image's maximum; its centroid's variance is the spread of those pixels over their number
plus the quantisation variance 1/12 px^2. The covariance of l is J Sigma J^T with J the
Jacobian of (h_r, h_c, c_row, c_col, r) -> l (central differences) and Sigma the
block-diagonal covariance of the centroid and of the circle fit.

**Lambertian sphere (or any >= 4 points of known normal).** Each image k satisfies
I_ik = n_i . L_k at lit points (L_k = E_k rho l_k), a linear least-squares problem for L_k
from the points that are lit (I above ``shadow`` times the image's maximum and n . L_k > 0,
refined by re-solving twice), with covariance sigma^2 (N^T N)^-1, sigma^2 = RSS / (m - 3).
The direction is L_k / |L_k| (covariance through its Jacobian (I - l l^T) / |L|) and the
intensity per channel the least-squares scale given that direction, relative to the
albedo of the sphere.

Uncertainties are reported as the 1-sigma angle, sqrt(trace of the covariance of l in the
tangent plane), in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._capture import PSInputError
from ._eval import angular_error
from ._sphere import Circle, fit_circle, sphere_normals

__all__ = [
    "LightCalibration",
    "chrome_sphere_lights",
    "lambertian_sphere_lights",
    "lights_from_shading",
]


@dataclass(frozen=True)
class LightCalibration:
    """directions (K, 3) unit, camera frame; intensities (K, C) relative or None; cov
    (K, 3, 3) of the directions; ``method``; ``circle`` of the sphere when there is one."""

    directions: np.ndarray
    intensities: np.ndarray | None
    cov: np.ndarray
    method: str
    circle: Circle | None = None

    @property
    def std_deg(self) -> np.ndarray:
        """1-sigma angular uncertainty of each direction, degrees (module docstring)."""
        d = self.directions
        p = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
        t = np.einsum("kij,kjl,kli->k", p, self.cov, p)
        return np.degrees(np.sqrt(np.maximum(t, 0.0)))

    def error_deg(self, reference: np.ndarray) -> np.ndarray:
        """Angle to reference directions (K, 3), degrees."""
        return angular_error(self.directions, reference)

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "directions": self.directions.tolist(),
            "std_deg": self.std_deg.tolist(),
            "intensities": None if self.intensities is None else self.intensities.tolist(),
        }


def _grey(images: np.ndarray) -> np.ndarray:
    a = np.asarray(images, np.float64)
    return a.mean(axis=-1) if a.ndim == 4 else a


def _mirror(x: np.ndarray) -> np.ndarray:
    """(h_r, h_c, c_row, c_col, r) -> reflected light direction."""
    hr, hc, cr, cc, r = x
    u, v = (hc - cc) / r, -(hr - cr) / r
    s = u * u + v * v
    # A centroid just outside the disc (rounding at the rim) is pulled onto it.
    nz = np.sqrt(max(1.0 - s, 0.0))
    n = np.array([u, v, nz]) / np.sqrt(max(s, 1.0) if s > 1.0 else 1.0)
    return 2.0 * n[2] * n - np.array([0.0, 0.0, 1.0])


def chrome_sphere_lights(
    images: np.ndarray,
    mask: np.ndarray,
    threshold: float = 0.9,
    circle: Circle | None = None,
    names: list[str] | None = None,
) -> LightCalibration:
    """Light directions from the highlights on a mirror sphere: ``images`` (K, H, W[, C])
    linear, ``mask`` (H, W) the sphere (module docstring). Raises :class:`PSInputError`
    naming the image where no highlight is found inside the mask."""
    g = _grey(images)
    mask = np.asarray(mask, bool)
    circle = fit_circle(mask, "chrome sphere mask") if circle is None else circle
    rows, cols = np.mgrid[: mask.shape[0], : mask.shape[1]]
    dirs, covs = [], []
    for k in range(g.shape[0]):
        img = np.where(mask, g[k], -np.inf)
        peak = img.max()
        where = names[k] if names else f"chrome image {k}"
        if not np.isfinite(peak) or peak <= 0:
            raise PSInputError(where, "no highlight inside the sphere mask (image is dark)")
        sel = img >= threshold * peak
        wts = g[k][sel]
        hr = float(np.average(rows[sel], weights=wts))
        hc = float(np.average(cols[sel], weights=wts))
        npx = int(sel.sum())
        var_r = np.average((rows[sel] - hr) ** 2, weights=wts) / npx + 1.0 / 12.0
        var_c = np.average((cols[sel] - hc) ** 2, weights=wts) / npx + 1.0 / 12.0
        x = np.array([hr, hc, circle.row, circle.col, circle.radius])
        sigma = np.zeros((5, 5))
        sigma[0, 0], sigma[1, 1] = var_r, var_c
        sigma[2:, 2:] = circle.cov
        jac = np.zeros((3, 5))
        for i in range(5):
            step = np.zeros(5)
            step[i] = 1e-3
            jac[:, i] = (_mirror(x + step) - _mirror(x - step)) / 2e-3
        dirs.append(_mirror(x))
        covs.append(jac @ sigma @ jac.T)
    d = np.array(dirs)
    return LightCalibration(
        d / np.linalg.norm(d, axis=1, keepdims=True), None, np.array(covs), "chrome_sphere", circle
    )


def lights_from_shading(
    values: np.ndarray, normals: np.ndarray, shadow: float = 0.05, refine: int = 2
) -> LightCalibration:
    """Lights from K images of M >= 4 points of known normal on a Lambertian surface:
    ``values`` (K, M) or (K, M, C) linear, ``normals`` (M, 3) (module docstring)."""
    v = np.asarray(values, np.float64)
    if v.ndim == 2:
        v = v[..., None]
    n = np.asarray(normals, np.float64)
    k, m, _ = v.shape
    if n.shape != (m, 3):
        raise PSInputError(None, f"normals are {n.shape}, expected ({m}, 3) for {m} points")
    if m < 4:
        raise PSInputError(None, f"{m} points of known normal; need >= 4 to calibrate lights")
    for name, x in (("values", v), ("normals", n)):
        if not np.all(np.isfinite(x)):
            raise PSInputError(name, "holds NaN or Inf; every value must be finite")
    g = v.mean(axis=-1)
    dirs, covs, ints = [], [], []
    for j in range(k):
        lit = g[j] > shadow * g[j].max()
        sol = np.zeros(3)
        for _ in range(refine + 1):
            if lit.sum() < 4:
                raise PSInputError(None, f"image {j}: {int(lit.sum())} lit points; need >= 4")
            a = n[lit]
            sol, *_ = np.linalg.lstsq(a, g[j][lit], rcond=None)
            lit = lit & (n @ sol > 0)
        a = n[lit]
        if lit.sum() < 3 or np.linalg.matrix_rank(a) < 3 or not np.linalg.norm(sol) > 0:
            raise PSInputError(
                "normals",
                f"image {j}: the normals of its lit points are coplanar (or too few), so they "
                "do not determine a light; use points with normals spanning 3 directions",
            )
        res = g[j][lit] - a @ sol
        dof = max(int(lit.sum()) - 3, 1)
        cov_l = float(res @ res) / dof * np.linalg.inv(a.T @ a)
        norm = np.linalg.norm(sol)
        d = sol / norm
        jac = (np.eye(3) - np.outer(d, d)) / norm
        dirs.append(d)
        covs.append(jac @ cov_l @ jac.T)
        shade = a @ d
        ints.append((v[j][lit] * shade[:, None]).sum(0) / (shade @ shade))
    return LightCalibration(np.array(dirs), np.array(ints), np.array(covs), "lambertian_points")


def lambertian_sphere_lights(
    images: np.ndarray,
    mask: np.ndarray,
    margin: float = 3.0,
    stride: int = 2,
    shadow: float = 0.05,
    circle: Circle | None = None,
) -> LightCalibration:
    """Lights from a Lambertian sphere: ``images`` (K, H, W[, C]), ``mask`` (H, W); the
    normals come from the circle fitted to the mask, every ``stride``-th pixel at least
    ``margin`` pixels inside the rim is used."""
    mask = np.asarray(mask, bool)
    circle = fit_circle(mask, "sphere mask") if circle is None else circle
    normals, inside = sphere_normals(mask.shape, circle)
    rows, cols = np.mgrid[: mask.shape[0], : mask.shape[1]]
    dist = np.hypot(rows - circle.row, cols - circle.col)
    sel = mask & inside & (dist <= circle.radius - margin)
    sel &= (rows % stride == 0) & (cols % stride == 0)
    imgs = np.asarray(images, np.float64)
    vals = imgs[:, sel]
    cal = lights_from_shading(vals, normals[sel], shadow=shadow)
    return LightCalibration(cal.directions, cal.intensities, cal.cov, "lambertian_sphere", circle)

"""The flash as a light to estimate: its offset from the lens, a gain per photo, their posterior.

Every capture layout states where the flash was (for a phone: at the lens) and one power for
every photo. A phone's flash sits 0.5-1.5 cm from its lens, and phones change exposure and
flash output from shot to shot. The capture-level light parameters are

    p_k = p_k^stated + R_k d        (cm)      the flash position of photo k
    I_kc = g_k I_kc^stated                    its intensity

* ``d`` (3,): the flash's offset from the stated position. Frame: the camera's (x right,
  y down, z forward) where the capture gives each photo's camera orientation R_k (the
  ``camera_orientation`` of ``calibration.json``, written by ``jaxrefl capture``: a phone
  turned between shots carries its flash with it); otherwise the sample's (x, y in the
  sample plane, z up: R_k = I), which assumes the phone is held the same way for every
  photo.
* ``g_k`` (K,): the photo's gain (flash output times exposure) relative to the stated power.
  Their geometric mean over the training photos is fixed at that of their prior means (a
  common factor of every gain is a common factor of every map, which the photos cannot
  tell apart). Prior: log g_k ~ N(log(H_k / H_ref), s^2), with H_k = t_k ISO_k / N_k^2 the
  EXIF exposure (:mod:`jaxrefl.phone._exif`) where every photo gives it, H_ref their
  geometric mean, and s = :data:`GAIN_LOG_STD_EXIF` (flash output still varies); without
  EXIF, H_k / H_ref = 1 and s = :data:`GAIN_LOG_STD`. A held-out photo keeps its prior
  gain: estimating it would use the photo.
* Prior on ``d``: N(0, diag(:data:`OFFSET_PRIOR_CM`)^2): a flash within a few cm of the
  lens in x and y, within a few mm of the lens's plane in z (the phone's normal in either
  frame, when the phone faces the sample). z changes every photo's irradiance nearly alike,
  which the maps absorb: the photos alone pin it to a few mm at best.

Estimation (profiling, variable projection: Golub & Pereyra 1973). Given the light, each
pixel and channel of a random pixel subsample is a linear least-squares problem in a basis
of M = 1 + len(alphas) columns: the diffuse term E cos_i / pi and unit-F0 GGX lobes
(height-correlated Smith, no Fresnel) at a few fixed widths spanning the capture's
resolvable width (:func:`jaxrefl.svbrdf.resolvable_alpha`) to :data:`ALPHA_MAX`, whose
combinations follow a per-pixel lobe width between them; the residual of that solve, as a
function of (d, log g), is minimised by Levenberg-Marquardt, its Jacobian by forward-mode
differentiation through the solve. Only measured observations enter (saturated, dark,
masked, held-out photos: weight 0). The light enters the compiled program as an array
argument: one compile serves every light value of every optimiser step.

Noise: a first fit with unit weights; its residuals, inflated by the per-pixel degrees of
freedom sqrt(n / (n - M)), give a noise scale linear in the prediction, sigma(y) = c0 + c1 y
(least squares of sqrt(pi / 2) |e| on y), and a second fit weighs each observation by
1 / sigma^2. Laplace: the covariance of (d, log g) is (J^T J + P)^-1 at the optimum, J the
whitened profiled residual's Jacobian (its Gauss-Newton curvature is the Schur complement
of the per-pixel parameters: the light's marginal curvature) and P the prior's precision;
gains' std by the delta method, g std(log g).

Kept only where held-out observations support it (``auto``, :func:`estimate_light`): the
subsample is split into two halves of pixels; for each candidate (``fixed``, ``offset``,
``offset+gains``) the light is estimated on one half and scored on the other by
leave-one-photo-out over the training photos (each pixel's basis coefficients fitted on the
other photos, photo j predicted; photo j's gain was estimated on the other half's pixels),
and the halves swap. The simplest candidate within :data:`jaxrefl.svbrdf.TOLERANCE`
(relative) of the lowest RMSE wins, as ``auto`` chooses models.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl import brdf
from jaxrefl._errors import JaxreflError
from jaxrefl._names import LIGHT_CHOICES
from jaxrefl.io import ObsStatus

from ._data import resolvable_alpha

__all__ = [
    "LIGHT_CHOICES",
    "LIGHT_MODES",
    "GainPrior",
    "LightEstimate",
    "LightProblem",
    "estimate_light",
    "gain_prior",
    "light_problem",
]

LIGHT_MODES: tuple[str, ...] = LIGHT_CHOICES[:3]  # the estimates; "auto" picks one
# Prior std of the offset's components (cm): a flash within a few cm of the lens, in the
# plane of the phone's back (z, the normal of that plane when the phone faces the sample,
# moves the flash by the lens bump's millimetres at most).
OFFSET_PRIOR_CM = (3.0, 3.0, 0.3)
GAIN_LOG_STD = 0.5  # no EXIF: exposure and flash output free within about x/ 1.6
GAIN_LOG_STD_EXIF = 0.05  # EXIF exposure known: the flash's own output varies by a few %
ALPHA_MAX = 1.0
WIDTHS = 16  # the grid of log widths a pixel's lobe is first sought among
REFINE_STEPS = 3
SELECTION_PIXELS = 2048  # per half of the subsample
# Ridge on the unit-diagonal normal equations of each pixel's solve: the lobe and the
# diffuse column are nearly collinear where a pixel never sees its highlight, and 1e-6
# bounds the condition number at 2e6 (float64) while biasing a coefficient by < 1e-6.
RIDGE = 1e-6
_LOBE = brdf.get(
    "cook_torrance", distribution="ggx", shadowing="smith_height_correlated", fresnel="none"
)
_Z90 = 1.6448536269514722  # the standard normal's 95% quantile: a central 90% interval


class LightData(NamedTuple):
    """A pixel subsample's observations and the capture's stated geometry (float64)."""

    points: jax.Array  # (N, 3)
    obs: jax.Array  # (N, K, C)
    usable: jax.Array  # (N, K, C) 1 where measured (status ok), else 0
    camera: jax.Array  # (K, 3)
    light: jax.Array  # (K, 3) stated flash positions
    power: jax.Array  # (K, C) stated intensities
    rot: jax.Array  # (K, 3, 3) frame of the offset (module docstring)
    grid: jax.Array  # (G,) log widths each pixel's lobe is first sought among


def _unit(v):
    r2 = jnp.sum(v * v, -1, keepdims=True)
    # A point exactly at the light or camera has no direction; the capture checks refuse it,
    # the guard keeps the gradient finite.
    return v / jnp.sqrt(jnp.where(r2 > 0, r2, 1.0)), r2[..., 0]


def _geometry(x, d: LightData):
    """(wi, wo (N, K, 3), s = E cos_i (N, K, C)) under the light x = (d (3), log g (K))."""
    off, log_g = x[:3], x[3:]
    lp = d.light + jnp.einsum("kij,j->ki", d.rot, off)
    wi, r2 = _unit(lp[None] - d.points[:, None])
    wo, _ = _unit(d.camera[None] - d.points[:, None])
    # A light at or below the plane lights nothing (cos_i 0); r^2 > 0 off the light itself.
    cos_i = jnp.maximum(wi[..., 2], 0.0)
    s = d.power[None] * jnp.exp(log_g)[None, :, None] * (cos_i / jnp.maximum(r2, 1e-12))[..., None]
    return wi, wo, s


def _columns(log_alpha, wi, wo, s):
    """(N, K, C, 2) radiance of the diffuse column (E cos_i / pi) and of a unit-F0 GGX lobe of
    width exp(log_alpha) (N,) per pixel."""
    n, k = wi.shape[:2]
    one = jnp.ones((n, k, 1), s.dtype)
    a = jnp.broadcast_to(jnp.exp(log_alpha)[:, None], (n, k))
    lobe = _LOBE.eval({"specular": one, "alpha": a}, wi, wo) * s
    return jnp.stack([s / jnp.pi, lobe], -1)


def _solve(b, y, w):
    """Per (pixel, channel): the non-negative coefficients of min sum_k w (y - b c)^2, c >= 0,
    exactly: the best feasible least-squares solution over the supports {both, one, the
    other} (the optimum is the least-squares solution on its own support), on the
    unit-diagonal normal equations with ridge :data:`RIDGE`. b (N, K, C, 2), y, w (N, K, C);
    returns (N, C, 2)."""
    g = jnp.einsum("nkcm,nkc,nkcl->ncml", b, w, b)
    t = jnp.einsum("nkcm,nkc,nkc->ncm", b, w, y)
    dg = jnp.diagonal(g, axis1=-2, axis2=-1)
    # A column no observation sees (diagonal 0) is solved as 0 through the ridge alone.
    sc = 1.0 / jnp.sqrt(jnp.where(dg > 0, dg, 1.0))
    a = g * sc[..., :, None] * sc[..., None, :]
    ts = t * sc
    a00, a01, a11 = a[..., 0, 0] + RIDGE, a[..., 0, 1], a[..., 1, 1] + RIDGE
    det = a00 * a11 - a01 * a01  # >= 2 RIDGE - RIDGE^2 > 0 on unit diagonals
    both = jnp.stack([a11 * ts[..., 0] - a01 * ts[..., 1], a00 * ts[..., 1] - a01 * ts[..., 0]], -1)
    both = both / det[..., None]
    only0 = jnp.stack([jnp.maximum(ts[..., 0], 0.0) / a00, jnp.zeros_like(det)], -1)
    only1 = jnp.stack([jnp.zeros_like(det), jnp.maximum(ts[..., 1], 0.0) / a11], -1)
    # The decrease of the objective from c = 0 at a support's optimum is c.t.
    g2 = jnp.where(jnp.all(both >= 0.0, -1), jnp.sum(both * ts, -1), -jnp.inf)
    g0, g1 = jnp.sum(only0 * ts, -1), jnp.sum(only1 * ts, -1)
    c = jnp.where(
        ((g2 >= g0) & (g2 >= g1))[..., None], both, jnp.where((g0 >= g1)[..., None], only0, only1)
    )
    return c * sc


def _sse(log_alpha, wi, wo, s, y, w):
    """(N,) weighted squared error of each pixel's non-negative fit at its width."""
    b = _columns(log_alpha, wi, wo, s)
    c = _solve(b, y, w)
    e = y - jnp.einsum("nkcm,ncm->nkc", b, c)
    return jnp.sum(w * e * e, (1, 2))


def _parabola(x0, h, f_m, f_0, f_p):
    """The vertex of the parabola through (x0 - h, f_m), (x0, f_0), (x0 + h, f_p), within
    [x0 - h, x0 + h]; x0 where the three do not curve upwards."""
    curv = f_m - 2.0 * f_0 + f_p
    # No upward curvature: no vertex to move to (x0 is the best of the three).
    ok = curv > 0
    shift = 0.5 * h * (f_m - f_p) / jnp.where(ok, curv, 1.0)
    return x0 + jnp.where(ok, jnp.clip(shift, -h, h), 0.0)


def _width(wi, wo, s, y, w, grid):
    """Each pixel's log width: the best of ``grid`` (G,, evenly spaced), then
    :data:`REFINE_STEPS` parabolic steps through its neighbours at half the spacing each
    time (a step that does not lower the pixel's error is not taken)."""
    n = y.shape[0]
    errs = jax.lax.map(lambda la: _sse(jnp.full(n, la), wi, wo, s, y, w), grid)
    i = jnp.argmin(errs, 0)
    g = grid.shape[0]
    f_0 = jnp.take_along_axis(errs, i[None], 0)[0]
    # At the grid's ends the missing neighbour counts as the end itself (no curvature).
    f_m = jnp.take_along_axis(errs, jnp.maximum(i - 1, 0)[None], 0)[0]
    f_p = jnp.take_along_axis(errs, jnp.minimum(i + 1, g - 1)[None], 0)[0]
    h = (grid[-1] - grid[0]) / (g - 1)
    la = grid[i]

    def f(v):
        return _sse(jnp.clip(v, grid[0], grid[-1]), wi, wo, s, y, w)

    for _ in range(REFINE_STEPS):
        cand = jnp.clip(_parabola(la, h, f_m, f_0, f_p), grid[0], grid[-1])
        f_c = f(cand)
        better = f_c < f_0
        la, f_0 = jnp.where(better, cand, la), jnp.where(better, f_c, f_0)
        h = 0.5 * h
        f_m, f_p = f(la - h), f(la + h)
    return la


@jax.jit
def _widths(x, d: LightData, w):
    """(N,) each pixel's log width under the light x (:func:`_width`)."""
    wi, wo, s = _geometry(x, d)
    return _width(wi, wo, s, d.obs, w, d.grid)


def _residuals(x, d: LightData, w, la):
    """Whitened profiled residuals sqrt(w) (y - b c) (N, K, C) and predictions, each pixel's
    width exp(la) (N,) and its coefficients the non-negative least-squares ones."""
    wi, wo, s = _geometry(x, d)
    b = _columns(la, wi, wo, s)
    c = _solve(b, d.obs, w)
    pred = jnp.einsum("nkcm,ncm->nkc", b, c)
    return jnp.sqrt(w) * (d.obs - pred), pred


@jax.jit
def _res_jac(x, d: LightData, w, la):
    """(residuals (R,), Jacobian (R, 3 + K), predictions (N, K, C)) at the light x, each
    pixel's width at its optimum ``la`` (:func:`_widths`): one compiled program for every
    light value (x is an array argument).

    The widths are profiled out in Gauss-Newton form: each pixel's rows of d r / d x lose
    their projection on that pixel's d r / d la (the Schur complement of its width in
    J^T J), as the non-negative least squares profiles out the coefficients."""
    r, pred = _residuals(x, d, w, la)
    jx = jax.jacfwd(lambda v: _residuals(v, d, w, la)[0])(x)  # (N, K, C, P)
    _, jl = jax.jvp(lambda v: _residuals(x, d, w, v)[0], (la,), (jnp.ones_like(la),))
    num = jnp.einsum("nkc,nkcp->np", jl, jx)
    den = jnp.sum(jl * jl, (1, 2))
    # A pixel whose residuals do not move with its width (no lobe seen) projects nothing.
    coef = num / jnp.where(den > 0, den, 1.0)[:, None]
    jx = jx - jl[..., None] * coef[:, None, None, :]
    return r.ravel(), jx.reshape(r.size, x.shape[0]), pred


@jax.jit
def _loo_sse(x, d: LightData, train):
    """Leave-one-photo-out squared error and count over the training photos ``train`` (K,)
    under the light x, unweighted (radiance units): each pixel's width and coefficients
    fitted on the other training photos."""
    wi, wo, s = _geometry(x, d)
    k = train.shape[0]
    base = d.usable * train[None, :, None]

    def fold(j):
        held = (jnp.arange(k) == j)[None, :, None]
        w = base * (1.0 - held)
        la = _width(wi, wo, s, d.obs, w, d.grid)
        b = _columns(la, wi, wo, s)
        c = _solve(b, d.obs, w)
        e = (jnp.einsum("nkcm,ncm->nkc", b, c) - d.obs) * d.usable * held * train[j]
        return jnp.sum(e * e), jnp.sum(d.usable * held) * train[j]

    sse, n = jax.lax.map(fold, jnp.arange(k))
    return jnp.sum(sse), jnp.sum(n)


@jax.jit
def _batch_cost(xs, d: LightData, w):
    """Sum of squared whitened residuals for a batch of light values xs (B, 3 + K), each
    pixel's width at its optimum."""

    def one(x):
        return jnp.sum(_residuals(x, d, w, _widths(x, d, w))[0] ** 2)

    return jax.lax.map(one, xs)


# ----------------------------------------------------------------------------- priors
@dataclass(frozen=True)
class GainPrior:
    """log g_k ~ N(log_mean_k, log_std^2) (module docstring); ``source`` says where the
    means come from, ``exposure`` the EXIF exposures H_k (s) where every photo gives one."""

    log_mean: np.ndarray
    log_std: float
    source: str
    exposure: tuple[float, ...] | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "exif": self.exposure is not None,
            "exposure_s": None if self.exposure is None else list(self.exposure),
            "relative_exposure": [float(v) for v in np.exp(self.log_mean)],
            "log_std": self.log_std,
        }


def _calibration_photos(capture) -> tuple[Path, list] | None:
    """(path, its ``photos`` list) of the ``calibration.json`` that ``jaxrefl capture`` keeps
    beside a capture, or None where there is none."""
    src = capture.source
    if src is None:
        return None
    folder = Path(src) if Path(src).is_dir() else Path(src).parent
    path = folder / "calibration.json"
    if not path.is_file():
        return None
    try:
        return path, list(json.loads(path.read_text())["photos"])
    except (ValueError, KeyError, TypeError) as e:
        raise JaxreflError(
            f"{path}: no readable photos list ({e}); rewrite the file with jaxrefl capture "
            "or remove it"
        ) from None


def _calibration_exposures(capture) -> list[float | None] | None:
    """EXIF exposures kept in ``calibration.json`` beside a capture of ``jaxrefl capture``."""
    found = _calibration_photos(capture)
    if found is None:
        return None
    path, photos = found
    try:
        return [(p.get("metadata") or {}).get("exposure") for p in photos][: capture.n_photos]
    except AttributeError as e:
        raise JaxreflError(
            f"{path}: photos[k].metadata.exposure cannot be read ({e}); rewrite the file "
            "with jaxrefl capture or remove it"
        ) from None


def _orientations(capture) -> np.ndarray | None:
    """(K, 3, 3) camera-to-sample rotations from ``calibration.json``, or None."""
    found = _calibration_photos(capture)
    if found is None:
        return None
    try:
        rot_a = np.asarray([p["camera_orientation"] for p in found[1]], np.float64)
        rot_a = rot_a[: capture.n_photos]
    except (ValueError, KeyError, TypeError):
        return None
    return rot_a if rot_a.shape == (capture.n_photos, 3, 3) else None


def gain_prior(capture) -> GainPrior:
    """The gains' prior of ``capture`` (module docstring): EXIF exposures from
    ``calibration.json`` beside the capture, else from the photo files' own EXIF (JPEG or
    TIFF, :func:`jaxrefl.phone.read_photo_meta`); absent unless every photo gives one."""
    k = capture.n_photos
    exposures = _calibration_exposures(capture)
    where = "calibration.json"
    if exposures is None and len(capture.files) == k:
        from jaxrefl.phone import read_photo_meta

        where = "the photos' EXIF"
        exposures = []
        for f in capture.files:
            try:
                exposures.append(read_photo_meta(f).exposure)
            except OSError:  # not an image Pillow reads (an EXR): no EXIF
                exposures.append(None)
    known = [e for e in (exposures or []) if e is not None and e > 0]
    if exposures is not None and len(known) == k:
        h = np.asarray(known, np.float64)
        log_h = np.log(h)
        return GainPrior(
            log_h - log_h.mean(),
            GAIN_LOG_STD_EXIF,
            f"EXIF exposure t ISO / N^2 of every photo ({where})",
            tuple(float(v) for v in h),
        )
    n = len(known)
    why = (
        "no EXIF exposure: every photo's prior gain is 1"
        if n == 0
        else f"EXIF exposure in {n} of {k} photos only: every photo's prior gain is 1"
    )
    return GainPrior(np.zeros(k), GAIN_LOG_STD, why)


# ----------------------------------------------------------------------------- problem
def _light_data(capture, pick: np.ndarray, rot: np.ndarray, alphas) -> LightData:
    _k, _h, w, _c = capture.shape
    rows, cols = np.divmod(pick, w)
    obs = np.moveaxis(capture.images[:, rows, cols], 0, 1).astype(np.float64)
    usable = np.moveaxis(capture.status[:, rows, cols] == ObsStatus.OK, 0, 1)
    return LightData(
        points=jnp.asarray(capture.points[rows, cols]),
        obs=jnp.asarray(np.where(usable, obs, 0.0)),
        usable=jnp.asarray(usable, jnp.float64),
        camera=jnp.asarray(capture.camera_pos),
        light=jnp.asarray(capture.light_pos),
        power=jnp.asarray(capture.light_power),
        rot=jnp.asarray(rot),
        grid=jnp.asarray(np.log(alphas), jnp.float64),
    )


@dataclass
class LightProblem:
    """The light's estimation problem on pixel halves of one capture (module docstring).

    halves: the LightData of each half (one compiled shape); train (K,) bool; prior: the
    gains'; rot: the offset's frame (K, 3, 3); frame: its description.
    """

    halves: list[LightData]
    train: np.ndarray
    prior: GainPrior
    frame: str
    weights: list[jax.Array] = field(default_factory=list)

    @property
    def k(self) -> int:
        return int(self.train.shape[0])

    def embed(self, mode: str) -> tuple[np.ndarray, np.ndarray]:
        """(x0 (3 + K,), A (3 + K, P)): x = x0 + A theta for the mode's free parameters theta:
        the offset (3), then K_train - 1 coordinates of the training log gains in the
        subspace that keeps their sum (an orthonormal basis: the prior stays isotropic)."""
        k = self.k
        x0 = np.concatenate([np.zeros(3), self.prior.log_mean])
        cols = [] if mode == "fixed" else [np.eye(3 + k)[:, :3]]
        idx = np.flatnonzero(self.train)
        if mode == "offset+gains" and idx.size > 1:
            # The last K_train - 1 columns of a QR basis of [1, I] span the sum-zero subspace.
            q, _ = np.linalg.qr(np.concatenate([np.ones((idx.size, 1)), np.eye(idx.size)], 1))
            basis = np.zeros((3 + k, idx.size - 1))
            basis[3 + idx] = q[:, 1 : idx.size]
            cols.append(basis)
        a = np.concatenate(cols, 1) if cols else np.zeros((3 + k, 0))
        return x0, a

    def prior_precision(self, mode: str) -> np.ndarray:
        _x0, a = self.embed(mode)
        n_off = 3 if mode != "fixed" else 0
        p = np.full(a.shape[1], 1.0 / self.prior.log_std**2)
        p[:n_off] = 1.0 / np.asarray(OFFSET_PRIOR_CM) ** 2
        return p

    def unit_weights(self, halves: list[int]) -> list[jax.Array]:
        tr = jnp.asarray(self.train, jnp.float64)[None, :, None]
        return [self.halves[i].usable * tr for i in halves]

    def residuals(self, theta, mode: str, halves: list[int], weights):
        """(r, J) stacked over ``halves``, prior rows appended, J with respect to theta."""
        x0, a = self.embed(mode)
        x = jnp.asarray(x0 + a @ theta)
        rs, js = [], []
        for i, w in zip(halves, weights, strict=True):
            r, jac, _ = _res_jac(x, self.halves[i], w, _widths(x, self.halves[i], w))
            rs.append(np.asarray(r))
            js.append(np.asarray(jac) @ a)
        sp = np.sqrt(self.prior_precision(mode))
        rs.append(sp * theta)
        js.append(np.diag(sp))
        return np.concatenate(rs), np.concatenate(js)

    def solve(self, mode: str, halves: list[int], weights, theta0=None, max_iter: int = 60):
        """Levenberg-Marquardt (Marquardt's diagonal scaling) from theta0 (default 0)."""
        _x0, a = self.embed(mode)
        theta = np.zeros(a.shape[1]) if theta0 is None else np.asarray(theta0, np.float64)
        r, jac = self.residuals(theta, mode, halves, weights)
        cost = float(r @ r)
        lam = 1e-3
        it = 0
        for it in range(1, max_iter + 1):  # noqa: B007 (the count is reported)
            if theta.size == 0:
                break
            h = jac.T @ jac
            g = jac.T @ r
            dh = np.diag(h)
            # A parameter no residual moves keeps its damping through the tiny floor.
            damp = lam * np.maximum(dh, 1e-12 * max(float(dh.max()), 1e-300))
            step = np.linalg.solve(h + np.diag(damp), -g)
            r_n, j_n = self.residuals(theta + step, mode, halves, weights)
            c_n = float(r_n @ r_n)
            if np.isfinite(c_n) and c_n < cost:
                done = cost - c_n <= 1e-12 * cost
                theta, r, jac, cost = theta + step, r_n, j_n, c_n
                lam = max(lam / 3.0, 1e-9)
                if done:
                    break
            else:
                lam *= 4.0
                if lam > 1e10:  # no step lowers the cost: at the optimum to round-off
                    break
        return theta, r, jac, it

    def predictions(self, theta, mode: str, halves: list[int], weights) -> list[np.ndarray]:
        x0, a = self.embed(mode)
        x = jnp.asarray(x0 + a @ theta)
        return [
            np.asarray(_res_jac(x, self.halves[i], w, _widths(x, self.halves[i], w))[2])
            for i, w in zip(halves, weights, strict=True)
        ]

    def noise_weights(self, theta, mode: str, halves: list[int]) -> tuple[list, tuple]:
        """1 / sigma(y)^2 from the unit-weight fit's residuals (module docstring)."""
        unit = self.unit_weights(halves)
        preds = self.predictions(theta, mode, halves, unit)
        e_all, y_all = [], []
        for i, w, p in zip(halves, unit, preds, strict=True):
            w_np = np.asarray(w) > 0
            m = 2 * w_np.shape[-1] + 1  # a pixel's albedo and F0 per channel, and its width
            n_obs = w_np.sum((1, 2), keepdims=True)
            # Residuals of a fit shrink by its per-pixel parameters: sqrt(n / (n - M)).
            infl = np.sqrt(n_obs / np.maximum(n_obs - m, 1))
            e = (np.asarray(self.halves[i].obs) - p) * np.broadcast_to(infl, p.shape)
            e_all.append(e[w_np])
            y_all.append(p[w_np])
        e = np.concatenate(e_all)
        y = np.maximum(np.concatenate(y_all), 0.0)
        design = np.stack([np.ones_like(y), y], 1)
        coef, *_ = np.linalg.lstsq(design, np.sqrt(np.pi / 2) * np.abs(e), rcond=None)
        # A noise floor: a fit whose intercept comes out at or below 0 (pure shot noise)
        # keeps 1% of the mean scale, so a dark observation does not get infinite weight.
        scale = float(np.mean(design @ coef))
        c0 = max(float(coef[0]), 0.01 * scale, 1e-12)
        c1 = max(float(coef[1]), 0.0)
        ws = []
        for w, p in zip(unit, preds, strict=True):
            sig = c0 + c1 * np.maximum(p, 0.0)
            ws.append(w / jnp.asarray(sig**2))
        return ws, (c0, c1)

    def loo_rmse(self, theta, mode: str, half: int) -> tuple[float, float]:
        x0, a = self.embed(mode)
        s, n = _loo_sse(jnp.asarray(x0 + a @ theta), self.halves[half], jnp.asarray(self.train))
        return float(s), float(n)

    def log_posterior(self, thetas: np.ndarray, mode: str, weights) -> np.ndarray:
        """Log posterior (up to a constant) of a batch of theta (B, P) on both halves with the
        given weights: the profiled Gaussian likelihood plus the priors (for MCMC checks)."""
        x0, a = self.embed(mode)
        xs = jnp.asarray(x0[None] + np.asarray(thetas) @ a.T)
        total = sum(
            np.asarray(_batch_cost(xs, self.halves[i], w))
            for i, w in zip(range(len(self.halves)), weights, strict=True)
        )
        pr = np.sum(self.prior_precision(mode) * np.asarray(thetas) ** 2, -1)
        return -0.5 * (total + pr)


def light_problem(
    capture, train: np.ndarray, *, n_pixels: int = SELECTION_PIXELS, seed: int = 0
) -> LightProblem:
    """Two pixel halves of ``n_pixels`` each (fewer where the capture is small) with the
    capture's stated geometry and the gains' prior (module docstring)."""
    k, h, w, _c = capture.shape
    total = h * w
    n = min(int(n_pixels), total // 2)
    if n < 1:
        raise JaxreflError("the light needs a capture of two pixels or more")
    pick = np.random.default_rng(seed).permutation(total)[: 2 * n]
    rot = _orientations(capture)
    if rot is None:
        rot = np.broadcast_to(np.eye(3), (k, 3, 3)).copy()
        frame = "sample: x, y in the sample plane, z up (cm); the same for every photo"
    else:
        frame = (
            "camera: x right, y down, z forward (cm), each photo's orientation from "
            "calibration.json"
        )
    alphas = np.geomspace(min(resolvable_alpha(capture), ALPHA_MAX), ALPHA_MAX, WIDTHS)
    halves = [_light_data(capture, np.sort(part), rot, alphas) for part in (pick[:n], pick[n:])]
    return LightProblem(halves, np.asarray(train, bool), gain_prior(capture), frame)


# ----------------------------------------------------------------------------- result
@dataclass(frozen=True)
class LightEstimate:
    """The capture's light (module docstring) and the evidence for it.

    mode:        what was estimated: ``fixed``, ``offset`` or ``offset+gains``
    asked:       the job's ``light`` (``auto`` or one of the modes)
    offset_cm:   d (3,), in ``frame``; offset_std_cm its Laplace std (None: fixed)
    photo_gain:  g (K,); photo_gain_std (K,) (0 for a gain not estimated but known from
                 EXIF, its prior's std where held out, None when fixed)
    estimated:   (K,) whether each photo's gain was estimated
    corr:        correlation matrix over ``labels`` (offset x, y, z, then log gains)
    cv_rmse:     held-out RMSE per candidate (``auto``)
    why:         one sentence, the form of ``auto``'s
    """

    mode: str
    asked: str
    offset_cm: np.ndarray
    photo_gain: np.ndarray
    offset_std_cm: np.ndarray | None = None
    photo_gain_std: np.ndarray | None = None
    estimated: np.ndarray | None = None
    labels: tuple[str, ...] = ()
    corr: np.ndarray | None = None
    cov: np.ndarray | None = None
    cv_rmse: dict[str, float] = field(default_factory=dict)
    why: str = ""
    frame: str = ""
    prior: GainPrior | None = None
    noise: tuple[float, float] | None = None
    pixels: int = 0
    iterations: int = 0
    rot: np.ndarray | None = None

    def apply(self, capture):
        """``capture`` with this light: flash at p + R d, power g I (module docstring)."""
        if self.mode == "fixed" and np.all(self.photo_gain == 1.0):
            return capture
        rot = np.broadcast_to(np.eye(3), (capture.n_photos, 3, 3)) if self.rot is None else self.rot
        return replace(
            capture,
            light_pos=capture.light_pos + np.einsum("kij,j->ki", rot, self.offset_cm),
            light_power=capture.light_power * self.photo_gain[:, None],
        )

    def interval90(self) -> dict[str, list[list[float]]] | None:
        """Central 90% Laplace intervals of the offset (cm) and gains (log-normal)."""
        if self.offset_std_cm is None or self.photo_gain_std is None:
            return None
        lo = self.offset_cm - _Z90 * self.offset_std_cm
        hi = self.offset_cm + _Z90 * self.offset_std_cm
        sl = self.photo_gain_std / self.photo_gain
        return {
            "offset_cm": [lo.tolist(), hi.tolist()],
            "photo_gain": [
                (self.photo_gain * np.exp(-_Z90 * sl)).tolist(),
                (self.photo_gain * np.exp(_Z90 * sl)).tolist(),
            ],
        }

    def as_dict(self) -> dict[str, Any]:
        def lst(a):
            return None if a is None else [float(v) for v in np.asarray(a).ravel()]

        return {
            "mode": self.mode,
            "asked": self.asked,
            "frame": self.frame,
            "offset_cm": lst(self.offset_cm),
            "offset_std_cm": lst(self.offset_std_cm),
            "photo_gain": lst(self.photo_gain),
            "photo_gain_std": lst(self.photo_gain_std),
            "photo_gain_estimated": None
            if self.estimated is None
            else [bool(v) for v in self.estimated],
            "interval90": self.interval90(),
            "labels": list(self.labels),
            "corr": None if self.corr is None else np.asarray(self.corr).tolist(),
            "why": self.why,
            "cv_rmse": dict(self.cv_rmse),
            "gain_prior": None if self.prior is None else self.prior.as_dict(),
            "noise_model": None
            if self.noise is None
            else {"sigma0": self.noise[0], "sigma_per_radiance": self.noise[1]},
            "pixels": self.pixels,
            "iterations": self.iterations,
        }


def fixed_light(capture, asked: str, why: str) -> LightEstimate:
    k = capture.n_photos
    return LightEstimate(
        "fixed",
        asked,
        np.zeros(3),
        np.ones(k),
        why=why,
        frame="as the capture states",
    )


def _tolerance() -> float:
    from ._auto import TOLERANCE

    return TOLERANCE


def _final(problem: LightProblem, mode: str, asked: str, cv: dict, why: str) -> LightEstimate:
    both = [0, 1]
    theta, _r, _j, it1 = problem.solve(mode, both, problem.unit_weights(both))
    weights, noise = problem.noise_weights(theta, mode, both)
    theta, _r, jac, it2 = problem.solve(mode, both, weights, theta0=theta)
    problem.weights = weights
    x0, a = problem.embed(mode)
    x = x0 + a @ theta
    # Laplace: the whitened J (prior rows included) gives the posterior precision.
    cov_t = np.linalg.inv(jac.T @ jac)
    cov = a @ cov_t @ a.T
    k = problem.k
    held = ~problem.train
    var = np.diag(cov).copy()
    if mode == "offset+gains":
        var[3 + np.flatnonzero(held)] = problem.prior.log_std**2
    std = np.sqrt(np.maximum(var, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    gain = np.exp(x[3:])
    est = np.zeros(k, bool) if mode != "offset+gains" else problem.train.copy()
    g_std = gain * std[3:] if mode == "offset+gains" else np.zeros(k)
    labels = ("offset_x", "offset_y", "offset_z", *[f"log_gain_{i}" for i in range(k)])
    return LightEstimate(
        mode,
        asked,
        x[:3],
        gain,
        offset_std_cm=std[:3],
        photo_gain_std=g_std,
        estimated=est,
        labels=labels,
        corr=corr,
        cov=cov,
        cv_rmse=cv,
        why=why,
        frame=problem.frame,
        prior=problem.prior,
        noise=noise,
        pixels=int(sum(h.obs.shape[0] for h in problem.halves)),
        iterations=it1 + it2,
        rot=np.asarray(problem.halves[0].rot),
    )


def choose_light(problem: LightProblem) -> tuple[str, dict[str, float]]:
    """Score ``fixed``, ``offset`` and ``offset+gains`` by the cross-fitted held-out RMSE
    (module docstring); returns the simplest within the tolerance of the best, and scores."""
    cv: dict[str, float] = {}
    for mode in LIGHT_MODES:
        sse = cnt = 0.0
        for fit_half, score_half in ((0, 1), (1, 0)):
            if mode == "fixed":
                theta = np.zeros(0)
            else:
                w = problem.unit_weights([fit_half])
                theta = problem.solve(mode, [fit_half], w)[0]
            s, n = problem.loo_rmse(theta, mode, score_half)
            sse, cnt = sse + s, cnt + n
        cv[mode] = float(np.sqrt(sse / cnt)) if cnt > 0 else float("inf")
    best = min(cv.values())
    chosen = next(m for m in LIGHT_MODES if cv[m] <= best * (1.0 + _tolerance()))
    return chosen, cv


def estimate_light(
    capture,
    light: str = "auto",
    holdout: tuple[int, ...] = (),
    *,
    n_pixels: int = SELECTION_PIXELS,
    seed: int = 0,
) -> LightEstimate:
    """The light of ``capture`` (module docstring): ``light`` one of :data:`LIGHT_CHOICES`;
    the photos in ``holdout`` are never looked at. ``fixed`` returns the stated light."""
    if light not in LIGHT_CHOICES:
        raise JaxreflError(f"light must be one of {', '.join(LIGHT_CHOICES)}, not {light!r}")
    if light == "fixed":
        return fixed_light(capture, light, "as asked (light fixed)")
    if capture.light_pos is None:
        return fixed_light(capture, light, "directional lights: there is no flash to place")
    train = np.ones(capture.n_photos, bool)
    train[[i for i in holdout if 0 <= i < capture.n_photos]] = False
    n_train = int(train.sum())
    # Each leave-one-out fold of the score fits a pixel's width and two columns per channel
    # on the other training photos (two at least) and predicts one.
    need = 3
    if light == "auto" and n_train < need:
        return fixed_light(
            capture,
            light,
            f"{n_train} training photos: scoring the light by leave-one-photo-out needs {need}",
        )
    with jax.enable_x64(True):
        problem = light_problem(capture, train, n_pixels=n_pixels, seed=seed)
        if light == "auto":
            chosen, cv = choose_light(problem)
            ranked = sorted(cv.items(), key=lambda kv: kv[1])
            why = (
                f"lowest held-out RMSE over {n_train} training photos, light fitted on one half "
                "of the pixels and scored on the other: "
                + ", ".join(f"{m} {r:.5f}" for m, r in ranked)
            )
            if chosen != "fixed":
                why += f" ({cv[chosen] / cv['fixed']:.2f} x fixed's)"
            if chosen == "fixed":
                est = fixed_light(capture, light, why)
                return replace(est, cv_rmse=cv, prior=problem.prior)
        else:
            chosen, cv = light, {}
            why = f"as asked (light {light}); not scored against fixed"
        return _final(problem, chosen, light, cv, why)

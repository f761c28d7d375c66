"""The flash's profiled estimation problem on a pixel subsample (:mod:`jaxrefl.svbrdf._light`).

Estimation (profiling, variable projection: Golub & Pereyra 1973). Given the light x =
(d (3), log g (K)), each pixel and channel of a random pixel subsample is a non-negative
least-squares problem in two columns: the diffuse term E cos_i / pi and a unit-F0 GGX lobe
(height-correlated Smith, no Fresnel) of the pixel's own width, sought on a grid spanning
the fit's lower bound of alpha (by default the capture's resolvable width,
:func:`jaxrefl.svbrdf.resolvable_alpha`) to :data:`ALPHA_MAX` and refined by parabolic
steps; E = g_k I_k / r^2 the flash's irradiance. The residual of that solve, as a function
of x, is minimised by Levenberg-Marquardt, its Jacobian by forward-mode differentiation
through the solve, each pixel's width profiled in
Gauss-Newton form (its column projected out). Only measured observations enter (saturated,
dark, masked, held-out photos: weight 0). x enters every compiled program as an array
argument: one compile serves every light value of every optimiser step.

Noise: a first fit with unit weights; its residuals, inflated by the per-pixel degrees of
freedom sqrt(n / (n - M)), give a noise scale linear in the prediction, sigma(y) = c0 + c1 y
(least squares of sqrt(pi / 2) |e| on y), and a second fit weighs each observation by
1 / sigma^2 (:meth:`LightProblem.noise_weights`).

Held-out score (:meth:`LightProblem.loo_sse`): under a light, one GGX width shared by every
pixel (the ``pooled`` model's lobe) is chosen on one half of the pixels, the width whose
leave-one-photo-out predictions of that half's training photos are best (as ``pooled``
chooses its width by held-out photos: the width that best fits the training photos is
narrower, and its lobes predict unseen highlights wildly, a score the light's moves then
shuffle at random), and the other half's training photos are predicted one at a time from
the others (leave-one-photo-out), each pixel's coefficients fitted on the other photos, the
predicted photo at its prior gain (a photo the fit did not see has no estimated gain:
scoring it at its estimated one would credit the gains with what no held-out photo gets).
Two nuisance models, each where it holds:

* the estimate needs each pixel's own width: a light fitted under one shared width absorbs
  the widths' spatial variation into its offset, a bias many times its Laplace std where
  the widths vary over the sample;
* the score needs predictions of unseen photos that stay bounded: a pixel's own width is
  pinned only where the pixel sees its highlight, and where the held-out photo alone shows
  it, the pixel's lobe fitted to the tails predicts it wildly (per-pixel GGX predicts the
  real captures' held-out photos several times worse than the shared width:
  ``docs/benchmarks.md``, ``real_captures``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl import brdf
from jaxrefl._errors import JaxreflError
from jaxrefl.io import ObsStatus

from ._data import resolvable_alpha
from ._light_prior import GainPrior, gain_prior, orientations

__all__ = ["LightData", "LightProblem", "light_problem"]

# Prior std of the offset's components (cm): a flash within a few cm of the lens, in the
# plane of the phone's back (z, the normal of that plane when the phone faces the sample,
# moves the flash by the lens bump's millimetres at most).
OFFSET_PRIOR_CM = (3.0, 3.0, 0.3)
# The offset's components the photos estimate: x and y. z is held at its prior (mean 0, std
# OFFSET_PRIOR_CM[2]): it moves every photo's irradiance nearly alike, which the maps absorb,
# so what pulls it is whatever the model misses (on a real capture, centimetres against a
# flash known from the phone's build to lie within millimetres of the lens's plane).
ESTIMATED_OFFSET = 2
ALPHA_MAX = 1.0
WIDTHS = 16  # the grid of log widths a pixel's lobe (or the shared one) is first sought among
REFINE_STEPS = 3
SELECTION_PIXELS = 2048  # per half of the subsample
# Ridge on the unit-diagonal normal equations of each pixel's solve: the lobe and the
# diffuse column are nearly collinear where a pixel never sees its highlight, and 1e-6
# bounds the condition number at 2e6 (float64) while biasing a coefficient by < 1e-6.
RIDGE = 1e-6
# The optimiser stops where a step that fails to lower the cost moves no parameter by more
# than this: 1e-4 cm of offset (1 um) and 1e-4 in a log gain (0.01%), a hundredth of the
# Laplace's std and less beside the reported one. The profiled cost is not smooth at that
# scale (each pixel's width comes from a grid and parabolic steps), so at its optimum every
# step fails, and damping them until lam passes 1e10 costs about twenty evaluations.
STEP_TOL = 1e-4
_LOBE = brdf.get(
    "cook_torrance", distribution="ggx", shadowing="smith_height_correlated", fresnel="none"
)


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
    """(residuals (R,), Jacobian (R, 3 + K), predictions (N, K, C), gradient (3 + K,)) at
    the light x, each pixel's width at its optimum ``la`` (:func:`_widths`): one compiled
    program for every light value (x is an array argument).

    The widths are profiled out in Gauss-Newton form: each pixel's rows of d r / d x lose
    their projection on that pixel's d r / d la (the Schur complement of its width in
    J^T J), as the non-negative least squares profiles out the coefficients. That gives
    the curvature, not the gradient: the projected rows' J^T r also drops each pixel's
    (d r / d la . r), which is 0 only where the width sits at its exact stationary point,
    and the grid and parabolic steps leave it off by a fraction of their spacing. The
    gradient is the profiled cost's own, d r / d x . r at the widths (the envelope theorem:
    the cost does not move with a width at its optimum); an optimiser stepping on the
    projected J^T r stops where that, not the cost's slope, vanishes."""
    r, pred = _residuals(x, d, w, la)
    jx = jax.jacfwd(lambda v: _residuals(v, d, w, la)[0])(x)  # (N, K, C, P)
    grad = jnp.einsum("nkc,nkcp->p", r, jx)
    _, jl = jax.jvp(lambda v: _residuals(x, d, w, v)[0], (la,), (jnp.ones_like(la),))
    num = jnp.einsum("nkc,nkcp->np", jl, jx)
    den = jnp.sum(jl * jl, (1, 2))
    # A pixel whose residuals do not move with its width (no lobe seen) projects nothing.
    coef = num / jnp.where(den > 0, den, 1.0)[:, None]
    jx = jx - jl[..., None] * coef[:, None, None, :]
    return r.ravel(), jx.reshape(r.size, x.shape[0]), pred, grad


@jax.jit
def _cost(x, d: LightData, w):
    """(sum of squared whitened residuals, each pixel's log width (N,)) at the light x, each
    pixel's width at its optimum (:func:`_widths`): the optimiser's trial of a step, without
    the Jacobian (:func:`_res_jac` adds it, at these widths, where the step is taken)."""
    la = _widths(x, d, w)
    return jnp.sum(_residuals(x, d, w, la)[0] ** 2), la


@jax.jit
def _batch_cost(xs, d: LightData, w):
    """Sum of squared whitened residuals for a batch of light values xs (B, 3 + K), each
    pixel's width at its optimum."""

    def one(x):
        return jnp.sum(_residuals(x, d, w, _widths(x, d, w))[0] ** 2)

    return jax.lax.map(one, xs)


def _predict_shared(x, la, d: LightData, w):
    """(N, K, C) predictions under the light x with one width exp(la) for every pixel, each
    pixel's coefficients the non-negative least-squares ones under the weights w."""
    wi, wo, s = _geometry(x, d)
    b = _columns(jnp.full(d.obs.shape[0], la), wi, wo, s)
    return jnp.einsum("nkcm,ncm->nkc", b, _solve(b, d.obs, w))


@jax.jit
def _loo_sse(x, la, d: LightData, train, log_g_prior):
    """Each pixel's leave-one-photo-out squared error and count (K, N), photo by photo (0
    for a photo not in ``train``), over the training photos ``train`` (K,) under the light x
    and the shared width exp(la), unweighted (radiance units): each pixel's coefficients
    fitted on the other training photos, the held-out photo predicted at its prior log gain
    ``log_g_prior`` (K,), as a fit predicts a photo it did not see."""
    k = train.shape[0]
    base = d.usable * train[None, :, None]

    def fold(j):
        held = (jnp.arange(k) == j)[None, :, None]
        x_j = x.at[3 + j].set(log_g_prior[j])
        pred = _predict_shared(x_j, la, d, base * (1.0 - held))
        e = (pred - d.obs) * d.usable * held * train[j]
        return jnp.sum(e * e, (1, 2)), jnp.sum(d.usable * held, (1, 2)) * train[j]

    return jax.lax.map(fold, jnp.arange(k))


@jax.jit
def _loo_width_sse(x, d: LightData, train, log_g_prior):
    """(G,) the leave-one-photo-out squared error of all pixels (:func:`_loo_sse`) under the
    light x with one width for every pixel, at each of the grid's widths."""
    return jax.lax.map(lambda la: jnp.sum(_loo_sse(x, la, d, train, log_g_prior)[0]), d.grid)


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
        the offset's x and y (:data:`ESTIMATED_OFFSET`), then K_train - 1 coordinates of the
        training log gains in the subspace that keeps their sum (an orthonormal basis: the
        prior stays isotropic)."""
        k = self.k
        x0 = np.concatenate([np.zeros(3), self.prior.log_mean])
        cols = [] if mode == "fixed" else [np.eye(3 + k)[:, :ESTIMATED_OFFSET]]
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
        n_off = ESTIMATED_OFFSET if mode != "fixed" else 0
        p = np.full(a.shape[1], 1.0 / self.prior.log_std**2)
        p[:n_off] = 1.0 / np.asarray(OFFSET_PRIOR_CM[:n_off]) ** 2
        return p

    def unit_weights(self, halves: list[int]) -> list[jax.Array]:
        tr = jnp.asarray(self.train, jnp.float64)[None, :, None]
        return [self.halves[i].usable * tr for i in halves]

    def cost(self, theta, mode: str, halves: list[int], weights) -> tuple[float, list]:
        """(r.r of :meth:`residuals`, each half's log widths) at theta, without the Jacobian."""
        x0, a = self.embed(mode)
        x = jnp.asarray(x0 + a @ theta)
        total, widths = 0.0, []
        for i, w in zip(halves, weights, strict=True):
            c, la = _cost(x, self.halves[i], w)
            total += float(c)
            widths.append(la)
        return total + float(np.sum(self.prior_precision(mode) * theta**2)), widths

    def residuals(self, theta, mode: str, halves: list[int], weights, widths=None):
        """(r, J) stacked over ``halves``, prior rows appended, J with respect to theta;
        ``widths``: each half's log widths at theta (:meth:`cost`; None: sought here)."""
        r, jac, _g = self.linearise(theta, mode, halves, weights, widths)
        return r, jac

    def linearise(self, theta, mode: str, halves: list[int], weights, widths=None):
        """(r, J, g) of :meth:`residuals` and g the gradient of r.r / 2 with respect to
        theta, the profiled cost's own (:func:`_res_jac`), not J^T r."""
        x0, a = self.embed(mode)
        x = jnp.asarray(x0 + a @ theta)
        if widths is None:
            widths = [_widths(x, self.halves[i], w) for i, w in zip(halves, weights, strict=True)]
        sp = np.sqrt(self.prior_precision(mode))
        rs, js, grad = [], [], sp * sp * theta
        for i, w, la in zip(halves, weights, widths, strict=True):
            r, jac, _, g = _res_jac(x, self.halves[i], w, la)
            rs.append(np.asarray(r))
            js.append(np.asarray(jac) @ a)
            grad = grad + np.asarray(g) @ a
        rs.append(sp * theta)
        js.append(np.diag(sp))
        return np.concatenate(rs), np.concatenate(js), grad

    def solve(self, mode: str, halves: list[int], weights, theta0=None, max_iter: int = 60):
        """Levenberg-Marquardt (Marquardt's diagonal scaling) from theta0 (default 0), until a
        step lowers the cost by less than 1e-9 of it, or one that fails to lower it moves no
        parameter by more than :data:`STEP_TOL`. A step is tried on the cost alone
        (:meth:`cost`) and the Jacobian computed only where it is taken: at the optimum
        most trials fail (the cost is rough there, :data:`STEP_TOL`), and the Jacobian, a
        forward-mode pass over every light parameter, costs more than the trial itself."""
        _x0, a = self.embed(mode)
        theta = np.zeros(a.shape[1]) if theta0 is None else np.asarray(theta0, np.float64)
        cost, widths = self.cost(theta, mode, halves, weights)
        r, jac, g = self.linearise(theta, mode, halves, weights, widths)
        lam = 1e-3
        it = 0
        for it in range(1, max_iter + 1):  # noqa: B007 (the count is reported)
            if theta.size == 0:
                break
            h = jac.T @ jac
            dh = np.diag(h)
            # A parameter no residual moves keeps its damping through the tiny floor.
            damp = lam * np.maximum(dh, 1e-12 * max(float(dh.max()), 1e-300))
            step = np.linalg.solve(h + np.diag(damp), -g)
            c_n, w_n = self.cost(theta + step, mode, halves, weights)
            if np.isfinite(c_n) and c_n < cost:
                done = cost - c_n <= 1e-9 * cost
                theta, cost = theta + step, c_n
                r, jac, g = self.linearise(theta, mode, halves, weights, w_n)
                lam = max(lam / 3.0, 1e-9)
                if done:
                    break
            else:
                # More damping only shortens the step: once a rejected one moves no
                # parameter by more than STEP_TOL, what is left to gain lies within it.
                if float(np.max(np.abs(step))) <= STEP_TOL:
                    break
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

    def loo_sse(
        self, theta, mode: str, fit_half: int, score_half: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """The held-out score of the light x0 + A theta (module docstring): the shared width
        that predicts ``fit_half``'s training photos best held out in turn under that light
        (the grid's best, then one parabolic step), then each pixel's leave-one-photo-out
        squared error and its count on ``score_half`` with that width, photo by photo
        (K, N)."""
        x0, a = self.embed(mode)
        x = jnp.asarray(x0 + a @ theta)
        train, log_g = jnp.asarray(self.train), jnp.asarray(x0[3:])
        errs = np.asarray(_loo_width_sse(x, self.halves[fit_half], train, log_g))
        grid = np.asarray(self.halves[fit_half].grid)
        i = int(np.argmin(errs))
        la = float(grid[i])
        if 0 < i < grid.size - 1:
            curv = errs[i - 1] - 2.0 * errs[i] + errs[i + 1]
            h = float(grid[1] - grid[0])
            # No upward curvature: the grid's best stays.
            if curv > 0:
                la += float(np.clip(0.5 * h * (errs[i - 1] - errs[i + 1]) / curv, -h, h))
        s, n = _loo_sse(x, la, self.halves[score_half], train, log_g)
        return np.asarray(s), np.asarray(n)

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
    capture,
    train: np.ndarray,
    *,
    n_pixels: int = SELECTION_PIXELS,
    seed: int = 0,
    alpha_min: float | None = None,
) -> LightProblem:
    """Two pixel halves of ``n_pixels`` each (fewer where the capture is small) with the
    capture's stated geometry and the gains' prior (module docstring). Deterministic given
    the capture, ``train`` and ``seed``. The lobes' widths span ``alpha_min`` (None: the
    resolvable width of the ``train`` photos, the fit's default) to :data:`ALPHA_MAX`: a
    lobe narrower than the grid reaches is a misfit the light would absorb."""
    k, h, w, _c = capture.shape
    total = h * w
    n = min(int(n_pixels), total // 2)
    if n < 1:
        raise JaxreflError("the light needs a capture of two pixels or more")
    pick = np.random.default_rng(seed).permutation(total)[: 2 * n]
    rot = orientations(capture)
    if rot is None:
        rot = np.broadcast_to(np.eye(3), (k, 3, 3)).copy()
        frame = "sample: x, y in the sample plane, z up (cm); the same for every photo"
    else:
        frame = (
            "camera: x right, y down, z forward (cm), each photo's orientation from "
            "calibration.json"
        )
    # the training photos' resolvable width: a held-out photo must not widen what they see
    train_mask = np.asarray(train, bool)
    lo = resolvable_alpha(capture, photos=train_mask) if alpha_min is None else float(alpha_min)
    alphas = np.geomspace(min(lo, ALPHA_MAX), ALPHA_MAX, WIDTHS)
    halves = [_light_data(capture, np.sort(part), rot, alphas) for part in (pick[:n], pick[n:])]
    problem = LightProblem(halves, train_mask, gain_prior(capture), frame)
    return problem

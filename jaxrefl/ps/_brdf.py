"""Non-Lambertian photometric stereo: normal and microfacet BRDF fitted together per pixel.

Per pixel, K observations in C channels under distant lights l_k of intensity E_kc:

    I_kc = E_kc f_r(wi_k, wo; x)_c cos(theta_i,k),      wi_k = F(n) l_k,   wo = F(n) (0, 0, 1)

with F(n) the rotation into the local frame of the normal (t, b, n) of
:func:`jaxrefl.scene.orthonormal_basis` (z = normal, as every :mod:`jaxrefl.brdf` model
expects) and f_r a model of :mod:`jaxrefl.brdf` (default Cook-Torrance, GGX, Smith
height-correlated shadowing, Schlick Fresnel with one grey F0 and a Lambertian diffuse
term: parameters albedo (C), specular (1), alpha). The unknowns are theta = (u, v, x):

    n(u, v) = (n0 + u t0 + v b0) / |n0 + u t0 + v b0|,     (t0, b0) the tangents of n0,

two tilt coordinates in the tangent plane of the starting normal n0: smooth, unconstrained
and non-singular for tilts below 90 degrees (a unit vector needs no constraint this way),
and x the model's unconstrained parameters (:class:`jaxrefl.fit.ParamSpace`). The residual
of the fitting engine (:func:`jaxrefl.fit.make_residual`: noise whitening, robust loss,
censoring of saturated observations, defensive masking) is evaluated on the directions
rotated into the current frame, and the solver of the :class:`jaxrefl.fit.FitConfig` (the
lean batched Levenberg-Marquardt by default; see :func:`jaxrefl.fit.solve`) minimises it
for every pixel at once.

Start: n0 and rho from robust Lambertian PS (:func:`jaxrefl.ps.robust`); the BRDF start is
:func:`jaxrefl.fit.initial_theta` at n0 (closed-form colours on a roughness grid).
Observations are divided per pixel by s = pi max_c(rho_c) / 0.5 so that the diffuse
albedo starts near 0.5 inside its range [0, 1] whatever the exposure; ``albedo`` of the
result is reported in the units of :class:`PSResult` (rho = albedo s / pi).
Dark observations (below ``shadow`` times the pixel's brightest, cast or attached
shadows: a local BRDF cannot explain a cast shadow) get weight 0; saturated ones are
censored (they only count when the prediction falls below them).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from jaxrefl import fit as jf
from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF
from jaxrefl.brdf import get as get_brdf
from jaxrefl.brdf import tilt_normal as tilt_slopes
from jaxrefl.scene import orthonormal_basis

from ._capture import PSInputError
from ._method import PSMethod
from ._robust import Robust, robust
from ._woodham import PSResult, prepare_inputs

__all__ = ["BRDFFit", "NormalBRDF", "NormalBRDFResidual", "default_model", "fit_normal_brdf"]

# The diffuse albedo starts here after the per-pixel scaling (inside [0, 1], away from 1
# so that a brighter channel still fits).
_ALBEDO_TARGET = 0.5


def default_model() -> BRDF:
    """Cook-Torrance GGX + Lambert (Schlick F0 fitted grey: one specular value)."""
    return get_brdf("cook_torrance", distribution="ggx", diffuse="lambert")


class PSPixel(eqx.Module):
    """Data of one pixel (leading N axis when batched)."""

    obs: Float[Array, "*n K C"]
    weight: Float[Array, "*n K C"]
    censored: Int[Array, "*n K C"]
    n0: Float[Array, "*n 3"]
    lights: Float[Array, "*n K 3"]
    intensities: Float[Array, "*n K C"]


def tilt_normal(uv: Float[Array, "*b 2"], n0: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
    """n(u, v) of the module docstring: :func:`jaxrefl.brdf.tilt_normal` (slopes u, v)
    expressed in the frame (t0, b0, n0) of the starting normal instead of the geometric one."""
    t0, b0 = orthonormal_basis(n0)
    local = tilt_slopes(uv[..., 0], uv[..., 1])  # (u, v, 1) / |(u, v, 1)|
    return local[..., :1] * t0 + local[..., 1:2] * b0 + local[..., 2:] * n0


class NormalBRDFResidual(eqx.Module):
    """r(theta, PSPixel) for theta = (u, v, x): the engine's residual in the tilted frame."""

    res: jf.Residual

    def local(self, theta, d: PSPixel) -> jf.PixelData:
        n = tilt_normal(theta[:2], d.n0)
        t, b = orthonormal_basis(n)
        frame = jnp.stack([t, b, n])  # rows: world -> local
        wi = jnp.sum(d.lights[:, None, :] * frame[None], axis=-1)
        wo = jnp.broadcast_to(frame[:, 2], wi.shape)
        # Below the local horizon the light contributes nothing (the model also returns 0).
        cos = jnp.maximum(wi[:, 2], 0.0)
        return jf.PixelData(
            d.obs, wi, wo, d.intensities * cos[:, None], d.weight, d.censored, False
        )

    def __call__(self, theta, d: PSPixel):
        return self.res(theta[2:], self.local(theta, d))


class BRDFFit(eqx.Module):
    """Outcome of :func:`fit_normal_brdf`: ``ps`` (normals, albedo in PS units, status),
    ``params`` (natural BRDF parameters of the scaled data, (N, ...)), ``scale`` (N,) the
    per-pixel factor the observations were divided by, ``cost`` (N,), ``lambert_cost`` (N,)
    the cost of the Lambertian start in the same residual (no specular lobe)."""

    ps: PSResult
    params: dict
    scale: Float[Array, " N"]
    cost: Float[Array, " N"]
    lambert_cost: Float[Array, " N"]


def _batched_local(residual, theta, data):
    return jax.vmap(residual.local)(theta, data)


class NormalBRDF(PSMethod):
    """Normal and BRDF fitted together per pixel (module docstring): the settings of
    :func:`fit_normal_brdf`, and the method object :func:`jaxrefl.ps.solve_capture` takes
    (saturated observations censored).

    model:  the BRDF (None: :func:`default_model`)
    space:  its parameter space (:class:`jaxrefl.fit.ParamSpace`; None: the model's with a
            grey ``specular``)
    config: solver, noise (in the units of the observations divided by the per-pixel scale
            s), loss (None: L2) and dtype (None: that of the observations) of the fit
    shadow: observations below it times the pixel's brightest get weight 0 (cast and
            attached shadows); also the robust Lambertian start's dark threshold
    init:   ``"diffuse"`` (the robust Lambertian albedo and the model's other defaults) or
            ``"grid"`` (:func:`jaxrefl.fit.initial_theta` at n0: closed-form colours on a
            roughness grid, a larger program to compile)
    batch:  pixels fitted at a time (the last batch padded with empty pixels), so every
            capture size reuses one compiled solver
    select: e.g. 0.5: keep the robust Lambertian normal where the fitted BRDF does not lower
            the cost below ``select`` times that of the Lambertian start (a lobe explaining
            little is likelier to be absorbing a model error than a highlight); None keeps
            every fitted normal
    """

    kind = "brdf"
    model: BRDF | None = None
    space: jf.ParamSpace | None = None
    config: jf.FitConfig = jf.FitConfig()
    shadow: float = 0.05
    init: str = "diffuse"
    batch: int = 2048
    select: float | None = None

    def __check_init__(self) -> None:
        if self.init not in ("diffuse", "grid"):
            raise JaxreflError(f"NormalBRDF init must be 'diffuse' or 'grid', not {self.init!r}")
        jf.check_number("NormalBRDF", "shadow", self.shadow)
        if self.batch < 1:
            raise JaxreflError(f"NormalBRDF needs batch >= 1, got {self.batch}")

    def solve(self, obs, lights, intensities, weight, saturated) -> PSResult:
        return fit_normal_brdf(obs, lights, intensities, weight, saturated, self).ps

    def to_json(self) -> dict[str, Any]:
        out = super().to_json()
        out["model"] = None if self.model is None else type(self.model).__name__
        sp = self.space
        out["space"] = None if sp is None else {"labels": list(sp.labels), "fixed": list(sp.fixed)}
        return out


def fit_normal_brdf(
    obs: Float[ArrayLike, "N K C"],
    lights: Float[ArrayLike, "K 3"],
    intensities: Float[ArrayLike, "K C"] | None = None,
    weight: Float[ArrayLike, "N K C"] | None = None,
    saturated: ArrayLike | None = None,
    options: NormalBRDF | None = None,
) -> BRDFFit:
    """Fit normal + BRDF per pixel (module docstring). ``saturated`` (N, K, C) bool marks
    censored observations; ``options``: every setting of the fit (:class:`NormalBRDF`:
    model, space, config, shadow, init, batch, select; None: its defaults)."""
    o = NormalBRDF() if options is None else options
    config = o.config
    obs, lights, e, w = prepare_inputs(obs, lights, intensities, weight)
    if config.dtype is not None:
        dt = np.dtype(config.dtype)
        obs, lights, e, w = (jnp.asarray(a, dt) for a in (obs, lights, e, w))
    n, k, c = obs.shape
    if saturated is not None and tuple(jnp.shape(saturated)) != (n, k, c):
        raise PSInputError(
            "saturated",
            f"must have the shape of obs (N, K, C) = ({n}, {k}, {c}); got {jnp.shape(saturated)}",
        )
    sat = jnp.zeros((n, k, c), bool) if saturated is None else jnp.asarray(saturated, bool)
    size = min(int(o.batch), max(256, 1 << max(n - 1, 0).bit_length()))
    pad = -n % size
    if pad:
        obs, w, sat = (jnp.pad(a, [(0, pad), (0, 0), (0, 0)]) for a in (obs, w, sat))
    parts = [
        _fit_batch(
            obs[i : i + size],
            lights,
            e,
            w[i : i + size],
            sat[i : i + size],
            model=o.model,
            space=o.space,
            config=config,
            shadow=o.shadow,
            init=o.init,
            select=o.select,
        )
        for i in range(0, n + pad, size)
    ]
    out = jax.tree.map(lambda *x: jnp.concatenate(x)[:n], *parts)
    return out


def _fit_batch(obs, lights, e, w, sat, *, model, space, config, shadow, init, select):
    dt = obs.dtype
    n, k, c = obs.shape
    finite = jnp.isfinite(obs) & jnp.isfinite(w)
    w = jnp.where(finite, w, 0.0)
    obs = jnp.where(finite, obs, 0.0)
    model = default_model() if model is None else model
    if space is None:
        grey = ("specular",) if "specular" in model.param_names else ()
        space = jf.ParamSpace(model, channels=c, grey=grey)
    start = robust(obs, lights, e, jnp.where(sat, 0.0, w), Robust(shadow=shadow))
    has = jf.has_estimate(start.status)
    n0 = jnp.where(has[:, None], start.normals, jnp.array([[0.0, 0.0, 1.0]], dt))
    peak_rho = jnp.max(jnp.where(has[:, None], start.albedo, 0.0), axis=-1)
    # Per-pixel scale; a pixel without a start (or black) keeps scale 1.
    s = jnp.where(peak_rho > 0, jnp.pi * peak_rho / _ALBEDO_TARGET, 1.0)
    peak = jnp.max(jnp.where(w > 0, obs, -jnp.inf), axis=1, keepdims=True)
    w_fit = jnp.where(obs >= shadow * peak, w, 0.0)
    data = PSPixel(
        obs / s[:, None, None],
        w_fit,
        sat.astype(jnp.int8),
        n0,
        jnp.broadcast_to(lights, (n, k, 3)),
        jnp.broadcast_to(e, (n, k, c)),
    )
    residual = NormalBRDFResidual(jf.make_residual(model, space, config.noise, config.loss))
    if init == "grid":
        local0 = _batched_local(residual, jnp.zeros((n, 2 + space.size), dt), data)
        x0 = jf.initial_theta(residual.res, local0)
    elif init == "diffuse":
        x0 = space.from_natural({"albedo": albedo_start(start, s, has)}, dtype=dt)
    else:
        raise JaxreflError(f"init must be 'grid' or 'diffuse', not {init!r}")
    theta0 = jnp.concatenate([jnp.zeros((n, 2), dt), x0], axis=-1)
    n_usable = jnp.sum(w_fit > 0, axis=(1, 2)).astype(jnp.int32)
    theta, info = jf.solve(residual, theta0, data, config.solver, n_usable=n_usable)
    normals = tilt_normal(theta[:, :2], n0)
    params = space.to_natural(theta[:, 2:])
    # The Lambertian alternative in the same residual: the start with no specular lobe.
    lam_nat = {"albedo": albedo_start(start, s, has)}
    if "specular" in space.free_names:
        lam_nat["specular"] = jnp.zeros((n, 1), dt)
    theta_l = jnp.concatenate([jnp.zeros((n, 2), dt), space.from_natural(lam_nat, dtype=dt)], -1)
    r_l = jax.vmap(residual)(theta_l, data)
    cost_l = 0.5 * jnp.sum(r_l * r_l, axis=-1)
    if select is not None:
        # Keep the lobe only where it explains most of what the Lambertian model cannot.
        keep = info.cost < select * cost_l
        normals = jnp.where(keep[:, None], normals, n0)
    status = jnp.where(has, info.status, jf.most_severe(start.status, jf.Status.MASKED))
    status = jnp.where(jnp.all(jnp.isfinite(normals), axis=-1), status, jf.Status.NONFINITE_INPUT)
    none = ~jf.has_estimate(status)
    rho = params["albedo"] * (s / jnp.pi)[:, None] if "albedo" in params else start.albedo
    ps = PSResult(
        jnp.where(none[:, None], jnp.nan, normals),
        jnp.where(none[:, None], jnp.nan, rho),
        status.astype(jnp.int32),
        n_usable,
    )
    return BRDFFit(ps, params, s, jnp.where(none, jnp.nan, info.cost), cost_l)


def albedo_start(start: PSResult, s, has):
    """The diffuse albedo of the robust Lambertian start in the scaled units of the fit."""
    # Clip inside (0, 1): the sigmoid of the albedo has no slope at its bounds.
    albedo0 = jnp.clip(jnp.pi * start.albedo / s[:, None], 0.02, 0.95)
    return jnp.where(has[:, None], albedo0, _ALBEDO_TARGET)

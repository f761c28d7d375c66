"""Robust calibrated photometric stereo: shadows and highlights rejected per pixel.

Lambertian least squares (:mod:`._woodham`) is biased wherever an observation breaks
I = E rho n.l: attached and cast shadows (I ~ 0 where n.l may be > 0) and specular
highlights (I far above the Lambertian value). The settings are one :class:`Robust`
(``shadow``, ``scale_floor``, ``iters``, ``trim``), the method object
:func:`jaxrefl.ps.solve_capture` also takes. Per pixel :func:`robust`

1. drops dark observations, I_kc < ``shadow`` * I_ref (cast and attached shadows; I_ref
   is the brightest observation once the brightest ``trim`` fraction is set aside, so the
   threshold follows exposure and albedo and is not raised by a highlight);
2. solves the weighted least squares of Woodham (1980) without the brightest ``trim``
   fraction (default 25%: where highlights are; a trimmed start, so that the reweighting
   below begins near the Lambertian answer instead of one a highlight pulled away);
3. repeats ``iters`` times (iteratively reweighted least squares, Holland & Welsch 1977):
   residuals e_kc = I_kc - E_kc rho_c max(n.l_k, 0); a robust scale
   s = 1.4826 median |e| (the MAD, consistent with sigma for Gaussian noise), floored at
   ``scale_floor`` times the median observation; Tukey's biweight
   w = (1 - (e / (c s))^2)^2 for |e| < c s, else 0 (c = 4.685: 95% efficiency at the
   Gaussian; Holland & Welsch 1977), and w = 0 where the current normal puts the light
   below the local horizon (n.l_k <= 0, an attached shadow); then solves again.

A pixel keeps its previous weights if the new ones would leave fewer than 3 lights in a
channel (the system would not be posed). Observations dropped by the caller (weight 0)
stay dropped. Noise-free Lambertian data without shadows give the exact normal (all
weights 1). Highlights are a minority of the lights at a pixel on most objects; where
they are not (a mirror-like surface), use the non-Lambertian fit (:mod:`._brdf`).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

from jaxrefl import fit as jf
from jaxrefl._errors import JaxreflError

from ._method import PSMethod
from ._woodham import PSResult, _woodham, cut, pad_pixels, prepare_inputs, scaled_normals

__all__ = ["Robust", "robust", "robust_weights"]

# Tukey biweight tuning constant (95% asymptotic efficiency under Gaussian noise).
_TUKEY_C = 4.685
# MAD -> standard deviation for Gaussian residuals.
_MAD_TO_SIGMA = 1.4826
_UP = jnp.array([0.0, 0.0, 1.0])


def _normals(obs, lights, e, w):
    b, _, _ = scaled_normals(obs, lights, e, w)
    total = jnp.sum(b, axis=1)
    norm = jnp.sqrt(jnp.sum(total * total, axis=-1, keepdims=True))
    # A pixel with no usable light has b = 0; +z keeps the iteration finite (it is MASKED).
    n = jnp.where(norm > 0, total / jnp.where(norm > 0, norm, 1.0), _UP[None])
    rho = jnp.sum(b * n[:, None, :], axis=-1)
    return n, rho


@partial(jax.jit, static_argnames=("iters",))
def robust_weights(obs, lights, e, w, shadow, scale_floor, iters: int, trim: float = 0.25):
    """The final per-observation weights of the procedure in the module docstring."""
    usable = w > 0
    n_u = jnp.sum(usable, axis=1, keepdims=True)
    # Rank of each usable observation among the pixel's usable ones (0 = darkest).
    rank = jnp.argsort(jnp.argsort(jnp.where(usable, obs, -jnp.inf), axis=1), axis=1)
    rank = rank - (obs.shape[1] - n_u)
    n_top = jnp.ceil(trim * n_u)
    top = rank >= n_u - n_top
    # A high but robust reference level: the brightest observation below the trimmed ones.
    ref_hi = jnp.max(jnp.where(usable & ~top, obs, -jnp.inf), axis=1, keepdims=True)
    w0 = jnp.where(obs >= shadow * ref_hi, w, 0.0)
    ref = jnp.nanmedian(jnp.where(w0 > 0, obs, jnp.nan), axis=(1, 2))
    # Scale floor: noise-free data have s = 0; a floor relative to the pixel's level keeps
    # the weights at 1 then instead of dividing by zero. All-dark pixels get a floor of 1.
    floor = scale_floor * jnp.where(jnp.isfinite(ref) & (ref > 0), ref, 1.0)
    # Start without the brightest ``trim`` fraction (where highlights are), if >= 3 remain.
    start = jnp.where(top, 0.0, w0)
    enough0 = jnp.all(jnp.sum(start > 0, axis=1) >= 3, axis=-1)
    wt = jnp.where(enough0[:, None, None], start, w0)
    for _ in range(iters):
        n, rho = _normals(obs, lights, e, wt)
        cos = jnp.einsum("ki,ni->nk", lights, n)
        pred = e[None] * rho[:, None, :] * jnp.maximum(cos, 0.0)[..., None]
        r = obs - pred
        mad = jnp.nanmedian(jnp.where(w0 > 0, jnp.abs(r), jnp.nan), axis=(1, 2))
        s = jnp.maximum(_MAD_TO_SIGMA * jnp.where(jnp.isfinite(mad), mad, 0.0), floor)
        u = r / (_TUKEY_C * s[:, None, None])
        tukey = jnp.where(jnp.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        new = w0 * tukey * (cos > 0)[..., None]
        enough = jnp.all(jnp.sum(new > 0, axis=1) >= 3, axis=-1)
        wt = jnp.where(enough[:, None, None], new, wt)
    return wt


class Robust(PSMethod):
    """Lambertian PS with shadows and highlights down-weighted (module docstring, :func:`robust`):
    ``shadow`` dark threshold relative to the pixel's reference level, ``scale_floor`` of
    the robust scale relative to the median observation, ``iters`` reweighting rounds,
    ``trim`` brightest share left out of the starting fit."""

    kind = "robust"
    shadow: float = 0.05
    scale_floor: float = 1e-3
    iters: int = 5
    trim: float = 0.25

    def __check_init__(self) -> None:
        for name in ("shadow", "scale_floor", "trim"):
            jf.check_number("Robust", name, getattr(self, name))
        if self.iters < 0:
            raise JaxreflError(f"Robust needs iters >= 0, got {self.iters}")

    def solve(self, obs, lights, intensities, weight, saturated) -> PSResult:
        return robust(obs, lights, intensities, weight, self)


def robust(
    obs: Float[ArrayLike, "N K C"],
    lights: Float[ArrayLike, "K 3"],
    intensities: Float[ArrayLike, "K C"] | None = None,
    weight: Float[ArrayLike, "N K C"] | None = None,
    options: Robust | None = None,
) -> PSResult:
    """Robust normals and albedo of N pixels (module docstring); arguments as
    :func:`jaxrefl.ps.woodham`, plus the settings ``options`` (:class:`Robust`; None: its
    defaults)."""
    o = Robust() if options is None else options
    obs, lights, e, w = prepare_inputs(obs, lights, intensities, weight)
    n = obs.shape[0]
    obs, w = pad_pixels(obs, w)
    wt = robust_weights(obs, lights, e, w, o.shadow, o.scale_floor, o.iters, o.trim)
    return cut(_woodham(obs, lights, e, wt), n)

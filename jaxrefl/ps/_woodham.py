"""Calibrated Lambertian photometric stereo: per-pixel weighted least squares (Woodham 1980).

For one pixel, K images in C channels under distant lights l_k (unit, camera frame) of
intensity E_kc, the Lambertian model is

    I_kc = E_kc rho_c n . l_k  =  E_kc l_k . b_c,      b_c = rho_c n     (n . l_k > 0)

Woodham, "Photometric method for determining surface orientation from multiple images",
Optical Engineering 19(1), 1980. Each channel's scaled normal b_c solves the 3 x 3 weighted
normal equations

    (sum_k w_kc E_kc^2 l_k l_k^T) b_c = sum_k w_kc E_kc I_kc l_k

(weights w_kc >= 0: 0 drops a shadowed, saturated or masked observation; per-image and
per-channel intensities enter as E_kc). The channels share one normal: n = sum_c b_c /
|sum_c b_c| (the albedo-weighted mean direction, exact when every b_c is parallel), and
rho_c = b_c . n (least-squares albedo of channel c given n). With noise-free Lambertian
data and >= 3 non-coplanar lit lights per channel the normal is exact.

Status per pixel (:class:`jaxrefl.fit.Status`): CONVERGED (solved), ILL_CONDITIONED (the
used lights are nearly coplanar: equilibrated condition number of the 3 x 3 system above
``cond_max``), MASKED (fewer than 3 usable lights in some channel: normal and albedo NaN),
NONFINITE_INPUT (a non-finite result).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from jaxrefl.fit import (
    Status,
    cho_solve_unrolled,
    cholesky_unrolled,
    equilibrated_condition,
    has_estimate,
)

__all__ = ["PSResult", "woodham"]

# Condition number of the equilibrated 3 x 3 light matrix above which the normal is not
# trusted (float32 keeps ~7 digits; a condition of 1e6 leaves about one).
_COND_MAX = 1e6
# Smallest padded batch: the closed-form methods cost microseconds per pixel, so padding
# small inputs to 4096 pixels costs nothing and lets them share one compilation.
_MIN_BUCKET = 4096


class PSResult(eqx.Module):
    """Per-pixel outcome of a photometric-stereo method (leading axis N: pixels).

    normals: (N, 3) unit normals in the camera frame (NaN where there is no estimate)
    albedo:  (N, C) rho_c with I = E rho n.l (image units per unit intensity)
    status:  (N,) :class:`jaxrefl.fit.Status` codes
    n_used:  (N,) observations (lights x channels) that took part
    """

    normals: Float[Array, "N 3"]
    albedo: Float[Array, "N C"]
    status: Int[Array, " N"]
    n_used: Int[Array, " N"]


def scaled_normals(
    obs: Float[Array, "N K C"],
    lights: Float[Array, "K 3"],
    intensities: Float[Array, "K C"],
    weight: Float[Array, "N K C"],
) -> tuple[Float[Array, "N C 3"], Float[Array, "N C"], Array]:
    """b_c per pixel and channel, the condition number of each system and its Cholesky ok."""
    e = intensities[None]
    a = jnp.einsum("nkc,ki,kj->ncij", weight * e * e, lights, lights)
    rhs = jnp.einsum("nkc,ki->nci", weight * e * obs, lights)
    cond = equilibrated_condition(a)
    # Ridge of eps * trace: keeps a rank-deficient system (too few lights) factorisable so
    # the batch never produces NaN; such pixels are flagged MASKED / ILL_CONDITIONED anyway.
    eps = jnp.finfo(a.dtype).eps
    tr = jnp.trace(a, axis1=-2, axis2=-1)[..., None, None]
    ridge = eps * jnp.maximum(tr, jnp.finfo(a.dtype).tiny) * jnp.eye(3, dtype=a.dtype)[None, None]
    chol, ok = cholesky_unrolled(a + ridge)
    b = cho_solve_unrolled(chol, rhs)
    return b, cond, ok


@jax.jit
def _woodham(obs, lights, intensities, weight):
    b, cond, ok = scaled_normals(obs, lights, intensities, weight)
    total = jnp.sum(b, axis=1)
    norm = jnp.sqrt(jnp.sum(total * total, axis=-1, keepdims=True))
    good_norm = norm > 0
    n = total / jnp.where(good_norm, norm, 1.0)
    rho = jnp.sum(b * n[:, None, :], axis=-1)
    used = weight > 0
    per_channel = jnp.sum(used, axis=1)
    n_used = jnp.sum(used, axis=(1, 2)).astype(jnp.int32)
    status = jnp.where(jnp.any(cond > _COND_MAX, axis=-1), Status.ILL_CONDITIONED, 0)
    finite = jnp.all(jnp.isfinite(n), axis=-1) & jnp.all(jnp.isfinite(rho), axis=-1)
    finite = finite & good_norm[:, 0] & jnp.all(ok, axis=-1)
    status = jnp.where(finite, status, Status.NONFINITE_INPUT)
    status = jnp.where(jnp.any(per_channel < 3, axis=-1), Status.MASKED, status)
    none = ~has_estimate(status)
    n = jnp.where(none[:, None], jnp.nan, n)
    rho = jnp.where(none[:, None], jnp.nan, rho)
    return PSResult(n, rho, status.astype(jnp.int32), n_used)


def bucket(n: int) -> int:
    """Padded batch size: the next power of two (>= 4096), so that captures of different
    sizes share compiled code (a new N would otherwise mean a new compilation)."""
    return max(_MIN_BUCKET, 1 << max(int(n) - 1, 0).bit_length())


def pad_pixels(*arrays):
    """Pad (N, ...) arrays with zeros to :func:`bucket` (N) rows (zero weight: MASKED)."""
    n = arrays[0].shape[0]
    extra = bucket(n) - n
    return tuple(jnp.pad(a, [(0, extra)] + [(0, 0)] * (a.ndim - 1)) for a in arrays)


def cut(r: PSResult, n: int) -> PSResult:
    """The first n pixels of a padded result."""
    return PSResult(r.normals[:n], r.albedo[:n], r.status[:n], r.n_used[:n])


def woodham(
    obs: Float[ArrayLike, "N K C"],
    lights: Float[ArrayLike, "K 3"],
    intensities: Float[ArrayLike, "K C"] | None = None,
    weight: Float[ArrayLike, "N K C"] | None = None,
) -> PSResult:
    """Least-squares normals and albedo of N pixels (module docstring).

    obs: linear values; lights: unit directions towards the lights; intensities: E_kc
    (default 1); weight: >= 0 per observation (default 1; 0 drops it). Non-finite
    observations are dropped (weight 0) before any arithmetic.
    """
    obs, lights, e, w = prepare_inputs(obs, lights, intensities, weight)
    n = obs.shape[0]
    obs, w = pad_pixels(obs, w)
    return cut(_woodham(obs, lights, e, w), n)


# Largest accepted | |l| - 1 | of a light direction (float32 rounding is ~1e-7).
_UNIT_TOL = 1e-3


def _concrete(a) -> bool:
    """Whether ``a`` holds values (not a JAX tracer inside a transformation)."""
    return not isinstance(a, jax.core.Tracer)


def check_inputs(obs, lights, intensities, weight):
    """Refuse inputs of the calibrated methods that would give a wrong answer silently.

    Rules (each failure raises :class:`~jaxrefl.ps.PSInputError` naming the argument):
    ``obs`` is (N, K, C); ``lights`` is (K, 3), finite, of unit length (within 1e-3) and
    above the horizon (z > 0: a light at or below it cannot light a surface the camera
    sees); ``intensities`` is (K, C), (K, 1) or (K,), finite and >= 0; ``weight`` is
    (N, K, C) and >= 0 where finite (non-finite weights and observations are dropped).
    Value checks are skipped for traced arrays (inside ``jax.jit``); shapes are always
    checked. Returns intensities as (K, C) (None stays None).
    """
    from ._capture import PSInputError

    shape = getattr(obs, "shape", None)
    if shape is None or len(shape) != 3:
        raise PSInputError(
            "obs", f"must be (N pixels, K lights, C channels), got shape {shape or '()'}"
        )
    n, k, c = shape
    ls = getattr(lights, "shape", None)
    if ls is None:
        lights = np.asarray(lights, np.float64)
        ls = lights.shape
    if tuple(ls) != (k, 3):
        raise PSInputError(
            "lights", f"must be (K, 3) = ({k}, 3), one unit direction per image; got {ls}"
        )
    if _concrete(lights):
        d = np.asarray(lights, np.float64)
        if not np.all(np.isfinite(d)):
            i = int(np.flatnonzero(~np.all(np.isfinite(d), axis=1))[0])
            raise PSInputError("lights", f"light {i} is not finite: {d[i].tolist()}")
        norm = np.linalg.norm(d, axis=1)
        off = np.abs(norm - 1.0)
        if np.any(off > _UNIT_TOL):
            i = int(np.argmax(off))
            raise PSInputError(
                "lights",
                f"must be unit vectors (|l| = 1 within {_UNIT_TOL:g}); light {i} has length "
                f"{norm[i]:.6g}",
            )
        if np.any(d[:, 2] <= 0):
            i = int(np.flatnonzero(d[:, 2] <= 0)[0])
            raise PSInputError(
                "lights",
                f"light {i} is at or below the horizon (z = {d[i, 2]:.3g}); directions go "
                "from the surface towards the light with +z towards the camera (z > 0)",
            )
    if intensities is not None:
        es = getattr(intensities, "shape", None)
        if es is None:
            intensities = np.asarray(intensities, np.float64)
            es = intensities.shape
        if len(es) == 1 and es[0] == k:
            intensities = intensities[:, None]
            es = (k, 1)
        if len(es) != 2 or es[0] != k or es[1] not in (1, c):
            raise PSInputError(
                "intensities", f"must be (K, C) = ({k}, {c}), ({k}, 1) or ({k},); got {es}"
            )
        if _concrete(intensities):
            e = np.asarray(intensities, np.float64)
            if not np.all(np.isfinite(e)) or np.any(e < 0):
                i = int(np.flatnonzero(~np.all(np.isfinite(e) & (e >= 0), axis=1))[0])
                raise PSInputError(
                    "intensities",
                    f"must be finite and >= 0; light {i} has {e[i].tolist()}",
                )
        if es[1] != c:
            intensities = jnp.broadcast_to(jnp.asarray(intensities), (k, c))
    if weight is not None:
        ws = getattr(weight, "shape", None)
        if ws is None:
            weight = np.asarray(weight, np.float64)
            ws = weight.shape
        if tuple(ws) != (n, k, c):
            raise PSInputError(
                "weight", f"must have the shape of obs (N, K, C) = ({n}, {k}, {c}); got {ws}"
            )
        if _concrete(weight):
            wv = np.asarray(weight, np.float64)
            if np.any(wv < 0):
                raise PSInputError(
                    "weight", f"must be >= 0 (0 drops an observation); min is {np.min(wv):g}"
                )
    return lights, intensities, weight


def prepare_inputs(
    obs: Float[ArrayLike, "N K C"],
    lights: Float[ArrayLike, "K 3"],
    intensities: Float[ArrayLike, "K C"] | None,
    weight: Float[ArrayLike, "N K C"] | None,
) -> tuple[Float[Array, "N K C"], Float[Array, "K 3"], Float[Array, "K C"], Float[Array, "N K C"]]:
    """Arrays of one floating dtype (float32 unless obs is floating): obs (N, K, C), lights
    (K, 3), intensities E (K, C) (default 1), weights (N, K, C) (default 1), with non-finite
    observations or weights dropped (weight 0, value 0) before any arithmetic. The inputs
    pass :func:`check_inputs` first."""
    obs = jnp.asarray(obs)
    lights, intensities, weight = check_inputs(obs, lights, intensities, weight)
    if not jnp.issubdtype(obs.dtype, jnp.floating):
        obs = obs.astype(jnp.float32)
    dt = obs.dtype
    n, k, c = obs.shape
    lights = jnp.asarray(lights, dt)
    e = jnp.ones((k, c), dt) if intensities is None else jnp.asarray(intensities, dt)
    w = jnp.ones((n, k, c), dt) if weight is None else jnp.asarray(weight, dt)
    finite = jnp.isfinite(obs) & jnp.isfinite(w)
    return jnp.where(finite, obs, 0.0), lights, e, jnp.where(finite, w, 0.0)

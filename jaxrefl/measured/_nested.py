"""Starts of a model from the fit of a smaller model it contains (nested starts).

Nested starts (:func:`nested_thetas`) serve a model that contains a smaller one
(:func:`nested_model`): Lafortune with L lobes contains Lafortune with L - 1 (a lobe of
amplitude 0 adds nothing). Its starts are the fitted (L-1)-lobe optimum plus one new lobe
(Lafortune et al. 1997 also fit their lobes one after another). The new lobe has a fixed
shape (Cx, Cy, Cz) = C0 times a scale k: C0 forward-specular (-1, -1, 1), off-specular
(-1, -1, 0.6), retro-reflective (1, 1, 1), elevation-only (0, 0, 1), or aimed at the
largest cosine-weighted residual of the (L-1)-lobe fit (the sample (wi*, wo*); C0 =
(s t, s t, 1) with t = tan theta_o* / tan theta_i* and s the sign of wi*_xy . wo*_xy, so
that the lobe's axis C0 * wi* points at wo*); each with exponents n in ``_NEW_LOBE_N``,
and the amplitude k^n the least-squares fit of the lobe to the achromatic residual
(floored at a small positive value, since a lobe of amplitude 0 has no slope). Two more
starts per existing lobe split it: the lobe at half its amplitude, plus a copy with
exponent 4n or n/4 at half the amplitude. Lambert, which every model contains, enters the
data-driven starts instead. Keeping the (L-1)-lobe optimum in a start makes the L-lobe
cost never exceed it by more than the solver's tolerance.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF, Lafortune
from jaxrefl.fit import ParamSpace

from ._seeds import _from_natural

__all__ = ["nested_model", "nested_thetas"]

# The new lobe of a nested start: shapes C0 (module docstring) and exponents.
_NEW_LOBE_SHAPES = ((-1.0, -1.0, 1.0), (-1.0, -1.0, 0.6), (1.0, 1.0, 1.0), (0.0, 0.0, 1.0))
_NEW_LOBE_N = (2.0, 10.0, 50.0, 250.0, 1250.0)
# tan theta_o / tan theta_i of the lobe aimed at the residual peak stays in this range.
_AIM_RANGE = (0.05, 20.0)


def nested_model(model: BRDF) -> BRDF | None:
    """The smaller model that ``model`` contains, whose fit seeds the nested starts: for
    Lafortune with L > 1 lobes, Lafortune with L - 1; None for every other model."""
    if isinstance(model, Lafortune) and model.num_lobes > 1:
        return Lafortune(num_lobes=model.num_lobes - 1)
    return None


def _is_nested(model: BRDF, smaller: BRDF) -> bool:
    inner = nested_model(model)
    return inner is not None and type(inner) is type(smaller) and bool(inner == smaller)


def _lobe_shapes(wi: np.ndarray, wo: np.ndarray, resid: np.ndarray, w: np.ndarray):
    """The shapes C0 of the new lobe: the fixed ones and the one aimed at the largest
    weighted residual (module docstring)."""
    shapes = [np.asarray(c, np.float64) for c in _NEW_LOBE_SHAPES]
    k = int(np.argmax(w * resid))
    if resid[k] > 0:
        wi_k, wo_k = wi[k], wo[k]
        tan_i = math.hypot(wi_k[0], wi_k[1]) / max(wi_k[2], 1e-12)
        tan_o = math.hypot(wo_k[0], wo_k[1]) / max(wo_k[2], 1e-12)
        t = float(np.clip(tan_o / max(tan_i, 1e-12), *_AIM_RANGE))
        s = 1.0 if float(wi_k[:2] @ wo_k[:2]) >= 0 else -1.0
        shapes.append(np.array([s * t, s * t, 1.0]))
    else:
        shapes.append(np.array([-1.0, -1.0, 1.0]))
    return shapes


def nested_thetas(
    space: ParamSpace,
    smaller: BRDF,
    smaller_params: dict[str, np.ndarray],
    wi: np.ndarray,
    wo: np.ndarray,
    values: np.ndarray,
    *,
    cosine: bool = True,
) -> np.ndarray:
    """(S, P) float64 starts of ``space.model`` from the fit of the model it contains
    (module docstring): ``smaller_params`` are the natural parameters of ``smaller``'s fit
    to the same problem (colours with ``space.channels`` entries), ``values`` (K, C) f_r."""
    if not _is_nested(space.model, smaller):
        raise JaxreflError(
            f"nested starts need the fit of {type(space.model).__name__}'s nested model "
            f"(nested_model), not of {type(smaller).__name__}"
        )
    wi = np.asarray(wi, np.float64)
    wo = np.asarray(wo, np.float64)
    f = np.asarray(values, np.float64).reshape(len(wi), -1)
    albedo = np.broadcast_to(np.asarray(smaller_params["albedo"], np.float64), (space.channels,))
    old = np.asarray(smaller_params["lobes"], np.float64).reshape(-1, 4)
    with jax.enable_x64(True):
        p = {"albedo": jnp.asarray(albedo), "lobes": jnp.asarray(old)}
        f_hat = np.asarray(smaller.eval(p, jnp.asarray(wi), jnp.asarray(wo)), np.float64)
    ok = np.all(np.isfinite(f), axis=-1) & (wi[:, 2] > 0) & (wo[:, 2] > 0)
    resid = np.where(ok, np.mean(np.where(ok[:, None], f - f_hat, 0.0), axis=-1), 0.0)
    # The solver's weights: cos^2 theta_i with the cosine-weighted residual.
    w = np.where(ok, wi[:, 2] ** 2 if cosine else 1.0, 0.0)
    ww = wi * wo
    floor = 1e-3 * max(float(np.max(np.abs(resid))), 1e-6)
    new_rows = []
    for c0 in _lobe_shapes(wi, wo, resid, np.sqrt(w)):
        x = np.maximum(ww @ c0, 0.0)
        # Scaled so that the unit-amplitude lobe peaks at 1 over the samples: x^n stays finite.
        # (A shape that no sample sees keeps its scale and gets the floor amplitude.)
        top = float(np.max(np.where(ok, x, 0.0))) or 1.0
        c0, x = c0 / top, np.where(ok, x / top, 0.0)
        for n in _NEW_LOBE_N:
            g = x**n
            den = float(np.sum(w * g * g))
            amp = float(np.sum(w * g * resid)) / den if den > 0 else 0.0
            amp = amp if np.isfinite(amp) and amp > floor else floor
            new_rows.append([*(c0 * amp ** (1.0 / n)), n])
    lobes = [np.concatenate([old, np.asarray([row])]) for row in new_rows]
    for j, (cj, nj) in enumerate(zip(old[:, :3], old[:, 3], strict=True)):
        half = old.copy()
        half[j, :3] = cj * 0.5 ** (1.0 / nj)
        # The lobe's peak is about m^nj, m = max |C_j| (C . (wi * wo) <= m for unit wi, wo);
        # the copy's is half that.
        m = max(float(np.max(np.abs(cj))), 1e-12)
        for k in (4.0, 0.25):
            n_new = float(np.clip(nj * k, 0.5, 1e5))
            scale = math.exp((nj * math.log(m) + math.log(0.5)) / n_new)
            lobes.append(np.concatenate([half, [[*(cj / m * scale), n_new]]]))
    stacked = {
        "albedo": np.broadcast_to(albedo, (len(lobes), space.channels)).copy(),
        "lobes": np.stack(lobes),
    }
    theta = _from_natural(space, stacked)
    return np.where(np.isfinite(theta), theta, _from_natural(space, {}))

"""Starts of a measured fit that need no earlier fit: read off the data, and quasi-random.

* **data-driven** (:func:`lobe_moments`, :func:`seed_params`): a Lambertian fit to the
  samples up to the ``_DIFFUSE_QUANTILE`` of brightness (cosine-weighted least squares),
  then the achromatic residual r = mean_c (f - albedo/pi) seen as a function of the
  half-vector angle theta_h (the peak around the mirror direction). Its width gives a
  Beckmann-like roughness two ways: the residual-weighted second moment alpha^2 = sum r+
  tan^2 theta_h / sum r+, and the half-maximum width alpha = tan theta_h(r = peak/2) /
  sqrt(ln 2) (exp(-tan^2/alpha^2) = 1/2 there); each, and half and twice each, gives a
  start. The width sets the model's shape parameter by name (``alpha``,
  ``alpha_u``/``alpha_v``; ``exponent`` n = 2/alpha^2, from cos^n theta_h ~ exp(-n theta_h^2
  / 2); a Lafortune lobe (-c, -c, c, n) with n = 1/(2 alpha^2), the angle to the mirror
  direction being about 2 theta_h, and c^n = the peak), and the peak value sets the lobe
  scale (``specular``: the peak divided by the model's own peak at unit scale, evaluated at
  a mirror pair ``_PEAK_THETA`` off the normal; ``eta``: the index whose normal-incidence F0
  = ((eta - 1)/(eta + 1))^2 gives that peak).
* **quasi-random** (:func:`random_thetas`): scrambled Sobol points (``scipy.stats.qmc``)
  in a box of the unconstrained space: albedo and specular log-uniform in [0.005, 0.9] and
  [1e-3, 0.9], alpha in [0.01, 0.8], exponent in [1, 1e4], eta in [1.05, 3], Lafortune
  rows with n in [1, 5000], peak c^n in [0.01, 100], Cz/|Cx| in [-0.3, 1.3], Cx/Cy in
  [0.8, 1.25], a quarter of them retro-reflective (Cx, Cy > 0), the rest specular; any
  other parameter its default +- 2 in theta.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import qmc

from jaxrefl.brdf import BRDF
from jaxrefl.fit import ParamSpace

from ._start_options import MultiStart

__all__ = ["LobeMoments", "lobe_moments", "random_thetas", "seed_params", "start_thetas"]

# The Lambertian fit of the data-driven start leaves out the brightest fifth of the samples
# (they likely hold the highlight).
_DIFFUSE_QUANTILE = 0.8
# Roughness estimates are kept within the range a measured lobe can show (the goniometer's
# angular resolution below, a lobe wider than the hemisphere above).
_ALPHA_RANGE = (0.005, 1.0)
# Lobe scales of a start stay inside their range: a start at a bound has no slope.
_SPEC_RANGE = (1e-3, 0.95)
# Share of the random Lafortune lobes that start retro-reflective.
_RETRO_SHARE = 0.25
# Sample directions of the model's peak at unit scale: a mirror pair 10 degrees off normal.
_PEAK_THETA = math.radians(10.0)


@dataclass(frozen=True)
class LobeMoments:
    """What the data say about the lobe (:func:`lobe_moments`).

    albedo:     (C,) Lambertian albedo of the dimmer samples, in [0, 1]
    peak:       peak of the achromatic residual above the diffuse level, f_r in 1/sr (>= 0)
    alphas:     roughness estimates (second moment, half maximum), in ``_ALPHA_RANGE``
    """

    albedo: np.ndarray
    peak: float
    alphas: tuple[float, ...]


def lobe_moments(
    wi: np.ndarray, wo: np.ndarray, values: np.ndarray, *, cosine: bool = True
) -> LobeMoments:
    """Diffuse level, lobe peak and lobe widths of f_r samples (module docstring).

    wi, wo (K, 3) unit directions above the horizon (z = normal), values (K, C) f_r in 1/sr;
    non-finite samples are ignored. With ``cosine`` the diffuse fit weights each sample by
    cos^2 theta_i, as the cosine-weighted residual does.
    """
    wi = np.asarray(wi, np.float64)
    wo = np.asarray(wo, np.float64)
    f = np.asarray(values, np.float64)
    ok = np.all(np.isfinite(f), axis=-1) & (wi[:, 2] > 0) & (wo[:, 2] > 0)
    if not np.any(ok):
        c = f.shape[-1]
        return LobeMoments(np.full(c, 0.5), 0.0, (0.2,))
    wi, wo, f = wi[ok], wo[ok], f[ok]
    lum = np.mean(f, axis=-1)
    dim = lum <= np.quantile(lum, _DIFFUSE_QUANTILE)
    w = wi[dim, 2] ** 2 if cosine else np.ones(int(dim.sum()))
    albedo = np.clip(np.pi * np.sum(w[:, None] * f[dim], 0) / np.sum(w), 0.0, 1.0)
    r = np.mean(f - albedo / np.pi, axis=-1)
    h = wi + wo
    tan2 = (h[:, 0] ** 2 + h[:, 1] ** 2) / np.maximum(h[:, 2], 1e-12) ** 2
    pos = np.maximum(r, 0.0)
    peak = float(np.max(pos))
    alphas = []
    if peak > 0:
        alphas.append(math.sqrt(float(np.sum(pos * tan2) / np.sum(pos))))
        half = tan2[r >= 0.5 * peak]
        alphas.append(math.sqrt(float(np.max(half)) / math.log(2.0)))
    alphas = [float(np.clip(a, *_ALPHA_RANGE)) for a in alphas if np.isfinite(a)] or [0.2]
    return LobeMoments(albedo, peak, tuple(alphas))


def _unit_peak(model: BRDF, p: dict[str, Any]) -> np.ndarray:
    """(C,) the model's f_r at a mirror pair 10 degrees off the normal, for natural ``p``
    (albedo set to 0 by the caller)."""
    s, c = math.sin(_PEAK_THETA), math.cos(_PEAK_THETA)
    wi = jnp.asarray([s, 0.0, c])
    wo = jnp.asarray([-s, 0.0, c])
    return np.asarray(model.eval({k: jnp.asarray(v) for k, v in p.items()}, wi, wo), np.float64)


def seed_params(
    space: ParamSpace, moments: LobeMoments, alpha: float, peak_share: float = 1.0
) -> dict[str, np.ndarray]:
    """Natural parameters of a start with lobe width ``alpha`` and height ``peak_share``
    times the measured peak (module docstring); parameters the width and peak do not set
    keep the model's default. Colours have C = ``space.channels`` entries."""
    model, n_ch = space.model, space.channels
    peak = max(moments.peak * peak_share, 1e-6)
    alb = np.broadcast_to(np.asarray(moments.albedo, np.float64), (n_ch,))
    p: dict[str, np.ndarray] = {}
    for q in model.params:
        d = np.asarray(q.default, np.float64)
        p[q.name] = np.broadcast_to(d, (n_ch,)).copy() if q.kind == "color" else d.copy()
    for name in p:
        if name in ("alpha", "alpha_u", "alpha_v"):
            p[name] = np.asarray(alpha)
        elif name == "exponent":
            # cos^n theta_h ~ exp(-n theta_h^2 / 2) against exp(-theta_h^2 / alpha^2).
            p[name] = np.asarray(np.clip(2.0 / alpha**2, 1.0, 1e4))
        elif name == "lobes":
            lobes = p[name]
            n_lobes = lobes.shape[0]
            for j in range(n_lobes):
                # Several lobes: widths alpha, alpha/2, 2 alpha, ... sharing the peak.
                a = alpha * (0.5 ** ((j + 1) // 2) if j % 2 else 2.0 ** (j // 2))
                n = float(np.clip(0.5 / a**2, 1.0, 5e3))
                c = (peak / n_lobes) ** (1.0 / n)
                lobes[j] = (-c, -c, c, n)
    if "albedo" in p:
        p["albedo"] = alb.copy()
    probe = {**p}
    if "albedo" in probe:
        probe["albedo"] = np.zeros(n_ch)
    if "specular" in p:
        unit = _unit_peak(model, {**probe, "specular": np.ones(n_ch)})
        p["specular"] = np.clip(peak / np.maximum(unit, 1e-12), *_SPEC_RANGE)
    if "eta" in p:
        # eta = 1.5 gives F0 = 0.04; F0 scales the peak, F0 = ((eta-1)/(eta+1))^2 inverts.
        unit = _unit_peak(model, {**probe, "eta": np.full(n_ch, 1.5)})
        f0 = np.clip(0.04 * peak / np.maximum(unit, 1e-12), 1e-4, 0.5)
        p["eta"] = (1.0 + np.sqrt(f0)) / (1.0 - np.sqrt(f0))
    return p


def _from_natural(space: ParamSpace, p: dict[str, np.ndarray]) -> np.ndarray:
    """theta for natural ``p`` in float64 (x64 switched on for the conversion only)."""
    with jax.enable_x64(True):
        return np.asarray(space.from_natural(p, dtype=jnp.float64), np.float64)


def _log_uniform(u: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.exp(np.log(lo) + u * (np.log(hi) - np.log(lo)))


def random_thetas(space: ParamSpace, n: int, seed: int = 0, *, sobol: bool = True) -> np.ndarray:
    """(n, P) starts in the box of the module docstring: scrambled Sobol points (``sobol``)
    or independent uniform ones, in float64."""
    if n == 0:
        return np.zeros((0, space.size))
    if sobol:
        # Sobol balance is exact for powers of 2 only; any n is still well spread.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            u = qmc.Sobol(d=space.size, scramble=True, seed=seed).random(n)
    else:
        u = np.random.default_rng(seed).uniform(size=(n, space.size))
    p: dict[str, np.ndarray] = {}
    generic = []
    for b in space.blocks:
        ub = u[:, b.start : b.stop]
        if b.name == "albedo":
            v = _log_uniform(ub, 0.005, 0.9)
        elif b.name == "specular":
            v = _log_uniform(ub, 1e-3, 0.9)
        elif b.name in ("alpha", "alpha_u", "alpha_v"):
            v = _log_uniform(ub, 0.01, 0.8)
        elif b.name == "exponent":
            v = _log_uniform(ub, 1.0, 1e4)
        elif b.name == "eta":
            v = 1.05 + ub * (3.0 - 1.05)
        elif b.name == "lobes":
            rows = ub.reshape(n, -1, 4)
            nn = _log_uniform(rows[..., 0], 1.0, 5e3)
            c = _log_uniform(rows[..., 1], 0.01, 100.0) ** (1.0 / nn)
            cz = c * (-0.3 + 1.6 * rows[..., 2])
            # The last coordinate picks the lobe's kind and its x/y ratio: a quarter of the
            # starts are retro-reflective (Cx, Cy > 0: the peak at wo = wi), the rest specular.
            u4 = rows[..., 3]
            retro = u4 < _RETRO_SHARE
            t = np.where(retro, u4 / _RETRO_SHARE, (u4 - _RETRO_SHARE) / (1 - _RETRO_SHARE))
            ratio = _log_uniform(t, 0.8, 1.25)
            sx = np.where(retro, 1.0, -1.0)
            v = np.stack([sx * c * np.sqrt(ratio), sx * c / np.sqrt(ratio), cz, nn], axis=-1)
        else:
            generic.append(b)
            continue
        p[b.name] = v.reshape((n, *b.shape)) if not b.grey else v
    theta = np.array(_from_natural(space, p))
    base = _from_natural(space, {})
    for b in generic:
        theta[:, b.start : b.stop] = base[b.start : b.stop] + 4.0 * (u[:, b.start : b.stop] - 0.5)
    return theta


def start_thetas(
    space: ParamSpace,
    wi: np.ndarray,
    wo: np.ndarray,
    values: np.ndarray,
    starts: MultiStart,
    *,
    cosine: bool = True,
) -> np.ndarray:
    """(S, P) float64 starts of one problem: the data-driven ones (each moment estimate of
    the width, and half and twice it), then ``starts.n_random`` quasi-random ones."""
    out = []
    if starts.data:
        mom = lobe_moments(wi, wo, values, cosine=cosine)
        has_lobe = any(b.name not in ("albedo",) for b in space.blocks)
        widths = [a * k for a in mom.alphas for k in (1.0, 0.5, 2.0)] if has_lobe else [0.2]
        seeds = [seed_params(space, mom, float(np.clip(a, *_ALPHA_RANGE))) for a in widths]
        stacked = {k: np.stack([s[k] for s in seeds]) for k in seeds[0]}
        out.append(_from_natural(space, stacked))
    out.append(random_thetas(space, starts.n_random, starts.seed))
    theta = np.concatenate(out, axis=0)
    # A start must be finite: a non-finite entry would stop the whole problem at once.
    return np.where(np.isfinite(theta), theta, _from_natural(space, {}))

"""Multi-start fits of one measured material: starts that see the data, a batch of diverse
starts solved together, and a certificate of the optimum.

A fit of a specular lobe from one start can stop next to the Lambertian solution (a lobe too
narrow or too weak to reach the highlight has no gradient towards it), so a model ranking
would compare the optimiser's luck. :func:`fit_multistart` therefore solves S starts of the
same problem in one batched Levenberg-Marquardt call (:func:`jaxrefl.fit.fit_pixels` on the
problem repeated S times) and keeps the start of lowest cost. The starts
(:func:`start_thetas`) are

* **data-driven** (:func:`lobe_moments`, :func:`seed_params`): a Lambertian fit to the
  dimmer 80% of the samples (cosine-weighted least squares), then the achromatic residual
  r = mean_c (f - albedo/pi) seen as a function of the half-vector angle theta_h (the
  peak around the mirror direction). Its width gives a Beckmann-like roughness two ways:
  the residual-weighted second moment alpha^2 = sum r+ tan^2 theta_h / sum r+, and the
  half-maximum width alpha = tan theta_h(r = peak/2) / sqrt(ln 2) (exp(-tan^2/alpha^2) =
  1/2 there); each, and half and twice each, gives a start. The width sets the model's
  shape parameter by name (``alpha``, ``alpha_u``/``alpha_v``; ``exponent`` n = 2/alpha^2,
  from cos^n theta_h ~ exp(-n theta_h^2 / 2); a Lafortune lobe (-c, -c, c, n) with
  n = 1/(2 alpha^2), the angle to the mirror direction being about 2 theta_h, and c^n =
  the peak), and the peak value sets the lobe scale (``specular``: the peak divided by the
  model's own peak at unit scale, evaluated at a mirror pair 10 degrees off the normal;
  ``eta``: the index whose normal-incidence F0 = ((eta - 1)/(eta + 1))^2 gives that peak).
* **quasi-random** (:func:`random_thetas`): scrambled Sobol points (``scipy.stats.qmc``)
  in a box of the unconstrained space: albedo and specular log-uniform in [0.005, 0.9] and
  [1e-3, 0.9], alpha in [0.01, 0.8], exponent in [1, 1e4], eta in [1.05, 3], Lafortune
  rows with n in [1, 5000], peak c^n in [0.01, 100], Cz/|Cx| in [-0.3, 1.3], Cx/Cy in
  [0.8, 1.25], a quarter of them retro-reflective (Cx, Cy > 0), the rest specular; any
  other parameter its default +- 2 in theta.
* **the automatic start** of a single fit (:func:`jaxrefl.fit.initial_theta`: closed-form
  colours on a roughness grid), so that the kept result is never worse than the single
  start's (both get the same iteration budget).
* **nested** (:func:`nested_thetas`), for a model that contains a smaller one
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

**Continuation.** Every start gets the solver's iteration budget; a narrow Lafortune lobe
(exponent in the hundreds) can need several budgets to converge, so that the best start
found after one budget may still be descending. While one of the ``polish`` lowest-cost
starts of a problem has stopped at the budget (``MAX_ITERATIONS``), every start that did
continues from where it stopped, for up to ``rounds`` more budgets; a continued start keeps
its old result if the new one is not lower. The continuation runs the same batch through
the same compiled program (same shapes, same static solver settings), so it compiles
nothing.

**Perturbed generations.** Where the starts disagree (the certificate below is doubtful:
the landscape has many basins, as multi-lobe Lafortune fits often do), the ``polish`` best
results so far seed a new generation of as many starts: each best result plus a Gaussian
step in the unconstrained space of scale 0.25, 0.5, 1 or 2 (a basin-hopping step, Wales &
Doye 1997), solved and continued like the first. Generations follow one another, up to
``generations``, while the certificate stays doubtful and the last one lowered some
problem's best cost by more than ``agree_rtol``; the best over all generations is kept and
all of them are certified together. They run through the same compiled program.

The :class:`Certificate` counts the starts whose cost is within ``agree_rtol`` (1%) of the
best and flags the optimum as doubtful when their share is below ``min_share``: a user
then sees that the starts disagree, not only the best value found.

Costs are the solver's own 1/2 |r|^2 (whitened and robust as the config says), compared in
float64. Problems: one for channels fitted jointly, C when every channel is its own problem
(results then have a leading axis C; the certificate reports the worst channel).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import qmc

from jaxrefl._errors import JaxreflError
from jaxrefl.brdf import BRDF, Lafortune
from jaxrefl.fit import (
    L2,
    FitConfig,
    FitResult,
    Option,
    ParamSpace,
    PixelData,
    Status,
    fit_pixels,
    initial_theta,
    make_residual,
    pixel_data,
)
from jaxrefl.fit import sample_arrays as _sample_arrays

__all__ = [
    "Certificate",
    "LobeMoments",
    "MultiStart",
    "certify",
    "fit_multistart",
    "lobe_moments",
    "nested_model",
    "nested_thetas",
    "random_thetas",
    "seed_params",
    "start_thetas",
]

Channels = Literal["joint", "separate"]

# The Lambertian fit of the data-driven start leaves out the brightest fifth of the samples
# (they likely hold the highlight).
_DIFFUSE_QUANTILE = 0.8
# Roughness estimates are kept within the range a measured lobe can show (the goniometer's
# angular resolution below, a lobe wider than the hemisphere above).
_ALPHA_RANGE = (0.005, 1.0)
# Lobe scales of a start stay inside their range: a start at a bound has no slope.
_SPEC_RANGE = (1e-3, 0.95)
# Costs below this fraction of the data's own 1/2 |y|^2 are an exact fit, equal within
# round-off (see certify).
_EXACT = 1e-6
# Share of the random Lafortune lobes that start retro-reflective.
_RETRO_SHARE = 0.25
# Sample directions of the model's peak at unit scale: a mirror pair 10 degrees off normal.
_PEAK_THETA = math.radians(10.0)
# The new lobe of a nested start: shapes C0 (module docstring) and exponents.
_NEW_LOBE_SHAPES = ((-1.0, -1.0, 1.0), (-1.0, -1.0, 0.6), (1.0, 1.0, 1.0), (0.0, 0.0, 1.0))
_NEW_LOBE_N = (2.0, 10.0, 50.0, 250.0, 1250.0)
# tan theta_o / tan theta_i of the lobe aimed at the residual peak stays in this range.
_AIM_RANGE = (0.05, 20.0)


class MultiStart(Option):
    """How many starts a measured fit solves, and when their agreement is doubtful.

    n_random:   quasi-random starts (Sobol, scrambled with ``seed``), >= 0; default 24
    data:       include the data-driven starts (default True; 6 starts, one for a model
                with no lobe)
    nested:     a model that contains a smaller one (:func:`nested_model`) also starts from
                the smaller model's fit plus one new lobe (default True; 25 + 2 (L-1) starts
                for L Lafortune lobes)

    The automatic start of a single fit is always solved too (module docstring).
    seed:       seed of the Sobol scrambling
    rounds:     continuation budgets (module docstring), >= 0; default 4
    polish:     how many of the lowest-cost starts of a problem must have converged (or
                stopped for another reason than the budget) for the continuation to end,
                >= 1; default 4; also how many best results the perturbed generation
                starts from
    generations: perturbed generations at most (module docstring), >= 0; default 3
    agree_rtol: a start agrees when its cost is within this fraction of the best (0.01)
    min_share:  the certificate flags the optimum as doubtful when fewer than this share
                of the starts agree (0.2)
    """

    kind: ClassVar[str] = "multistart"
    n_random: int = 24
    data: bool = True
    nested: bool = True
    seed: int = 0
    rounds: int = 4
    polish: int = 4
    generations: int = 3
    agree_rtol: float = 0.01
    min_share: float = 0.2

    def __check_init__(self):
        if not isinstance(self.n_random, int) or self.n_random < 0:
            raise JaxreflError(f"MultiStart needs an integer n_random >= 0, got {self.n_random}")
        if not isinstance(self.rounds, int) or self.rounds < 0:
            raise JaxreflError(f"MultiStart needs an integer rounds >= 0, got {self.rounds}")
        if not isinstance(self.generations, int) or self.generations < 0:
            raise JaxreflError(
                f"MultiStart needs an integer generations >= 0, got {self.generations}"
            )
        if not isinstance(self.polish, int) or self.polish < 1:
            raise JaxreflError(f"MultiStart needs an integer polish >= 1, got {self.polish}")
        if self.n_random == 0 and not self.data:
            raise JaxreflError("MultiStart needs at least one start: n_random > 0 or data=True")
        if not (math.isfinite(self.agree_rtol) and self.agree_rtol >= 0):
            raise JaxreflError(f"MultiStart needs a finite agree_rtol >= 0, got {self.agree_rtol}")
        if not (0.0 <= self.min_share <= 1.0):
            raise JaxreflError(f"MultiStart needs min_share in [0, 1], got {self.min_share}")


_DEFAULT_STARTS = MultiStart()
_FLOAT32_CONFIG = FitConfig(dtype=np.float32)


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


@dataclass(frozen=True)
class Certificate:
    """How far the starts of a multi-start fit agree on its optimum.

    n_starts:   starts solved (per problem)
    n_agree:    starts whose cost is within ``rtol`` of the best (the worst problem's count
                when channels are separate problems)
    best_cost:  the lowest cost (the solver's 1/2 |r|^2), summed over problems
    excess:     relative excess (c - c_best)/c_best of the starts that do not agree:
                ``min``, ``median``, ``max`` over the finite ones (None where there are
                none), ``failed`` the count of starts without a finite cost
    rtol, min_share: the thresholds (:class:`MultiStart`)
    """

    n_starts: int
    n_agree: int
    best_cost: float
    excess: dict[str, Any]
    rtol: float
    min_share: float

    @property
    def share(self) -> float:
        """Fraction of the starts that agree."""
        return self.n_agree / max(self.n_starts, 1)

    @property
    def doubtful(self) -> bool:
        """True when fewer than ``min_share`` of the starts agree."""
        return self.share < self.min_share

    def short(self) -> str:
        """``"18/30"``, with ``" doubtful"`` appended when flagged."""
        return f"{self.n_agree}/{self.n_starts}" + (" doubtful" if self.doubtful else "")

    def to_dict(self) -> dict[str, Any]:
        return {
            "n_starts": self.n_starts,
            "n_agree": self.n_agree,
            "share": self.share,
            "agree_rtol": self.rtol,
            "min_share": self.min_share,
            "doubtful": self.doubtful,
            "best_cost": self.best_cost,
            "excess_of_the_rest": self.excess,
        }


def certify(
    costs: np.ndarray, rtol: float = 0.01, min_share: float = 0.2, scale: float = 0.0
) -> Certificate:
    """The :class:`Certificate` of costs (S,) of one problem or (N, S) of N problems.

    A start agrees when c - c_best <= rtol max(c_best, ``_EXACT`` scale), where ``scale`` is
    the cost of a zero prediction (1/2 |y|^2): at an (almost) exact fit every cost is
    round-off, and those below a millionth of the data's own agree with each other.
    """
    c = np.atleast_2d(np.asarray(costs, np.float64))
    c = np.where(np.isfinite(c), c, np.inf)
    best = np.min(c, axis=1, keepdims=True)
    tol = rtol * np.maximum(np.abs(best), _EXACT * scale) + np.finfo(np.float64).tiny
    agree = c <= best + tol
    n_agree = int(np.min(np.sum(agree, axis=1)))
    rel = (c - best) / np.where(best > 0, best, 1.0)
    rest = rel[~agree & np.isfinite(rel)]
    excess: dict[str, Any] = {"failed": int(np.sum(~np.isfinite(c)))}
    for k, fn in (("min", np.min), ("median", np.median), ("max", np.max)):
        excess[k] = float(fn(rest)) if rest.size else None
    total = float(np.sum(best)) if np.all(np.isfinite(best)) else math.inf
    return Certificate(c.shape[1], n_agree, total, excess, rtol, min_share)


def _problem(
    wi: np.ndarray,
    wo: np.ndarray,
    values: np.ndarray,
    channels: Channels,
    cosine: bool,
    dtype: np.dtype,
) -> PixelData:
    """The samples as N problems (N = 1 joint, C separate), as :func:`jaxrefl.fit.fit_samples`
    builds them."""
    obs, scale, weight = _sample_arrays(wi, wo, values, cosine=cosine, dtype=dtype)
    k, c = obs.shape
    if channels == "joint":
        return pixel_data(
            obs[None],
            wi[None].astype(dtype),
            wo[None].astype(dtype),
            scale=None if scale is None else scale[None],
            weight=weight[None],
        )
    return pixel_data(
        obs.T[..., None],
        np.broadcast_to(wi.astype(dtype), (c, k, 3)),
        np.broadcast_to(wo.astype(dtype), (c, k, 3)),
        scale=None if scale is None else scale.T[..., None],
        weight=weight.T[..., None],
    )


def _nested_starts(
    space: ParamSpace,
    nested: FitResult,
    wi: np.ndarray,
    wo: np.ndarray,
    f: np.ndarray,
    n: int,
    cosine: bool,
) -> np.ndarray:
    """(N, S, P) :func:`nested_thetas` of each of the N problems from the fit ``nested``
    (theta (P',) for one problem, (N, P') for N)."""
    theta = np.asarray(nested.theta, np.float64)
    if theta.size != n * nested.space.size:
        raise JaxreflError(
            f"the nested fit has {theta.size // max(nested.space.size, 1)} problems, "
            f"this fit {n}: fit both with the same channels"
        )
    with jax.enable_x64(True):
        natural = nested.space.to_natural(jnp.asarray(theta.reshape(n, -1)))
        nat = {k: np.asarray(v, np.float64) for k, v in natural.items()}
    out = []
    for i in range(n):
        p = {k: v[i] for k, v in nat.items()}
        fi = f if n == 1 else f[:, i : i + 1]
        out.append(nested_thetas(space, nested.model, p, wi, wo, fi, cosine=cosine))
    return np.stack(out)


def _finite_costs(r: FitResult, n: int, s: int) -> np.ndarray:
    c = np.asarray(r.cost, np.float64).reshape(n, s)
    return np.where(np.isfinite(c), c, np.inf)


# Perturbation scales (unconstrained units) of the perturbed generations of starts.
_PERTURB_SCALES = (0.25, 0.5, 1.0, 2.0)


def _perturbed(
    theta: np.ndarray, costs: np.ndarray, starts: MultiStart, generation: int
) -> np.ndarray:
    """(N * S, P) starts of a perturbed generation from the results so far (N, G * S, P)
    and their costs (N, G * S): the ``starts.polish`` lowest-cost results of each problem,
    each perturbed by Gaussian steps of every scale in ``_PERTURB_SCALES`` in turn
    (module docstring). ``generation`` = G, the generations so far; each has S starts."""
    n, _, p = theta.shape
    s = theta.shape[1] // generation
    rng = np.random.default_rng([starts.seed, generation])
    top = np.argsort(costs, axis=1)[:, : min(starts.polish, s)]
    m = np.arange(s)
    base = theta[np.arange(n)[:, None], top[:, m % top.shape[1]]]
    step = np.asarray(_PERTURB_SCALES)[(m // top.shape[1]) % len(_PERTURB_SCALES)]
    out = base + step[None, :, None] * rng.standard_normal((n, s, p))
    return out.reshape(n * s, p)


def _stack(a: FitResult, b: FitResult) -> FitResult:
    """Two batched results as one, ``a``'s rows first."""

    def cat(x, y):
        return jnp.concatenate([jnp.asarray(x), jnp.asarray(y)])

    return FitResult(
        jax.tree.map(cat, a.params, b.params),
        cat(a.theta, b.theta),
        cat(a.status, b.status),
        cat(a.cost, b.cost),
        cat(a.iterations, b.iterations),
        cat(a.n_used, b.n_used),
        a.space,
        a.model,
        a.backend,
    )


def _continue(
    model: BRDF,
    batch: PixelData,
    config: FitConfig,
    space: ParamSpace,
    r: FitResult,
    n: int,
    s: int,
    starts: MultiStart,
) -> FitResult:
    """The continuation of the module docstring: up to ``starts.rounds`` more budgets for
    the starts that stopped at the iteration limit, while one of each problem's
    ``starts.polish`` best has."""
    for _ in range(starts.rounds):
        status = np.asarray(r.status).reshape(n, s)
        costs = _finite_costs(r, n, s)
        top = np.argsort(costs, axis=1)[:, : starts.polish]
        if not np.any(np.take_along_axis(status, top, axis=1) == Status.MAX_ITERATIONS):
            break
        more = fit_pixels(model, batch, config=config, space=space, init=r.theta)
        # A start that had stopped for another reason keeps its result, and so does one
        # whose continuation did not lower its cost (the LM restarts its damping).
        hit = np.asarray(r.status) == Status.MAX_ITERATIONS
        lower = np.asarray(_finite_costs(more, n, s) < costs).reshape(-1)
        take = hit & lower
        iters = np.asarray(r.iterations) + np.where(hit, np.asarray(more.iterations), 0)

        def pick(a, b, take=take):
            a, b = np.asarray(a), np.asarray(b)
            return jnp.asarray(np.where(take.reshape(-1, *([1] * (a.ndim - 1))), b, a))

        r = FitResult(
            jax.tree.map(pick, r.params, more.params),
            pick(r.theta, more.theta),
            pick(r.status, more.status),
            pick(r.cost, more.cost),
            jnp.asarray(iters),
            pick(r.n_used, more.n_used),
            space,
            model,
            r.backend,
        )
    return r


def fit_multistart(
    model: BRDF,
    wi: np.ndarray,
    wo: np.ndarray,
    values: np.ndarray,
    *,
    channels: Channels = "joint",
    cosine: bool = True,
    config: FitConfig = _FLOAT32_CONFIG,
    starts: MultiStart = _DEFAULT_STARTS,
    thetas: np.ndarray | None = None,
    channel_names: tuple[str, ...] | None = None,
    nested: FitResult | None = None,
) -> tuple[FitResult, Certificate, np.ndarray]:
    """Fit ``model`` to f_r samples from many starts at once and keep the best per problem.

    wi, wo (K, 3), values (K, C) f_r in 1/sr (samples below the horizon get weight 0);
    ``channels``, ``cosine`` and ``config`` as for :func:`jaxrefl.fit.fit_samples` (config's
    dtype None: float32). The starts: the automatic one, then :func:`start_thetas`, then,
    with ``nested`` (the fit of :func:`nested_model` to the same samples, channels and
    cosine; used when ``starts.nested``), :func:`nested_thetas`; ``thetas`` (S, P) replaces
    them all (the thresholds of ``starts`` still certify).
    Returns the best result shaped as :func:`jaxrefl.fit.fit_samples` returns it (no
    leading axis when joint, C when separate), its :class:`Certificate`, and the (N, S)
    costs of every start.
    """
    dtype = np.dtype(np.float32 if config.dtype is None else config.dtype)
    wi = np.asarray(wi, np.float64)
    wo = np.asarray(wo, np.float64)
    f = np.asarray(values, np.float64)
    if f.ndim == 1:
        f = f[:, None]
    data = _problem(wi, wo, f, channels, cosine, dtype)
    n = data.obs.shape[0]
    names = channel_names if channels == "joint" else None
    if names is not None and len(names) != data.obs.shape[-1]:
        names = None
    space = ParamSpace(model, channels=data.obs.shape[-1], channel_names=names)
    if thetas is None:
        per = [
            start_thetas(space, wi, wo, f if n == 1 else f[:, i : i + 1], starts, cosine=cosine)
            for i in range(n)
        ]
        loss = L2() if config.loss is None else config.loss
        auto = np.asarray(initial_theta(make_residual(model, space, config.noise, loss), data))
        t0 = np.concatenate([auto[:, None].astype(np.float64), np.stack(per)], axis=1)
        if nested is not None and starts.nested:
            t0 = np.concatenate([t0, _nested_starts(space, nested, wi, wo, f, n, cosine)], axis=1)
    else:
        t0 = np.broadcast_to(np.asarray(thetas, np.float64), (n, *np.shape(thetas)))
    s = t0.shape[1]
    batch = jax.tree.map(lambda a: jnp.repeat(a, s, axis=0), data)
    r = fit_pixels(
        model,
        batch,
        config=config.replace(dtype=dtype),
        space=space,
        init=jnp.asarray(t0.reshape(n * s, -1), dtype),
    )
    cfg = config.replace(dtype=dtype)
    r = _continue(model, batch, cfg, space, r, n, s, starts)
    costs = _finite_costs(r, n, s)
    y = np.where(np.asarray(data.weight) > 0, np.asarray(data.obs, np.float64), 0.0)
    scale = float(0.5 * np.sum(y * y) / n)
    # Generations side by side: row g * n * s + i * s + j holds start j of problem i in
    # generation g; costs (n, G * s) in the same order along axis 1.
    thetas_all = np.asarray(r.theta, np.float64).reshape(n, s, -1)
    gen, improved = 1, True
    while (
        thetas is None
        and gen <= starts.generations
        and improved
        and certify(costs, starts.agree_rtol, starts.min_share, scale).doubtful
    ):
        t1 = _perturbed(thetas_all, costs, starts, gen)
        r1 = fit_pixels(model, batch, config=cfg, space=space, init=jnp.asarray(t1, dtype))
        r1 = _continue(model, batch, cfg, space, r1, n, s, starts)
        c1 = _finite_costs(r1, n, s)
        best = np.min(costs, axis=1)
        improved = bool(np.any(np.min(c1, axis=1) < best - starts.agree_rtol * np.abs(best)))
        r = _stack(r, r1)
        costs = np.concatenate([costs, c1], axis=1)
        thetas_all = np.concatenate(
            [thetas_all, np.asarray(r1.theta, np.float64).reshape(n, s, -1)], axis=1
        )
        gen += 1
    j = np.argmin(costs, axis=1)
    pick = (j // s) * n * s + np.arange(n) * s + j % s
    cert = certify(costs, starts.agree_rtol, starts.min_share, scale)

    def take(x):
        x = jnp.asarray(x)[pick]
        return x[0] if channels == "joint" else x

    theta = take(r.theta)
    params = space.to_natural(theta)
    if channels == "separate":
        kinds = {q.name: q.kind for q in model.params}
        params = {k: (v[:, 0] if kinds[k] == "color" else v) for k, v in params.items()}
    best = FitResult(
        params,
        theta,
        take(r.status),
        take(r.cost),
        take(r.iterations),
        take(r.n_used),
        space,
        model,
        r.backend,
    )
    return best, cert, costs

"""Stiff synthetic fits: problems built to stress the solver and float32, with known truth.

Each case draws ``n`` independent problems (one "pixel" each: K samples of f_r in C = 3
channels, 1% relative Gaussian noise) from a model with random parameters:

=====================  ====================================================================
case                   what makes it stiff
=====================  ====================================================================
``sharp_highlight``    GGX + Lambert with alpha = 1e-3: D peaks at 1/(pi alpha^2) ~ 3e5;
                       half of the samples lie within 3 alpha of the mirror direction
``grazing_only``       GGX + Lambert (alpha 0.1-0.5), every wi and wo at 80-89.5 degrees:
                       cosines down to 0.009, the Smith term and 1/(cos_i cos_o) steep
``exponent_1e4``       normalised Blinn-Phong with n = 1e4 (a lobe 0.6 degrees wide, peak
                       (n + 8)/(8 pi) ~ 400): half of the samples near the half-vector peak
``collinear_lights``   GGX + Lambert (alpha 0.1-0.5), every light within 0.05 degrees of one
                       direction and the view within 0.5 degrees of another (one camera, as
                       in a photographed capture): J^T J nearly singular, equilibrated
                       condition 5e5-6e9 (float32 resolves up to ~1e7)
=====================  ====================================================================

:func:`stiff_problems` returns the data as :class:`~jaxrefl.fit.PixelData` (float64) with
the truth; :func:`run_stiff` fits every case in float32, float64 and float32 with the
automatic float64 retry (:func:`fit_pixels_retry`) and scores each problem: *converged*
(the solver's convergence test passed within the iteration budget, whatever else the
status says: AT_BOUND outranks CONVERGED in the status code), *finite* (cost and
parameters finite) and *at optimum* (its cost,
re-evaluated in float64, within 1e-3 relative of the best cost known for that problem:
the lower of float64 fits started from the automatic start and from the truth).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from jaxrefl.brdf import BRDF, BlinnPhong, CookTorrance
from jaxrefl.fit import (
    FitConfig,
    FitResult,
    LMOptions,
    PixelData,
    fit_pixels,
    has_estimate,
    pixel_data,
)
from jaxrefl.measured import RetryResult, fit_pixels_retry
from jaxrefl.measured._retry import cost64, x64

__all__ = ["STIFF_CASES", "StiffProblem", "StiffRow", "run_stiff", "stiff_problems"]

STIFF_CASES = ("sharp_highlight", "grazing_only", "exponent_1e4", "collinear_lights")
# Relative slack of "at the optimum": float32 round-off of the parameters moves the cost of
# a converged fit by far less; a different basin moves it by orders of magnitude more.
OPTIMUM_RTOL = 1e-3
# Iteration budget of every fit here (the lean solver's default).
MAX_ITERS = 40
CONFIG = FitConfig(solver=LMOptions(max_iters=MAX_ITERS))


@dataclass(frozen=True, eq=False)
class StiffProblem:
    """``n`` problems of one case: the model, the data (float64, leading axis n) and truth."""

    case: str
    model: BRDF
    data: PixelData
    truth: dict[str, np.ndarray]


@dataclass(frozen=True)
class StiffRow:
    """Fractions over the n problems of one case fitted one way."""

    case: str
    mode: str  # "float32", "float64" or "float32+retry"
    n: int
    converged: float
    finite: float
    at_optimum: float
    retried: float  # fraction sent to float64 (retry mode only)
    kept_float64: float  # fraction where the float64 redo was kept
    fit_time_s: float  # warm wall time of the batched fit (retry: both passes)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _hemisphere(rng, shape, theta_min_deg=0.0, theta_max_deg=85.0) -> np.ndarray:
    """Directions uniform in solid angle between two polar angles."""
    c_hi, c_lo = np.cos(np.radians(theta_min_deg)), np.cos(np.radians(theta_max_deg))
    u = rng.uniform(c_lo, c_hi, shape)
    phi = rng.uniform(0.0, 2.0 * np.pi, shape)
    s = np.sqrt(1.0 - u * u)
    return np.stack([s * np.cos(phi), s * np.sin(phi), u], axis=-1)


def _around(axis: np.ndarray, max_angle: np.ndarray, rng) -> np.ndarray:
    """Directions within ``max_angle`` (radians, per entry) of unit ``axis`` (..., 3)."""
    t = rng.uniform(0.0, 1.0, axis.shape[:-1]) * max_angle
    phi = rng.uniform(0.0, 2.0 * np.pi, axis.shape[:-1])
    helper = np.where(np.abs(axis[..., 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    e1 = _unit(np.cross(axis, helper))
    e2 = np.cross(axis, e1)
    d = np.cos(t)[..., None] * axis + np.sin(t)[..., None] * (
        np.cos(phi)[..., None] * e1 + np.sin(phi)[..., None] * e2
    )
    return _unit(d)


def _mirror(w: np.ndarray) -> np.ndarray:
    return w * np.array([-1.0, -1.0, 1.0])


def _ggx() -> BRDF:
    return CookTorrance("ggx", diffuse="lambert")


def _truth_ggx(rng, n, alpha) -> dict[str, np.ndarray]:
    return {
        "albedo": rng.uniform(0.1, 0.6, (n, 3)),
        "specular": np.repeat(rng.uniform(0.03, 0.2, (n, 1)), 3, axis=1),
        "alpha": np.asarray(alpha, dtype=np.float64) * np.ones(n),
    }


def _case(
    case: str, n: int, k: int, rng
) -> tuple[BRDF, dict[str, np.ndarray], np.ndarray, np.ndarray]:
    half = k // 2
    if case == "sharp_highlight":
        truth = _truth_ggx(rng, n, 1e-3)
        wi = _hemisphere(rng, (n, k), 5.0, 70.0)
        wo = _hemisphere(rng, (n, k), 5.0, 80.0)
        # Half of the views within 3 alpha of the mirror direction (the highlight is seen).
        near = _around(_mirror(wi[:, :half]), np.full((n, half), 3e-3), rng)
        wo[:, :half] = near
        return _ggx(), truth, wi, wo
    if case == "grazing_only":
        truth = _truth_ggx(rng, n, np.exp(rng.uniform(np.log(0.1), np.log(0.5), n)))
        wi = _hemisphere(rng, (n, k), 80.0, 89.5)
        wo = _hemisphere(rng, (n, k), 80.0, 89.5)
        return _ggx(), truth, wi, wo
    if case == "exponent_1e4":
        model = BlinnPhong(normalized=True)
        truth = {
            "albedo": rng.uniform(0.1, 0.6, (n, 3)),
            "specular": np.repeat(rng.uniform(0.05, 0.3, (n, 1)), 3, axis=1),
            "exponent": np.full(n, 1e4),
        }
        wi = _hemisphere(rng, (n, k), 5.0, 60.0)
        wo = _hemisphere(rng, (n, k), 5.0, 80.0)
        # Half of the views put the half vector within ~2.5 lobe widths (1/sqrt(n)) of z.
        near = _around(_mirror(wi[:, :half]), np.full((n, half), 0.05), rng)
        wo[:, :half] = near
        return model, truth, wi, wo
    if case == "collinear_lights":
        truth = _truth_ggx(rng, n, np.exp(rng.uniform(np.log(0.1), np.log(0.5), n)))
        axis = _hemisphere(rng, (n, 1), 20.0, 50.0)
        wi = _around(np.broadcast_to(axis, (n, k, 3)), np.full((n, k), np.radians(0.05)), rng)
        view = _hemisphere(rng, (n, 1), 20.0, 50.0)
        wo = _around(np.broadcast_to(view, (n, k, 3)), np.full((n, k), np.radians(0.5)), rng)
        return _ggx(), truth, wi, wo
    raise ValueError(f"unknown stiff case {case!r}; choose from {STIFF_CASES}")


def stiff_problems(
    case: str, n: int = 32, k: int = 64, seed: int = 0, noise: float = 0.01
) -> StiffProblem:
    """``n`` problems of ``case`` with ``k`` samples each (module docstring), float64."""
    rng = np.random.default_rng(seed)
    model, truth, wi, wo = _case(case, n, k, rng)
    wi, wo = _unit(wi), _unit(wo)
    # Samples must lie above the horizon for the fit to use them.
    wo[..., 2] = np.maximum(wo[..., 2], 1e-3)
    wo = _unit(wo)
    with x64():
        p = {name: jnp.asarray(v)[:, None] for name, v in truth.items()}
        f = np.asarray(model.eval(p, jnp.asarray(wi), jnp.asarray(wo)), dtype=np.float64)
    obs = f * (1.0 + noise * rng.standard_normal(f.shape))
    with x64():
        data = pixel_data(jnp.asarray(obs), jnp.asarray(wi), jnp.asarray(wo))
    return StiffProblem(case, model, data, truth)


def _score(result: FitResult, c64: np.ndarray, best: np.ndarray) -> tuple[float, float, float]:
    status = np.asarray(result.status)
    stopped = (np.asarray(result.iterations) < MAX_ITERS) & has_estimate(status)
    finite = np.isfinite(np.asarray(result.cost)) & np.all(
        np.isfinite(np.asarray(result.theta)), axis=-1
    )
    opt = finite & (c64 <= best * (1.0 + OPTIMUM_RTOL) + 1e-12)
    return (
        float(np.mean(stopped & finite)),
        float(np.mean(finite)),
        float(np.mean(opt)),
    )


def _timed_fit(fn):
    import time

    import jax

    fn()  # compile
    t0 = time.perf_counter()
    out = fn()
    jax.block_until_ready(out.theta)
    return out, time.perf_counter() - t0


def run_stiff(
    cases: Sequence[str] = STIFF_CASES, n: int = 32, k: int = 64, seed: int = 0
) -> list[StiffRow]:
    """Fit every case three ways (module docstring); one :class:`StiffRow` per case and way."""
    rows = []
    for case in cases:
        pr = stiff_problems(case, n=n, k=k, seed=seed)
        model, data = pr.model, pr.data
        with x64():
            r64, t64 = _timed_fit(
                lambda m=model, d=data: fit_pixels(m, d, config=CONFIG.replace(dtype=jnp.float64))
            )
            r_truth = fit_pixels(
                model,
                data,
                dtype=jnp.float64,
                init={name: jnp.asarray(v) for name, v in pr.truth.items()},
            )
        c_auto = cost64(r64, data)
        c_truth = cost64(r_truth, data)
        best = np.fmin(c_auto, c_truth)
        r32, t32 = _timed_fit(
            lambda m=model, d=data: fit_pixels(m, d.astype(jnp.float32), config=CONFIG)
        )
        rr, trr = _timed_fit(lambda m=model, d=data: fit_pixels_retry(m, d, config=CONFIG))
        for mode, res, t, retried, kept in (
            ("float32", r32, t32, None, None),
            ("float64", r64, t64, None, None),
            ("float32+retry", rr, trr, rr.retried, rr.kept_float64),
        ):
            fr = res.result if isinstance(res, RetryResult) else res
            conv, fin, opt = _score(fr, cost64(fr, data), best)
            rows.append(
                StiffRow(
                    case=case,
                    mode=mode,
                    n=n,
                    converged=conv,
                    finite=fin,
                    at_optimum=opt,
                    retried=float("nan") if retried is None else float(np.mean(retried)),
                    kept_float64=float("nan") if kept is None else float(np.mean(kept)),
                    fit_time_s=t,
                )
            )
    return rows

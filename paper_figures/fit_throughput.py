"""Throughput of the lean batched LM against pixel count and observations per pixel.

    python paper_figures/fit_throughput.py [--out paper_figures]

Writes ``fit_throughput.csv`` and ``fit_throughput.png``: pixels/s of the lean LM
(``fit_pixels(init=theta0)``, the lean LM, from the ``initial_theta`` start) and of
``fit_pixels`` end to end (start included), for N = 1k, 4k, 16k, 64k pixels at K = 32, and
for K = 8, 16, 32, 64 observations per pixel at N = 16k; all from the public API. The
problem is that of ``benchmarks/fit_throughput.py``: GGX + Lambert, free (albedo, specular,
alpha), one channel, float32, fixed-seed synthetic pixels (albedo U(0.05, 0.8), specular
U(0.02, 0.2), alpha log-uniform in [0.02, 0.6]), lights on a Fibonacci spiral within 60
degrees, views mirrored about half vectors on a 40-degree spiral, scale = cos(theta_i), 1%
additive Gaussian noise. Times are warm calls (best of two for the LM, compile time apart,
``jax.block_until_ready``); the dashed line is the 30,000 pixels/s target of the benchmark.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import jaxrefl
from jaxrefl import fit

PIXELS = (1_000, 4_000, 16_000, 64_000)
KS = (8, 16, 32, 64)
N_FOR_K, K_FOR_N = 16_000, 32
TARGET = 30_000


def spiral(k: int, max_deg: float, rot: float = 0.0) -> np.ndarray:
    j = np.arange(k) + 0.5
    cos_t = 1.0 - (j / k) * (1.0 - np.cos(np.radians(max_deg)))
    sin_t = np.sqrt(1.0 - cos_t**2)
    phi = j * np.pi * (3.0 - np.sqrt(5.0)) + rot
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


def problem(model, n: int, k: int, seed: int = 0) -> fit.PixelData:
    rng = np.random.default_rng(seed)
    wi = spiral(k, 60.0)
    h = spiral(k, 40.0, rot=1.0)
    wo = 2.0 * np.sum(wi * h, axis=-1, keepdims=True) * h - wi
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    p = {
        "albedo": jnp.asarray(rng.uniform(0.05, 0.8, (n, 1, 1)), jnp.float32),
        "specular": jnp.asarray(rng.uniform(0.02, 0.2, (n, 1, 1)), jnp.float32),
        "alpha": jnp.asarray(np.exp(rng.uniform(np.log(0.02), np.log(0.6), (n, 1))), jnp.float32),
    }
    wi32, wo32 = jnp.asarray(wi, jnp.float32), jnp.asarray(wo, jnp.float32)
    scale = np.broadcast_to(wi[:, 2].astype(np.float32)[None, :, None], (n, k, 1))
    clean = np.asarray(model.eval(p, wi32[None], wo32[None])) * scale
    sigma = 0.01 * clean.mean(axis=(1, 2), keepdims=True)
    obs = (clean + sigma * rng.standard_normal(clean.shape)).astype(np.float32)
    return fit.pixel_data(
        obs,
        np.broadcast_to(wi32, (n, k, 3)),
        np.broadcast_to(wo32, (n, k, 3)),
        scale=scale,
    )


def _wait(r):
    jax.block_until_ready((r.theta, r.cost, r.status))
    return r


def measure(model, space, n: int, k: int) -> dict:
    data = problem(model, n, k)
    res = fit.make_residual(model, space)
    t0 = time.perf_counter()
    theta0 = jax.block_until_ready(fit.initial_theta(res, data))
    init_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    theta0 = jax.block_until_ready(fit.initial_theta(res, data))
    init_s = time.perf_counter() - t0

    def lean():
        return _wait(fit.fit_pixels(model, data, space=space, init=theta0))

    t0 = time.perf_counter()
    lean()
    first = time.perf_counter() - t0
    best, cores = math.inf, math.nan
    for _ in range(2):
        t0, c0 = time.perf_counter(), time.process_time()
        lean()
        dt = time.perf_counter() - t0
        if dt < best:
            best, cores = dt, (time.process_time() - c0) / dt
    t0 = time.perf_counter()
    _wait(fit.fit_pixels(model, data, space=space))  # compiled by the calls above
    fit_s = time.perf_counter() - t0
    return {
        "pixels": n,
        "k": k,
        "lm_compile_s": round(first - best, 3),
        "lm_s": round(best, 4),
        "lm_px_per_s": round(n / best),
        "lm_cores_used": round(cores, 2),
        "init_compile_s": round(init_first - init_s, 3),
        "init_s": round(init_s, 4),
        "fit_s": round(fit_s, 4),
        "fit_px_per_s": round(n / fit_s),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    model = jaxrefl.brdf.get(
        "cook_torrance",
        distribution="ggx",
        shadowing="smith_height_correlated",
        fresnel="schlick",
        diffuse="lambert",
    )
    space = fit.ParamSpace(model, channels=1, grey=("specular",))
    where = f"{platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__} on " + ", ".join(
        sorted({d.platform for d in jax.devices()})
    )
    done: dict[tuple[int, int], dict] = {}
    rows = []
    for sweep, points in (
        ("pixels", [(n, K_FOR_N) for n in PIXELS]),
        ("k", [(N_FOR_K, k) for k in KS]),
    ):
        for n, k in points:
            if (n, k) not in done:
                done[(n, k)] = measure(model, space, n, k)
                r = done[(n, k)]
                print(
                    f"N = {n:>6}, K = {k:>2}: lean LM {r['lm_px_per_s']:>7,} px/s "
                    f"(compile {r['lm_compile_s']:.1f} s), fit_pixels {r['fit_px_per_s']:>6,} px/s",
                    flush=True,
                )
            rows.append({"sweep": sweep, **done[(n, k)]})

    with open(args.out / "fit_throughput.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), sharey=True)
    for ax, sweep, key, label in (
        (axes[0], "pixels", "pixels", f"pixels N (K = {K_FOR_N})"),
        (axes[1], "k", "k", f"observations per pixel K (N = {N_FOR_K:,})"),
    ):
        sel = [r for r in rows if r["sweep"] == sweep]
        x = [r[key] for r in sel]
        ax.plot(x, [r["lm_px_per_s"] for r in sel], "o-", label="lean LM (from start)")
        ax.plot(x, [r["fit_px_per_s"] for r in sel], "s--", label="fit_pixels (start + LM)")
        ax.axhline(TARGET, color="grey", ls=":", lw=1, label=f"target {TARGET:,} px/s")
        ax.set_xscale("log", base=2 if sweep == "k" else 10)
        ax.set_xticks(x, [f"{v:,}" for v in x])
        ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("pixels / s (warm, float32)")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"GGX + Lambert, (albedo, specular, alpha): {where}", fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "fit_throughput.png", dpi=120)
    print(f"wrote {args.out / 'fit_throughput.csv'} and {args.out / 'fit_throughput.png'}")


if __name__ == "__main__":
    main()

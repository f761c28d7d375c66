"""Fit throughput: the lean batched LM against scipy, optimistix and jaxopt on the same pixels.

    python benchmarks/fit_throughput.py [--pixels 100000] [--k 32] [--quick] [--csv out.csv]

Problem: GGX + Lambert Cook-Torrance (height-correlated Smith, Schlick), one channel, free
(albedo, specular, alpha) = (albedo, specular, roughness); float32. Synthetic pixels (fixed
seed): albedo ~ U(0.05, 0.8), specular F0 ~ U(0.02, 0.2), alpha log-uniform in [0.02, 0.6];
K observations per pixel from one fixed set of directions shared by every pixel: lights on a
Fibonacci spiral within 60 degrees of the normal, views the mirror images of the lights
about half vectors on a second spiral within 40 degrees (for K = 32: views within 57
degrees of the normal, at least 12 degrees from their light; half vectors 5-40 degrees
from the normal); scale = cos(theta_i); additive Gaussian
noise of 1% of the pixel's mean clean observation. A second geometry, co-located light and
view (a flash capture, wo = wi on the 60-degree spiral), is timed for the lean LM only.

Measured, in one run and on the same data:

* ``initial_theta`` (closed-form colours on a roughness grid): the start shared by every
  solver below, timed on its own;
* the lean batched LM (``fit_pixels(init=theta0)``, solver ``fit.LMOptions()``) on all N
  pixels, its steps driven from Python; and the same as one compiled program
  (``LMOptions(host_loop=False)``, what runs under a trace), its baseline;
* ``fit_pixels`` end to end (default ``init="auto"``: start + lean LM), all N pixels;
* optimistix LM and jaxopt LM under vmap (``fit.OptimistixLM()``, ``fit.JaxoptLM()``, same
  start) on the
  first ``--lib-pixels`` pixels; a vmapped while loop runs every pixel until the slowest
  stops, so their per-pixel throughput is, if anything, flattered by the smaller batch;
* ``scipy.optimize.least_squares(method="lm")`` (MINPACK) in a per-pixel Python loop, on the
  first ``--scipy-pixels`` pixels, with the same residual and its ``jax.jacfwd`` Jacobian,
  jit-compiled, in float64 (scipy's own precision; its default tolerances need it).

Compile time is the first call on a shape minus the best warm call on the same shape;
pixels/s comes from warm calls only (best of ``--repeats``; ``jax.block_until_ready``).
"cores used" is process CPU time / wall time of that warm call (below 1 on a busy machine).
Accuracy is measured against the truth on the same pixels for every method (the first
``--scipy-pixels``, which every method fitted): the median relative roughness error
|alpha_hat / alpha - 1| (a pixel without an estimate counts as an infinite error) and the
fraction "at the optimum": the pixel's final cost, re-evaluated in float64 with the same
residual, within 1e-3 relative (+1e-12 absolute) of the lowest cost any method reached.

Also reported: the Laplace uncertainty map (``fit.laplace``, warm) as a fraction of the lean
LM's and of ``fit_pixels``' time on the same N pixels (target < 25%), and peak memory when
fitting a square capture tile by tile (16384 pixels a tile), one subprocess per image side
(512, 1024, 2048): the capture's input (a K-image stack, float32) and output maps are
allocated up front and scale with H * W; the peak RSS above that while tiles are fitted (the
per-tile working set) should not. For the larger sides only the first ``--mem-tiles`` tiles
are fitted (the working set of a tile does not depend on its position). Targets are reported
PASS / FALL SHORT, never asserted.

End to end (``--e2e-side``, default 1024; ``--no-e2e`` skips it): the library path of
``jaxrefl fit``, :func:`jaxrefl.svbrdf.fit_capture`, on a synthetic capture: the demo's
procedural SVBRDF (:mod:`jaxrefl.demo`, GGX + Lambert) rendered at side x side pixels in
its nine co-located flash photos, with the demo's sensor noise (1% relative + 0.2% of full
scale, Gaussian), kept in float (no 8-bit encoding). Rows: ``FitJob(model="ggx")`` and,
with ``--e2e-auto``, ``model="auto"`` (the default, which first chooses the model on held-out
photos); compile time apart (the job's own warm-up), pixels/s from the run's tile times.
In the same run and on the same capture's pixels (``--e2e-lm-pixels``, tile-shaped
blocks of ``pixel_block``): the lean LM alone from the automatic start, and the start
alone. Printed: px/s end to end, its ratio to the LM alone (target >= 50%, and >= 25,000
px/s), and the job's stage split (read, fit = start + LM, Laplace, errors + copy to host,
write; the fit stage split into start and LM by the start's share measured on the same
pixels).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, run_and_record, table

import jaxrefl
from jaxrefl import fit

TARGET_PX_S = 30_000
TARGET_E2E_RATIO, TARGET_E2E_PX_S = 0.5, 25_000
TARGET_LAPLACE = 0.25
OPT_RTOL, OPT_ATOL = 1e-3, 1e-12
SEED = 20240611


# ---------------------------------------------------------------------------- problem
def make_model():
    return jaxrefl.brdf.get(
        "cook_torrance",
        distribution="ggx",
        shadowing="smith_height_correlated",
        fresnel="schlick",
        diffuse="lambert",
    )


def make_space(model):
    return fit.ParamSpace(model, channels=1, grey=("specular",))


def spiral(k: int, max_deg: float, rot: float = 0.0) -> np.ndarray:
    """(k, 3) Fibonacci spiral of unit vectors within ``max_deg`` of +z (equal solid angle)."""
    j = np.arange(k) + 0.5
    cos_t = 1.0 - (j / k) * (1.0 - np.cos(np.radians(max_deg)))
    sin_t = np.sqrt(1.0 - cos_t**2)
    phi = j * np.pi * (3.0 - np.sqrt(5.0)) + rot
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


def directions(k: int, colocated: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """(wi, wo) of shape (k, 3) (module docstring); wo None when co-located."""
    wi = spiral(k, 60.0)
    if colocated:
        return wi, None
    h = spiral(k, 40.0, rot=1.0)
    wo = 2.0 * np.sum(wi * h, axis=-1, keepdims=True) * h - wi
    return wi, wo / np.linalg.norm(wo, axis=-1, keepdims=True)


def synth(n: int, k: int, colocated: bool = False, seed: int = SEED):
    """(data, truth, obs): PixelData (float32), natural truth (float64 numpy), obs array."""
    model = make_model()
    rng = np.random.default_rng(seed)
    truth = {
        "albedo": rng.uniform(0.05, 0.8, n),
        "specular": rng.uniform(0.02, 0.2, n),
        "alpha": np.exp(rng.uniform(np.log(0.02), np.log(0.6), n)),
    }
    wi, wo = directions(k, colocated)
    wi32 = jnp.asarray(wi, jnp.float32)
    wo32 = wi32 if wo is None else jnp.asarray(wo, jnp.float32)
    p = {
        "albedo": jnp.asarray(truth["albedo"][:, None, None], jnp.float32),
        "specular": jnp.asarray(truth["specular"][:, None, None], jnp.float32),
        "alpha": jnp.asarray(truth["alpha"][:, None], jnp.float32),
    }
    scale = wi[:, 2].astype(np.float32)[None, :, None]  # cos(theta_i), (1, K, 1)
    clean = np.asarray(model.eval(p, wi32[None], wo32[None])) * scale  # (n, K, 1)
    sigma = 0.01 * clean.mean(axis=(1, 2), keepdims=True)
    obs = (clean + sigma * rng.standard_normal(clean.shape)).astype(np.float32)
    data = pixel_data_for(obs, wi, wo)
    return data, truth, obs


def pixel_data_for(obs: np.ndarray, wi: np.ndarray, wo: np.ndarray | None):
    n, k, _ = obs.shape
    wi_b = np.broadcast_to(wi.astype(np.float32), (n, k, 3))
    wo_b = None if wo is None else np.broadcast_to(wo.astype(np.float32), (n, k, 3))
    scale = np.broadcast_to(wi[:, 2].astype(np.float32)[None, :, None], obs.shape)
    return fit.pixel_data(obs, wi_b, wo_b, scale=scale)


def head(data, n: int):
    """The first n pixels of a PixelData."""
    return jax.tree.map(lambda x: x[:n], data)


# ---------------------------------------------------------------------------- timing
def _block(out):
    """Wait for ``out`` (a FitResult, LaplaceResult or array tree) and return it."""
    if isinstance(out, fit.FitResult):
        jax.block_until_ready((out.theta, out.cost, out.status))
    elif isinstance(out, fit.LaplaceResult):
        jax.block_until_ready((out.std, out.flag))
    else:
        jax.block_until_ready(out)
    return out


def timed(fn, repeats: int, warm: bool = False):
    """(result, first-call seconds, best warm seconds, cores used in that call).

    ``warm=True``: the shapes are already compiled; the first call is not timed apart."""
    first = math.nan
    if not warm:
        t0 = time.perf_counter()
        out = _block(fn())
        first = time.perf_counter() - t0
    best, cores = math.inf, math.nan
    for _ in range(max(1, repeats)):
        t0, c0 = time.perf_counter(), time.process_time()
        out = _block(fn())
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        if dt < best:
            best, cores = dt, dc / dt
    return out, first, best, cores


# ---------------------------------------------------------------------------- accuracy
def cost64(model, space, theta: np.ndarray, data) -> np.ndarray:
    """1/2 |r|^2 per pixel in float64 with the fit's residual; inf where theta is not finite."""
    theta = np.asarray(theta, np.float64)
    ok = np.all(np.isfinite(theta), axis=-1)
    with jax.enable_x64(True):
        res = fit.make_residual(model, space)
        d64 = data.astype(jnp.float64)
        f = jax.jit(jax.vmap(lambda t, d: 0.5 * jnp.sum(res(t, d) ** 2)))
        c = np.asarray(f(jnp.asarray(np.where(ok[:, None], theta, 0.0)), d64))
    return np.where(ok & np.isfinite(c), c, np.inf)


def alpha_of(space, theta: np.ndarray) -> np.ndarray:
    theta = np.asarray(theta, np.float64)
    with jax.enable_x64(True):
        a = np.asarray(space.to_natural(jnp.asarray(theta))["alpha"], np.float64)
    return a.reshape(theta.shape[0])


def rel_alpha_err(space, theta, alpha_true) -> np.ndarray:
    err = np.abs(alpha_of(space, theta) / alpha_true - 1.0)
    return np.where(np.isfinite(err), err, np.inf)


# ---------------------------------------------------------------------------- scipy loop
def scipy_loop(model, space, theta0: np.ndarray, data):
    """least_squares(method="lm") per pixel: (theta, compile s, run s, cores used)."""
    from scipy.optimize import least_squares

    n = theta0.shape[0]
    out = np.full(theta0.shape, np.nan)
    with jax.enable_x64(True):
        res = fit.make_residual(model, space)
        d64 = data.astype(jnp.float64)

        def one(d, i):
            return jax.tree.map(lambda x: x[i], d)

        fun = jax.jit(lambda t, d, i: res(t, one(d, i)))
        jac = jax.jit(lambda t, d, i: jax.jacfwd(res)(t, one(d, i)))
        t0 = time.perf_counter()
        x0 = np.asarray(theta0[0], np.float64)
        jax.block_until_ready((fun(x0, d64, 0), jac(x0, d64, 0)))
        compile_s = time.perf_counter() - t0
        t0, c0 = time.perf_counter(), time.process_time()
        for i in range(n):
            x0 = np.asarray(theta0[i], np.float64)
            if not np.all(np.isfinite(x0)):
                continue
            sol = least_squares(
                lambda t, i=i: np.asarray(fun(t, d64, i)),
                x0,
                jac=lambda t, i=i: np.asarray(jac(t, d64, i)),
                method="lm",
            )
            out[i] = sol.x
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
    return out, compile_s, dt, dc / dt


# ---------------------------------------------------------------------------- memory
def _proc_kib(field: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return -1


def _reset_peak() -> bool:
    """Reset the kernel's peak-RSS mark (VmHWM) of this process; False if not supported."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return _proc_kib("VmHWM") <= _proc_kib("VmRSS") + 1024
    except OSError:
        return False


def memory_child(side: int, tile: int, max_tiles: int, k: int) -> dict:
    """Fit a side x side capture tile by tile; prints one JSON line (run in a subprocess)."""
    import resource

    mib = 1.0 / 1024.0
    model, space = make_model(), make_space(make_model())
    wi, wo = directions(k, colocated=False)
    bank_data, _, bank_obs = synth(tile, k)
    t0 = time.perf_counter()
    _block(fit.fit_pixels(model, bank_data, space=space))  # compile on the tile shape
    compile_s = time.perf_counter() - t0
    del bank_data
    rss_base = _proc_kib("VmRSS")
    n_pix = side * side
    n_tiles = -(-n_pix // tile)
    # The capture: a K-image float32 stack (pixels, K, 1), filled with copies of the bank
    # (the content does not matter for memory), and the output maps (3 parameters, status).
    obs = np.empty((n_pix, k, 1), np.float32)
    for s in range(0, n_pix, tile):
        m = min(tile, n_pix - s)
        obs[s : s + m] = bank_obs[:m]
    out_theta = np.full((n_pix, space.size), np.nan, np.float32)
    out_status = np.full((n_pix,), -1, np.int32)
    rss_inputs = _proc_kib("VmRSS")
    hwm = _reset_peak()
    run = min(n_tiles, max_tiles)
    t0 = time.perf_counter()
    for t in range(run):
        s = t * tile
        sl = obs[s : s + tile]
        if sl.shape[0] < tile:  # a short last tile is padded to the compiled shape
            sl = np.concatenate([sl, np.repeat(sl[-1:], tile - sl.shape[0], axis=0)])
        r = fit.fit_pixels(model, pixel_data_for(sl, wi, wo), space=space)
        m = min(tile, n_pix - s)
        out_theta[s : s + m] = np.asarray(r.theta)[:m]
        out_status[s : s + m] = np.asarray(r.status)[:m]
        del r
    tiles_s = time.perf_counter() - t0
    peak = _proc_kib("VmHWM") if hwm else -1
    live = sum(x.nbytes for x in jax.live_arrays())
    rec = {
        "side": side,
        "pixels": n_pix,
        "tile": tile,
        "tiles": n_tiles,
        "tiles_fitted": run,
        "input_mib": obs.nbytes / 2**20,
        "output_mib": (out_theta.nbytes + out_status.nbytes) / 2**20,
        "rss_base_mib": rss_base * mib,
        "rss_inputs_mib": rss_inputs * mib,
        "peak_tiles_mib": peak * mib if hwm else math.nan,
        "growth_mib": (peak - rss_inputs) * mib if hwm else math.nan,
        "ru_maxrss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * mib,
        "live_jax_mib": live / 2**20,
        "compile_s": compile_s,
        "s_per_tile": tiles_s / run,
    }
    print("MEMORY " + json.dumps(rec), flush=True)
    return rec


def memory_table(sides, tile: int, max_tiles: int, k: int) -> list[dict]:
    here = str(Path(__file__).resolve().parent)
    recs = []
    for side in sides:
        n_tiles = -(-side * side // tile)
        run = n_tiles if side == sides[0] else max_tiles
        code = (
            f"import sys; sys.path.insert(0, {here!r}); import fit_throughput as ft; "
            f"ft.memory_child({side}, {tile}, {run}, {k})"
        )
        p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        line = [x for x in p.stdout.splitlines() if x.startswith("MEMORY ")]
        if p.returncode != 0 or not line:
            print(f"memory run for side {side} failed:\n{p.stderr[-2000:]}", file=sys.stderr)
            continue
        recs.append(json.loads(line[-1][len("MEMORY ") :]))
    return recs


# ---------------------------------------------------------------------------- end to end
def noisy_demo_capture(side: int, seed: int = 0):
    """The demo scene rendered at side x side (9 flash photos, float, demo sensor noise)."""
    from jaxrefl.cli._demo import _NOISE_ABS, _NOISE_REL
    from jaxrefl.demo import demo_capture, demo_scene, render_demo

    scene = demo_scene(size=side, seed=seed)
    lin = np.asarray(jax.jit(lambda: render_demo(scene, encode=False))(), np.float32)
    rng = np.random.default_rng(seed + 1)
    noisy = lin * (1 + _NOISE_REL * rng.standard_normal(lin.shape, np.float32))
    noisy = np.clip(noisy + _NOISE_ABS * rng.standard_normal(lin.shape, np.float32), 0.0, 1.0)
    return demo_capture(scene, noisy)


def end_to_end(side: int, lm_pixels: int, repeats: int, auto: bool) -> list[dict]:
    """fit_capture rows on a side x side demo capture, with the LM and the start alone on
    the same capture's pixels (module docstring)."""
    from jaxrefl import svbrdf
    from jaxrefl.svbrdf._data import pixel_block
    from jaxrefl.svbrdf._tile_fitter import TileFitter

    t0 = time.perf_counter()
    cap = noisy_demo_capture(side)
    print(
        f"capture: {side} x {side}, {cap.n_photos} photos, rendered in "
        f"{time.perf_counter() - t0:.1f} s"
    )
    n_px = side * side
    recs = []
    lm_ref: dict = {}
    for model in ("ggx", "auto") if auto else ("ggx",):
        job = svbrdf.FitJob(model=model)
        t0 = time.perf_counter()
        r = svbrdf.fit_capture(cap, job)
        wall = time.perf_counter() - t0
        tm = r.report["timings"]
        rec = {
            "model": model,
            "chosen": r.job.model,
            "pixels": n_px,
            "compile_s": tm["compile_s"],
            "run_s": tm["run_s"],
            "choose_s": tm["choose_s"],
            "wall_s": wall,
            "px_per_s": n_px / tm["run_s"],
            "stages_s": tm["stages_s"],
            "tile_pixels": tm["tile_pixels"],
            "status": r.report["status_counts"],
        }
        if r.job.model not in lm_ref:
            # The LM alone and the start alone on the same pixels, tile-shaped blocks (the
            # job's own compiled shapes), same model, space, noise and loss as the job.
            # The fit's job records the compaction that ran (FitJob.compact).
            fitter = TileFitter(cap, r.job, pooled=r.pooled)
            tile = r.job.tile_pixels
            n_lm = min(lm_pixels, n_px) // tile * tile or tile
            blocks = [
                pixel_block(cap, s, min(s + tile, n_px), tile, dtype=np.float32)
                for s in range(0, n_lm, tile)
            ]
            res = fitter.residual
            kw = dict(space=fitter.space, config=fitter.config, prior=fitter.prior)
            thetas = [jax.block_until_ready(fit.initial_theta(res, d)) for d in blocks]

            def start_all(res=res, blocks=blocks):
                return [fit.initial_theta(res, d) for d in blocks]

            def lm_all(model=fitter.model, blocks=blocks, thetas=thetas, kw=kw):
                return [
                    fit.fit_pixels(model, d, init=t, **kw).theta
                    for d, t in zip(blocks, thetas, strict=True)
                ]

            _, _, start_s, _ = timed(start_all, repeats)
            _, _, lm_s, _ = timed(lm_all, repeats)
            lm_ref[r.job.model] = {"pixels": len(blocks) * tile, "start_s": start_s, "lm_s": lm_s}
        ref = lm_ref[r.job.model]
        rec["lm_px_per_s"] = ref["pixels"] / ref["lm_s"]
        rec["start_px_per_s"] = ref["pixels"] / ref["start_s"]
        rec["lm_pixels"] = ref["pixels"]
        recs.append(rec)
    return recs


def e2e_report(recs: list[dict]) -> None:
    def f(v, spec):
        return "-" if v is None else format(v, spec)

    print(
        table(
            [
                "fit_capture model",
                "pixels",
                "compile s",
                "choose s",
                "run s",
                "px/s end to end",
                "LM alone px/s",
                "end to end / LM",
                "start alone px/s",
            ],
            [
                [
                    r["model"] + ("" if r["model"] == r["chosen"] else f" -> {r['chosen']}"),
                    r["pixels"],
                    f"{r['compile_s']:.1f}",
                    f"{r['choose_s']:.1f}",
                    f"{r['run_s']:.2f}",
                    f"{r['px_per_s']:,.0f}",
                    f"{r['lm_px_per_s']:,.0f}",
                    f"{r['px_per_s'] / r['lm_px_per_s']:.0%}",
                    f"{r['start_px_per_s']:,.0f}",
                ]
                for r in recs
            ],
        )
    )
    print("\nstage split of the run (seconds; share of run s):")
    for r in recs:
        st = dict(r["stages_s"])
        # The fit stage as start + LM, by their times alone on the same pixels.
        share = (1 / r["start_px_per_s"]) / (1 / r["start_px_per_s"] + 1 / r["lm_px_per_s"])
        parts = {
            "read": st["read"],
            "start (est.)": st["fit"] * share,
            "LM (est.)": st["fit"] * (1 - share),
            "laplace": st["laplace"],
            "errors + to host": st["errors"],
            "write": st["write"],
        }
        other = r["run_s"] - sum(st.values())
        body = ", ".join(f"{k} {v:.2f} ({v / r['run_s']:.0%})" for k, v in parts.items())
        print(f"  {r['model']}: {body}, other {other:.2f}")
    for r in recs:
        ratio = r["px_per_s"] / r["lm_px_per_s"]
        ok = ratio >= TARGET_E2E_RATIO and r["px_per_s"] >= TARGET_E2E_PX_S
        print(
            f"target end to end >= {TARGET_E2E_RATIO:.0%} of the LM alone and >= "
            f"{TARGET_E2E_PX_S:,} px/s, fit_capture model={r['model']}: {r['px_per_s']:,.0f}"
            f" px/s, {ratio:.0%} of the LM -> {'PASS' if ok else 'FALL SHORT'}"
        )


# ---------------------------------------------------------------------------- main
def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--pixels", type=int, default=100_000, help="pixels for the lean LM")
    ap.add_argument("--k", type=int, default=32, help="observations per pixel")
    ap.add_argument("--lib-pixels", type=int, default=4000, help="pixels for optimistix/jaxopt")
    ap.add_argument("--scipy-pixels", type=int, default=1000, help="pixels for the scipy loop")
    ap.add_argument("--repeats", type=int, default=2, help="warm calls per JAX method (best)")
    ap.add_argument("--mem-tiles", type=int, default=3, help="tiles fitted for larger sides")
    ap.add_argument("--tile", type=int, default=16384, help="pixels per tile (memory part)")
    ap.add_argument("--no-memory", action="store_true", help="skip the capture memory part")
    ap.add_argument("--e2e-side", type=int, default=1024, help="side of the end-to-end capture")
    ap.add_argument("--e2e-lm-pixels", type=int, default=65536, help="pixels for the LM alone")
    ap.add_argument("--e2e-auto", action="store_true", help="also fit_capture with model=auto")
    ap.add_argument("--no-e2e", action="store_true", help="skip the end-to-end part")
    ap.add_argument("--e2e-only", action="store_true", help="only the end-to-end part")
    ap.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run")
    ap.add_argument("--csv", type=Path, help="also write the rows as CSV")
    args = ap.parse_args()
    sides = [512, 1024, 2048]
    if args.quick:
        args.pixels, args.lib_pixels, args.scipy_pixels = 2000, 500, 100
        args.tile, args.mem_tiles, args.repeats = 4096, 2, 1
        sides = [128, 256, 512]
        args.e2e_side, args.e2e_lm_pixels = min(args.e2e_side, 128), 8192
    n, k = args.pixels, args.k
    n_lib = min(args.lib_pixels, n)
    n_sp = min(args.scipy_pixels, n_lib)
    load0 = os.getloadavg()
    print(f"# Fit throughput: GGX + Lambert, (albedo, specular, alpha), K = {k}, float32")
    print(f"machine: {machine()}")
    print(
        f"jax devices: {jax.device_count()}; XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}; "
        f"load average at start: {load0[0]:.2f} (1 min)\n"
    )

    if args.e2e_only:
        print(f"## End to end: fit_capture on a {args.e2e_side} x {args.e2e_side} demo capture\n")
        e2e_report(end_to_end(args.e2e_side, args.e2e_lm_pixels, args.repeats, args.e2e_auto))
        return 0

    model = make_model()
    space = make_space(model)
    res = fit.make_residual(model, space)
    data, truth, _ = synth(n, k)
    rows: list[dict] = []
    thetas: dict[str, np.ndarray] = {}

    def row(method, pixels, compile_s, run_s, cores, note=""):
        rows.append(
            {
                "method": method,
                "pixels": pixels,
                "compile_s": compile_s,
                "run_s": run_s,
                "px_per_s": pixels / run_s,
                "cores_used": cores,
                "note": note,
            }
        )

    # 1. The shared start.
    theta0, first, best, cores = timed(lambda: fit.initial_theta(res, data), args.repeats)
    row("start: initial_theta", n, first - best, best, cores, "shared start of every solver")
    theta0_np = np.asarray(theta0)
    thetas["start: initial_theta"] = theta0_np[:n_sp]

    # 2. Lean batched LM from that start.
    def lean():
        return fit.fit_pixels(model, data, space=space, init=theta0)

    r_lean, first, best, cores = timed(lean, args.repeats)
    row("lean LM (batched)", n, first - best, best, cores)
    thetas["lean LM (batched)"] = np.asarray(r_lean.theta)[:n_sp]
    lean_s = best

    # 2b. The same LM as one compiled program (its steps in loops, compaction stages in
    # blocks): the organisation under a trace, as a baseline for the host-driven steps.
    one_program = fit.LMOptions(host_loop=False)
    r_one, first, best, cores = timed(
        lambda: fit.fit_pixels(
            model, data, config=fit.FitConfig(solver=one_program), space=space, init=theta0
        ),
        args.repeats,
    )
    label = "lean LM, one program (host_loop=False)"
    row(label, n, first - best, best, cores, "baseline of row 2")
    thetas[label] = np.asarray(r_one.theta)[:n_sp]

    # 3. fit_pixels end to end (the same jitted pieces, already compiled above).
    r_auto, _, best, cores = timed(
        lambda: fit.fit_pixels(model, data, space=space), args.repeats, warm=True
    )
    row("fit_pixels (start + lean LM)", n, math.nan, best, cores, "compiled in rows 1-2")
    thetas["fit_pixels (start + lean LM)"] = np.asarray(r_auto.theta)[:n_sp]
    fit_s = best

    # 4. Laplace map on the same N pixels.
    lap, first, lap_s, lap_cores = timed(lambda: fit.laplace(r_lean, data), args.repeats)
    lap_compile = first - lap_s

    # 5. Library LMs under vmap on the first n_lib pixels.
    d_lib, t_lib = head(data, n_lib), theta0[:n_lib]
    for be, label in (
        (fit.OptimistixLM(), "optimistix LM (vmap)"),
        (fit.JaxoptLM(), "jaxopt LM (vmap)"),
    ):
        cfg = fit.FitConfig(solver=be)
        r, first, best, cores = timed(
            lambda cfg=cfg: fit.fit_pixels(model, d_lib, config=cfg, space=space, init=t_lib),
            args.repeats,
        )
        row(label, n_lib, first - best, best, cores, "same start")
        thetas[label] = np.asarray(r.theta)[:n_sp]

    # 6. scipy per-pixel loop.
    d_sp = head(data, n_sp)
    th_sp, comp, run_s, cores = scipy_loop(model, space, theta0_np[:n_sp], d_sp)
    row("scipy least_squares lm (loop, f64)", n_sp, comp, run_s, cores, "same start")
    thetas["scipy least_squares lm (loop, f64)"] = th_sp

    # 7. The lean LM on the co-located (flash) geometry, same truth.
    data_c, truth_c, _ = synth(n, k, colocated=True)
    theta0_c = jax.block_until_ready(fit.initial_theta(res, data_c))
    r_c, first, best, cores = timed(
        lambda: fit.fit_pixels(model, data_c, space=space, init=theta0_c), args.repeats
    )
    row("lean LM, co-located geometry", n, first - best, best, cores, "flash: wo = wi")
    err_c = rel_alpha_err(space, np.asarray(r_c.theta)[:n_sp], truth_c["alpha"][:n_sp])

    # Accuracy on the common pixels (the first n_sp, fitted by every method).
    costs = {m: cost64(model, space, th, d_sp) for m, th in thetas.items()}
    solvers = [m for m in costs if not m.startswith("start")]
    best_cost = np.min(np.stack([costs[m] for m in solvers]), axis=0)
    a_true = truth["alpha"][:n_sp]
    for rw in rows:
        m = rw["method"]
        if m in thetas:
            err = rel_alpha_err(space, thetas[m], a_true)
            rw["median_rel_alpha_err"] = float(np.median(err))
            at = costs[m] <= best_cost * (1.0 + OPT_RTOL) + OPT_ATOL
            rw["at_optimum"] = float(np.mean(at))
        elif m.startswith("lean LM, co-located"):
            rw["median_rel_alpha_err"] = float(np.median(err_c))
            rw["at_optimum"] = math.nan
        rw["lean_over_this"] = (n / lean_s) / rw["px_per_s"]

    def fmt(v, spec):
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)

    print(
        table(
            [
                "method",
                "pixels",
                "compile s",
                "run s",
                "pixels/s",
                "lean LM / this",
                "cores used",
                "med. rel. alpha err",
                "at optimum",
            ],
            [
                [
                    r["method"],
                    r["pixels"],
                    fmt(r["compile_s"], ".1f"),
                    fmt(r["run_s"], ".3f"),
                    fmt(r["px_per_s"], ",.0f"),
                    "-" if r["method"].startswith("start") else fmt(r["lean_over_this"], ".2f"),
                    fmt(r["cores_used"], ".2f"),
                    fmt(r.get("median_rel_alpha_err"), ".4f"),
                    fmt(r.get("at_optimum"), ".3f"),
                ]
                for r in rows
            ],
        )
    )
    print(
        f"\naccuracy columns: the first {n_sp} pixels (fitted by every method); optimum ="
        f" float64 cost within {OPT_RTOL:g} rel + {OPT_ATOL:g} abs of the best solver's cost"
        f" (co-located row: its own data, no optimum reference)."
    )
    err_all = rel_alpha_err(space, np.asarray(r_lean.theta), truth["alpha"])
    print(
        f"lean LM on all {n} pixels: median rel. alpha err {np.median(err_all):.4f}, "
        f"iterations mean {float(np.mean(np.asarray(r_lean.iterations))):.1f}, "
        f"status {r_lean.status_counts()}"
    )
    lean_px = n / lean_s
    ok = lean_px >= TARGET_PX_S
    print(
        f"\ntarget >= {TARGET_PX_S:,} px/s, batched LM: {lean_px:,.0f} px/s -> "
        f"{'PASS' if ok else 'FALL SHORT'}"
        f" (fit_pixels end to end, start included: {n / fit_s:,.0f} px/s)"
    )
    frac_lm, frac_fit = lap_s / lean_s, lap_s / fit_s
    print(
        f"Laplace map: compile {lap_compile:.1f} s, run {lap_s:.3f} s on {n} pixels "
        f"({n / lap_s:,.0f} px/s, {lap.flag_counts()['reliable']} reliable); "
        f"fraction of the lean LM {frac_lm:.1%}, of fit_pixels {frac_fit:.1%} "
        f"(target < {TARGET_LAPLACE:.0%}): "
        f"vs LM {'PASS' if frac_lm < TARGET_LAPLACE else 'FALL SHORT'}, "
        f"vs fit_pixels {'PASS' if frac_fit < TARGET_LAPLACE else 'FALL SHORT'}"
    )

    mem: list[dict] = []
    if not args.no_memory:
        print(
            f"\n## Peak memory, tiled capture fit ({args.tile} pixels a tile, fit_pixels per"
            " tile, one subprocess per side)\n"
        )
        mem = memory_table(sides, args.tile, args.mem_tiles, k)
        if mem:
            for m in mem:
                m["footprint_mib"] = m["peak_tiles_mib"] - m["input_mib"] - m["output_mib"]
            print(
                table(
                    [
                        "side",
                        "pixels",
                        "tiles fitted",
                        "capture in MiB",
                        "maps out MiB",
                        "RSS before capture MiB",
                        "RSS with capture MiB",
                        "peak fitting MiB",
                        "peak - capture MiB",
                        "growth fitting MiB",
                        "s / tile",
                    ],
                    [
                        [
                            f"{m['side']} x {m['side']}",
                            m["pixels"],
                            f"{m['tiles_fitted']} / {m['tiles']}",
                            f"{m['input_mib']:.0f}",
                            f"{m['output_mib']:.0f}",
                            f"{m['rss_base_mib']:.0f}",
                            f"{m['rss_inputs_mib']:.0f}",
                            fmt(m["peak_tiles_mib"], ".0f"),
                            fmt(m["footprint_mib"], ".0f"),
                            fmt(m["growth_mib"], ".0f"),
                            f"{m['s_per_tile']:.2f}",
                        ]
                        for m in mem
                    ],
                )
            )
            print(
                "\ncapture in / maps out: the capture's own arrays (K-image float32 stack;"
                " parameter and status maps), allocated before fitting. RSS before capture:"
                " after import and a warm-up fit of one tile (compile). peak fitting: peak RSS"
                " while the tiles are fitted (kernel VmHWM, reset after allocation); peak -"
                " capture: that minus the capture's arrays (runtime + compiled code + one"
                " tile's working set); growth fitting: peak fitting - RSS with capture."
            )
            fp = [m["footprint_mib"] for m in mem]
            if all(math.isfinite(v) for v in fp):
                flat = max(fp) - min(fp) <= max(64.0, 0.1 * max(fp))
                print(
                    f"peak - capture {min(fp):.0f}-{max(fp):.0f} MiB over sides "
                    f"{mem[0]['side']}-{mem[-1]['side']} (capture {mem[0]['input_mib']:.0f}-"
                    f"{mem[-1]['input_mib']:.0f} MiB): constant in image size -> "
                    f"{'PASS' if flat else 'FALL SHORT'}; live JAX buffers after the last "
                    f"tile: {max(m['live_jax_mib'] for m in mem):.1f} MiB"
                )
            else:
                print("peak RSS could not be reset on this system (/proc/self/clear_refs)")
    e2e: list[dict] = []
    if not args.no_e2e:
        side = args.e2e_side
        print(f"\n## End to end: fit_capture on a {side} x {side} demo capture\n")
        e2e = end_to_end(side, args.e2e_lm_pixels, args.repeats, args.e2e_auto)
        e2e_report(e2e)
    load1 = os.getloadavg()
    print(f"\nload average at end: {load1[0]:.2f} (1 min)")

    if args.csv:
        fields = [
            "section",
            "method",
            "pixels",
            "compile_s",
            "run_s",
            "px_per_s",
            "lean_over_this",
            "cores_used",
            "median_rel_alpha_err",
            "at_optimum",
            "note",
        ]
        extra = [
            {
                "section": "laplace",
                "method": "laplace map",
                "pixels": n,
                "compile_s": lap_compile,
                "run_s": lap_s,
                "px_per_s": n / lap_s,
                "cores_used": lap_cores,
                "note": f"fraction of lean LM {frac_lm:.4f}; of fit_pixels {frac_fit:.4f}",
            }
        ]
        mem_fields = sorted({key for m in mem for key in m} - set(fields))
        with open(args.csv, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields + mem_fields, extrasaction="ignore")
            w.writeheader()
            for r in rows:
                w.writerow({"section": "throughput", **r})
            w.writerows(extra)
            for m in mem:
                w.writerow({"section": "memory", "method": f"tiled {m['side']}", **m})
            for r in e2e:
                w.writerow(
                    {
                        "section": "end_to_end",
                        "method": f"fit_capture {r['model']}",
                        "pixels": r["pixels"],
                        "compile_s": r["compile_s"],
                        "run_s": r["run_s"],
                        "px_per_s": r["px_per_s"],
                        "note": f"LM alone {r['lm_px_per_s']:.0f} px/s; stages {r['stages_s']}",
                    }
                )
    return 0


if __name__ == "__main__":
    sys.exit(run_and_record("fit_throughput", "Fit throughput", main))

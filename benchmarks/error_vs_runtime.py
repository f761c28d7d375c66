"""Fit error against run time: every model x solver backend x dtype on a fixed set of BRDFs.

    python benchmarks/error_vs_runtime.py [--models ...] [--csv out.csv] [--quick]

Materials (fixed): the two Cornell files (spectra -> linear sRGB under D65, 1439 samples
within 80 degrees), two CURET samples (grey, 189 samples within 80 degrees) and two
synthetic materials of 1439 gonioreflectometer samples with 1% noise (a GGX + Lambert
plastic and a two-lobe Lafortune material). Every fit minimises the cosine-weighted
residual (``jaxrefl.measured.fit_model``'s default) with :func:`jaxrefl.fit.fit_samples`;
no float64 retry, so that each row is the dtype it says.

Per row: the three error metrics of :mod:`jaxrefl.measured._metrics` (against the measured
samples, evaluated in float64), the warm wall time of the fit (a second identical call)
and the compile time (first call minus warm call; the Cornell and synthetic materials share
one shape, so only the first of them pays compilation and the others report 0), the
solver status and iterations. The table printed at the end aggregates over materials:
median fit time, geometric mean over materials of the error relative to the best fit of
that material, and on how many materials the configuration is on the Pareto front
(lowest error for its time).
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, run_and_record, table

from jaxrefl import measured as jm
from jaxrefl.brdf import CookTorrance, Lafortune
from jaxrefl.cli._options import solver_from_flags
from jaxrefl.fit import FitConfig, SamplesOptions, Status, fit_samples
from jaxrefl.io import MeasuredBRDF
from jaxrefl.measured import _retry as jm_retry

DATA = (
    Path(
        os.environ.get(
            "JAXREFL_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"
        )
    )
    / "brdf"
)
MODELS = jm.DEFAULT_MODELS  # Lambert + {Blinn-Phong, Ward, CT Beckmann/GGX, Lafortune 1-3}
BACKENDS = ("lean", "optimistix", "jaxopt")
DTYPES = ("float32", "float64")
CURET_SAMPLES = (2, 12)
# The residual (f̂ - f) cos(theta_i), as the measured fits' (MeasuredOptions().cosine).
COSINE = SamplesOptions(cosine=True)
# Pareto: configuration a dominates b when it is no slower and no worse, and better in one.


def _gonio(k: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Gonioreflectometer-like directions within 75 degrees; a third near the mirror."""

    def hemi():
        u = rng.uniform(np.cos(np.radians(75.0)), 1.0, k)
        phi = rng.uniform(0.0, 2 * np.pi, k)
        s = np.sqrt(1 - u * u)
        return np.stack([s * np.cos(phi), s * np.sin(phi), u], -1)

    wi, wo = hemi(), hemi()
    m = k // 3
    wo[:m] = wi[:m] * np.array([-1.0, -1.0, 1.0]) + 0.05 * rng.normal(size=(m, 3))
    wo[:, 2] = np.abs(wo[:, 2]) + 0.05
    return wi, wo / np.linalg.norm(wo, axis=-1, keepdims=True)


def synthetic(k: int = 1439, seed: int = 0) -> list[MeasuredBRDF]:
    """The two synthetic materials (module docstring), f_r with 1% relative noise."""
    rng = np.random.default_rng(seed)
    out = []
    specs = [
        (
            "synthetic_ggx",
            CookTorrance("ggx", diffuse="lambert"),
            {"albedo": [0.5, 0.3, 0.2], "specular": [0.05] * 3, "alpha": 0.15},
        ),
        (
            "synthetic_lafortune2",
            Lafortune(num_lobes=2),
            {
                "albedo": [0.3, 0.35, 0.4],
                "lobes": [[-0.9, -0.9, 0.9, 40.0], [-0.5, -0.5, 0.6, 6.0]],
            },
        ),
    ]
    for name, model, p in specs:
        wi, wo = _gonio(k, rng)
        f = np.asarray(model.eval({n: jnp.asarray(v) for n, v in p.items()}, wi, wo))
        f = f * (1.0 + 0.01 * rng.standard_normal(f.shape))
        out.append(MeasuredBRDF(wi, wo, f, ("R", "G", "B"), name=name, source="synthetic"))
    return out


def materials(quick: bool = False) -> list[MeasuredBRDF]:
    """The fixed set (module docstring), each restricted to 80 degrees."""
    mats = []
    for f in ("acryl_blue.astm", "krylon_blue.astm")[: 1 if quick else 2]:
        mats.append(jm.to_rgb(jm.load_measured(DATA / "cornell" / f)))
    mats += synthetic()[: 1 if quick else 2]
    for s in CURET_SAMPLES[: 1 if quick else 2]:
        mats.append(jm.load_measured(DATA / "curet" / "abrdf.dat", curet_sample=s))
    return [jm.restrict(m, 80.0) for m in mats]


def _fit(model, m: MeasuredBRDF, backend: str, dtype: str):
    # float64 only inside its own block: with x64 on globally, the optimistix backend mixes
    # float64 into float32 fits (lineax structure mismatch; reported, jaxrefl.fit).
    if dtype == "float32":
        cfg = FitConfig(solver=solver_from_flags(backend), dtype=jnp.float32)
        r = fit_samples(model, m, options=COSINE, config=cfg)
        jax.block_until_ready(r.theta)
        return r
    with jm_retry.x64():
        cfg = FitConfig(solver=solver_from_flags(backend), dtype=jnp.float64)
        r = fit_samples(model, m, options=COSINE, config=cfg)
        jax.block_until_ready(r.theta)
        return r


def run(
    models=MODELS,
    backends=BACKENDS,
    dtypes=DTYPES,
    quick=False,
    log=print,
    csv_path=None,
    keep: list[dict] | None = None,
) -> list[dict]:
    """Every configuration on every material; with ``csv_path`` the rows so far (Pareto
    marked among them) are written after each model, so a long run that is stopped keeps
    what it measured. ``keep``: rows of an earlier run (their ``measured`` column says
    when) that join this run's for the Pareto marks and the table."""
    rows = list(keep or [])
    today = time.strftime("%Y-%m-%d")
    mats = materials(quick)
    for name in models:
        model = jm.build_model(name)
        for backend in backends:
            for dtype in dtypes:
                for m in mats:
                    t0 = time.perf_counter()
                    _fit(model, m, backend, dtype)
                    t1 = time.perf_counter()
                    r = _fit(model, m, backend, dtype)
                    t2 = time.perf_counter()
                    warm = t2 - t1
                    f_hat = jm.predict(r, m.wi, m.wo)
                    err = jm.error_metrics(m.values, f_hat, m.wi, m.wo, max_theta_deg=None)
                    st = int(np.asarray(r.status))
                    rows.append(
                        {
                            "material": m.name,
                            "model": name,
                            "backend": backend,
                            "dtype": dtype,
                            "n_samples": len(m),
                            "n_params": int(r.space.size),
                            **{k: float(v) for k, v in err.items()},
                            "fit_time_s": warm,
                            "compile_time_s": max(t1 - t0 - warm, 0.0),
                            "status": Status(st).name,
                            "iterations": int(np.asarray(r.iterations)),
                            "measured": today,
                        }
                    )
                    log(
                        f"{m.name:22s} {name:18s} {backend:10s} {dtype}  "
                        f"err {err['cosine_weighted_l2']:.4g}  fit {1e3 * warm:8.1f} ms  "
                        f"compile {rows[-1]['compile_time_s']:.1f} s  {Status(st).name}"
                    )
        if csv_path is not None:
            mark_pareto(rows)
            write_csv(csv_path, rows)
    mark_pareto(rows)
    return rows


def mark_pareto(rows: list[dict], metric: str = "cosine_weighted_l2", rtol: float = 1e-3) -> None:
    """Set ``pareto`` (bool) and ``error_ratio`` (error / best error of the material).

    Configuration a dominates b when a is no slower and its error is at most b's times
    (1 + ``rtol``), and a is faster or clearly (beyond rtol) more accurate: errors within
    0.1% are the same optimum reached, not a better fit.
    """
    by_mat: dict[str, list[dict]] = {}
    for r in rows:
        by_mat.setdefault(r["material"], []).append(r)
    for rs in by_mat.values():
        errs = np.array([r[metric] if np.isfinite(r[metric]) else np.inf for r in rs])
        times = np.array([r["fit_time_s"] for r in rs])
        best = np.min(errs)
        for i, r in enumerate(rs):
            no_worse = errs <= errs[i] * (1.0 + rtol)
            better = (times < times[i]) | (errs * (1.0 + rtol) < errs[i])
            dominated = np.any((times <= times[i]) & no_worse & better)
            r["pareto"] = bool(np.isfinite(errs[i]) and not dominated)
            r["error_ratio"] = float(errs[i] / best) if best > 0 else float("nan")


def summary(rows: list[dict]) -> list[list[object]]:
    """One line per model x backend x dtype (see the module docstring)."""
    keys: dict[tuple, list[dict]] = {}
    for r in rows:
        keys.setdefault((r["model"], r["backend"], r["dtype"]), []).append(r)
    out = []
    for (model, backend, dtype), rs in keys.items():
        ratios = np.array([r["error_ratio"] for r in rs])
        ok = np.isfinite(ratios)
        gm = float(np.exp(np.mean(np.log(ratios[ok])))) if ok.any() else float("nan")
        conv = sum(r["status"] == "CONVERGED" for r in rs)
        out.append(
            [
                model,
                backend,
                dtype,
                f"{1e3 * np.median([r['fit_time_s'] for r in rs]):.1f}",
                f"{max(r['compile_time_s'] for r in rs):.1f}",
                f"{gm:.3f}",
                f"{sum(r['pareto'] for r in rs)}/{len(rs)}",
                f"{conv}/{len(rs)}",
            ]
        )
    return out


SUMMARY_HEADERS = [
    "model",
    "backend",
    "dtype",
    "median fit ms",
    "compile s",
    "error / best (geo. mean)",
    "on front",
    "converged",
]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--models", nargs="+", default=list(MODELS))
    ap.add_argument("--backends", nargs="+", default=list(BACKENDS))
    ap.add_argument("--dtypes", nargs="+", default=list(DTYPES))
    ap.add_argument("--quick", action="store_true", help="one material of each kind")
    ap.add_argument("--csv", type=Path, help="write every row as CSV")
    ap.add_argument(
        "--merge",
        action="store_true",
        help="keep the rows of --csv for models not in --models (an earlier run's: the "
        "'measured' column says when) and re-mark the Pareto front over all of them",
    )
    args = ap.parse_args()
    keep = None
    if args.merge:
        if args.csv is None or not args.csv.exists():
            ap.error("--merge needs an existing --csv to merge into")
        keep = [r for r in read_csv(args.csv) if r["model"] not in set(args.models)]
    t0 = time.perf_counter()
    rows = run(args.models, args.backends, args.dtypes, args.quick, csv_path=args.csv, keep=keep)
    dt = time.perf_counter() - t0
    print(f"\n# Fit error against run time\nmachine: {machine()}\n")
    print(table(SUMMARY_HEADERS, summary(rows)))
    print(f"\n{len(rows)} fits in {dt:.0f} s (compilation included)")
    if args.csv:
        write_csv(args.csv, rows)
    return 0


_FLOATS = ("cosine_weighted_l2", "log_l2", "relative_l2", "fit_time_s", "compile_time_s")


def read_csv(path: Path) -> list[dict]:
    """Rows written by :func:`write_csv`, with their types back (``measured`` defaults to
    'earlier run' for files written before that column existed)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        for k in _FLOATS:
            r[k] = float(r[k])
        for k in ("n_samples", "n_params", "iterations"):
            r[k] = int(r[k])
        r.setdefault("measured", "earlier run")
        r.pop("pareto", None)
        r.pop("error_ratio", None)
    return rows


def write_csv(path: Path, rows: list[dict]) -> None:
    """Every row as CSV (atomically: a partial run never leaves a half-written file)."""
    tmp = Path(f"{path}.tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    os.replace(tmp, path)


if __name__ == "__main__":
    sys.exit(run_and_record("error_vs_runtime", "Error against run time", main))

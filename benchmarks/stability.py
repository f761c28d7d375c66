"""Stability tables: the forward models at the edges of their domain, and stiff fits.

    python benchmarks/stability.py [--full] [--csv out.csv]
    python benchmarks/stability.py --fit [--fit-only] [--fit-csv paper_figures/fit_stability.csv]

Forward models: per model and dtype, how many (parameter set x direction pair) cases were
run, how many gave a non-finite value or gradient (must be 0), and the largest finite
magnitudes.

Fits (``--fit``): the stiff cases of ``_stiff_fits.py`` (roughness 1e-3 with a
sharp highlight, grazing-only observations, a Blinn-Phong exponent of 1e4, nearly collinear
lights), ``--n`` problems each, fitted in float32, in float64, and in float32 with the
automatic float64 retry (:func:`jaxrefl.measured.fit_pixels_retry`): the fraction of
fits that converge, are finite, and reach the optimum (cost within 1e-3 of the best known),
the fraction the retry detected and sent to float64, the fraction where the float64 redo was
kept, and the warm fit time.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from dataclasses import asdict
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine, run_and_record, table  # noqa: E402
from _stability_sweep import run_stability  # noqa: E402
from _stiff_fits import run_stiff  # noqa: E402

from jaxrefl.brdf import model_zoo  # noqa: E402


def fit_stability(n: int, csv_path: Path | None) -> int:
    """Print the stiff-fit table; 1 when the retried fits are not all finite."""
    t0 = time.perf_counter()
    rows = run_stiff(n=n)
    dt = time.perf_counter() - t0
    print(f"# Stiff fits ({n} problems per case)\nmachine: {machine()}\n")
    pct = lambda x: "-" if x != x else f"{100 * x:.0f}%"  # noqa: E731 (NaN: not a retry row)
    print(
        table(
            ["case", "mode", "converged", "finite", "at optimum", "retried", "kept f64", "fit ms"],
            [
                [
                    r.case,
                    r.mode,
                    pct(r.converged),
                    pct(r.finite),
                    pct(r.at_optimum),
                    pct(r.retried),
                    pct(r.kept_float64),
                    f"{1e3 * r.fit_time_s:.1f}",
                ]
                for r in rows
            ],
        )
    )
    detected = [r.case for r in rows if r.mode == "float32+retry" and r.retried > 0]
    print(f"\nfloat32 fits detected and retried in float64: {', '.join(detected) or 'none'}")
    print(f"stiff fits took {dt:.1f} s (compile included)")
    if csv_path:
        with open(csv_path, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(asdict(rows[0])))
            w.writeheader()
            w.writerows(asdict(r) for r in rows)
    retry_rows = [r for r in rows if r.mode == "float32+retry"]
    return 0 if all(r.finite == 1.0 for r in retry_rows) else 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--full", action="store_true", help="every Cook-Torrance combination")
    ap.add_argument("--csv", type=Path, help="also write the rows as CSV")
    ap.add_argument("--fit", action="store_true", help="also the stiff-fit table")
    ap.add_argument("--fit-only", action="store_true", help="only the stiff-fit table")
    ap.add_argument("--fit-csv", type=Path, help="write the stiff-fit rows as CSV")
    ap.add_argument("--n", type=int, default=32, help="problems per stiff case")
    args = ap.parse_args()
    if args.fit or args.fit_only:
        bad_fit = fit_stability(args.n, args.fit_csv)
        if args.fit_only:
            return bad_fit
    t0 = time.perf_counter()
    rows = run_stability(model_zoo(full=args.full))
    dt = time.perf_counter() - t0
    print(f"# Stability sweep\nmachine: {machine()}\n")
    print(
        table(
            ["model", "dtype", "cases", "non-finite f", "non-finite grad", "max |f|", "max |grad|"],
            [
                [
                    r.label,
                    r.dtype,
                    r.cases,
                    r.nonfinite_values,
                    r.nonfinite_grads,
                    f"{r.max_abs_value:.3g}",
                    f"{r.max_abs_grad:.3g}",
                ]
                for r in rows
            ],
        )
    )
    total = sum(r.cases for r in rows)
    bad = sum(r.nonfinite_values + r.nonfinite_grads for r in rows)
    print(f"\n{len(rows)} rows, {total} cases, {bad} non-finite")
    print(f"sweep took {dt:.1f} s (compile included)")
    if args.csv:
        with open(args.csv, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(asdict(rows[0])))
            w.writeheader()
            w.writerows(asdict(r) for r in rows)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(run_and_record("stability", "Stability at the edges", main))
